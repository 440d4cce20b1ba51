// Prometheus metrics over HTTP (Boost.Beast): a tiny server for GET /metrics and a builder for the
// text exposition format. The server serves the latest published snapshot, so a scrape never
// touches game state and the tick never waits for a scraper.
#pragma once

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

/// Serves GET /metrics with the latest published body on its own I/O thread (404 for other
/// paths, 405 for other methods; one request per connection). publish() is thread-safe.
class metrics_server {
 public:
  /// `port` 0 = an ephemeral port (see port()).
  metrics_server(std::string address, std::uint16_t port);
  ~metrics_server();
  metrics_server(const metrics_server&) = delete;
  metrics_server& operator=(const metrics_server&) = delete;

  [[nodiscard]] std::optional<std::string> start();
  void stop();
  [[nodiscard]] std::uint16_t port() const;
  void publish(std::string body);
  [[nodiscard]] std::uint64_t requests() const;
  /// Hands the /viewer routes (net/viewer.h) to `viewer` (call before start(); it must outlive
  /// this server). Without one they answer 404 like any other path.
  void attach_viewer(viewer_server* viewer);

  struct impl;  ///< the Beast implementation (metrics.cpp)

 private:
  std::unique_ptr<impl> impl_;
};

}  // namespace zone::net
