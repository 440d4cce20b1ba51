// The choice of world-gate (docs/world.md, "Logging in through a gate"): which zone a client that
// logs in goes to, from the regions' leases and the loads their zones tell beside them.
#pragma once

#include <chrono>
#include <cstdint>
#include <iterator>
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

/// The leases a gate sends clients to: those their zones renewed lately. A zone renews its lease
/// every quarter of the TTL (a new KV revision); one whose revision has not changed for
/// `stale_after` (half the TTL) belongs to a zone that has most likely died (killed: its lease has
/// not lapsed yet), and is left out, so that no login or resume goes to an address nobody answers
/// (a zone whose renewals are only late is back once one goes through).
class lease_watch {
 public:
  using clock = std::chrono::steady_clock;
  /// The leases read at `now`, less those whose revision has not changed for `stale_after` (a
  /// lease seen for the first time counts as changed then; revision 0, unknown, is kept).
  [[nodiscard]] std::map<std::uint32_t, lease_info> fresh(std::map<std::uint32_t, lease_info> leases,
                                                          clock::time_point now, clock::duration stale_after) {
    for (auto it = changed_.begin(); it != changed_.end();) {
      it = leases.contains(it->first) ? std::next(it) : changed_.erase(it);  // lapsed: forgotten
    }
    for (auto it = leases.begin(); it != leases.end();) {
      auto [seen, fresh] = changed_.try_emplace(it->first, it->second.revision, now);
      if (!fresh && seen->second.first != it->second.revision) seen->second = {it->second.revision, now};
      const bool stale = it->second.revision != 0 && now - seen->second.second > stale_after;
      it = stale ? leases.erase(it) : std::next(it);
    }
    return leases;
  }

 private:
  std::map<std::uint32_t, std::pair<std::uint64_t, clock::time_point>>
      changed_;  ///< region -> (revision, when it changed)
};

}  // namespace zone::world
