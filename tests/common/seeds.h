// Fresh random seeds for the test suites: every run tests new random inputs; each test CAPTUREs
// the seed it used, so a failure prints what reproduces it.
#pragma once

#include <cstdint>
#include <random>

namespace zone::test {

/// A new 64-bit seed per call, from a per-process random base.
inline std::uint64_t fresh_seed() {
  static const std::uint64_t base = std::random_device{}() ^ (std::uint64_t{std::random_device{}()} << 32);
  static std::uint64_t k = 0;
  return base + 0x9e3779b97f4a7c15ull * ++k;
}

}  // namespace zone::test
