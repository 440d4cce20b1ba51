// Plain structs shared by the visibility engine's host dispatch (visibility_engine.cpp) and its
// kernels (visibility_kernels.cu). No host-library headers here (see pbig_launch.h for why).
#pragma once

#include <cuda_runtime.h>

#include <cstdint>

namespace zone::gpu::detail::vis {

inline constexpr std::uint32_t no_row = 0xffffffffu;
inline constexpr std::uint32_t no_box = 0xffffffffu;

/// The uniform grid over the presence boxes, in x and y (z is tested exactly: a zone is flat).
struct grid_params {
  float ox = 0, oy = 0;  ///< origin: the presence boxes' minimum corner
  float edge = 1;        ///< cell edge (metres)
  float inv_edge = 1;    ///< 1 / edge, the factor of the cell function
  std::uint32_t nx = 1, ny = 1;
  std::uint32_t cells = 1;  ///< nx * ny
  std::uint32_t pad = 0;
};

/// Per update: reductions of the prep kernel (integers, so that the plan does not depend on the
/// order of the atomics), the plan, overflow flags and totals; read back once at the end.
struct tick_state {
  int min_x, min_y, max_x, max_y;      ///< presence bounds as order-preserving ints
  unsigned long long aoi_width_sum;    ///< grown AOI widths (x + y) / 2 of observers, 1/16 m units
  unsigned long long body_width_sum;   ///< presence widths (x + y) / 2, 1/16 m units
  std::uint32_t observers;             ///< rows that see something (sees != 0)
  std::uint32_t bodies;                ///< rows with a valid presence box
  std::uint32_t self_pairs;            ///< rows whose AOI sees their own class
  std::uint32_t bad_box;               ///< first invalid box (2i AOI, 2i + 1 presence) or no_box
  std::uint32_t large_count;           ///< presence boxes kept out of the grid
  std::uint32_t overflow;              ///< bit 0: cell entries, bit 1: enters, bit 2: visible entries
  grid_params grid;
  unsigned long long entries;          ///< (cell, presence) entries of the grid
  unsigned long long candidates;       ///< summed by the query kernel
  unsigned long long enter_count;      ///< enters appended by the query kernel
  std::uint32_t visible_total, enter_total, leave_total;
  std::uint32_t download_total;        ///< visible entries of the wanted rows
};

/// The device arrays of the inputs (uploaded as one block, see visibility_engine.cpp).
struct input_arrays {
  const float3* pos;
  const float3* aoi;
  const float3* body;
  const std::uint32_t* cls;
  const std::uint32_t* sees;
  const std::uint32_t* ids;
  const std::uint8_t* wanted;  ///< null: every row
  std::uint32_t* prev_row;  ///< written by the prep kernel from the slot map
};

/// The previous update's rows: its handles and the slot -> row map (stale entries are told apart
/// by comparing the handle).
struct previous_rows {
  std::uint32_t* ids;
  std::uint32_t* row_of_slot;
  std::uint32_t rows;
  std::uint32_t slot_mask;
};

/// The boxes of every row (float4, w unused): grown AOI box and presence box.
struct box_arrays {
  float4* g_lo;
  float4* g_hi;
  float4* p_lo;
  float4* p_hi;
};

/// The grid: per cell the first entry (exclusive scan of counts, cells + 1 entries); per entry
/// the presence box with its class in lo.w and its row in hi.w (bit patterns), and its cell's x.
struct grid_arrays {
  const std::uint32_t* start;
  float4* e_lo;
  float4* e_hi;
  std::uint32_t* e_cx;
  std::uint64_t entry_capacity;
  std::uint32_t* large;  ///< rows of the presence boxes kept out of the grid
};

/// Everything the query, classify and write kernels read and write.
struct pass_args {
  std::uint32_t n;
  input_arrays in;
  box_arrays box;
  grid_arrays grid;
  tick_state* st;
  previous_rows prev;
  // enters as the query finds them: (row << 32) | handle, in no order
  unsigned long long* enter_pairs;
  std::uint64_t enter_capacity;  ///< of enter_pairs, enter_tmp, enter_out
  std::uint32_t* enter_cursor;   ///< n: per row, enters placed so far
  std::uint64_t vis_capacity;    ///< of vis_out, dl_out
  // previous update
  const std::uint32_t* prev_vis;
  const std::uint32_t* prev_off;  ///< prev_rows + 1
  std::uint32_t prev_rows;
  std::uint8_t* flag;             ///< per previous entry: still a candidate
  std::uint32_t* kept_prefix;     ///< per previous entry: kept entries before it in its row
  // this update
  std::uint32_t* enter_tmp;       ///< enters by row, unsorted, at the row's enter offset
  std::uint32_t* vis_len;         ///< n + 1
  std::uint32_t* enter_len;       ///< n + 1
  std::uint32_t* leave_len;       ///< n + 1
  const std::uint32_t* vis_off;   ///< n + 1
  const std::uint32_t* enter_off;
  const std::uint32_t* leave_off;
  std::uint32_t* vis_out;
  std::uint32_t* enter_out;
  std::uint32_t* leave_out;
  // the wanted rows' visible sets, gathered for the download
  std::uint32_t* dl_len;          ///< n + 1
  const std::uint32_t* dl_off;    ///< n + 1
  std::uint32_t* dl_out;
};

}  // namespace zone::gpu::detail::vis
