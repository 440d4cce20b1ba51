// The thread pool: every index of every run exactly once, with and without spinning, runs back to
// back and after the workers went to sleep, nested data written by tasks visible to the caller.
#include <doctest/doctest.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <ctime>
#include <mutex>
#include <thread>
#include <vector>

#include "interest/thread_pool.h"

using zone::interest::thread_pool;

namespace {

/// Runs `rounds` runs of varying sizes; each task adds its index to its own slot.
void check_runs(thread_pool& pool, int rounds, bool pause_between) {
  std::vector<std::uint64_t> hits;
  for (int r = 0; r < rounds; ++r) {
    const std::size_t n = static_cast<std::size_t>((r * 37) % 300) + 1;
    hits.assign(n, 0);
    std::atomic<std::size_t> calls{0};
    pool.run(n, [&](std::size_t i) {
      hits[i] += i + 1;  // a plain write: the caller must see it after run() returns
      calls.fetch_add(1, std::memory_order_relaxed);
    });
    REQUIRE(calls.load() == n);
    for (std::size_t i = 0; i < n; ++i) REQUIRE(hits[i] == i + 1);
    if (pause_between && r % 50 == 0) std::this_thread::sleep_for(std::chrono::milliseconds(3));
  }
}

}  // namespace

TEST_SUITE("interest.thread_pool") {
  TEST_CASE("every index exactly once: blocking pool, spinning pool, one thread") {
    for (const unsigned threads : {1u, 2u, 5u}) {
      for (const unsigned spin : {0u, 200u, 5000u}) {
        CAPTURE(threads);
        CAPTURE(spin);
        thread_pool pool(threads, spin);
        CHECK(pool.size() == threads);
        CHECK(pool.spin_us() == spin);
        check_runs(pool, 400, false);  // back to back: workers still spinning or still draining
        check_runs(pool, 200, true);   // with pauses longer than the spin: workers asleep
      }
    }
  }

  TEST_CASE("a small run then a larger one, back to back: no index of the next run claimed early") {
    // Regression: a worker that had read the small run's last job value (every index claimed)
    // could read the next run's larger count and claim an index of it before the run was
    // published: that index ran twice, and the extra finish could hang the caller.
    for (const unsigned spin : {0u, 2000u}) {
      CAPTURE(spin);
      thread_pool pool(4, spin);
      std::vector<std::uint32_t> hits(64);
      for (int r = 0; r < 20000; ++r) {
        const std::size_t n = r % 2 == 0 ? 2 : 64;
        std::fill(hits.begin(), hits.begin() + static_cast<std::ptrdiff_t>(n), 0u);
        pool.run(n, [&](std::size_t i) { ++hits[i]; });
        for (std::size_t i = 0; i < n; ++i) {
          if (hits[i] != 1) FAIL("run " << r << " index " << i << " ran " << hits[i] << " times");
        }
      }
    }
  }

  TEST_CASE("uneven tasks: the caller waits for the slowest") {
    thread_pool pool(4, 100);
    std::vector<int> done(16, 0);
    pool.run(done.size(), [&](std::size_t i) {
      if (i % 5 == 0) std::this_thread::sleep_for(std::chrono::milliseconds(2));
      done[i] = 1;
    });
    for (const int d : done) CHECK(d == 1);
  }

  TEST_CASE("destruction while workers sleep or spin") {
    for (const unsigned spin : {0u, 100000u}) {
      thread_pool pool(3, spin);
      pool.run(10, [](std::size_t) {});
    }  // the destructor must not hang, whichever state the workers are in
  }

  TEST_CASE("park: spinning workers go to sleep at once (no CPU while idle), and the next runs are whole") {
    // Workers that spin for a whole second after a run would burn ~3 CPU-seconds per second
    // here; parked, they burn nothing while the caller waits.
    thread_pool pool(4, 1000000);
    for (int round = 0; round < 3; ++round) {
      pool.run(64, [](std::size_t) {});
      pool.park();
      timespec a{}, b{};
      clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &a);
      std::this_thread::sleep_for(std::chrono::milliseconds(200));
      clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &b);
      const double cpu_ms = (b.tv_sec - a.tv_sec) * 1e3 + (b.tv_nsec - a.tv_nsec) / 1e6;
      CAPTURE(round);
      CHECK(cpu_ms < 60);  // spinning: ~600 ms of CPU in these 200 ms
      check_runs(pool, 20, false);
    }
    pool.park();  // parking twice in a row, then destruction
    pool.park();
  }

  TEST_CASE("on_start runs once on each worker thread, before that worker takes a task") {
    std::mutex m;
    std::vector<unsigned> started;
    std::vector<std::thread::id> ids;
    {
      thread_pool pool(4, 0, [&](unsigned worker) {
        const std::lock_guard lock(m);
        started.push_back(worker);
        ids.push_back(std::this_thread::get_id());
      });
      std::mutex seen_m;
      std::vector<std::thread::id> ran_on;
      for (int r = 0; r < 50; ++r) {
        pool.run(64, [&](std::size_t) {
          std::this_thread::sleep_for(std::chrono::microseconds(20));
          const std::lock_guard lock(seen_m);
          ran_on.push_back(std::this_thread::get_id());
        });
      }
      const std::lock_guard lock(m);
      // Every thread that ran a task other than the caller is a worker whose on_start had run.
      for (const auto id : ran_on) {
        if (id != std::this_thread::get_id()) CHECK(std::find(ids.begin(), ids.end(), id) != ids.end());
      }
    }
    // The workers joined: each started once (one may start after the runs on a loaded machine).
    std::sort(started.begin(), started.end());
    CHECK(started == std::vector<unsigned>{1, 2, 3});
  }
}
