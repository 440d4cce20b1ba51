// Replication (zone.h): per client, one tick_update moving the client's view toward the
// observer's visible set within a byte budget. Algorithm in docs/zone.md.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <functional>
#include <cmath>
#include <cstring>
#include <exception>
#include <stdexcept>

#include "zone/replicator.h"

namespace zone {

namespace {

/// reserve() with 50% spare when it must grow, so sizes creeping up tick by tick do not
/// reallocate every time.
template <class T>
void reserve_with_headroom(std::vector<T>& v, std::size_t n) {
  if (v.capacity() < n) v.reserve(n + n / 2 + 16);
}

/// interest::run_tasks without a heap allocation per call: std::function keeps a
/// reference_wrapper in place, where a lambda capturing several references would be copied to
/// the heap (the tick allocates nothing in steady state).
template <class F>
void run_each(interest::thread_pool* pool, std::size_t n, F&& task) {
  interest::run_tasks(pool, n, std::ref(task));
}

/// What each entry costs against the byte budget: net::frame_cost, the closed-form upper bound
/// that the GPU path computes too (the frame's size is a function of the counts alone).
constexpr std::size_t enter_cost = net::frame_cost::enter;
constexpr std::size_t leave_cost = net::frame_cost::leave;
constexpr std::size_t update_cost = net::frame_cost::update;
static_assert(update_cost == sizeof(net::wire::entity_update));

/// Entities per task of build_many's snapshot.
constexpr std::size_t snapshot_chunk = 4096;

net::vec3f to_net(const vec3& v) { return {v.x, v.y, v.z}; }

float distance_sq(const vec3& a, const vec3& b) {
  const float dx = a.x - b.x, dy = a.y - b.y, dz = a.z - b.z;
  return dx * dx + dy * dy + dz * dz;
}

float distance(const vec3& a, const vec3& b) { return std::sqrt(distance_sq(a, b)); }

net::wire::entity_update wire_update(entity_id id, const vec3& p, const vec3& v, const net::position_quantizer& q) {
  const auto qp = q.quantize(to_net(p));
  const auto qv = net::quantize_velocity(to_net(v));
  return {id, net::wire::qpos3(qp[0], qp[1], qp[2]), net::wire::qvel3(qv[0], qv[1], qv[2])};
}

void prefetch(const void* p) { __builtin_prefetch(p); }

/// net::canonical_tick_update as the replication engine takes it (plain numbers).
interest::replication_frame_format frame_format() {
  using c = net::canonical_tick_update;
  interest::replication_frame_format f;
  for (std::uint32_t i = 0; i < 128; ++i) {
    c::parts p;
    p.enters = (i & interest::frame_part_enters) != 0;
    p.leaves = (i & interest::frame_part_leaves) != 0;
    p.updates = (i & interest::frame_part_updates) != 0;
    p.digest = (i & interest::frame_part_digest) != 0;
    p.self = (i & interest::frame_part_self) != 0;
    p.deferred = (i & interest::frame_part_deferred) != 0;
    p.reset = (i & interest::frame_part_reset) != 0;
    const c::table_layout l = c::layout(p);
    auto& t = f.tables[i];
    t.at = static_cast<std::uint16_t>(l.table_at);
    t.size = static_cast<std::uint16_t>(l.table_size);
    t.vtable = static_cast<std::uint16_t>(l.vtable_size);
    for (int k = 0; k < 10; ++k) t.field[k] = l.field[k];
    f.header_max = std::max<std::uint32_t>(f.header_max, static_cast<std::uint32_t>(l.table_at + l.table_size));
  }
  static_assert(sizeof f.enter_vtable == c::enter_vtable);
  for (int k = 0; k < 10; ++k) f.enter_vtable[k] = c::enter_vtable_fields[k];
  f.enter_table = static_cast<std::uint32_t>(c::enter_table);
  f.enter_name = static_cast<std::uint32_t>(c::name_bytes(0));
  f.prefix_bytes = static_cast<std::uint32_t>(net::frame_header_bytes);
  std::memcpy(f.identifier, net::wire::envelopeIdentifier(), 4);
  f.message_type = static_cast<std::uint32_t>(net::wire::message::tick_update);
  return f;
}


}  // namespace

/// The entities as the store has them; each update sent is quantized on the spot (build()).
struct replicator::store_source {
  const entity_store& store;
  const net::position_quantizer& quantizer;
  const entity_id* ids = store.ids().data();
  const vec3* pos = store.positions().data();
  const vec3* vel = store.velocities().data();
  std::size_t size = store.size();

  /// The entity's dense index: the hint when it still holds the entity, else the store's lookup.
  std::size_t find(entity_id id, std::uint32_t hint) const {
    return hint < size && ids[hint] == id ? hint : store.index_of(id);
  }
  void prefetch_entity(std::uint32_t hint) const {
    if (hint < size) prefetch(pos + hint);
  }
  const vec3& position(std::size_t k) const { return pos[k]; }
  net::wire::entity_update update(std::size_t k) const { return wire_update(ids[k], pos[k], vel[k], quantizer); }
};

/// build_many's snapshot: id, position and quantized update of an entity in one place.
struct replicator::snapshot_source {
  const entity_store& store;
  const entity_snapshot* snap;
  std::size_t size;

  std::size_t find(entity_id id, std::uint32_t hint) const {
    return hint < size && snap[hint].id == id ? hint : store.index_of(id);
  }
  void prefetch_entity(std::uint32_t hint) const {
    if (hint < size) prefetch(snap + hint);
  }
  const vec3& position(std::size_t k) const { return snap[k].position; }
  const net::wire::entity_update& update(std::size_t k) const { return snap[k].update; }
};

replicator::replicator(replication_options opt)
    : opt_(opt),
      quantizer_(opt.world),
      mid_period_(std::max<std::uint32_t>(1, opt.mid_period)),
      far_period_(std::max<std::uint32_t>(1, opt.far_period)) {
  const auto bound = [](float limit) {
    const float l2 = limit * limit;
    return tier_bound{limit, l2 * 0.9999f, l2 * 1.0001f};
  };
  near_ = bound(opt.near_distance);
  mid_ = bound(opt.mid_distance);
}

/// Exactly `std::sqrt(d2) < b.limit` (limit >= 0): decided on d2 unless it lies within a
/// relative 1e-4 of limit^2, where rounding could decide it and the square root is taken
/// (rarely, so that branch is predictable).
inline bool replicator::tier_below(float d2, const tier_bound& b) {
  const bool below = d2 < b.below_sq;
  if (!below & !(d2 > b.above_sq)) return std::sqrt(d2) < b.limit;
  return below;
}

client_id replicator::add_client(entity_id observer) {
  client_id c;
  if (!free_clients_.empty()) {
    c = free_clients_.back();
    free_clients_.pop_back();
  } else {
    c = static_cast<client_id>(clients_.size());
    clients_.emplace_back();
  }
  client_state& s = clients_[c];
  s.observer = observer;
  s.active = true;
  s.reset_pending = true;
  s.class_notes = false;
  clear_view(s);
  s.meta.clear();
  s.hash = 0;
  s.built_tick = s.told_through = 0;
  s.boxed_tick = ~std::uint64_t{0};
  return c;
}

void replicator::set_class_notes(client_id c, bool on) { clients_[c].class_notes = on; }

void replicator::remove_client(client_id c) {
  if (c >= clients_.size() || !clients_[c].active) return;
  client_state& s = clients_[c];
  s.active = false;
  s.observer = null_entity;
  clear_view(s);
  s.meta.clear();
  s.hash = 0;
  free_clients_.push_back(c);
}

void replicator::set_observer(client_id c, entity_id observer) {
  client_state& s = clients_[c];
  s.observer = observer;
  // Its view was built with the old observer's mask: the box test (which reads the new one) is
  // not exact for it until a frame has sent every leave with the new one; judged by its view.
  s.built_tick = ~std::uint64_t{0};
}

void replicator::resync(client_id c) { clients_[c].reset_pending = true; }

std::size_t replicator::resync_viewers_of(const entity_store& store, const interest::interest_tracker& tracker,
                                          std::uint64_t tick, entity_id changed, std::uint32_t old_class,
                                          std::uint32_t old_sees) {
  const class_change one{changed, old_class, old_sees};
  return resync_viewers_of(store, tracker, tick, std::span<const class_change>(&one, 1), nullptr);
}

void replicator::after_frame(client_state& s, std::uint64_t tick, bool reset, bool deferred_leaves) const {
  // Told through this tick: after a reset (every class current); or when no leave was deferred
  // and either this tick's changes were box-tested for it (the box test holds for a frame that
  // sends every leave) or there were no changes since it was last told.
  if (reset || (!deferred_leaves &&
                ((s.boxed_tick == tick && s.told_through + 1 >= tick) || s.told_through >= last_judged_tick_))) {
    s.told_through = std::max(s.told_through, tick);
  }
  // Only a frame that sent every leave leaves a view within the visible set, which the next tick's
  // box test assumes (told_through alone does not say so: a client judged by its view is told
  // through the tick before its frame, which may then defer leaves).
  if (!deferred_leaves) s.built_tick = tick;
}

std::size_t replicator::resync_viewers_of(const entity_store& store, const interest::interest_tracker& tracker,
                                          std::uint64_t tick, std::span<const class_change> changes,
                                          interest::thread_pool* pool, std::vector<class_note_target>* notes) {
  if (notes != nullptr) notes->clear();
  auto& ch = changed_scratch_;
  ch.clear();
  for (const class_change& c : changes) {
    const std::size_t x = store.index_of(c.entity);
    if (x == entity_store::npos) continue;
    ch.push_back({c.entity, store.visibility_classes()[x], store.sees()[x], c.old_class, c.old_sees,
                  store.positions()[x], store.presence_half_extents()[x], tick});
  }
  // With no change this tick, only the clients not yet told of an earlier one have anything to learn.
  if (ch.empty() && change_history_.empty()) return 0;
  if (!ch.empty()) last_judged_tick_ = tick;
  const float slack = tracker.options().hysteresis + 0.01f;
  // The changes a client judged by its view may not have been told of: the history's (those of
  // ticks after its told_through) and this call's, in order, and by id for the walk.
  window_.assign(change_history_.begin(), change_history_.end());
  const std::size_t first_now = window_.size();
  window_.insert(window_.end(), ch.begin(), ch.end());
  window_by_id_.clear();
  for (std::size_t k = 0; k < window_.size(); ++k)
    window_by_id_.push_back({window_[k].id, static_cast<std::uint32_t>(k)});
  std::sort(window_by_id_.begin(), window_by_id_.end());
  // Client c against the changes, in order: the first that resyncs it decides. A client with
  // notes collects one per changed entity instead (the class now). True: resync it.
  const auto judge = [&](client_id id, client_state& s, std::vector<class_note_target>& out) {
    if (!s.active || s.reset_pending) return false;
    const bool noting = s.class_notes && notes != nullptr;
    const std::size_t first_note = out.size();
    const auto note = [&](entity_id e, std::uint32_t cls) { out.push_back({id, e, cls}); };
    // An entity named twice (switched twice, or held and seen anew on its own switch): one note,
    // the client's notes in entity order (the class is the store's, the same for both). Sorted
    // once rather than searched at each note: a client's own switch may note its whole view.
    const auto one_note_each = [&] {
      const auto begin = out.begin() + static_cast<std::ptrdiff_t>(first_note);
      if (out.end() - begin < 2) return;
      std::sort(begin, out.end(),
                [](const class_note_target& a, const class_note_target& b) { return a.entity < b.entity; });
      out.erase(
          std::unique(begin, out.end(),
                      [](const class_note_target& a, const class_note_target& b) { return a.entity == b.entity; }),
          out.end());
    };
    // (A frame that deferred leaves does not count as built: such a client is judged by its view.)
    // (No frame before tick 0: set_observer's ~0 never reads as built.)
    const bool boxed = tick != 0 && s.built_tick + 1 == tick && s.told_through + 1 >= tick;
    if (boxed) {
      // Its view is within its visible set of the tick before: the box test at this tick's
      // positions names every change it may hold and keep (for this tick only; after_frame
      // confirms it once its frame sent every leave).
      s.boxed_tick = tick;
      if (ch.empty()) return false;  // a tick without switches (another client is behind)
    }
    const std::size_t o = store.index_of(s.observer);
    const std::uint32_t m = o != entity_store::npos ? store.sees()[o] : 0u;
    if (boxed) {
      // Its own switches of the tick: one that changed its mask resyncs a client without notes;
      // the first one's old mask is the one its view was built with (a later one's old mask is
      // one in between).
      std::uint32_t m_before = m;
      bool first_own = true;
      for (const changed_entity& c : ch) {
        if (s.observer != c.id) continue;
        if (!noting && c.sees != c.old_sees) return true;
        if (first_own) m_before = c.old_sees, first_own = false;
      }
      vec3 q{}, a{};
      if (o != entity_store::npos) q = store.positions()[o], a = store.aoi_half_extents()[o];
      for (const changed_entity& c : ch) {
        if (s.observer == c.id || c.cls == c.old_class || o == entity_store::npos) continue;
        if ((m & c.cls) == 0 || (m_before & c.old_class) == 0) continue;
        if (std::fabs(c.p.x - q.x) > a.x + c.b.x + slack || std::fabs(c.p.y - q.y) > a.y + c.b.y + slack ||
            std::fabs(c.p.z - q.z) > a.z + c.b.z + slack) {
          continue;
        }
        if (!noting) return true;
        note(c.id, c.cls);
      }
      one_note_each();
      return false;
    }
    // By its view: every change since it was last told of all. Too far back: start over.
    if (s.told_through < forgotten_through_) return true;
    // Its own switches among them, as above: the first one's old mask is the one its view was
    // built with.
    const changed_entity* own = nullptr;
    for (std::size_t k = 0; k < window_.size(); ++k) {
      const changed_entity& c = window_[k];
      if ((c.tick <= s.told_through && k < first_now) || s.observer != c.id) continue;
      if (!noting && c.sees != c.old_sees) return true;
      if (own == nullptr) own = &c;
    }
    settle_view(s);
    thread_local std::vector<std::uint32_t> held;
    held.clear();
    const bool any =
        !s.view.empty() && window_by_id_.front().first <= s.view.back() && s.view.front() <= window_by_id_.back().first;
    for (std::size_t v = 0, k = 0; any && v < s.view.size() && k < window_by_id_.size();) {
      if (s.view[v] < window_by_id_[k].first) {
        ++v;
      } else if (window_by_id_[k].first < s.view[v]) {
        ++k;
      } else {
        const std::uint32_t w = window_by_id_[k++].second;  // v stays: an id may change twice
        if (w >= first_now || window_[w].tick > s.told_through) held.push_back(w);
      }
    }
    std::sort(held.begin(), held.end());
    const auto classes = store.visibility_classes();
    for (const std::uint32_t w : held) {
      const changed_entity& c = window_[w];
      if (s.observer == c.id || c.cls == c.old_class) continue;
      // Held: the class it has now, if its mask holds it (one it no longer sees leaves, its
      // class no matter, and comes back only through a change judged again: the entity's or
      // its own mask's, below).
      const std::size_t x = store.index_of(c.id);
      if (x == entity_store::npos || (m & classes[x]) == 0) continue;
      if (!noting) return true;
      note(c.id, classes[x]);
    }
    if (own != nullptr) {
      // Its own mask changed (no reset for a noting client): what it holds and sees now but did
      // not see before (an entity whose leave was not sent yet) may hold an older class.
      for (const entity_id e : s.view) {
        const std::size_t x = store.index_of(e);
        if (x == entity_store::npos) continue;
        if ((m & classes[x]) != 0 && (own->old_sees & classes[x]) == 0) note(e, classes[x]);
      }
    }
    one_note_each();
    s.told_through = tick;
    return false;
  };
  constexpr std::size_t chunk = 1024;
  const std::size_t n = clients_.size(), tasks = (n + chunk - 1) / chunk;
  resync_counts_.assign(tasks, 0);
  chunk_min_told_.assign(tasks, tick);
  if (chunk_notes_.size() < tasks) chunk_notes_.resize(tasks);
  const auto run_chunk = [&](std::size_t t) {
    std::size_t k = 0;
    auto& out = chunk_notes_[t];
    out.clear();
    std::uint64_t least = tick;
    for (std::size_t i = t * chunk; i < std::min(n, (t + 1) * chunk); ++i) {
      client_state& s = clients_[i];
      if (judge(static_cast<client_id>(i), s, out)) s.reset_pending = true, ++k;
      // Box-tested for this tick: told through it once its frame is sent (after_frame).
      if (s.active && !s.reset_pending) least = std::min(least, s.boxed_tick == tick ? tick - 1 : s.told_through);
    }
    resync_counts_[t] = k;
    chunk_min_told_[t] = least;
  };
  if (pool != nullptr && tasks > 1) {
    pool->run(tasks, run_chunk);
  } else {
    for (std::size_t t = 0; t < tasks; ++t) run_chunk(t);
  }
  std::size_t total = 0;
  std::uint64_t least = tick;
  for (std::size_t t = 0; t < tasks; ++t) {
    total += resync_counts_[t];
    least = std::min(least, chunk_min_told_[t]);
    if (notes != nullptr) notes->insert(notes->end(), chunk_notes_[t].begin(), chunk_notes_[t].end());
  }
  // The history keeps what a client may still need: the changes after the least told_through,
  // and at most the last 128 ticks with changes (a client told only before those is reset).
  change_history_.insert(change_history_.end(), ch.begin(), ch.end());
  std::size_t drop = 0;
  while (drop < change_history_.size() && change_history_[drop].tick <= least) ++drop;
  if (drop < change_history_.size() && change_history_.back().tick - change_history_[drop].tick >= 128) {
    const std::uint64_t keep_from = change_history_.back().tick - 127;
    while (drop < change_history_.size() && change_history_[drop].tick < keep_from) ++drop;
    forgotten_through_ = std::max(forgotten_through_, keep_from - 1);
  }
  change_history_.erase(change_history_.begin(), change_history_.begin() + static_cast<std::ptrdiff_t>(drop));
  return total;
}

std::span<const std::uint8_t> replicator::build(client_id c, const entity_store& store, const interest::interest_tracker& tracker,
                                                std::uint64_t tick, std::uint64_t server_time_us,
                                                std::uint32_t last_input_sequence, replication_writer& writer,
                                                replication_stats* stats) {
  return build_from(store_source{store, quantizer_}, c, store, tracker, tick, server_time_us, last_input_sequence,
                    writer, stats);
}

template <class Source>
std::span<const std::uint8_t> replicator::build_from(const Source& source, client_id c, const entity_store& store,
                                                     const interest::interest_tracker& tracker, std::uint64_t tick,
                                                     std::uint64_t server_time_us, std::uint32_t last_input_sequence,
                                                     replication_writer& w, replication_stats* stats,
                                                     const frame_room* out_room, std::size_t k) {
  client_state& s = clients_[c];
  net::tick_update_writer& writer = w.frame_;
  replication_stats st;
  writer.begin(tick, server_time_us, last_input_sequence);
  settle_view(s);
  if (s.reset_pending) {
    clear_view(s);
    s.meta.clear();
    s.hash = 0;
    s.reset_pending = false;
    writer.set_reset(true);
    st.reset = true;
  }
  const auto fits = [&](std::size_t cost) { return writer.size_estimate() + cost <= opt_.byte_budget; };

  // The observer's visible set (empty when it is gone) and position.
  std::span<const entity_id> visible;
  const std::size_t row = tracker.row_of(s.observer);
  if (row != entity_store::npos) visible = tracker.visible(row);
  const std::size_t self = store.index_of(s.observer);
  const vec3 eye = self != entity_store::npos ? store.positions()[self] : vec3{};
  if (self != entity_store::npos) writer.set_self_position(to_net(eye));  // lets the client check its view exactly
  const vec3* const pos = store.positions().data();

  // The scratch is the writer's, shared by the clients it builds; room for the most this tick
  // can need, with headroom (a steady tick allocates nothing).
  const std::size_t view_size = s.view.size();
  if (w.due_.size() < view_size) w.due_.resize(view_size + view_size / 2 + 16);  // used up to due_count
  w.enters_.clear();
  w.left_.clear();

  // An entry of both the view and the visible set is due when its staleness reaches its tier's
  // period (the tier from the squared distance; the square root only near a boundary). Written
  // without branches on the verdicts, which are unpredictable from one entry to the next: every
  // entry is written to due_ and the count advances only for the due ones, so the loop runs
  // ahead and the entries' loads from the store (cache misses, most of its time) overlap.
  const std::uint32_t tick32 = static_cast<std::uint32_t>(tick);
  const entity_id* const view = s.view.data();
  view_meta* const meta = s.meta.data();
  replication_writer::due_update* const due = w.due_.data();
  std::size_t due_count = 0;
  constexpr std::size_t lookahead = 6;  // entries whose store data is prefetched ahead
  const auto consider = [&](std::size_t j) {
    if (j + lookahead < view_size) source.prefetch_entity(meta[j + lookahead].dense);
    const std::size_t k = source.find(view[j], meta[j].dense);
    if (k == entity_store::npos) return;
    meta[j].dense = static_cast<std::uint32_t>(k);
    const float d2 = distance_sq(eye, source.position(k));
    const bool near = tier_below(d2, near_);
    const bool mid = tier_below(d2, mid_);
    const std::uint32_t period = near ? 1u : mid ? mid_period_ : far_period_;
    const std::uint32_t staleness = tick32 - meta[j].last_sent;
    due[due_count] = {static_cast<std::uint32_t>(j), static_cast<std::uint32_t>(k), d2, staleness};
    due_count += staleness >= period ? 1 : 0;
  };

  if (visible.size() == view_size && std::equal(visible.begin(), visible.end(), view)) {
    // The usual tick: the view is the visible set; no leaves, no enters.
    for (std::size_t j = 0; j < std::min(lookahead, view_size); ++j) source.prefetch_entity(meta[j].dense);
    for (std::size_t j = 0; j < view_size; ++j) consider(j);
  } else {
    // Merge the visible set with the view (both sorted): leaves are written at once (they come
    // first), enters are collected with their distance, due updates as above.
    reserve_with_headroom(w.enters_, visible.size());
    reserve_with_headroom(w.left_, view_size);
    std::size_t i = 0, j = 0;
    while (i < visible.size() || j < view_size) {
      if (j < view_size && (i == visible.size() || view[j] < visible[i])) {
        if (fits(leave_cost)) {
          writer.add_leave(view[j]);
          w.left_.push_back(static_cast<std::uint32_t>(j));
          s.hash = net::digest_remove(s.hash, view[j]);
          ++st.leaves;
        } else {
          ++st.deferred_leaves;
        }
        ++j;
      } else if (j == view_size || visible[i] < view[j]) {
        const std::size_t k = store.index_of(visible[i]);
        if (k != entity_store::npos) {
          w.enters_.push_back(
              {distance(eye, pos[k]), static_cast<std::uint32_t>(k), visible[i], static_cast<std::uint32_t>(k)});
        }
        ++i;
      } else {
        consider(j);
        ++i;
        ++j;
      }
    }
  }

  using pending = replication_writer::pending;
  const auto by_priority = [](const pending& a, const pending& b) {
    return a.priority < b.priority || (a.priority == b.priority && a.id < b.id);
  };

  // Enters, closest first, with full state.
  std::size_t entered = 0;
  if (!w.enters_.empty()) {
    std::sort(w.enters_.begin(), w.enters_.end(), by_priority);
    for (const pending& e : w.enters_) {
      if (!fits(enter_cost)) {
        st.deferred_enters = static_cast<std::uint32_t>(w.enters_.size() - entered);
        break;
      }
      const std::size_t k = e.index;
      writer.add_enter({e.id, static_cast<net::entity_kind>(store.kinds()[k]), store.visibility_classes()[k],
                        to_net(pos[k]), to_net(store.velocities()[k]), to_net(store.presence_half_extents()[k]), {}});
      s.hash = net::digest_add(s.hash, e.id);
      w.enters_[entered++] = e;  // compact: the first `entered` were sent
    }
  }
  st.enters = static_cast<std::uint32_t>(entered);

  // Updates of the view, most stale per metre first. Each costs exactly update_cost in the
  // writer's estimate, so the ones that fit are the first `room` by priority: when the budget
  // binds they are selected (nth_element) and sent in priority order; when everything fits the
  // order changes nothing that is sent: they go in view order and no priority is computed.
  const auto send_update = [&](std::uint32_t j, std::uint32_t k) {
    writer.add_wire_update(source.update(k));
    meta[j].last_sent = tick32;
  };
  const std::size_t used = writer.size_estimate();
  const std::size_t room = used >= opt_.byte_budget ? 0 : (opt_.byte_budget - used) / update_cost;
  if (room >= due_count) {
    for (std::size_t n = 0; n < due_count; ++n) send_update(due[n].index, due[n].dense);
    st.updates = static_cast<std::uint32_t>(due_count);
  } else {
    reserve_with_headroom(w.ranked_, due_count);
    w.ranked_.clear();
    for (std::size_t n = 0; n < due_count; ++n) {
      const auto& u = due[n];
      const float d = std::sqrt(u.distance_sq);
      w.ranked_.push_back({-static_cast<float>(u.staleness) / std::max(d, 1.0f), u.index, view[u.index], u.dense});
    }
    const auto cut = w.ranked_.begin() + static_cast<std::ptrdiff_t>(room);
    std::nth_element(w.ranked_.begin(), cut, w.ranked_.end(), by_priority);
    std::sort(w.ranked_.begin(), cut, by_priority);
    for (std::size_t n = 0; n < room; ++n) send_update(w.ranked_[n].index, w.ranked_[n].dense);
    st.updates = static_cast<std::uint32_t>(room);
    st.deferred_updates = static_cast<std::uint32_t>(due_count - room);
  }

  // The new view when it changed: what was kept plus what entered, sorted. (Otherwise the
  // updates above have already refreshed last_sent in place.)
  if (entered > 0 || !w.left_.empty()) {
    std::sort(w.enters_.begin(), w.enters_.begin() + static_cast<std::ptrdiff_t>(entered),
              [](const pending& a, const pending& b) { return a.id < b.id; });
    const std::size_t next_size = view_size + entered - w.left_.size();
    reserve_with_headroom(w.next_view_, next_size);
    reserve_with_headroom(w.next_meta_, next_size);
    w.next_view_.clear();
    w.next_meta_.clear();
    std::size_t e = 0, l = 0;
    for (std::size_t v = 0; v < view_size; ++v) {
      while (e < entered && w.enters_[e].id < view[v]) {
        w.next_view_.push_back(w.enters_[e].id);
        w.next_meta_.push_back({w.enters_[e++].dense, tick32});
      }
      if (l < w.left_.size() && w.left_[l] == v) {
        ++l;  // sent as a leave
        continue;
      }
      w.next_view_.push_back(view[v]);
      w.next_meta_.push_back(meta[v]);
    }
    while (e < entered) {
      w.next_view_.push_back(w.enters_[e].id);
      w.next_meta_.push_back({w.enters_[e++].dense, tick32});
    }
    reserve_with_headroom(s.view, next_size);
    reserve_with_headroom(s.meta, next_size);
    s.view.assign(w.next_view_.begin(), w.next_view_.end());
    s.meta.assign(w.next_meta_.begin(), w.next_meta_.end());
  }

  if (opt_.send_digest && (st.reset || opt_.digest_period <= 1 || tick % opt_.digest_period == 0)) {
    writer.set_digest({tick, s.hash, static_cast<std::uint32_t>(s.view.size())});
  }
  // What the budget left for later: a client (the oracle, docs/bots.md) can then tell a deferral from a loss.
  writer.set_deferred({st.deferred_enters, st.deferred_leaves, st.deferred_updates});
  // Into the caller's memory when it gives some (build_many's room), else the writer's buffer.
  const auto frame =
      out_room != nullptr && *out_room ? writer.finish_into((*out_room)(k, writer.frame_size())) : writer.finish();
  st.bytes = frame.size();
  after_frame(s, tick, st.reset, st.deferred_leaves > 0);
  if (stats) *stats = st;
  return frame;
}

void replicator::prefetch_client(client_id c) const {
  const client_state& s = clients_[c];
  prefetch(s.view.data());
  prefetch(s.meta.data());
  prefetch(reinterpret_cast<const char*>(s.meta.data()) + 64);
}

void replicator::reset_all_clients() {
  for (client_state& s : clients_) {
    if (!s.active) continue;
    s.reset_pending = true;
    clear_view(s);
    s.meta.clear();
    s.hash = 0;
    s.engine_view_size = 0;
  }
}

void replicator::note_engine_error(const std::exception& e) {
  engine_error_ = e.what();
  if (engine_error_.empty()) engine_error_ = "replication engine failed";
}

double replicator::grow_ahead(std::chrono::steady_clock::time_point deadline) noexcept {
  if (!on_engine()) return 0;
  try {
    return engine_->grow_ahead(deadline);
  } catch (...) {
    return 0;
  }
}

void replicator::set_engine(interest::replication_engine* engine) {
  engine_ = engine;
  engine_error_.clear();
  if (engine_ != nullptr) {
    try {
      engine_->set_frame_format(frame_format());
    } catch (const std::exception& e) {
      note_engine_error(e);
    }
    engine_->forget_all();
  }
  reset_all_clients();
}

namespace {

/// The engine's entity staging in tasks: task 0 the slot map, tasks 1.. the entities by chunks.
std::size_t entity_task_count(std::size_t n) { return 1 + (n + snapshot_chunk - 1) / snapshot_chunk; }

void stage_entity_task(const entity_store& store, const interest::replication_engine::staging& st, std::size_t task) {
  if (task == 0) {
    const auto slot_dense = store.slot_dense();
    if (!slot_dense.empty()) std::memcpy(st.slot_dense, slot_dense.data(), slot_dense.size_bytes());
    return;
  }
  const auto ids = store.ids();
  const auto pos = store.positions();
  const auto vel = store.velocities();
  const std::size_t n = store.size();
  const std::size_t begin = (task - 1) * snapshot_chunk, end = std::min(n, begin + snapshot_chunk);
  for (std::size_t k = begin; k < end; ++k) {
    interest::replication_entity& e = st.entities[k];
    e.x = pos[k].x;
    e.y = pos[k].y;
    e.z = pos[k].z;
    e.id = ids[k];
    e.vx = vel[k].x;
    e.vy = vel[k].y;
    e.vz = vel[k].z;
    e.pad = 0;
  }
}

}  // namespace

void replicator::prestage(const entity_store& store, std::uint64_t tick, interest::thread_pool* pool) {
  prestaged_ = false;
  if (!on_engine()) return;
  try {
    const std::size_t n = store.size(), slots = store.slot_dense().size();
    const auto st = engine_->stage_entities(n, slots);
    if (st.entities == nullptr && n > 0) return;  // the engine takes no entities ahead
    run_each(pool, entity_task_count(n), [&](std::size_t task) { stage_entity_task(store, st, task); });
    engine_->upload_entities();
    prestaged_ = true;
    prestaged_layout_ = store.layout_version();
    prestaged_tick_ = tick;
    prestaged_n_ = n;
    prestaged_slots_ = slots;
  } catch (const std::exception& e) {
    // As build_many: the engine is given up, the next frames are built on the CPU from scratch.
    note_engine_error(e);
    reset_all_clients();
  }
}

namespace detail {

void move_view(std::vector<entity_id>& view, std::span<const entity_id> leaves, std::span<const entity_id> enters) {
  // Segment by segment: each id after the first change moves once for the leaves and once for the
  // enters, in one memmove per change (an insert or erase per change would move the whole tail
  // each time; a copy through a second list would move every id twice). A crowd's view holds
  // thousands of ids.
  // The leaves: the kept runs between them slide down over those that left.
  if (!leaves.empty() && !view.empty()) {
    auto write = view.end(), kept = view.end(), at = view.begin();
    for (const entity_id l : leaves) {
      at = std::lower_bound(at, view.end(), l);
      if (at == view.end()) break;
      if (*at != l) continue;  // not held
      write = write == view.end() ? at : std::move(kept, at, write);
      kept = ++at;
    }
    if (write != view.end()) view.erase(std::move(kept, view.end(), write), view.end());
  }
  // The enters, from the last: the run above each moves up by the enters still to place.
  if (enters.empty()) return;
  const std::size_t held = view.size();
  reserve_with_headroom(view, held + enters.size());
  view.resize(held + enters.size());
  auto to = view.end(), end = view.begin() + static_cast<std::ptrdiff_t>(held);
  for (std::size_t e = enters.size(); e > 0; --e) {
    const auto at = std::upper_bound(view.begin(), end, enters[e - 1]);
    to = std::move_backward(at, end, to);
    *--to = enters[e - 1];
    end = at;
  }
}

bool view_changes::note(std::span<const entity_id> frame_leaves, std::span<const entity_id> frame_enters,
                        const std::vector<entity_id>& view) {
  // An id entered since the last settle and now leaving was never in `view`; one left since and
  // now entering again is still there. Else the change waits for the settle.
  const auto change = [](std::vector<entity_id>& cancel, std::vector<entity_id>& add, entity_id id) {
    const auto at = std::lower_bound(cancel.begin(), cancel.end(), id);
    if (at != cancel.end() && *at == id) {
      cancel.erase(at);
    } else {
      add.insert(std::lower_bound(add.begin(), add.end(), id), id);
    }
  };
  for (const entity_id l : frame_leaves) change(enters, leaves, l);
  for (const entity_id e : frame_enters) change(leaves, enters, e);
  // 1/32: a crowd's view of ~2,500 with ~4 changes a frame moves once per ~18 frames, and the
  // lists stay short to search.
  return enters.size() + leaves.size() > std::max<std::size_t>(16, view.size() / 32);
}

void view_changes::settle(std::vector<entity_id>& view) {
  move_view(view, leaves, enters);
  clear();
}

}  // namespace detail

void replicator::follow_view(client_state& s, std::span<const entity_id> enters, const std::uint8_t* frame,
                             bool any_leaves) {
  // The client's view as the engine moved it on, from the frame's leaves and enters (ids; the
  // engine keeps the views themselves on its device): what resync_viewers_of reads. Held as
  // unsettled changes, which a leave or enter of the same id cancels: a large view (a crowd's
  // thousands) is read and moved once per many frames, not at every change of every frame.
  thread_local std::vector<entity_id> leaves;
  leaves.clear();
  if (any_leaves) {
    const auto* env = net::wire::GetSizePrefixedenvelope(frame);
    const auto* u = env != nullptr ? env->message_as_tick_update() : nullptr;
    if (u != nullptr && u->leaves() != nullptr) leaves.assign(u->leaves()->begin(), u->leaves()->end());
  }
  if (s.unsettled.note(leaves, enters, s.view)) s.unsettled.settle(s.view);
}

void replicator::settle_view(client_state& s) {
  if (!s.unsettled.empty()) s.unsettled.settle(s.view);
}

void replicator::clear_view(client_state& s) {
  s.view.clear();
  s.unsettled.clear();
}

void replicator::build_on_engine(std::span<const replication_request> requests, const entity_store& store,
                                 const interest::interest_tracker& tracker, std::uint64_t tick, std::uint64_t server_time_us,
                                 interest::thread_pool* pool, const frame_sink& sink, const chunk_sink& chunk_done,
                                 const frame_room& room, const frame_share& share,
                                 const std::function<void()>* while_waiting) {
  // Phase clocks: wall always, the process's CPU time when asked (set_phase_cpu_timing).
  replication_phase_times times;
  times.cpu = static_cast<bool>(phase_cpu_);
  auto mark_wall = std::chrono::steady_clock::now();
  double mark_cpu = phase_cpu_ ? phase_cpu_() : 0;
  const auto phase_end = [&](double& wall, double& cpu) {
    const auto now = std::chrono::steady_clock::now();
    wall = std::chrono::duration<double, std::milli>(now - mark_wall).count();
    mark_wall = now;
    if (phase_cpu_) {
      const double c = phase_cpu_();
      cpu = c - mark_cpu;
      mark_cpu = c;
    }
  };
  // Idle workers sleep after each host phase rather than spin until the next (options).
  const auto rest = [&] {
    if (pool != nullptr && opt_.park_between_phases) pool->park();
  };

  const std::size_t n = store.size(), jobs = requests.size();
  const auto slot_dense = store.slot_dense();
  const std::size_t chunk = std::max<std::uint32_t>(1, opt_.clients_per_task);
  const std::size_t chunks = (jobs + chunk - 1) / chunk;
  const auto visible_of = [&](client_id c) -> std::span<const entity_id> {
    const std::size_t row = tracker.row_of(clients_[c].observer);
    return row != entity_store::npos ? tracker.visible(row) : std::span<const entity_id>{};
  };
  // The visible sets: read in place from the interest engine's device rows when the replication
  // engine can (then each job names its observer's row), else copied into the staging.
  const auto rows = engine_->reads_resident() ? tracker.resident_visible() : interest::visibility_engine::resident_lists{};
  const bool resident = rows.data != nullptr;
  std::uint64_t total = 0;
  if (!resident) {
    job_visible_.assign(jobs + 1, 0);
    run_each(pool, chunks, [&](std::size_t ch) {
      const std::size_t end = std::min(jobs, (ch + 1) * chunk);
      for (std::size_t k = ch * chunk; k < end; ++k) {
        job_visible_[k] = static_cast<std::uint32_t>(visible_of(requests[k].client).size());
      }
    });
    for (std::size_t k = 0; k < jobs; ++k) {
      const std::uint32_t len = job_visible_[k];
      job_visible_[k] = static_cast<std::uint32_t>(total);
      total += len;
    }
    job_visible_[jobs] = static_cast<std::uint32_t>(total);
    if (total > 0xffffffffu) throw std::length_error("replication engine: more than 2^32 visible entries");
  }

  // The staging, in one pool run: every entity as the store has it (the engine quantizes), the
  // slot map, the jobs (each names its observer; the engine finds its position) with their sets.
  // The entities and the slot map are on the device already when prestage() put them there for
  // this store as it is.
  const bool ahead = prestaged_ && prestaged_tick_ == tick && prestaged_layout_ == store.layout_version() &&
                     prestaged_n_ == n && prestaged_slots_ == slot_dense.size();
  if (prestaged_ && !ahead) engine_->discard_entities();
  prestaged_ = false;
  times.entities_ahead = ahead;
  const auto st = engine_->stage(n, slot_dense.size(), jobs, resident ? 0 : total);
  const std::size_t entity_tasks = ahead ? 0 : entity_task_count(n);
  run_each(pool, entity_tasks + chunks, [&](std::size_t task) {
    if (task < entity_tasks) {
      stage_entity_task(store, st, task);
      return;
    }
    const std::size_t ch = task - entity_tasks;
    const std::size_t end = std::min(jobs, (ch + 1) * chunk);
    for (std::size_t k = ch * chunk; k < end; ++k) {
      const client_state& s = clients_[requests[k].client];
      interest::replication_job& j = st.jobs[k];
      j.client = requests[k].client;
      j.flags = s.reset_pending ? interest::job_reset : 0;
      j.observer = s.observer;
      j.last_input = requests[k].last_input_sequence;
      if (resident) {
        const std::size_t row = tracker.row_of(s.observer);
        j.visible_off = row != entity_store::npos ? static_cast<std::uint32_t>(row) : interest::no_row;
        j.visible_len = 0;
        continue;
      }
      j.visible_off = job_visible_[k];
      j.visible_len = job_visible_[k + 1] - job_visible_[k];
      const auto vis = visible_of(requests[k].client);
      if (!vis.empty()) std::memcpy(st.visible + j.visible_off, vis.data(), vis.size_bytes());
    }
  });

  interest::replication_rules rules;
  rules.tick = tick;
  rules.server_time_us = server_time_us;
  // The digest: in every frame of a digest tick, else only in reset frames (build_from's rule).
  rules.digest = !opt_.send_digest ? 0u : (opt_.digest_period <= 1 || tick % opt_.digest_period == 0) ? 2u : 1u;
  rules.byte_budget = opt_.byte_budget;
  rules.header_cost = static_cast<std::uint32_t>(net::frame_cost::header);
  rules.self_cost = static_cast<std::uint32_t>(net::frame_cost::self_position);
  rules.enter_cost = static_cast<std::uint32_t>(enter_cost);
  rules.leave_cost = static_cast<std::uint32_t>(leave_cost);
  rules.update_cost = static_cast<std::uint32_t>(update_cost);
  rules.near_limit = near_.limit;
  rules.near_below_sq = near_.below_sq;
  rules.near_above_sq = near_.above_sq;
  rules.mid_limit = mid_.limit;
  rules.mid_below_sq = mid_.below_sq;
  rules.mid_above_sq = mid_.above_sq;
  rules.mid_period = mid_period_;
  rules.far_period = far_period_;
  rules.slot_mask = entity_index_mask;
  const net::world_bounds& wb = quantizer_.world();
  rules.quant_lo[0] = wb.lo.x;
  rules.quant_lo[1] = wb.lo.y;
  rules.quant_lo[2] = wb.lo.z;
  for (int d = 0; d < 3; ++d) rules.quant_step[d] = quantizer_.step(d);
  // The workers would spin through the device's work: let them sleep until the wrapping below
  // (always, whatever park_between_phases says).
  if (pool != nullptr) pool->park();
  phase_end(times.stage_ms, times.stage_cpu_ms);
  const auto out = engine_->run(rules, clients_.size(), resident ? &rows : nullptr, while_waiting);
  phase_end(times.engine_ms, times.engine_cpu_ms);

  // The frames are the engine's, whole but for the enters' class, half extents and kind (from
  // the store: enters are few once the views are built); each goes to the sink from where the
  // engine put it. Chunks of requests per task, as on the CPU path.
  std::size_t threads = pool != nullptr ? pool->size() : 1;
  if (opt_.wrap_threads > 0) threads = std::min<std::size_t>(threads, opt_.wrap_threads);
  const std::size_t tasks = std::min(chunks, threads);
  std::atomic<std::size_t> next_chunk{0};
  const auto kinds = store.kinds();
  const auto classes = store.visibility_classes();
  const auto extents = store.presence_half_extents();
  const std::size_t enter_step = net::canonical_tick_update::enter_table + net::canonical_tick_update::name_bytes(0);
  const auto put32 = [](std::uint8_t* p, std::uint32_t v) { std::memcpy(p, &v, 4); };
  // Frames handed on without a copy where the engine keeps its buffer for them (share); each
  // chunk's frames hold one count of their own, so that the frames' copies and releases (here
  // and on the network's threads) do not all meet on the buffer's one counter.
  const bool sharing = share && out.records_keep != nullptr;
  run_each(pool, tasks, [&](std::size_t) {
    for (std::size_t ch = next_chunk.fetch_add(1, std::memory_order_relaxed); ch < chunks;
         ch = next_chunk.fetch_add(1, std::memory_order_relaxed)) {
      const std::size_t begin = ch * chunk, end = std::min(jobs, begin + chunk);
      std::shared_ptr<const void> chunk_keep;
      if (sharing) chunk_keep = std::make_shared<std::shared_ptr<const void>>(out.records_keep);
      for (std::size_t k = begin; k < end; ++k) {
        const interest::replication_result& res = out.results[k];
        client_state& s = clients_[requests[k].client];
        replication_stats stats;
        if ((st.jobs[k].flags & interest::job_reset) != 0) {
          stats.reset = true;
          s.reset_pending = false;
        }
        std::uint8_t* const frame = out.records + res.record_off;
        if (stats.reset) clear_view(s);
        thread_local std::vector<entity_id> entered;  // for follow_view
        entered.clear();
        for (std::uint32_t e = 0; e < res.enters; ++e) {
          std::uint8_t* const table = frame + res.enters_at + e * enter_step;
          std::uint32_t id = 0;
          std::memcpy(&id, table + 4, 4);
          entered.push_back(id);
          const std::size_t d = store.index_of(id);  // live: the engine found it in this tick's staging
          if (d == entity_store::npos) continue;
          put32(table + 8, classes[d]);
          const net::vec3f half = to_net(extents[d]);
          std::memcpy(table + 36, &half.x, 4);
          std::memcpy(table + 40, &half.y, 4);
          std::memcpy(table + 44, &half.z, 4);
          put32(table + 52, static_cast<std::uint32_t>(static_cast<std::uint8_t>(kinds[d])));
        }
        if (!entered.empty() || res.leaves > 0) follow_view(s, entered, frame, res.leaves > 0);
        s.hash = res.hash;
        s.engine_view_size = res.view_size;
        after_frame(s, tick, stats.reset, res.deferred_leaves > 0);
        stats.enters = res.enters;
        stats.leaves = res.leaves;
        stats.updates = res.updates;
        stats.deferred_enters = res.deferred_enters;
        stats.deferred_leaves = res.deferred_leaves;
        stats.deferred_updates = res.deferred_updates;
        stats.bytes = res.frame_size;
        if (sharing) {
          share(k, net::make_shared_frame_in(chunk_keep, {frame, res.frame_size}), stats);
        } else if (room) {
          // Copied where the caller sends it from (the engine's output is reused next tick).
          const auto to = room(k, res.frame_size);
          std::memcpy(to.data(), frame, res.frame_size);
          sink(k, to.first(res.frame_size), stats);
        } else {
          sink(k, {frame, res.frame_size}, stats);
        }
      }
      if (chunk_done) chunk_done(begin, end);
    }
  });
  rest();
  phase_end(times.wrap_ms, times.wrap_cpu_ms);
  phase_times_ = times;
}

void replicator::build_many(std::span<const replication_request> requests, const entity_store& store,
                            const interest::interest_tracker& tracker, std::uint64_t tick, std::uint64_t server_time_us,
                            interest::thread_pool* pool, const frame_sink& sink, const chunk_sink& chunk_done,
                            const frame_room& room, const frame_share& share,
                            const std::function<void()>* side_work) {
  // The caller's side work, exactly once per call: through `once`, which an engine calls while
  // the device works; else (the CPU path, no requests, an engine that threw before calling it)
  // after the frames. What it throws is held until then, so that it never reads as the engine's
  // failure, and rethrown.
  const bool has_side = side_work != nullptr && static_cast<bool>(*side_work);
  bool side_ran = false;
  std::exception_ptr side_error;
  const auto once = [&] {
    if (side_ran) return;
    side_ran = true;
    try {
      (*side_work)();
    } catch (...) {
      side_error = std::current_exception();
    }
  };
  // By reference: no allocation (a reference_wrapper fits std::function's own storage).
  const std::function<void()> once_ref = std::ref(once);
  const auto finish = [&] {
    if (has_side) once();
    if (side_error) std::rethrow_exception(side_error);
  };
  if (requests.empty()) {
    // Entities staged ahead for this tick are not used: the engine drops them.
    if (prestaged_ && on_engine()) engine_->discard_entities();
    prestaged_ = false;
    return finish();
  }
  if (on_engine()) {
    bool built = false;
    try {
      build_on_engine(requests, store, tracker, tick, server_time_us, pool, sink, chunk_done, room, share,
                      has_side ? &once_ref : nullptr);
      built = true;
    } catch (const std::exception& e) {
      // Nothing reached the sink: this tick is built on the CPU, every client starting over.
      note_engine_error(e);
      reset_all_clients();
    }
    if (built) return finish();  // outside the try: the side work's exception is not the engine's
  }
  // The snapshot: one quantization per entity rather than one per update sent.
  const std::size_t n = store.size();
  // Each client is sent tens of updates a tick, so with clients at least 1/16 of the entities
  // (the default) the snapshot is the smaller job.
  const bool snapshot = opt_.snapshot_entities_per_client > 0 && requests.size() * opt_.snapshot_entities_per_client >= n;
  if (snapshot) {
    reserve_with_headroom(snapshot_, n);
    snapshot_.resize(n);
    const auto ids = store.ids();
    const auto pos = store.positions();
    const auto vel = store.velocities();
    run_each(pool, (n + snapshot_chunk - 1) / snapshot_chunk, [&](std::size_t task) {
      const std::size_t end = std::min(n, (task + 1) * snapshot_chunk);
      for (std::size_t k = task * snapshot_chunk; k < end; ++k) {
        snapshot_[k].position = pos[k];
        snapshot_[k].id = ids[k];
        snapshot_[k].update = wire_update(ids[k], pos[k], vel[k], quantizer_);
      }
    });
  }
  const snapshot_source from_snapshot{store, snapshot_.data(), snapshot ? n : 0};
  const store_source from_store{store, quantizer_};

  // One task per thread, each with its own writer, taking chunks of requests from a shared
  // counter (a client's frame does not depend on who builds it).
  const std::size_t chunk = std::max<std::uint32_t>(1, opt_.clients_per_task);
  const std::size_t chunks = (requests.size() + chunk - 1) / chunk;
  const std::size_t tasks = std::min<std::size_t>(chunks, pool != nullptr ? pool->size() : 1);
  while (writers_.size() < tasks) writers_.push_back(std::make_unique<replication_writer>());
  std::atomic<std::size_t> next_chunk{0};
  run_each(pool, tasks, [&](std::size_t task) {
    replication_writer& writer = *writers_[task];
    for (std::size_t ch = next_chunk.fetch_add(1, std::memory_order_relaxed); ch < chunks;
         ch = next_chunk.fetch_add(1, std::memory_order_relaxed)) {
      const std::size_t begin = ch * chunk, end = std::min(requests.size(), begin + chunk);
      for (std::size_t k = begin; k < end; ++k) {
        if (k + 1 < requests.size()) prefetch_client(requests[k + 1].client);
        const replication_request& r = requests[k];
        replication_stats st;
        const auto frame =
            snapshot ? build_from(from_snapshot, r.client, store, tracker, tick, server_time_us, r.last_input_sequence,
                                  writer, &st, &room, k)
                     : build_from(from_store, r.client, store, tracker, tick, server_time_us, r.last_input_sequence,
                                  writer, &st, &room, k);
        sink(k, frame, st);
      }
      if (chunk_done) chunk_done(begin, end);
    }
  });
  finish();
}

}  // namespace zone
