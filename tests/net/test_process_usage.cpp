// net/os_limits.h's read_process_usage (zone-server's process_* and zone_thread_cpu_seconds_total
// metrics): the process's CPU time grows by what a thread burns, a named thread is listed with
// its own CPU time, the descriptors count a file opened and closed, and the resident memory a
// block touched.
#include <doctest/doctest.h>

#include <fcntl.h>
#include <pthread.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstring>
#include <memory>
#include <thread>

#include "net/os_limits.h"

using namespace zone::net;

namespace {
// Burns `seconds` of the calling thread's own CPU time.
void burn(double seconds) {
  timespec ts{};
  const auto cpu = [&] {
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
    return static_cast<double>(ts.tv_sec) + static_cast<double>(ts.tv_nsec) * 1e-9;
  };
  const double until = cpu() + seconds;
  volatile unsigned x = 1;
  while (cpu() < until) {
    for (int i = 0; i < 10000; ++i) x = x * 1664525u + 1013904223u;
  }
}
}  // namespace

TEST_SUITE("net.process_usage") {
  TEST_CASE("CPU time: the process's grows by what a thread burns; that thread is listed by name with its own") {
    const auto before = read_process_usage(false);
    CHECK(before.error.empty());
    CHECK(before.threads.empty());  // not asked for
    std::atomic<int> tid{0};
    std::atomic<bool> done{false}, release{false};
    std::thread t([&] {
      pthread_setname_np(pthread_self(), "usage-burner");
      tid = current_thread_id();
      burn(0.3);
      done = true;
      while (!release) std::this_thread::sleep_for(std::chrono::milliseconds(1));
    });
    while (!done) std::this_thread::sleep_for(std::chrono::milliseconds(1));
    const auto after = read_process_usage(true);
    release = true;
    t.join();
    CHECK(after.error.empty());
    CHECK(after.cpu_seconds >= before.cpu_seconds + 0.29);
    bool found = false;
    for (const auto& th : after.threads) {
      if (th.tid != tid.load()) continue;
      found = true;
      CHECK(th.name == "usage-burner");
      CHECK(th.cpu_seconds >= 0.25);  // clock ticks of 10 ms: 0.3 s read as 0.29-0.31
      CHECK(th.cpu_seconds <= after.cpu_seconds);
    }
    CHECK(found);
    // This thread is listed too, under its id.
    bool me = false;
    for (const auto& th : after.threads) me = me || th.tid == current_thread_id();
    CHECK(me);
    CHECK(after.threads.size() >= 2);
  }

  TEST_CASE("descriptors: one more while a file is open, and the limit is the soft RLIMIT_NOFILE") {
    const auto before = read_process_usage(false);
    const int fd = ::open("/dev/null", O_RDONLY);
    REQUIRE(fd >= 0);
    const auto open_now = read_process_usage(false);
    ::close(fd);
    const auto after = read_process_usage(false);
    CHECK(open_now.open_fds == before.open_fds + 1);
    CHECK(after.open_fds == before.open_fds);
    CHECK(before.open_fds >= 3);  // stdin, stdout, stderr at least
    CHECK(before.max_fds >= before.open_fds);
  }

  TEST_CASE("resident memory: 64 MB touched shows") {
    const auto before = read_process_usage(false);
    constexpr std::size_t n = 64u << 20;
    std::unique_ptr<char[]> block(new char[n]);
    std::memset(block.get(), 1, n);
    const auto after = read_process_usage(false);
    CHECK(before.resident_bytes > 0);
    CHECK(after.resident_bytes >= before.resident_bytes + n / 2);
    volatile char keep = block[n - 1];
    (void)keep;
  }
}
