// host-jitter: how steady is this host for a paced tick? (docs/zone-benchmarks.md)
//
// The zone server's tick is a chain of short parallel phases, once per period (33.3 ms at 30 Hz),
// with the threads asleep in between. A phase lasts as long as its slowest thread, so a thread
// that the OS (or a hypervisor) stops for a few milliseconds stretches the whole phase. This tool
// runs the same shape with a fixed amount of pure CPU work and no GPU, no memory traffic and no
// locks: every period, each of T threads sleeps until the period's start, then does W us of
// arithmetic (calibrated alone on one thread). It prints the distribution of
//   - one thread's W us of work (the calling thread, timed alone), and
//   - the phase: from the period's start until the last of the T threads is done,
// and, on Linux, the CPU time the kernel reports as stolen (the hypervisor ran something else)
// and the busiest other processes. Any spread here is the host's, not the server's code.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <limits>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "interest/measure.h"
#include "net/os_limits.h"
#include "tools/cli.h"

namespace {

using clock_type = std::chrono::steady_clock;

struct options {
  int threads = 0;  // 0 = all hardware threads
  double work_us = 500;
  double rate = 30;
  int periods = 600;
  bool pairs = false;
};

const char* const usage_text = R"(host-jitter: a paced, pure-CPU stand-in for the tick, to measure the host's noise

Usage: host-jitter [--threads N] [--work-us US] [--rate HZ] [--periods N] [--pairs] [--help]
  --threads N    threads in the parallel phase, the calling one included (default 0 = all cores)
  --work-us US   work per thread per period, calibrated on one thread (default 500)
  --rate HZ      periods per second (default 30)
  --periods N    measured periods (default 600, after 30 warm-up periods)
  --pairs        instead: which CPUs slow each other down (share a physical core): the same work
                 on two pinned CPUs at once, for every pair of the CPUs this process may use,
                 against each alone; prints the pairs slowed by 15% or more and the kernel's
                 sibling lists (in a VM the hypervisor's placement, not the guest's, decides)
Prints p50 / p90 / p99 / max of one thread's work and of the parallel phase (start of the period
-> last thread done), the ratio to the calibrated work, and the host's steal time (/proc/stat).
)";

/// A dependent chain of integer operations the compiler cannot fold or vectorise.
std::uint64_t spin(std::uint64_t iters, std::uint64_t seed) {
  std::uint64_t x = seed | 1u;
  for (std::uint64_t i = 0; i < iters; ++i) {
    x ^= x << 13;
    x ^= x >> 7;
    x ^= x << 17;
  }
  return x;
}

double us_since(clock_type::time_point t) {
  return std::chrono::duration<double, std::micro>(clock_type::now() - t).count();
}

/// Iterations of spin() that take about `us` microseconds on this thread (best of several tries).
std::uint64_t calibrate(double us) {
  std::uint64_t iters = 1u << 16;
  volatile std::uint64_t sink = 0;
  double best = 1e30;
  for (int k = 0; k < 40; ++k) {
    const auto t0 = clock_type::now();
    sink = sink + spin(iters, static_cast<std::uint64_t>(k) + 1);
    best = std::min(best, us_since(t0));
  }
  return std::max<std::uint64_t>(1, static_cast<std::uint64_t>(static_cast<double>(iters) * us / best));
}

struct cpu_times {
  unsigned long long total = 0, steal = 0;
};
cpu_times read_cpu() {
  cpu_times c;
  std::ifstream f("/proc/stat");
  std::string label;
  if (!(f >> label) || label != "cpu") return c;
  for (int i = 0; i < 10; ++i) {
    unsigned long long v = 0;
    if (!(f >> v)) break;
    c.total += v;
    if (i == 7) c.steal = v;
  }
  return c;
}

void print_row(const char* what, std::vector<double> v, double work_us) {
  std::sort(v.begin(), v.end());
  const auto q = [&](double p) { return zone::quantile(v, p); };
  const double over = static_cast<double>(std::count_if(v.begin(), v.end(), [&](double x) { return x > 2.0 * work_us; }));
  std::printf("| %s | %.0f | %.0f | %.0f | %.0f | %.2f | %.2f | %.1f%% |\n", what, q(0.5), q(0.9), q(0.99), v.back(),
              q(0.5) / work_us, q(0.99) / work_us, 100.0 * over / static_cast<double>(v.size()));
}

bool pin_to(int cpu) { return !zone::net::pin_current_thread({cpu}).has_value(); }

/// Microseconds `iters` of spin() take on `cpu` (best of three).
double alone_on(int cpu, std::uint64_t iters) {
  double best = 1e30;
  std::thread t([&] {
    if (!pin_to(cpu)) return;
    volatile std::uint64_t sink = 0;
    for (int k = 0; k < 3; ++k) {
      const auto t0 = clock_type::now();
      sink = sink + spin(iters, static_cast<std::uint64_t>(k) + 7);
      best = std::min(best, us_since(t0));
    }
  });
  t.join();
  return best;
}

/// --pairs: the slowdown of each pair of allowed CPUs running the work at once.
int run_pairs(double work_us) {
  const std::vector<int> cpus = zone::net::allowed_cpus();
  if (cpus.empty()) {
    std::fprintf(stderr, "host-jitter: cannot read the CPUs this process may use\n");
    return 1;
  }
  const std::uint64_t iters = calibrate(work_us);
  std::vector<double> alone(cpus.size());
  for (std::size_t i = 0; i < cpus.size(); ++i) {
    alone[i] = alone_on(cpus[i], iters);
    if (!(alone[i] < 1e30)) {
      std::fprintf(stderr, "host-jitter: cannot pin a thread to CPU %d\n", cpus[i]);
      return 1;
    }
  }
  std::printf("host-jitter --pairs: %zu CPUs, %.0f us of work on two CPUs at once (best of 3) against each alone\n\n",
              cpus.size(), work_us);
  std::printf("| CPU pair | slowdown (the slower of the two) |\n|---|---|\n");
  std::size_t slowed = 0, total = 0;
  double worst = 0;
  for (std::size_t i = 0; i < cpus.size(); ++i) {
    for (std::size_t j = i + 1; j < cpus.size(); ++j) {
      double took[2] = {1e30, 1e30};
      for (int rep = 0; rep < 3; ++rep) {
        std::atomic<int> ready{0};
        double once[2] = {0, 0};
        const auto side = [&](int k, int cpu) {
          const bool pinned = pin_to(cpu);
          ready.fetch_add(1);  // pinned or not: the other side must not wait forever
          while (ready.load() < 2) {}
          if (!pinned) {
            once[k] = std::numeric_limits<double>::quiet_NaN();
            return;
          }
          const auto t0 = clock_type::now();
          volatile std::uint64_t sink = spin(iters, static_cast<std::uint64_t>(rep * 2 + k) + 11);
          (void)sink;
          once[k] = us_since(t0);
        };
        std::thread a(side, 0, cpus[i]), b(side, 1, cpus[j]);
        a.join();
        b.join();
        if (std::isnan(once[0]) || std::isnan(once[1])) {
          std::fprintf(stderr, "host-jitter: cannot pin threads to CPUs %d and %d\n", cpus[i], cpus[j]);
          return 1;
        }
        took[0] = std::min(took[0], once[0]);
        took[1] = std::min(took[1], once[1]);
      }
      const double slow = std::max(took[0] / alone[i], took[1] / alone[j]);
      worst = std::max(worst, slow);
      ++total;
      if (slow >= 1.15) {
        ++slowed;
        std::printf("| %d + %d | %.2fx |\n", cpus[i], cpus[j], slow);
      }
    }
  }
  std::printf("\n%zu of %zu pairs slowed by 15%% or more (the worst %.2fx)\n", slowed, total, worst);
  std::printf("\nthe kernel's thread siblings:");
  for (const int c : cpus) {
    std::ifstream f("/sys/devices/system/cpu/cpu" + std::to_string(c) + "/topology/thread_siblings_list");
    std::string list;
    std::printf(" %d:[%s]", c, (f >> list) ? list.c_str() : "?");
  }
  std::printf("\n");
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  options o;
  namespace po = zone::tools::po;
  po::options_description cli;
  cli.add_options()("threads", po::value(&o.threads))("work-us", po::value(&o.work_us))("rate", po::value(&o.rate))(
      "periods", po::value(&o.periods))("pairs", po::bool_switch(&o.pairs));
  if (const auto rc = zone::tools::parse_command_line(argc, argv, "host-jitter", usage_text, cli, 2)) return *rc;
  if (o.pairs) {
    if (!(o.work_us > 0)) {
      std::cerr << "host-jitter: need work-us > 0\n";
      return 2;
    }
    return run_pairs(o.work_us);
  }
  if (o.threads <= 0) o.threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  if (!(o.work_us > 0) || !(o.rate > 0) || o.periods <= 0 || 1e6 / o.rate <= 2 * o.work_us) {
    std::cerr << "host-jitter: need work-us > 0, rate > 0, periods > 0 and the work well inside a period\n";
    return 2;
  }
  const std::uint64_t iters = calibrate(o.work_us);
  const auto period = std::chrono::duration_cast<clock_type::duration>(std::chrono::duration<double>(1.0 / o.rate));
  const int warmup = 30, total = warmup + o.periods;
  std::printf("host-jitter: %d threads, %.0f us of work each per period, %.1f Hz, %d periods (+%d warm-up)\n", o.threads,
              o.work_us, o.rate, o.periods, warmup);

  // done[p * threads + t]: when thread t finished period p.
  std::vector<clock_type::time_point> done(static_cast<std::size_t>(total) * o.threads);
  std::vector<double> alone;
  const auto start = clock_type::now() + std::chrono::milliseconds(50);
  std::atomic<std::uint64_t> sink{0};
  const auto worker = [&](int t) {
    std::uint64_t acc = 0;
    for (int p = 0; p < total; ++p) {
      std::this_thread::sleep_until(start + p * period);
      acc += spin(iters, static_cast<std::uint64_t>(p * 131 + t));
      done[static_cast<std::size_t>(p) * o.threads + t] = clock_type::now();
    }
    sink += acc;
  };
  std::vector<std::thread> pool;
  for (int t = 1; t < o.threads; ++t) pool.emplace_back(worker, t);
  const cpu_times c0 = read_cpu();
  {
    std::uint64_t acc = 0;
    for (int p = 0; p < total; ++p) {
      std::this_thread::sleep_until(start + p * period);
      const auto t0 = clock_type::now();
      acc += spin(iters, static_cast<std::uint64_t>(p * 131));
      done[static_cast<std::size_t>(p) * o.threads] = clock_type::now();
      if (p >= warmup) alone.push_back(std::chrono::duration<double, std::micro>(done[static_cast<std::size_t>(p) * o.threads] - t0).count());
    }
    sink += acc;
  }
  for (auto& th : pool) th.join();
  const cpu_times c1 = read_cpu();

  std::vector<double> phase;
  for (int p = warmup; p < total; ++p) {
    auto last = done[static_cast<std::size_t>(p) * o.threads];
    for (int t = 1; t < o.threads; ++t) last = std::max(last, done[static_cast<std::size_t>(p) * o.threads + t]);
    phase.push_back(std::chrono::duration<double, std::micro>(last - (start + p * period)).count());
  }
  std::printf("\n| us | p50 | p90 | p99 | max | p50 / work | p99 / work | over 2x work |\n|---|---|---|---|---|---|---|---|\n");
  print_row("one thread's work", alone, o.work_us);
  print_row("parallel phase (period start -> last thread done)", phase, o.work_us);
  if (c1.total > c0.total) {
    std::printf("\nsteal time (/proc/stat): %.2f%% of all CPU time in the run\n",
                100.0 * static_cast<double>(c1.steal - c0.steal) / static_cast<double>(c1.total - c0.total));
  }
  std::printf("(checksum %llu)\n", static_cast<unsigned long long>(sink.load() & 0xff));
  return 0;
}
