// bench-handoff: the cost of handing replicated frames to the network (net::server), without the
// game. N loopback clients connect to a net::server; each "tick", K sender threads (the
// replication workers' role) give every session one state frame of B bytes, paced like the zone
// server (no frame while the session's state backlog is at 2): as the zone server does it by
// default (--mode many: frames carved from a per-sender net::frame_arena, handed over a chunk of
// sessions at a time with server::send_many) or one by one (--mode send: make_shared_frame +
// server::send per frame). A reader thread drains every client socket through epoll and discards
// the bytes. Prints a table: the senders' CPU per frame, the server's CPU per frame (the whole
// process less the reader and
// the idle main thread: senders plus I/O threads), the hand-off's wall time per tick, and what the
// server wrote. Benchmarks print tables; they are not timed tests (docs/zone-benchmarks.md).
#include <arpa/inet.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <sys/epoll.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include <spdlog/spdlog.h>

#include "interest/measure.h"
#include "net/server.h"
#include "tools/cli.h"

using namespace zone::net;

namespace {

double thread_cpu_s() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + static_cast<double>(ts.tv_nsec) * 1e-9;
}
double process_cpu_s() {
  rusage r{};
  getrusage(RUSAGE_SELF, &r);
  return static_cast<double>(r.ru_utime.tv_sec + r.ru_stime.tv_sec) +
         static_cast<double>(r.ru_utime.tv_usec + r.ru_stime.tv_usec) * 1e-6;
}

struct options {
  std::size_t sessions = 1000;
  std::size_t ticks = 300;
  unsigned senders = 2;
  unsigned io_threads = 2;
  std::size_t frame_bytes = 600;
  double rate_hz = 30;  // 0: back to back
  std::uint32_t max_backlog = 2;
  bool many = true;         // --mode many (send_many + frame_arena) or send
  std::size_t chunk = 16;   // sessions per send_many call (the zone's clients per replication task)
  bool direct_writes = false;
  write_batching batching = write_batching::automatic;
  std::size_t write_slice = 256;  // ready sessions an I/O thread writes before it reads again
};

using zone::quantile;

}  // namespace

int main(int argc, char** argv) {
  const std::string usage =
      "usage: bench-handoff [--sessions 1000] [--ticks 300] [--senders 2] [--io-threads 2] "
      "[--frame-bytes 600] [--rate 30 (0: back to back)] [--max-backlog 2 (0: off)]\n"
      "                     [--mode many|send (default many: frame_arena + send_many, the zone server's "
      "way; send: make_shared_frame + send per frame)] [--chunk 16 (sessions per send_many; the zone server hands over chunks of clients_per_task, 64)]\n"
      "                     [--direct-writes 0|1 (default 0: the I/O threads write)]\n"
      "                     [--write-batching auto|io_uring|sendmsg (default auto: io_uring where the "
      "kernel allows it)]\n"
      "                     [--write-slice 256 (sessions an I/O thread writes before it reads again)]\n";
  options o;
  std::string mode = "many", batching = "auto";
  int direct_writes = 0;
  namespace po = zone::tools::po;
  po::options_description cli;
  cli.add_options()("sessions", po::value(&o.sessions))("ticks", po::value(&o.ticks))("senders", po::value(&o.senders))(
      "io-threads", po::value(&o.io_threads))("frame-bytes", po::value(&o.frame_bytes))("rate", po::value(&o.rate_hz))(
      "max-backlog", po::value(&o.max_backlog))("chunk", po::value(&o.chunk))(
      "direct-writes", po::value(&direct_writes))("write-batching", po::value(&batching))(
      "write-slice", po::value(&o.write_slice))("mode", po::value(&mode));
  if (const auto rc = zone::tools::parse_command_line(argc, argv, "bench-handoff", usage, cli, 64)) return *rc;
  const auto b = parse_write_batching(batching);
  if (!b || (mode != "many" && mode != "send") || (direct_writes != 0 && direct_writes != 1) || o.sessions == 0 ||
      o.senders == 0 || o.frame_bytes < 64 || o.chunk == 0 || o.write_slice == 0) {
    std::fprintf(stderr,
                 "bench-handoff: bad value (--mode many|send, --write-batching auto|io_uring|sendmsg, "
                 "--direct-writes 0|1, --sessions, --senders, --chunk and --write-slice > 0, --frame-bytes >= 64)\n%s",
                 usage.c_str());
    return 64;
  }
  o.batching = *b;
  o.many = mode == "many";
  o.direct_writes = direct_writes == 1;
  spdlog::set_level(spdlog::level::warn);
  server_options so;
  so.io_threads = o.io_threads;
  so.direct_writes = o.direct_writes;
  so.batching = o.batching;
  so.write_slice = o.write_slice;
  so.max_connections = o.sessions + 16;
  so.max_pending = so.max_pending_per_address = o.sessions + 16;  // every client connects at once from loopback
  so.idle_timeout = std::chrono::hours(1);
  server srv(so);
  if (auto err = srv.start()) {
    std::fprintf(stderr, "bench-handoff: %s\n", err->c_str());
    return 1;
  }

  // Clients: plain sockets, one hello each (the session exists from the connection on).
  std::vector<int> fds;
  const auto hello = encode_frame(hello_msg{"bench", "", protocol_version});
  for (std::size_t i = 0; i < o.sessions; ++i) {
    const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(srv.port());
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    if (fd < 0 || ::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
      std::fprintf(stderr, "bench-handoff: connect %zu failed: %s (ulimit -n?)\n", i, std::strerror(errno));
      return 1;
    }
    (void)::write(fd, hello.data(), hello.size());
    fds.push_back(fd);
  }
  std::vector<session_id> sessions;
  std::vector<std::shared_ptr<const std::atomic<std::uint32_t>>> backlogs;
  std::vector<inbound_event> events;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(20);
  while (sessions.size() < o.sessions && std::chrono::steady_clock::now() < deadline) {
    events.clear();
    srv.poll(events);
    for (const auto& e : events) {
      if (e.type == inbound_event::kind::connected) {
        sessions.push_back(e.session);
        backlogs.push_back(srv.state_backlog(e.session));
      }
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  if (sessions.size() < o.sessions) {
    std::fprintf(stderr, "bench-handoff: only %zu of %zu sessions\n", sessions.size(), o.sessions);
    return 1;
  }

  // The reader: drains every client socket, discards the bytes.
  std::atomic<bool> stop{false};
  std::atomic<std::uint64_t> bytes_read{0};
  double reader_cpu = 0;
  std::thread reader([&] {
    const int ep = epoll_create1(0);
    for (const int fd : fds) {
      epoll_event ev{};
      ev.events = EPOLLIN;
      ev.data.fd = fd;
      epoll_ctl(ep, EPOLL_CTL_ADD, fd, &ev);
    }
    std::vector<epoll_event> ready(256);
    std::vector<char> buf(1 << 16);
    const double c0 = thread_cpu_s();
    while (!stop.load(std::memory_order_relaxed)) {
      const int n = epoll_wait(ep, ready.data(), static_cast<int>(ready.size()), 20);
      for (int i = 0; i < n; ++i) {
        const ssize_t got = ::read(ready[static_cast<std::size_t>(i)].data.fd, buf.data(), buf.size());
        if (got > 0) bytes_read.fetch_add(static_cast<std::uint64_t>(got), std::memory_order_relaxed);
      }
    }
    reader_cpu = thread_cpu_s() - c0;
    ::close(ep);
  });

  // A real tick_update of about frame_bytes (leaves of 4 bytes each), serialized per session
  // per tick as the zone server does (each client's frame is its own).
  tick_update_msg u;
  u.server_tick = 1;
  u.leaves.assign((o.frame_bytes - 64) / 4, 7u);
  const auto payload = encode_frame(u);

  std::vector<double> tick_wall_ms, tick_sender_cpu_ms;
  std::atomic<std::uint64_t> sent{0}, held{0};
  const auto period = o.rate_hz > 0 ? std::chrono::duration<double>(1.0 / o.rate_hz) : std::chrono::duration<double>(0);
  const auto s0 = srv.stats();
  const auto age0 = srv.frame_write_age().snapshot();  // the welcomes are control frames: none
  const double p0 = process_cpu_s();
  double senders_cpu_total = 0;
  const auto w0 = std::chrono::steady_clock::now();
  auto next = std::chrono::steady_clock::now();
  std::vector<frame_arena> arenas(o.senders);  // each sender's, kept across ticks like a worker's
  for (std::size_t t = 0; t < o.ticks; ++t) {
    std::vector<double> cpu(o.senders, 0);
    const auto t0 = std::chrono::steady_clock::now();
    const std::uint64_t tick_us = srv.now_us();  // each frame's age (frame_write_age) counts from here
    std::vector<std::thread> workers;
    for (unsigned k = 0; k < o.senders; ++k) {
      workers.emplace_back([&, k] {
        const double c0 = thread_cpu_s();
        std::uint64_t n = 0, h = 0;
        std::vector<outgoing_frame> batch;
        batch.reserve(o.chunk);
        for (std::size_t i = k; i < sessions.size(); i += o.senders) {
          if (o.max_backlog != 0 && backlogs[i] && backlogs[i]->load(std::memory_order_relaxed) >= o.max_backlog) {
            ++h;
            continue;
          }
          if (o.many) {
            batch.push_back({sessions[i], arenas[k].make(payload), delivery::state, tick_us});
            if (batch.size() == o.chunk) {
              srv.send_many_moved(batch);  // as the zone server: the frames handed over
              batch.clear();
            }
          } else {
            srv.send(sessions[i], make_shared_frame(payload), delivery::state);
          }
          ++n;
        }
        if (!batch.empty()) srv.send_many_moved(batch);
        sent += n;
        held += h;
        cpu[k] = thread_cpu_s() - c0;
      });
    }
    for (auto& w : workers) w.join();
    tick_wall_ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
    double c = 0;
    for (const double x : cpu) c += x;
    tick_sender_cpu_ms.push_back(c * 1000);
    senders_cpu_total += c;
    if (o.rate_hz > 0) {
      next += std::chrono::duration_cast<std::chrono::steady_clock::duration>(period);
      std::this_thread::sleep_until(next);
    }
  }
  // Let the I/O threads write what is queued.
  const auto flush_deadline = std::chrono::steady_clock::now() + std::chrono::seconds(5);
  while (std::chrono::steady_clock::now() < flush_deadline) {
    const auto s = srv.stats();
    if (s.frames_out - s0.frames_out + s.frames_dropped - s0.frames_dropped >= sent.load()) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - w0).count();
  const double p1 = process_cpu_s();
  stop = true;
  reader.join();
  const auto s1 = srv.stats();
  // Server CPU: the process less the reader thread (the main thread sleeps; its polling is noise).
  const double server_cpu = (p1 - p0) - reader_cpu;
  const double frames = static_cast<double>(sent.load());

  std::printf("bench-handoff: %zu sessions, %zu ticks at %s, %u senders, %u I/O threads, %zu-byte frames, pacing %u, %s, %s, %s\n",
              o.sessions, o.ticks, o.rate_hz > 0 ? (std::to_string(o.rate_hz) + " Hz").c_str() : "back to back",
              o.senders, o.io_threads, payload.size(), o.max_backlog,
              o.many ? ("send_many of " + std::to_string(o.chunk) + " + frame_arena").c_str() : "send per frame",
              o.direct_writes ? "direct writes" : "I/O-thread writes",
              srv.uses_io_uring() ? "io_uring batches" : "sendmsg per write");
  std::printf("| frames handed off | held (paced) | written | dropped | resyncs | wall s |\n");
  std::printf("|---|---|---|---|---|---|\n");
  std::printf("| %llu | %llu | %llu | %llu | %llu | %.2f |\n", static_cast<unsigned long long>(sent.load()),
              static_cast<unsigned long long>(held.load()),
              static_cast<unsigned long long>(s1.frames_out - s0.frames_out),
              static_cast<unsigned long long>(s1.frames_dropped - s0.frames_dropped),
              static_cast<unsigned long long>(s1.resyncs_requested - s0.resyncs_requested), wall);
  const auto writes = s1.writes - s0.writes, batches = s1.write_batches - s0.write_batches;
  // Each frame's age when written: from its tick's start (--mode many), or from its send().
  auto age = srv.frame_write_age().snapshot();
  for (std::size_t b = 0; b < age.size(); ++b) age[b] -= age0[b];
  using h_us = latency_histogram_us;
  std::printf(
      "| senders' CPU per frame | I/O threads' CPU per frame | server CPU per frame (senders + I/O) | hand-off wall per tick p50 / p99 | "
      "senders' CPU per tick p50 | reader CPU per frame | writes per io_uring submission | written p50 / p99 |\n");
  std::printf("|---|---|---|---|---|---|---|---|\n");
  std::printf("| %.2f us | %.2f us | %.2f us | %.3f / %.3f ms | %.3f ms | %.2f us | %s | %.3f / %.3f ms |\n",
              senders_cpu_total / frames * 1e6, (server_cpu - senders_cpu_total) / frames * 1e6,
              server_cpu / frames * 1e6, quantile(tick_wall_ms, 0.5), quantile(tick_wall_ms, 0.99),
              quantile(tick_sender_cpu_ms, 0.5), reader_cpu / frames * 1e6,
              batches > 0 ? std::to_string(static_cast<double>(writes) / static_cast<double>(batches)).c_str() : "-",
              h_us::percentile_mid(age, 0.5) / 1000.0, h_us::percentile_mid(age, 0.99) / 1000.0);
  srv.stop();
  for (const int fd : fds) ::close(fd);
  return 0;
}
