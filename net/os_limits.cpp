// net/os_limits.h: the open-file limit.
#include "os_limits.h"

#include <sys/resource.h>

#include <cerrno>
#include <cstring>

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

}  // namespace zone::net
