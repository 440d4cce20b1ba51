// libFuzzer: the server's handling of what a client sends (net/server.cpp: admission, hello, the
// name rules, inputs, teleports, pings, rate limits, the decoder) on a real server over loopback.
// Each input is one connection: its bytes, then end of stream. The game side checks what reaches
// it: a session is announced (connected) before any of its messages, every hello it sees carries
// a valid name, no input, teleport or ping event at all (pings are the server's), and the server
// keeps serving (every connection is closed by it after the end of stream).
#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <spdlog/spdlog.h>
#include <cerrno>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <set>
#include <vector>

#include "net/protocol.h"
#include "net/server.h"

using namespace zone::net;

namespace {

server& the_server() {
  static std::unique_ptr<server> srv = [] {
    spdlog::set_level(spdlog::level::off);
    server_options opt;
    opt.io_threads = 1;
    opt.inbound.max_frame_bytes = 4096;
    opt.flood_limit = 20;
    // One short connection per input from one address, thousands a second: the reconnect churn
    // limit would refuse (and hold) nearly all of them; it has its own tests (tests/net).
    opt.connect_rate = 0;
    auto s = std::make_unique<server>(opt);
    if (s->start()) std::abort();
    return s;
  }();
  return *srv;
}

std::set<session_id> announced;

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  server& srv = the_server();
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  if (fd < 0) std::abort();
  // From 127.0.0.1 .. 127.0.0.250 in turn: the server closes first, so each connection leaves a
  // TIME_WAIT (60 s) on its 4-tuple, and one source address runs out of ports at ~470 runs a second.
  static std::uint32_t next_source = 0;
  sockaddr_in from{};
  from.sin_family = AF_INET;
  from.sin_addr.s_addr = htonl(0x7f000001u + next_source++ % 250);
  if (::bind(fd, reinterpret_cast<sockaddr*>(&from), sizeof from) != 0) {
    ::close(fd);
    return 0;  // no port left here: the harness's limit, not the server's
  }
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(srv.port());
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  // A signal (libFuzzer's once-a-second SIGALRM for -timeout) may interrupt the connect, which
  // then completes on its own: wait for it and take its outcome.
  int rc = ::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr);
  if (rc != 0 && errno == EINTR) {
    pollfd w{fd, POLLOUT, 0};
    int n = 0;
    do {
      n = ::poll(&w, 1, 5000);
    } while (n < 0 && errno == EINTR);
    int err = ETIMEDOUT;
    socklen_t len = sizeof err;
    if (n > 0) ::getsockopt(fd, SOL_SOCKET, SO_ERROR, &err, &len);
    errno = err;
    rc = err == 0 ? 0 : -1;
  }
  if (rc != 0) {
    if (errno == EADDRNOTAVAIL || errno == EADDRINUSE) {
      ::close(fd);
      return 0;  // the harness's ports, as above
    }
    // Refused: the server stopped accepting. Said with the reason, as a finding needs it.
    std::fprintf(stderr, "fuzz_session: connect to the server failed: %s (errno %d)\n", std::strerror(errno), errno);
    std::abort();
  }
  std::size_t at = 0;
  while (at < size) {
    const ssize_t n = ::send(fd, data + at, size - at, MSG_NOSIGNAL);
    if (n <= 0) break;  // the server closed it already (an error frame on its way)
    at += static_cast<std::size_t>(n);
  }
  ::shutdown(fd, SHUT_WR);
  // The server closes every connection after the end of its stream (or sooner, with an error).
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(5);
  std::uint8_t buf[4096];
  for (;;) {
    if (std::chrono::steady_clock::now() > deadline) std::abort();  // a connection it never closed
    pollfd p{fd, POLLIN, 0};
    if (::poll(&p, 1, 100) <= 0) continue;
    const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
    if (n <= 0) break;
  }
  ::close(fd);
  std::vector<inbound_event> events;
  srv.poll(events);
  for (const auto& e : events) {
    switch (e.type) {
      case inbound_event::kind::connected:
        if (!announced.insert(e.session).second) std::abort();
        break;
      case inbound_event::kind::message:
        if (!announced.count(e.session) || !e.msg) std::abort();
        if (const auto* h = std::get_if<hello_msg>(&*e.msg)) {
          if (check_player_name(h->name, srv.options().max_name_bytes)) std::abort();
        } else if (!std::holds_alternative<input_msg>(*e.msg) && !std::holds_alternative<teleport_msg>(*e.msg) &&
                   !std::holds_alternative<set_visibility_msg>(*e.msg)) {
          std::abort();  // only hello, input, teleport and set_visibility reach the game
        }
        break;
      case inbound_event::kind::disconnected:
        if (announced.erase(e.session) != 1) std::abort();
        break;
      case inbound_event::kind::frames_dropped:
        break;
    }
  }
  return 0;
}
