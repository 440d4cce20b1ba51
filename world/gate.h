// The choice of world-gate (docs/world.md, "Logging in through a gate"): which zone a client that
// logs in goes to, from the regions' leases.
#pragma once

#include <cstdint>
#include <map>
#include <optional>

#include "nats_node.h"

namespace zone::world {

/// The zone the `n`-th login goes to: round robin over the regions whose lease names an address
/// (a zone that listens: incarnation and port set; not "claiming", not port 0 while its server
/// starts). Nothing when no zone serves the world.
[[nodiscard]] inline std::optional<lease_info> gate_pick(const std::map<std::uint32_t, lease_info>& leases,
                                                         std::uint64_t n) {
  std::size_t serving = 0;
  for (const auto& [region, l] : leases) serving += l.incarnation != 0 && l.port != 0 ? 1 : 0;
  if (serving == 0) return std::nullopt;
  std::uint64_t k = n % serving;
  for (const auto& [region, l] : leases) {
    if (l.incarnation == 0 || l.port == 0) continue;
    if (k-- == 0) return l;
  }
  return std::nullopt;
}

}  // namespace zone::world
