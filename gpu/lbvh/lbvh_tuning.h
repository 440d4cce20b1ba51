// Tuning constants of the GPU LBVH finder, in one place (docs/gpu.md, "LBVH", says how they were chosen).
#pragma once

#include <cstddef>
#include <cstdint>

namespace zone::gpu::lbvh_tuning {

/// Block size of the element-wise kernels and the traversal.
inline constexpr std::uint32_t block = 256;
/// Entries of a traversal thread's stack. The tree's depth bound: along any root-to-leaf path the
/// common-prefix length delta of the internal nodes strictly grows. Tree keys are below 2^31 (30
/// Morton bits and the target bit), so delta is in [1, 31] between different keys and in
/// 32 + [2, 31] between equal ones (sorted positions < 2^30 are appended): at most 61 values, so
/// no path has more than 61 internal nodes and a query, which pushes at most one entry per level,
/// never needs more than 61 entries.
inline constexpr std::uint32_t max_stack = 64;
/// A box is "large" (kept out of the tree, tested against every box by the brute pass) when a
/// uniform-density estimate of its overlaps exceeds max(large_min_overlaps, N / large_n_divisor).
/// The brute pass then costs at most about 2 * large_n_divisor tests per expected pair.
inline constexpr double large_min_overlaps = 4096.0;
inline constexpr double large_n_divisor = 64.0;
/// Brute pass (large boxes and overflowed queries): boxes tested per thread, per block of `block`.
inline constexpr std::uint32_t brute_per_thread = 8;
inline constexpr std::uint32_t brute_chunk = block * brute_per_thread;
/// Fill batches: about one per this many tree leaves (at most max_batches), so the device-to-host
/// copy of batch k overlaps the writing pass of batch k + 1.
inline constexpr std::uint32_t leaves_per_batch = 1u << 19;
inline constexpr std::uint32_t max_batches = 16;
/// Default device output capacity in pairs when lbvh_options::initial_output_pairs is 0.
inline constexpr std::size_t default_output_pairs = std::size_t{1} << 20;
/// Upload: the pinned staging copy is cut into parts so that packing part k + 1 on the CPU
/// overlaps the host-to-device copy of part k; packing and the final copy run on the pool from
/// this many boxes / pairs up.
inline constexpr std::size_t upload_part_boxes = std::size_t{1} << 19;
inline constexpr std::size_t max_upload_parts = 16;
inline constexpr std::size_t parallel_copy_pairs = 65536;

}  // namespace zone::gpu::lbvh_tuning
