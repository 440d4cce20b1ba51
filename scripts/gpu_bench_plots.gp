# The plots of docs/gpu-benchmarks.md ("The PBIG paper's experiments"): one figure of five panels
# (Fig. 8, Fig. 11, Fig. 9, Fig. 10, Table VI) from the data files scripts/gpu_bench_tables.py writes.
# Usage: gnuplot -e "dir='/tmp/gp'; out='docs/img'" scripts/gpu_bench_plots.gp   (writes out/gpu-paper.png)
# The figure in docs/img is of three runs (gpu/gpu-bench-2026-11-22{,b,c}.csv in docs/data.tar.xz):
# each CSV through gpu_bench_tables.py into its own folder, then into dir: nsweep_*.dat from run C
# (-22c), gauss_*.dat and ablation.dat from run B (-22b), doc.dat and cells_*.dat from run A (-22);
# then `optipng -o7` and `zopflipng -m` (both lossless: the same pixels, fewer bytes).
set terminal pngcairo noenhanced size 1200,1380 font ",10"
set output out."/gpu-paper.png"
set multiplot
set size 0.5,0.34
set grid
set key top left
set logscale y
set ylabel "time (ms)"

set origin 0,0.66
set logscale x
set xlabel "boxes N (uniform)"
set title "Fig. 8: uniform N sweep, end to end on the H100 host"
plot dir."/nsweep_DPB.dat" u 1:2 w lp lw 2 t "GPU, direct output (default), find_pairs_view", \
     dir."/nsweep_CPB.dat" u 1:2 w lp lw 2 t "GPU, paper output (C+P+B), find_pairs_view", \
     dir."/nsweep_CPB.dat" u 1:3 w lp lw 2 t "GPU, paper output, via pair_finder::find", \
     dir."/nsweep_CPB.dat" u 1:4 w lp lw 2 t "CPU grid_finder, 16 threads"

set origin 0.5,0.66
set xlabel "boxes N (Gaussian)"
set title "Fig. 11: Gaussian N sweep, end to end"
plot dir."/gauss_DPB.dat" u 1:2 w lp lw 2 t "GPU, direct output (default), find_pairs_view", \
     dir."/gauss_CPB.dat" u 1:2 w lp lw 2 t "GPU, paper output (C+P+B), find_pairs_view", \
     dir."/gauss_CPB.dat" u 1:3 w lp lw 2 t "GPU, paper output, via pair_finder::find", \
     dir."/gauss_CPB.dat" u 1:4 w lp lw 2 t "CPU grid_finder, 16 threads"

set origin 0,0.33
set xlabel "cell edge (first point of each line: Eq. 6)"
set title "Fig. 9: cell-size sweep (uniform, paper output C+P+B), end to end"
plot dir."/cells_100000.dat" u 1:2 w lp lw 2 t "N = 1e5", \
     dir."/cells_1000000.dat" u 1:2 w lp lw 2 t "N = 1e6", \
     dir."/cells_10000000.dat" u 1:2 w lp lw 2 t "N = 1e7"

set origin 0.5,0.33
set xlabel "degree of coverage (N = 1e7)"
set title "Fig. 10: DoC sweep at N = 1e7, end to end"
plot dir."/doc.dat" u 1:2 w lp lw 2 t "GPU, paper output (C+P+B), find_pairs_view", \
     dir."/doc.dat" u 1:3 w lp lw 2 t "GPU, paper output, via pair_finder::find", \
     dir."/doc.dat" u 1:4 w lp lw 2 t "CPU grid_finder, 16 threads"

set origin 0,0
set size 1,0.33
unset logscale
set style data histograms
set style histogram rowstacked
set style fill solid 0.8 border -1
set boxwidth 0.7
set xlabel "C compression, P pipelining, B load balancing, D direct output; Gaussian N = 1e7"
set title "Table VI: where the time goes (ms)"
set key top right opaque
set yrange [0:760]
plot dir."/ablation.dat" u 2:xtic(1) t "DataIn", '' u 3 t "PLAN", '' u 4 t "MAP", '' u 5 t "SCHED", \
     '' u 6 t "CHECK + DataOut + REPORT (wall)"
unset multiplot
