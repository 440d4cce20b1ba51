// The client connector (Boost.Asio) that bots use: many connections in one process share a
// client_pool's I/O threads; each connection says hello, keeps a verified client_view from the
// tick updates it receives, sends inputs and pings, and measures round trips. No Asio types here.
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>

#include "protocol.h"

namespace zone::net {

/// The I/O threads shared by many client connections. Destroy every connection before its pool.
class client_pool {
 public:
  explicit client_pool(unsigned io_threads = 1);
  ~client_pool();
  client_pool(const client_pool&) = delete;
  client_pool& operator=(const client_pool&) = delete;

  struct impl;  ///< the Asio implementation (client.cpp)
  [[nodiscard]] impl& get() { return *impl_; }

 private:
  std::unique_ptr<impl> impl_;
};

struct client_options {
  std::string address = "127.0.0.1";  ///< an IP address (no name lookup)
  std::uint16_t port = 7777;
  std::string name = "bot";
  std::string token;
  /// Inbound limit: tick updates can be large.
  decoder_options inbound = [] {
    decoder_options o;
    o.max_frame_bytes = 1 << 20;
    return o;
  }();
  std::size_t max_queued_frames = 64;  ///< outbound; the oldest input is dropped beyond it
};

/// What a connection knows, as a consistent copy (thread-safe to take at any time).
struct client_snapshot {
  enum class state : std::uint8_t { connecting, connected, welcomed, closed };
  state phase = state::connecting;
  std::uint32_t entity_id = 0;
  world_bounds world{};
  std::uint16_t tick_rate_hz = 0;
  std::uint64_t updates = 0;          ///< tick updates applied
  std::uint64_t digests_checked = 0;  ///< verify digests compared
  std::uint64_t problems = 0;         ///< inconsistent updates or digest mismatches
  std::uint64_t resets = 0;           ///< updates that reset the view
  std::size_t visible = 0;            ///< entities in the view
  std::uint64_t last_tick = 0;
  std::uint32_t last_input_echo = 0;  ///< last_input_sequence of the latest update
  std::uint32_t inputs_sent = 0;
  std::uint64_t pongs = 0;
  double last_rtt_ms = 0;             ///< round trip of the latest pong
  std::uint64_t bytes_in = 0;
  std::optional<error_msg> error;     ///< the server's error before it closed, if any
  std::string close_reason;
};

/// One connection to a zone server. All calls are thread-safe and never block on the network.
class client_connection {
 public:
  client_connection(client_pool& pool, client_options opt);
  ~client_connection();  ///< closes
  client_connection(const client_connection&) = delete;
  client_connection& operator=(const client_connection&) = delete;

  /// Connects and sends hello. Inputs and pings sent before the connection is up wait for it
  /// and go out after the hello.
  void connect();
  /// Sends a movement intent with the next sequence number.
  void send_input(const vec3f& move);
  /// Sends a ping stamped with the local steady clock; the pong gives the round trip.
  void send_ping();
  /// Sends raw bytes (tests of hostile clients).
  void send_raw(std::vector<std::uint8_t> bytes);
  void close();

  [[nodiscard]] client_snapshot snapshot() const;

  struct impl;  ///< the Asio implementation (client.cpp)

 private:
  std::shared_ptr<impl> impl_;
};

}  // namespace zone::net
