#include "token.h"

#include <cstdio>
#include <random>

namespace zone {

std::optional<std::uint64_t> parse_token(std::string_view token) {
  if (token.size() != 16) return std::nullopt;
  std::uint64_t v = 0;
  for (const char c : token) {
    const int d = c >= '0' && c <= '9'   ? c - '0'
                  : c >= 'a' && c <= 'f' ? c - 'a' + 10
                  : c >= 'A' && c <= 'F' ? c - 'A' + 10
                                         : -1;
    if (d < 0) return std::nullopt;
    v = v << 4 | static_cast<std::uint64_t>(d);
  }
  if (v == 0) return std::nullopt;
  return v;
}

std::string hex16(std::uint64_t v) {
  char b[17];
  std::snprintf(b, sizeof b, "%016llx", static_cast<unsigned long long>(v));
  return b;
}

std::uint64_t os_random_u64() {
  std::random_device os;
  return std::uint64_t{os()} << 32 | os();
}

}  // namespace zone
