#!/usr/bin/env python3
"""Every flag the documentation gives a program exists in that program's --help.

Usage: check_docs_flags.py REPO_ROOT NAME=EXECUTABLE...
Reads docs/*.md, README.md and the shell scripts under scripts/ and bots/. A flag counts as given
to NAME when it follows NAME's executable on a command line (a line, joined with the next while
it ends in a backslash) before the command ends (|, ;, &&, a backtick or another program's name)
and the first word after NAME is itself a flag (so `script.sh build/zone/zone-server TAG --x` is a
script's argument, not zone-server's), unless NAME is an option's value (`tool --server NAME --x`). Exits 1 naming each flag --help lacks, with where the
documentation gives it.
"""
import glob
import os
import re
import subprocess
import sys


def help_flags(exe):
    out = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=60)
    flags = set(re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", out.stdout + out.stderr))
    if out.returncode != 0 or not flags:
        sys.exit(f"{exe} --help: exit {out.returncode}, {len(flags)} flags:\n{out.stdout}{out.stderr}")
    return flags


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
    flags = {name: help_flags(exe) for name, exe in programs.items()}
    stop = re.compile(r"\||;|&&|`|\b(?:" + "|".join(map(re.escape, programs)) + r"|bench-handoff|bench-gpu|"
                      r"bench-finders|host-jitter|interest-pairs)\b")
    files = sorted(glob.glob(os.path.join(root, "docs", "*.md"))) + [os.path.join(root, "README.md")]
    files += sorted(glob.glob(os.path.join(root, "scripts", "*.sh")) + glob.glob(os.path.join(root, "bots", "*.sh")))
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
                    for flag in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", rest):
                        checked += 1
                        if flag not in flags[name]:
                            missing.append(f"{os.path.relpath(path, root)}:{number}: {name} {flag}")
    print(f"{checked} flags given to {', '.join(programs)} in the documentation checked against --help")
    if missing:
        print("not in --help:\n  " + "\n  ".join(missing))
        return 1
    return 0 if checked > 0 else 1


if __name__ == "__main__":
    sys.exit(main())
