#include <chrono>
#include <limits>
#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#endif

#include "thread_pool.h"

#include <pthread.h>

#include <cstdio>

namespace zone::interest {

namespace {

using clock_type = std::chrono::steady_clock;

inline void cpu_relax() {
#if defined(__x86_64__) || defined(__i386__)
  _mm_pause();
#else
  std::this_thread::yield();
#endif
}

/// Spins until `ready()` or `spin_us` have passed; true when ready.
template <class Ready>
bool spin_until(unsigned spin_us, Ready ready) {
  if (spin_us == 0) return ready();
  const auto until = clock_type::now() + std::chrono::microseconds(spin_us);
  for (unsigned k = 0;; ++k) {
    if (ready()) return true;
    cpu_relax();
    if ((k & 63) == 63 && clock_type::now() >= until) return ready();
  }
}

}  // namespace

thread_pool::thread_pool(unsigned threads, unsigned spin_us, std::function<void(unsigned)> on_start)
    : spin_us_(spin_us) {
  if (threads == 0) threads = std::max(1u, std::thread::hardware_concurrency());
  workers_.reserve(threads - 1);
  for (unsigned i = 1; i < threads; ++i) {
    workers_.emplace_back([this, i, on_start] {
      // Named for per-thread CPU readings (top -H, /proc/<pid>/task/*/comm).
      char name[16];
      std::snprintf(name, sizeof name, "zone-worker-%u", i);
      pthread_setname_np(pthread_self(), name);
      if (on_start) on_start(i);
      worker_loop();
    });
  }
}

thread_pool::~thread_pool() {
  {
    std::lock_guard lock(mutex_);
    stop_ = true;
  }
  wake_.notify_all();
  for (auto& w : workers_) w.join();
}

void thread_pool::drain(std::uint32_t generation) {
  std::uint64_t w = job_.load();
  for (;;) {
    if (static_cast<std::uint32_t>(w >> 32) != generation) return;  // a later run (or none)
    const auto i = static_cast<std::uint32_t>(w);
    // The count read here is this run's: run() closes job_ (a new value) before it stores the
    // next run's count, so if the count read is a later run's, the CAS below fails (all seq_cst).
    const std::uint32_t count = task_count_.load();
    if (i >= count) return;
    if (!job_.compare_exchange_weak(w, w + 1)) continue;
    // Index i of this run is ours: the run's task and count were published before job_.
    (*task_.load())(i);
    if (finished_.fetch_add(1) + 1 == count && caller_waiting_.load()) {  // seq_cst: see run()
      std::lock_guard lock(mutex_);
      done_.notify_all();
    }
    w = job_.load(std::memory_order_acquire);
  }
}

void thread_pool::worker_loop() {
  std::uint32_t seen = 0;
  for (;;) {
    std::uint32_t g = seen;
    // park() after run `seen` (the one this worker just drained) ends the spin: sleep then.
    spin_until(spin_us_, [&] {
      return stop_.load(std::memory_order_relaxed) || (g = generation_.load()) != seen ||
             park_.load(std::memory_order_relaxed) == seen;
    });
    if (g == seen && !stop_) {
      std::unique_lock lock(mutex_);
      ++sleepers_;
      wake_.wait(lock, [&] { return stop_.load() || generation_.load() != seen; });
      --sleepers_;
      g = generation_.load();
    }
    if (stop_) return;
    seen = g;
    drain(g);
  }
}

void thread_pool::run(std::size_t n, const std::function<void(std::size_t)>& task) {
  if (n == 0) return;
  if (workers_.empty() || n == 1) {
    for (std::size_t i = 0; i < n; ++i) task(i);
    return;
  }
  // Indices are 32-bit: a larger run goes in rounds.
  constexpr std::size_t most = std::numeric_limits<std::uint32_t>::max() / 2;
  if (n > most) {
    for (std::size_t base = 0; base < n; base += most) {
      const std::size_t len = std::min(most, n - base);
      const std::function<void(std::size_t)> shifted = [&](std::size_t i) { task(base + i); };
      run(len, shifted);
    }
    return;
  }
  const auto count = static_cast<std::uint32_t>(n);
  const std::uint32_t generation = generation_.load(std::memory_order_relaxed) + 1;
  // Close the previous run first: a worker that read its last job_ value (every index claimed)
  // and is about to read the count must fail its CAS rather than claim an index of this run with
  // this run's count (that ran an index twice and could leave finished_ past the count: a hang).
  job_.store((static_cast<std::uint64_t>(generation) << 32) | closed_index);
  task_.store(&task);
  task_count_.store(count);
  finished_.store(0);
  job_.store(static_cast<std::uint64_t>(generation) << 32);
  generation_.store(generation);  // seq_cst: ordered against sleepers_ below
  if (sleepers_.load() > 0) {
    std::lock_guard lock(mutex_);
    wake_.notify_all();
  }
  drain(generation);
  if (!spin_until(spin_us_, [&] { return finished_.load(std::memory_order_acquire) == count; })) {
    std::unique_lock lock(mutex_);
    caller_waiting_ = true;
    done_.wait(lock, [&] { return finished_.load() == count; });
    caller_waiting_ = false;
  }
}

void run_tasks(thread_pool* pool, std::size_t n, const std::function<void(std::size_t)>& task) {
  if (pool != nullptr) {
    pool->run(n, task);
  } else {
    for (std::size_t i = 0; i < n; ++i) task(i);
  }
}

}  // namespace zone::interest
