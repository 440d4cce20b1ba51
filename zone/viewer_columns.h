// The live viewer's snapshot columns (net/viewer.h) copied from the zone's entity store, on the
// tick's worker pool when there is one: docs/viewer.md, "How it stays off the tick's back".
#pragma once

#include <condition_variable>
#include <cstddef>
#include <mutex>
#include <optional>
#include <thread>

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

/// A thread of its own that fills a due snapshot's entity columns after the tick and publishes
/// it (zone-server `--viewer-fill after`): the tick hands over and moves on, and the store stays
/// as that tick left it until the next tick starts, which first waits for the copy (wait()).
/// At 30 Hz the copy (about 0.15 ms at 100,000 entities on the H200) runs in the tick's slack;
/// a tick that is late waits for it, and the wait is that tick's.
class viewer_copier {
 public:
  viewer_copier();
  ~viewer_copier();  ///< waits for a copy in flight
  viewer_copier(const viewer_copier&) = delete;
  viewer_copier& operator=(const viewer_copier&) = delete;

  /// The tick's thread: fill_viewer_columns(store, s, nullptr, chunk) on the copier's thread,
  /// then viewer.publish(). Nothing may change `store` nor touch `viewer`'s snapshots until wait()
  /// returns. At most one copy in flight (a second start() waits for the first).
  void start(const entity_store& store, net::viewer_snapshot& s, net::viewer_server& viewer, std::size_t chunk);
  /// The tick's thread: waits for the copy in flight; what it copied (nullopt: none was started
  /// since the last wait) and the milliseconds it took on the copier's thread.
  struct done {
    viewer_columns_fill what;
    double copy_ms;
    bool failed;  ///< the copy threw (out of memory): nothing was published; the next copy starts over
  };
  std::optional<done> wait();

 private:
  void loop();
  std::mutex mutex_;
  std::condition_variable cv_;
  bool pending_ = false, busy_ = false, stop_ = false, finished_ = false;
  const entity_store* store_ = nullptr;
  net::viewer_snapshot* snapshot_ = nullptr;
  net::viewer_server* viewer_ = nullptr;
  std::size_t chunk_ = 0;
  done result_{};
  std::thread thread_;  // last: started once the members above are
};

}  // namespace zone
