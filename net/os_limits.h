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
