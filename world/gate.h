// The choice of world-gate (docs/world.md, "Logging in through a gate"): which zone a client that
// logs in goes to, from the regions' leases and the loads their zones tell beside them.
#pragma once

#include <cstdint>
#include <map>
#include <optional>
#include <utility>
#include <vector>

#include "nats_node.h"

namespace zone::world {

/// The region (and its lease) the `n`-th login goes to, among those whose lease names an address
/// (a zone that listens: incarnation and port set; not "claiming", not port 0 while its server
/// starts): the least loaded, its load being the players its zone last told (lease_info::players;
/// 0 when it told none) plus `sent[region]`, the logins sent there since; a zone whose load has
/// reached its player slots is skipped. Ties go round robin from `n`. Nothing when no zone serves
/// the world or every one is full.
[[nodiscard]] inline std::optional<std::pair<std::uint32_t, lease_info>> gate_pick(
    const std::map<std::uint32_t, lease_info>& leases, std::uint64_t n,
    const std::map<std::uint32_t, std::uint64_t>& sent = {}) {
  std::vector<std::pair<std::uint32_t, const lease_info*>> serving;
  for (const auto& [region, l] : leases) {
    if (l.incarnation != 0 && l.port != 0) serving.emplace_back(region, &l);
  }
  if (serving.empty()) return std::nullopt;
  std::optional<std::size_t> best;
  std::int64_t best_load = 0;
  for (std::size_t i = 0; i < serving.size(); ++i) {
    const std::size_t k = (n + i) % serving.size();
    const auto& [region, l] = serving[k];
    const auto s = sent.find(region);
    const std::int64_t load =
        std::max<std::int64_t>(0, l->players) + (s == sent.end() ? 0 : static_cast<std::int64_t>(s->second));
    if (l->players >= 0 && l->slots > 0 && load >= l->slots) continue;  // full
    if (!best || load < best_load) best = k, best_load = load;
  }
  if (!best) return std::nullopt;
  return std::pair{serving[*best].first, *serving[*best].second};
}

}  // namespace zone::world
