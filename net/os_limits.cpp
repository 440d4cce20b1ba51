// net/os_limits.h: the open-file limit; CPU lists and pinning.
#include "os_limits.h"

#include <dirent.h>
#include <fcntl.h>
#include <pthread.h>
#include <sched.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <climits>
#include <cstdio>
#include <cstring>
#include <iterator>
#include <string_view>

namespace zone::net {

open_file_limit raise_open_file_limit() {
  open_file_limit out;
  rlimit rl{};
  if (::getrlimit(RLIMIT_NOFILE, &rl) != 0) {
    out.error = std::string("getrlimit(RLIMIT_NOFILE): ") + std::strerror(errno);
    return out;
  }
  out.before = rl.rlim_cur;
  if (rl.rlim_cur < rl.rlim_max) {
    rlimit raised = rl;
    raised.rlim_cur = rl.rlim_max;
    if (::setrlimit(RLIMIT_NOFILE, &raised) == 0) {
      rl = raised;
    } else {
      out.error = std::string("setrlimit(RLIMIT_NOFILE): ") + std::strerror(errno);
    }
  }
  out.soft = rl.rlim_cur;
  out.hard = rl.rlim_max;
  return out;
}

namespace {

// The entries of a /proc folder that are numbers (descriptors, thread ids); -1 when it cannot be read.
long count_numbered(const char* dir, std::vector<int>* ids) {
  DIR* d = ::opendir(dir);
  if (d == nullptr) return -1;
  long n = 0;
  while (const dirent* e = ::readdir(d)) {
    int v = 0;
    const char* end = e->d_name + std::strlen(e->d_name);
    if (e->d_name[0] == '\0' || std::from_chars(e->d_name, end, v).ptr != end) continue;
    ++n;
    if (ids != nullptr) ids->push_back(v);
  }
  ::closedir(d);
  return n;
}

// A /proc/<pid>/task/<tid>/stat line: its comm (between the first '(' and the last ')': a name may
// hold either) and utime + stime (fields 14 and 15) in clock ticks.
bool parse_stat(std::string_view line, std::string& name, unsigned long long& ticks) {
  const auto open = line.find('('), close = line.rfind(')');
  if (open == std::string_view::npos || close == std::string_view::npos || close < open) return false;
  name.assign(line.substr(open + 1, close - open - 1));
  std::size_t at = close + 1;
  unsigned long long utime = 0, stime = 0;
  for (int field = 3; field <= 15; ++field) {  // field 3 (the state) is the first after the comm
    while (at < line.size() && line[at] == ' ') ++at;
    const std::size_t end = line.find(' ', at);
    if (at >= line.size() || end == std::string_view::npos) return false;
    if (field == 14 || field == 15) {
      unsigned long long v = 0;
      if (std::from_chars(line.data() + at, line.data() + end, v).ptr != line.data() + end) return false;
      (field == 14 ? utime : stime) = v;
    }
    at = end;
  }
  ticks = utime + stime;
  return true;
}

// A small /proc file's text (the first `buf` bytes); empty when it cannot be read.
std::string_view read_small(const char* path, char* buf, std::size_t size) {
  const int fd = ::open(path, O_RDONLY | O_CLOEXEC);
  if (fd < 0) return {};
  const ssize_t n = ::read(fd, buf, size);
  ::close(fd);
  return n > 0 ? std::string_view(buf, static_cast<std::size_t>(n)) : std::string_view();
}

}  // namespace

process_usage read_process_usage(bool with_threads) {
  process_usage u;
  rusage r{};
  if (::getrusage(RUSAGE_SELF, &r) == 0) {
    u.cpu_seconds = static_cast<double>(r.ru_utime.tv_sec + r.ru_stime.tv_sec) +
                    static_cast<double>(r.ru_utime.tv_usec + r.ru_stime.tv_usec) * 1e-6;
  } else {
    u.error += "getrusage; ";
  }
  // statm: the sizes in pages, the whole program's first and the resident set's second.
  char buf[1024];
  const std::string_view statm = read_small("/proc/self/statm", buf, sizeof buf);
  const std::size_t second = statm.find(' ');
  unsigned long long resident = 0;
  if (second != std::string_view::npos &&
      std::from_chars(statm.data() + second + 1, statm.data() + statm.size(), resident).ec == std::errc()) {
    u.resident_bytes = resident * static_cast<std::uint64_t>(::sysconf(_SC_PAGESIZE));
  } else {
    u.error += "/proc/self/statm; ";
  }
  // The descriptor opendir holds is counted too: one less.
  if (const long n = count_numbered("/proc/self/fd", nullptr); n > 0) {
    u.open_fds = static_cast<std::uint64_t>(n - 1);
  } else {
    u.error += "/proc/self/fd; ";
  }
  rlimit rl{};
  if (::getrlimit(RLIMIT_NOFILE, &rl) == 0) u.max_fds = rl.rlim_cur;
  if (with_threads) {
    std::vector<int> tids;
    if (count_numbered("/proc/self/task", &tids) < 0) u.error += "/proc/self/task; ";
    const double tick = static_cast<double>(::sysconf(_SC_CLK_TCK));
    char path[64];
    for (const int tid : tids) {
      std::snprintf(path, sizeof path, "/proc/self/task/%d/stat", tid);
      std::string name;
      unsigned long long ticks = 0;
      // A thread that ended since the listing has no file: left out.
      if (parse_stat(read_small(path, buf, sizeof buf), name, ticks)) {
        u.threads.push_back({tid, std::move(name), static_cast<double>(ticks) / tick});
      }
    }
  }
  if (!u.error.empty()) u.error.resize(u.error.size() - 2);
  return u;
}

int current_thread_id() { return static_cast<int>(::syscall(SYS_gettid)); }

namespace {

bool parse_cpu(std::string_view t, int& out) {
  unsigned v = 0;  // unsigned: no sign accepted ("-0", "+1")
  if (t.empty()) return false;
  const auto r = std::from_chars(t.data(), t.data() + t.size(), v);
  if (r.ec != std::errc() || r.ptr != t.data() + t.size() || v > static_cast<unsigned>(INT_MAX)) return false;
  out = static_cast<int>(v);
  return true;
}

}  // namespace

std::optional<std::vector<int>> parse_cpu_list(std::string_view text, std::string* error) {
  const auto fail = [&](const std::string& why) -> std::optional<std::vector<int>> {
    if (error) *error = "bad CPU list '" + std::string(text) + "': " + why;
    return std::nullopt;
  };
  std::vector<int> cpus;
  if (text.empty()) return cpus;
  std::size_t at = 0;
  while (at <= text.size()) {
    const std::size_t comma = std::min(text.find(',', at), text.size());
    const std::string_view item = text.substr(at, comma - at);
    const std::size_t dash = item.find('-');
    int lo = 0, hi = 0;
    if (!parse_cpu(item.substr(0, dash), lo) ||
        (dash != std::string_view::npos && !parse_cpu(item.substr(dash + 1), hi))) {
      std::string why(1, '\'');  // built by appends: GCC 12 warns falsely (-Wrestrict) on "'" + string
      why.append(item).append("' is not a CPU number or a range a-b");
      return fail(why);
    }
    if (dash == std::string_view::npos) hi = lo;
    if (lo > hi) return fail("the range " + std::string(item) + " runs backwards");
    if (hi >= CPU_SETSIZE)
      return fail("CPU " + std::to_string(hi) + " is past the largest, " + std::to_string(CPU_SETSIZE - 1));
    for (int c = lo; c <= hi; ++c) cpus.push_back(c);
    at = comma + 1;
  }
  std::sort(cpus.begin(), cpus.end());
  cpus.erase(std::unique(cpus.begin(), cpus.end()), cpus.end());
  return cpus;
}

std::vector<int> allowed_cpus() {
  std::vector<int> out;
  cpu_set_t set;
  CPU_ZERO(&set);
  if (::sched_getaffinity(0, sizeof set, &set) != 0) return out;
  for (int c = 0; c < CPU_SETSIZE; ++c) {
    if (CPU_ISSET(c, &set)) out.push_back(c);
  }
  return out;
}

std::optional<std::string> check_cpus_allowed(const std::vector<int>& cpus) {
  const std::vector<int> allowed = allowed_cpus();
  std::vector<int> wanted = cpus, missing;  // any order, repeats allowed (an embedder's list)
  std::sort(wanted.begin(), wanted.end());
  wanted.erase(std::unique(wanted.begin(), wanted.end()), wanted.end());
  std::set_difference(wanted.begin(), wanted.end(), allowed.begin(), allowed.end(), std::back_inserter(missing));
  if (missing.empty()) return std::nullopt;
  return "names CPU " + format_cpu_list(missing) +
         ", which this process may not run on (allowed: " + format_cpu_list(allowed) + ")";
}

std::string format_cpu_list(const std::vector<int>& cpus) {
  std::string out;
  for (std::size_t i = 0; i < cpus.size();) {
    std::size_t j = i;
    while (j + 1 < cpus.size() && cpus[j + 1] == cpus[j] + 1) ++j;
    if (!out.empty()) out += ',';
    out += std::to_string(cpus[i]);
    if (j > i) out += '-' + std::to_string(cpus[j]);
    i = j + 1;
  }
  return out;
}

std::optional<std::string> pin_current_thread(const std::vector<int>& cpus) {
  if (cpus.empty()) return std::nullopt;
  cpu_set_t set;
  CPU_ZERO(&set);
  for (const int c : cpus) {
    if (c < 0 || c >= CPU_SETSIZE)
      return "CPU " + std::to_string(c) + " is not a CPU number (0 .. " + std::to_string(CPU_SETSIZE - 1) + ")";
    CPU_SET(c, &set);
  }
  const int r = ::pthread_setaffinity_np(::pthread_self(), sizeof set, &set);
  if (r != 0) return "pthread_setaffinity_np(" + format_cpu_list(cpus) + "): " + std::strerror(r);
  return std::nullopt;
}

}  // namespace zone::net
