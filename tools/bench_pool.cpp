// bench-pool: the tick's shape of parallel work (several short data-parallel phases per tick) on
// the interest core's thread_pool and on oneTBB (tbb::parallel_for in a task_arena of the same
// size), to judge whether the hand-made pool should give way to the library (issue 20, item 6;
// docs/zone-benchmarks.md, "Thread pool or oneTBB"). Every task checks its own result, so a
// scheduler that skipped or repeated a task fails the run instead of looking fast.
#include <oneapi/tbb/blocked_range.h>
#include <oneapi/tbb/global_control.h>
#include <oneapi/tbb/parallel_for.h>
#include <oneapi/tbb/task_arena.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <fstream>
#include <functional>
#include <string>
#include <thread>
#include <vector>

#include "interest/measure.h"
#include "interest/thread_pool.h"
#include "tools/cli.h"

namespace {

using clock_type = std::chrono::steady_clock;

const char* const usage_text = R"(bench-pool: the tick's parallel phases on interest::thread_pool and on oneTBB

Usage: bench-pool [--threads N] [--ticks N] [--phases N] [--tasks N] [--work-us US] [--spin-us US]
                  [--csv FILE]
  --threads N   threads, the calling one included (default 0 = all cores)
  --ticks N     measured ticks per scheduler (default 600, after 30 warm-up ticks)
  --phases N    parallel phases per tick (default 6: the zone tick's inputs, behaviours,
                integrate, interest, replicate, viewer)
  --tasks N     tasks per phase (default 64)
  --work-us US  work per task, calibrated on one thread (default 20; 64 x 20 us = 1.28 ms of work a phase)
  --spin-us US  the thread pool's spin before its idle threads sleep (default 1000; the pool
                without a spin, zone-server's default --worker-spin-us 0, is measured too)
  --csv FILE    also write the table as CSV (default bench-pool.csv in the current directory)
Prints, per scheduler, the tick's wall time p50 / p99 / max and its ratio to the ideal
(phases x tasks x work / threads).
)";

/// A dependent chain of integer operations the compiler cannot fold.
std::uint64_t spin(std::uint64_t iters, std::uint64_t seed) {
  std::uint64_t x = seed;
  for (std::uint64_t i = 0; i < iters; ++i) x = x * 6364136223846793005ull + 1442695040888963407ull;
  return x;
}

std::uint64_t calibrate(double us) {
  const std::uint64_t iters = 1u << 16;
  double best = 1e30;
  volatile std::uint64_t sink = 0;
  for (int k = 0; k < 40; ++k) {
    const auto t0 = clock_type::now();
    sink = sink + spin(iters, static_cast<std::uint64_t>(k) + 1);
    best = std::min(best, std::chrono::duration<double, std::micro>(clock_type::now() - t0).count());
  }
  return std::max<std::uint64_t>(1, static_cast<std::uint64_t>(static_cast<double>(iters) * us / best));
}

struct row {
  std::string scheduler;
  double p50 = 0, p99 = 0, max = 0, ideal = 0;
  bool ok = true;
};

/// Runs ticks of `phases` phases, each through `parallel(n, task)`; every task writes its result
/// and the tick checks them all against the sequential values.
row measure(const std::string& name, int ticks, int phases, std::size_t tasks, std::uint64_t iters, double ideal_ms,
            const std::function<void(std::size_t, const std::function<void(std::size_t)>&)>& parallel) {
  std::vector<std::uint64_t> out(tasks), expect(tasks);
  for (std::size_t i = 0; i < tasks; ++i) expect[i] = spin(iters, i + 1);
  std::vector<double> ms;
  row r{name, 0, 0, 0, ideal_ms, true};
  const int warmup = 30;
  for (int t = 0; t < warmup + ticks; ++t) {
    const auto t0 = clock_type::now();
    for (int p = 0; p < phases; ++p) {
      std::fill(out.begin(), out.end(), 0);
      parallel(tasks, [&](std::size_t i) { out[i] = spin(iters, i + 1); });
      if (out != expect) r.ok = false;
    }
    if (t >= warmup) ms.push_back(std::chrono::duration<double, std::milli>(clock_type::now() - t0).count());
  }
  std::sort(ms.begin(), ms.end());
  r.p50 = zone::quantile(ms, 0.5);
  r.p99 = zone::quantile(ms, 0.99);
  r.max = ms.back();
  return r;
}

}  // namespace

int main(int argc, char** argv) {
  unsigned threads = 0, spin_us = 1000;
  int ticks = 600, phases = 6;
  std::size_t tasks = 64;
  double work_us = 20;
  std::string csv = "bench-pool.csv";
  namespace po = zone::tools::po;
  po::options_description cli;
  cli.add_options()("threads", po::value(&threads))("ticks", po::value(&ticks))("phases", po::value(&phases))(
      "tasks", po::value(&tasks))("work-us", po::value(&work_us))("spin-us", po::value(&spin_us))(
      "csv", po::value(&csv));
  if (const auto rc = zone::tools::parse_command_line(argc, argv, "bench-pool", usage_text, cli, 2)) return *rc;
  if (ticks < 1 || ticks > 100000 || phases < 1 || phases > 64 || tasks < 1 || tasks > 1000000 || !(work_us > 0) ||
      work_us > 100000) {
    std::fprintf(stderr, "bench-pool: need 1 <= ticks <= 100000, 1 <= phases <= 64, 1 <= tasks <= 10^6, 0 < work-us <= 10^5\n");
    return 2;
  }
  if (threads == 0) threads = std::max(1u, std::thread::hardware_concurrency());
  const std::uint64_t iters = calibrate(work_us);
  const double ideal = phases * static_cast<double>(tasks) * work_us / 1000.0 / threads;
  std::printf("bench-pool: %u threads, %d phases x %zu tasks x %.0f us a tick, %d ticks (+30 warm-up); ideal %.3f ms\n",
              threads, phases, tasks, work_us, ticks, ideal);

  std::vector<row> rows;
  {
    zone::interest::thread_pool pool(threads, spin_us);
    rows.push_back(measure("thread_pool, spin " + std::to_string(spin_us) + " us", ticks, phases, tasks, iters, ideal,
                           [&](std::size_t n, const std::function<void(std::size_t)>& f) { pool.run(n, f); }));
  }
  {
    zone::interest::thread_pool pool(threads, 0);
    rows.push_back(measure("thread_pool, spin 0", ticks, phases, tasks, iters, ideal,
                           [&](std::size_t n, const std::function<void(std::size_t)>& f) { pool.run(n, f); }));
  }
  {
    oneapi::tbb::global_control limit(oneapi::tbb::global_control::max_allowed_parallelism, threads);
    oneapi::tbb::task_arena arena(static_cast<int>(threads));
    rows.push_back(measure("oneTBB parallel_for (auto partitioner)", ticks, phases, tasks, iters, ideal,
                           [&](std::size_t n, const std::function<void(std::size_t)>& f) {
                             arena.execute([&] {
                               oneapi::tbb::parallel_for(oneapi::tbb::blocked_range<std::size_t>(0, n),
                                                         [&](const oneapi::tbb::blocked_range<std::size_t>& r) {
                                                           for (std::size_t i = r.begin(); i != r.end(); ++i) f(i);
                                                         });
                             });
                           }));
    rows.push_back(measure("oneTBB parallel_for (one task each)", ticks, phases, tasks, iters, ideal,
                           [&](std::size_t n, const std::function<void(std::size_t)>& f) {
                             arena.execute([&] {
                               oneapi::tbb::parallel_for(std::size_t{0}, n, [&](std::size_t i) { f(i); });
                             });
                           }));
  }

  std::printf("\n| scheduler | tick p50 ms | tick p99 ms | tick max ms | p50 / ideal | p99 / ideal | results |\n");
  std::printf("|---|---|---|---|---|---|---|\n");
  for (const auto& r : rows) {
    std::printf("| %s | %.3f | %.3f | %.3f | %.2f | %.2f | %s |\n", r.scheduler.c_str(), r.p50, r.p99, r.max,
                r.p50 / r.ideal, r.p99 / r.ideal, r.ok ? "all right" : "WRONG");
  }
  std::ofstream f(csv);
  if (f) {
    f << "scheduler,threads,phases,tasks,work_us,tick_p50_ms,tick_p99_ms,tick_max_ms,ideal_ms,results_ok\n";
    for (const auto& r : rows) {
      f << '"' << r.scheduler << "\"," << threads << ',' << phases << ',' << tasks << ',' << work_us << ',' << r.p50 << ','
        << r.p99 << ',' << r.max << ',' << r.ideal << ',' << (r.ok ? 1 : 0) << '\n';
    }
  }
  if (!f) std::fprintf(stderr, "bench-pool: cannot write %s\n", csv.c_str());
  const bool all_ok = std::all_of(rows.begin(), rows.end(), [](const row& r) { return r.ok; });
  return all_ok ? 0 : 1;
}
