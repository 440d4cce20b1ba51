// bench-handoff: the cost of handing replicated frames to the network (net::server), without the
// game. N loopback clients connect to a net::server; each "tick", K sender threads (the
// replication workers' role) give every session one state frame of B bytes, paced like the zone
// server (no frame while the session's state backlog is at 2): as the zone server does it by
// default (--mode many: frames carved from a per-sender net::frame_arena, handed over a chunk of
// sessions at a time with server::send_many) or one by one (--mode send: make_shared_frame +
// server::send per frame). The clients live in a child process, where --readers threads drain
// them through epoll and discard the bytes. Prints a table: the senders' CPU per frame, the
// server's CPU per frame (the process's: senders plus I/O threads, the main thread idle), the
// hand-off's wall time per tick, and what the server wrote. Benchmarks print tables; they are not
// timed tests (docs/zone-benchmarks.md).
//
// --mode floor measures what no server can go below on this host: no net::server, no frames
// built; --io-threads threads each write one --frame-bytes buffer a tick to each of its share of
// the sockets, one send() per frame (or, with --write-batching io_uring, one io_uring submission
// of registered-file sends per 256 sockets, the zone server's batching), and --readers threads
// drain the clients through epoll. Its CPU per frame is the kernel's loopback TCP path alone,
// with what loopback charges the sending thread (the receiving socket's work).
#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <pthread.h>
#include <signal.h>
#include <sys/epoll.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>
#if ZONE_HAVE_LIBURING
#include <liburing.h>
#endif

#include <algorithm>
#include <atomic>
#include <barrier>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include <spdlog/spdlog.h>

#include "interest/measure.h"
#include "net/os_limits.h"
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
  unsigned readers = 1;           // threads draining the clients' sockets
  std::string csv;                // --csv: one line a run appended
  std::vector<int> io_cpus, reader_cpus,
      sender_cpus;  // where the I/O threads (floor's writers), readers and senders run
};

using zone::quantile;

// The readers: each drains its share of the client sockets through epoll and discards the bytes
// until `stop`; their CPU time summed into `cpu_s`.
struct reader_pool {
  std::atomic<bool> stop{false};
  std::atomic<std::uint64_t> bytes{0};
  std::vector<double> cpu;
  std::vector<std::thread> threads;

  reader_pool(const std::vector<int>& fds, unsigned n, const std::vector<int>& cpus) : cpu(n, 0) {
    for (unsigned r = 0; r < n; ++r) {
      threads.emplace_back([this, &fds, n, r, &cpus] {
        ::pthread_setname_np(::pthread_self(), "handoff-reader");
        if (!cpus.empty()) (void)pin_current_thread(cpus);
        const int ep = epoll_create1(0);
        for (std::size_t i = r; i < fds.size(); i += n) {
          epoll_event ev{};
          ev.events = EPOLLIN;
          ev.data.fd = fds[i];
          epoll_ctl(ep, EPOLL_CTL_ADD, fds[i], &ev);
        }
        std::vector<epoll_event> ready(256);
        std::vector<char> buf(1 << 16);
        const double c0 = thread_cpu_s();
        while (!stop.load(std::memory_order_relaxed)) {
          const int k = epoll_wait(ep, ready.data(), static_cast<int>(ready.size()), 20);
          for (int i = 0; i < k; ++i) {
            const ssize_t got = ::read(ready[static_cast<std::size_t>(i)].data.fd, buf.data(), buf.size());
            if (got > 0) bytes.fetch_add(static_cast<std::uint64_t>(got), std::memory_order_relaxed);
          }
        }
        cpu[r] = thread_cpu_s() - c0;
        ::close(ep);
      });
    }
  }
  double finish() {
    stop = true;
    for (auto& t : threads) t.join();
    double c = 0;
    for (const double x : cpu) c += x;
    return c;
  }
};

// The clients, in a child process forked while the bench is one thread (a host's open-file limit
// is per process, 20,000 on the device hosts, and the two ends of 19,900 connections would not fit
// in one): told a port, it connects o.sessions sockets to 127.0.0.1 there, sends `hello` on each
// (when not empty), and drains them with o.readers threads (reader_pool) until told how many bytes
// the server wrote; then it reports its readers' CPU time and the bytes they read.
class client_process {
 public:
  /// Forks the child (call before any thread starts); null with the reason on stderr on failure.
  static std::unique_ptr<client_process> fork_clients(const options& o, std::vector<std::uint8_t> hello) {
    int to[2], from[2];
    if (::pipe(to) != 0 || ::pipe(from) != 0) {
      std::fprintf(stderr, "bench-handoff: pipe: %s\n", std::strerror(errno));
      return nullptr;
    }
    std::fflush(nullptr);
    const pid_t pid = ::fork();
    if (pid < 0) {
      std::fprintf(stderr, "bench-handoff: fork: %s\n", std::strerror(errno));
      return nullptr;
    }
    if (pid == 0) {
      ::close(to[1]);
      ::close(from[0]);
      ::_exit(run_child(o, hello, to[0], from[1]));
    }
    ::close(to[0]);
    ::close(from[1]);
    return std::unique_ptr<client_process>(new client_process(pid, to[1], from[0]));
  }
  ~client_process() {
    ::close(to_);
    ::close(from_);
    if (pid_ > 0) {
      ::kill(pid_, SIGKILL);
      ::waitpid(pid_, nullptr, 0);
    }
  }
  /// The child connects to `port` now.
  void connect_to(std::uint16_t port) { (void)!::write(to_, &port, sizeof port); }
  /// False once the child has ended (a connect failed: its reason is on stderr).
  bool alive() {
    if (pid_ > 0 && ::waitpid(pid_, nullptr, WNOHANG) == pid_) pid_ = -1;
    return pid_ > 0;
  }
  /// Tells the child the server wrote `expect` bytes; once it has read them (or after 10 s) it
  /// stops and reports. False when it ended without a report.
  bool finish(std::uint64_t expect, double& reader_cpu_s, std::uint64_t& bytes_read) {
    (void)!::write(to_, &expect, sizeof expect);
    double report[2] = {0, 0};
    const bool ok = ::read(from_, report, sizeof report) == static_cast<ssize_t>(sizeof report);
    if (pid_ > 0) ::waitpid(pid_, nullptr, 0);
    pid_ = -1;
    reader_cpu_s = report[0];
    bytes_read = static_cast<std::uint64_t>(report[1]);
    return ok;
  }

 private:
  client_process(pid_t pid, int to, int from) : pid_(pid), to_(to), from_(from) {}
  static int run_child(const options& o, const std::vector<std::uint8_t>& hello, int in, int out) {
    std::uint16_t port = 0;
    if (::read(in, &port, sizeof port) != static_cast<ssize_t>(sizeof port)) return 1;
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(port);
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    std::vector<int> fds;
    for (std::size_t i = 0; i < o.sessions; ++i) {
      const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
      if (fd < 0 || ::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
        std::fprintf(stderr, "bench-handoff: connect %zu failed: %s (ulimit -n?)\n", i, std::strerror(errno));
        return 1;
      }
      if (!hello.empty() && ::write(fd, hello.data(), hello.size()) != static_cast<ssize_t>(hello.size())) {
        std::fprintf(stderr, "bench-handoff: hello %zu not written: %s\n", i, std::strerror(errno));
        return 1;
      }
      fds.push_back(fd);
    }
    double report[2] = {0, 0};
    {
      reader_pool readers(fds, o.readers, o.reader_cpus);
      std::uint64_t expect = 0;
      while (::read(in, &expect, sizeof expect) < 0 && errno == EINTR) {}
      const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(10);
      while (readers.bytes.load() < expect && std::chrono::steady_clock::now() < until)
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
      report[0] = readers.finish();
      report[1] = static_cast<double>(readers.bytes.load());
    }
    (void)!::write(out, report, sizeof report);
    return 0;
  }
  pid_t pid_;
  int to_, from_;
};

// --csv FILE: one line for the run appended (the header first when the file is new or empty);
// the same columns in every mode (a mode's missing figures empty). False when it cannot write.
struct csv_row {
  std::string mode, writes;
  double frame_bytes = 0, frames = 0, dropped = 0, senders_us = -1, io_us = 0, server_us = 0, readers_us = 0,
         wall_p50_ms = 0, wall_p99_ms = 0;
};
bool append_csv(const options& o, const csv_row& r) {
  if (o.csv.empty()) return true;
  std::FILE* f = std::fopen(o.csv.c_str(), "a");
  if (f == nullptr) {
    std::fprintf(stderr, "bench-handoff: cannot write %s: %s\n", o.csv.c_str(), std::strerror(errno));
    return false;
  }
  if (std::ftell(f) == 0) {
    std::fprintf(f,
                 "mode,writes,sessions,ticks,rate_hz,io_threads,senders,readers,io_cpus,reader_cpus,frame_bytes,frames,"
                 "dropped_or_failed,senders_us_per_frame,io_us_per_frame,server_us_per_frame,readers_us_per_frame,"
                 "wall_p50_ms,wall_p99_ms\n");
  }
  char senders_us[32] = "";
  if (r.senders_us >= 0) std::snprintf(senders_us, sizeof senders_us, "%.3f", r.senders_us);
  const std::string senders = r.mode == "floor" ? "" : std::to_string(o.senders);
  std::fprintf(f, "%s,%s,%zu,%zu,%g,%u,%s,%u,\"%s\",\"%s\",%.0f,%.0f,%.0f,%s,%.3f,%.3f,%.3f,%.3f,%.3f\n",
               r.mode.c_str(), r.writes.c_str(), o.sessions, o.ticks, o.rate_hz, o.io_threads, senders.c_str(),
               o.readers, format_cpu_list(o.io_cpus).c_str(), format_cpu_list(o.reader_cpus).c_str(), r.frame_bytes,
               r.frames, r.dropped, senders_us, r.io_us, r.server_us, r.readers_us, r.wall_p50_ms, r.wall_p99_ms);
  return std::fclose(f) == 0;
}

std::string rate_text(double hz) {
  if (hz <= 0) return "back to back";
  char b[32];
  std::snprintf(b, sizeof b, "at %g Hz", hz);
  return b;
}

// --mode floor (the header): returns the exit status.
int run_floor(const options& o, bool uring) {
#if !ZONE_HAVE_LIBURING
  if (uring) {
    std::fprintf(stderr, "bench-handoff: --mode floor --write-batching io_uring: built without liburing\n");
    return 1;
  }
#endif
  auto clients = client_process::fork_clients(o, {});  // while this is the only thread
  if (!clients) return 1;
  const int lfd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  socklen_t len = sizeof addr;
  if (lfd < 0 || ::fcntl(lfd, F_SETFL, O_NONBLOCK) != 0 ||
      ::bind(lfd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0 || ::listen(lfd, 4096) != 0 ||
      ::getsockname(lfd, reinterpret_cast<sockaddr*>(&addr), &len) != 0) {
    std::fprintf(stderr, "bench-handoff: listen on 127.0.0.1: %s\n", std::strerror(errno));
    return 1;
  }
  clients->connect_to(ntohs(addr.sin_port));
  // The accepted side is the server's: nonblocking with TCP_NODELAY, as net::server's sessions.
  std::vector<int> conns;
  const auto accept_deadline = std::chrono::steady_clock::now() + std::chrono::seconds(120);
  while (conns.size() < o.sessions) {
    pollfd pf{lfd, POLLIN, 0};
    if (std::chrono::steady_clock::now() > accept_deadline || ::poll(&pf, 1, 1000) < 0 || !clients->alive()) {
      std::fprintf(stderr, "bench-handoff: only %zu of %zu connections accepted\n", conns.size(), o.sessions);
      return 1;
    }
    for (;;) {
      const int c = ::accept4(lfd, nullptr, nullptr, SOCK_NONBLOCK);
      if (c < 0) break;
      const int one = 1;
      ::setsockopt(c, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
      conns.push_back(c);
    }
  }
  ::close(lfd);

  std::vector<char> frame(o.frame_bytes, 'x');
  const unsigned writers = std::max(1u, o.io_threads);
  std::vector<double> cpu(writers, 0);
  std::vector<std::uint64_t> written(writers, 0), short_writes(writers, 0), failed(writers, 0), bytes(writers, 0);
  std::vector<double> tick_wall_ms;
  std::atomic<bool> setup_failed{false};
  // Each tick the main thread lets every writer write its share (start_line), waits for the last
  // (finish_line): the tick's write wall time, then sleeps until the next tick is due.
  std::barrier start_line(static_cast<std::ptrdiff_t>(writers) + 1);
  std::barrier finish_line(static_cast<std::ptrdiff_t>(writers) + 1);
  std::vector<std::thread> threads;
  for (unsigned k = 0; k < writers; ++k) {
    threads.emplace_back([&, k] {
      ::pthread_setname_np(::pthread_self(), "floor-writer");
      if (!o.io_cpus.empty()) (void)pin_current_thread(o.io_cpus);
      std::vector<int> mine;
      for (std::size_t i = k; i < conns.size(); i += writers) mine.push_back(conns[i]);
#if ZONE_HAVE_LIBURING
      io_uring ring{};
      constexpr unsigned batch = 256;  // sends a submission, the zone server's ring size
      if (uring && !mine.empty()) {
        io_uring_params p{};
        p.flags = IORING_SETUP_SUBMIT_ALL | IORING_SETUP_COOP_TASKRUN;
        if (io_uring_queue_init_params(batch, &ring, &p) < 0 ||
            io_uring_register_files(&ring, mine.data(), static_cast<unsigned>(mine.size())) < 0)
          setup_failed = true;
      }
#endif
      const double c0 = thread_cpu_s();
      for (std::size_t t = 0; t < o.ticks; ++t) {
        start_line.arrive_and_wait();
        if (setup_failed) {
          finish_line.arrive_and_wait();
          continue;
        }
        if (!uring || mine.empty()) {
          for (const int fd : mine) {
            const ssize_t r = ::send(fd, frame.data(), frame.size(), MSG_DONTWAIT | MSG_NOSIGNAL);
            if (r > 0) bytes[k] += static_cast<std::uint64_t>(r);
            if (r == static_cast<ssize_t>(frame.size()))
              ++written[k];
            else if (r > 0)
              ++short_writes[k];
            else
              ++failed[k];
          }
        }
#if ZONE_HAVE_LIBURING
        else {
          for (std::size_t b = 0; b < mine.size(); b += batch) {
            const auto n = static_cast<unsigned>(std::min<std::size_t>(batch, mine.size() - b));
            for (unsigned j = 0; j < n; ++j) {
              io_uring_sqe* sqe = io_uring_get_sqe(&ring);
              io_uring_prep_send(sqe, static_cast<int>(b + j), frame.data(), frame.size(), MSG_DONTWAIT | MSG_NOSIGNAL);
              sqe->flags |= IOSQE_FIXED_FILE;
            }
            io_uring_submit_and_wait(&ring, n);
            unsigned seen = 0;
            while (seen < n) {
              io_uring_cqe* cqe = nullptr;
              if (io_uring_wait_cqe(&ring, &cqe) != 0) {
                failed[k] += n - seen;  // never answered: counted as failed
                break;
              }
              if (cqe->res > 0) bytes[k] += static_cast<std::uint64_t>(cqe->res);
              if (cqe->res == static_cast<int>(frame.size()))
                ++written[k];
              else if (cqe->res > 0)
                ++short_writes[k];
              else
                ++failed[k];
              io_uring_cqe_seen(&ring, cqe);
              ++seen;
            }
          }
        }
#endif
        finish_line.arrive_and_wait();
      }
      cpu[k] = thread_cpu_s() - c0;
#if ZONE_HAVE_LIBURING
      if (uring && !mine.empty()) io_uring_queue_exit(&ring);
#endif
    });
  }
  const auto period = o.rate_hz > 0 ? std::chrono::duration<double>(1.0 / o.rate_hz) : std::chrono::duration<double>(0);
  std::fprintf(stderr, "bench-handoff: %zu connections, writing\n", conns.size());  // a profiler's cue
  const auto w0 = std::chrono::steady_clock::now();
  auto next = w0;
  for (std::size_t t = 0; t < o.ticks; ++t) {
    const auto t0 = std::chrono::steady_clock::now();
    start_line.arrive_and_wait();
    finish_line.arrive_and_wait();
    tick_wall_ms.push_back(std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
    if (o.rate_hz > 0) {
      next += std::chrono::duration_cast<std::chrono::steady_clock::duration>(period);
      std::this_thread::sleep_until(next);
    }
  }
  for (auto& th : threads) th.join();
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - w0).count();
  std::uint64_t bytes_written = 0;
  for (const auto b : bytes) bytes_written += b;
  double reader_cpu = 0;
  std::uint64_t bytes_read = 0;
  if (!clients->finish(bytes_written, reader_cpu, bytes_read)) {
    std::fprintf(stderr, "bench-handoff: the readers' process ended without its report\n");
    return 1;
  }
  if (setup_failed) {
    std::fprintf(stderr, "bench-handoff: io_uring setup failed (io_uring_queue_init or register_files)\n");
    return 1;
  }
  std::uint64_t frames = 0, shorts = 0, fails = 0;
  double writer_cpu = 0;
  for (unsigned k = 0; k < writers; ++k) {
    frames += written[k];
    shorts += short_writes[k];
    fails += failed[k];
    writer_cpu += cpu[k];
  }
  std::printf(
      "bench-handoff --mode floor: %zu sockets, %zu ticks %s, %u writer threads%s, %u readers%s, %zu-byte frames, %s\n",
      o.sessions, o.ticks, rate_text(o.rate_hz).c_str(), writers,
      o.io_cpus.empty() ? "" : (" on CPUs " + format_cpu_list(o.io_cpus)).c_str(), o.readers,
      o.reader_cpus.empty() ? "" : (" on CPUs " + format_cpu_list(o.reader_cpus)).c_str(), o.frame_bytes,
      uring ? "io_uring submissions of 256 sends (registered files)" : "one send() a frame");
  std::printf(
      "| frames written | short writes | failed (EAGAIN, errors) | bytes written | bytes read | wall s | writers' CPU per frame | readers' CPU per frame | write wall per tick p50 / p99 |\n");
  std::printf("|---|---|---|---|---|---|---|---|---|\n");
  const double f = std::max<double>(1, static_cast<double>(frames));
  std::printf("| %llu | %llu | %llu | %llu | %llu | %.2f | %.2f us | %.2f us | %.3f / %.3f ms |\n",
              static_cast<unsigned long long>(frames), static_cast<unsigned long long>(shorts),
              static_cast<unsigned long long>(fails), static_cast<unsigned long long>(bytes_written),
              static_cast<unsigned long long>(bytes_read), wall, writer_cpu / f * 1e6, reader_cpu / f * 1e6,
              quantile(tick_wall_ms, 0.5), quantile(tick_wall_ms, 0.99));
  for (const int fd : conns) ::close(fd);
  csv_row row;
  row.mode = "floor";
  row.writes = uring ? "io_uring" : "send";
  row.frame_bytes = static_cast<double>(o.frame_bytes);
  row.frames = static_cast<double>(frames);
  row.dropped = static_cast<double>(shorts + fails);
  row.io_us = row.server_us = writer_cpu / f * 1e6;
  row.readers_us = reader_cpu / f * 1e6;
  row.wall_p50_ms = quantile(tick_wall_ms, 0.5);
  row.wall_p99_ms = quantile(tick_wall_ms, 0.99);
  return append_csv(o, row) ? 0 : 1;
}

}  // namespace

int main(int argc, char** argv) {
  const std::string usage =
      "usage: bench-handoff [--sessions 1000] [--ticks 300] [--senders 2] [--io-threads 2] "
      "[--frame-bytes 600] [--rate 30 (0: back to back)] [--max-backlog 2 (0: off)]\n"
      "                     [--mode many|send|floor (default many: frame_arena + send_many, the zone server's "
      "way; send: make_shared_frame + send per frame; floor: no server, --io-threads threads writing a frame "
      "to each socket with one send() each, or io_uring batches with --write-batching io_uring: the kernel's "
      "share alone)] [--chunk 16 (sessions per send_many; the zone server hands over chunks of clients_per_task, 64)]\n"
      "                     [--direct-writes 0|1 (default 0: the I/O threads write)]\n"
      "                     [--write-batching auto|io_uring|sendmsg (default auto: io_uring where the "
      "kernel allows it)]\n"
      "                     [--write-slice 256 (sessions an I/O thread writes before it reads again)]\n"
      "                     [--readers 1 (threads draining the clients)] [--io-cpus LIST] [--reader-cpus LIST] "
      "[--sender-cpus LIST] (CPU lists as 0-5,8: pin the I/O threads or floor's writers, the readers, the senders)\n"
      "                     [--csv FILE (one line for the run appended, a header first in a new file)]\n";
  options o;
  std::string mode = "many", batching = "auto", io_cpus, reader_cpus, sender_cpus;
  int direct_writes = 0;
  namespace po = zone::tools::po;
  po::options_description cli;
  cli.add_options()("sessions", po::value(&o.sessions))("ticks", po::value(&o.ticks))("senders", po::value(&o.senders))(
      "io-threads", po::value(&o.io_threads))("frame-bytes", po::value(&o.frame_bytes))("rate", po::value(&o.rate_hz))(
      "max-backlog", po::value(&o.max_backlog))("chunk", po::value(&o.chunk))(
      "direct-writes", po::value(&direct_writes))("write-batching", po::value(&batching))(
      "write-slice", po::value(&o.write_slice))("mode", po::value(&mode))("readers", po::value(&o.readers))(
      "io-cpus", po::value(&io_cpus))("reader-cpus", po::value(&reader_cpus))("sender-cpus", po::value(&sender_cpus))(
      "csv", po::value(&o.csv));
  if (const auto rc = zone::tools::parse_command_line(argc, argv, "bench-handoff", usage, cli, 64)) return *rc;
  const auto b = parse_write_batching(batching);
  std::string cpu_error;
  const auto io_list = parse_cpu_list(io_cpus, &cpu_error);
  const auto reader_list = io_list ? parse_cpu_list(reader_cpus, &cpu_error) : std::nullopt;
  const auto sender_list = reader_list ? parse_cpu_list(sender_cpus, &cpu_error) : std::nullopt;
  if (!b || (mode != "many" && mode != "send" && mode != "floor") || (direct_writes != 0 && direct_writes != 1) ||
      o.sessions == 0 || o.senders == 0 || o.frame_bytes < 64 || o.chunk == 0 || o.write_slice == 0 || o.readers == 0 ||
      !io_list || !reader_list || !sender_list) {
    std::fprintf(stderr,
                 "bench-handoff: bad value (--mode many|send|floor, --write-batching auto|io_uring|sendmsg, "
                 "--direct-writes 0|1, --sessions, --senders, --chunk, --write-slice and --readers > 0, "
                 "--frame-bytes >= 64, CPU lists as 0-5,8%s%s)\n%s",
                 cpu_error.empty() ? "" : ": ", cpu_error.c_str(), usage.c_str());
    return 64;
  }
  o.io_cpus = *io_list;
  o.reader_cpus = *reader_list;
  o.sender_cpus = *sender_list;
  for (const auto* list : {&o.io_cpus, &o.reader_cpus, &o.sender_cpus}) {
    if (const auto why = check_cpus_allowed(*list)) {
      std::fprintf(stderr, "bench-handoff: a CPU list %s\n", why->c_str());
      return 64;
    }
  }
  if (!o.csv.empty()) {  // a path it cannot write is refused now, not after the run
    std::FILE* f = std::fopen(o.csv.c_str(), "a");
    if (f == nullptr) {
      std::fprintf(stderr, "bench-handoff: cannot write %s: %s\n", o.csv.c_str(), std::strerror(errno));
      return 64;
    }
    std::fclose(f);
  }
  // Every socket is a descriptor: the limit raised once, before the clients' process is forked
  // (it inherits it).
  (void)raise_open_file_limit();
  if (mode == "floor") return run_floor(o, *b == write_batching::uring);
  o.batching = *b;
  o.many = mode == "many";
  o.direct_writes = direct_writes == 1;
  spdlog::set_level(spdlog::level::warn);
  server_options so;
  so.io_threads = o.io_threads;
  so.direct_writes = o.direct_writes;
  so.batching = o.batching;
  so.write_slice = o.write_slice;
  so.io_thread_cpus = o.io_cpus;
  so.max_connections = o.sessions + 16;
  so.max_pending = so.max_pending_per_address = o.sessions + 16;  // every client connects at once from loopback
  so.idle_timeout = std::chrono::hours(1);
  // Clients: plain sockets in a child process, one hello each (the session exists from the
  // connection on), forked before the server's threads start.
  const auto hello = encode_frame(hello_msg{"bench", "", protocol_version});
  auto clients = client_process::fork_clients(o, std::vector<std::uint8_t>(hello.begin(), hello.end()));
  if (!clients) return 1;
  server srv(so);
  if (auto err = srv.start()) {
    std::fprintf(stderr, "bench-handoff: %s\n", err->c_str());
    return 1;
  }
  clients->connect_to(srv.port());
  std::vector<session_id> sessions;
  std::vector<std::shared_ptr<const std::atomic<std::uint32_t>>> backlogs;
  std::vector<inbound_event> events;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(120);
  while (sessions.size() < o.sessions && std::chrono::steady_clock::now() < deadline && clients->alive()) {
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
  std::fprintf(stderr, "bench-handoff: %zu sessions, writing\n", sessions.size());  // a profiler's cue
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
        if (!o.sender_cpus.empty()) (void)pin_current_thread(o.sender_cpus);
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
  const auto s1 = srv.stats();
  double reader_cpu = 0;
  std::uint64_t bytes_read = 0;
  if (!clients->finish(s1.bytes_out, reader_cpu, bytes_read)) {
    std::fprintf(stderr, "bench-handoff: the clients' process ended without its report\n");
    return 1;
  }
  if (bytes_read != s1.bytes_out) {
    std::fprintf(stderr, "bench-handoff: the clients read %llu of the %llu bytes written\n",
                 static_cast<unsigned long long>(bytes_read), static_cast<unsigned long long>(s1.bytes_out));
  }
  // Server CPU: the whole process (the main thread sleeps; its polling is noise); the readers are
  // the child's.
  const double server_cpu = p1 - p0;
  const double frames = static_cast<double>(sent.load());

  std::printf(
      "bench-handoff: %zu sessions, %zu ticks %s, %u senders, %u I/O threads, %zu-byte frames, pacing %u, %s, %s, %s\n",
      o.sessions, o.ticks, rate_text(o.rate_hz).c_str(), o.senders, o.io_threads, payload.size(), o.max_backlog,
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
  csv_row row;
  row.mode = o.many ? "many" : "send";
  row.writes = srv.uses_io_uring() ? "io_uring" : "sendmsg";
  row.frame_bytes = static_cast<double>(payload.size());
  row.frames = frames;
  row.dropped = static_cast<double>(s1.frames_dropped - s0.frames_dropped);
  row.senders_us = senders_cpu_total / frames * 1e6;
  row.io_us = (server_cpu - senders_cpu_total) / frames * 1e6;
  row.server_us = server_cpu / frames * 1e6;
  row.readers_us = reader_cpu / frames * 1e6;
  row.wall_p50_ms = quantile(tick_wall_ms, 0.5);
  row.wall_p99_ms = quantile(tick_wall_ms, 0.99);
  return append_csv(o, row) ? 0 : 1;
}
