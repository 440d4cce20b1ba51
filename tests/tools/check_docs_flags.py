#!/usr/bin/env python3
"""The documentation and the programs' --help agree, both ways.

Usage: check_docs_flags.py REPO_ROOT NAME=EXECUTABLE...

1. Every flag the documentation gives a program exists in that program's --help. Reads docs/*.md,
   README.md and the shell scripts under scripts/ and bots/. A flag counts as given to NAME when it
   follows NAME's executable on a command line (a line, joined with the next while it ends in a
   backslash) before the command ends (|, ;, &&, a backtick or another program's name) and the
   first word after NAME is itself a flag (so `script.sh build/zone/zone-server TAG --x` is a
   script's argument, not zone-server's), unless NAME is an option's value
   (`tool --server NAME --x`).
2. Every option a program's --help defines is documented in that program's manual (MANUALS
   below): the flag appears there as `--flag`. An option is defined by a --help line that starts
   with it (indented by at most 4 spaces, or `-h [ --help ]`; a deeper line continues a
   description), or by a usage line (`usage: ...` and the lines of `[...]` under it).
3. Every default a manual's option table gives (a row `| `--flag` | default | ...`, or several
   flags in the first cell with their defaults comma-separated in the second) is the default
   --help prints (`--flag arg (=default)`, Boost.Program_options' form; numbers compared as
   numbers). Options whose --help prints no default are not checked.
A manual is a file, or one section of it (`path#Heading`: the heading's lines up to the next
heading of its level or above); a whole file's option tables leave out the sections other
programs claim as their manuals.
Exits 1 naming each flag --help lacks, with where the documentation gives it, each option
its manual lacks and each default that differs.
"""
import glob
import os
import re
import subprocess
import sys

FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")

# Where each program's options are documented (paths relative to the repository root).
MANUALS = {
    "zone-server": ["docs/operating.md"],
    "bot-swarm": ["docs/bots.md"],
    "bench-zone": ["docs/zone-benchmarks.md"],
    "bench-handoff": ["docs/zone-benchmarks.md"],
    "bench-pool": ["docs/zone-benchmarks.md"],
    "bench-gpu": ["docs/gpu-benchmarks.md"],
    "bench-peers": ["docs/gpu-benchmarks.md"],
    "bench-finders": ["docs/gpu-benchmarks.md"],
    "host-jitter": ["docs/zone-benchmarks.md"],
    "interest-pairs": ["docs/embedding.md"],
    "world-check": ["docs/world.md"],
    "world-gate": ["docs/world.md"],
    "zone-probe": ["docs/operating.md"],
    "bench-oracle": ["docs/bots.md#What it costs"],
}
# Every program of the tree, so that a command line given to one ends where another begins.
PROGRAMS = set(MANUALS)


def run_help(exe):
    out = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=60)
    text = out.stdout + out.stderr
    if out.returncode != 0 or not FLAG.search(text):
        sys.exit(f"{exe} --help: exit {out.returncode}:\n{text}")
    return text


def defined_options(text):
    """The options a --help text defines (not the ones its descriptions merely mention)."""
    found = set()
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.lower().startswith("usage") or stripped.startswith("["):
            found |= set(FLAG.findall(stripped))
        elif re.match(r" {0,4}-", line):  # an option's own line; deeper lines continue a description
            m = re.match(r"(?:-[a-zA-Z] \[ )?(--[a-z][a-z0-9-]*)", stripped)
            if m:
                found.add(m.group(1))
            found |= set(re.findall(r"\s{2,}(--[a-z][a-z0-9-]*)", stripped))  # two on one line
    found.discard("--help")
    return found


def help_defaults(text):
    """{--flag: default} for the options whose --help line prints one (`--flag arg (=X)`)."""
    return {m.group(1): m.group(2) for m in re.finditer(r"^\s*(--[a-z][a-z0-9-]*) arg \(=([^)]*)\)", text, re.M)}


def same_default(documented, shown):
    documented = documented.replace("`", "").strip()
    try:
        return float(documented.replace(",", "")) == float(shown)
    except ValueError:
        return documented == shown


def manual_lines(root, entry):
    """(line number, line) of a manual: a whole file, or `path#Heading`'s section of it."""
    path, _, heading = entry.partition("#")
    with open(os.path.join(root, path), encoding="utf-8") as f:
        lines = list(enumerate(f, 1))
    if not heading:
        return lines
    level, fenced, out = None, False, []
    for number, line in lines:
        fenced ^= line.startswith("```")
        m = None if fenced else re.match(r"(#+)\s+(.*?)\s*$", line)
        if level is None:
            if m and m.group(2) == heading:
                level = len(m.group(1))
                out.append((number, line))
        elif m and len(m.group(1)) <= level:
            break
        else:
            out.append((number, line))
    if level is None:
        sys.exit(f"{path}: no heading '{heading}' (MANUALS)")
    return out


def table_defaults(lines):
    """(line number, flag, documented default) from a manual's option tables."""
    for number, line in lines:
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if not line.startswith("|") or len(cells) < 3:
            continue
        names = re.findall(r"`(--[a-z][a-z0-9-]*)[^`]*`", cells[0])
        if not names or re.sub(r"`[^`]*`|[,\s]", "", cells[0]):
            continue  # not a row of options
        values = [cells[1]] if len(names) == 1 else [v.strip() for v in cells[1].split(", ")]
        if len(values) == len(names):
            for name, value in zip(names, values):
                yield number, name, value


def command_lines(path):
    """(line number, text) with backslash continuations joined."""
    joined, start = "", None
    with open(path, encoding="utf-8") as f:
        for number, line in enumerate(f, 1):
            line = line.rstrip("\n")
            if start is None:
                start = number
            if line.endswith("\\"):
                joined += line[:-1] + " "
                continue
            yield start, joined + line
            joined, start = "", None
    if start is not None:
        yield start, joined


def main():
    root, pairs = sys.argv[1], sys.argv[2:]
    programs = dict(p.split("=", 1) for p in pairs)
    unknown = set(programs) - set(MANUALS)
    if unknown:
        sys.exit(f"no manual known for {', '.join(sorted(unknown))}: add it to MANUALS")
    helps = {name: run_help(exe) for name, exe in programs.items()}
    flags = {name: set(FLAG.findall(text)) for name, text in helps.items()}
    stop = re.compile(r"\||;|&&|`|\b(?:" + "|".join(map(re.escape, sorted(PROGRAMS | set(programs)))) + r")\b")
    files = sorted(glob.glob(os.path.join(root, "docs", "*.md"))) + [os.path.join(root, "README.md")]
    files += sorted(glob.glob(os.path.join(root, "scripts", "*.sh")) + glob.glob(os.path.join(root, "bots", "*.sh")))

    # 1. What the documentation gives a program exists in its --help.
    missing, checked = [], 0
    for path in files:
        if not os.path.exists(path):
            continue
        for number, line in command_lines(path):
            for name in programs:
                for m in re.finditer(r"(?<![\w.-])(?:[\w./$-]*/)?" + re.escape(name) + r"(?![\w.-])", line):
                    before = line[:m.start()].split()
                    if before and before[-1].startswith("-"):
                        continue  # the program is an option's value (`tool --server build/zone/zone-server`)
                    rest = stop.split(line[m.end():])[0]
                    words = rest.split()
                    if not words or not words[0].startswith("-"):
                        continue
                    for flag in FLAG.findall(rest):
                        checked += 1
                        if flag not in flags[name]:
                            missing.append(f"{os.path.relpath(path, root)}:{number}: {name} {flag}")

    # 2. What --help defines is documented in the program's manual.
    undocumented, defined = [], 0
    for name, text in helps.items():
        manual_text = ""
        for rel in MANUALS[name]:
            manual_text += "".join(line for _, line in manual_lines(root, rel))
        documented = set(FLAG.findall(manual_text))
        for option in sorted(defined_options(text)):
            defined += 1
            if option not in documented:
                undocumented.append(f"{name} {option} (not in {', '.join(MANUALS[name])})")

    # 3. The defaults the manuals' option tables give are --help's.
    wrong_defaults, compared = [], 0
    for name, text in helps.items():
        shown = help_defaults(text)
        for rel in MANUALS[name]:
            lines = manual_lines(root, rel)
            if "#" not in rel:  # leave out the sections other programs claim in this file
                claimed = {n for other, entries in MANUALS.items() if other != name
                           for e in entries if e.startswith(rel + "#") for n, _ in manual_lines(root, e)}
                lines = [(n, line) for n, line in lines if n not in claimed]
            for number, flag, value in table_defaults(lines):
                if flag in shown:
                    compared += 1
                    if not same_default(value, shown[flag]):
                        wrong_defaults.append(f"{rel}:{number}: {name} {flag}: documented {value!r}, --help {shown[flag]!r}")

    print(f"{checked} flags given to {', '.join(programs)} in the documentation checked against --help; "
          f"{defined} options of their --help checked against their manuals; "
          f"{compared} documented defaults checked against --help")
    if missing:
        print("given in the documentation, not in --help:\n  " + "\n  ".join(missing))
    if undocumented:
        print("in --help, not in the manual:\n  " + "\n  ".join(undocumented))
    if wrong_defaults:
        print("defaults that differ from --help:\n  " + "\n  ".join(wrong_defaults))
    return 1 if missing or undocumented or wrong_defaults or checked == 0 or defined == 0 else 0


if __name__ == "__main__":
    sys.exit(main())
