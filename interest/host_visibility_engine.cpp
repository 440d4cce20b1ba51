// The interest step's host reference engine (host_visibility_engine.h; algorithm in docs/zone.md).
//
// One finder call per update with every AOI box grown by the hysteresis margin h yields, per
// observer, every target that could be visible under either rule: inside the grown box (the
// "stay" rule for targets already visible) is exactly what the finder reports, and inside the
// exact box (the "enter" rule) is a subset of it, because float rounding is monotone:
// p - (a + h) <= p - a and p + a <= p + (a + h). Each candidate is then classified with the exact
// test: a target already visible stays; a new one enters only when its presence box meets the
// exact AOI box. Targets of the previous set that are not candidates leave.
#include "host_visibility_engine.h"

#include <algorithm>
#include <array>
#include <atomic>
#include <bit>
#include <chrono>
#include <cmath>
#include <functional>
#include <limits>
#include <stdexcept>
#include <string>
#include <utility>

#include "measure.h"

namespace zone::interest {

namespace {

/// resize() with 25% spare capacity when it must grow, so that counts creeping up from update to
/// update do not reallocate every time.
template <class V>
void resize_with_headroom(V& v, std::size_t n) {
  if (v.capacity() < n) v.reserve(n + n / 4 + 64);
  v.resize(n);
}

/// run_tasks without a heap allocation per call: std::function keeps a reference_wrapper in
/// place, where a lambda capturing several references would be copied to the heap (the step
/// allocates nothing in steady state).
template <class F>
void run_each(thread_pool* pool, std::size_t n, F&& task) {
  run_tasks(pool, n, std::ref(task));
}

using clock_type = std::chrono::steady_clock;

constexpr std::uint32_t no_row = 0xffffffffu;
constexpr std::size_t no_pair = static_cast<std::size_t>(-1);

/// Squared distance of two points (3 floats each), as an order-preserving unsigned key
/// (non-negative floats order like their bit patterns).
std::uint32_t distance_key(const float* a, const float* b) {
  const float dx = a[0] - b[0], dy = a[1] - b[1], dz = a[2] - b[2];
  return std::bit_cast<std::uint32_t>(dx * dx + dy * dy + dz * dz);
}

/// The presence grid (host_visibility_engine::grid_candidates): a presence box covering more
/// cells than this is kept out of the grid and tested by every observer (a boss's footprint), as
/// in the GPU engine.
constexpr std::uint64_t grid_large_cells = 64;
/// At most 8 cells per row (plus 1,024) and 2^20 in all: the per-cell arrays, zeroed and scanned
/// every update, stay linear in the rows.
constexpr double grid_cells_per_row = 8;
constexpr double grid_max_cells = 1 << 20;
/// The grid declines (the pair finder runs) when more presence boxes than this share of the rows
/// (and more than grid_large_min) are large: every observer tests each of them.
constexpr std::size_t grid_large_min = 256;
constexpr std::size_t grid_large_share = 16;  // 1/16

/// The presence grid's cell function: floor((v - origin) / edge) clamped to [0, last]; monotone
/// non-decreasing in v (a rounded subtraction and a product with a positive constant, then
/// clamped), which the output-cell rule in grid_candidates relies on.
inline std::uint32_t grid_cell(float v, float origin, float inv_edge, std::uint32_t last) {
  float t = (v - origin) * inv_edge;
  t = t > 0.0f ? t : 0.0f;  // NaN cannot occur (finite inputs), but would map to 0
  const auto top = static_cast<float>(last);
  return t < top ? static_cast<std::uint32_t>(t) : last;
}

}  // namespace

void build_step_boxes(const visibility_input& in, box_set& out, thread_pool* pool) {
  namespace cb = category_bits;
  const std::size_t n = in.n;
  out.resize(2 * n);
  const float* pos = in.position;
  const float* aoi = in.aoi_half;
  const float* body = in.body_half;
  const std::uint32_t* cls = in.visibility;
  const std::uint32_t* sees = in.sees;
  const float h = in.hysteresis;
  // In fixed chunks on the pool (each box is written by exactly one task).
  const std::size_t chunk = 8192;
  run_each(n > chunk ? pool : nullptr, (n + chunk - 1) / chunk, [&](std::size_t c) {
    for (std::size_t k = c * chunk, end = std::min(n, (c + 1) * chunk); k < end; ++k) {
      const float px = pos[3 * k], py = pos[3 * k + 1], pz = pos[3 * k + 2];
      // AOI box grown by the margin: the finder reports every target inside it.
      const float gx = aoi[3 * k] + h, gy = aoi[3 * k + 1] + h, gz = aoi[3 * k + 2] + h;
      out.lo_x[2 * k] = px - gx;
      out.lo_y[2 * k] = py - gy;
      out.lo_z[2 * k] = pz - gz;
      out.hi_x[2 * k] = px + gx;
      out.hi_y[2 * k] = py + gy;
      out.hi_z[2 * k] = pz + gz;
      out.category[2 * k] = cb::aoi;
      out.mask[2 * k] = sees[k];
      // Presence box. Its mask is 0 (not aoi): with the contract's symmetric rule
      // (cat_a & mask_b) | (cat_b & mask_a), a presence mask of aoi would let every AOI/presence
      // pair through whatever the classes; with 0 only (class & sees of the observer) counts.
      const float bx = body[3 * k], by = body[3 * k + 1], bz = body[3 * k + 2];
      out.lo_x[2 * k + 1] = px - bx;
      out.lo_y[2 * k + 1] = py - by;
      out.lo_z[2 * k + 1] = pz - bz;
      out.hi_x[2 * k + 1] = px + bx;
      out.hi_y[2 * k + 1] = py + by;
      out.hi_z[2 * k + 1] = pz + bz;
      out.category[2 * k + 1] = cls[k];
      out.mask[2 * k + 1] = 0;
    }
  });
}

box step_box(const visibility_input& in, std::size_t index) {
  const std::size_t k = index / 2;
  const bool aoi = index % 2 == 0;
  const float grow = aoi ? in.hysteresis : 0.0f;
  const float* half = aoi ? in.aoi_half : in.body_half;
  box b;
  for (int d = 0; d < 3; ++d) {
    // The same float expressions as build_step_boxes (the presence box's half-extent alone).
    const float e = aoi ? half[3 * k + d] + grow : half[3 * k + d];
    b.lo[d] = in.position[3 * k + d] - e;
    b.hi[d] = in.position[3 * k + d] + e;
  }
  b.category = aoi ? category_bits::aoi : in.visibility[k];
  b.mask = aoi ? in.sees[k] : 0;
  return b;
}

host_visibility_engine::host_visibility_engine(pair_finder& finder, thread_pool* pool, host_engine_options opt)
    : finder_(&finder), pool_(pool), opt_(opt) {}

void host_visibility_engine::begin(const visibility_input& in) {
  slot_bits_ = in.slot_bits;
  std::size_t slots = in.slot_count;
  if (slots == 0) {
    for (std::size_t i = 0; i < in.n; ++i) slots = std::max<std::size_t>(slots, slot_of(in.ids[i]) + std::size_t{1});
  }
  slot_count_ = std::max(slot_count_, slots);
}

void host_visibility_engine::map_rows() {
  // Entries of slots not in ids_ may be stale; every lookup checks the handle.
  const std::size_t n = ids_.size();
  if (row_of_slot_.size() < slot_count_) row_of_slot_.resize(slot_count_, no_row);
  const std::size_t chunk = 16384;
  run_each(n > chunk ? pool_ : nullptr, (n + chunk - 1) / chunk, [&](std::size_t c) {
    for (std::size_t i = c * chunk, e = std::min(n, (c + 1) * chunk); i < e; ++i) {
      row_of_slot_[slot_of(ids_[i])] = static_cast<std::uint32_t>(i);
    }
  });
}

std::optional<std::size_t> host_visibility_engine::update(const visibility_input& in, visibility_output& out) {
  // in.while_waiting is not called: there is no device to overlap, the caller does that work after.
  const auto t0 = clock_type::now();
  if (opt_.presence_grid) {
    begin(in);
    std::size_t bad = 0;
    double build_ms = 0;
    const grid_result r = grid_candidates(in, bad, build_ms);
    if (r == grid_result::invalid) return bad;
    if (r == grid_result::done) {
      const double query_ms = ms_since(t0) - build_ms;
      const auto t_diff = clock_type::now();
      // Counts per row (task_cursor_) into offsets; the candidates stay in their tasks' buffers.
      const std::size_t n = in.n;
      std::uint64_t candidates = 0;
      for (std::size_t i = 0; i < n; ++i) candidates += task_cursor_[i];
      if (candidates > 0xffffffffu) {
        throw std::length_error("too many visibility candidates in one tick (" + std::to_string(candidates) + ")");
      }
      std::swap(ids_, prev_ids_);
      std::swap(vis_off_, prev_off_);
      std::swap(vis_len_, prev_len_);
      std::swap(vis_, prev_vis_);
      ids_.assign(in.ids, in.ids + n);
      full_made_ = false;
      vis_off_.resize(n + 1);
      std::uint32_t running = 0;
      for (std::size_t i = 0; i < n; ++i) {
        vis_off_[i] = running;
        running += task_cursor_[i];
      }
      vis_off_[n] = running;
      const double offsets_ms = ms_since(t_diff);
      finish_rows(in, candidates, true, out);
      out.pairs = candidates + grid_self_pairs_;
      out.timing.boxes_ms = build_ms;
      out.timing.find_ms = query_ms;
      out.timing.offsets_ms = offsets_ms;
      out.timing.diff_ms = ms_since(t_diff);
      out.timing.total_ms = ms_since(t0);
      last_on_grid_ = true;
      return std::nullopt;
    }
  }
  build_step_boxes(in, boxes_, pool_);
  const double boxes_ms = ms_since(t0);
  const auto t_find = clock_type::now();
  std::span<const id_pair> pairs;
  auto err = opt_.finder_view ? finder_->find_view(boxes_, pairs_, pairs) : finder_->find(boxes_, pairs_);
  if (err) return err->index;
  if (!opt_.finder_view) pairs = pairs_;
  const double find_ms = ms_since(t_find);
  if (auto apply_err = apply_pairs(in, boxes_, pairs, out)) {
    // Only the candidate count can be refused here (the boxes and pairs are the engine's own).
    throw std::length_error(apply_err->message);
  }
  out.timing.boxes_ms = boxes_ms;
  out.timing.find_ms = find_ms;
  out.timing.total_ms = ms_since(t0);
  return std::nullopt;
}

void host_visibility_engine::load_previous(std::span<const std::uint32_t> ids, std::uint32_t slot_bits,
                                           std::span<const std::uint32_t> offsets, std::span<const std::uint32_t> visible) {
  const std::size_t rows = ids.size();
  if (rows == 0 && offsets.size() <= 1) {
    ids_.clear();
    vis_off_.assign(1, 0);
    vis_len_.clear();
    full_made_ = false;
    return;
  }
  if (offsets.size() != rows + 1) throw std::invalid_argument("load_previous: offsets must have ids.size() + 1 entries");
  for (std::size_t r = 0; r < rows; ++r) {
    if (offsets[r] > offsets[r + 1] || offsets[r + 1] > visible.size()) {
      throw std::invalid_argument("load_previous: offsets beyond the visible entries");
    }
  }
  slot_bits_ = slot_bits;
  std::size_t slots = 0;
  for (const std::uint32_t id : ids) slots = std::max<std::size_t>(slots, slot_of(id) + std::size_t{1});
  slot_count_ = std::max(slot_count_, slots);
  ids_.assign(ids.begin(), ids.end());
  vis_off_.assign(offsets.begin(), offsets.end());
  vis_len_.resize(rows);
  for (std::size_t r = 0; r < rows; ++r) vis_len_[r] = offsets[r + 1] - offsets[r];
  vis_.assign(visible.begin(), visible.begin() + offsets[rows]);
  map_rows();
  full_made_ = false;
}

visibility_lists host_visibility_engine::fetch_all_visible() {
  if (!full_made_) {
    const std::size_t rows = ids_.size();
    full_off_.resize(rows + 1);
    full_off_[0] = 0;
    for (std::size_t r = 0; r < rows; ++r) full_off_[r + 1] = full_off_[r] + vis_len_[r];
    full_vis_.resize(full_off_[rows]);
    for (std::size_t r = 0; r < rows; ++r) {
      std::copy_n(vis_.begin() + vis_off_[r], vis_len_[r], full_vis_.begin() + full_off_[r]);
    }
    full_made_ = true;
  }
  return {full_vis_.data(), full_off_.data()};
}

std::optional<box_error> host_visibility_engine::apply_pairs(const visibility_input& in, const box_set& boxes,
                                                             std::span<const id_pair> pairs, visibility_output& out) {
  const auto t0 = clock_type::now();
  if (boxes.size() != 2 * in.n) {
    return box_error{boxes.size(), "box set has " + std::to_string(boxes.size()) + " boxes, expected 2 x " +
                                       std::to_string(in.n) + " entities"};
  }
  begin(in);
  const std::size_t n = in.n;
  const std::span<const std::uint32_t> ids(in.ids, n);

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

  // The last update's output becomes the previous state.
  std::swap(ids_, prev_ids_);
  std::swap(vis_off_, prev_off_);
  std::swap(vis_len_, prev_len_);
  std::swap(vis_, prev_vis_);
  ids_.assign(ids.begin(), ids.end());
  full_made_ = false;

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

  finish_rows(in, candidates, false, out);
  out.pairs = pairs.size();
  out.timing.count_ms = count_ms;
  out.timing.offsets_ms = offsets_ms;
  out.timing.fill_ms = fill_ms;
  out.timing.diff_ms = ms_since(t0);
  out.timing.total_ms = out.timing.diff_ms;
  last_on_grid_ = false;
  return std::nullopt;
}

void host_visibility_engine::finish_rows(const visibility_input& in, std::uint64_t candidates, bool from_grid,
                                         visibility_output& out) {
  const std::size_t n = in.n;
  const std::uint32_t* ids = in.ids;
  const std::size_t prev_rows = prev_ids_.size();
  resize_with_headroom(vis_, candidates);
  resize_with_headroom(enter_, candidates);
  if (in.max_visible != 0) resize_with_headroom(cap_keys_, candidates);

  // Previous row of each observer, and leave room = its previous set's size.
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
  //    The grid path's candidates are in one buffer per chunk (the same chunks).
  const std::size_t chunk = std::max<std::uint32_t>(1, opt_.rows_per_task);
  const std::size_t tasks = (n + chunk - 1) / chunk;
  capped_pending_ = 0;
  const auto t_part = clock_type::now();
  // Slot -> row of this update (the previous rows are looked up above): for the cap's positions
  // by handle and the next update's lookups.
  map_rows();
  run_each(pool_, tasks, [&](std::size_t task) {
    const std::size_t first = task * chunk;
    const std::uint64_t* cand = from_grid ? grid_cand_[task].data() : cand_.data() + vis_off_[first];
    process_rows(in, first, std::min(n, (task + 1) * chunk), cand);
  });
  const double rows_ms = ms_since(t_part);

  out = {};
  out.visible = vis_.data();
  out.visible_off = vis_off_.data();
  out.visible_len = vis_len_.data();
  out.enters = enter_.data();
  out.enter_off = vis_off_.data();
  out.enter_len = enter_len_.data();
  out.leaves = leave_.data();
  out.leave_off = leave_off_.data();
  out.leave_len = leave_len_.data();
  out.visible_complete = true;
  std::uint64_t visible_total = 0;
  for (std::size_t i = 0; i < n; ++i) visible_total += vis_len_[i];
  out.visible_total = visible_total;
  out.candidates = candidates;
  out.capped = capped_pending_;
  out.timing.rows_ms = rows_ms;
}

host_visibility_engine::grid_result host_visibility_engine::grid_candidates(const visibility_input& in,
                                                                              std::size_t& bad, double& build_ms) {
  const auto t0 = clock_type::now();
  const std::size_t n = in.n;
  const float* pos = in.position;
  const float* aoi = in.aoi_half;
  const float* body = in.body_half;
  const std::uint32_t* cls = in.visibility;
  const std::uint32_t* sees = in.sees;
  const std::uint32_t* ids = in.ids;
  const float h = in.hysteresis;
  grid_stats_ = {};

  // 1. Both boxes of every row (build_step_boxes' float expressions), validated as validate()
  //    would (the first invalid box: 2k AOI, 2k + 1 presence); presence records, the presence
  //    bounds in x and y, the mean grown AOI and body widths. Fixed chunks: the sums, and so the
  //    plan, never depend on the thread count.
  const std::size_t vchunk = 8192;
  const std::size_t vchunks = std::max<std::size_t>(1, (n + vchunk - 1) / vchunk);
  grid_part_.resize(vchunks);
  presence_.resize(n);
  // (On the pool only from 8 chunks: below, a phase's hand-off costs more than it saves.)
  run_each(vchunks >= 8 ? pool_ : nullptr, vchunks, [&](std::size_t c) {
    grid_bounds b{std::numeric_limits<float>::max(), std::numeric_limits<float>::max(),
                  std::numeric_limits<float>::lowest(), std::numeric_limits<float>::lowest(), 0, 0, 0, 0, no_pair};
    for (std::size_t k = c * vchunk, e = std::min(n, (c + 1) * vchunk); k < e; ++k) {
      const float px = pos[3 * k], py = pos[3 * k + 1], pz = pos[3 * k + 2];
      const float gx = aoi[3 * k] + h, gy = aoi[3 * k + 1] + h, gz = aoi[3 * k + 2] + h;
      const float glx = px - gx, gly = py - gy, glz = pz - gz, ghx = px + gx, ghy = py + gy, ghz = pz + gz;
      const float bx = body[3 * k], by = body[3 * k + 1], bz = body[3 * k + 2];
      const presence_box p{px - bx, py - by, pz - bz, px + bx, py + by, pz + bz};
      const bool g_ok = valid_bounds(glx, gly, glz, ghx, ghy, ghz);
      const bool p_ok = valid_bounds(p.lo_x, p.lo_y, p.lo_z, p.hi_x, p.hi_y, p.hi_z);
      if (!g_ok || !p_ok) {
        if (b.bad == no_pair) b.bad = g_ok ? 2 * k + 1 : 2 * k;
        continue;
      }
      presence_[k] = p;
      b.lo_x = std::min(b.lo_x, p.lo_x);
      b.lo_y = std::min(b.lo_y, p.lo_y);
      b.hi_x = std::max(b.hi_x, p.hi_x);
      b.hi_y = std::max(b.hi_y, p.hi_y);
      b.body_width += 0.5 * ((static_cast<double>(p.hi_x) - p.lo_x) + (static_cast<double>(p.hi_y) - p.lo_y));
      // Rows whose AOI sees their own class: the finder's self pairs (both boxes hold the centre).
      b.self += (sees[k] & cls[k]) != 0 ? 1u : 0u;
      if (sees[k] != 0) {
        b.aoi_width += 0.5 * ((static_cast<double>(ghx) - glx) + (static_cast<double>(ghy) - gly));
        ++b.observers;
      }
    }
    grid_part_[c] = b;
  });
  grid_bounds all{std::numeric_limits<float>::max(), std::numeric_limits<float>::max(),
                  std::numeric_limits<float>::lowest(), std::numeric_limits<float>::lowest(), 0, 0, 0, 0, no_pair};
  for (const grid_bounds& b : grid_part_) {
    if (b.bad != no_pair) {
      bad = b.bad;
      build_ms = ms_since(t0);
      return grid_result::invalid;
    }
    all.lo_x = std::min(all.lo_x, b.lo_x);
    all.lo_y = std::min(all.lo_y, b.lo_y);
    all.hi_x = std::max(all.hi_x, b.hi_x);
    all.hi_y = std::max(all.hi_y, b.hi_y);
    all.aoi_width += b.aoi_width;
    all.body_width += b.body_width;
    all.observers += b.observers;
    all.self += b.self;
  }

  // 2. Plan: the cell edge from the mean grown AOI width (an average AOI box spans about two
  //    cells a side: the tests of a range are vectorised, so fewer cell rows per query pay more
  //    than fewer tests; the GPU engine takes four) and twice the mean body width; the cells
  //    capped so that the per-cell arrays stay linear in the rows.
  float ox = 0, oy = 0, inv_edge = 1;
  std::uint32_t nx = 1, ny = 1;
  double edge = 1;
  if (n > 0) {
    const double ex = static_cast<double>(all.hi_x) - all.lo_x, ey = static_cast<double>(all.hi_y) - all.lo_y;
    const double mean_aoi = all.observers != 0 ? all.aoi_width / all.observers : 0.0;
    const double mean_body = all.body_width / static_cast<double>(n);
    edge = opt_.grid_cell_edge > 0 ? static_cast<double>(opt_.grid_cell_edge) : std::max(mean_aoi / 2.0, mean_body * 2.0);
    edge = std::max(edge, std::max(ex, ey) / 4096.0);
    if (!(edge > 0.0) || !std::isfinite(edge)) edge = 1.0;
    const double max_cells = std::min(grid_max_cells, grid_cells_per_row * static_cast<double>(n) + 1024.0);
    double cx = 1, cy = 1;
    for (int k = 0; k < 200; ++k) {
      cx = std::floor(ex / edge) + 1.0;
      cy = std::floor(ey / edge) + 1.0;
      if (cx * cy <= max_cells) break;
      edge *= 1.25;
    }
    if (cx * cy > max_cells || !std::isfinite(cx * cy)) cx = cy = 1;  // degenerate extents: one cell
    nx = static_cast<std::uint32_t>(cx);
    ny = static_cast<std::uint32_t>(cy);
    ox = all.lo_x;
    oy = all.lo_y;
    inv_edge = static_cast<float>(1.0 / edge);
  }
  const std::size_t cells = std::size_t{nx} * ny;
  const std::uint32_t last_x = nx - 1, last_y = ny - 1;
  const auto cell_range = [&](const float lo_x, const float lo_y, const float hi_x, const float hi_y) {
    return std::array<std::uint32_t, 4>{grid_cell(lo_x, ox, inv_edge, last_x), grid_cell(hi_x, ox, inv_edge, last_x),
                                        grid_cell(lo_y, oy, inv_edge, last_y), grid_cell(hi_y, oy, inv_edge, last_y)};
  };

  // 3. Count, scan, scatter: every presence box into each cell it covers (rows in order, so a
  //    cell's entries are in row order), except the large ones.
  cell_start_.assign(cells + 1, 0);
  grid_large_.clear();
  std::uint64_t entries = 0;
  for (std::size_t k = 0; k < n; ++k) {
    const presence_box& p = presence_[k];
    const auto r = cell_range(p.lo_x, p.lo_y, p.hi_x, p.hi_y);
    const std::uint64_t covered = std::uint64_t{r[1] - r[0] + 1} * (r[3] - r[2] + 1);
    if (covered > grid_large_cells) {
      grid_large_.push_back(static_cast<std::uint32_t>(k));
      continue;
    }
    entries += covered;
    for (std::uint32_t y = r[2]; y <= r[3]; ++y) {
      for (std::uint32_t x = r[0]; x <= r[1]; ++x) ++cell_start_[std::size_t{y} * nx + x + 1];
    }
  }
  if (entries > 0xffffffffu ||
      (grid_large_.size() > grid_large_min && grid_large_.size() > n / grid_large_share)) {
    build_ms = ms_since(t0);
    return grid_result::declined;
  }
  for (std::size_t c = 0; c < cells; ++c) cell_start_[c + 1] += cell_start_[c];
  cell_cursor_.assign(cell_start_.begin(), cell_start_.end() - 1);
  // 8 entries of padding (class 0: never a hit), so that the query's flags can be computed in
  // whole vectors past a range's end.
  for (auto* v : {&e_lo_x_, &e_lo_y_, &e_lo_z_, &e_hi_x_, &e_hi_y_, &e_hi_z_}) resize_with_headroom(*v, entries + 8);
  for (auto* v : {&e_cls_, &e_tx_, &e_ty_, &e_row_}) resize_with_headroom(*v, entries + 8);
  std::fill_n(e_cls_.begin() + static_cast<std::ptrdiff_t>(entries), 8, 0u);
  resize_with_headroom(e_key_, entries);
  std::size_t next_large = 0;
  for (std::size_t k = 0; k < n; ++k) {
    if (next_large < grid_large_.size() && grid_large_[next_large] == k) {
      ++next_large;
      continue;
    }
    const presence_box& p = presence_[k];
    const auto r = cell_range(p.lo_x, p.lo_y, p.hi_x, p.hi_y);
    const std::uint64_t key = (std::uint64_t{ids[k]} << 32) | k;
    for (std::uint32_t y = r[2]; y <= r[3]; ++y) {
      for (std::uint32_t x = r[0]; x <= r[1]; ++x) {
        const std::uint32_t e = cell_cursor_[std::size_t{y} * nx + x]++;
        e_lo_x_[e] = p.lo_x;
        e_lo_y_[e] = p.lo_y;
        e_lo_z_[e] = p.lo_z;
        e_hi_x_[e] = p.hi_x;
        e_hi_y_[e] = p.hi_y;
        e_hi_z_[e] = p.hi_z;
        e_cls_[e] = cls[k];
        // The output-cell rule as one comparison per axis: in the query, every entry's column x
        // and the query's first column x0 satisfy x0 <= x and r[0] <= x, so x == max(x0, r[0])
        // exactly when x == r[0] (the box's first column: threshold 0) or x0 >= x.
        e_tx_[e] = x == r[0] ? 0 : x;
        e_ty_[e] = y == r[2] ? 0 : y;
        e_row_[e] = static_cast<std::uint32_t>(k);
        e_key_[e] = key;
      }
    }
  }
  build_ms = ms_since(t0);

  // 4. Query, in the row tasks of the classification (fixed chunks of rows_per_task): each cell
  //    row that an observer's grown AOI box covers is one contiguous range of entries. A presence
  //    box listed in several cells is taken only in the cell holding the lower corner of the two
  //    boxes' intersection, (max(x0, cell(P.lo.x)), max(y0, cell(P.lo.y))): the cell function
  //    is monotone, so both boxes cover that cell and each (observer, target) pair is found once.
  //    Candidates (class & sees, not the observer itself) go to the task's own buffer, their
  //    count per row to task_cursor_; the tests are branch-free (a block of hit flags, then
  //    every entry written and the cursor advanced by its flag).
  const std::size_t chunk = std::max<std::uint32_t>(1, opt_.rows_per_task);
  const std::size_t tasks = (n + chunk - 1) / chunk;
  if (grid_cand_.size() < tasks) grid_cand_.resize(tasks);
  grid_task_checks_.assign(tasks, 0);
  task_cursor_.resize(n);
  const std::uint32_t* start = cell_start_.data();
  const float *elx = e_lo_x_.data(), *ely = e_lo_y_.data(), *elz = e_lo_z_.data();
  const float *ehx = e_hi_x_.data(), *ehy = e_hi_y_.data(), *ehz = e_hi_z_.data();
  const std::uint32_t *ecls = e_cls_.data(), *etx = e_tx_.data(), *ety = e_ty_.data(), *erow = e_row_.data();
  const std::uint64_t* ekey = e_key_.data();
  run_each(pool_, tasks, [&](std::size_t task) {
    std::vector<std::uint64_t>& buf = grid_cand_[task];
    if (buf.size() < 1024) buf.resize(1024);
    std::size_t used = 0;
    std::uint64_t checks = 0;
    for (std::size_t i = task * chunk, last = std::min(n, (task + 1) * chunk); i < last; ++i) {
      const std::size_t row_first = used;
      const std::uint32_t s = sees[i];
      if (s != 0) {
        const float px = pos[3 * i], py = pos[3 * i + 1], pz = pos[3 * i + 2];
        const float gx = aoi[3 * i] + h, gy = aoi[3 * i + 1] + h, gz = aoi[3 * i + 2] + h;
        const float lx = px - gx, ly = py - gy, lz = pz - gz, hx = px + gx, hy = py + gy, hz = pz + gz;
        const auto r = cell_range(lx, ly, hx, hy);
        const std::uint32_t x0 = r[0], y0 = r[2];  // the query's first column and row
        const auto self = static_cast<std::uint32_t>(i);
        for (std::uint32_t y = r[2]; y <= r[3]; ++y) {
          const std::size_t row = std::size_t{y} * nx;
          const std::uint32_t b = start[row + r[0]], e = start[row + r[1] + 1];
          checks += e - b;
          for (std::uint32_t block = b; block < e; block += 64) {
            const std::uint32_t len = std::min<std::uint32_t>(e - block, 64);
            alignas(64) std::uint32_t hit[64];
            const float* blx = elx + block;
            const float* bly = ely + block;
            const float* blz = elz + block;
            const float* bhx = ehx + block;
            const float* bhy = ehy + block;
            const float* bhz = ehz + block;
            const std::uint32_t* bcls = ecls + block;
            const std::uint32_t* btx = etx + block;
            const std::uint32_t* bty = ety + block;
            const std::uint32_t* brow = erow + block;
            const std::uint32_t vlen = (len + 7) & ~7u;  // whole vectors (padding above)
            for (std::uint32_t t = 0; t < vlen; ++t) {
              hit[t] = static_cast<std::uint32_t>((blx[t] <= hx) & (lx <= bhx[t]) & (bly[t] <= hy) & (ly <= bhy[t]) &
                                                  (blz[t] <= hz) & (lz <= bhz[t]) & ((bcls[t] & s) != 0) &
                                                  (x0 >= btx[t]) & (y0 >= bty[t]) & (brow[t] != self));
            }
            if (buf.size() - used < 64) buf.resize(2 * buf.size());
            std::uint64_t* out = buf.data() + used;
            std::size_t hits = 0;
            for (std::uint32_t t = 0; t < len; ++t) {
              out[hits] = ekey[block + t];
              hits += hit[t];
            }
            used += hits;
          }
        }
        for (const std::uint32_t j : grid_large_) {
          const presence_box& p = presence_[j];
          ++checks;
          if ((cls[j] & s) != 0 && j != self && p.lo_x <= hx && lx <= p.hi_x && p.lo_y <= hy && ly <= p.hi_y &&
              p.lo_z <= hz && lz <= p.hi_z) {
            if (buf.size() == used) buf.resize(2 * buf.size());
            buf[used++] = (std::uint64_t{ids[j]} << 32) | j;
          }
        }
      }
      task_cursor_[i] = static_cast<std::uint32_t>(used - row_first);
    }
    grid_task_checks_[task] = checks;
  });
  grid_self_pairs_ = all.self;
  grid_stats_.cell_edge = edge;
  grid_stats_.cells = cells;
  grid_stats_.cell_entries = entries;
  grid_stats_.large_boxes = grid_large_.size();
  for (const auto c : grid_task_checks_) grid_stats_.checks += c;
  grid_stats_.plan_ms = build_ms;
  grid_stats_.check_ms = ms_since(t0) - build_ms;
  return grid_result::done;
}

void host_visibility_engine::process_rows(const visibility_input& in, std::size_t first, std::size_t last,
                                          const std::uint64_t* cand_first) {
  const float* pos = in.position;
  const float* aoi = in.aoi_half;
  const std::uint32_t cap = in.max_visible;
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
    // (handle << 32) | row: a target that may enter has its presence box looked up by row
    // directly (through the handle's slot it cost two more cache misses for each target in the
    // hysteresis band, every update).
    const std::uint64_t* cand = cand_first + (off - vis_off_[first]);
    const std::uint32_t cand_n = vis_off_[i + 1] - off;

    const std::uint32_t* old = nullptr;
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
    const float* p = pos + 3 * i;
    const float* a = aoi + 3 * i;
    const float lo_x = p[0] - a[0], lo_y = p[1] - a[1], lo_z = p[2] - a[2];
    const float hi_x = p[0] + a[0], hi_y = p[1] + a[1], hi_z = p[2] + a[2];

    // A candidate that was visible stays (its mark is cleared: seen); another enters if its
    // presence box meets the exact AOI box. Previous entries still marked were no candidates:
    // they leave; the others stay, in the previous (handle) order.
    std::uint32_t* kept = vis_.data() + off;
    std::uint32_t* enter = enter_.data() + off;
    std::uint32_t* leave = leave_.data() + leave_off_[i];
    std::uint32_t kept_n = 0, en = 0, ln = 0;
    for (std::uint32_t c = 0; c < cand_n; ++c) {
      const auto target = static_cast<std::uint32_t>(cand[c] >> 32);
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
        const std::uint32_t key = enter[c];
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
        keys[k] = (std::uint64_t{distance_key(p, pos + 3 * std::size_t{row_of_slot_[slot_of(kept[k])]})} << 32) | kept[k];
      }
      std::nth_element(keys, keys + cap, keys + kept_n);
      for (std::uint32_t k = 0; k < cap; ++k) kept[k] = static_cast<std::uint32_t>(keys[k]);
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

}  // namespace zone::interest
