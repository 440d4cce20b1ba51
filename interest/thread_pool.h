// The worker threads of the interest core (and of the GPU finders' host-side work): a fixed pool
// for short data-parallel phases, the calling thread included. Installed as <zone/thread_pool.h>:
// a program that hands the finders a pool constructs it from this header (docs/embedding.md).
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

namespace zone::interest {

/// A fixed set of worker threads for data-parallel loops. `run` hands out task indices to the
/// workers and the calling thread and returns when every task has finished. One `run` at a time.
///
/// Idle workers (and the caller waiting for the last task) spin for `spin_us` microseconds before
/// they block: a tick made of several short parallel phases then pays no thread wake-up between
/// its phases (on a virtual machine a wake-up of a sleeping thread can take milliseconds), at the
/// price of up to `spin_us` of busy CPU per thread after each phase. 0 blocks at once.
class thread_pool {
 public:
  /// `threads` = total threads that run tasks, the caller included; 0 = hardware concurrency.
  /// `on_start`, when set, runs first on each worker thread it starts (worker 1 .. threads - 1),
  /// e.g. to pin it to CPUs; the caller's thread is the caller's to set up.
  explicit thread_pool(unsigned threads = 0, unsigned spin_us = 0, std::function<void(unsigned worker)> on_start = {});
  ~thread_pool();
  thread_pool(const thread_pool&) = delete;
  thread_pool& operator=(const thread_pool&) = delete;

  [[nodiscard]] unsigned size() const { return static_cast<unsigned>(workers_.size()) + 1; }
  [[nodiscard]] unsigned spin_us() const { return spin_us_; }
  /// Runs task(i) for every i in [0, n), each exactly once, spread over the threads.
  void run(std::size_t n, const std::function<void(std::size_t)>& task);
  /// Idle workers stop spinning now and sleep until the next run (which wakes them): for a caller
  /// about to block for longer than the spin (e.g. on a device), so the workers do not burn the
  /// spin meanwhile. Any thread may call it; it changes nothing else.
  void park() noexcept { park_.store(generation_.load()); }

 private:
  void worker_loop();
  void drain(std::uint32_t generation);
  std::vector<std::thread> workers_;
  unsigned spin_us_ = 0;
  std::mutex mutex_;
  std::condition_variable wake_, done_;
  // The current run: its task and size are written before the run is published through job_;
  // job_ = (generation << 32) | next index, claimed by compare-and-swap, so a worker late from
  // an earlier run can never take an index of a later one.
  std::atomic<const std::function<void(std::size_t)>*> task_{nullptr};
  std::atomic<std::uint32_t> task_count_{0};
  std::atomic<std::uint64_t> job_{0};
  static constexpr std::uint32_t closed_index = 0xffffffffu;  ///< in job_: no index to claim (above any count)
  std::atomic<std::uint32_t> generation_{0};
  std::atomic<std::uint32_t> finished_{0};
  std::atomic<int> sleepers_{0};
  std::atomic<bool> caller_waiting_{false};
  std::atomic<bool> stop_{false};
  /// The run generation after which park() was called: a worker idle after that run sleeps.
  std::atomic<std::uint32_t> park_{0xffffffffu};
};

/// Runs task(i) for i in [0, n) on `pool`, or inline when `pool` is null.
void run_tasks(thread_pool* pool, std::size_t n, const std::function<void(std::size_t)>& task);

}  // namespace zone::interest
