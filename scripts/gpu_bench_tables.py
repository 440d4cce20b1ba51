#!/usr/bin/env python3
"""Turns bench-gpu's CSV into the markdown tables of docs/gpu-benchmarks.md and the data files
that scripts/gpu_bench_plots.gp plots. Usage: gpu_bench_tables.py BENCH.csv OUTDIR"""
import csv, os, sys

src, outdir = sys.argv[1], sys.argv[2]
os.makedirs(outdir, exist_ok=True)
rows, floors = [], {}
with open(src) as f:
    for r in csv.reader(f):
        if not r:
            continue
        if r[0] == 'floors':
            floors = dict(zip(r[1::2], r[2::2]))
        else:
            rows.append(r)
head, data = rows[0], [dict(zip(rows[0], r)) for r in rows[1:]]

def f(x, nd=3):
    v = float(x)
    return f"{v:.{nd}f}"

def table(cols, sel):
    out = ["| " + " | ".join(c for c, _ in cols) + " |", "|" + "---|" * len(cols)]
    for d in sel:
        out.append("| " + " | ".join(fn(d) for _, fn in cols) + " |")
    return "\n".join(out)

cpu = lambda d: (f(d['cpu_ms'], 1) if float(d['cpu_ms']) >= 0 else "-")
common = [
    ("N", lambda d: f"{int(d['n']):.0e}".replace("+0", "").replace("+", "")),
    ("e2e ms (view)", lambda d: f(d['e2e_ms'])),
    ("via find() ms", lambda d: f(d['find_ms'])),
    ("DataIn", lambda d: f(d['data_in_ms'])),
    ("PLAN", lambda d: f(d['plan_ms'])),
    ("MAP", lambda d: f(d['map_ms'])),
    ("SCHED", lambda d: f(d['sched_ms'])),
    ("CHECK", lambda d: f(d['check_ms'])),
    ("DataOut", lambda d: f(d['data_out_ms'])),
    ("REPORT", lambda d: f(d['report_ms'])),
    ("CHECK+Out+REPORT wall", lambda d: f(d['pipeline_ms'])),
    ("pairs", lambda d: d['pairs']),
    ("CPU grid_finder ms", cpu),
    ("verified", lambda d: d['verified']),
]
print("## floors\n", floors, "\n")
print("## targets\n")
targets = [d for d in data if d['experiment'] == 'targets']
print(table([("set", lambda d: d['set']), ("target ms", lambda d: d['param'].lstrip('<=')), ("mode", lambda d: d['options'])] + common +
            [("met", lambda d: "yes" if float(d['e2e_ms']) <= float(d['param'].lstrip('<=')) else "no")], targets))
for exp, title in [('nsweep', 'Fig. 8 uniform'), ('gauss', 'Fig. 11 Gaussian')]:
    print(f"\n## {title}\n")
    print(table([("mode", lambda d: d['param'])] + common, [d for d in data if d['experiment'] == exp]))
print("\n## Fig. 9 cells\n")
print(table([("edge", lambda d: d['param'])] + common[:3] + [("MAP", lambda d: f(d['map_ms'])), ("CHECK", lambda d: f(d['check_ms'])),
             ("REPORT", lambda d: f(d['report_ms'])), ("checks", lambda d: f"{float(d['checks']):.3g}"),
             ("out MB", lambda d: f(float(d['bytes_out']) / 1e6, 1))],
            [d for d in data if d['experiment'] == 'cells']))
print("\n## Fig. 10 / Table III doc\n")
print(table([("DoC", lambda d: d['param'].split('=')[1]), ("pairs", lambda d: d['pairs']),
             ("checks", lambda d: f"{float(d['checks']):.3g}"), ("input MB", lambda d: f(float(d['bytes_in']) / 1e6, 1)),
             ("output MB", lambda d: f(float(d['bytes_out']) / 1e6, 2)), ("cell edge", lambda d: f(d['cell_edge'], 1)),
             ("e2e ms (view)", lambda d: f(d['e2e_ms'])), ("via find() ms", lambda d: f(d['find_ms'])),
             ("CPU grid_finder ms", cpu), ("verified", lambda d: d['verified'])],
            [d for d in data if d['experiment'] == 'doc']))
print("\n## ablation\n")
abl = [d for d in data if d['experiment'] == 'ablation']
base = float(abl[0]['e2e_ms']) if abl else 1
print(table([("config", lambda d: d['param']), ("e2e ms (view)", lambda d: f(d['e2e_ms'])),
             ("speedup", lambda d: f(base / float(d['e2e_ms']), 2)), ("via find() ms", lambda d: f(d['find_ms'])),
             ("DataIn", lambda d: f(d['data_in_ms'])), ("PLAN", lambda d: f(d['plan_ms'])), ("MAP", lambda d: f(d['map_ms'])),
             ("SCHED", lambda d: f(d['sched_ms'])), ("CHECK", lambda d: f(d['check_ms'])),
             ("DataOut", lambda d: f(d['data_out_ms'])), ("REPORT", lambda d: f(d['report_ms'])),
             ("CHECK+Out+REPORT wall", lambda d: f(d['pipeline_ms'])), ("D2H MB", lambda d: f(float(d['bytes_out']) / 1e6, 0))],
            abl))
# plot data
def dump(name, sel, cols):
    with open(os.path.join(outdir, name), 'w') as g:
        for d in sel:
            g.write(" ".join(str(c(d)) for c in cols) + "\n")
num = lambda k: (lambda d: d[k])
for exp in ('nsweep', 'gauss'):
    for mode in ('CPB', 'DPB'):
        dump(f'{exp}_{mode}.dat', [d for d in data if d['experiment'] == exp and d['param'] in (mode, '-')],
             [num('n'), num('e2e_ms'), num('find_ms'), lambda d: d['cpu_ms'] if float(d['cpu_ms']) > 0 else 'NaN'])
if any(d['experiment'] == 'doc' for d in data): dump('doc.dat', [d for d in data if d['experiment'] == 'doc'], [lambda d: d['param'].split('=')[1], num('e2e_ms'), num('find_ms'), lambda d: d['cpu_ms'] if float(d['cpu_ms']) > 0 else 'NaN'])
for n in ('100000', '1000000', '10000000') if any(d['experiment'] == 'cells' for d in data) else ():
    dump(f'cells_{n}.dat', [d for d in data if d['experiment'] == 'cells' and d['n'] == n], [num('cell_edge'), num('e2e_ms')])
dump('ablation.dat', abl if abl else [], [num('param'), num('data_in_ms'), num('plan_ms'), num('map_ms'), num('sched_ms'), num('pipeline_ms')])
