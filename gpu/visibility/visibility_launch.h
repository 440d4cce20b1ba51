// Host-callable launchers of the visibility engine's kernels and CUB steps (kept free of
// host-library headers; see pbig_launch.h). Each returns the launch's cudaError_t; the CUB
// wrappers follow CUB's convention: with temp == nullptr they only set temp_bytes.
#pragma once

#include <cuda_runtime.h>

#include <cstddef>
#include <cstdint>

#include "visibility_shared.h"

namespace zone::gpu::detail::vis {

/// Resets the state's reductions and flags.
cudaError_t launch_init(tick_state* st, cudaStream_t stream);
/// Boxes of every row, validation (first invalid box), bounds and width sums, previous rows.
cudaError_t launch_prep(const input_arrays& in, std::uint32_t n, float hysteresis, const box_arrays& box,
                        const previous_rows& prev, tick_state* st, cudaStream_t stream);
/// One thread: the grid from the reductions (at most max_cells cells).
cudaError_t launch_plan(tick_state* st, std::uint32_t max_cells, cudaStream_t stream);
/// Entries per cell (atomics); presence boxes covering more than large_cells cells go to the large list.
cudaError_t launch_count(const pass_args& a, std::uint32_t* counts, cudaStream_t stream);
/// Exclusive scan of max_cells + 1 counts into start.
cudaError_t scan_cells(void* temp, std::size_t& temp_bytes, const std::uint32_t* counts, std::uint32_t* start,
                       std::uint32_t items, cudaStream_t stream);
/// Entries into their cells (cursor: max_cells zeroed counters).
cudaError_t launch_scatter(const pass_args& a, std::uint32_t* cursor, cudaStream_t stream);
/// One warp per observer: its candidates from the grid, each classified at once (a stay flags
/// its previous entry; an enter is appended to enter_pairs), and the row's list sizes.
cudaError_t launch_query(const pass_args& a, cudaStream_t stream);
/// Exclusive scan of n + 1 u32 counts into u32 offsets.
cudaError_t scan_u32(void* temp, std::size_t& temp_bytes, const std::uint32_t* counts, std::uint32_t* off,
                     std::uint32_t items, cudaStream_t stream);
/// An empty kernel (wakes an idle device before an update).
cudaError_t launch_touch(cudaStream_t stream);
/// Flags a visible-list total beyond vis_capacity (after the scans).
cudaError_t launch_capacity(const pass_args& a, cudaStream_t stream);
/// The appended enters into their rows (enter_tmp at enter_off; unsorted within a row).
cudaError_t launch_place_enters(const pass_args& a, cudaStream_t stream);
/// Per observer: sorted enters, leaves in order, the merged visible set.
cudaError_t launch_write(const pass_args& a, cudaStream_t stream);
/// Visible-set sizes of the wanted rows (0 for the others).
cudaError_t launch_wanted_sizes(const pass_args& a, cudaStream_t stream);
/// The wanted rows' visible sets into dl_out at dl_off; one warp per row.
cudaError_t launch_gather(const pass_args& a, cudaStream_t stream);
/// Copies the totals (entries, candidates, list sizes) into the state.
cudaError_t launch_totals(const pass_args& a, std::uint32_t max_cells, cudaStream_t stream);
/// When the update is valid and nothing overflowed: this update's rows become the previous rows
/// (handles and slot map).
cudaError_t launch_commit(const pass_args& a, cudaStream_t stream);
/// The slot map of `rows` handles (the map is first cleared: 2^slot_bits entries).
cudaError_t launch_map_slots(const std::uint32_t* ids, std::uint32_t rows, std::uint32_t slot_bits,
                             std::uint32_t* row_of_slot, cudaStream_t stream);

}  // namespace zone::gpu::detail::vis
