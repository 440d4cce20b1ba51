// Host-callable launchers of the PBIG kernels and the CUB steps, one per kernel or library call.
// Kept free of host-library headers so that nvcc compiles only pbig_kernels.cu; the dispatch
// (pbig_dispatch.cpp, plain C++) calls these. Each returns the launch's cudaError_t. The CUB
// wrappers follow CUB's convention: with temp == nullptr they only set temp_bytes.
#pragma once

#include <cuda_runtime.h>

#include <cstddef>
#include <cstdint>

#include "pbig_shared.h"

namespace zone::gpu::detail {

cudaError_t launch_plan(const box_arrays& boxes, bounds_dev* bounds, const plan_params& prm, plan_state* state,
                        grid_plan_dev* plan, cudaStream_t stream);
/// The plan is read from device memory; nothing is counted when plan->cells > cell_capacity.
cudaError_t launch_count(const box_arrays& boxes, std::uint32_t n, const grid_plan_dev* plan, std::uint64_t cell_capacity,
                         std::uint32_t* counts, std::uint8_t* is_large, std::uint32_t* large_count, cudaStream_t stream);
cudaError_t select_large(void* temp, std::size_t& temp_bytes, const std::uint8_t* is_large, std::uint32_t* large,
                         std::uint32_t* large_count, std::uint32_t n, cudaStream_t stream);
cudaError_t scan_cells(void* temp, std::size_t& temp_bytes, const std::uint32_t* counts, cell_prefix* prefix,
                       std::uint32_t cells, cudaStream_t stream);  // scans cells + 1 values (counts[cells] == 0)
cudaError_t reduce_cells(void* temp, std::size_t& temp_bytes, const std::uint32_t* counts, cell_totals* totals,
                         std::uint32_t cells, cudaStream_t stream);
/// Fills rb (its totals written by reduce_cells before): plan, fits (against cap), totals, batches.
cudaError_t launch_batch_plan(const grid_plan_dev* plan, const cell_prefix* prefix, const std::uint32_t* large_count,
                              map_readback* rb, const grid_capacity& cap, std::uint32_t min_tiles,
                              std::uint32_t max_batches, cudaStream_t stream);
/// Writes a_bytes from device memory `a` to pinned host memory `host_a` (and b_bytes from `b` to
/// `host_b`, when b_bytes > 0) from a kernel: pinned memory is mapped under unified addressing, so
/// the values the host waits for do not queue on the copy engine behind the pairs' copies queued
/// before them (a read-back by cudaMemcpyAsync does). Sizes and addresses multiples of 4; the host
/// reads them once an event recorded after this launch has completed.
cudaError_t launch_to_host(const void* a, void* host_a, std::size_t a_bytes, const void* b, void* host_b,
                           std::size_t b_bytes, cudaStream_t stream);
// The kernels below read `grid` (device memory, filled by launch_batch_plan) and do nothing past
// its sizes, so they can be queued with capacities as sizes before the host knows the grid.
/// Box i of `boxes` (and is_large[i]) has the id first_id + i.
cudaError_t launch_map(const box_arrays& boxes, std::uint32_t n, std::uint32_t first_id, const grid_plan_dev* plan,
                       const map_readback* grid, const std::uint8_t* is_large, const cell_prefix* prefix,
                       std::uint32_t* cursor, std::uint32_t* entries, cudaStream_t stream);
cudaError_t sort_cells(void* temp, std::size_t& temp_bytes, const std::uint32_t* in, std::uint32_t* out,
                       std::uint32_t entries, std::uint32_t cells, const cell_prefix* prefix, cudaStream_t stream);
/// The per-cell sort for grids whose fullest cell holds at most tuning::small_cell_sort entries.
cudaError_t launch_sort_small_cells(const std::uint32_t* in, std::uint32_t* out, const cell_prefix* prefix,
                                    std::uint32_t cells, const map_readback* grid, cudaStream_t stream);
cudaError_t launch_pack_boxes(const box_arrays& boxes, std::uint32_t n, float4* box_lo, float4* box_hi,
                              cudaStream_t stream);
/// out[0, n) = value (a class array whose boxes all share one value: not uploaded, filled here).
cudaError_t launch_fill_u32(std::uint32_t* out, std::uint32_t n, std::uint32_t value, cudaStream_t stream);
cudaError_t launch_gather(const float4* box_lo, const float4* box_hi, const std::uint32_t* entries, std::uint32_t count,
                          const map_readback* grid, float4* packed_lo, float4* packed_hi, cudaStream_t stream);
cudaError_t launch_expand(const cell_prefix* prefix, std::uint32_t cells, const map_readback* grid, std::uint32_t* items,
                          cudaStream_t stream);
cudaError_t launch_check(const check_args& args, bool balanced, bool compressed, cudaStream_t stream);
// The overlapped upload (stage_lists, check_stage_kernel): stage j's per-cell prefixes and totals
// from chunk j's counts and the earlier chunks' lists (`earlier`: chunks 0..j-1) at the stage width
// (`width`, one of stage_widths: stage_layout; else cudaErrorInvalidValue), the stage's checks at
// the same width, and the validation of one chunk (the lowest invalid index of `boxes` in result->bad).
cudaError_t scan_stage_cells(void* temp, std::size_t& temp_bytes, const std::uint32_t* counts,
                             const stage_lists& earlier, std::uint32_t width, cell_prefix* prefix, std::uint32_t cells,
                             cudaStream_t stream);
cudaError_t reduce_stage_cells(void* temp, std::size_t& temp_bytes, const std::uint32_t* counts,
                               const stage_lists& earlier, std::uint32_t width, cell_totals* totals,
                               std::uint32_t cells, cudaStream_t stream);
cudaError_t launch_check_stage(const check_args& args, const stage_lists& lists, bool balanced, std::uint32_t width,
                               cudaStream_t stream);
cudaError_t launch_validate(const box_arrays& boxes, std::uint32_t n, bounds_dev* result, cudaStream_t stream);
/// Direct output: moves each tile's plain chunk (written by launch_check, uncompressed) to
/// out_pairs + 2 * tile_pos[tile]; nothing when *cursor > capacity (the batch overflowed).
cudaError_t launch_place_chunks(const unsigned char* chunks, const unsigned long long* cursor, std::uint64_t capacity,
                                const std::uint64_t* tile_off, const std::uint32_t* tile_pairs,
                                const std::uint64_t* tile_pos, std::uint32_t tiles, std::uint32_t* out_pairs,
                                cudaStream_t stream);
/// Exclusive scan of per-tile pair counts into 64-bit positions (count values; pass count + 1
/// with a zero last count to get the total at position count).
cudaError_t scan_tiles(void* temp, std::size_t& temp_bytes, const std::uint32_t* tile_pairs, std::uint64_t* tile_pos,
                       std::uint64_t count, cudaStream_t stream);
cudaError_t launch_large_count(const box_arrays& boxes, std::uint32_t n, const std::uint32_t* large,
                               std::uint32_t large_count, const std::uint8_t* is_large, std::uint32_t chunks,
                               std::uint32_t* counts, cudaStream_t stream);
cudaError_t scan_u32(void* temp, std::size_t& temp_bytes, const std::uint32_t* in, std::uint32_t* out,
                     std::uint64_t n, cudaStream_t stream);
cudaError_t launch_large_write(const box_arrays& boxes, std::uint32_t n, const std::uint32_t* large,
                               std::uint32_t large_count, const std::uint8_t* is_large, std::uint32_t chunks,
                               const std::uint32_t* offsets, std::uint32_t* pairs, cudaStream_t stream);

}  // namespace zone::gpu::detail
