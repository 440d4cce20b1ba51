#include "zone/viewer_columns.h"

#include <algorithm>
#include <cstring>
#include <functional>

namespace zone {

void fill_viewer_columns(const entity_store& store, net::viewer_snapshot& s, interest::thread_pool* pool,
                         std::size_t chunk) {
  chunk = std::max<std::size_t>(1, chunk);
  const std::size_t n = store.size();
  const auto pos = store.positions();
  // Plain copies of the store's columns, converted only when encoded on the viewer's thread:
  // positions always (12 bytes an entity); ids, classes and kinds only when the store's layout
  // changed since this buffer was filled (its version covers ids and classes; an entity's kind
  // is fixed at creation).
  const std::uint64_t layout = store.layout_version();
  const bool all = layout == 0 || s.layout != layout || s.ids.size() != n;
  s.xyz.resize(3 * n);
  if (all) {
    s.ids.resize(n);
    s.classes.resize(n);
    s.kind.resize(n);
  }
  static_assert(sizeof(vec3) == 3 * sizeof(float));
  static_assert(sizeof(entity_kind) == 1);
  static_assert(sizeof(entity_id) == sizeof(std::uint32_t));
  const auto ids = store.ids();
  const auto cls = store.visibility_classes();
  const auto kinds = store.kinds();
  const auto copy = [&](std::size_t begin, std::size_t end) {
    if (begin >= end) return;
    const std::size_t len = end - begin;
    std::memcpy(s.xyz.data() + 3 * begin, pos.data() + begin, len * sizeof(vec3));
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
}

}  // namespace zone
