// End-to-end tests of the zone server with the bot swarm: both real executables on loopback
// (ephemeral ports read back from the server's log), every child killed on any exit path.
// Bounds and scenarios are documented in docs/bots.md.
#include <doctest/doctest.h>

#include <regex>

#include <netinet/tcp.h>
#include <poll.h>

#include <atomic>
#include <cerrno>
#include <cstring>
#include <initializer_list>
#include <optional>
#include <random>
#include <set>
#include <sstream>

#include "bots/swarm.h"
#include "net/protocol.h"
#include "../common/process.h"

using namespace zone::test;

namespace {

// The server every test runs: CPU grid finder, 2,000 NPCs, 20 Hz (a tick period of 50 ms); four towns, so
// the bots (who spawn at towns) form four crowds of ~50 rather than one of 200.
const std::vector<std::string> server_args = {"--npcs", "2000", "--towns", "4", "--threads", "2", "--tick-rate", "20",
                                              "--io-threads", "2"};
// Documented bound on the server's p99 tick for these tests (docs/bots.md): one tick period.
constexpr double p99_tick_bound_ms = 50;
// A machine too busy to judge timing on (tests/common/process.h, cpu_stretch): the server's tick
// thread waited for a CPU 3 times as long as it ran, on average (1-3 where the machine has
// capacity).
constexpr double busy_stretch = 4;

/// server_args, then `extra`.
std::vector<std::string> server_args_with(std::initializer_list<std::string> extra) {
  std::vector<std::string> a = server_args;
  a.insert(a.end(), extra);
  return a;
}

/// How the machine treated the server during a run. The rates these tests bound (frames, digests
/// and checks, inputs: they follow the server's ticks) and its tick time hold where the server
/// gets the CPU it asks for (CI's 2-core machine running two tests at once). How long its tick
/// thread waited for a CPU when it could run tells (tests/common/process.h, cpu_stretch: 1-3
/// where the machine has capacity, 20 and more beside 8 busy loops on 2 cores). On a machine that
/// busy, tick-time bounds are reported but not judged, and the rates must reach half their bounds.
struct machine_judgement {
  double stretch = 1;
  bool busy = false;
  double rate = 1;  ///< the share of the rate bounds a run must reach
};
machine_judgement judge_machine(const zone_server_process& server) {
  machine_judgement j;
  j.stretch = cpu_stretch(sched_times_of(server.proc.pid()));
  j.busy = j.stretch >= busy_stretch;
  j.rate = j.busy ? 0.5 : 1;
  MESSAGE("CPU stretch of the server's tick thread (runnable time / CPU time): " << j.stretch
          << std::string(j.busy ? " (a busy machine: rate bounds halved, tick bounds not judged)" : ""));
  return j;
}

std::vector<std::string> swarm_args(std::uint16_t port, const std::string& dir, std::vector<std::string> extra) {
  std::vector<std::string> a{BOT_SWARM_EXE, "--port", std::to_string(port), "--threads", "2", "--report-json", dir + "/report.json"};
  a.insert(a.end(), extra.begin(), extra.end());
  return a;
}

/// How a bot-swarm run ended: its exit code (none when it outlived the limit and was killed), its
/// JSON report and its output.
struct swarm_end {
  std::optional<int> rc;
  std::string report, log;
};

/// Waits (at most `limit`) for `swarm`, started with swarm_args(.., dir, ..), to end.
swarm_end finish(child_process& swarm, const std::string& dir, std::chrono::milliseconds limit) {
  swarm_end e;
  e.rc = swarm.wait(limit);
  e.report = read_file(dir + "/report.json");
  e.log = swarm.log();
  return e;
}

/// bot-swarm against the server on `port` with `extra` arguments, run to its end (at most 60 s:
/// REQUIREs that it ended).
swarm_end run_swarm(std::uint16_t port, const std::string& dir, std::vector<std::string> extra) {
  child_process swarm(swarm_args(port, dir, std::move(extra)), dir + "/bot-swarm.log");
  swarm_end e = finish(swarm, dir, 60000ms);
  REQUIRE_MESSAGE(e.rc.has_value(), "bot-swarm did not end within 60 s; its output:\n" << e.log);
  return e;
}

/// A raw loopback client for hostile behaviour (plain POSIX sockets).
struct raw_client {
  int fd = -1;
  explicit raw_client(std::uint16_t port, int rcvbuf = 0) {
    fd = ::socket(AF_INET, SOCK_STREAM, 0);
    if (rcvbuf > 0) ::setsockopt(fd, SOL_SOCKET, SO_RCVBUF, &rcvbuf, sizeof rcvbuf);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(port);
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    if (::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
      ::close(fd);
      fd = -1;
    }
  }
  ~raw_client() {
    if (fd >= 0) ::close(fd);
  }
  bool send_bytes(const std::vector<std::uint8_t>& b) {
    std::size_t at = 0;
    while (at < b.size()) {
      const ssize_t n = ::send(fd, b.data() + at, b.size() - at, MSG_NOSIGNAL | MSG_DONTWAIT);
      if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
        pollfd p{fd, POLLOUT, 0};
        ::poll(&p, 1, 100);
        continue;
      }
      if (n <= 0) return false;
      at += static_cast<std::size_t>(n);
    }
    return true;
  }
  /// Reads (and discards) what is there for up to `ms`; false once the server closed the connection.
  bool drain(int ms, std::size_t* bytes = nullptr) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(ms);
    while (std::chrono::steady_clock::now() < deadline) {
      pollfd p{fd, POLLIN, 0};
      if (::poll(&p, 1, 20) <= 0) continue;
      char buf[65536];
      const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
      if (n <= 0) return false;
      if (bytes) *bytes += static_cast<std::size_t>(n);
    }
    return true;
  }
  /// True when the server closes the connection within `ms` (reading everything meanwhile).
  bool closed_within(int ms) { return !drain(ms); }
};

/// A loopback client that checks every frame it reads (net::client_view: consistency and the
/// digest) and can stop reading, or read slowly, to be a slow client of the zone server.
struct verifying_client {
  raw_client sock;
  zone::net::frame_decoder decoder{[] {
    zone::net::decoder_options o;
    o.max_frame_bytes = 1 << 22;
    o.max_tables = 1u << 22;
    return o;
  }()};
  std::optional<zone::net::client_view> view;
  std::uint64_t frames = 0, resets = 0, inconsistent = 0, digest_mismatches = 0, digests = 0, bytes = 0;
  bool closed = false, bad_stream = false;

  explicit verifying_client(std::uint16_t port, const std::string& name) : sock(port, 4096) {
    sock.send_bytes(zone::net::encode_frame(zone::net::hello_msg{name, "", zone::net::protocol_version}));
  }
  /// Reads for `ms`, at most `max_bytes` every 20 ms (0: as fast as it comes), applying every frame;
  /// pings every second.
  void read_for(int ms, std::size_t max_bytes = 0) {
    const auto start = std::chrono::steady_clock::now();
    const auto deadline = start + std::chrono::milliseconds(ms);
    auto next_ping = start;
    while (!closed && !bad_stream && std::chrono::steady_clock::now() < deadline) {
      if (std::chrono::steady_clock::now() >= next_ping) {
        sock.send_bytes(zone::net::encode_frame(zone::net::ping_msg{0}));
        next_ping += 1000ms;
      }
      pollfd p{sock.fd, POLLIN, 0};
      if (::poll(&p, 1, 20) <= 0) continue;
      const auto buf = decoder.prepare(max_bytes ? max_bytes : 65536);
      const ssize_t n = ::recv(sock.fd, buf.data(), buf.size(), 0);
      if (n <= 0) {
        closed = true;
        break;
      }
      decoder.commit(static_cast<std::size_t>(n));
      bytes += static_cast<std::size_t>(n);
      for (auto step = decoder.next(); step.is_frame(); step = decoder.next()) apply(step.frame);
      bad_stream = decoder.failed();
      if (max_bytes) std::this_thread::sleep_for(20ms);
    }
  }
  /// Stops reading for `ms`, pinging every second so as not to be idle.
  void stall(int ms) {
    for (int t = 0; t < ms; t += 1000) {
      std::this_thread::sleep_for(std::chrono::milliseconds(std::min(1000, ms - t)));
      sock.send_bytes(zone::net::encode_frame(zone::net::ping_msg{static_cast<std::uint64_t>(t)}));
    }
  }
  void apply(const zone::net::frame_view& f) {
    if (f.type == zone::net::wire::message::welcome) {
      const auto* w = f.envelope->message_as_welcome();
      view.emplace(zone::net::world_bounds{{w->world()->lo().x(), w->world()->lo().y(), w->world()->lo().z()},
                                           {w->world()->hi().x(), w->world()->hi().y(), w->world()->hi().z()}});
      return;
    }
    if (f.type != zone::net::wire::message::tick_update) return;
    const auto* u = f.envelope->message_as_tick_update();
    if (!view) {
      ++inconsistent;  // a tick update before the welcome
      return;
    }
    if (u->reset() && frames > 0) ++resets;
    ++frames;
    digests += u->digest() ? 1 : 0;
    switch (view->apply(*u)) {
      case zone::net::client_view::status::ok: break;
      case zone::net::client_view::status::inconsistent: ++inconsistent; break;
      case zone::net::client_view::status::digest_mismatch: ++digest_mismatches; break;
    }
  }
};

/// A scripted zone for the swarm's read path (plain sockets on loopback, driven by the test): it
/// accepts connections, writes frames, closes its side when the script says so, and notes what
/// each client sent and when the client closed.
struct scripted_zone {
  struct peer {
    int fd = -1;
    zone::net::frame_decoder decoder{zone::net::decoder_options{}};
    std::vector<zone::net::message> got;
    std::optional<std::chrono::steady_clock::time_point> closed_at;  ///< the client's end of stream
  };
  int listen_fd = -1;
  std::uint16_t port = 0;
  std::vector<std::unique_ptr<peer>> peers;

  scripted_zone() {
    listen_fd = ::socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    socklen_t len = sizeof addr;
    if (::bind(listen_fd, reinterpret_cast<sockaddr*>(&addr), len) == 0 && ::listen(listen_fd, 512) == 0 &&
        ::getsockname(listen_fd, reinterpret_cast<sockaddr*>(&addr), &len) == 0) {
      port = ntohs(addr.sin_port);
    }
  }
  ~scripted_zone() {
    for (auto& p : peers) ::close(p->fd);
    ::close(listen_fd);
  }
  /// Accepts until `n` clients are in (at most `ms`).
  void accept_n(std::size_t n, int ms) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(ms);
    while (peers.size() < n && std::chrono::steady_clock::now() < deadline) {
      pollfd p{listen_fd, POLLIN, 0};
      if (::poll(&p, 1, 20) <= 0) continue;
      const int fd = ::accept(listen_fd, nullptr, nullptr);
      if (fd < 0) continue;
      peers.push_back(std::make_unique<peer>());
      peers.back()->fd = fd;
    }
  }
  static void send_all(int fd, const std::vector<zone::net::message>& frames) {
    std::vector<std::uint8_t> bytes;
    for (const auto& m : frames) {
      const auto f = zone::net::encode_frame(m);
      bytes.insert(bytes.end(), f.begin(), f.end());
    }
    for (std::size_t at = 0; at < bytes.size();) {
      const ssize_t n = ::send(fd, bytes.data() + at, bytes.size() - at, MSG_NOSIGNAL);
      if (n <= 0) return;
      at += static_cast<std::size_t>(n);
    }
  }
  /// Reads every client (decoding what it sent) until each has closed or `ms` passed.
  void read_until_closed(int ms) {
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(ms);
    while (std::chrono::steady_clock::now() < deadline) {
      std::vector<pollfd> fds;
      std::vector<peer*> open;
      for (auto& p : peers) {
        if (p->closed_at) continue;
        fds.push_back({p->fd, POLLIN, 0});
        open.push_back(p.get());
      }
      if (fds.empty()) return;
      if (::poll(fds.data(), fds.size(), 20) <= 0) continue;
      for (std::size_t i = 0; i < fds.size(); ++i) {
        if (fds[i].revents == 0) continue;
        peer& p = *open[i];
        const auto buf = p.decoder.prepare(65536);
        const ssize_t n = ::recv(p.fd, buf.data(), buf.size(), MSG_DONTWAIT);
        if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) continue;
        if (n <= 0) {
          p.closed_at = std::chrono::steady_clock::now();
          continue;
        }
        p.decoder.commit(static_cast<std::size_t>(n));
        for (auto step = p.decoder.next(); step.is_frame(); step = p.decoder.next()) {
          if (auto m = zone::net::to_message(*step.frame.envelope)) p.got.push_back(std::move(*m));
        }
      }
    }
  }
};

/// A welcome of the scripted zone, and empty tick updates from `from` on.
std::vector<zone::net::message> welcome_and_ticks(std::uint32_t entity, std::uint64_t from, int ticks) {
  std::vector<zone::net::message> m;
  zone::net::welcome_msg w;
  w.entity_id = entity;
  w.world = {{0, 0, 0}, {1000, 1000, 100}};
  w.tick_rate_hz = 20;
  w.server_tick = from;
  m.emplace_back(w);
  for (int t = 0; t < ticks; ++t) {
    zone::net::tick_update_msg u;
    u.server_tick = from + 1 + static_cast<std::uint64_t>(t);
    m.emplace_back(u);
  }
  return m;
}

/// Swarm options for the scripted zones: every bot launched at once, two threads.
zone::bots::swarm_options scripted_swarm(std::uint16_t port, unsigned bots, double duration_s) {
  zone::bots::swarm_options o;
  o.port = port;
  o.bots = bots;
  o.duration_s = duration_s;
  o.ramp = 5000;
  o.threads = 2;
  o.verify = true;
  return o;
}

}  // namespace

TEST_SUITE("bots") {

TEST_CASE("latency histogram percentiles") {
  zone::bots::latency_histogram_us h;
  for (int i = 1; i <= 1000; ++i) h.record(static_cast<std::uint64_t>(i) * 10);  // 10 us .. 10 ms
  const auto c = h.snapshot();
  CHECK(zone::bots::latency_histogram_us::total(c) == 1000);
  CHECK(zone::bots::percentile_ms(c, 0.5) == doctest::Approx(5.0).epsilon(0.05));
  CHECK(zone::bots::percentile_ms(c, 0.99) == doctest::Approx(9.9).epsilon(0.05));
  CHECK(h.max() / 1000.0 == doctest::Approx(10.0));
}

TEST_CASE("end to end: 200 bots in verify mode and checked by the oracle, zero mismatches, p99 tick bounded") {
  const std::string dir = temp_dir();
  zone_server_process server(ZONE_SERVER_EXE, dir, server_args_with({"--oracle"}));
  REQUIRE_MESSAGE(server.port != 0, server.proc.log());
  const swarm_end run = run_swarm(server.port, dir, {"--bots", "200", "--duration", "15", "--ramp", "100", "--input-hz", "10", "--verify",
                                                     "--oracle", "--mix", "walk=0.4,patrol=0.2,follow=0.2,crowd=0.2", "--stealth-bots",
                                                     "0.1", "--team-bots", "0.2", "--visibility-switch-hz", "0.5", "--report-csv",
                                                     dir + "/report.csv"});
  const auto [stretch, busy, rate] = judge_machine(server);
  const std::string& report = run.report;
  INFO("bot-swarm output:\n" << run.log);
  INFO("CPU stretch " << stretch);
  CHECK(run.rc == 0);
  CHECK(json_number(report, "bots_connected").value_or(-1) == 200);
  CHECK(json_number(report, "connect_failures").value_or(-1) == 0);
  CHECK(json_number(report, "unexpected_disconnects").value_or(-1) == 0);
  CHECK(json_number(report, "mismatches").value_or(-1) == 0);
  CHECK(json_number(report, "digests_checked").value_or(0) > 200 * 20 * 5 * rate);
  CHECK(json_number(report, "aoi_checked").value_or(0) > 0);
  CHECK(json_number(report, "samples").value_or(0) > 0);
  // The oracle checked (nearly) every frame of every bot against the ground truth: not one
  // mismatch of any kind, and the stream ran to the end.
  CHECK(report.find("\"rules_from_server\": true") != std::string::npos);
  CHECK(report.find("\"stream_error\": \"\"") != std::string::npos);
  CHECK(json_number(report, "oracle_mismatches").value_or(-1) == 0);
  // Stealth and team bots joined and switched during the run (each switch of a team bot resyncs
  // its teammates nearby): the oracle judged every class from the tick it took effect.
  CHECK(json_number(report, "stealth_joins").value_or(0) > 5);
  CHECK(json_number(report, "team_joins").value_or(0) > 15);
  CHECK(json_number(report, "visibility_switches_sent").value_or(0) > 100);
  // The truth stream carried the switches as changes to the layout (net/truth.h), not whole
  // layouts, and the oracle above judged every frame from them.
  CHECK(json_number(report, "truth_changes").value_or(0) > 30);
  const double checked = json_number(report, "frames_checked").value_or(0);
  CHECK(checked > 200 * 20 * 5 * rate);
  CHECK(json_number(report, "frames_unchecked").value_or(1e9) <= checked / 100);
  CHECK(json_number(report, "entities_checked").value_or(0) > checked * 5);
  CHECK(json_number(report, "positions_checked").value_or(0) > checked * 5);
  // The steady state: 200 bots at 100 a second are all connected after ~2 s (sampled once a
  // second), and its latency samples are part of the whole run's.
  const auto steady_at = report.find("\"latency_steady_ms\"");
  REQUIRE(steady_at != std::string::npos);
  const std::string steady = report.substr(steady_at);
  const double from_s = json_number(steady, "from_s").value_or(-1);
  CHECK(from_s >= 1);
  CHECK(from_s <= (busy ? 12 : 6));
  const double steady_samples = json_number(steady, "samples").value_or(0);
  CHECK(steady_samples > 200 * 20 * 5 * rate);
  CHECK(steady_samples < json_number(report, "samples").value_or(0));
  CHECK(json_number(steady, "p99").value_or(0) > 0);
  // --inputs changes (the default): the intent is evaluated at 10 Hz (>= 10 s of play per bot),
  // and sent only when it changed or as the 1 s keep-alive. Walk and patrol bots (60 %) change
  // every 3-4 s, follow and crowd bots (40 %) steer all the time: measured 43 % of evaluations sent.
  const double sent = json_number(report, "inputs_sent").value_or(0);
  const double unchanged = json_number(report, "inputs_unchanged").value_or(0);
  MESSAGE("inputs sent " << sent << ", unchanged intents not sent " << unchanged);
  CHECK(sent + unchanged >= 200 * 10 * 10 * rate);  // (evaluated as frames come: at most one per frame)
  CHECK(sent >= 200 * 10);  // at least the keep-alives
  CHECK(sent < 0.75 * (sent + unchanged));
  CHECK(server.proc.alive());
  REQUIRE(server.proc.terminate().value_or(-1) == 0);
  const auto p99 = server.p99_tick_ms();
  INFO("zone-server log tail:\n" << server.proc.log().substr(server.proc.log().size() > 2000 ? server.proc.log().size() - 2000 : 0));
  REQUIRE(p99.has_value());
  MESSAGE("server p99 tick " << *p99 << " ms; bot latency p99 " << json_number(report, "p99").value_or(-1) << " ms");
  if (busy) {
    MESSAGE("NOT JUDGED: the server's tick thread waited for a CPU (stretch " << stretch << "); p99 tick " << *p99 << " ms");
  } else {
    CHECK(*p99 <= p99_tick_bound_ms);
  }
}

namespace {

/// The p-quantile of one column of zone-server's --tick-csv, over the ticks from `from_s` seconds on.
std::optional<double> tick_csv_quantile(const std::string& path, const std::string& column, double from_s, double q) {
  std::istringstream in(read_file(path));
  std::string line;
  if (!std::getline(in, line)) return std::nullopt;
  std::vector<std::string> header;
  {
    std::istringstream h(line);
    for (std::string f; std::getline(h, f, ',');) header.push_back(f);
  }
  const auto col = std::find(header.begin(), header.end(), column) - header.begin();
  const auto t_col = std::find(header.begin(), header.end(), "t_s") - header.begin();
  if (col == static_cast<std::ptrdiff_t>(header.size()) || t_col == static_cast<std::ptrdiff_t>(header.size())) return std::nullopt;
  std::vector<double> v;
  while (std::getline(in, line)) {
    std::vector<std::string> f;
    std::istringstream l(line);
    for (std::string x; std::getline(l, x, ',');) f.push_back(x);
    if (f.size() != header.size() || std::stod(f[static_cast<std::size_t>(t_col)]) < from_s) continue;
    v.push_back(std::stod(f[static_cast<std::size_t>(col)]));
  }
  if (v.empty()) return std::nullopt;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, static_cast<std::size_t>(q * static_cast<double>(v.size())))];
}

}  // namespace

// Bounds of the timing test (docs/bots.md): about 1.5 x the figures measured on the 2-core
// machine, so that a 2x regression fails it (run alone: RUN_SERIAL).
constexpr double timing_tick_p99_bound_ms = TIMING_TICK_P99_BOUND_MS;
constexpr double timing_latency_p99_bound_ms = TIMING_LATENCY_P99_BOUND_MS;

namespace {

struct timing_figures {
  double tick_p99 = -1, latency_p99 = -1;
};

/// One timing run: 200 bots on 2,000 NPCs at 20 Hz for 15 s; the steady state's tick p99 (from
/// --tick-csv) and update latency p99 (the swarm's report).
timing_figures timing_run() {
  const std::string dir = temp_dir();
  zone_server_process server(ZONE_SERVER_EXE, dir, server_args_with({"--tick-csv", dir + "/ticks.csv"}));
  REQUIRE_MESSAGE(server.port != 0, server.proc.log());
  const swarm_end run = run_swarm(server.port, dir, {"--bots", "200", "--duration", "15", "--ramp", "100", "--mix",
                                                     "walk=0.4,patrol=0.2,follow=0.2,crowd=0.2"});
  const std::string& report = run.report;
  INFO("bot-swarm output:\n" << run.log);
  CHECK(run.rc == 0);
  REQUIRE(server.proc.terminate().value_or(-1) == 0);
  const auto steady_at = report.find("\"latency_steady_ms\"");
  REQUIRE(steady_at != std::string::npos);
  const double from_s = json_number(report.substr(steady_at), "from_s").value_or(-1);
  REQUIRE(from_s >= 0);
  timing_figures f;
  f.latency_p99 = json_number(report.substr(steady_at), "p99").value_or(-1);
  // The server's ticks over the same steady window (its clock starts a moment before the swarm's).
  const auto tick_p99 = tick_csv_quantile(dir + "/ticks.csv", "tick_ms", from_s + 1, 0.99);
  REQUIRE(tick_p99.has_value());
  f.tick_p99 = *tick_p99;
  return f;
}

}  // namespace

namespace {

/// The 1-minute load average (/proc/loadavg), or a negative number when unknown.
double load_average() {
  std::istringstream in(read_file("/proc/loadavg"));
  double load = -1;
  in >> load;
  return load;
}

}  // namespace

TEST_CASE("timing: 200 bots on 2,000 NPCs at 20 Hz; tick p99 and update latency p99 in the steady state within bounds") {
  // Timing is judged on a machine that is not busy with other work: wait (up to 90 s) for the
  // 1-minute load average to fall below the core count + 1 (CI's fresh machine, once the tests
  // before this one have ended); on a machine that stays busier (a shared developer host) the
  // figures are reported but not judged.
  const double cores = std::max(1u, std::thread::hardware_concurrency());
  double load = load_average();
  for (int waited = 0; waited < 90 && load >= cores + 1; ++waited) {
    std::this_thread::sleep_for(1s);
    load = load_average();
  }
  const bool judged = load >= 0 && load < cores + 1;
  // The best of up to three runs: a 2x regression makes every run slow, while a neighbour's
  // burst of CPU seldom spoils three in a row.
  timing_figures best{1e9, 1e9};
  for (int attempt = 1; attempt <= 3; ++attempt) {
    const timing_figures f = timing_run();
    MESSAGE("run " << attempt << ": tick p99 " << f.tick_p99 << " ms (bound " << timing_tick_p99_bound_ms
                   << "), update latency p99 " << f.latency_p99 << " ms (bound " << timing_latency_p99_bound_ms << ")");
    REQUIRE(f.latency_p99 > 0);
    REQUIRE(f.tick_p99 > 0);
    best.tick_p99 = std::min(best.tick_p99, f.tick_p99);
    best.latency_p99 = std::min(best.latency_p99, f.latency_p99);
    if (best.tick_p99 <= timing_tick_p99_bound_ms && best.latency_p99 <= timing_latency_p99_bound_ms) break;
  }
  if (!judged) {
    MESSAGE("NOT JUDGED: the machine stayed busy (1-minute load " << load << " on " << cores
                                                                << " cores); best tick p99 " << best.tick_p99
                                                                << " ms, latency p99 " << best.latency_p99 << " ms");
    return;
  }
  MESSAGE("load before the runs " << load << " on " << cores << " cores");
  CHECK(best.tick_p99 <= timing_tick_p99_bound_ms);
  CHECK(best.latency_p99 <= timing_latency_p99_bound_ms);
}

TEST_CASE("zone-server logs on stderr: its stdout stays empty while it runs and stops") {
  const std::string dir = temp_dir();
  const std::string err = dir + "/stderr.log", out = dir + "/stdout.log";
  // The shell sends the server's stderr to its own file; the child's log gets its stdout only.
  child_process proc({"/bin/sh", "-c", "exec \"$0\" --listen 127.0.0.1 --port 0 --metrics-port 0 --npcs 50 2>\"$1\"",
                      ZONE_SERVER_EXE, err},
                     out);
  bool listening = false;
  for (int i = 0; i < 1000 && !listening && proc.alive(); ++i) {
    listening = read_file(err).find("listening on 127.0.0.1:") != std::string::npos;
    if (!listening) std::this_thread::sleep_for(20ms);
  }
  INFO("stderr:\n" << read_file(err) << "\nstdout:\n" << read_file(out));
  REQUIRE(listening);
  CHECK(proc.terminate().value_or(-1) == 0);
  CHECK(read_file(err).find("zone server stopped") != std::string::npos);
  CHECK(read_file(out).empty());
}

TEST_CASE("rules: zone-server --player-aoi 100 --hysteresis 7 with a default bot-swarm gives no mismatch (the welcome tells the rules)") {
  const std::string dir = temp_dir();
  zone_server_process server(ZONE_SERVER_EXE, dir, server_args_with({"--player-aoi", "100", "--hysteresis", "7", "--oracle"}));
  REQUIRE_MESSAGE(server.port != 0, server.proc.log());
  const swarm_end run = run_swarm(server.port, dir, {"--bots", "60", "--duration", "8", "--ramp", "100", "--verify", "--oracle"});
  const double rate = judge_machine(server).rate;
  const std::string& report = run.report;
  INFO("bot-swarm output:\n" << run.log);
  CHECK(run.rc == 0);
  CHECK(report.find("\"rules_from_server\": true") != std::string::npos);
  CHECK(json_number(report, "mismatches").value_or(-1) == 0);
  CHECK(json_number(report, "aoi_checked").value_or(0) > 1000);
  CHECK(json_number(report, "frames_checked").value_or(0) > 60 * 20 * 4 * rate);
  CHECK(server.proc.terminate().value_or(-1) == 0);
}

TEST_CASE(
    "oracle restart: the zone-server killed and started again on its port; the oracle follows the new server's truth, or fails when it publishes none") {
  for (const bool truth_again : {true, false}) {
    CAPTURE(truth_again);
    const std::string dir = temp_dir();
    auto first = std::make_unique<zone_server_process>(ZONE_SERVER_EXE, dir, server_args_with({"--oracle"}));
    REQUIRE_MESSAGE(first->port != 0, first->proc.log());
    const std::uint16_t port = first->port;
    child_process swarm(swarm_args(port, dir,
                                   {"--bots", "40", "--duration", "10", "--ramp", "100", "--verify", "--oracle",
                                    "--reconnect", "--relogin-delay", "0.3", "--connect-timeout", "10"}),
                        dir + "/bot-swarm.log");
    std::this_thread::sleep_for(3s);
    first->proc.kill_now();  // SIGKILL: its truth stream ends mid-run
    std::vector<std::string> again{ZONE_SERVER_EXE,      "--listen",       "127.0.0.1", "--port",
                                   std::to_string(port), "--metrics-port", "0"};
    again.insert(again.end(), server_args.begin(), server_args.end());
    if (truth_again) again.push_back("--oracle");
    child_process second(again, dir + "/zone-server-2.log");
    REQUIRE_MESSAGE(second.wait_for_log("listening on", 20000ms).has_value(), second.log());
    const swarm_end run = finish(swarm, dir, 60000ms);
    REQUIRE_MESSAGE(run.rc.has_value(), "bot-swarm did not end within 60 s; its output:\n" << run.log);
    INFO("bot-swarm output:\n" << run.log);
    const std::string& report = run.report;
    CHECK(json_number(report, "reconnects").value_or(0) >= 40);  // every bot logged in again, on the new server
    CHECK(json_number(report, "digest_mismatches").value_or(-1) == 0);
    if (truth_again) {
      // The old stream's end is explained by the restart: no error; the bots on the new server
      // are judged by its truth.
      CHECK(json_number(report, "truth_restarts").value_or(-1) == 1);
      CHECK(json_number(report, "frames_checked_after_restart").value_or(0) > 1000);
      CHECK(json_number(report, "oracle_mismatches").value_or(-1) == 0);
      CHECK(json_number(report, "mismatches").value_or(-1) == 0);
      CHECK(report.find("\"stream_error\": \"\"") != std::string::npos);
    } else {
      // A new server without a truth stream: nothing to follow; the old stream's end stays a
      // failure of the run (its frames cannot be checked).
      CHECK(json_number(report, "truth_restarts").value_or(-1) == 0);
      CHECK(report.find("\"stream_error\": \"\"") == std::string::npos);
      CHECK(json_number(report, "mismatches").value_or(0) >= 1);
      CHECK(run.rc == 1);
    }
    CHECK(second.terminate().value_or(-1) == 0);
  }
}

TEST_CASE("ramp: 800 bots launched at once from one address all join under the server's default pending caps") {
  // Every bot connects from 127.0.0.1 and the swarm's threads lag behind a ramp this fast: before
  // --max-connecting, hundreds of connections were open with no hello written yet, the server's
  // default --max-pending-per-address (256) closed the oldest of them, and those bots failed with
  // "write: Broken pipe" (about a quarter joined). The ramp now waits for hellos.
  const std::string dir = temp_dir();
  zone_server_process server(ZONE_SERVER_EXE, dir, server_args_with({"--max-clients", "900"}));
  REQUIRE_MESSAGE(server.port != 0, server.proc.log());
  const swarm_end run = run_swarm(server.port, dir, {"--bots", "800", "--duration", "4", "--ramp", "100000", "--quiet"});
  const std::string& report = run.report;
  INFO("bot-swarm output:\n" << run.log);
  CHECK(run.rc == 0);
  CHECK(json_number(report, "bots_connected").value_or(-1) == 800);
  CHECK(json_number(report, "connect_failures").value_or(-1) == 0);
  // Every login's two durations were recorded (launch to connected, connected to welcome).
  for (const char* key : {"login_connect_ms", "login_welcome_ms"}) {
    CAPTURE(key);
    std::smatch m;
    const std::regex samples(std::string("\"") + key + "\": \\{[^}]*\"samples\": ([0-9]+)");
    REQUIRE(std::regex_search(report, m, samples));
    CHECK(std::stoull(m[1].str()) == 800);
    const std::regex p99(std::string("\"") + key + "\": \\{[^}]*\"p99\": ([-0-9.eE+]+)");
    REQUIRE(std::regex_search(report, m, p99));
    CHECK(std::stod(m[1].str()) > 0);
  }
  // The server closed no connection for the pending caps (the swarm held at most --max-connecting).
  const std::string scrape = http_get_metrics(server.metrics_port);
  INFO("zone-server metrics:\n" << scrape);
  CHECK(scrape.find("zone_net_pending_evicted_total{cap=\"address\"} 0\n") != std::string::npos);
  CHECK(scrape.find("zone_net_pending_evicted_total{cap=\"total\"} 0\n") != std::string::npos);
  CHECK(server.proc.terminate().value_or(-1) == 0);
}

namespace {

/// zone-server --test-fault KIND against 20 bots with the oracle: the swarm fails, the oracle
/// reports the fault (and only it) under its kind's counter, and, for the faults whose frames keep
/// the digest consistent with what the client holds, the server's own digests see nothing.
void oracle_catches(const std::string& fault, const std::string& counter, bool digests_blind) {
  const std::string dir = temp_dir();
  zone_server_process server(ZONE_SERVER_EXE, dir, server_args_with({"--oracle", "--test-fault", fault, "--test-fault-tick", "40"}));
  REQUIRE_MESSAGE(server.port != 0, server.proc.log());
  // With stealth and team bots switching: the faults are caught among legitimate class changes.
  const swarm_end run = run_swarm(server.port, dir, {"--bots", "20", "--duration", "7", "--ramp", "100", "--verify", "--oracle",
                                                     "--stealth-bots", "0.2", "--team-bots", "0.4", "--visibility-switch-hz", "0.5"});
  const double rate = judge_machine(server).rate;
  const std::string& report = run.report;
  INFO("bot-swarm output:\n" << run.log);
  CHECK(run.rc == 1);  // mismatches
  const double caught = json_number(report, counter).value_or(0);
  MESSAGE("fault " << fault << ": the oracle counted " << caught << " " << counter << " mismatches");
  CHECK(caught > 0);
  CHECK(json_number(report, "oracle_mismatches").value_or(-1) == caught);
  if (digests_blind) CHECK(json_number(report, "digest_mismatches").value_or(-1) == 0);
  CHECK(json_number(report, "frames_checked").value_or(0) > 20 * 20 * 4 * rate);
  CHECK(server.proc.terminate().value_or(-1) == 0);
}

}  // namespace

TEST_CASE("oracle fault drop: an entity left out of one client's view is caught as missing") {
  oracle_catches("drop", "missing", true);
}
TEST_CASE("oracle fault extra: an entity far outside one client's AOI is caught as extra") {
  oracle_catches("extra", "extra", false);
}
TEST_CASE("oracle fault stealth: a stealth entity leaked to one client is caught as leaked") {
  oracle_catches("stealth", "leaked", true);
}
TEST_CASE("oracle fault freeze: one entity's frozen position is caught as a position mismatch") {
  oracle_catches("freeze", "position", true);
}
TEST_CASE("oracle fault class: an entity sent with the wrong class is caught") {
  oracle_catches("class", "wrong_class", true);
}

TEST_CASE("teleport: bots jump at random across the world; views and AOI checks stay exact") {
  const std::string dir = temp_dir();
  zone_server_process server(ZONE_SERVER_EXE, dir, server_args_with({"--teleport", "1", "--teleport-cooldown", "0.2"}));
  REQUIRE_MESSAGE(server.port != 0, server.proc.log());
  const swarm_end run = run_swarm(server.port, dir, {"--bots", "100", "--duration", "15", "--ramp", "100", "--verify", "--mix",
                                                     "walk=0.3,teleport=0.5,follow=0.1,crowd=0.1", "--teleport-hz", "1"});
  const double rate = judge_machine(server).rate;
  const std::string& report = run.report;
  INFO("bot-swarm output:\n" << run.log);
  CHECK(run.rc == 0);
  CHECK(json_number(report, "bots_connected").value_or(-1) == 100);
  CHECK(json_number(report, "mismatches").value_or(-1) == 0);
  CHECK(json_number(report, "digests_checked").value_or(0) > 100 * 20 * 5 * rate);
  // 50 teleport bots at 1 jump/s for ~14 s: ~700 jumps.
  const double sent = json_number(report, "teleports_sent").value_or(0);
  CHECK(sent > 300);
  // Every frame carried the bot's own position, so every AOI check used the position of that very
  // tick (none skipped for want of it, none stale across a jump).
  CHECK(json_number(report, "self_positions").value_or(0) > 0);
  CHECK(json_number(report, "aoi_checked").value_or(0) > 0);
  CHECK(json_number(report, "aoi_unchecked").value_or(-1) == 0);
  // The server applied them (the cooldown, 0.2 s, refuses only jumps that come too close together).
  std::optional<double> applied;
  for (int i = 0; i < 20 && applied.value_or(0) < sent / 2; ++i) {
    applied = metric(http_get_metrics(server.metrics_port), "zone_teleports_total");
    std::this_thread::sleep_for(250ms);
  }
  MESSAGE("teleports sent " << sent << ", applied by the server " << applied.value_or(-1));
  CHECK(applied.value_or(0) > sent / 2);
  CHECK(server.proc.terminate().value_or(-1) == 0);
}

namespace {
/// The server's zone_entities before any bot joined (its NPCs): a loaded machine may answer the
/// first scrape late (or before the first tick), so it asks for up to 10 s.
std::optional<double> entities_before_any_bot(const zone_server_process& server) {
  std::optional<double> n;
  for (int i = 0; i < 40 && !n; ++i) {
    n = metric(http_get_metrics(server.metrics_port), "zone_entities");
    if (!n) std::this_thread::sleep_for(250ms);
  }
  return n;
}
}  // namespace

TEST_CASE("churn: bots log out and in continuously for a minute; no crash, no leaked sessions") {
  const std::string dir = temp_dir();
  zone_server_process server(ZONE_SERVER_EXE, dir, server_args);
  REQUIRE_MESSAGE(server.port != 0, server.proc.log());
  REQUIRE(server.metrics_port != 0);
  const std::optional<double> baseline = entities_before_any_bot(server);
  REQUIRE(baseline.has_value());
  constexpr int bots = 80;
  // The churn settings come from a scenario file (also covering --scenario); the command line adds to it.
  // 60 s of churn (it starts once all 80 bots are launched, 0.4 s in), then 8 s without, in which
  // every bot is logged in again and the server's counts must equal the live count.
  constexpr double churn_s = 60.5, duration_s = 68.5;
  {
    std::ofstream scenario(dir + "/churn.json");
    scenario << R"({"duration": )" << duration_s << R"(, "ramp": 200, "churn": 20, "churn-for": )" << churn_s
             << R"(, "relogin-delay": 0.1, "verify": true, "mix": {"walk": 0.4, "patrol": 0.4, "teleport": 0.2}})";
  }
  child_process swarm(swarm_args(server.port, dir, {"--bots", std::to_string(bots), "--scenario", dir + "/churn.json"}),
                      dir + "/bot-swarm.log");
  const auto started = std::chrono::steady_clock::now();
  // While it runs, the server never holds more sessions than bots (plus a few closing). Once the
  // churn has stopped, the sessions, clients and entities settle on the live count: every bot
  // logged in, nothing left over from the ~1,200 sessions that came and went.
  double most_sessions = 0;
  bool settled = false;
  std::optional<double> live_sessions, live_clients, live_entities;
  while (swarm.alive()) {
    const auto text = http_get_metrics(server.metrics_port);
    most_sessions = std::max(most_sessions, metric(text, "zone_net_sessions_open").value_or(0));
    if (std::chrono::steady_clock::now() - started > std::chrono::duration<double>(churn_s + 1.5) && !settled) {
      live_sessions = metric(text, "zone_net_sessions_open");
      live_clients = metric(text, "zone_clients");
      live_entities = metric(text, "zone_entities");
      settled = live_sessions == double{bots} && live_clients == double{bots} && live_entities == *baseline + bots;
    }
    std::this_thread::sleep_for(250ms);
    REQUIRE(server.proc.alive());
  }
  const swarm_end run = finish(swarm, dir, 1000ms);
  const std::string& report = run.report;
  INFO("bot-swarm output:\n" << run.log);
  CHECK(run.rc == 0);
  // 20 logouts a second for 60 s is 1,200; a loaded machine may fall somewhat behind.
  CHECK(json_number(report, "logouts").value_or(0) >= 800);
  CHECK(report.find("\"verify\": true") != std::string::npos);
  CHECK(json_number(report, "mismatches").value_or(-1) == 0);
  CHECK(json_number(report, "teleports_sent").value_or(0) > 0);
  CHECK(most_sessions <= bots + 10);
  CHECK_MESSAGE(settled, "after the churn: sessions " << live_sessions.value_or(-1) << ", clients "
                                                      << live_clients.value_or(-1) << ", entities "
                                                      << live_entities.value_or(-1) << " (live: " << bots << " bots, "
                                                      << *baseline + bots << " entities)");
  // Every bot is gone: the server's sessions, clients and entities return to the live count.
  std::optional<double> sessions, clients, entities;
  for (int i = 0; i < 40; ++i) {
    const auto text = http_get_metrics(server.metrics_port);
    sessions = metric(text, "zone_net_sessions_open");
    clients = metric(text, "zone_clients");
    entities = metric(text, "zone_entities");
    if (sessions == 0.0 && clients == 0.0 && entities == baseline) break;
    std::this_thread::sleep_for(250ms);
  }
  CHECK(sessions.value_or(-1) == 0);
  CHECK(clients.value_or(-1) == 0);
  CHECK(entities.value_or(-1) == *baseline);
  CHECK(server.proc.terminate().value_or(-1) == 0);
}

TEST_CASE(
    "resume: bots whose connections drop (--cut) come back to their own entities with their tokens (--linger); the oracle checks them; leaves free the rest at once") {
  const std::string dir = temp_dir();
  zone_server_process server(ZONE_SERVER_EXE, dir, server_args_with({"--oracle", "--linger", "30"}));
  REQUIRE_MESSAGE(server.port != 0, server.proc.log());
  REQUIRE(server.metrics_port != 0);
  const std::optional<double> baseline = entities_before_any_bot(server);
  REQUIRE(baseline.has_value());
  // 4 cuts a second for 9 s (about 36), then 4 s for the last ones to come back.
  const swarm_end run = run_swarm(server.port, dir,
                                  {"--bots", "60", "--duration", "13", "--ramp", "200", "--cut", "4", "--churn-for",
                                   "9", "--relogin-delay", "0.1", "--verify", "--oracle"});
  const std::string& report = run.report;
  INFO("bot-swarm output:\n" << run.log);
  CHECK(run.rc == 0);
  const double cuts = json_number(report, "cuts").value_or(0);
  CHECK(cuts >= 15);  // 36 asked for; a loaded machine may fall somewhat behind
  // Every cut bot's login again said its token and got its own entity back.
  CHECK(json_number(report, "resumes").value_or(-1) == cuts);
  CHECK(json_number(report, "resumes_refused").value_or(-1) == 0);
  CHECK(json_number(report, "unexpected_disconnects").value_or(-1) == 0);
  CHECK(json_number(report, "connect_failures").value_or(-1) == 0);
  CHECK(json_number(report, "server_errors").value_or(-1) == 0);
  CHECK(json_number(report, "mismatches").value_or(-1) == 0);
  // The oracle followed the resumed entities' views against the ground truth.
  CHECK(report.find("\"stream_error\": \"\"") != std::string::npos);
  CHECK(json_number(report, "oracle_mismatches").value_or(-1) == 0);
  // The server's side: each cut player kept and claimed back (or taken over, when the new
  // connection came before the old one's end was read), none expired. Then every bot said leave:
  // the entities are gone at once, not kept for the 30 s linger.
  std::string text;
  std::optional<double> clients, entities;
  for (int i = 0; i < 40; ++i) {
    text = http_get_metrics(server.metrics_port);
    clients = metric(text, "zone_clients");
    entities = metric(text, "zone_entities");
    if (clients == 0.0 && entities == baseline) break;
    std::this_thread::sleep_for(250ms);
  }
  INFO("server metrics:\n" << text);
  CHECK(metric(text, "zone_players_resumed_total").value_or(-1) + metric(text, "zone_takeovers_total").value_or(-1) ==
        cuts);
  CHECK(metric(text, "zone_resumes_refused_total").value_or(-1) == 0);
  CHECK(metric(text, "zone_linger_expired_total").value_or(-1) == 0);
  CHECK(metric(text, "zone_logouts_total").value_or(-1) == 61);  // the 60 bots and the oracle's probe
  CHECK(metric(text, "zone_players_lingering").value_or(-1) == 0);
  CHECK(clients.value_or(-1) == 0);
  CHECK(entities.value_or(-1) == *baseline);
  CHECK(server.proc.terminate().value_or(-1) == 0);
}

namespace {

/// The hostile test's stalled reader, checked, and a reader at 3/4 of the rate it is sent to,
/// beside 50 verifying bots. Paced (the default --client-max-backlog 2): the server builds a slow
/// client no new frame while two are unwritten, so nothing is dropped and no reset is needed;
/// unpaced (0): state frames are dropped for both, and after a drop they must get nothing they
/// cannot apply (a delta on top of a dropped frame) until a reset. Either way every frame they
/// get applies, both are served again afterwards, and the bots see no mismatch.
void slow_clients(bool paced) {
  const std::string dir = temp_dir();
  // A small world (~150 entities in a view) and every visible entity updated every tick: ~60 KB/s
  // per client; a 32 KiB socket send buffer (the kernel's default autotuning would hold up to
  // 4 MiB, over a minute of these frames, before the server's queue saw anything).
  zone_server_process server(ZONE_SERVER_EXE, dir, server_args_with({"--world-x", "800", "--world-y", "800", "--player-aoi", "120", "--update-near", "120",
                           "--update-mid", "120", "--socket-send-buffer", "32768", "--client-max-backlog",
                           paced ? "2" : "0"}));
  REQUIRE_MESSAGE(server.port != 0, server.proc.log());
  child_process swarm(swarm_args(server.port, dir, {"--bots", "50", "--duration", "24", "--ramp", "100", "--verify",
                                                    "--aoi", "120"}),
                      dir + "/bot-swarm.log");
  verifying_client stalled(server.port, "stalled"), slow(server.port, "slow");
  std::uint64_t stalled_before = 0, slow_before = 0;
  std::thread stalled_thread([&] {
    stalled.read_for(3000);
    stalled_before = stalled.frames;
    stalled.stall(10000);
    stalled.read_for(6000);
  });
  std::thread slow_thread([&] {
    slow.read_for(3000);
    slow_before = slow.frames;
    // Then at 3/4 of the rate the server sends at: its queue fills now and then, frames are
    // dropped, and it catches up in between (what made the old server send deltas it could not
    // apply; a reader far slower than that gets nothing but resets).
    const double rate = static_cast<double>(slow.bytes) / 3.0;
    slow.read_for(10000, std::max<std::size_t>(64, static_cast<std::size_t>(rate * 0.75 * 0.02)));
    slow.read_for(6000);
  });
  stalled_thread.join();
  slow_thread.join();
  const auto text = http_get_metrics(server.metrics_port);
  const double dropped = metric(text, "zone_net_frames_dropped_total").value_or(0);
  const double resyncs = metric(text, "zone_net_resyncs_requested_total").value_or(0);
  const double held = metric(text, "zone_frames_held_total").value_or(0);
  MESSAGE("paced " << paced << ", frames held back " << held << "; " << "stalled: " << stalled.frames << " frames (" << stalled.resets << " resets, " << stalled.bytes << " bytes); slow: "
                      << slow.frames << " frames (" << slow.resets << " resets, " << slow.bytes
                      << " bytes); server: " << dropped << " state frames dropped, " << resyncs << " resyncs");
  for (auto* c : {&stalled, &slow}) {
    CHECK_FALSE(c->closed);
    CHECK_FALSE(c->bad_stream);
    CHECK(c->inconsistent == 0);
    CHECK(c->digest_mismatches == 0);
    CHECK(c->digests == c->frames);
    if (paced) {
      // The stalled reader's backlog stayed full past --client-stall (1 s): its queued state was
      // dropped and it got a reset once it drained; the slow reader drains all along: no reset.
      CHECK(c->resets == (c == &stalled ? 1u : 0u));
    } else {
      CHECK(c->resets >= 1);  // it was resynchronised after its drops
    }
  }
  CHECK(stalled.frames > stalled_before + 40);  // served again
  CHECK(slow.frames > slow_before + 40);
  const double stalls = metric(text, "zone_client_stalls_total").value_or(0);
  if (paced) {
    CHECK(held > 0);
    CHECK(stalls == 1);      // the stalled reader, once
    CHECK(dropped <= 2);     // at most what was queued behind its write in flight
    CHECK(resyncs == 0);     // the queue never overflowed
  } else {
    CHECK(dropped > 0);
    CHECK(resyncs >= 2);
  }

  const swarm_end run = finish(swarm, dir, 60000ms);
  const std::string& report = run.report;
  INFO("bot-swarm output:\n" << run.log);
  CHECK(run.rc == 0);
  CHECK(json_number(report, "bots_connected").value_or(-1) == 50);
  CHECK(json_number(report, "mismatches").value_or(-1) == 0);
  CHECK(server.proc.terminate().value_or(-1) == 0);
}

}  // namespace

TEST_CASE("slow clients paced: one stops reading for 10 s (one reset when it drains), one reads slower than it is sent to (no reset)") {
  slow_clients(true);
}

TEST_CASE("slow clients unpaced: frames dropped, then only frames they can apply until a reset") {
  slow_clients(false);
}

TEST_CASE("hostile clients beside 100 good bots") {
  const std::string dir = temp_dir();
  zone_server_process server(ZONE_SERVER_EXE, dir, server_args);
  REQUIRE_MESSAGE(server.port != 0, server.proc.log());
  child_process swarm(swarm_args(server.port, dir, {"--bots", "100", "--duration", "22", "--ramp", "100", "--verify"}),
                      dir + "/bot-swarm.log");
  std::this_thread::sleep_for(3000ms);
  const long rss_before = server.proc.rss_kib();
  const std::uint16_t port = server.port;
  using zone::net::encode_frame;

  // Garbage bytes: a plausible length, then junk: the verifier rejects it and the server closes.
  std::atomic<int> closed_garbage{0}, closed_oversize{0}, closed_flood{0}, stalled_ok{0};
  std::thread garbage([&] {
    std::mt19937 rng(7);
    for (int i = 0; i < 20; ++i) {
      raw_client c(port);
      std::vector<std::uint8_t> junk(4 + 64);
      junk[0] = 64;
      for (std::size_t k = 4; k < junk.size(); ++k) junk[k] = static_cast<std::uint8_t>(rng());
      c.send_bytes(junk);
      if (c.closed_within(3000)) ++closed_garbage;
    }
  });
  // Oversize: a 1 MiB length prefix (the inbound limit is 16 KiB): closed from the prefix alone.
  std::thread oversize([&] {
    for (int i = 0; i < 10; ++i) {
      raw_client c(port);
      std::vector<std::uint8_t> frame(4 + 4096, 0xAB);
      frame[0] = 0, frame[1] = 0, frame[2] = 0x10, frame[3] = 0;
      c.send_bytes(frame);
      if (c.closed_within(3000)) ++closed_oversize;
    }
  });
  // Input flood: hello, then inputs as fast as the socket takes them: rate-limited and closed.
  std::thread flood([&] {
    for (int i = 0; i < 3; ++i) {
      raw_client c(port);
      c.send_bytes(encode_frame(zone::net::hello_msg{"flood", "", zone::net::protocol_version}));
      const auto deadline = std::chrono::steady_clock::now() + 8000ms;
      bool closed = false;
      for (std::uint32_t seq = 1; std::chrono::steady_clock::now() < deadline && !closed; ++seq) {
        if (!c.send_bytes(encode_frame(zone::net::input_msg{seq, {1, 0, 0}}))) closed = true;
        if (seq % 100 == 0 && !c.drain(1)) closed = true;
      }
      if (closed || c.closed_within(2000)) ++closed_flood;
    }
  });
  // A reader that stops reading for 10 s (pinging so as not to be idle), then reads again.
  std::thread stalled([&] {
    raw_client c(port, 4096);
    c.send_bytes(encode_frame(zone::net::hello_msg{"stalled", "", zone::net::protocol_version}));
    for (int s = 0; s < 10; ++s) {
      std::this_thread::sleep_for(1000ms);
      c.send_bytes(encode_frame(zone::net::ping_msg{static_cast<std::uint64_t>(s)}));
    }
    std::size_t got = 0;
    const bool open = c.drain(2000, &got);
    // Either it is served again (bytes arrive) or it was cut as a stuck client: both bounded.
    if (got > 0 || !open) ++stalled_ok;
  });
  garbage.join();
  oversize.join();
  flood.join();
  stalled.join();
  const long rss_after = server.proc.rss_kib();

  const swarm_end run = finish(swarm, dir, 60000ms);
  const std::string& report = run.report;
  INFO("bot-swarm output:\n" << run.log);
  CHECK(run.rc == 0);
  CHECK(json_number(report, "bots_connected").value_or(-1) == 100);
  CHECK(json_number(report, "mismatches").value_or(-1) == 0);
  CHECK(json_number(report, "unexpected_disconnects").value_or(-1) == 0);
  CHECK(closed_garbage == 20);
  CHECK(closed_oversize == 10);
  CHECK(closed_flood == 3);
  CHECK(stalled_ok == 1);
  MESSAGE("server RSS " << rss_before << " KiB -> " << rss_after << " KiB during the hostile clients");
  CHECK(rss_after - rss_before < 64 * 1024);  // bounded: under 64 MiB of growth
  CHECK(server.proc.alive());
  CHECK(server.proc.terminate().value_or(-1) == 0);
}

// The swarm reads its sockets edge-triggered (docs/bots.md): a short read ends a wakeup, so a
// close that arrived with the last bytes must still be read to its end (a 0-byte read).
TEST_CASE("read path: a zone closes every connection right behind its last frames; each bot notices at once") {
  constexpr unsigned bots = 48;
  constexpr int ticks = 3;
  scripted_zone zone;
  REQUIRE(zone.port != 0);
  std::chrono::steady_clock::time_point closed_at{};
  std::thread server([&] {
    zone.accept_n(bots, 5000);
    std::this_thread::sleep_for(300ms);  // every bot connected and waiting for bytes
    closed_at = std::chrono::steady_clock::now();
    for (std::size_t i = 0; i < zone.peers.size(); ++i) {
      const int fd = zone.peers[i]->fd;
      scripted_zone::send_all(fd, welcome_and_ticks(static_cast<std::uint32_t>(100 + i), 10, ticks));
      // Half close at once (the end of stream behind the frames), half 50 ms later (an edge of its own).
      if (i % 2 == 0) ::shutdown(fd, SHUT_WR);
    }
    std::this_thread::sleep_for(50ms);
    for (std::size_t i = 1; i < zone.peers.size(); i += 2) ::shutdown(zone.peers[i]->fd, SHUT_WR);
    zone.read_until_closed(4000);
  });
  const auto options = scripted_swarm(zone.port, bots, 4);
  const auto out = zone::bots::run_swarm(options, nullptr);
  server.join();
  REQUIRE(out.error.empty());
  const auto& r = out.result;
  CHECK(zone.peers.size() == bots);
  CHECK(r.welcomes == bots);
  CHECK(r.tick_updates == bots * ticks);
  CHECK(r.mismatches() == 0);
  // Each bot saw the end of its stream and closed on its own (not at the swarm's end, 4 s in).
  CHECK(r.unexpected_disconnects == bots);
  for (const auto& p : zone.peers) {
    REQUIRE(p->closed_at.has_value());
    CHECK(*p->closed_at - closed_at < 2000ms);
  }
  // The threads ran out of work once every session had closed (no wait left behind).
  CHECK(r.elapsed_s < options.duration_s + 2);
}

TEST_CASE("read path: a redirect with the connection closed behind it; every bot follows it to the next zone") {
  constexpr unsigned bots = 48;
  scripted_zone a, b;
  REQUIRE(a.port != 0);
  REQUIRE(b.port != 0);
  std::thread zone_a([&] {
    a.accept_n(bots, 5000);
    std::this_thread::sleep_for(200ms);
    for (std::size_t i = 0; i < a.peers.size(); ++i) {
      auto frames = welcome_and_ticks(static_cast<std::uint32_t>(100 + i), 10, 2);
      frames.emplace_back(zone::net::redirect_msg{"127.0.0.1", b.port, "token-" + std::to_string(i)});
      scripted_zone::send_all(a.peers[i]->fd, frames);
      ::shutdown(a.peers[i]->fd, SHUT_WR);
    }
    a.read_until_closed(3000);
  });
  std::thread zone_b([&] {
    b.accept_n(bots, 5000);
    std::this_thread::sleep_for(200ms);
    for (std::size_t i = 0; i < b.peers.size(); ++i) {
      scripted_zone::send_all(b.peers[i]->fd, welcome_and_ticks(static_cast<std::uint32_t>(1000 + i), 20, 2));
    }
    b.read_until_closed(8000);  // the bots stay until the swarm's end
  });
  const auto options = scripted_swarm(a.port, bots, 3);
  const auto out = zone::bots::run_swarm(options, nullptr);
  zone_a.join();
  zone_b.join();
  REQUIRE(out.error.empty());
  const auto& r = out.result;
  CHECK(a.peers.size() == bots);
  CHECK(b.peers.size() == bots);
  CHECK(r.redirects == bots);
  CHECK(r.welcomes == 2 * bots);
  CHECK(r.tick_updates == 4 * bots);
  CHECK(r.unexpected_disconnects == 0);
  CHECK(r.connect_failures == 0);
  CHECK(r.mismatches() == 0);
  // Zone b heard each token once, in a hello.
  std::set<std::string> tokens;
  for (const auto& p : b.peers) {
    for (const auto& m : p->got) {
      if (const auto* h = std::get_if<zone::net::hello_msg>(&m)) CHECK(tokens.insert(h->token).second);
    }
  }
  CHECK(tokens.size() == bots);
  CHECK(tokens.count("token-0") == 1);
  CHECK(tokens.count("token-" + std::to_string(bots - 1)) == 1);
  // The bots logged out at the swarm's end, and the threads ran out of work (no wait left behind).
  CHECK(r.elapsed_s < options.duration_s + 2);
}

}  // TEST_SUITE
