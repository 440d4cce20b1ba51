// zone-probe: hostile clients against a running zone-server on loopback (docs/operating.md,
// "Limits and hardening"; the figures: docs/zone-benchmarks.md, "Hostile clients"). Every attack is
// bounded in connections and time.
//
//   zone-probe --port P --attack halfopen [--count 1000] [--server-pid PID]
//   zone-probe --port P --attack pingflood [--seconds 5] [--server-pid PID]
//   zone-probe --port P --attack reconnect [--seconds 5] [--server-pid PID]
//   zone-probe --port P --attack httpidle --metrics-port M [--count 1000] [--server-pid PID]
//
// halfopen: --count connections from 127.0.0.1, half silent, half dripping a hello a byte every
//   500 ms; then a player from 127.0.0.2 says hello. Reports the player's time to its welcome
//   and, for the attackers, how many were closed and the longest any stayed open.
// pingflood: a good client (127.0.0.3) reads its tick updates (frame gap p50/p99) for `seconds`
//   alone, then `seconds` beside a flood from 127.0.0.2 in two forms: blast (pings as fast as the
//   socket takes them; reconnecting with a hello when cut off) and paced (just under the
//   disconnect rule: 190 pings per 110 ms). Reports the server's CPU (from /proc/PID/stat) in each.
// reconnect: a good client as in pingflood, alone, then beside a reconnect flood from 127.0.0.2:
//   min(--count, 32) threads each connect, say hello, wait for the welcome (or the server's error,
//   or the close), close, and at once again, for `seconds` (a welcome waits for the next tick, so
//   one thread joins about once a tick). Reports the connections, joins (welcomes) and refusals a second, the
//   server's CPU above the baseline and the good client's frame gaps.
// httpidle: --count idle connections to /metrics, then a player joins (time to its welcome) and
//   a scrape is tried; reports how many of the idle connections the server kept.
// stall: --count players (at most 2,000) from 127.0.0.4 read and verify their views (digests) for
//   2 s, then all stop reading for `seconds` (pinging once a second) and read again (docs/zone.md,
//   "Slow and stalled clients"). Reports, over the players: the age of the first frame after
//   resuming, the stale frames and bytes read before a frame at most 2 ticks old, how long after
//   resuming that fresh frame came, views that failed to apply or verify, and the server's RSS
//   before, at the end of and after the stall (with --server-pid). --rcvbuf sets the players'
//   SO_RCVBUF (what their kernel holds for them unread).
// With --server-pid the server's RSS and high-water mark (VmRSS, VmHWM) are reported at the end.
// Output: a table, then one CSV line per figure (attack,metric,value).
#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <optional>
#include <sstream>
#include <string>
#include <atomic>
#include <thread>
#include <vector>

#include "interest/measure.h"
#include "net/protocol.h"
#include "tools/cli.h"

namespace {

using namespace zone::net;
using steady = std::chrono::steady_clock;
using namespace std::chrono_literals;

struct options {
  std::uint16_t port = 0, metrics_port = 0;
  std::string attack;
  std::size_t count = 1000;
  double seconds = 5;
  long server_pid = 0;
  int rcvbuf = 0;  ///< stall: each player's SO_RCVBUF (0 = the system's)
};

std::vector<std::pair<std::string, double>> figures;
void figure(const std::string& name, double value) { figures.emplace_back(name, value); }

using zone::ms_since;

/// A TCP connection to 127.0.0.1:port from 127.0.0.<from> (SO_RCVBUF `rcvbuf` unless 0); -1 on failure.
int connect_from(std::uint16_t port, std::uint8_t from, bool nonblocking, int rcvbuf = 0) {
  const int fd = ::socket(AF_INET, SOCK_STREAM | (nonblocking ? SOCK_NONBLOCK : 0), 0);
  if (fd < 0) return -1;
  // Before connect: the window scale is agreed in the handshake (set later, the kernel may have
  // advertised more than the buffer then holds, and drop what overflows).
  if (rcvbuf > 0) ::setsockopt(fd, SOL_SOCKET, SO_RCVBUF, &rcvbuf, sizeof rcvbuf);
  int one = 1;
  ::setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
  sockaddr_in src{};
  src.sin_family = AF_INET;
  src.sin_addr.s_addr = htonl(0x7f000000u | from);
  if (::bind(fd, reinterpret_cast<sockaddr*>(&src), sizeof src) != 0) {
    ::close(fd);
    return -1;
  }
  sockaddr_in dst{};
  dst.sin_family = AF_INET;
  dst.sin_port = htons(port);
  dst.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (::connect(fd, reinterpret_cast<sockaddr*>(&dst), sizeof dst) != 0 && errno != EINPROGRESS) {
    ::close(fd);
    return -1;
  }
  return fd;
}

bool send_all(int fd, std::span<const std::uint8_t> b) {
  std::size_t at = 0;
  while (at < b.size()) {
    const ssize_t n = ::send(fd, b.data() + at, b.size() - at, MSG_NOSIGNAL);
    if (n <= 0) return false;
    at += static_cast<std::size_t>(n);
  }
  return true;
}

/// Reads from a blocking socket until a message satisfying `pred` arrives or `timeout` passes.
template <class Pred>
bool read_until(int fd, frame_decoder& dec, std::chrono::milliseconds timeout, Pred pred) {
  const auto deadline = steady::now() + timeout;
  std::uint8_t buf[65536];
  while (steady::now() < deadline) {
    pollfd p{fd, POLLIN, 0};
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - steady::now()).count();
    if (::poll(&p, 1, static_cast<int>(std::max<long long>(1, left))) <= 0) continue;
    const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
    if (n <= 0) return false;
    dec.feed({buf, static_cast<std::size_t>(n)});
    for (auto s = dec.next(); s.is_frame(); s = dec.next()) {
      if (auto m = to_message(*s.frame.envelope); m && pred(*m)) return true;
    }
    if (dec.failed()) return false;
  }
  return false;
}

/// A player from 127.0.0.<from> says hello; ms to its welcome, or nothing.
std::optional<double> join_ms(std::uint16_t port, std::uint8_t from, int* keep_fd = nullptr) {
  const auto t0 = steady::now();
  const int fd = connect_from(port, from, false);
  if (fd < 0) return std::nullopt;
  frame_decoder dec;
  const bool ok = send_all(fd, encode_frame(hello_msg{"probe-player", "", protocol_version})) &&
                  read_until(fd, dec, 5000ms, [](const message& m) { return std::holds_alternative<welcome_msg>(m); });
  const double ms = ms_since(t0);
  if (keep_fd && ok) {
    *keep_fd = fd;
  } else {
    ::close(fd);
  }
  if (!ok) return std::nullopt;
  return ms;
}

/// utime + stime of a process in seconds (0 when unreadable).
double cpu_seconds(long pid) {
  if (pid <= 0) return 0;
  std::ifstream f("/proc/" + std::to_string(pid) + "/stat");
  std::string text((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
  const auto close_paren = text.rfind(')');
  if (close_paren == std::string::npos) return 0;
  std::istringstream rest(text.substr(close_paren + 2));
  std::string field;
  unsigned long long utime = 0, stime = 0;
  for (int i = 3; i <= 15 && rest >> field; ++i) {
    if (i == 14) utime = std::strtoull(field.c_str(), nullptr, 10);
    if (i == 15) stime = std::strtoull(field.c_str(), nullptr, 10);
  }
  return static_cast<double>(utime + stime) / static_cast<double>(::sysconf(_SC_CLK_TCK));
}

/// VmRSS or VmHWM of a process in MiB (0 when unreadable).
double status_mib(long pid, const char* key) {
  if (pid <= 0) return 0;
  std::ifstream f("/proc/" + std::to_string(pid) + "/status");
  for (std::string line; std::getline(f, line);) {
    if (line.starts_with(key)) return std::strtod(line.c_str() + std::strlen(key) + 1, nullptr) / 1024.0;
  }
  return 0;
}

int attack_halfopen(const options& o) {
  const auto hello = encode_frame(hello_msg{"dripper", "", protocol_version});
  struct attacker {
    int fd;
    steady::time_point opened;
    std::optional<double> closed_after_ms;
  };
  std::vector<attacker> a;
  const auto t0 = steady::now();
  for (std::size_t i = 0; i < o.count; ++i) {
    const int fd = connect_from(o.port, 1, true);
    if (fd < 0) {
      std::fprintf(stderr, "zone-probe: connection %zu failed: %s\n", i, std::strerror(errno));
      break;
    }
    a.push_back({fd, steady::now(), std::nullopt});
  }
  figure("attack connections opened", static_cast<double>(a.size()));
  std::this_thread::sleep_for(100ms);  // the server takes them from its backlog
  const auto joined = join_ms(o.port, 2);
  figure("player join ms (from 127.0.0.2)", joined.value_or(-1));
  const auto same = join_ms(o.port, 1);
  figure("player join ms (from 127.0.0.1, the attackers' address)", same.value_or(-1));
  // Drip a byte of the hello every 500 ms on the odd ones; watch every socket for its close.
  std::size_t dripped = 0, open = a.size();
  auto next_drip = steady::now();
  std::vector<pollfd> fds;
  while (open > 0 && ms_since(t0) < 20000) {
    if (steady::now() >= next_drip && dripped + 1 < hello.size()) {
      for (std::size_t i = 1; i < a.size(); i += 2) {
        if (!a[i].closed_after_ms) (void)::send(a[i].fd, hello.data() + dripped, 1, MSG_NOSIGNAL | MSG_DONTWAIT);
      }
      ++dripped;
      next_drip += 500ms;
    }
    fds.clear();
    for (const auto& x : a) fds.push_back({x.closed_after_ms ? -1 : x.fd, POLLIN, 0});
    ::poll(fds.data(), fds.size(), 50);
    for (std::size_t i = 0; i < a.size(); ++i) {
      if (a[i].closed_after_ms || !(fds[i].revents & (POLLIN | POLLHUP | POLLERR))) continue;
      std::uint8_t buf[4096];
      const ssize_t n = ::recv(a[i].fd, buf, sizeof buf, MSG_DONTWAIT);
      if (n == 0 || (n < 0 && errno != EAGAIN)) {
        a[i].closed_after_ms = std::chrono::duration<double, std::milli>(steady::now() - a[i].opened).count();
        --open;
      }
    }
  }
  double longest = 0;
  std::size_t closed = 0;
  for (const auto& x : a) {
    if (x.closed_after_ms) {
      ++closed;
      longest = std::max(longest, *x.closed_after_ms);
    }
    ::close(x.fd);
  }
  figure("attack connections closed by the server", static_cast<double>(closed));
  figure("longest an attack connection stayed open (ms)", longest);
  return joined && closed == a.size() ? 0 : 1;
}

/// The good client's frame gaps (ms) over `seconds`, while `during` runs between reads.
template <class During>
std::vector<double> frame_gaps(int fd, frame_decoder& dec, double seconds, During during) {
  std::vector<double> gaps;
  std::optional<steady::time_point> last;
  const auto end = steady::now() + std::chrono::duration_cast<steady::duration>(std::chrono::duration<double>(seconds));
  std::uint8_t buf[65536];
  while (steady::now() < end) {
    during();
    pollfd p{fd, POLLIN, 0};
    if (::poll(&p, 1, 1) <= 0) continue;
    const ssize_t n = ::recv(fd, buf, sizeof buf, MSG_DONTWAIT);
    if (n <= 0) break;
    dec.feed({buf, static_cast<std::size_t>(n)});
    for (auto s = dec.next(); s.is_frame(); s = dec.next()) {
      if (s.frame.type != wire::message::tick_update) continue;
      const auto now = steady::now();
      if (last) gaps.push_back(std::chrono::duration<double, std::milli>(now - *last).count());
      last = now;
    }
  }
  std::sort(gaps.begin(), gaps.end());
  return gaps;
}

double percentile(const std::vector<double>& sorted, double q) {
  if (sorted.empty()) return -1;
  return sorted[std::min(sorted.size() - 1, static_cast<std::size_t>(q * static_cast<double>(sorted.size())))];
}

/// The good client the floods are measured against: joined, kept alive with a ping a second
/// (within any rate limit), its baseline over o.seconds (frame gaps, the server's CPU) printed.
struct good_client {
  int fd = -1;
  frame_decoder dec;
  steady::time_point next_keepalive = steady::now();
  double base_cpu = 0;  ///< the server's CPU, fraction of a core, without the attack
  void keepalive() {
    if (steady::now() < next_keepalive) return;
    (void)send_all(fd, encode_frame(ping_msg{1}));
    next_keepalive += 1s;
  }
};

/// Joins the good client and measures its baseline; false (said on stderr) when it cannot join.
bool start_good_client(const options& o, good_client& g) {
  if (!join_ms(o.port, 3, &g.fd)) {
    std::fprintf(stderr, "zone-probe: the good client could not join\n");
    return false;
  }
  g.next_keepalive = steady::now();
  const double c0 = cpu_seconds(o.server_pid);
  const auto t0 = steady::now();
  const auto base = frame_gaps(g.fd, g.dec, o.seconds, [&] { g.keepalive(); });
  g.base_cpu = (cpu_seconds(o.server_pid) - c0) / std::chrono::duration<double>(steady::now() - t0).count();
  figure("baseline: good client frame gap p50 (ms)", percentile(base, 0.5));
  figure("baseline: good client frame gap p99 (ms)", percentile(base, 0.99));
  figure("baseline: server CPU (% of a core)", 100 * g.base_cpu);
  return true;
}

int attack_pingflood(const options& o) {
  good_client g;
  if (!start_good_client(o, g)) return 1;

  std::vector<std::uint8_t> pings;
  for (std::uint64_t i = 0; i < 190; ++i) {
    const auto f = encode_frame(ping_msg{i});
    pings.insert(pings.end(), f.begin(), f.end());
  }
  const auto hello = encode_frame(hello_msg{"flooder", "", protocol_version});
  for (const bool paced : {false, true}) {
    const std::string tag = paced ? "paced flood" : "blast flood";
    int fd = -1;
    std::uint64_t sent = 0, reconnects = 0;
    auto next_batch = steady::now();
    const auto flood = [&] {
      for (int burst = 0; burst < (paced ? 1 : 64); ++burst) {
        if (fd < 0) {
          fd = connect_from(o.port, 2, false);
          if (fd < 0) return;
          ++reconnects;
          if (!send_all(fd, hello)) {
            ::close(fd);
            fd = -1;
            return;
          }
          ::fcntl(fd, F_SETFL, ::fcntl(fd, F_GETFL) | O_NONBLOCK);
        }
        if (paced && steady::now() < next_batch) return;
        const ssize_t n = ::send(fd, pings.data(), pings.size(), MSG_NOSIGNAL | MSG_DONTWAIT);
        if (n > 0) sent += static_cast<std::uint64_t>(n) / (pings.size() / 190);
        if (n < 0 && errno != EAGAIN) {
          ::close(fd);
          fd = -1;
        }
        next_batch = steady::now() + 110ms;
        std::uint8_t sink[65536];
        while (fd >= 0) {
          const ssize_t r = ::recv(fd, sink, sizeof sink, MSG_DONTWAIT);
          if (r > 0) continue;
          if (r == 0 || errno != EAGAIN) {
            ::close(fd);
            fd = -1;
          }
          break;
        }
      }
    };
    const double c0 = cpu_seconds(o.server_pid);
    const auto t0 = steady::now();
    const auto gaps = frame_gaps(g.fd, g.dec, o.seconds, [&] {
      g.keepalive();
      flood();
    });
    const double secs = std::chrono::duration<double>(steady::now() - t0).count();
    const double cpu = (cpu_seconds(o.server_pid) - c0) / secs;
    if (fd >= 0) ::close(fd);
    figure(tag + ": pings written per second (blast: mostly never read)", static_cast<double>(sent) / secs);
    figure(tag + ": connections (hellos) per second", static_cast<double>(reconnects) / secs);
    figure(tag + ": server CPU (% of a core)", 100 * cpu);
    figure(tag + ": server CPU above baseline (% of a core)", 100 * (cpu - g.base_cpu));
    figure(tag + ": good client frame gap p50 (ms)", percentile(gaps, 0.5));
    figure(tag + ": good client frame gap p99 (ms)", percentile(gaps, 0.99));
  }
  ::close(g.fd);
  return 0;
}

int attack_reconnect(const options& o) {
  good_client g;
  if (!start_good_client(o, g)) return 1;

  // The flood, on its own threads: each one connection at a time, closed as soon as the server
  // has answered its hello (welcome: a join and, at the close, a leave; an error: refused).
  const auto hello = encode_frame(hello_msg{"reconnector", "", protocol_version});
  std::atomic<bool> stop{false};
  std::atomic<std::uint64_t> attempts{0}, welcomes{0}, rate_limited{0}, other_errors{0}, silent_closes{0}, failed_connects{0};
  const auto flood = [&] {
    while (!stop.load(std::memory_order_relaxed)) {
      const int fd = connect_from(o.port, 2, false);
      if (fd < 0) {
        ++failed_connects;
        continue;
      }
      ++attempts;
      frame_decoder dec;
      std::optional<message> answer;
      if (send_all(fd, hello)) {
        (void)read_until(fd, dec, 1000ms, [&](const message& m) {
          if (!std::holds_alternative<welcome_msg>(m) && !std::holds_alternative<error_msg>(m)) return false;
          answer = m;
          return true;
        });
      }
      ::close(fd);
      if (!answer) ++silent_closes;
      else if (std::holds_alternative<welcome_msg>(*answer)) ++welcomes;
      else if (std::get<error_msg>(*answer).code == error_code::rate_limited) ++rate_limited;
      else ++other_errors;
    }
  };
  const std::size_t threads = std::clamp<std::size_t>(o.count, 1, 32);
  std::vector<std::thread> flooders;
  const double c0 = cpu_seconds(o.server_pid);
  const auto t0 = steady::now();
  for (std::size_t i = 0; i < threads; ++i) flooders.emplace_back(flood);
  const auto gaps = frame_gaps(g.fd, g.dec, o.seconds, [&] { g.keepalive(); });
  const double secs = std::chrono::duration<double>(steady::now() - t0).count();
  const double cpu = (cpu_seconds(o.server_pid) - c0) / secs;
  stop = true;
  for (auto& t : flooders) t.join();
  ::close(g.fd);
  figure("reconnect flood: threads", static_cast<double>(threads));
  figure("reconnect flood: connections per second", static_cast<double>(attempts.load()) / secs);
  figure("reconnect flood: joins (welcomes) per second", static_cast<double>(welcomes.load()) / secs);
  figure("reconnect flood: refused with rate_limited per second", static_cast<double>(rate_limited.load()) / secs);
  figure("reconnect flood: other errors", static_cast<double>(other_errors.load()));
  figure("reconnect flood: closed without an answer", static_cast<double>(silent_closes.load()));
  figure("reconnect flood: failed connects", static_cast<double>(failed_connects.load()));
  figure("reconnect flood: server CPU (% of a core)", 100 * cpu);
  figure("reconnect flood: server CPU above baseline (% of a core)", 100 * (cpu - g.base_cpu));
  figure("reconnect flood: good client frame gap p50 (ms)", percentile(gaps, 0.5));
  figure("reconnect flood: good client frame gap p99 (ms)", percentile(gaps, 0.99));
  return 0;
}

int attack_httpidle(const options& o) {
  std::vector<int> idle;
  for (std::size_t i = 0; i < o.count; ++i) {
    const int fd = connect_from(o.metrics_port, 1, true);
    if (fd < 0) break;
    idle.push_back(fd);
  }
  figure("idle /metrics connections opened", static_cast<double>(idle.size()));
  std::this_thread::sleep_for(300ms);
  std::size_t closed = 0;
  for (const int fd : idle) {
    std::uint8_t b;
    const ssize_t n = ::recv(fd, &b, 1, MSG_DONTWAIT);
    if (n == 0 || (n < 0 && errno != EAGAIN)) ++closed;
  }
  figure("of them closed by the server at once", static_cast<double>(closed));
  figure("player join ms beside them", join_ms(o.port, 2).value_or(-1));
  for (const int fd : idle) ::close(fd);
  return 0;
}

/// A player of the stall attack: its socket, decoder and verified view.
struct stall_player {
  int fd = -1;
  frame_decoder dec;
  std::optional<client_view> view;
  double tick_ms = 50;
  bool closed = false;
  std::uint64_t problems = 0, frames = 0;
  // After resuming: the first frame's age, stale frames and bytes before a fresh one, when that came.
  std::optional<double> first_age, fresh_ms;
  std::uint64_t stale_frames = 0, stale_bytes = 0, resets = 0;
};

std::uint64_t host_us() {
  return static_cast<std::uint64_t>(std::chrono::duration_cast<std::chrono::microseconds>(steady::now().time_since_epoch()).count());
}

/// Reads what is there for every player (poll, up to `ms`), applying every frame; `resumed` set:
/// records each player's ages after that time point.
void stall_read(std::vector<stall_player>& ps, double ms, const steady::time_point* resumed) {
  const auto deadline = steady::now() + std::chrono::duration_cast<steady::duration>(std::chrono::duration<double, std::milli>(ms));
  std::vector<pollfd> fds(ps.size());
  std::uint8_t buf[65536];
  while (steady::now() < deadline) {
    for (std::size_t i = 0; i < ps.size(); ++i) fds[i] = {ps[i].closed ? -1 : ps[i].fd, POLLIN, 0};
    if (::poll(fds.data(), fds.size(), 5) <= 0) continue;
    for (std::size_t i = 0; i < ps.size(); ++i) {
      if ((fds[i].revents & (POLLIN | POLLHUP | POLLERR)) == 0) continue;
      auto& p = ps[i];
      const ssize_t n = ::recv(p.fd, buf, sizeof buf, MSG_DONTWAIT);
      if (n <= 0) {
        if (n == 0 || (errno != EAGAIN && errno != EWOULDBLOCK)) p.closed = true;
        continue;
      }
      p.dec.feed({buf, static_cast<std::size_t>(n)});
      for (auto st = p.dec.next(); st.is_frame(); st = p.dec.next()) {
        const auto m = to_message(*st.frame.envelope);
        if (!m) continue;
        if (const auto* w = std::get_if<welcome_msg>(&*m)) {
          p.view.emplace(w->world);
          p.tick_ms = 1000.0 / std::max<double>(1, w->tick_rate_hz);
          continue;
        }
        const auto* u = std::get_if<tick_update_msg>(&*m);
        if (!u || !p.view) continue;
        ++p.frames;
        if (p.view->apply(*u) != client_view::status::ok) ++p.problems;
        if (!resumed || p.fresh_ms) continue;
        const double age = static_cast<double>(host_us() - u->server_time_us) / 1000.0;
        if (!p.first_age) p.first_age = age;
        if (age <= 2 * p.tick_ms) {
          p.fresh_ms = ms_since(*resumed);
          p.resets += u->reset ? 1 : 0;
        } else {
          ++p.stale_frames;
          p.stale_bytes += st.frame.bytes.size();
        }
      }
      if (p.dec.failed()) p.closed = true;
    }
  }
}

int attack_stall(const options& o) {
  const std::size_t n = std::max<std::size_t>(1, std::min<std::size_t>(o.count, 2000));
  std::vector<stall_player> ps(n);
  for (auto& p : ps) {
    p.fd = connect_from(o.port, 4, false, o.rcvbuf);
    if (p.fd < 0 || !send_all(p.fd, encode_frame(hello_msg{"stall", "", protocol_version}))) {
      std::fprintf(stderr, "zone-probe: a stalling player could not connect: %s\n", std::strerror(errno));
      return 1;
    }
  }
  stall_read(ps, 2000, nullptr);
  std::size_t joined = 0;
  for (const auto& p : ps) joined += p.view && p.frames > 0 ? 1 : 0;
  figure("players (joined and reading)", static_cast<double>(joined));
  figure("stall (s)", o.seconds);
  figure("server RSS before the stall (MiB)", status_mib(o.server_pid, "VmRSS:"));
  // The stall: nothing read, a ping a second (not idle).
  for (double t = 0; t < o.seconds; t += 1) {
    std::this_thread::sleep_for(std::chrono::duration<double>(std::min(1.0, o.seconds - t)));
    for (auto& p : ps) (void)send_all(p.fd, encode_frame(ping_msg{0}));
  }
  figure("server RSS at the end of the stall (MiB)", status_mib(o.server_pid, "VmRSS:"));
  const auto resumed = steady::now();
  stall_read(ps, 3000, &resumed);
  figure("server RSS 3 s after resuming (MiB)", status_mib(o.server_pid, "VmRSS:"));
  std::vector<double> first, fresh, stale, stale_kb;
  std::size_t never = 0, closed = 0, problems = 0, resets = 0;
  for (const auto& p : ps) {
    closed += p.closed ? 1 : 0;
    problems += p.problems;
    resets += p.resets;
    if (p.first_age) first.push_back(*p.first_age);
    if (!p.fresh_ms) {
      ++never;
      continue;
    }
    fresh.push_back(*p.fresh_ms);
    stale.push_back(static_cast<double>(p.stale_frames));
    stale_kb.push_back(static_cast<double>(p.stale_bytes) / 1024.0);
  }
  for (auto* v : {&first, &fresh, &stale, &stale_kb}) std::sort(v->begin(), v->end());
  const auto both = [](const std::string& name, const std::vector<double>& v) {
    figure(name + ", median", v.empty() ? -1 : percentile(v, 0.5));
    figure(name + ", max", v.empty() ? -1 : v.back());
  };
  both("age of the first frame after resuming (ms)", first);
  both("stale frames read before a fresh one (<= 2 ticks old)", stale);
  both("stale KiB read before it", stale_kb);
  both("fresh frame this long after resuming (ms)", fresh);
  figure("fresh frames that were resets (resyncs after the stall)", static_cast<double>(resets));
  figure("players with no fresh frame within 3 s", static_cast<double>(never));
  figure("frames that did not apply or verify (digest)", static_cast<double>(problems));
  figure("players disconnected", static_cast<double>(closed));
  for (auto& p : ps) ::close(p.fd);
  return never == 0 && problems == 0 && closed == 0 ? 0 : 1;
}

const char* const usage_text =
    "usage: zone-probe --port P --attack halfopen|pingflood|reconnect|httpidle|stall [--count N (1000)] [--seconds S (5)]\n"
    "                  [--metrics-port M (httpidle)] [--server-pid PID (CPU and memory readings)]\n"
    "                  [--rcvbuf BYTES (stall: the players' SO_RCVBUF; 0 = the system's)]\n"
    "Hostile clients against a zone-server on loopback (docs/operating.md, Limits and hardening).\n";

int usage(bool help) {
  std::fputs(usage_text, help ? stdout : stderr);
  return help ? 0 : 64;
}

}  // namespace

int main(int argc, char** argv) {
  options o;
  namespace po = zone::tools::po;
  po::options_description cli;
  cli.add_options()("port", po::value(&o.port))("metrics-port", po::value(&o.metrics_port))(
      "attack", po::value(&o.attack))("count", po::value(&o.count))("seconds", po::value(&o.seconds))(
      "server-pid", po::value(&o.server_pid))("rcvbuf", po::value(&o.rcvbuf));
  if (const auto rc = zone::tools::parse_command_line(argc, argv, "zone-probe", usage_text, cli, 64)) return *rc;
  o.count = std::min<std::size_t>(o.count, 20000);
  o.seconds = std::clamp(o.seconds, 0.5, 120.0);
  o.rcvbuf = std::clamp(o.rcvbuf, 0, 1 << 26);
  if (o.port == 0 || (o.attack == "httpidle" && o.metrics_port == 0)) return usage(false);
  int rc;
  if (o.attack == "halfopen") rc = attack_halfopen(o);
  else if (o.attack == "pingflood") rc = attack_pingflood(o);
  else if (o.attack == "reconnect") rc = attack_reconnect(o);
  else if (o.attack == "httpidle") rc = attack_httpidle(o);
  else if (o.attack == "stall") rc = attack_stall(o);
  else return usage(false);
  if (o.server_pid > 0) {
    figure("server RSS now (MiB)", status_mib(o.server_pid, "VmRSS:"));
    figure("server RSS high-water mark (MiB)", status_mib(o.server_pid, "VmHWM:"));
  }
  std::printf("| %-62s | %12s |\n|%s|%s|\n", ("zone-probe " + o.attack).c_str(), "value", std::string(64, '-').c_str(),
              std::string(14, '-').c_str());
  for (const auto& [name, value] : figures) std::printf("| %-62s | %12.2f |\n", name.c_str(), value);
  std::printf("\nattack,metric,value\n");
  for (const auto& [name, value] : figures) std::printf("%s,\"%s\",%.3f\n", o.attack.c_str(), name.c_str(), value);
  return rc;
}
