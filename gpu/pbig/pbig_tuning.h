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
/// Cost-aware edge choice (beyond the paper; pbig_options::cost_aware_plan, docs/gpu.md "PLAN").
/// Eq. 6's edge e0 (smallest cubic edge with f >= W) is kept as the paper's baseline and as the
/// smallest candidate; the candidates are e0 * 2^(j/3), j = 0..plan_candidates-1 (f only grows
/// with the edge, so each still meets f >= W). Each is scored from the same sample as
///   cost(e) = plan_cost_entry_ns * N*alpha(e)   (MAP: count, scatter, sort, gather per cell entry)
///           + plan_cost_cell_ns  * M(e)         (per grid cell: counters, scans, sort segments,
///                                                work items of the checking kernel)
///           + plan_cost_check_ns * C(e)         (CHECK: C = sum over cells of n_c(n_c-1)/2, the
///                                                pair checks; estimated from the sample's shared
///                                                cells, never below its Cauchy-Schwarz bound
///                                                ((N alpha)^2/M - N alpha)/2)
/// and the cheapest wins if it saves at least plan_min_saving_ns over e0 (else e0: the paper's
/// edge). The output (pairs) does not depend on the edge and is left out. A larger candidate whose
/// mean fill N*alpha/M passes plan_max_fill is not taken: its fullest cells would pass
/// small_cell_sort and the per-cell sort by id would switch to CUB's segmented sort, which costs
/// far more per cell than the one-kernel sort.
/// The sort by id of small cells (one warp per cell, O(n_c^2)) is in the check term.
/// Calibration: the three cost constants are fitted to the phase breakdown (MAP per cell entry and
/// per cell, CHECK per pair check) of `bench-gpu --only wsweep` and of the edge sweep
/// `bench-gpu --only esweep` (fixed edges e0 * 2^(j/3) on the six target sets), direct output,
/// pinned input; the figures, the machine, the date and the data files are in
/// docs/gpu-benchmarks.md ("Where the cost-aware plan's constants come from").
inline constexpr std::uint32_t plan_candidates = 7;
inline constexpr double plan_cost_entry_ns = 0.11;
inline constexpr double plan_cost_cell_ns = 2.0;
inline constexpr double plan_cost_check_ns = 0.0015;
inline constexpr double plan_min_saving_ns = 20000.0;
inline constexpr double plan_max_fill = 128.0;  // half of small_cell_sort (Poisson tail of the fullest cell)
/// The candidates' pair counts are summed by plan_candidates * plan_cost_chunks blocks of
/// plan_cost_threads threads (each block a slice of the sample's pairs for one candidate).
inline constexpr std::uint32_t plan_cost_chunks = 16;
inline constexpr std::uint32_t plan_cost_threads = 256;
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
/// Pinned upload: from this many boxes on, while the coordinates are copied the host checks (on
/// the decode pool, early exit) whether every box has the same category and the same mask, as in
/// the plain self-join; then those two arrays (8 of the 32 bytes a box) are not copied but filled
/// on the device. Below it the check would cost more than the copy it saves.
inline constexpr std::size_t uniform_classes_min_boxes = std::size_t{1} << 18;
/// Overlapped upload (pbig_options::overlap_min_boxes, overlap_chunks, overlap_always; docs/gpu.md
/// "Overlapped upload"): pinned input of at least overlap_min_boxes boxes goes up in overlap_chunks
/// chunks of ids, each chunk's pairs (those whose larger id is in it) checked and copied out while
/// the later chunks upload. Below the threshold the one-shot path runs (its two copies are short
/// there); the threshold is the indirect checks' (the stages read boxes through their ids).
/// The pipeline pays only when the pairs-out copy is about as long as the boxes-in copy: it hides
/// one behind the other, while every stage re-reads the earlier chunks' lists, so the checks cost
/// more than the one-shot path's and grow with k. On an output-bound set (many pairs a box) there
/// is nothing to hide the extra checks behind and the call gets slower. So it is taken only when
/// the finder's previous call, on a set of about this size (box count within
/// overlap_size_tolerance of it), wrote at most overlap_max_out_in times the bytes it uploaded
/// (pairs x 8 against 24 or 32 bytes a box); a first call, or one after a call of another size,
/// runs one-shot. The measured cases behind the constants (docs/gpu-benchmarks.md, "Uniform
/// 10^7 through the API"; docs/gpu.md, "Overlapped upload"): a set with under 2x its input bytes out gains from 3 chunks and loses from 6 or more,
/// a set with about 40x its input bytes out loses with 4 chunks; the bound sits between them.
/// 3 chunks: the fastest chunk count measured (the per-stage checks grow with k; 4 is already
/// about even with the one-shot path). Each stage is cut into at most
/// max(2, ceil(max_batches / k)) batches, so the whole call has about max_batches copies.
inline constexpr std::size_t overlap_min_boxes = std::size_t{1} << 22;
inline constexpr std::uint32_t overlap_chunks = 3;
inline constexpr double overlap_max_out_in = 3.0;
inline constexpr double overlap_size_tolerance = 0.25;
/// The overlapped upload's stage width W (check_stage_kernel, stage_layout: W rows of chunk j's
/// cell list a work item, column tiles of W boxes; pbig_options::overlap_stage_width forces one).
/// A stage costs its tests plus fixed costs per tile (the columns' loads and output-cell flags,
/// the scan, the output chunk's atomic, a warp of the placing kernel) and per work item. A chunk
/// holds s = f / k boxes of a cell on average (f = N alpha / M, the plan's), most cells of a
/// uniform set at most s + stage_width_spread sqrt(s) (Poisson). When that fits 8 or 16 boxes, W
/// is 8 or 16: 32 / W items share a warp instead of one item leaving most lanes idle. Else W = 64:
/// one item a warp, a lane's second row (lane + 32) only past 32 boxes, where it shares each
/// column's load with the first; its 64-column tiles take the earlier boxes in half the tiles of
/// W = 32, and a cell's chunk share past 32 stays one item instead of spilling into a second,
/// nearly empty one (uniform 10^7 at k = 3: f = 93, s = 31, at W = 32 about 2 cells in 5 spilled;
/// 11 tiles a cell over the 3 stages against 5.4 at W = 64, and 3 in the one-shot check).
/// W = 32, the layout before (one row a lane, 32-column tiles), is never cheaper than 64 by that
/// count and is not chosen; it stays selectable for A/B runs. Eq. 6's f >= 32 gives s >= 32 / k:
/// W = 16 from k = 4 chunks on such plans, W = 8 only on sparser ones (a fixed cell edge).
inline constexpr double stage_width_spread = 2.0;
/// The overlapped upload's waits for the device (a stage's read-back, a batch's totals, the last
/// copies) give up after this many seconds: a message names the wait, and the call throws
/// std::runtime_error instead of waiting forever on a kernel that does not end. A whole call on
/// 10^7 boxes takes under 0.3 s on the H200.
inline constexpr double overlap_wait_limit_s = 10.0;
/// Boxes per part of that check (parts run on the pool; each stops once a part found a difference).
inline constexpr std::size_t uniform_classes_part = std::size_t{1} << 16;
/// Single queue (pbig_options::single_queue): the next call's capacity is this call's figure x
/// plus x / queue_margin_div + queue_margin_add (cells, entries, work items, tiles, pairs), so a
/// set that grows by up to 25% between calls still fits.
inline constexpr std::uint64_t queue_margin_div = 4;
inline constexpr std::uint64_t queue_margin_add = 64;

}  // namespace zone::gpu::tuning
