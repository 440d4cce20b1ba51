// Structs read by both the host dispatch and the kernels of the GPU LBVH finder.
#pragma once

#include <vector_types.h>  // float4, uint4 (plain C structs from the CUDA toolkit)

#include <cstdint>

#include "gpu/common/box_arrays.h"  // box_arrays, the input boxes

namespace zone::gpu::detail::lbvh {

/// One internal node of the hierarchy, as the traversal reads it: the boxes of its two children
/// (Karras numbering: node 0 is the root; leaves are the sorted boxes). For child c:
/// lo[c].xyz / hi[c].xyz its bounding box, lo[c].w the sorted index of its rightmost leaf and
/// hi[c].w its reference (>= 0: internal node, < 0: leaf ~ref), both as int bits.
struct alignas(64) node {
  float4 lo[2];
  float4 hi[2];
};
static_assert(sizeof(node) == 64);

/// Scene statistics: bounds as order-preserving ints, the sum of box edges per axis, the OR and
/// AND of every category and mask (all equal: the filter bits cannot prune), and the device-side
/// counters of one call.
struct scene {
  std::int32_t lo[3];
  std::int32_t hi[3];
  double edge_sum[3];
  std::uint32_t category_or, category_and, mask_or, mask_and;
  std::uint32_t large_count;  ///< boxes kept out of the tree (sorted to the end)
  std::uint32_t max_depth;    ///< deepest leaf (when measured)
};

/// What a call reads back after the counting pass (one synchronisation).
inline constexpr int max_batch_slots = 17;  // lbvh_tuning::max_batches + 1
struct readback {
  std::uint64_t batch_pos[max_batch_slots];  ///< first pair of each fill batch; [batches] = tree total
  std::uint32_t large_count;
  std::uint32_t overflow_count;  ///< queries whose stack overflowed (redone by the brute pass)
  std::uint32_t max_depth;
  std::uint32_t pad;
};

/// Arguments of the traversal kernels (counting and writing passes).
struct traverse_args {
  const node* nodes;
  const uint4* node_bits;  ///< per internal node: OR of categories and of masks under child 0, child 1
  const float4* leaf_lo;  ///< sorted boxes: lo.xyz, category bits in w
  const float4* leaf_hi;  ///< hi.xyz, mask bits in w
  const std::uint32_t* ids;  ///< sorted position -> box id
  const scene* sc;           ///< large_count: tree leaves = n - large_count
  std::uint32_t n;
  std::uint32_t stack_cap;  ///< <= lbvh_tuning::max_stack
  std::uint32_t first, last;  ///< leaves of this launch (writing pass: one batch)
  std::uint32_t* counts;      ///< per leaf (n + 1 entries; 0 past the tree)
  std::uint8_t* overflowed;   ///< per leaf: 1 when its stack overflowed (n entries)
  const std::uint64_t* pos;   ///< writing pass: first pair of each leaf
  std::uint32_t* out;         ///< writing pass: pairs {a, b} as 2 x u32
};

/// Arguments of the brute pass: queries are the overflowed leaves (ov_list) and then the large
/// boxes (sorted positions n - large_count .. n - 1); items are (query, chunk of brute_chunk boxes).
struct brute_args {
  const float4* leaf_lo;
  const float4* leaf_hi;
  const std::uint32_t* ids;
  const scene* sc;
  const std::uint32_t* ov_list;
  std::uint32_t ov_count;
  std::uint32_t queries;
  std::uint32_t chunks;
  std::uint32_t n;
  std::uint32_t* item_counts;  ///< counting pass: per item (+1 zero at the end)
  const std::uint64_t* item_pos;  ///< writing pass
  std::uint64_t base;             ///< writing pass: pairs before the brute pass's
  std::uint32_t* out;
};

}  // namespace zone::gpu::detail::lbvh
