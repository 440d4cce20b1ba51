# Plots of docs/gpu-benchmarks.md from the data files written by scripts/gpu_bench_tables.py.
# Usage: gnuplot -e "dir='/tmp/gpuplots'; out='docs/img'" scripts/gpu_bench_plots.gp
set terminal pngcairo noenhanced size 800,520 font ",11"
set grid
set key top left
set logscale y
set ylabel "time (ms)"

set output out."/gpu-fig8-uniform.png"
set logscale x
set xlabel "boxes N (uniform)"
set title "Fig. 8: uniform N sweep, end to end on the H100 host"
plot dir."/nsweep_DPB.dat" u 1:2 w lp lw 2 t "GPU, direct output (default), find_pairs_view", \
     dir."/nsweep_CPB.dat" u 1:2 w lp lw 2 t "GPU, paper output (C+P+B), find_pairs_view", \
     dir."/nsweep_CPB.dat" u 1:3 w lp lw 2 t "GPU, paper output, via pair_finder::find", \
     dir."/nsweep_CPB.dat" u 1:4 w lp lw 2 t "CPU grid_finder, 16 threads"

set output out."/gpu-fig11-gaussian.png"
set xlabel "boxes N (Gaussian)"
set title "Fig. 11: Gaussian N sweep, end to end"
plot dir."/gauss_DPB.dat" u 1:2 w lp lw 2 t "GPU, direct output (default), find_pairs_view", \
     dir."/gauss_CPB.dat" u 1:2 w lp lw 2 t "GPU, paper output (C+P+B), find_pairs_view", \
     dir."/gauss_CPB.dat" u 1:3 w lp lw 2 t "GPU, paper output, via pair_finder::find", \
     dir."/gauss_CPB.dat" u 1:4 w lp lw 2 t "CPU grid_finder, 16 threads"

set output out."/gpu-fig10-doc.png"
set xlabel "degree of coverage (N = 1e7)"
set title "Fig. 10: DoC sweep at N = 1e7, end to end"
plot dir."/doc.dat" u 1:2 w lp lw 2 t "GPU, paper output (C+P+B), find_pairs_view", \
     dir."/doc.dat" u 1:3 w lp lw 2 t "GPU, paper output, via pair_finder::find", \
     dir."/doc.dat" u 1:4 w lp lw 2 t "CPU grid_finder, 16 threads"

set output out."/gpu-fig9-cells.png"
set xlabel "cell edge (first point of each line: Eq. 6)"
set title "Fig. 9: cell-size sweep (uniform, paper output C+P+B), end to end"
plot dir."/cells_100000.dat" u 1:2 w lp lw 2 t "N = 1e5", \
     dir."/cells_1000000.dat" u 1:2 w lp lw 2 t "N = 1e6", \
     dir."/cells_10000000.dat" u 1:2 w lp lw 2 t "N = 1e7"

set output out."/gpu-table6-ablation.png"
unset logscale
set style data histograms
set style histogram rowstacked
set style fill solid 0.8 border -1
set boxwidth 0.7
set xlabel "C compression, P pipelining, B load balancing, D direct output; Gaussian N = 1e7"
set title "Table VI: where the time goes (ms)"
set key outside bottom center horizontal
set yrange [0:*]
plot dir."/ablation.dat" u 2:xtic(1) t "DataIn", '' u 3 t "PLAN", '' u 4 t "MAP", '' u 5 t "SCHED", \
     '' u 6 t "CHECK + DataOut + REPORT (wall)"
