// net/os_limits.h: the open-file limit; CPU lists and pinning.
#include "os_limits.h"

#include <pthread.h>
#include <sched.h>
#include <sys/resource.h>

#include <algorithm>
#include <cerrno>
#include <charconv>
#include <climits>
#include <cstring>
#include <iterator>

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
