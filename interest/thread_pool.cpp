#include "interest.h"

namespace zone::interest {

thread_pool::thread_pool(unsigned threads) {
  if (threads == 0) threads = std::max(1u, std::thread::hardware_concurrency());
  workers_.reserve(threads - 1);
  for (unsigned i = 1; i < threads; ++i) workers_.emplace_back([this] { worker_loop(); });
}

thread_pool::~thread_pool() {
  {
    std::lock_guard lock(mutex_);
    stop_ = true;
  }
  wake_.notify_all();
  for (auto& w : workers_) w.join();
}

void thread_pool::drain() {
  // Called with mutex_ unlocked; takes indices one at a time until none are left.
  for (;;) {
    std::size_t i;
    const std::function<void(std::size_t)>* task;
    {
      std::lock_guard lock(mutex_);
      if (task_ == nullptr || next_ >= task_count_) return;
      i = next_++;
      task = task_;
    }
    (*task)(i);
    bool last;
    {
      std::lock_guard lock(mutex_);
      last = ++finished_ == task_count_;
    }
    if (last) done_.notify_all();
  }
}

void thread_pool::worker_loop() {
  std::uint64_t seen = 0;
  for (;;) {
    {
      std::unique_lock lock(mutex_);
      wake_.wait(lock, [&] { return stop_ || generation_ != seen; });
      if (stop_) return;
      seen = generation_;
    }
    drain();
  }
}

void thread_pool::run(std::size_t n, const std::function<void(std::size_t)>& task) {
  if (n == 0) return;
  if (workers_.empty() || n == 1) {
    for (std::size_t i = 0; i < n; ++i) task(i);
    return;
  }
  {
    std::lock_guard lock(mutex_);
    task_ = &task;
    task_count_ = n;
    next_ = 0;
    finished_ = 0;
    ++generation_;
  }
  wake_.notify_all();
  drain();
  std::unique_lock lock(mutex_);
  done_.wait(lock, [&] { return finished_ == task_count_; });
  task_ = nullptr;
}

void run_tasks(thread_pool* pool, std::size_t n, const std::function<void(std::size_t)>& task) {
  if (pool != nullptr) {
    pool->run(n, task);
  } else {
    for (std::size_t i = 0; i < n; ++i) task(i);
  }
}

}  // namespace zone::interest
