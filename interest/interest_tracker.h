// interest/interest_tracker.h: the interest step's one home: per-observer visible sets with enter
// and leave events, hysteresis and visibility classes, from plain entity columns (docs/zone.md,
// "Interest tracker"). Every update runs on a visibility engine (visibility_engine.h): the one
// given to set_engine (the GPU's, gpu/visibility.h), or the tracker's own host reference
// (host_visibility_engine.h, on the pair_finder it was built with) when none is set, when the
// set one cannot cap (max_visible) or after it failed; the result is the same. The tracker keeps
// the rows, hands the sets over when the engine changes and names invalid input. A server calls
// it through interest_space.h (the tick-level API); this header is the layer below it.
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
#include <utility>
#include <vector>

#include "host_visibility_engine.h"
#include "interest.h"
#include "thread_pool.h"
#include "visibility_engine.h"

namespace zone::interest {

/// A point or a half-extent (metres): three packed floats.
struct vec3 {
  float x = 0, y = 0, z = 0;
  friend bool operator==(const vec3&, const vec3&) = default;
};
static_assert(sizeof(vec3) == 3 * sizeof(float), "vec3 must be three packed floats");

/// An entity handle: its low `slot_bits` bits are its slot (distinct among live entities, reused
/// after a remove), the rest a generation; 0 is never a handle.
using entity_id = std::uint32_t;
inline constexpr entity_id null_entity = 0;

/// One update's entities as plain columns, n rows each (row = the caller's index of the entity,
/// e.g. a dense store's). The tracker reads them during update() only.
struct entity_columns {
  std::size_t n = 0;
  const entity_id* ids = nullptr;  ///< handles, never 0; their slots pairwise distinct
  std::uint32_t slot_bits = 22;    ///< slot = id & ((1 << slot_bits) - 1); at most 31
  /// One past the highest slot of any id (sizes per-slot tables); 0: the tracker computes it.
  std::size_t slot_count = 0;
  const vec3* position = nullptr;       ///< centre of both boxes
  const vec3* aoi_half = nullptr;       ///< AOI half-extents (>= 0)
  const vec3* presence_half = nullptr;  ///< presence (body) half-extents (>= 0)
  const std::uint32_t* visibility = nullptr;  ///< the presence box's class (one bit, never category_bits::aoi)
  const std::uint32_t* sees = nullptr;        ///< the classes the AOI box sees (0: none)
  /// Identifies ids, extents, classes and sees: equal non-zero versions promise equal columns
  /// (an engine then skips uploading them). 0: unknown.
  std::uint64_t layout_version = 0;
};

struct interest_options {
  /// Hysteresis margin h (metres, >= 0): an entity enters A's view when its presence box meets
  /// A's AOI box, and leaves only when it no longer meets A's AOI box grown by h on every side.
  float hysteresis = 4.0f;
  /// Keep at most this many entities per observer, the closest (0 = no cap). See docs/zone.md.
  std::uint32_t max_visible = 0;
  /// The host reference engine's tuning (host_engine_options): observers per parallel task
  /// (fixed, so output never depends on the thread count), and whether it reads the finder's own
  /// result buffer (pair_finder::find_view) or finds into a list of its own.
  std::uint32_t rows_per_task = 256;
  bool finder_view = true;
  /// The host reference engine finds the candidates on a grid of the presence boxes instead of
  /// through the pair finder (host_engine_options::presence_grid): the same output, faster on a
  /// zone's boxes; false: the pair finder.
  bool presence_grid = false;
};

/// Counters and phase times of the last update (from its engine's visibility_output).
struct interest_stats {
  std::uint64_t pairs = 0;       ///< pairs found with the grown AOI boxes
  std::uint64_t candidates = 0;  ///< (observer, target) candidates after the self/visibility filter
  std::uint64_t visible = 0;     ///< sum of visible-set sizes
  std::uint64_t enters = 0;
  std::uint64_t leaves = 0;
  std::uint64_t capped = 0;  ///< entities dropped by the max_visible cap
  /// boxes_ms: the engine's box building; find_ms: its call less the phases it reports apart
  /// (boxes, diff): the host reference's pair finder, a device engine's whole call; diff_ms: its
  /// diff plus the tracker's own bookkeeping (rows, slot map; overlapped with the device or not).
  double boxes_ms = 0, find_ms = 0, diff_ms = 0;
  /// Parts of the host reference's diff: counting candidates per row, row offsets, filling the
  /// rows, the per-row merge with the previous sets (the rest: presence records, previous rows).
  double count_ms = 0, offsets_ms = 0, fill_ms = 0, rows_ms = 0;
  /// The update ran on the engine given to set_engine (not the tracker's own host reference).
  bool on_engine = false;
  visibility_timing engine_timing;  ///< the engine's own phases
};

/// Per-observer visible sets with enter/leave events and hysteresis, on a visibility engine (its
/// own host reference on any pair_finder, or the one set).
///
/// Every entity is an observer (players and NPCs alike: NPC perception uses the same sets).
/// After update(), row r (= row r of the columns given to it) holds the
/// observer's visible set and this tick's enter and leave events, each sorted ascending by handle.
/// A visible set never contains the observer itself. Output is deterministic: it depends only on
/// the columns' contents and the previous tick, not on the finder's pair order or the thread count.
/// Memory is reused between ticks: no allocation in steady state beyond growth (a change of
/// engine copies the sets once).
class interest_tracker {
 public:
  /// `finder` (the host reference engine's) and `pool` must outlive the tracker; `pool` may be
  /// null (single-threaded).
  interest_tracker(pair_finder& finder, thread_pool* pool = nullptr, interest_options opt = {});

  /// One tick on the engine in use (see set_engine): visible sets and events. On error (a
  /// non-finite position or extent) nothing changes and the error names the entity and its box.
  /// A device error of a set engine is not an error here: the host reference redoes the tick.
  [[nodiscard]] std::optional<box_error> update(const entity_columns& in);

  /// The two halves of update() on the host reference, for callers that find pairs themselves
  /// (e.g. a GPU pipeline): build_boxes writes build_step_boxes' layout (entity k's AOI box grown
  /// by the margin as box 2k, its presence box as 2k + 1); apply_pairs takes every qualifying pair
  /// of exactly those boxes (any order, each once). It refuses (error, nothing changes) a box set
  /// whose size is not 2 * in.n or a pair with an id beyond it.
  void build_boxes(const entity_columns& in, box_set& out) const;
  [[nodiscard]] std::optional<box_error> apply_pairs(const entity_columns& in, const box_set& boxes,
                                                     std::span<const id_pair> pairs);

  /// When set (non-null; it must outlive the tracker or be unset first), update() runs on
  /// `engine` instead of the host reference, with the same result. Not used while max_visible != 0
  /// unless it caps (visibility_engine::caps_visible), and not after it failed once (engine_error()
  /// says why; the host reference takes over from the last sets).
  void set_engine(visibility_engine* engine);
  /// Which observers' visible sets are read on the host right after an update (by slot: non-zero
  /// = read; slots beyond the vector: not read), so that an engine copies only those back; any
  /// other row's set is fetched from the engine on first access (visible() stays exact for every
  /// row). Null (the default): every row's. The vector must outlive the tracker or be unset.
  void set_view_demand(const std::vector<std::uint8_t>* by_slot) { view_demand_ = by_slot; }
  /// Work of the caller's to run while an engine's device finds the sets (non-null; it must
  /// outlive the tracker or be unset first): update() calls it once, on its own thread, after
  /// its own bookkeeping there, when the engine waits for a device (visibility_engine's
  /// while_waiting); not on the host reference or an engine without a device. It must not
  /// change what update() reads (the columns given to it).
  void set_while_device_works(const std::function<void()>* work) { while_device_works_ = work; }
  /// Why the engine was given up (empty while it works or when none is set).
  [[nodiscard]] const std::string& engine_error() const { return engine_error_; }
  /// Tells the engine (if any) that an update follows soon (see visibility_engine::prepare).
  void prepare() noexcept { active()->prepare(); }
  /// True when the last update ran on the engine given to set_engine.
  [[nodiscard]] bool last_update_on_engine() const { return last_on_engine_; }
  /// The last update's visible sets where the engine keeps them (its device), by this tracker's
  /// rows, for a replication engine on the same device to read in place; empty when the last
  /// update did not run on an engine or the engine keeps none.
  [[nodiscard]] visibility_engine::resident_lists resident_visible() const {
    if (!last_on_engine_ || producer_ == nullptr || !engine_error_.empty()) return {};
    const auto r = producer_->resident_visible();
    return r.rows == ids_.size() ? r : visibility_engine::resident_lists{};
  }

  /// Observer `observer` starts the next update with exactly `targets` as its previous visible
  /// set, as if the last update had seen them (a handoff: the view the observer had in the zone
  /// it comes from, docs/world.md "Handoff"). At the next successful update (or apply_pairs) the
  /// carried set replaces the observer's previous row (its own, or one of another generation of
  /// its slot; a row is added when it had none), and the usual rule applies: each target stays,
  /// without an enter event, iff it meets the AOI box grown by the margin and its class is seen;
  /// otherwise it leaves. Ignored at that update: the observer itself, null, and handles not in
  /// that update's columns (an observer not there is not carried). Calls for one observer before
  /// an update add up; they stay pending across a refused update. Costs one load_previous of
  /// every set to the engine in use (a copy) on the update that takes them.
  void carry_visible(entity_id observer, std::span<const entity_id> targets);
  /// Carried targets waiting for the next update (carry_visible).
  [[nodiscard]] std::size_t carried_pending() const { return carry_.size(); }
  /// What the last update took from carry_visible: (observer, target) pairs ascending, each carried
  /// observer with a (observer, null_entity) pair first (an observer carried with no targets has
  /// only that), every target as given (the update ignored those not in its columns). Empty when
  /// it took none. For a reader of the rules (the ground-truth stream: zone-server --oracle).
  [[nodiscard]] std::span<const std::pair<entity_id, entity_id>> carried_by_last_update() const { return last_carry_; }

  /// Rows of the last update (= its columns' n).
  [[nodiscard]] std::size_t observer_count() const { return ids_.size(); }
  [[nodiscard]] entity_id observer(std::size_t row) const { return ids_[row]; }
  /// Row of an observer in the last update, or npos.
  [[nodiscard]] std::size_t row_of(entity_id id) const;
  static constexpr std::size_t npos = static_cast<std::size_t>(-1);

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
  void set_options(const interest_options& opt);
  /// The host reference engine the tracker falls back to (its pair finder, its options).
  [[nodiscard]] const host_visibility_engine& reference() const { return reference_; }

 private:
  /// The engine the next update runs on.
  [[nodiscard]] visibility_engine* active() {
    const bool usable = engine_ != nullptr && engine_error_.empty() && (opt_.max_visible == 0 || engine_->caps_visible());
    return usable ? engine_ : &reference_;
  }
  [[nodiscard]] visibility_input input_of(const entity_columns& in) const;
  [[nodiscard]] std::optional<box_error> run(visibility_engine& e, const entity_columns& in);
  /// After a successful update or apply_pairs on `e`: rows, lists and stats from out_.
  void commit(visibility_engine& e, const entity_columns& in, double engine_ms, double host_ms, bool host_done);
  [[nodiscard]] std::optional<box_error> name_box_error(const entity_columns& in, std::optional<box_error> err) const;
  /// The last update's sets, enters and leaves into the tracker's own arrays (the lists then no
  /// longer point into an engine's output); nothing when they already are.
  void adopt();
  /// Hands the last update's sets to `e` (load_previous) from the tracker's own copy.
  void hand_over(visibility_engine& e);
  /// Hands `e` the last update's sets with the pending carried targets merged in (carry_visible),
  /// for the update of `in`; the carry stays pending until that update is committed.
  void hand_over_carried(visibility_engine& e, const entity_columns& in);
  [[nodiscard]] std::span<const entity_id> fetched_row(std::size_t row) const;
  void begin_update(const entity_columns& in);  // slot_bits_, slot_count_
  void map_rows_into(const std::vector<entity_id>& ids, std::vector<std::uint32_t>& row_of_slot) const;
  /// One kind of per-row list: row r is data[off[r], off[r] + len[r]) (len null: off[r + 1]).
  struct row_lists {
    const entity_id* data = nullptr;
    const std::uint32_t* off = nullptr;
    const std::uint32_t* len = nullptr;
    [[nodiscard]] std::span<const entity_id> row(std::size_t r) const {
      return {data + off[r], len != nullptr ? len[r] : off[r + 1] - off[r]};
    }
  };

  thread_pool* pool_;
  interest_options opt_;
  interest_stats stats_;
  host_visibility_engine reference_;
  visibility_engine* engine_ = nullptr;  // set_engine's
  std::string engine_error_;
  visibility_engine* holder_ = nullptr;    // holds the last update's sets as its previous ones
  visibility_engine* producer_ = nullptr;  // the lists point into its output (null: own_*)
  bool last_on_engine_ = false;
  visibility_output out_;
  std::uint32_t slot_bits_ = 22;  // of the last update's ids
  std::size_t slot_count_ = 0;    // one past the highest slot seen
  [[nodiscard]] std::uint32_t slot_of(entity_id id) const { return id & ((1u << slot_bits_) - 1u); }

  std::vector<entity_id> ids_, next_ids_;                          // rows of the last update / the next
  std::vector<std::uint32_t> row_of_slot_, spare_row_of_slot_;     // slot -> row (checked against ids)
  const std::vector<std::uint8_t>* view_demand_ = nullptr;
  const std::function<void()>* while_device_works_ = nullptr;
  std::vector<std::uint8_t> demand_rows_, next_demand_rows_;  // per row of the last / next update
  bool partial_ = false;  // vis_list_ holds the demanded rows only; the rest via fetched_row
  mutable std::mutex fetch_mutex_;
  mutable std::atomic<bool> fetched_{false};
  mutable row_lists full_list_;

  // What the accessors read: producer_'s output, or the tracker's own copy.
  row_lists vis_list_, enter_list_, leave_list_;
  std::vector<entity_id> own_vis_, own_enter_, own_leave_;
  std::vector<std::uint32_t> own_vis_off_{0}, own_enter_off_{0}, own_leave_off_{0};

  // carry_visible's pending (observer, target) pairs, and the merged previous sets built from them.
  std::vector<std::pair<entity_id, entity_id>> carry_, last_carry_;
  std::vector<entity_id> carry_ids_, carry_vis_;
  std::vector<std::uint32_t> carry_off_;
};

}  // namespace zone::interest
