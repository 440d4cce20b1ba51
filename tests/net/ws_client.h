// A blocking WebSocket client for the viewer's tests (net/viewer.h), with a read timeout.
// Shared by the net and zone test suites.
#pragma once

#include <utility>  // before Asio: GCC 12 in C++20 mode needs it first

#include <boost/asio.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/websocket.hpp>
#include <sys/socket.h>

#include <chrono>
#include <cstring>
#include <optional>
#include <thread>
#include <vector>

#include "net/viewer.h"

namespace zone::net::testing {

namespace asio = boost::asio;
namespace beast = boost::beast;
namespace websocket = beast::websocket;
using tcp = asio::ip::tcp;

inline std::vector<std::uint8_t> request_bytes(const viewer_request& r, std::uint8_t type = viewer_request_type) {
  std::vector<std::uint8_t> b(viewer_request_bytes, 0);
  b[0] = type;
  std::memcpy(&b[4], &r.x0, 4);
  std::memcpy(&b[8], &r.y0, 4);
  std::memcpy(&b[12], &r.x1, 4);
  std::memcpy(&b[16], &r.y1, 4);
  std::memcpy(&b[20], &r.selected, 4);
  std::memcpy(&b[24], &r.max_points, 4);
  return b;
}

template <class T>
T at(const std::vector<std::uint8_t>& b, std::size_t o) {
  T v;
  std::memcpy(&v, b.data() + o, sizeof v);
  return v;
}

template <class F>
bool eventually(F f, std::chrono::milliseconds limit = std::chrono::milliseconds(5000)) {
  const auto end = std::chrono::steady_clock::now() + limit;
  while (std::chrono::steady_clock::now() < end) {
    if (f()) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return f();
}

/// A blocking WebSocket client with a receive timeout.
struct ws_client {
  asio::io_context ctx;
  websocket::stream<tcp::socket> ws{ctx};
  beast::error_code error;

  explicit ws_client(std::uint16_t port, int rcvbuf = 0) {
    ws.next_layer().connect({asio::ip::make_address("127.0.0.1"), port});
    if (rcvbuf > 0) ::setsockopt(ws.next_layer().native_handle(), SOL_SOCKET, SO_RCVBUF, &rcvbuf, sizeof rcvbuf);
    ws.handshake("127.0.0.1", "/viewer/ws", error);
  }
  bool send(const std::vector<std::uint8_t>& b, bool binary = true) {
    ws.binary(binary);
    ws.write(asio::buffer(b), error);
    return !error;
  }
  /// The next message (text or binary), or nothing on error or after 3 s (error = timed_out).
  std::optional<std::pair<bool, std::vector<std::uint8_t>>> read() {
    beast::flat_buffer buf;
    bool done = false;
    ws.async_read(buf, [&](beast::error_code ec, std::size_t) {
      error = ec;
      done = true;
    });
    ctx.restart();
    ctx.run_for(std::chrono::seconds(3));
    if (!done) {
      beast::error_code ignored;
      ws.next_layer().cancel(ignored);
      ctx.restart();
      ctx.run();
      error = asio::error::timed_out;
      return std::nullopt;
    }
    if (error) return std::nullopt;
    const auto d = buf.cdata();
    const auto* p = static_cast<const std::uint8_t*>(d.data());
    return std::pair{ws.got_text(), std::vector<std::uint8_t>(p, p + d.size())};
  }
  /// Reads until a binary frame of `type` (skipping stats), at most `limit` messages.
  std::optional<std::vector<std::uint8_t>> read_frame(std::uint8_t type, int limit = 20) {
    for (int k = 0; k < limit; ++k) {
      auto m = read();
      if (!m) return std::nullopt;
      if (!m->first && !m->second.empty() && m->second[0] == type) return m->second;
    }
    return std::nullopt;
  }
  /// True once the server has closed the connection (a read fails other than by timeout).
  bool closed_by_server(int tries = 20) {
    for (int k = 0; k < tries; ++k) {
      if (!read()) return error != asio::error::timed_out;
    }
    return false;
  }
};


}  // namespace zone::net::testing
