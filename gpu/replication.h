// Replication's per-client decisions on the GPU (interest/replication_engine.h's engine): one thread
// per client walks its view, held in device memory, against its visible set, and writes the
// leaves, enters and updates it sends in their wire layout into one buffer copied back per tick.
// See docs/zone.md ("Replication on the GPU").
#pragma once

#include <memory>
#include <string>

#include "interest/replication_engine.h"

namespace zone::gpu {

/// Creates the GPU replication engine, or returns null with the reason in `why` when no device can
/// be used (or the build has no CUDA).
[[nodiscard]] std::unique_ptr<interest::replication_engine> make_replication_engine(std::string* why = nullptr);

}  // namespace zone::gpu
