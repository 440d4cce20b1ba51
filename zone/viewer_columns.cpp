#include "zone/viewer_columns.h"

#include <pthread.h>

#include <algorithm>
#include <chrono>
#include <cstring>
#include <functional>

#if defined(__x86_64__) || defined(_M_X64)
#include <immintrin.h>
#define ZONE_VIEWER_STREAM_STORES 1
#endif

namespace zone {

namespace {

/// x and y of positions [begin, end) into xy (two floats an entity). On x86-64 with streaming
/// (non-temporal) stores: the snapshot is read next by the viewer's thread on another core, so
/// its lines need not pass through this core's caches (nor be read in before being written);
/// the fence orders them before the pool's completion and the snapshot's hand-over.
void copy_xy(const vec3* pos, float* xy, std::size_t begin, std::size_t end) {
#ifdef ZONE_VIEWER_STREAM_STORES
  auto* out = reinterpret_cast<long long*>(xy);  // 8-byte aligned: a float vector's data, an even index
  for (std::size_t i = begin; i < end; ++i) {
    long long v;
    std::memcpy(&v, &pos[i], sizeof v);  // x, then y
    _mm_stream_si64(out + i, v);
  }
  _mm_sfence();
#else
  for (std::size_t i = begin; i < end; ++i) {
    xy[2 * i] = pos[i].x;
    xy[2 * i + 1] = pos[i].y;
  }
#endif
}

}  // namespace

viewer_columns_fill fill_viewer_columns(const entity_store& store, net::viewer_snapshot& s, interest::thread_pool* pool,
                                        std::size_t chunk) {
  if (chunk == 0) chunk = viewer_columns_chunk;
  const std::size_t n = store.size();
  const auto pos = store.positions();
  const auto ids = store.ids();
  const auto cls = store.visibility_classes();
  const auto kinds = store.kinds();
  // Plain copies of the store's columns, converted only when encoded on the viewer's thread:
  // x and y always (8 bytes an entity); ids, classes and kinds only when the store's layout
  // changed since this buffer was filled (its version covers ids and classes; an entity's kind
  // is fixed at creation), and of those only the classes of the entities set_visibility changed
  // when that is all that changed (entity_store::class_changes_since: the dense order is the same).
  const std::uint64_t layout = store.layout_version();
  viewer_columns_fill what = viewer_columns_fill::positions;
  if (layout == 0 || s.layout == 0 || s.ids.size() != n || s.classes.size() != n || s.kind.size() != n) {
    what = viewer_columns_fill::all;
  } else if (s.layout != layout) {
    what = store.class_changes_since(s.layout, [&](std::size_t d) { s.classes[d] = cls[d]; })
               ? viewer_columns_fill::classes_patched
               : viewer_columns_fill::all;
  }
  const bool all = what == viewer_columns_fill::all;
  s.xy.resize(2 * n);
  if (all) {
    s.ids.resize(n);
    s.classes.resize(n);
    s.kind.resize(n);
  }
  static_assert(sizeof(vec3) == 3 * sizeof(float));
  static_assert(sizeof(entity_kind) == 1);
  static_assert(sizeof(entity_id) == sizeof(std::uint32_t));
  const auto copy = [&](std::size_t begin, std::size_t end) {
    if (begin >= end) return;
    const std::size_t len = end - begin;
    copy_xy(pos.data(), s.xy.data(), begin, end);
    if (!all) return;
    std::memcpy(s.ids.data() + begin, ids.data() + begin, len * sizeof(std::uint32_t));
    std::memcpy(s.classes.data() + begin, cls.data() + begin, len * sizeof(std::uint32_t));
    std::memcpy(s.kind.data() + begin, kinds.data() + begin, len);
  };
  const std::size_t chunks = (n + chunk - 1) / chunk;
  if (pool == nullptr || pool->size() < 2 || chunks < 2) {
    copy(0, n);
  } else {
    // The pool is idle here (its caller's device wait): each task one chunk, the caller's thread
    // taking them too, so a worker slow to wake only leaves it more of them.
    const auto task = [&](std::size_t c) { copy(c * chunk, std::min(n, (c + 1) * chunk)); };
    pool->run(chunks, std::ref(task));  // by reference: no allocation
  }
  s.layout = layout;
  return what;
}

viewer_copier::viewer_copier() : thread_([this] { loop(); }) {}

viewer_copier::~viewer_copier() {
  (void)wait();
  {
    const std::lock_guard lock(mutex_);
    stop_ = true;
  }
  cv_.notify_all();
  thread_.join();
}

void viewer_copier::start(const entity_store& store, net::viewer_snapshot& s, net::viewer_server& viewer,
                          std::size_t chunk) {
  (void)wait();
  {
    const std::lock_guard lock(mutex_);
    store_ = &store, snapshot_ = &s, viewer_ = &viewer, chunk_ = chunk;
    pending_ = busy_ = true;
    finished_ = false;
  }
  cv_.notify_all();
}

std::optional<viewer_copier::done> viewer_copier::wait() {
  std::unique_lock lock(mutex_);
  cv_.wait(lock, [&] { return !busy_; });
  if (!finished_) return std::nullopt;
  finished_ = false;
  return result_;
}

void viewer_copier::loop() {
  // Named for per-thread CPU accounting (/proc/<pid>/task/*/comm), apart from the viewer's thread.
  pthread_setname_np(pthread_self(), "zone-vcopy");
  std::unique_lock lock(mutex_);
  for (;;) {
    cv_.wait(lock, [&] { return pending_ || stop_; });
    if (stop_ && !pending_) return;
    pending_ = false;
    const entity_store& store = *store_;
    net::viewer_snapshot& s = *snapshot_;
    net::viewer_server& viewer = *viewer_;
    const std::size_t chunk = chunk_;
    lock.unlock();
    const auto t0 = std::chrono::steady_clock::now();
    viewer_columns_fill what = viewer_columns_fill::all;
    bool failed = false;
    try {
      what = fill_viewer_columns(store, s, nullptr, chunk);
      viewer.publish();
    } catch (...) {
      // Growing the buffer failed: not published, and marked stale so that the next fill copies
      // every column (the viewer misses a snapshot; the tick goes on).
      s.layout = 0;
      failed = true;
    }
    const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    lock.lock();
    result_ = {what, ms, failed};
    busy_ = false;
    finished_ = true;
    cv_.notify_all();
  }
}

}  // namespace zone
