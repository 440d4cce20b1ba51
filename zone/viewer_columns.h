// The live viewer's snapshot columns (net/viewer.h) copied from the zone's entity store, on the
// tick's worker pool when there is one: docs/viewer.md, "How it stays off the tick's back".
#pragma once

#include <cstddef>

#include "interest/thread_pool.h"
#include "net/viewer.h"
#include "zone/entity_store.h"

namespace zone {

/// Entities per task of fill_viewer_columns on a pool (192 KB of positions); a store of fewer
/// than two tasks' worth is copied on the calling thread alone.
inline constexpr std::size_t viewer_columns_chunk = 16384;

/// The snapshot's entity columns from `store`: every position, and the ids, classes and kinds
/// when the store's layout changed since `s` was filled (s.layout, its version; also when s holds
/// another count). With `pool` (and at least two chunks of viewer_columns_chunk entities) the
/// copies are split into chunks of `chunk` entities over the pool's threads, the caller's
/// included; the bytes are those of the single-threaded copy (pool null). Nothing is allocated
/// once s has grown to the store's size. The pool must be idle (one run at a time).
void fill_viewer_columns(const entity_store& store, net::viewer_snapshot& s, interest::thread_pool* pool,
                         std::size_t chunk = viewer_columns_chunk);

}  // namespace zone
