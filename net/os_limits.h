// Process limits that a server or a swarm with thousands of sockets needs (docs/protocol.md), and
// CPU lists for pinning threads (zone-server --worker-cpus / --io-cpus, docs/operating.md).
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace zone::net {

/// The open-file limit (RLIMIT_NOFILE) of this process.
struct open_file_limit {
  std::uint64_t soft = 0;  ///< what the process may open now (every socket is a file descriptor)
  std::uint64_t hard = 0;  ///< the most the soft limit can be raised to without privileges
  std::uint64_t before = 0;  ///< the soft limit before raise_open_file_limit()
  std::string error;       ///< why reading or raising failed (empty when it worked)
};

/// Raises the soft open-file limit to the hard limit (once, at startup: it changes the whole
/// process) and reports the limits. Never lowers it. Call before opening many sockets.
[[nodiscard]] open_file_limit raise_open_file_limit();

/// File descriptors a process needs beside its sockets (logs, epoll, pipes, libraries): the
/// headroom kept when checking a connection count against the limit.
inline constexpr std::uint64_t reserved_file_descriptors = 64;

/// This process's use of the machine, as Linux reports it (for /metrics: docs/operating.md).
struct process_usage {
  double cpu_seconds = 0;            ///< user + system time of every thread, ended ones too (getrusage)
  std::uint64_t resident_bytes = 0;  ///< resident memory (/proc/self/statm)
  std::uint64_t open_fds = 0;        ///< open file descriptors (/proc/self/fd)
  std::uint64_t max_fds = 0;         ///< the soft open-file limit
  struct thread {
    int tid = 0;
    std::string name;        ///< its comm (pthread_setname_np; at most 15 bytes)
    double cpu_seconds = 0;  ///< user + system time (/proc/self/task/<tid>/stat; clock-tick resolution)
  };
  std::vector<thread> threads;  ///< the live threads, with `with_threads`
  std::string error;            ///< what could not be read (the fields it feeds stay 0); empty when all was
};

/// Reads process_usage (each thread's too with `with_threads`: a file per thread).
[[nodiscard]] process_usage read_process_usage(bool with_threads);

/// The calling thread's kernel id (gettid).
[[nodiscard]] int current_thread_id();

/// A CPU list as taskset and cpuset write it ("0-5,8,10-11"): the CPUs in ascending order, each
/// once; "" is the empty list (no pinning). Null with `error` set on anything else (a bad number,
/// a range backwards, a CPU at or past CPU_SETSIZE).
[[nodiscard]] std::optional<std::vector<int>> parse_cpu_list(std::string_view text, std::string* error = nullptr);

/// The CPUs the calling thread may run on now (sched_getaffinity(0): the process's, as taskset or
/// a cgroup set them, unless this thread was pinned since).
[[nodiscard]] std::vector<int> allowed_cpus();

/// Null when every CPU of `cpus` (any order) is one the calling thread may run on (allowed_cpus),
/// else why not (the CPUs missing and those allowed, as CPU lists).
[[nodiscard]] std::optional<std::string> check_cpus_allowed(const std::vector<int>& cpus);

/// `cpus` as a CPU list ("0-5,8"), the inverse of parse_cpu_list.
[[nodiscard]] std::string format_cpu_list(const std::vector<int>& cpus);

/// Pins the calling thread to `cpus` (nothing when empty); null, or why it failed (a number
/// outside 0 .. CPU_SETSIZE - 1, or the system's refusal: no CPU of the list allowed).
std::optional<std::string> pin_current_thread(const std::vector<int>& cpus);

}  // namespace zone::net
