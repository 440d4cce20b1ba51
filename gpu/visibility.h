// The interest step on the GPU (interest/visibility_engine.h): per observer, candidates from a
// uniform grid over the presence boxes, classified against the previous visible sets kept in
// device memory; only the new sets and the events come back to the host. See docs/zone.md
// ("The interest step on the GPU") for the algorithm and how it relates to the pair finders.
#pragma once

#include <memory>
#include <string>

#include "interest.h"
#include "visibility_engine.h"

namespace zone::gpu {

/// Creates the GPU visibility engine, or returns null with the reason in `why` when no device can
/// be used (or the build has no CUDA). `pool` (may be null) packs the inputs on the host; it must
/// outlive the engine.
[[nodiscard]] std::unique_ptr<interest::visibility_engine> make_visibility_engine(interest::thread_pool* pool,
                                                                                  std::string* why = nullptr);

}  // namespace zone::gpu
