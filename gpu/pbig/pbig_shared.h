// Structs read by both the host dispatch and the kernels of the GPU PBIG finder.
#pragma once

#include <vector_types.h>  // float4 (plain C struct from the CUDA toolkit)

#include <cstdint>

#include "gpu/common/box_arrays.h"  // box_arrays, the input boxes

namespace zone::gpu::detail {

/// The grid plan, written by the planning kernel in device memory and copied back to the host.
/// The cell of coordinate x on axis d is clamp(floor((x - origin[d]) * inv_edge), 0, dims[d]-1),
/// computed in double precision by one function (cell_of) everywhere, so it is monotone in x.
struct grid_plan_dev {
  double origin[3];
  double edge;
  double inv_edge;
  double alpha;          ///< estimated average number of cells a box occupies
  double large_cells;    ///< boxes occupying more cells than this are handled apart
  std::uint32_t dims[3];
  std::uint32_t reused;  ///< 1 when the previous call's edge was kept (statistics unchanged)
  std::uint64_t cells;   ///< dims[0] * dims[1] * dims[2]
};

/// Box statistics the planner compares to decide whether the previous edge still fits.
/// With the cost-aware plan it also carries the candidate edges from the planning kernel to the
/// cost kernel, and that kernel's sums (zeroed by the planning kernel on every fresh plan).
inline constexpr int max_plan_candidates = 8;
struct plan_state {
  double edge;
  double count;
  double extent[3];
  double mean_size[3];
  std::uint32_t valid;
  std::uint32_t cost_pending;  ///< 1: the cost kernel scores cand_edge[] and may replace the edge
  std::uint32_t cost_blocks_done;
  double cand_edge[max_plan_candidates];  ///< candidate 0 = Eq. 6's edge; 0 = no candidate
  unsigned long long cand_cells[max_plan_candidates];   ///< sum over the sample of cells occupied
  unsigned long long cand_shared[max_plan_candidates];  ///< sum over sample pairs of cells shared
};

/// Scene bounds as order-preserving integers (float bit patterns mapped to signed ints).
struct bounds_dev {
  std::int32_t lo[3];
  std::int32_t hi[3];
  std::uint32_t bad;  ///< with plan_params::validate: the first invalid box, else 0xffffffff
};

/// Per-cell exclusive prefixes: first entry (box slot), first work item, first tile.
struct cell_prefix {
  std::uint32_t entry;
  std::uint32_t item;
  std::uint32_t tile;
};

/// Whole-grid totals (64-bit, to detect 32-bit overflow of the prefixes).
struct cell_totals {
  std::uint64_t entries;
  std::uint64_t tiles;
  std::uint64_t checks;
  std::uint64_t max_count;
};

/// Batch boundaries, written by the batch-planning kernel: batch b covers cells
/// [cell[b], cell[b+1]), work items [item[b], item[b+1]) and tiles [tile[b], tile[b+1]).
inline constexpr int max_batch_slots = 17;  // tuning::max_batches + 1
struct batch_plan {
  std::uint32_t count;
  std::uint32_t cell[max_batch_slots];
  std::uint32_t item[max_batch_slots];
  std::uint32_t tile[max_batch_slots];
};

/// The sizes a call's grid buffers were queued with (the batch-planning kernel checks the grid
/// against them). Read-back sizing: the planned cells and the 32-bit limits. Single queue: the
/// last call's figures with a margin, so nothing waits for the host; a grid past any of them is
/// not mapped (every later kernel of the call does nothing) and the call is re-run with the
/// read-back sizes.
struct grid_capacity {
  std::uint64_t cells;      ///< counts and prefixes hold cells + 1 values
  std::uint64_t entries;    ///< (cell, box) entries: entry lists and the packed box array
  std::uint64_t items;      ///< work items (cell, row segment)
  std::uint64_t tiles;      ///< tiles (one batch's tile index)
  std::uint64_t max_count;  ///< the fullest cell the queued per-cell sort handles
  std::uint32_t large;      ///< 1: boxes handled apart may exist (their passes read sizes back)
};

/// What one call reads back after mapping (the batch-planning kernel fills it; the reduce writes
/// `totals`). When the grid does not fit the capacity it was queued with, `fits` is 0 and
/// `cells` and `total` are 0: the later kernels of the call, which read them, do nothing.
struct map_readback {
  cell_prefix total;  ///< prefix at cell M: totals of entries, items, tiles (32-bit)
  cell_totals totals;
  std::uint32_t large_count;
  std::uint32_t cells;  ///< the grid's cells when it fits, else 0
  std::uint32_t fits;
  batch_plan batches;
  grid_plan_dev plan;  ///< the call's plan (for the host's report and statistics)
};

/// Header of one output chunk (one tile with at least one pair), 12 bytes, 4-byte aligned.
/// Compressed body: per row with matches, [local_v:u8][count-1:u8][local_h:u8 x count];
/// plain body: count x {a:u32, b:u32} with a < b, the final box ids.
struct chunk_header {
  std::uint32_t cell_begin;  ///< first entry of the cell (the cell's level of Eq. 8)
  std::uint16_t seg_v;       ///< segment of the rows
  std::uint16_t seg_h;       ///< segment of the columns
  std::uint16_t body_bytes;
  std::uint16_t pairs;
};
static_assert(sizeof(chunk_header) == 12);

/// Parameters of the planning kernel.
struct plan_params {
  std::uint32_t n;
  std::uint32_t samples;
  std::uint64_t seed;
  double min_boxes_per_cell;  // W
  double fixed_edge;          // > 0: use it (grown only to respect the cell cap)
  std::uint32_t allow_reuse;
  std::uint32_t validate;     // 1: the bounds kernel validates every box (pinned input: no host pass)
  std::uint32_t cost_aware;   // 1: score larger edges than Eq. 6's and keep the cheapest (beyond the paper)
  std::uint32_t sample_n;     // bounds and sample from boxes [0, sample_n) (n; the overlapped upload: its first chunk)
};

/// Arguments of one checking-kernel launch (one batch).
struct check_args {
  const grid_plan_dev* plan;  // device memory (the planning kernel's output)
  const map_readback* grid;   // device memory: blocks past grid->total.item do nothing
  const float4* packed_lo;  // in cell order (entry e), or by box id when `indirect`
  const float4* packed_hi;
  const std::uint32_t* entries;  // cell-sorted box ids (plain mode writes final ids)
  std::uint32_t indirect;        // 1: packed_lo/hi are indexed by entries[e] (no gathered copy)
  const cell_prefix* prefix;
  const std::uint32_t* items;
  std::uint32_t item_first;
  std::uint32_t item_last;
  std::uint64_t* tile_off;  // per tile: byte offset of its chunk in the batch's output buffer
  std::uint32_t* tile_pairs;
  std::uint32_t tile_first;  // first tile of the batch (tile arrays are batch-relative)
  unsigned char* out;
  std::uint64_t capacity;
  unsigned long long* cursor;  // bytes claimed in `out` (may pass capacity: overflow)
};

/// The overlapped upload (pbig_options::overlap_min_boxes; docs/gpu.md, "Overlapped upload"): the
/// boxes arrive in at most max_overlap_chunks chunks of ids, and stage j checks the pairs whose
/// larger id is in chunk j. Each chunk i has its own per-cell lists: prefix[i][c].entry is cell
/// c's first entry in entries[i] (ids sorted in each cell). Stage j reads lists 0..j (count = j+1):
/// list j (the stage's own) holds its rows, lists 0..j-1 (the earlier boxes) only columns.
inline constexpr int max_overlap_chunks = 8;
struct stage_lists {
  const cell_prefix* prefix[max_overlap_chunks];
  const std::uint32_t* entries[max_overlap_chunks];
  std::uint32_t count;
};

/// Stage j's work in one cell (check_stage_kernel), from the cell's q boxes of chunk j and p
/// boxes of the earlier chunks, at width W (one of stage_widths, chosen per call on the host:
/// pbig_engine::stage_width, tuning::stage_width_spread): W rows of chunk j's list a work item,
/// column tiles of W boxes. Work item u (u < items) holds row segment u; its column tiles, in this
/// order: the earlier boxes' segments 0..earlier-1 (every pair), then chunk j's own segments
/// u..items-1 (u: the triangle; above: every pair). So the cell has items * earlier +
/// items (items + 1) / 2 tiles, and item u's first is first_tile(u). Two earlier boxes are never
/// tested against each other. The kernel gives an item min(W, 32) lanes (W = 64: two rows a lane,
/// rows lane and lane + 32; W < 32: 32 / W items a warp).
inline constexpr std::uint32_t stage_widths[] = {8, 16, 32, 64};
constexpr bool is_stage_width(std::uint32_t w) { return w == 8 || w == 16 || w == 32 || w == 64; }
struct stage_cell_layout {
  std::uint32_t items;    ///< ceil(q / W)
  std::uint32_t earlier;  ///< ceil(p / W) (0 when q == 0)
  [[nodiscard]] constexpr std::uint32_t tiles_of(std::uint32_t u) const { return earlier + items - u; }
  [[nodiscard]] constexpr std::uint64_t first_tile(std::uint32_t u) const {
    // sum over u' < u of tiles_of(u')
    return std::uint64_t{u} * earlier + std::uint64_t{u} * (2ull * items + 1 - u) / 2;
  }
  [[nodiscard]] constexpr std::uint64_t tiles() const { return first_tile(items); }
};
constexpr stage_cell_layout stage_layout(std::uint32_t q, std::uint32_t p, std::uint32_t w) {
  return {(q + w - 1) / w, q == 0 ? 0u : (p + w - 1) / w};
}

}  // namespace zone::gpu::detail
