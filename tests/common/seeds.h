// Fresh random seeds for the test suites: every run tests new random inputs; each test CAPTUREs
// the seed it used, so a failure prints what reproduces it: ZONE_TEST_SEED=<that seed> makes every
// call return it (run the one test case with -tc="...").
#pragma once

#include <cstdint>
#include <cstdlib>
#include <random>
#include <string>

namespace zone::test {

/// A new 64-bit seed per call, from a per-process random base (or ZONE_TEST_SEED's).
inline std::uint64_t fresh_seed() {
  if (const char* forced = std::getenv("ZONE_TEST_SEED"); forced != nullptr && *forced != '\0') {
    return std::stoull(forced, nullptr, 0);
  }
  static const std::uint64_t base = std::random_device{}() ^ (std::uint64_t{std::random_device{}()} << 32);
  static std::uint64_t k = 0;
  return base + 0x9e3779b97f4a7c15ull * ++k;
}

}  // namespace zone::test
