// The zone's interest step from its configuration (interest_setup.h).
#include "zone/interest_setup.h"

#include "gpu/device.h"
#include "gpu/finders.h"
#include "gpu/visibility.h"

namespace zone {

interest_parts make_interest_parts(const zone_config& cfg, interest::thread_pool* pool,
                                   const interest::grid_finder_options& grid) {
  interest_parts p;
  p.finder = gpu::make_finder(cfg.finder, pool, &p.finder_error, grid);
  if (!p.finder) {
    if (gpu::parse_backend(cfg.finder)) p.finder_error += " (use --finder auto or cpu)";
    p.finder = std::make_unique<interest::grid_finder>(pool);
  }
  // The host path's candidates: on the presence grid where the finder would be the CPU grid finder.
  if (cfg.host_grid == "on") {
    p.presence_grid = true;
  } else if (cfg.host_grid == "auto") {
    p.presence_grid = cfg.finder == "cpu" || (cfg.finder == "auto" && !gpu::device_available());
  }
  // The interest step on the GPU (the whole of it: candidates, classification, events).
  if (cfg.interest == "gpu" || (cfg.interest == "auto" && cfg.max_visible == 0)) {
    std::string why;
    p.engine = gpu::make_visibility_engine(pool, &why);
    if (!p.engine) {
      if (cfg.interest == "gpu") {
        p.engine_error = "interest 'gpu' cannot run here: " + why + " (use --interest auto or host)";
      } else {
        p.engine_note = why;
      }
    }
  } else if (cfg.interest == "auto") {
    p.engine_note = "max-visible is set (the cap runs on the host)";
  }
  return p;
}

}  // namespace zone
