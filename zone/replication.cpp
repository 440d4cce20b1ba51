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

/// Exactly `std::sqrt(d2) < limit` (limit >= 0), without the square root unless d2 lies within
/// a relative 1e-4 of limit^2, where rounding could decide it.
bool sqrt_below(float d2, float limit) {
  const float l2 = limit * limit;
  if (d2 < l2 * 0.9999f) return true;
  if (d2 > l2 * 1.0001f) return false;
  return std::sqrt(d2) < limit;
}

}  // namespace

replicator::replicator(replication_options opt) : opt_(opt), quantizer_(opt.world) {}

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
                                                std::uint32_t last_input_sequence, net::tick_update_writer& writer,
                                                replication_stats* stats) {
  client_state& s = clients_[c];
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
  const auto pos = store.positions();

  // Merge the visible set with the view (both sorted): leaves are written at once (they come
  // first), enters and due updates are collected with their priorities.
  // Room for the most this tick can need, with headroom, so that sizes creeping up from tick to
  // tick do not reallocate every time (the tick allocates nothing in steady state).
  reserve_with_headroom(s.keep, s.view.size());
  reserve_with_headroom(s.enters, visible.size());
  reserve_with_headroom(s.updates, std::min(visible.size(), s.view.size()));
  reserve_with_headroom(s.next_view, s.view.size() + visible.size());
  reserve_with_headroom(s.next_last_sent, s.view.size() + visible.size());
  s.keep.assign(s.view.size(), 1);
  s.enters.clear();
  s.updates.clear();
  std::size_t i = 0, j = 0;
  while (i < visible.size() || j < s.view.size()) {
    if (j < s.view.size() && (i == visible.size() || s.view[j] < visible[i])) {
      if (fits(leave_cost)) {
        writer.add_leave(s.view[j]);
        s.keep[j] = 0;
        s.hash = net::digest_remove(s.hash, s.view[j]);
        ++st.leaves;
      } else {
        ++st.deferred_leaves;
      }
      ++j;
    } else if (j == s.view.size() || visible[i] < s.view[j]) {
      const std::size_t k = store.index_of(visible[i]);
      if (k != entity_store::npos) {
        s.enters.push_back({distance(eye, pos[k]), static_cast<std::uint32_t>(k), visible[i], static_cast<std::uint32_t>(k)});
      }
      ++i;
    } else {
      const std::size_t k = store.index_of(visible[i]);
      if (k != entity_store::npos) {
        // The tier from the squared distance; the square root only for what is due (its priority).
        const float d2 = distance_sq(eye, pos[k]);
        const std::uint64_t period = sqrt_below(d2, opt_.near_distance)  ? 1
                                     : sqrt_below(d2, opt_.mid_distance) ? std::max<std::uint32_t>(1, opt_.mid_period)
                                                                         : std::max<std::uint32_t>(1, opt_.far_period);
        const std::uint64_t staleness = tick - s.last_sent[j];
        if (staleness >= period) {
          const float d = std::sqrt(d2);
          s.updates.push_back({-static_cast<float>(staleness) / std::max(d, 1.0f), static_cast<std::uint32_t>(j),
                               visible[i], static_cast<std::uint32_t>(k)});
        }
      }
      ++i;
      ++j;
    }
  }

  const auto by_priority = [](const pending& a, const pending& b) {
    return a.priority < b.priority || (a.priority == b.priority && a.id < b.id);
  };

  // Enters, closest first, with full state.
  std::sort(s.enters.begin(), s.enters.end(), by_priority);
  std::size_t entered = 0;
  for (const pending& e : s.enters) {
    if (!fits(enter_cost_base)) {
      st.deferred_enters = static_cast<std::uint32_t>(s.enters.size() - entered);
      break;
    }
    const std::size_t k = e.index;
    writer.add_enter({e.id, static_cast<net::entity_kind>(store.kinds()[k]), store.visibility_classes()[k],
                      to_net(pos[k]), to_net(store.velocities()[k]), to_net(store.presence_half_extents()[k]), {}});
    s.hash = net::digest_add(s.hash, e.id);
    s.enters[entered++] = e;  // compact: the first `entered` were sent
  }
  st.enters = static_cast<std::uint32_t>(entered);

  // Updates of the view, most stale per metre first. Each costs exactly update_cost in the
  // writer's estimate, so the ones that fit are the first `room` by priority: when the budget
  // binds they are selected (nth_element) and sent in priority order; when everything fits the
  // order changes nothing that is sent, and the sort is skipped (view order).
  const std::size_t used = writer.size_estimate();
  const std::size_t room = used >= opt_.byte_budget ? 0 : (opt_.byte_budget - used) / update_cost;
  if (room < s.updates.size()) {
    const auto cut = s.updates.begin() + static_cast<std::ptrdiff_t>(room);
    std::nth_element(s.updates.begin(), cut, s.updates.end(), by_priority);
    std::sort(s.updates.begin(), cut, by_priority);
  }
  for (const pending& u : s.updates) {
    if (!fits(update_cost)) {
      ++st.deferred_updates;
      continue;
    }
    const std::size_t k = u.dense;
    writer.add_update({u.id, quantizer_.quantize(to_net(pos[k])), net::quantize_velocity(to_net(store.velocities()[k]))});
    s.last_sent[u.index] = tick;
    ++st.updates;
  }

  // The new view: what was kept plus what entered, sorted.
  s.enters.resize(entered);
  std::sort(s.enters.begin(), s.enters.end(), [](const pending& a, const pending& b) { return a.id < b.id; });
  s.next_view.clear();
  s.next_last_sent.clear();
  std::size_t e = 0;
  for (std::size_t v = 0; v <= s.view.size(); ++v) {
    const entity_id bound = v < s.view.size() ? s.view[v] : 0xffffffffu;
    while (e < s.enters.size() && s.enters[e].id < bound) {
      s.next_view.push_back(s.enters[e++].id);
      s.next_last_sent.push_back(tick);
    }
    if (v < s.view.size() && s.keep[v]) {
      s.next_view.push_back(s.view[v]);
      s.next_last_sent.push_back(s.last_sent[v]);
    }
  }
  while (e < s.enters.size()) {  // an id of 0xffffffff, in theory
    s.next_view.push_back(s.enters[e++].id);
    s.next_last_sent.push_back(tick);
  }
  std::swap(s.view, s.next_view);
  std::swap(s.last_sent, s.next_last_sent);

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
  while (writers_.size() < tasks) writers_.push_back(std::make_unique<net::tick_update_writer>());
  // Each task owns one writer and distinct clients; build() reads only shared, unchanging state.
  run_each(pool, tasks, [&](std::size_t task) {
    net::tick_update_writer& writer = *writers_[task];
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
