// zone/interest_setup.h: the zone's interest step built from its configuration, in one place for
// zone-server and bench-zone: the pair finder of --finder (the host reference engine's,
// interest/host_visibility_engine.h, which the world's tracker builds on it) and, per --interest,
// the GPU visibility engine; both handed to the world's interest_space (interest/interest_space.h).
#pragma once

#include <memory>
#include <string>

#include "interest/interest.h"
#include "interest/thread_pool.h"
#include "interest/visibility_engine.h"
#include "zone/zone_config.h"

namespace zone {

/// What make_interest_parts built. The world takes `finder` (its CPU backend) and, when set,
/// `engine` (zone_world::set_visibility_engine); both must outlive the world.
struct interest_parts {
  std::unique_ptr<interest::pair_finder> finder;        ///< never null (the CPU grid finder at worst)
  std::unique_ptr<interest::visibility_engine> engine;  ///< null: the step runs on the host
  std::string finder_error;  ///< the configured finder cannot run here (refuse to start)
  std::string engine_error;  ///< --interest gpu cannot run here (refuse to start)
  std::string engine_note;   ///< why --interest auto chose the host
  /// The host path finds candidates on the presence grid (cfg.host_grid; zone_world::set_presence_grid).
  bool presence_grid = false;
};

/// The finder of cfg.finder (gpu/finders.h; one that cannot run here leaves the CPU grid finder
/// and finder_error) and, for cfg.interest "gpu" or "auto" (without max_visible, which runs on the
/// host), the GPU visibility engine (gpu/visibility.h) on `pool` (which must outlive both).
/// `grid`: the CPU grid finder's tuning (bench-zone --w). presence_grid per cfg.host_grid.
[[nodiscard]] interest_parts make_interest_parts(const zone_config& cfg, interest::thread_pool* pool,
                                                 const interest::grid_finder_options& grid = {});

}  // namespace zone
