// The interest tracker (interest_tracker.h; algorithm in docs/zone.md).
//
// One finder call per tick with every AOI box grown by the hysteresis margin h yields, per
// observer, every target that could be visible under either rule: inside the grown box (the
// "stay" rule for targets already visible) is exactly what the finder reports, and inside the
// exact box (the "enter" rule) is a subset of it, because float rounding is monotone:
// p - (a + h) <= p - a and p + a <= p + (a + h). Each candidate is then classified with the exact
// test: a target already visible stays; a new one enters only when its presence box meets the
// exact AOI box. Targets of the previous set that are not candidates leave.
#include <algorithm>
#include <functional>
#include <atomic>
#include <bit>
#include <chrono>
#include <cmath>
#include <utility>

#include "interest_tracker.h"
#include "measure.h"

namespace zone::interest {

namespace {

/// run_tasks without a heap allocation per call: std::function keeps a
/// reference_wrapper in place, where a lambda capturing several references would be copied to
/// the heap (the tick allocates nothing in steady state).
/// resize() with 25% spare capacity when it must grow, so that counts creeping up from tick to
/// tick do not reallocate every time.
template <class V>
void resize_with_headroom(V& v, std::size_t n) {
  if (v.capacity() < n) v.reserve(n + n / 4 + 64);
  v.resize(n);
}

template <class F>
void run_each(thread_pool* pool, std::size_t n, F&& task) {
  run_tasks(pool, n, std::ref(task));
}

using clock_type = std::chrono::steady_clock;

constexpr std::uint32_t no_row = 0xffffffffu;
constexpr std::size_t no_pair = static_cast<std::size_t>(-1);

/// Squared distance of two points, as an order-preserving unsigned key (non-negative floats order
/// like their bit patterns).
std::uint32_t distance_key(const vec3& a, const vec3& b) {
  const float dx = a.x - b.x, dy = a.y - b.y, dz = a.z - b.z;
  return std::bit_cast<std::uint32_t>(dx * dx + dy * dy + dz * dz);
}

std::uint64_t mix(std::uint64_t h, std::uint64_t v) {
  h ^= v + 0x9e3779b97f4a7c15ull + (h << 6) + (h >> 2);
  return h * 0xff51afd7ed558ccdull;
}

}  // namespace

interest_tracker::interest_tracker(pair_finder& finder, thread_pool* pool, interest_options opt)
    : finder_(&finder), pool_(pool), opt_(opt) {}

std::size_t interest_tracker::row_of(entity_id id) const {
  const std::uint32_t slot = slot_of(id);
  if (id == null_entity || slot >= row_of_slot_.size()) return npos;
  const std::uint32_t row = row_of_slot_[slot];
  if (row >= ids_.size() || ids_[row] != id) return npos;
  return row;
}

void interest_tracker::build_boxes(const entity_columns& in, box_set& out) const {
  namespace cb = category_bits;
  const std::size_t n = in.n;
  out.resize(2 * n);
  const vec3* pos = in.position;
  const vec3* aoi = in.aoi_half;
  const vec3* body = in.presence_half;
  const std::uint32_t* cls = in.visibility;
  const std::uint32_t* sees = in.sees;
  const float h = opt_.hysteresis;
  // In fixed chunks on the pool (each box is written by exactly one task).
  const std::size_t chunk = 8192;
  run_each(n > chunk ? pool_ : nullptr, (n + chunk - 1) / chunk, [&](std::size_t c) {
    for (std::size_t k = c * chunk, end = std::min(n, (c + 1) * chunk); k < end; ++k) {
      const vec3 p = pos[k];
      // AOI box grown by the margin: the finder reports every target inside it.
      const vec3 g{aoi[k].x + h, aoi[k].y + h, aoi[k].z + h};
      out.lo_x[2 * k] = p.x - g.x;
      out.lo_y[2 * k] = p.y - g.y;
      out.lo_z[2 * k] = p.z - g.z;
      out.hi_x[2 * k] = p.x + g.x;
      out.hi_y[2 * k] = p.y + g.y;
      out.hi_z[2 * k] = p.z + g.z;
      out.category[2 * k] = cb::aoi;
      out.mask[2 * k] = sees[k];
      // Presence box. Its mask is 0 (not aoi): with the contract's symmetric rule
      // (cat_a & mask_b) | (cat_b & mask_a), a presence mask of aoi would let every AOI/presence
      // pair through whatever the classes; with 0 only (class & sees of the observer) counts.
      const vec3 b = body[k];
      out.lo_x[2 * k + 1] = p.x - b.x;
      out.lo_y[2 * k + 1] = p.y - b.y;
      out.lo_z[2 * k + 1] = p.z - b.z;
      out.hi_x[2 * k + 1] = p.x + b.x;
      out.hi_y[2 * k + 1] = p.y + b.y;
      out.hi_z[2 * k + 1] = p.z + b.z;
      out.category[2 * k + 1] = cls[k];
      out.mask[2 * k + 1] = 0;
    }
  });
}

void interest_tracker::begin_update(const entity_columns& in) {
  slot_bits_ = in.slot_bits;
  std::size_t slots = in.slot_count;
  if (slots == 0) {
    for (std::size_t i = 0; i < in.n; ++i) slots = std::max<std::size_t>(slots, slot_of(in.ids[i]) + std::size_t{1});
  }
  slot_count_ = std::max(slot_count_, slots);
}

std::optional<box_error> interest_tracker::update(const entity_columns& in) {
  begin_update(in);
  if (engine_ != nullptr && engine_error_.empty() && opt_.max_visible == 0) {
    try {
      return update_on_engine(in);
    } catch (const std::exception& e) {
      // A device error: the host path takes over from the last update's sets, which are intact
      // (update_on_engine changes the tracker only after the engine's call succeeded).
      engine_error_ = e.what();
      engine_synced_ = false;
    }
  }
  return update_on_host(in);
}

std::optional<box_error> interest_tracker::name_box_error(const entity_columns& in,
                                                                   std::optional<box_error> err) const {
  if (!err) return err;
  const std::size_t k = err->index / 2;
  err->message = "entity " + std::to_string(in.ids[k]) + (err->index % 2 ? " (presence box): " : " (AOI box): ") +
                 err->message;
  return err;
}

std::optional<box_error> interest_tracker::update_on_host(const entity_columns& in) {
  auto t0 = clock_type::now();
  build_boxes(in, boxes_);
  const double boxes_ms = ms_since(t0);
  t0 = clock_type::now();
  std::span<const id_pair> pairs;
  auto err = opt_.finder_view ? finder_->find_view(boxes_, pairs_, pairs) : finder_->find(boxes_, pairs_);
  if (err) return name_box_error(in, std::move(err));
  if (!opt_.finder_view) pairs = pairs_;
  const double find_ms = ms_since(t0);
  if (auto apply_err = apply_pairs(in, boxes_, pairs)) return apply_err;
  stats_.boxes_ms = boxes_ms;
  stats_.find_ms = find_ms;
  return std::nullopt;
}

void interest_tracker::set_engine(visibility_engine* engine) {
  adopt_engine_output();  // an earlier engine's output stays readable through the host arrays
  engine_ = engine;
  engine_synced_ = false;
  engine_error_.clear();
}

void interest_tracker::map_rows() { map_rows_into(ids_, row_of_slot_); }

void interest_tracker::map_rows_into(const std::vector<entity_id>& ids,
                                     std::vector<std::uint32_t>& row_of_slot) const {
  // Entries of slots not in `ids` may be stale; row_of() checks the handle.
  const std::size_t n = ids.size();
  if (row_of_slot.size() < slot_count_) row_of_slot.resize(slot_count_, no_row);
  const std::size_t chunk = 16384;
  run_each(n > chunk ? pool_ : nullptr, (n + chunk - 1) / chunk, [&](std::size_t c) {
    for (std::size_t i = c * chunk, e = std::min(n, (c + 1) * chunk); i < e; ++i) {
      row_of_slot[slot_of(ids[i])] = static_cast<std::uint32_t>(i);
    }
  });
}

std::span<const entity_id> interest_tracker::fetched_row(std::size_t row) const {
  if (!fetched_.load(std::memory_order_acquire)) {
    const std::lock_guard lock(fetch_mutex_);
    if (!fetched_.load(std::memory_order_relaxed)) {
      const visibility_lists all = engine_->fetch_all_visible();
      full_list_ = {all.data, all.off, nullptr};
      fetched_.store(true, std::memory_order_release);
    }
  }
  return full_list_.row(row);
}

void interest_tracker::point_lists_at_host() {
  vis_list_ = {vis_.data(), vis_off_.data(), vis_len_.data()};
  partial_ = false;
  enter_list_ = {enter_.data(), vis_off_.data(), enter_len_.data()};
  leave_list_ = {leave_.data(), leave_off_.data(), leave_len_.data()};
}

void interest_tracker::adopt_engine_output() {
  if (!last_by_engine_) return;
  // The engine's compact lists into the host path's layout: visible sets and enters share the
  // visible offsets (enters are a subset of the visible set), leaves have their own.
  const std::size_t n = ids_.size();
  const visibility_output& o = engine_out_;
  // Every row's visible set: the engine may have kept some rows' sets on the device. If the device
  // is gone (an engine failure), those rows start again from empty sets (their targets enter anew;
  // nothing on the host read them).
  bool device_lost = false;
  if (partial_ && n > 0) {
    try {
      (void)fetched_row(0);
    } catch (const std::exception&) {
      device_lost = true;
    }
  }
  const auto row_of_output = [&](std::size_t r) -> std::span<const entity_id> {
    if (!partial_ || demand_rows_[r] != 0) return vis_list_.row(r);
    if (device_lost) return {};
    return full_list_.row(r);
  };
  std::vector<std::uint32_t> len(n);
  vis_off_.resize(n + 1);
  vis_off_[0] = 0;
  for (std::size_t r = 0; r < n; ++r) {
    len[r] = static_cast<std::uint32_t>(row_of_output(r).size());
    vis_off_[r + 1] = vis_off_[r] + len[r];
  }
  vis_.resize(vis_off_[n]);
  enter_.resize(vis_off_[n]);
  vis_len_.resize(n);
  enter_len_.resize(n);
  for (std::size_t r = 0; r < n; ++r) {
    const auto row = row_of_output(r);
    std::copy(row.begin(), row.end(), vis_.begin() + vis_off_[r]);
    vis_len_[r] = len[r];
    const std::uint32_t en = o.enter_off[r + 1] - o.enter_off[r];
    enter_len_[r] = en <= len[r] ? en : 0u;  // 0 only for a row lost with the device
    std::copy(o.enters + o.enter_off[r], o.enters + o.enter_off[r] + enter_len_[r], enter_.begin() + vis_off_[r]);
  }
  leave_.assign(o.leaves, o.leaves + o.leave_off[n]);
  leave_off_.assign(o.leave_off, o.leave_off + n + 1);
  leave_len_.resize(n);
  for (std::size_t r = 0; r < n; ++r) leave_len_[r] = o.leave_off[r + 1] - o.leave_off[r];
  point_lists_at_host();
  last_by_engine_ = false;
}

std::optional<box_error> interest_tracker::update_on_engine(const entity_columns& in) {
  const auto t0 = clock_type::now();
  const std::size_t n = in.n;
  const std::span<const entity_id> ids(in.ids, n);
  if (!engine_synced_) {
    // The engine does not hold the last update's sets (first use, or the host path made them):
    // hand them over in compact form.
    const std::size_t prev_rows = ids_.size();
    std::vector<std::uint32_t> off, vis;
    if (prev_rows > 0) {
      off.resize(prev_rows + 1);
      off[0] = 0;
      for (std::size_t r = 0; r < prev_rows; ++r) off[r + 1] = off[r] + static_cast<std::uint32_t>(visible(r).size());
      vis.reserve(off[prev_rows]);
      for (std::size_t r = 0; r < prev_rows; ++r) {
        const auto row = visible(r);
        vis.insert(vis.end(), row.begin(), row.end());
      }
    }
    engine_->load_previous(ids_, slot_bits_, off, vis);
    engine_synced_ = true;
  }
  visibility_input vin;
  vin.n = n;
  vin.ids = ids.data();
  vin.slot_bits = slot_bits_;
  vin.position = reinterpret_cast<const float*>(in.position);
  vin.aoi_half = reinterpret_cast<const float*>(in.aoi_half);
  vin.body_half = reinterpret_cast<const float*>(in.presence_half);
  vin.visibility = in.visibility;
  vin.sees = in.sees;
  vin.hysteresis = opt_.hysteresis;
  vin.static_version = in.layout_version;
  if (view_demand_ != nullptr) {
    // Per row: is its visible set read on the host (by slot, from the caller).
    next_demand_rows_.resize(n);
    const std::vector<std::uint8_t>& by_slot = *view_demand_;
    const std::size_t chunk = 16384;
    run_each(n > chunk ? pool_ : nullptr, (n + chunk - 1) / chunk, [&](std::size_t c) {
      for (std::size_t i = c * chunk, e = std::min(n, (c + 1) * chunk); i < e; ++i) {
        const std::uint32_t slot = slot_of(ids[i]);
        next_demand_rows_[i] = slot < by_slot.size() ? by_slot[slot] : std::uint8_t{0};
      }
    });
    vin.wanted = next_demand_rows_.data();
  }
  // While the device works: this update's rows and slot map, into spare buffers (swapped in only
  // if the update succeeds, so that a refused one changes nothing here either).
  double host_ms = 0;
  bool host_done = false;
  vin.while_waiting = [&] {
    host_done = true;
    const auto th = clock_type::now();
    next_ids_.assign(ids.begin(), ids.end());
    map_rows_into(next_ids_, spare_row_of_slot_);
    host_ms = ms_since(th);
  };
  const auto t_engine = clock_type::now();
  const auto bad = engine_->update(vin, engine_out_);
  const double engine_ms = ms_since(t_engine);
  if (bad) {
    // Nothing changed, on the engine or here. The host's validation names the box exactly as the
    // host path would.
    build_boxes(in, boxes_);
    auto err = validate(boxes_, pool_);
    if (!err) err = box_error{*bad, "box " + std::to_string(*bad) + " is invalid"};
    return name_box_error(in, std::move(err));
  }
  if (!host_done) {
    next_ids_.assign(ids.begin(), ids.end());
    map_rows_into(next_ids_, spare_row_of_slot_);
  }
  std::swap(ids_, next_ids_);
  std::swap(row_of_slot_, spare_row_of_slot_);
  std::swap(demand_rows_, next_demand_rows_);
  partial_ = !engine_out_.visible_complete;
  fetched_.store(false, std::memory_order_relaxed);
  vis_list_ = {engine_out_.visible, engine_out_.visible_off, nullptr};
  enter_list_ = {engine_out_.enters, engine_out_.enter_off, nullptr};
  leave_list_ = {engine_out_.leaves, engine_out_.leave_off, nullptr};
  last_by_engine_ = true;

  stats_ = {};
  stats_.pairs = engine_out_.pairs;
  stats_.candidates = engine_out_.candidates;
  stats_.visible = engine_out_.visible_total;
  stats_.enters = engine_out_.enter_off[n];
  stats_.leaves = engine_out_.leave_off[n];
  stats_.find_ms = engine_ms;
  stats_.diff_ms = ms_since(t0) - engine_ms + host_ms;  // the host's own work, overlapped or not
  stats_.on_engine = true;
  stats_.engine_timing = engine_out_.timing;
  return std::nullopt;
}

std::optional<box_error> interest_tracker::apply_pairs(const entity_columns& in,
                                                                const box_set& boxes,
                                                                std::span<const id_pair> pairs) {
  const auto t0 = clock_type::now();
  begin_update(in);
  if (boxes.size() != 2 * in.n) {
    return box_error{boxes.size(), "box set has " + std::to_string(boxes.size()) + " boxes, expected 2 x " +
                                                 std::to_string(in.n) + " entities"};
  }
  adopt_engine_output();  // the previous sets in this path's arrays
  const std::size_t n = in.n;
  const std::span<const entity_id> ids(in.ids, n);

  // Box 2k is entity k's AOI box, 2k+1 its presence box; only mixed pairs mean "k sees j" (an
  // entity's own AOI and presence boxes aside). The visibility rule needs no re-check here: a
  // mixed pair qualifies (the contract: every pair given qualifies) exactly when
  // (aoi & 0) | (class & sees) != 0, i.e. when k sees j's class, and reading the two columns
  // for every pair cost two cache misses each in both passes below.
  const auto split = [](const id_pair& p, std::uint32_t& observer, std::uint32_t& target) {
    if ((p.a & 1u) == (p.b & 1u)) return false;
    const std::uint32_t aoi_box = (p.a & 1u) ? p.b : p.a;
    const std::uint32_t presence_box = (p.a & 1u) ? p.a : p.b;
    observer = aoi_box / 2;
    target = presence_box / 2;
    return observer != target;
  };

  // 1. Count candidates per (task, observer row) over fixed slices of the pair list, checking
  //    the pair ids on the way. Private counters per task: no atomics, and the fill below writes
  //    each task's candidates at offsets of its own. Only scratch memory is written before the
  //    checks pass, so a refused input changes nothing.
  //    Each task's counters are a row-indexed array of their own ([task][row]: laid out by row
  //    instead, 16 threads incrementing counters of one cache line thrashed it between cores);
  //    at most one pair task per thread bounds that matrix at threads x rows, and the offsets
  //    pass below runs over fixed chunks of rows in parallel.
  const std::size_t threads = pool_ != nullptr ? pool_->size() : 1;
  const std::size_t pair_tasks = threads == 1 ? 1 : std::clamp<std::size_t>(pairs.size() / 32768, 1, threads);
  const auto pair_begin = [&](std::size_t t) { return pairs.size() * t / pair_tasks; };
  // Fixed chunks of rows for the parallel passes over rows (the output never depends on them).
  const std::size_t row_chunk = 4096;
  const std::size_t row_chunks = (n + row_chunk - 1) / row_chunk;
  const auto chunk_rows = [&](std::size_t c) { return std::pair{c * row_chunk, std::min(n, (c + 1) * row_chunk)}; };
  task_cursor_.resize(pair_tasks * n);
  task_bad_.assign(pair_tasks, no_pair);
  const std::size_t box_count = boxes.size();
  auto t_part = clock_type::now();
  run_each(pair_tasks > 1 ? pool_ : nullptr, pair_tasks, [&](std::size_t task) {
    std::uint32_t* count = task_cursor_.data() + task * n;
    std::fill(count, count + n, 0u);
    for (std::size_t k = pair_begin(task), e = pair_begin(task + 1); k < e; ++k) {
      const auto& p = pairs[k];
      if (std::max(p.a, p.b) >= box_count) {
        task_bad_[task] = std::min(task_bad_[task], k);
        continue;
      }
      std::uint32_t o, t;
      if (split(p, o, t)) ++count[o];
    }
  });
  for (const std::size_t k : task_bad_) {
    if (k == no_pair) continue;
    const auto& p = pairs[k];
    return box_error{std::max(p.a, p.b), "pair (" + std::to_string(p.a) + ", " + std::to_string(p.b) +
                                                      ") refers to a box beyond the set"};
  }

  const double count_ms = ms_since(t_part);
  t_part = clock_type::now();

  // 2. Row offsets, and each (row, task)'s first slot: counts become cursors. Two passes over
  //    fixed chunks of rows: chunk totals, then (after a scan of those) offsets within chunks.
  chunk_base_.resize(row_chunks + 1);
  run_each(row_chunks > 1 ? pool_ : nullptr, row_chunks, [&](std::size_t c) {
    const auto [b, e] = chunk_rows(c);
    std::uint64_t sum = 0;
    for (std::size_t t = 0; t < pair_tasks; ++t) {
      const std::uint32_t* count = task_cursor_.data() + t * n;
      for (std::size_t i = b; i < e; ++i) sum += count[i];
    }
    chunk_base_[c + 1] = sum;
  });
  chunk_base_[0] = 0;
  for (std::size_t c = 0; c < row_chunks; ++c) chunk_base_[c + 1] += chunk_base_[c];
  const std::uint64_t candidates = chunk_base_[row_chunks];
  if (candidates > 0xffffffffu) {
    return box_error{0, "too many visibility candidates in one tick (" + std::to_string(candidates) + ")"};
  }

  // The last tick's output becomes the previous state.
  std::swap(ids_, prev_ids_);
  std::swap(vis_off_, prev_off_);
  std::swap(vis_len_, prev_len_);
  std::swap(vis_, prev_vis_);
  const std::size_t prev_rows = prev_ids_.size();
  ids_.assign(ids.begin(), ids.end());

  vis_off_.resize(n + 1);
  run_each(row_chunks > 1 ? pool_ : nullptr, row_chunks, [&](std::size_t c) {
    const auto [b, e] = chunk_rows(c);
    auto running = static_cast<std::uint32_t>(chunk_base_[c]);
    for (std::size_t i = b; i < e; ++i) {
      vis_off_[i] = running;
      for (std::size_t t = 0; t < pair_tasks; ++t) running += std::exchange(task_cursor_[t * n + i], running);
    }
  });
  vis_off_[n] = static_cast<std::uint32_t>(candidates);

  const double offsets_ms = ms_since(t_part);
  t_part = clock_type::now();

  // 3. Fill: target handles by observer row (the order within a row is sorted later).
  resize_with_headroom(cand_, candidates);
  resize_with_headroom(vis_, candidates);
  resize_with_headroom(enter_, candidates);
  if (opt_.max_visible != 0) resize_with_headroom(cap_keys_, candidates);
  run_each(pair_tasks > 1 ? pool_ : nullptr, pair_tasks, [&](std::size_t task) {
    std::uint32_t* cursor = task_cursor_.data() + task * n;
    for (std::size_t k = pair_begin(task), e = pair_begin(task + 1); k < e; ++k) {
      std::uint32_t o, t;
      if (split(pairs[k], o, t)) cand_[cursor[o]++] = (std::uint64_t{ids[t]} << 32) | t;
    }
  });

  const double fill_ms = ms_since(t_part);

  // Presence boxes as one record each: the exact test reads a target's box with one cache miss
  // instead of six (one per column).
  presence_.resize(n);
  run_each(row_chunks > 1 ? pool_ : nullptr, row_chunks, [&](std::size_t c) {
    const auto [first, end] = chunk_rows(c);
    for (std::size_t k = first; k < end; ++k) {
      const std::size_t b = 2 * k + 1;
      presence_[k] = {boxes.lo_x[b], boxes.lo_y[b], boxes.lo_z[b], boxes.hi_x[b], boxes.hi_y[b], boxes.hi_z[b]};
    }
  });

  // Previous row of each observer, and leave capacity = its previous set's size.
  prev_row_.resize(n);
  leave_off_.resize(n + 1);
  leave_off_[0] = 0;
  for (std::size_t i = 0; i < n; ++i) {
    const std::uint32_t slot = slot_of(ids[i]);
    std::uint32_t r = slot < row_of_slot_.size() ? row_of_slot_[slot] : no_row;
    if (r >= prev_rows || prev_ids_[r] != ids[i]) r = no_row;
    prev_row_[i] = r;
    leave_off_[i + 1] = leave_off_[i] + (r == no_row ? 0 : prev_len_[r]);
  }
  resize_with_headroom(leave_, leave_off_[n]);
  vis_len_.resize(n);
  enter_len_.resize(n);
  leave_len_.resize(n);

  // 4. Per observer, in fixed chunks of rows (the output never depends on the thread count).
  const std::size_t chunk = std::max<std::uint32_t>(1, opt_.rows_per_task);
  const std::size_t tasks = (n + chunk - 1) / chunk;
  capped_pending_ = 0;
  t_part = clock_type::now();
  // Slot -> row of this update (the previous rows are looked up above): for the cap's positions
  // by handle, the next tick's lookups and row_of().
  map_rows();
  run_each(pool_, tasks, [&](std::size_t task) {
    process_rows(in, task * chunk, std::min(n, (task + 1) * chunk));
  });
  const double rows_ms = ms_since(t_part);
  point_lists_at_host();
  engine_synced_ = false;

  stats_ = {};
  stats_.pairs = pairs.size();
  stats_.candidates = candidates;
  stats_.capped = capped_pending_;
  for (std::size_t i = 0; i < n; ++i) {
    stats_.visible += vis_len_[i];
    stats_.enters += enter_len_[i];
    stats_.leaves += leave_len_[i];
  }
  stats_.diff_ms = ms_since(t0);
  stats_.count_ms = count_ms;
  stats_.offsets_ms = offsets_ms;
  stats_.fill_ms = fill_ms;
  stats_.rows_ms = rows_ms;
  return std::nullopt;
}

void interest_tracker::process_rows(const entity_columns& in, std::size_t first,
                                    std::size_t last) {
  const vec3* pos = in.position;
  const vec3* aoi = in.aoi_half;
  const std::uint32_t cap = opt_.max_visible;
  std::uint64_t capped = 0;

  // Membership in the previous set without sorting the candidates: a per-thread array by slot
  // holds (stamp << 32) | handle for the previous set's entries of the row being processed
  // (stamps never repeat until the 32-bit counter wraps, which clears the array), so a
  // candidate's "was it visible" is one lookup, and a previous entry still marked afterwards was
  // no candidate: it leaves. Slots are stable for an entity's life and the full handle is
  // compared, so a slot reused by a new entity is never mistaken for the old one.
  thread_local std::vector<std::uint64_t> mark;
  thread_local std::uint32_t stamp = 0;
  if (mark.size() < slot_count_) mark.resize(slot_count_, 0);

  for (std::size_t i = first; i < last; ++i) {
    const std::uint32_t off = vis_off_[i];
    // (handle << 32) | dense index: a target that may enter has its presence box looked up by
    // dense index directly (through the handle's slot it cost two more cache misses for each
    // target in the hysteresis band, every tick).
    const std::uint64_t* cand = cand_.data() + off;
    const std::uint32_t cand_n = vis_off_[i + 1] - off;

    const entity_id* old = nullptr;
    std::uint32_t old_n = 0;
    if (prev_row_[i] != no_row) {
      old = prev_vis_.data() + prev_off_[prev_row_[i]];
      old_n = prev_len_[prev_row_[i]];
    }
    if (++stamp == 0) {
      std::fill(mark.begin(), mark.end(), 0);
      stamp = 1;
    }
    const std::uint64_t tag = std::uint64_t{stamp} << 32;
    for (std::uint32_t j = 0; j < old_n; ++j) mark[slot_of(old[j])] = tag | old[j];

    // The observer's exact AOI box (the same float expressions as the grown one, minus h).
    const vec3 p = pos[i], a = aoi[i];
    const float lo_x = p.x - a.x, lo_y = p.y - a.y, lo_z = p.z - a.z;
    const float hi_x = p.x + a.x, hi_y = p.y + a.y, hi_z = p.z + a.z;

    // A candidate that was visible stays (its mark is cleared: seen); another enters if its
    // presence box meets the exact AOI box. Previous entries still marked were no candidates:
    // they leave; the others stay, in the previous (handle) order.
    entity_id* kept = vis_.data() + off;
    entity_id* enter = enter_.data() + off;
    entity_id* leave = leave_.data() + leave_off_[i];
    std::uint32_t kept_n = 0, en = 0, ln = 0;
    for (std::uint32_t c = 0; c < cand_n; ++c) {
      const auto target = static_cast<entity_id>(cand[c] >> 32);
      std::uint64_t& m = mark[slot_of(target)];
      if (m == (tag | target)) {
        m = 0;
        continue;
      }
      const presence_box& b = presence_[static_cast<std::uint32_t>(cand[c])];
      if (b.lo_x <= hi_x && lo_x <= b.hi_x && b.lo_y <= hi_y && lo_y <= b.hi_y && b.lo_z <= hi_z && lo_z <= b.hi_z) {
        enter[en++] = target;
      }
    }
    for (std::uint32_t j = 0; j < old_n; ++j) {
      if (mark[slot_of(old[j])] == (tag | old[j])) {
        leave[ln++] = old[j];
      } else {
        kept[kept_n++] = old[j];
      }
    }
    // Enters by handle (usually a handful), merged into the kept entries from the back (the
    // row's room holds every candidate, so both fit).
    if (en < 32) {
      for (std::uint32_t c = 1; c < en; ++c) {
        const entity_id key = enter[c];
        std::uint32_t k = c;
        for (; k > 0 && enter[k - 1] > key; --k) enter[k] = enter[k - 1];
        enter[k] = key;
      }
    } else {
      std::sort(enter, enter + en);
    }
    for (std::uint32_t w = kept_n + en, k = kept_n, e = en; e > 0;) {
      kept[--w] = (k > 0 && kept[k - 1] > enter[e - 1]) ? kept[--k] : enter[--e];
    }
    kept_n += en;

    // Cap: keep the `cap` closest (ties by handle), back to handle order, and redo the diff.
    if (cap != 0 && kept_n > cap) {
      std::uint64_t* keys = cap_keys_.data() + off;
      for (std::uint32_t k = 0; k < kept_n; ++k) {
        keys[k] = (std::uint64_t{distance_key(p, pos[row_of_slot_[slot_of(kept[k])]])} << 32) | kept[k];
      }
      std::nth_element(keys, keys + cap, keys + kept_n);
      for (std::uint32_t k = 0; k < cap; ++k) kept[k] = static_cast<entity_id>(keys[k]);
      std::sort(kept, kept + cap);
      capped += kept_n - cap;
      kept_n = cap;
      // Diff of two sorted lists: enters = kept \ old, leaves = old \ kept.
      std::uint32_t k = 0, j = 0;
      en = ln = 0;
      while (k < kept_n || j < old_n) {
        if (j == old_n || (k < kept_n && kept[k] < old[j])) {
          enter[en++] = kept[k++];
        } else if (k == kept_n || old[j] < kept[k]) {
          leave[ln++] = old[j++];
        } else {
          ++k;
          ++j;
        }
      }
    }
    vis_len_[i] = kept_n;
    enter_len_[i] = en;
    leave_len_[i] = ln;
  }
  if (capped != 0) {
    std::atomic_ref<std::uint64_t>(capped_pending_).fetch_add(capped, std::memory_order_relaxed);
  }
}

std::uint64_t interest_tracker::digest() const {
  std::uint64_t h = 0x5a4f4e45ull;  // "ZONE"
  for (std::size_t i = 0; i < ids_.size(); ++i) {
    h = mix(h, ids_[i]);
    for (const auto id : visible(i)) h = mix(h, id);
    h = mix(h, 0xfffffffd);
    for (const auto id : enters(i)) h = mix(h, id);
    h = mix(h, 0xfffffffe);
    for (const auto id : leaves(i)) h = mix(h, id);
    h = mix(h, 0xffffffff);
  }
  return h;
}

}  // namespace zone::interest
