// A blocking loopback test client on plain POSIX sockets that reads with the codec under test.
// Shared by the net and zone test suites.
#pragma once

#include <doctest/doctest.h>

#include <arpa/inet.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <deque>
#include <optional>
#include <string>
#include <vector>

#include "net/protocol.h"

namespace zone::net::testing {

using namespace std::chrono_literals;

/// A blocking loopback client on plain POSIX sockets, using the codec under test to read.
class test_client {
 public:
  /// `source`: the loopback address to connect from (host order, e.g. 0x7f000002 for
  /// 127.0.0.2; 0 = the system's choice, 127.0.0.1), so tests can play several hosts.
  explicit test_client(std::uint16_t port, int rcvbuf = 0, std::uint32_t source = 0) {
    fd_ = ::socket(AF_INET, SOCK_STREAM, 0);
    REQUIRE(fd_ >= 0);
    if (rcvbuf > 0) ::setsockopt(fd_, SOL_SOCKET, SO_RCVBUF, &rcvbuf, sizeof rcvbuf);
    int one = 1;
    ::setsockopt(fd_, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
    if (source != 0) {
      sockaddr_in from{};
      from.sin_family = AF_INET;
      from.sin_addr.s_addr = htonl(source);
      REQUIRE(::bind(fd_, reinterpret_cast<sockaddr*>(&from), sizeof from) == 0);
    }
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(port);
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    REQUIRE(::connect(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) == 0);
  }
  ~test_client() {
    if (fd_ >= 0) ::close(fd_);
  }
  test_client(const test_client&) = delete;
  test_client& operator=(const test_client&) = delete;

  bool send_bytes(std::span<const std::uint8_t> bytes) {
    std::size_t at = 0;
    while (at < bytes.size()) {
      const ssize_t n = ::send(fd_, bytes.data() + at, bytes.size() - at, MSG_NOSIGNAL);
      if (n <= 0) return false;
      at += static_cast<std::size_t>(n);
    }
    return true;
  }
  bool send(const message& m) { return send_bytes(encode_frame(m)); }

  /// The next message, or nothing after `timeout` or when the connection is closed.
  std::optional<message> read(std::chrono::milliseconds timeout = 3000ms) {
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    while (pending_.empty() && !closed_) {
      // Rounded up: a 1 ms read waits up to 1 ms (truncated, it would return at once, unread).
      const auto left = std::chrono::ceil<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
      if (left.count() <= 0) break;
      pollfd p{fd_, POLLIN, 0};
      if (::poll(&p, 1, static_cast<int>(left.count())) <= 0) continue;
      std::uint8_t buf[65536];
      const ssize_t n = ::recv(fd_, buf, sizeof buf, 0);
      if (n <= 0) {
        closed_ = true;
        reset_ = n < 0 && errno == ECONNRESET;
        break;
      }
      decoder_.feed({buf, static_cast<std::size_t>(n)});
      for (auto s = decoder_.next(); s.is_frame(); s = decoder_.next()) pending_.push_back(*to_message(*s.frame.envelope));
      REQUIRE_FALSE(decoder_.failed());
    }
    if (pending_.empty()) return std::nullopt;
    message m = std::move(pending_.front());
    pending_.pop_front();
    return m;
  }

  /// Reads until the server closes the connection (true) or `timeout` passes (false); the
  /// messages seen meanwhile are appended to `seen`.
  bool wait_closed(std::chrono::milliseconds timeout, std::vector<message>* seen = nullptr) {
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    while (std::chrono::steady_clock::now() < deadline) {
      auto m = read(std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now()));
      if (m && seen) seen->push_back(std::move(*m));
      if (!m && closed_ && pending_.empty()) return true;
    }
    return false;
  }
  [[nodiscard]] bool closed() const { return closed_; }
  [[nodiscard]] bool reset() const { return reset_; }
  /// The socket, for tests that read it themselves (then read() no longer sees whole frames).
  [[nodiscard]] int fd() const { return fd_; }

 private:
  int fd_ = -1;
  frame_decoder decoder_{[] {
    decoder_options o;
    o.max_frame_bytes = 1 << 22;
    return o;
  }()};
  std::deque<message> pending_;
  bool closed_ = false, reset_ = false;
};

/// One HTTP/1.1 request over a raw socket; returns the whole response (until the server closes).
inline std::string http_request(std::uint16_t port, const std::string& request) {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  REQUIRE(fd >= 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(port);
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  REQUIRE(::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) == 0);
  REQUIRE(::send(fd, request.data(), request.size(), MSG_NOSIGNAL) == static_cast<ssize_t>(request.size()));
  std::string response;
  char buf[4096];
  for (;;) {
    pollfd p{fd, POLLIN, 0};
    if (::poll(&p, 1, 3000) <= 0) break;
    const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
    if (n <= 0) break;
    response.append(buf, static_cast<std::size_t>(n));
  }
  ::close(fd);
  return response;
}

/// GET `path` over HTTP/1.1 from a loopback server; the whole response.
inline std::string http_get(std::uint16_t port, const std::string& path) {
  return http_request(port, "GET " + path + " HTTP/1.1\r\nHost: localhost\r\n\r\n");
}

}  // namespace zone::net::testing
