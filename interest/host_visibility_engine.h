// interest/host_visibility_engine.h: the interest step's host reference engine (visibility_engine.h)
// on any pair_finder: one finder call per update over every AOI box grown by the hysteresis margin
// and every presence box, then the diff on the host (per observer: candidates classified against
// the previous visible set, enters at the exact AOI box, leaves beyond the grown one; the
// optional max_visible cap). It is the reference the GPU engine (gpu/visibility.h) is tested
// against, and the engine interest_tracker falls back to. Algorithm: docs/zone.md, "Interest tracker".
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <vector>

#include "interest.h"
#include "thread_pool.h"
#include "visibility_engine.h"

namespace zone::interest {

/// Box 2k: row k's AOI box grown by in.hysteresis (category aoi, mask = sees[k]); box 2k + 1: its
/// presence box (category = visibility[k], mask 0). The numbering visibility_engine::update's
/// error index refers to. Written in fixed chunks on `pool` (may be null).
void build_step_boxes(const visibility_input& in, box_set& out, thread_pool* pool = nullptr);
/// Box `index` of build_step_boxes alone (index < 2 * in.n).
[[nodiscard]] box step_box(const visibility_input& in, std::size_t index);

/// Tuning of the host engine (its output never depends on it).
struct host_engine_options {
  /// Observers per parallel task of the diff (fixed, so output never depends on the thread count).
  std::uint32_t rows_per_task = 256;
  /// Find the pairs through pair_finder::find_view (the GPU finders hand over their own result
  /// buffer: no copy of every pair); false: find() into the engine's own list.
  bool finder_view = true;
  /// Find each observer's candidates on a grid of the presence boxes (the GPU engine's query,
  /// gpu/visibility.h, on the host threads) instead of through the pair finder: no pair list, no
  /// count and fill passes over it. The same output. False: the pair finder (the reference path).
  bool presence_grid = false;
  /// The presence grid's cell edge in metres; 0: planned per update from the mean AOI and body
  /// widths (docs/zone.md, "Interest tracker").
  float grid_cell_edge = 0;
};

/// The host reference engine. Its output keeps row lengths apart (visibility_output's `len`
/// arrays): the visible sets and enters share offsets (a row's room = its candidate count). It
/// honours max_visible (caps_visible). Memory is reused between updates: no allocation in steady
/// state beyond growth. Not safe to call from several threads at once.
class host_visibility_engine final : public visibility_engine {
 public:
  /// `finder` and `pool` (may be null: the calling thread only) must outlive the engine.
  explicit host_visibility_engine(pair_finder& finder, thread_pool* pool = nullptr, host_engine_options opt = {});

  /// Builds the boxes, finds the pairs and diffs them; in.while_waiting is not called (no device
  /// to overlap: the caller does that work after). The finder's first invalid box is returned (nothing changes).
  /// Throws std::length_error for more than 2^32 - 1 candidates in one update (nothing changes).
  [[nodiscard]] std::optional<std::size_t> update(const visibility_input& in, visibility_output& out) override;
  /// Throws std::invalid_argument for inconsistent spans (ids.size() + 1 != offsets.size(), or an
  /// offset beyond `visible`).
  void load_previous(std::span<const std::uint32_t> ids, std::uint32_t slot_bits, std::span<const std::uint32_t> offsets,
                     std::span<const std::uint32_t> visible) override;
  /// The last update's visible sets in compact form (a copy, made on the first call after an update).
  [[nodiscard]] visibility_lists fetch_all_visible() override;
  [[nodiscard]] bool caps_visible() const override { return true; }
  [[nodiscard]] const char* name() const override { return "host"; }

  /// The second half of update(), for callers that find the pairs themselves: `boxes` must be
  /// build_step_boxes(in) (its size 2 * in.n is checked) and `pairs` every qualifying pair of
  /// it, in any order, each once. Refuses (an error, nothing changes) a box set of another size,
  /// a pair with an id beyond it and more than 2^32 - 1 candidates. `out` is written on success.
  [[nodiscard]] std::optional<box_error> apply_pairs(const visibility_input& in, const box_set& boxes,
                                                     std::span<const id_pair> pairs, visibility_output& out);

  [[nodiscard]] pair_finder& finder() const { return *finder_; }
  [[nodiscard]] const host_engine_options& options() const { return opt_; }
  void set_options(const host_engine_options& opt) { opt_ = opt; }
  /// The boxes of the last update() that ran the pair finder (build_step_boxes' layout).
  [[nodiscard]] const box_set& boxes() const { return boxes_; }
  /// True when the last successful update() found its candidates on the presence grid.
  [[nodiscard]] bool last_on_grid() const { return last_on_grid_; }
  /// The presence grid's figures of the last update on it (finder_stats' fields: cell edge, cells,
  /// cell entries, large boxes, checks; plan_ms = validation, plan and grid build, check_ms = the
  /// query).
  [[nodiscard]] const finder_stats& grid_stats() const { return grid_stats_; }

 private:
  struct presence_box {
    float lo_x, lo_y, lo_z, hi_x, hi_y, hi_z;
  };
  void begin(const visibility_input& in);  // slot_bits_, slot_count_
  [[nodiscard]] std::uint32_t slot_of(std::uint32_t id) const { return id & ((1u << slot_bits_) - 1u); }
  void map_rows();  // row_of_slot_ for ids_
  /// Per row of [first, last): classified against the previous set, merged, capped. `cand` holds
  /// row first's candidates, the others' follow (vis_off_ relative to vis_off_[first]).
  void process_rows(const visibility_input& in, std::size_t first, std::size_t last, const std::uint64_t* cand);
  /// What grid_candidates did: declined (the pair finder runs), an invalid box, or the candidates.
  enum class grid_result { declined, invalid, done };
  /// The presence-grid path's first half: validation, the grid, the candidates per row into
  /// grid_cand_ (one buffer per row task) and their counts into task_cursor_. Only scratch memory
  /// is written. `bad` gets the first invalid box.
  [[nodiscard]] grid_result grid_candidates(const visibility_input& in, std::size_t& bad, double& build_ms);
  /// The common second half: this update's rows, offsets, leaves, classification. `from_grid`:
  /// candidates in grid_cand_ (per row task), else in cand_.
  void finish_rows(const visibility_input& in, std::uint64_t candidates, bool from_grid, visibility_output& out);

  pair_finder* finder_;
  thread_pool* pool_;
  host_engine_options opt_;
  std::uint32_t slot_bits_ = 22;
  std::size_t slot_count_ = 0;  // one past the highest slot seen
  box_set boxes_;
  pair_list pairs_;

  // This update, by row. Visible sets and enters share the candidate offsets (room per row =
  // candidate count); leaves are laid out by the previous set's size.
  std::vector<std::uint32_t> ids_;
  std::vector<std::uint32_t> vis_off_;  // rows + 1
  std::vector<std::uint32_t> vis_len_, enter_len_, leave_off_, leave_len_;
  std::vector<std::uint32_t> vis_, enter_, leave_;
  std::vector<std::uint64_t> cand_;        // candidates by row: (target handle << 32) | target row
  std::vector<std::uint32_t> task_cursor_;  // per (pair task, row): candidate count, then fill cursor
  std::vector<std::uint64_t> chunk_base_;   // per chunk of rows: its first candidate (a scan)
  std::vector<std::size_t> task_bad_;       // per pair task: first pair with an id beyond the set
  std::vector<std::uint64_t> cap_keys_;     // (distance key << 32) | handle, for the cap
  std::vector<std::uint32_t> prev_row_;     // previous row of each row's observer, or none
  std::vector<presence_box> presence_;      // presence box by row (from the box set)
  std::uint64_t capped_pending_ = 0;        // summed by the row tasks (atomic_ref)

  // The presence grid (grid_candidates): entries sorted by cell (x-major rows of cells), the
  // presence boxes kept out of it (large), and each row task's candidates.
  struct grid_bounds {
    float lo_x, lo_y, hi_x, hi_y;
    double aoi_width, body_width;  // sums
    std::uint32_t observers;       // rows that see something
    std::uint32_t self;            // rows that see their own class
    std::size_t bad;               // first invalid box of the chunk, or none
  };
  std::vector<grid_bounds> grid_part_;          // per chunk of rows
  std::vector<std::uint32_t> cell_start_;       // per cell + 1
  std::vector<std::uint32_t> cell_cursor_;      // per cell (scatter)
  std::vector<float> e_lo_x_, e_lo_y_, e_lo_z_, e_hi_x_, e_hi_y_, e_hi_z_;
  // Class, row, and the output-cell rule's thresholds per axis (0 in the box's first column or
  // row of cells, else that column or row: see grid_candidates).
  std::vector<std::uint32_t> e_cls_, e_row_, e_tx_, e_ty_;
  std::vector<std::uint64_t> e_key_;            // (handle << 32) | row
  std::vector<std::uint32_t> grid_large_;       // rows whose presence box is kept out of the grid
  std::vector<std::vector<std::uint64_t>> grid_cand_;  // per row task: its rows' candidates
  std::vector<std::uint64_t> grid_task_checks_;  // per row task
  std::uint64_t grid_self_pairs_ = 0;
  finder_stats grid_stats_;
  bool last_on_grid_ = false;

  // The previous update (or load_previous).
  std::vector<std::uint32_t> prev_ids_;
  std::vector<std::uint32_t> prev_off_, prev_len_;
  std::vector<std::uint32_t> prev_vis_;
  std::vector<std::uint32_t> row_of_slot_;  // slot -> row of ids_ (checked against ids)

  // fetch_all_visible's compact copy.
  std::vector<std::uint32_t> full_vis_, full_off_;
  bool full_made_ = false;
};

}  // namespace zone::interest
