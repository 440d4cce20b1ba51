// tests/common/process.h: child processes for the end-to-end tests (tests/bots, tests/world): the
// real zone-server and bot-swarm executables, each with its output in a file, killed (SIGKILL)
// when the owning object goes away and also when the test process dies (PR_SET_PDEATHSIG), so no
// test leaves a server behind.
#pragma once

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <optional>
#include <regex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

namespace zone::test {

using namespace std::chrono_literals;

inline std::string read_file(const std::string& path) {
  std::ifstream in(path);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

/// A fresh temporary directory for one test's logs and reports.
inline std::string temp_dir() {
  std::string t = "/tmp/zone-bots-test-XXXXXX";
  if (!::mkdtemp(t.data())) return "/tmp";
  return t;
}

class child_process {
 public:
  /// Starts `argv[0]` with the arguments; stdout and stderr go to `log_path`.
  child_process(std::vector<std::string> argv, std::string log_path) : log_(std::move(log_path)) {
    const pid_t parent = ::getpid();
    pid_ = ::fork();
    if (pid_ == 0) {
      ::prctl(PR_SET_PDEATHSIG, SIGKILL);
      if (::getppid() != parent) ::_exit(127);
      const int fd = ::open(log_.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
      if (fd >= 0) {
        ::dup2(fd, 1);
        ::dup2(fd, 2);
        ::close(fd);
      }
      std::vector<char*> args;
      for (auto& a : argv) args.push_back(a.data());
      args.push_back(nullptr);
      ::execv(args[0], args.data());
      ::_exit(127);
    }
  }
  ~child_process() { kill_now(); }
  child_process(const child_process&) = delete;
  child_process& operator=(const child_process&) = delete;

  [[nodiscard]] pid_t pid() const { return pid_; }
  [[nodiscard]] const std::string& log_path() const { return log_; }
  [[nodiscard]] std::string log() const { return read_file(log_); }

  /// Still running?
  bool alive() {
    if (exited_) return false;
    int status = 0;
    if (::waitpid(pid_, &status, WNOHANG) == pid_) {
      record(status);
      return false;
    }
    return true;
  }
  /// Waits up to `timeout` for the exit; the exit code (128 + signal when killed), or nothing.
  std::optional<int> wait(std::chrono::milliseconds timeout) {
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    while (alive()) {
      if (std::chrono::steady_clock::now() >= deadline) return std::nullopt;
      std::this_thread::sleep_for(20ms);
    }
    return code_;
  }
  /// SIGTERM, then wait (SIGKILL after `timeout`).
  std::optional<int> terminate(std::chrono::milliseconds timeout = 10000ms) {
    if (alive()) ::kill(pid_, SIGTERM);
    auto rc = wait(timeout);
    if (!rc) kill_now();
    return rc;
  }
  void kill_now() {
    if (pid_ > 0 && alive()) {
      ::kill(pid_, SIGKILL);
      int status = 0;
      if (::waitpid(pid_, &status, 0) == pid_) record(status);
    }
  }
  /// Resident memory in KiB (/proc), 0 when unknown.
  [[nodiscard]] long rss_kib() const {
    std::ifstream in("/proc/" + std::to_string(pid_) + "/status");
    std::string line;
    while (std::getline(in, line)) {
      if (line.rfind("VmRSS:", 0) == 0) return std::strtol(line.c_str() + 6, nullptr, 10);
    }
    return 0;
  }

  /// Waits until the log matches `pattern`; the first capture group, or nothing after `timeout`.
  std::optional<std::string> wait_for_log(const std::string& pattern, std::chrono::milliseconds timeout) {
    const std::regex re(pattern);
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    while (std::chrono::steady_clock::now() < deadline) {
      std::smatch m;
      const std::string text = log();
      if (std::regex_search(text, m, re)) return m.size() > 1 ? m[1].str() : m[0].str();
      if (!alive()) return std::nullopt;
      std::this_thread::sleep_for(50ms);
    }
    return std::nullopt;
  }

 private:
  void record(int status) {
    exited_ = true;
    code_ = WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
  }
  pid_t pid_ = -1;
  std::string log_;
  bool exited_ = false;
  int code_ = -1;
};

/// The zone server on an ephemeral loopback port (and an ephemeral /metrics port), both read
/// back from its log.
struct zone_server_process {
  child_process proc;
  std::uint16_t port = 0, metrics_port = 0;

  zone_server_process(const std::string& exe, const std::string& dir, std::vector<std::string> extra)
      : proc(
            [&] {
              std::vector<std::string> a{exe, "--listen", "127.0.0.1", "--port", "0", "--metrics-port", "0"};
              a.insert(a.end(), extra.begin(), extra.end());
              return a;
            }(),
            dir + "/zone-server.log") {
    if (auto p = proc.wait_for_log(R"(listening on [0-9.]+:([0-9]+))", 20000ms)) port = static_cast<std::uint16_t>(std::stoi(*p));
    if (auto p = proc.wait_for_log(R"(metrics on http://[0-9.]+:([0-9]+)/metrics)", 5000ms)) {
      metrics_port = static_cast<std::uint16_t>(std::stoi(*p));
    }
  }
  /// The p99 tick time in ms from the server's exit report (after terminate()).
  [[nodiscard]] std::optional<double> p99_tick_ms() const {
    std::smatch m;
    const std::string text = proc.log();
    static const std::regex re(R"(tick\s+p50\s+[0-9.]+ ms\s+p99\s+([0-9.]+) ms)");
    if (std::regex_search(text, m, re)) return std::stod(m[1].str());
    return std::nullopt;
  }
};

/// Scheduler time of a live process's main thread (/proc/PID/schedstat): ms on a CPU, and ms
/// runnable but waiting for one. Nothing where the kernel keeps no schedstat.
struct sched_times {
  double run_ms = 0, wait_ms = 0;
};
inline std::optional<sched_times> sched_times_of(pid_t pid) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/schedstat");
  double run_ns = 0, wait_ns = 0;
  if (!(in >> run_ns >> wait_ns)) return std::nullopt;
  return sched_times{run_ns / 1e6, wait_ns / 1e6};
}

/// How much longer than its CPU time a thread's runnable work took, (run + wait) / run, over its
/// life so far (1 when it never waited for a CPU; about L / cores with L busy threads on the
/// machine). Bounds on how fast zone-server goes (tick time, the rates that follow from its tick
/// rate) are stretched by its main (tick) thread's (never below 1): a machine shared with other
/// work does not fail them, while a quiet one, as CI's, judges them at their documented values.
/// 1 where the kernel keeps no schedstat.
inline double cpu_stretch(const std::optional<sched_times>& t) {
  if (!t || t->run_ms <= 0) return 1;
  return std::max(1.0, (t->run_ms + t->wait_ms) / t->run_ms);
}

/// A TCP connection to loopback `port` whose reads time out after `recv_timeout_s`: its
/// descriptor, or -1.
inline int connect_loopback(std::uint16_t port, int recv_timeout_s = 5) {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  if (fd < 0) return -1;
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(port);
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  timeval tv{recv_timeout_s, 0};
  ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
  if (::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
    ::close(fd);
    return -1;
  }
  return fd;
}

/// GET /metrics over plain sockets; the body, or empty on failure.
inline std::string http_get_metrics(std::uint16_t port) {
  const int fd = connect_loopback(port);
  if (fd < 0) return {};
  std::string out;
  const std::string req = "GET /metrics HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n";
  if (::send(fd, req.data(), req.size(), MSG_NOSIGNAL) == static_cast<ssize_t>(req.size())) {
    char buf[8192];
    for (ssize_t n; (n = ::recv(fd, buf, sizeof buf, 0)) > 0;) out.append(buf, static_cast<std::size_t>(n));
  }
  ::close(fd);
  return out;
}

/// A metric's value from Prometheus text (first sample of that name), or nothing.
inline std::optional<double> metric(const std::string& text, const std::string& name) {
  const std::regex re("(^|\\n)" + name + "(\\{[^}]*\\})? ([-0-9.eE+]+)");
  std::smatch m;
  if (std::regex_search(text, m, re)) return std::stod(m[3].str());
  return std::nullopt;
}

/// A number field of the bot-swarm JSON report (`"name": value`, first occurrence).
inline std::optional<double> json_number(const std::string& text, const std::string& name) {
  const std::regex re("\"" + name + "\": ([-0-9.eE+]+)");
  std::smatch m;
  if (std::regex_search(text, m, re)) return std::stod(m[1].str());
  return std::nullopt;
}

}  // namespace zone::test
