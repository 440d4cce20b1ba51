// The live viewer's snapshot columns (net/viewer.h) copied from the zone's entity store, on the
// tick's worker pool when there is one: docs/viewer.md, "How it stays off the tick's back".
#pragma once

#include <cstddef>

#include "interest/thread_pool.h"
#include "net/viewer.h"
#include "zone/entity_store.h"

namespace zone {

/// Entities per task of fill_viewer_columns on a pool (128 KB of x and y); a store of fewer
/// than two tasks' worth is copied on the calling thread alone.
inline constexpr std::size_t viewer_columns_chunk = 16384;

/// What fill_viewer_columns copied besides the positions (x and y, always).
enum class viewer_columns_fill : unsigned char {
  positions,        ///< nothing more: the store's layout is the one the buffer was filled with
  classes_patched,  ///< the classes of the entities set_visibility changed since (a few values)
  all,              ///< ids, classes and kinds: entities created or destroyed, an extent set, a fresh buffer
};

/// The snapshot's entity columns from `store`: every entity's x and y (8 bytes an entity), and the
/// ids, classes and kinds when the store's layout changed since `s` was filled (s.layout, its
/// version; also when s holds another count), of those only the changed classes when
/// set_visibility calls are all that changed (entity_store::class_changes_since). The columns
/// afterwards are what a full copy of every column would give. With `pool` (and at least two
/// chunks of viewer_columns_chunk entities) the copies are split into chunks of `chunk` entities (0:
/// viewer_columns_chunk)
/// over the pool's threads, the caller's included; the bytes are those of the single-threaded
/// copy (pool null). Nothing is allocated once s has grown to the store's size. The pool must be
/// idle (one run at a time).
viewer_columns_fill fill_viewer_columns(const entity_store& store, net::viewer_snapshot& s, interest::thread_pool* pool,
                                        std::size_t chunk = viewer_columns_chunk);

}  // namespace zone
