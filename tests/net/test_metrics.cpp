// The Prometheus text builder and the /metrics HTTP server over loopback.
#include <doctest/doctest.h>

#include <random>
#include <string>

#include "loopback_client.h"
#include "net/metrics.h"

using namespace zone::net;
using zone::net::testing::http_get;
using zone::net::testing::http_request;

TEST_SUITE("net.metrics") {
  TEST_CASE("prometheus text: counters, gauges, labelled histograms") {
    prometheus_text t;
    t.counter("zone_frames_out_total", "Frames sent.", 42);
    t.gauge("zone_entities", "Live entities.", 7);
    const double bounds[] = {0.001, 0.01};
    const std::uint64_t cumulative[] = {3, 5};
    t.histogram("zone_tick_phase_seconds", "Tick phases.", bounds, cumulative, 0.02, 6, "phase=\"interest\"");
    t.histogram("zone_tick_phase_seconds", "Tick phases.", bounds, cumulative, 0.5, 9, "phase=\"total\"");
    const std::string& s = t.str();
    CHECK(s.find("# TYPE zone_frames_out_total counter\nzone_frames_out_total 42\n") != std::string::npos);
    CHECK(s.find("# TYPE zone_entities gauge\nzone_entities 7\n") != std::string::npos);
    CHECK(s.find("zone_tick_phase_seconds_bucket{phase=\"interest\",le=\"0.001\"} 3\n") != std::string::npos);
    CHECK(s.find("zone_tick_phase_seconds_bucket{phase=\"interest\",le=\"+Inf\"} 6\n") != std::string::npos);
    CHECK(s.find("zone_tick_phase_seconds_count{phase=\"total\"} 9\n") != std::string::npos);
    // HELP/TYPE once per metric name.
    std::size_t types = 0;
    for (std::size_t at = 0; (at = s.find("# TYPE zone_tick_phase_seconds ", at)) != std::string::npos; ++at) ++types;
    CHECK(types == 1);
  }

  TEST_CASE("GET /metrics serves the latest snapshot; other paths and methods are refused") {
    metrics_server m("127.0.0.1", 0);
    REQUIRE_FALSE(m.start().has_value());
    REQUIRE(m.port() != 0);
    const std::string first = "zone_entities 1\n";
    m.publish(first);
    auto r = http_get(m.port(), "/metrics");
    CHECK(r.starts_with("HTTP/1.1 200"));
    CHECK(r.find("text/plain; version=0.0.4") != std::string::npos);
    CHECK(r.ends_with("\r\n\r\n" + first));
    const std::string second = "zone_entities " + std::to_string(std::random_device{}()) + "\n";
    m.publish(second);
    CHECK(http_get(m.port(), "/metrics").ends_with(second));
    CHECK(http_get(m.port(), "/nope").starts_with("HTTP/1.1 404"));
    CHECK(http_request(m.port(), "POST /metrics HTTP/1.1\r\nHost: x\r\nContent-Length: 0\r\n\r\n").starts_with("HTTP/1.1 405"));
    // Garbage does not take the server down.
    (void)http_request(m.port(), "\x01\x02 garbage\r\n\r\n");
    CHECK(http_get(m.port(), "/metrics").ends_with(second));
    CHECK(m.requests() >= 5);
    m.stop();
    m.stop();
  }
}
