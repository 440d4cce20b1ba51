// A small, fast-moving zone and a seeded player script, shared by the world tests (CPU finders)
// and the CPU-vs-GPU determinism test: per-tick world digests of one run.
#pragma once

#include <doctest/doctest.h>

#include <cstdint>
#include <random>
#include <vector>

#include "zone/zone.h"

namespace zone::test {

inline zone_config small_config(std::uint64_t seed) {
  zone_config c;
  c.world = {{0, 0, 0}, {800, 800, 50}};
  c.seed = seed;
  c.npc_count = 600;
  c.boss_count = 2;
  c.town_count = 3;
  c.npc_speed = 30;  // fast, so a short run moves things across AOI edges
  c.player_speed = 40;
  c.tick_rate_hz = 10;
  return c;
}

/// Per-tick digests of a run with some players steered by a seeded script. `finder_view`: the
/// tracker reads the finder's own result buffer (pair_finder::find_view; zone-server's way).
/// `presence_grid`: the host path finds candidates on the presence grid (zone_world::set_presence_grid).
inline std::vector<std::uint64_t> run_digests(const zone_config& cfg, interest::pair_finder& finder,
                                              interest::thread_pool* pool, int ticks, int players = 8,
                                              bool finder_view = false,
                                              interest::visibility_engine* engine = nullptr,
                                              bool presence_grid = false) {
  zone_world w(cfg, finder, pool);
  w.set_finder_view(finder_view);
  w.set_presence_grid(presence_grid);
  if (engine != nullptr) w.set_visibility_engine(engine);
  w.populate();
  std::mt19937_64 script(cfg.seed + 7);
  std::vector<entity_id> ids;
  const float step_x = (cfg.world.hi.x - cfg.world.lo.x) / static_cast<float>(players);
  const float mid_y = (cfg.world.lo.y + cfg.world.hi.y) / 2;
  for (int p = 0; p < players; ++p) ids.push_back(w.spawn_player({cfg.world.lo.x + step_x * static_cast<float>(p), mid_y, 0}));
  std::vector<std::uint64_t> out;
  for (int t = 0; t < ticks; ++t) {
    for (const auto p : ids) {
      std::uniform_real_distribution<float> u(-2, 2);
      w.set_intent(p, {u(script), u(script), 0});
    }
    REQUIRE_FALSE(w.step().has_value());
    if (engine != nullptr) REQUIRE(w.tracker().last_update_on_engine());
    out.push_back(w.digest());
  }
  return out;
}

}  // namespace zone::test
