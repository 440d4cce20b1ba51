// Prometheus metrics over HTTP (Boost.Beast): a tiny server for GET /metrics and a builder for the
// text exposition format. The server serves the latest published snapshot, so a scrape never
// touches game state and the tick never waits for a scraper.
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>

namespace zone::net {

class viewer_server;  // net/viewer.h

/// Builds Prometheus text exposition format (version 0.0.4).
class prometheus_text {
 public:
  /// `labels` is either empty or like `phase="interest"` (already escaped).
  void counter(std::string_view name, std::string_view help, double value, std::string_view labels = {});
  void gauge(std::string_view name, std::string_view help, double value, std::string_view labels = {});
  /// A histogram: `upper_bounds` ascending (seconds or any unit), `cumulative` counts per bound
  /// (same length), plus the +Inf bucket = count. HELP/TYPE are written once per name.
  void histogram(std::string_view name, std::string_view help, std::span<const double> upper_bounds,
                 std::span<const std::uint64_t> cumulative, double sum, std::uint64_t count, std::string_view labels = {});
  [[nodiscard]] const std::string& str() const { return out_; }
  void clear() { out_.clear(); last_header_.clear(); }

 private:
  void header(std::string_view name, std::string_view help, std::string_view type);
  std::string out_;
  std::string last_header_;
};

/// What the metrics server allows itself: its own descriptors, apart from the game's.
struct metrics_limits {
  /// Connections open at once; one over it is closed as soon as it is accepted (counted).
  std::size_t max_connections = 16;
  /// A connection must have sent its request and taken the answer within this.
  std::chrono::milliseconds request_timeout{5000};
};

/// Serves GET /metrics with the latest published body on its own I/O thread (404 for other
/// paths, 405 for other methods; one request per connection). publish() is thread-safe.
/// Accept errors (out of descriptors) pause accepting 50 ms at a time and are logged at most
/// once a second, with the count since the last line.
class metrics_server {
 public:
  /// `port` 0 = an ephemeral port (see port()).
  metrics_server(std::string address, std::uint16_t port, metrics_limits limits = {});
  ~metrics_server();
  metrics_server(const metrics_server&) = delete;
  metrics_server& operator=(const metrics_server&) = delete;

  [[nodiscard]] std::optional<std::string> start();
  void stop();
  [[nodiscard]] std::uint16_t port() const;
  void publish(std::string body);
  [[nodiscard]] std::uint64_t requests() const;
  /// Connections closed at accept because max_connections were open.
  [[nodiscard]] std::uint64_t connections_refused() const;
  /// Failed accepts (each followed by a pause).
  [[nodiscard]] std::uint64_t accept_errors() const;
  /// Connections open now.
  [[nodiscard]] std::uint64_t connections_open() const;
  /// Hands the /viewer routes (net/viewer.h) to `viewer` (call before start(); it must outlive
  /// this server). Without one they answer 404 like any other path.
  void attach_viewer(viewer_server* viewer);

  struct impl;  ///< the Beast implementation (metrics.cpp)

 private:
  std::unique_ptr<impl> impl_;
};

}  // namespace zone::net
