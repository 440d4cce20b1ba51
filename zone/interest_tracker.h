// zone/interest_tracker.h: the interest tracker (pairs -> per-observer visible sets -> enter/leave
// events with hysteresis; docs/zone.md, "Interest tracker").
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <atomic>
#include <memory>
#include <mutex>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "interest/interest.h"
#include "interest/thread_pool.h"
#include "interest/visibility_engine.h"
#include "zone/entity_store.h"

namespace zone {

struct interest_options {
  /// Hysteresis margin h (metres, >= 0): an entity enters A's view when its presence box meets
  /// A's AOI box, and leaves only when it no longer meets A's AOI box grown by h on every side.
  float hysteresis = 4.0f;
  /// Keep at most this many entities per observer, the closest (0 = no cap). See docs/zone.md.
  std::uint32_t max_visible = 0;
  /// Observers per parallel task (fixed, so output never depends on the thread count).
  std::uint32_t rows_per_task = 256;
};

/// Counters and phase times of the last update.
struct interest_stats {
  std::uint64_t pairs = 0;       ///< pairs found with the grown AOI boxes
  std::uint64_t candidates = 0;  ///< (observer, target) candidates after the self/visibility filter
  std::uint64_t visible = 0;     ///< sum of visible-set sizes
  std::uint64_t enters = 0;
  std::uint64_t leaves = 0;
  std::uint64_t capped = 0;  ///< entities dropped by the max_visible cap
  double boxes_ms = 0, find_ms = 0, diff_ms = 0;
  /// Parts of diff_ms: counting candidates per row, row offsets, filling the rows, the per-row
  /// sort-and-merge with the previous sets (the rest: presence records, previous rows, stats).
  double count_ms = 0, offsets_ms = 0, fill_ms = 0, rows_ms = 0;
  /// The update ran on the visibility engine (set_engine): then find_ms is the engine's whole
  /// call, boxes_ms and the parts above are 0, diff_ms is the host's bookkeeping (previous rows,
  /// row map), and `engine_timing` says where the engine's time went.
  bool on_engine = false;
  interest::visibility_timing engine_timing;
};

/// Per-observer visible sets with enter/leave events and hysteresis, on top of any pair_finder.
///
/// Every entity is an observer (players and NPCs alike: NPC perception uses the same sets).
/// After update(), row r (= the entity's dense index in the store at that moment) holds the
/// observer's visible set and this tick's enter and leave events, each sorted ascending by handle.
/// A visible set never contains the observer itself. Output is deterministic: it depends only on
/// the store's contents and the previous tick, not on the finder's pair order or the thread count.
/// Memory is reused between ticks: no allocation in steady state beyond growth.
class interest_tracker {
 public:
  /// `finder` and `pool` must outlive the tracker; `pool` may be null (single-threaded).
  interest_tracker(interest::pair_finder& finder, interest::thread_pool* pool = nullptr, interest_options opt = {});

  /// One tick: builds the boxes, finds the pairs, updates visible sets and events. On error (a
  /// non-finite position or extent) nothing changes and the error names the entity.
  [[nodiscard]] std::optional<interest::box_error> update(const entity_store& store);

  /// The two halves of update(), for callers that find pairs themselves (e.g. a GPU pipeline):
  /// build_boxes writes entity k's AOI box grown by the hysteresis margin as box 2k (category
  /// aoi, mask = sees) and its presence box as box 2k+1 (category = class, mask 0);
  /// apply_pairs takes every qualifying pair of exactly those boxes (any order, each once). It
  /// refuses (error, nothing changes) a box set whose size is not 2 * store.size() or a pair with
  /// an id beyond it.
  void build_boxes(const entity_store& store, interest::box_set& out) const;
  [[nodiscard]] std::optional<interest::box_error> apply_pairs(const entity_store& store, const interest::box_set& boxes,
                                                               std::span<const interest::id_pair> pairs);

  /// Finds the pairs of a box set into a view the callee owns (valid until its next call).
  using pair_view_source = std::function<std::optional<interest::box_error>(const interest::box_set&,
                                                                            std::span<const interest::id_pair>&)>;
  /// When set, update() finds the pairs through `source` instead of finder.find into a list of
  /// its own: for the GPU finders, gpu::find_view hands over the finder's pinned result buffer
  /// and saves copying every pair once more (docs/zone.md). Empty: back to finder.find.
  void set_pair_view_source(pair_view_source source) { view_source_ = std::move(source); }

  /// When set (non-null; it must outlive the tracker or be unset first), update() runs the whole
  /// interest step on the engine (the GPU: gpu/visibility.h) instead of the finder and the host
  /// diff, with the same result. Not used while max_visible != 0 (the cap is host-only), and not
  /// after the engine failed once (engine_error() says why; the host path takes over).
  void set_engine(interest::visibility_engine* engine);
  /// Which observers' visible sets are read on the host right after an update (by slot: non-zero
  /// = read; slots beyond the vector: not read), so that an engine copies only those back; any
  /// other row's set is fetched from the engine on first access (visible() stays exact for every
  /// row). Null (the default): every row's. The vector must outlive the tracker or be unset.
  void set_view_demand(const std::vector<std::uint8_t>* by_slot) { view_demand_ = by_slot; }
  /// Why the engine was given up (empty while it works or when none is set).
  [[nodiscard]] const std::string& engine_error() const { return engine_error_; }
  /// Tells the engine (if any) that an update follows soon (see visibility_engine::prepare).
  void prepare() noexcept {
    if (engine_ != nullptr && engine_error_.empty()) engine_->prepare();
  }
  /// True when the last update ran on the engine.
  [[nodiscard]] bool last_update_on_engine() const { return last_by_engine_; }
  /// The last update's visible sets where the engine keeps them (its device), by this tracker's
  /// rows, for a replication engine on the same device to read in place; empty when the last
  /// update did not run on an engine or the engine keeps none.
  [[nodiscard]] interest::visibility_engine::resident_lists resident_visible() const {
    if (!last_by_engine_ || engine_ == nullptr || !engine_error_.empty()) return {};
    const auto r = engine_->resident_visible();
    return r.rows == ids_.size() ? r : interest::visibility_engine::resident_lists{};
  }

  /// Rows of the last update (= the store's size then).
  [[nodiscard]] std::size_t observer_count() const { return ids_.size(); }
  [[nodiscard]] entity_id observer(std::size_t row) const { return ids_[row]; }
  /// Row of an observer in the last update, or entity_store::npos.
  [[nodiscard]] std::size_t row_of(entity_id id) const;

  /// Safe to call from several threads at once (the first access to a row whose set the engine
  /// kept on the device fetches them all, once).
  [[nodiscard]] std::span<const entity_id> visible(std::size_t row) const {
    if (partial_ && demand_rows_[row] == 0) return fetched_row(row);
    return vis_list_.row(row);
  }
  [[nodiscard]] std::span<const entity_id> enters(std::size_t row) const { return enter_list_.row(row); }
  [[nodiscard]] std::span<const entity_id> leaves(std::size_t row) const { return leave_list_.row(row); }

  /// 64-bit hash of the last update's output (observers, visible sets, enters, leaves, in row
  /// order): equal across runs, finders and thread counts for equal inputs.
  [[nodiscard]] std::uint64_t digest() const;

  [[nodiscard]] const interest_stats& stats() const { return stats_; }
  [[nodiscard]] const interest_options& options() const { return opt_; }
  /// Takes effect at the next update (the margin applies to the sets kept from this tick).
  void set_options(const interest_options& opt) { opt_ = opt; }
  /// The boxes of the last update (build_boxes' layout).
  [[nodiscard]] const interest::box_set& boxes() const { return boxes_; }

 private:
  void process_rows(const entity_store& store, std::size_t first, std::size_t last);
  [[nodiscard]] std::optional<interest::box_error> update_on_engine(const entity_store& store);
  [[nodiscard]] std::optional<interest::box_error> update_on_host(const entity_store& store);
  [[nodiscard]] std::optional<interest::box_error> name_box_error(const entity_store& store,
                                                                  std::optional<interest::box_error> err) const;
  void adopt_engine_output();  // the engine's last output into the host path's arrays
  [[nodiscard]] std::span<const entity_id> fetched_row(std::size_t row) const;
  void point_lists_at_host();
  void map_rows(const entity_store& store);  // row_of_slot_ for the rows of this update
  void map_rows_into(const entity_store& store, const std::vector<entity_id>& ids,
                     std::vector<std::uint32_t>& row_of_slot) const;
  /// One kind of per-row list: row r is data[off[r], off[r] + len[r]) (len null: off[r + 1]).
  struct row_lists {
    const entity_id* data = nullptr;
    const std::uint32_t* off = nullptr;
    const std::uint32_t* len = nullptr;
    [[nodiscard]] std::span<const entity_id> row(std::size_t r) const {
      return {data + off[r], len != nullptr ? len[r] : off[r + 1] - off[r]};
    }
  };
  struct presence_box {
    float lo_x, lo_y, lo_z, hi_x, hi_y, hi_z;
  };

  interest::pair_finder* finder_;
  pair_view_source view_source_;
  interest::thread_pool* pool_;
  interest_options opt_;
  interest_stats stats_;
  interest::box_set boxes_;
  interest::pair_list pairs_;

  // This tick, by row. Visible sets and enters share the candidate offsets (capacity per row =
  // candidate count); leaves are laid out by the previous set's size.
  std::vector<entity_id> ids_;
  std::vector<std::uint32_t> vis_off_;  // size rows + 1
  std::vector<std::uint32_t> vis_len_, enter_len_, leave_off_, leave_len_;
  std::vector<entity_id> vis_, enter_, leave_;
  std::vector<std::uint64_t> cand_;         // candidates by row: (target handle << 32) | target dense index
  std::vector<std::uint32_t> task_cursor_;   // per (pair task, row): candidate count, then fill cursor
  std::vector<std::uint64_t> chunk_base_;    // per chunk of rows: its first candidate (a scan)
  std::vector<std::size_t> task_bad_;        // per pair task: first pair with an id beyond the set
  std::vector<std::uint64_t> cap_keys_;      // (distance key << 32) | handle, for the cap
  std::vector<std::uint32_t> prev_row_;    // previous row of each row's observer, or none
  std::vector<presence_box> presence_;     // presence box by dense index (from the box set)

  // The previous tick.
  std::vector<entity_id> prev_ids_;
  std::vector<std::uint32_t> prev_off_, prev_len_;
  std::vector<entity_id> prev_vis_;
  std::vector<std::uint32_t> row_of_slot_;  // slot -> row in the last update (checked against ids)
  std::uint64_t capped_pending_ = 0;        // summed by the row tasks (atomic_ref)

  // What the accessors read: the host path's arrays, or the engine's output.
  row_lists vis_list_, enter_list_, leave_list_;
  interest::visibility_engine* engine_ = nullptr;
  interest::visibility_output engine_out_;
  bool engine_synced_ = false;  // the engine holds the last update's sets
  std::vector<entity_id> next_ids_;                 // engine path: this update's rows, swapped in on success
  std::vector<std::uint32_t> spare_row_of_slot_;    // engine path: this update's slot map, likewise
  const std::vector<std::uint8_t>* view_demand_ = nullptr;
  std::vector<std::uint8_t> demand_rows_, next_demand_rows_;  // per row of the last / next update
  bool partial_ = false;  // vis_list_ holds the demanded rows only; the rest via fetched_row
  mutable std::mutex fetch_mutex_;
  mutable std::atomic<bool> fetched_{false};
  mutable row_lists full_list_;
  bool last_by_engine_ = false;
  std::string engine_error_;
};

}  // namespace zone
