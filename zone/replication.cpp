// Replication (zone.h): per client, one tick_update moving the client's view toward the
// observer's visible set within a byte budget. Algorithm in docs/zone.md.
#include <algorithm>
#include <functional>
#include <cmath>

#include "zone.h"

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

/// Upper bound on the bytes one entered entity adds to a frame: the entity_state table (vtable,
/// fields, padding), its name string and its offset in the enters vector.
constexpr std::size_t enter_cost_base = 128;
constexpr std::size_t leave_cost = sizeof(std::uint32_t);
constexpr std::size_t update_cost = sizeof(net::wire::entity_update);

net::vec3f to_net(const vec3& v) { return {v.x, v.y, v.z}; }

float distance_sq(const vec3& a, const vec3& b) {
  const float dx = a.x - b.x, dy = a.y - b.y, dz = a.z - b.z;
  return dx * dx + dy * dy + dz * dz;
}

float distance(const vec3& a, const vec3& b) { return std::sqrt(distance_sq(a, b)); }

/// Exactly `std::sqrt(d2) < limit` (limit >= 0), given below_sq = limit^2 * 0.9999f and
/// above_sq = limit^2 * 1.0001f: the square root only when d2 lies within a relative 1e-4 of
/// limit^2, where rounding could decide it.
bool sqrt_below(float d2, float limit, float below_sq, float above_sq) {
  if (d2 < below_sq) return true;
  if (d2 > above_sq) return false;
  return std::sqrt(d2) < limit;
}

}  // namespace

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
  s.view.clear();
  s.last_sent.clear();
  s.hash = 0;
  return c;
}

void replicator::remove_client(client_id c) {
  if (c >= clients_.size() || !clients_[c].active) return;
  client_state& s = clients_[c];
  s.active = false;
  s.observer = null_entity;
  s.view.clear();
  s.last_sent.clear();
  s.hash = 0;
  free_clients_.push_back(c);
}

void replicator::set_observer(client_id c, entity_id observer) { clients_[c].observer = observer; }

void replicator::resync(client_id c) { clients_[c].reset_pending = true; }

std::span<const std::uint8_t> replicator::build(client_id c, const entity_store& store, const interest_tracker& tracker,
                                                std::uint64_t tick, std::uint64_t server_time_us,
                                                std::uint32_t last_input_sequence, replication_writer& w,
                                                replication_stats* stats) {
  client_state& s = clients_[c];
  net::tick_update_writer& writer = w.frame_;
  replication_stats st;
  writer.begin(tick, server_time_us, last_input_sequence);
  if (s.reset_pending) {
    s.view.clear();
    s.last_sent.clear();
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
  reserve_with_headroom(w.due_, view_size);
  w.due_.clear();
  w.enters_.clear();
  w.left_.clear();

  // An entry of both the view and the visible set is due when its staleness reaches its tier's
  // period (the tier from the squared distance; the square root only near a boundary).
  const std::uint32_t tick32 = static_cast<std::uint32_t>(tick);
  const entity_id* const view = s.view.data();
  std::uint32_t* const last_sent = s.last_sent.data();
  const auto consider = [&](std::size_t j) {
    const std::size_t k = store.index_of(view[j]);
    if (k == entity_store::npos) return;
    const float d2 = distance_sq(eye, pos[k]);
    const std::uint32_t period = sqrt_below(d2, near_.limit, near_.below_sq, near_.above_sq)  ? 1
                                 : sqrt_below(d2, mid_.limit, mid_.below_sq, mid_.above_sq) ? mid_period_
                                                                                            : far_period_;
    const std::uint32_t staleness = tick32 - last_sent[j];
    if (staleness >= period) {
      w.due_.push_back({static_cast<std::uint32_t>(j), static_cast<std::uint32_t>(k), d2, staleness});
    }
  };

  if (visible.size() == view_size && std::equal(visible.begin(), visible.end(), view)) {
    // The usual tick: the view is the visible set; no leaves, no enters.
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
      if (!fits(enter_cost_base)) {
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
  const vec3* const vel = store.velocities().data();
  const auto send_update = [&](std::uint32_t j, std::uint32_t k) {
    writer.add_update({view[j], quantizer_.quantize(to_net(pos[k])), net::quantize_velocity(to_net(vel[k]))});
    last_sent[j] = tick32;
  };
  const std::size_t used = writer.size_estimate();
  const std::size_t room = used >= opt_.byte_budget ? 0 : (opt_.byte_budget - used) / update_cost;
  if (room >= w.due_.size()) {
    for (const auto& u : w.due_) send_update(u.index, u.dense);
    st.updates = static_cast<std::uint32_t>(w.due_.size());
  } else {
    reserve_with_headroom(w.ranked_, w.due_.size());
    w.ranked_.clear();
    for (const auto& u : w.due_) {
      const float d = std::sqrt(u.distance_sq);
      w.ranked_.push_back({-static_cast<float>(u.staleness) / std::max(d, 1.0f), u.index, view[u.index], u.dense});
    }
    const auto cut = w.ranked_.begin() + static_cast<std::ptrdiff_t>(room);
    std::nth_element(w.ranked_.begin(), cut, w.ranked_.end(), by_priority);
    std::sort(w.ranked_.begin(), cut, by_priority);
    for (std::size_t n = 0; n < room; ++n) send_update(w.ranked_[n].index, w.ranked_[n].dense);
    st.updates = static_cast<std::uint32_t>(room);
    st.deferred_updates = static_cast<std::uint32_t>(w.due_.size() - room);
  }

  // The new view when it changed: what was kept plus what entered, sorted. (Otherwise the
  // updates above have already refreshed last_sent in place.)
  if (entered > 0 || !w.left_.empty()) {
    std::sort(w.enters_.begin(), w.enters_.begin() + static_cast<std::ptrdiff_t>(entered),
              [](const pending& a, const pending& b) { return a.id < b.id; });
    const std::size_t next_size = view_size + entered - w.left_.size();
    reserve_with_headroom(w.next_view_, next_size);
    reserve_with_headroom(w.next_last_sent_, next_size);
    w.next_view_.clear();
    w.next_last_sent_.clear();
    std::size_t e = 0, l = 0;
    for (std::size_t v = 0; v < view_size; ++v) {
      while (e < entered && w.enters_[e].id < view[v]) {
        w.next_view_.push_back(w.enters_[e++].id);
        w.next_last_sent_.push_back(tick32);
      }
      if (l < w.left_.size() && w.left_[l] == v) {
        ++l;  // sent as a leave
        continue;
      }
      w.next_view_.push_back(view[v]);
      w.next_last_sent_.push_back(last_sent[v]);
    }
    while (e < entered) {
      w.next_view_.push_back(w.enters_[e++].id);
      w.next_last_sent_.push_back(tick32);
    }
    reserve_with_headroom(s.view, next_size);
    reserve_with_headroom(s.last_sent, next_size);
    s.view.assign(w.next_view_.begin(), w.next_view_.end());
    s.last_sent.assign(w.next_last_sent_.begin(), w.next_last_sent_.end());
  }

  if (opt_.send_digest && (st.reset || opt_.digest_period <= 1 || tick % opt_.digest_period == 0)) {
    writer.set_digest({tick, s.hash, static_cast<std::uint32_t>(s.view.size())});
  }
  const auto frame = writer.finish();
  st.bytes = frame.size();
  if (stats) *stats = st;
  return frame;
}

void replicator::build_many(std::span<const replication_request> requests, const entity_store& store,
                            const interest_tracker& tracker, std::uint64_t tick, std::uint64_t server_time_us,
                            interest::thread_pool* pool, const frame_sink& sink) {
  const std::size_t chunk = std::max<std::uint32_t>(1, opt_.clients_per_task);
  const std::size_t tasks = (requests.size() + chunk - 1) / chunk;
  while (writers_.size() < tasks) writers_.push_back(std::make_unique<replication_writer>());
  // Each task owns one writer and distinct clients; build() reads only shared, unchanging state.
  run_each(pool, tasks, [&](std::size_t task) {
    replication_writer& writer = *writers_[task];
    const std::size_t end = std::min(requests.size(), (task + 1) * chunk);
    for (std::size_t k = task * chunk; k < end; ++k) {
      replication_stats st;
      const auto frame =
          build(requests[k].client, store, tracker, tick, server_time_us, requests[k].last_input_sequence, writer, &st);
      sink(k, frame, st);
    }
  });
}

}  // namespace zone
