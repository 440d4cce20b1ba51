// Host-callable launchers of the LBVH kernels and CUB steps (see pbig_launch.h for why they are
// kept free of host-library headers). Each returns the launch's cudaError_t; the CUB wrappers
// follow CUB's convention: with temp == nullptr they only set temp_bytes.
#pragma once

#include <cuda_runtime.h>

#include <cstddef>
#include <cstdint>

#include "lbvh_shared.h"

namespace zone::gpu::detail::lbvh {

/// Scene bounds and edge sums (zeroes the scene's counters first).
cudaError_t launch_scene(const box_arrays& boxes, std::uint32_t n, scene* sc, cudaStream_t stream);
/// 30-bit Morton codes of the centroids, bit 30 for mask-0 boxes (large boxes: key 2^31, after
/// every other key) and ids 0..n-1.
cudaError_t launch_morton(const box_arrays& boxes, std::uint32_t n, scene* sc, double large_threshold,
                          std::uint32_t* keys, std::uint32_t* ids, cudaStream_t stream);
/// Stable radix sort of (key, id) by the 32 bits of the key.
cudaError_t sort_keys(void* temp, std::size_t& temp_bytes, const std::uint32_t* keys_in, std::uint32_t* keys_out,
                      const std::uint32_t* ids_in, std::uint32_t* ids_out, std::uint32_t n, cudaStream_t stream);
/// Sorted boxes as two float4 each; hierarchy (Karras's determineRange / findSplit); parents.
cudaError_t launch_build(const box_arrays& boxes, std::uint32_t n, const scene* sc, const std::uint32_t* keys,
                         const std::uint32_t* ids, float4* leaf_lo, float4* leaf_hi, node* nodes,
                         std::uint32_t* parent, std::uint32_t* flags, cudaStream_t stream);
/// Bottom-up boxes and filter bits, one thread per leaf, one atomic flag per node; optional
/// depth measurement.
cudaError_t launch_refit(const float4* leaf_lo, const float4* leaf_hi, std::uint32_t n, const scene* sc,
                         const std::uint32_t* parent, node* nodes, uint4* bits, std::uint32_t* flags,
                         bool measure_depth, scene* sc_out, cudaStream_t stream);
/// Traversal: counting pass (counts and overflow flags of leaves [0, n]) or writing pass
/// (leaves [args.first, args.last)).
cudaError_t launch_traverse(const traverse_args& args, bool count_only, cudaStream_t stream);
/// Exclusive scan of n + 1 u32 counts into 64-bit positions.
cudaError_t scan_counts(void* temp, std::size_t& temp_bytes, const std::uint32_t* counts, std::uint64_t* pos,
                        std::uint64_t count, cudaStream_t stream);
/// Compacts the overflowed leaves (ascending) into list, their number into *count.
cudaError_t select_overflowed(void* temp, std::size_t& temp_bytes, const std::uint8_t* flags, std::uint32_t* list,
                              std::uint32_t* count, std::uint32_t n, cudaStream_t stream);
/// rb->batch_pos[k] = pos[tree * k / batches] (tree = n - large_count); copies the counters.
cudaError_t launch_readback(const std::uint64_t* pos, std::uint32_t n, std::uint32_t batches, const scene* sc,
                            readback* rb, cudaStream_t stream);
/// Brute pass: counting (item counts) or writing.
cudaError_t launch_brute(const brute_args& args, bool count_only, cudaStream_t stream);

}  // namespace zone::gpu::detail::lbvh
