// Process limits that a server or a swarm with thousands of sockets needs (docs/protocol.md).
#pragma once

#include <cstdint>
#include <string>

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

}  // namespace zone::net
