// Tuning constants of the GPU PBIG finder, in one place (see docs/gpu.md for how they were chosen).
#pragma once

#include <cstdint>

namespace zone::gpu::tuning {

/// Box-segment length T = threads per checking block (the paper's T; 64 keeps a thread's matches
/// of one segment in one 64-bit mask, and local ids fit the 8-bit field of the 3-level encoding).
inline constexpr std::uint32_t segment = 64;
/// Eq. 6's lower bound W on f = N*alpha/M: the warp width.
inline constexpr double warp_width = 32.0;
/// Boxes sampled on the GPU to estimate alpha (the paper uses 1000; at most plan_threads).
inline constexpr std::uint32_t plan_samples = 1000;
inline constexpr std::uint32_t plan_threads = 1024;
/// A box that would occupy more than max(large_box_min_cells, large_box_alpha_factor * alpha)
/// cells is handled apart from the grid (same rule as the CPU grid finder).
inline constexpr double large_box_min_cells = 64.0;
inline constexpr double large_box_alpha_factor = 16.0;
/// Plan reuse: the previous cell edge is kept when N moved by at most 10% and the scene extent
/// and the sample's mean box size per axis by at most 5%.
inline constexpr double reuse_count_tolerance = 0.10;
inline constexpr double reuse_size_tolerance = 0.05;
/// Pipeline batching: cells are cut into batches of about equal tile count (a tile = one
/// segment-by-segment block of checks), at least min_tiles_per_batch each, at most max_batches.
inline constexpr std::uint32_t min_tiles_per_batch = 16384;
inline constexpr std::uint32_t max_batches = 16;
/// Default output capacity per buffer, in pairs, when pbig_options::initial_output_pairs is 0.
inline constexpr std::size_t default_output_pairs = std::size_t{1} << 22;
/// Batches with fewer pairs are decoded on the calling thread (waking the pool costs more).
inline constexpr std::uint64_t parallel_decode_pairs = 32768;
/// Validation in find_pairs_view: boxes per parallel chunk.
inline constexpr std::size_t validate_chunk = 65536;
/// Per-cell sort by id after the mapping: one warp per cell ranks its ids when the fullest cell
/// holds at most this many entries (one kernel); otherwise CUB's segmented sort.
inline constexpr std::uint32_t small_cell_sort = 256;
/// Block size of the element-wise kernels (bounds, count, map, gather, large boxes).
inline constexpr std::uint32_t block = 256;
/// Box upload: the pinned staging copy is cut into parts so that packing part k+1 on the CPU
/// overlaps the host-to-device copy of part k.
inline constexpr std::size_t upload_part_boxes = std::size_t{1} << 19;
inline constexpr std::size_t max_upload_parts = 16;
/// Single queue (pbig_options::single_queue): the next call's capacity is this call's figure x
/// plus x / queue_margin_div + queue_margin_add (cells, entries, work items, tiles, pairs), so a
/// set that grows by up to 25% between calls still fits.
inline constexpr std::uint64_t queue_margin_div = 4;
inline constexpr std::uint64_t queue_margin_add = 64;

}  // namespace zone::gpu::tuning
