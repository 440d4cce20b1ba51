// tests/common/device_or_skip.h: a GPU suite without a usable CUDA device exits with 77 (CTest:
// Skipped, never Passed) before doctest runs any case.
#pragma once

#include <cstdio>
#include <cstdlib>
#include <string>

#include "gpu/device.h"

namespace zone::test {

/// For a static initialiser of each GPU suite's source: returns true with a device; otherwise says
/// why on stdout, naming `suite`, and ends the process with 77.
inline bool device_or_skip(const char* suite) {
  std::string why;
  if (!zone::gpu::device_available(nullptr, &why)) {
    std::printf("%s: skipped, no CUDA device: %s\n", suite, why.c_str());
    std::fflush(stdout);
    std::_Exit(77);
  }
  return true;
}

}  // namespace zone::test
