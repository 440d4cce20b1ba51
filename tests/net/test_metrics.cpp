// The Prometheus text builder and the /metrics HTTP server over loopback.
#include <doctest/doctest.h>

#include <sys/resource.h>

#include <random>
#include <sstream>
#include <string>
#include <thread>

#include <spdlog/sinks/ostream_sink.h>
#include <spdlog/spdlog.h>

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

  TEST_CASE("its own connection cap: idle connections beyond it are closed at once, the held ones time out") {
    metrics_limits limits;
    limits.max_connections = 4;
    // Longer than accepting the 200 connections takes on a busy machine: the 4 held ones are
    // still held when the last is refused.
    limits.request_timeout = std::chrono::milliseconds(2000);
    metrics_server m("127.0.0.1", 0, limits);
    REQUIRE_FALSE(m.start().has_value());
    m.publish("zone_entities 3\n");
    std::vector<std::unique_ptr<zone::net::testing::test_client>> idle;
    for (int i = 0; i < 200; ++i) idle.push_back(std::make_unique<zone::net::testing::test_client>(m.port()));
    const auto wait_until = [](auto pred, std::chrono::milliseconds timeout) {
      const auto deadline = std::chrono::steady_clock::now() + timeout;
      while (!pred() && std::chrono::steady_clock::now() < deadline) std::this_thread::sleep_for(std::chrono::milliseconds(5));
      return pred();
    };
    (void)wait_until([&] { return m.connections_refused() >= 196; }, std::chrono::milliseconds(10000));
    CHECK(m.connections_refused() == 196);
    CHECK(m.connections_open() == 4);
    // Every idle connection is closed: 196 at once, 4 at the request timeout (the server counts
    // a connection closed a moment after its client sees the close).
    std::size_t closed = 0;
    for (auto& c : idle) closed += c->wait_closed(std::chrono::milliseconds(10000)) ? 1 : 0;
    CHECK(closed == 200);
    CHECK(wait_until([&] { return m.connections_open() == 0; }, std::chrono::milliseconds(5000)));
    CHECK(http_get(m.port(), "/metrics").ends_with("zone_entities 3\n"));
  }

  TEST_CASE("out of descriptors: accepting pauses and the log gets at most a line a second, then it serves again") {
    std::ostringstream log;
    auto logger = std::make_shared<spdlog::logger>("capture", std::make_shared<spdlog::sinks::ostream_sink_mt>(log));
    const auto previous = spdlog::default_logger();
    spdlog::set_default_logger(logger);
    metrics_limits limits;
    limits.request_timeout = std::chrono::milliseconds(500);
    metrics_server m("127.0.0.1", 0, limits);
    REQUIRE_FALSE(m.start().has_value());
    m.publish("zone_entities 5\n");
    // The client's socket first (a descriptor); then the process's table is made full, and only
    // then does the client connect (which takes no descriptor), so every accept of it fails until
    // the limit is back. (Connecting before lowering the limit raced with the server's I/O thread:
    // a loaded host could run its accept first, and the test saw no accept error at all.)
    rlimit before{};
    REQUIRE(::getrlimit(RLIMIT_NOFILE, &before) == 0);
    const int pending = ::socket(AF_INET, SOCK_STREAM, 0);
    REQUIRE(pending >= 0);
    sockaddr_in to{};
    to.sin_family = AF_INET;
    to.sin_port = htons(m.port());
    to.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    rlimit low = before;
    low.rlim_cur = 3;  // stdin, stdout, stderr: every other descriptor in use is already beyond it
    const auto t_low = std::chrono::steady_clock::now();
    REQUIRE(::setrlimit(RLIMIT_NOFILE, &low) == 0);
    const int connected = ::connect(pending, reinterpret_cast<sockaddr*>(&to), sizeof to);  // waits in the backlog
    std::this_thread::sleep_for(std::chrono::milliseconds(1500));
    REQUIRE(::setrlimit(RLIMIT_NOFILE, &before) == 0);
    REQUIRE(connected == 0);
    // How long it really lasted (a busy machine wakes this thread late).
    const double low_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t_low).count();
    const auto errors = m.accept_errors();
    const std::string text = log.str();
    // Served once descriptors are back: accepted, then closed at the request timeout (it sent no request).
    bool closed = false;
    for (const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(10); !closed && std::chrono::steady_clock::now() < until;) {
      pollfd p{pending, POLLIN, 0};
      if (::poll(&p, 1, 100) <= 0) continue;
      char buf[256];
      closed = ::recv(pending, buf, sizeof buf, 0) <= 0;
    }
    ::close(pending);
    CHECK(closed);
    CHECK(http_get(m.port(), "/metrics").ends_with("zone_entities 5\n"));
    spdlog::set_default_logger(previous);
    MESSAGE("accept errors in " << low_s << " s: " << errors << "; log: " << text.size() << " bytes");
    CHECK(errors >= 2);
    CHECK(errors <= low_s * 20 + 10);  // 50 ms pauses (1.5 s: at most 40), not a spin
    std::size_t lines = 0;
    for (const char ch : text) lines += ch == '\n' ? 1 : 0;
    CHECK(lines >= 1);
    CHECK(lines <= low_s + 1.5);  // a line a second at most (1.5 s: 3 lines)
    CHECK(text.size() < 400 * (low_s + 1.5));  // short lines (1.5 s: 1,200 bytes)
  }
}
