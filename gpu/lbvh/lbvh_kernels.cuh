// Kernels of the GPU LBVH finder (Karras, "Thinking Parallel" Parts II-III and HPG 2012): small
// and single-purpose, each starting with a bounds guard. Included only by lbvh_kernels.cu.
#pragma once

#include <cub/block/block_reduce.cuh>
#include <cub/block/block_scan.cuh>
#include <cuda_runtime.h>

#include <cfloat>
#include <cstdint>

#include "lbvh_shared.h"
#include "lbvh_tuning.h"

namespace zone::gpu::detail::lbvh {

/// Order-preserving map between floats and signed ints (for atomicMin/atomicMax on floats).
__device__ __forceinline__ std::int32_t to_ordered(float f) {
  const std::int32_t i = __float_as_int(f);
  return i >= 0 ? i : i ^ 0x7FFFFFFF;
}
__device__ __forceinline__ float from_ordered(std::int32_t i) { return __int_as_float(i >= 0 ? i : i ^ 0x7FFFFFFF); }

/// Tree leaves: the sorted boxes before the large ones.
__device__ __forceinline__ std::uint32_t tree_leaves(const scene* sc, std::uint32_t n) { return n - sc->large_count; }

// ---- scene statistics and Morton codes --------------------------------------------------------

__global__ void init_scene_kernel(scene* sc) {
  if (threadIdx.x != 0 || blockIdx.x != 0) return;
  for (int d = 0; d < 3; ++d) {
    sc->lo[d] = to_ordered(FLT_MAX);
    sc->hi[d] = to_ordered(-FLT_MAX);
    sc->edge_sum[d] = 0.0;
  }
  sc->category_or = 0;
  sc->category_and = ~0u;
  sc->mask_or = 0;
  sc->mask_and = ~0u;
  sc->large_count = 0;
  sc->max_depth = 0;
}

/// Scene bounds (min lo, max hi) and the sum of edges per axis: block reductions, one atomic each.
__global__ void scene_kernel(box_arrays boxes, std::uint32_t n, scene* sc) {
  using reduce_f = cub::BlockReduce<float, lbvh_tuning::block>;
  using reduce_d = cub::BlockReduce<double, lbvh_tuning::block>;
  __shared__ union {
    typename reduce_f::TempStorage f;
    typename reduce_d::TempStorage d;
  } temp;
  float lo[3] = {FLT_MAX, FLT_MAX, FLT_MAX}, hi[3] = {-FLT_MAX, -FLT_MAX, -FLT_MAX};
  double sum[3] = {0, 0, 0};
  std::uint32_t cat_or = 0, cat_and = ~0u, mask_or = 0, mask_and = ~0u;
  for (std::uint32_t i = blockIdx.x * blockDim.x + threadIdx.x; i < n; i += gridDim.x * blockDim.x) {
    for (int d = 0; d < 3; ++d) {
      const float l = boxes.lo[d][i], h = boxes.hi[d][i];
      lo[d] = fminf(lo[d], l);
      hi[d] = fmaxf(hi[d], h);
      sum[d] += static_cast<double>(h) - static_cast<double>(l);
    }
    const std::uint32_t c = boxes.category[i], m = boxes.mask[i];
    cat_or |= c;
    cat_and &= c;
    mask_or |= m;
    mask_and &= m;
  }
  // Filter bits: warp reductions, one atomic per warp.
  cat_or = __reduce_or_sync(0xFFFFFFFFu, cat_or);
  cat_and = __reduce_and_sync(0xFFFFFFFFu, cat_and);
  mask_or = __reduce_or_sync(0xFFFFFFFFu, mask_or);
  mask_and = __reduce_and_sync(0xFFFFFFFFu, mask_and);
  if ((threadIdx.x & 31u) == 0) {
    atomicOr(&sc->category_or, cat_or);
    atomicAnd(&sc->category_and, cat_and);
    atomicOr(&sc->mask_or, mask_or);
    atomicAnd(&sc->mask_and, mask_and);
  }
  for (int d = 0; d < 3; ++d) {
    const float mn = reduce_f(temp.f).Reduce(lo[d], [](float a, float b) { return fminf(a, b); });
    __syncthreads();
    const float mx = reduce_f(temp.f).Reduce(hi[d], [](float a, float b) { return fmaxf(a, b); });
    __syncthreads();
    const double s = reduce_d(temp.d).Sum(sum[d]);
    __syncthreads();
    if (threadIdx.x == 0) {
      atomicMin(&sc->lo[d], to_ordered(mn));
      atomicMax(&sc->hi[d], to_ordered(mx));
      atomicAdd(&sc->edge_sum[d], s);
    }
  }
}

/// Spreads the low 10 bits of v to every third bit (Karras's expandBits).
__device__ __forceinline__ std::uint32_t expand_bits(std::uint32_t v) {
  v = (v * 0x00010001u) & 0xFF0000FFu;
  v = (v * 0x00000101u) & 0x0F00F00Fu;
  v = (v * 0x00000011u) & 0xC30C30C3u;
  v = (v * 0x00000005u) & 0x49249249u;
  return v;
}

/// Key of each box: the 30-bit Morton code of its centroid relative to the scene bounds, with bit
/// 30 set for a box of mask 0 (a pure target, e.g. an MMO presence box: it pairs only with boxes
/// whose mask holds its category, so targets form their own subtree, which the filter bits of
/// the nodes let every other target skip whole); or large_key for a box whose estimated overlap
/// count (uniform density: N times the product over axes of min(1, (edge + mean edge) / scene
/// extent)) exceeds large_threshold.
inline constexpr std::uint32_t target_bit = 1u << 30;
inline constexpr std::uint32_t large_key = 1u << 31;
__global__ void morton_kernel(box_arrays boxes, std::uint32_t n, scene* sc, double large_threshold,
                              std::uint32_t* keys, std::uint32_t* ids) {
  const std::uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= n) return;
  std::uint32_t q[3];
  double est = static_cast<double>(n);
  for (int d = 0; d < 3; ++d) {
    const float slo = from_ordered(sc->lo[d]), shi = from_ordered(sc->hi[d]);
    const float l = boxes.lo[d][i], h = boxes.hi[d][i];
    const double extent = static_cast<double>(shi) - static_cast<double>(slo);
    const double centre = 0.5 * (static_cast<double>(l) + static_cast<double>(h));
    double t = extent > 0 ? (centre - slo) / extent : 0.5;
    t = fmin(fmax(t * 1024.0, 0.0), 1023.0);
    q[d] = static_cast<std::uint32_t>(t);
    if (extent > 0) {
      const double mean = sc->edge_sum[d] / n;
      est *= fmin(1.0, (static_cast<double>(h) - l + mean) / extent);
    }
  }
  std::uint32_t key = expand_bits(q[0]) * 4 + expand_bits(q[1]) * 2 + expand_bits(q[2]);
  if (boxes.mask[i] == 0) key |= target_bit;
  if (est > large_threshold) {
    key = large_key;
    atomicAdd(&sc->large_count, 1u);
  }
  keys[i] = key;
  ids[i] = i;
}

// ---- hierarchy --------------------------------------------------------------------------------

/// The sorted boxes as the traversal reads them: lo.xyz + category bits, hi.xyz + mask bits.
__global__ void gather_kernel(box_arrays boxes, std::uint32_t n, const std::uint32_t* ids, float4* leaf_lo,
                              float4* leaf_hi) {
  const std::uint32_t p = blockIdx.x * blockDim.x + threadIdx.x;
  if (p >= n) return;
  const std::uint32_t i = ids[p];
  leaf_lo[p] = make_float4(boxes.lo[0][i], boxes.lo[1][i], boxes.lo[2][i], __uint_as_float(boxes.category[i]));
  leaf_hi[p] = make_float4(boxes.hi[0][i], boxes.hi[1][i], boxes.hi[2][i], __uint_as_float(boxes.mask[i]));
}

/// Karras's delta: length of the common prefix of the keys at sorted positions a and b, with the
/// position appended to the key so equal Morton codes still differ (-1 outside [0, leaves)).
__device__ __forceinline__ int delta(const std::uint32_t* keys, std::uint32_t leaves, int a, int b) {
  if (b < 0 || b >= static_cast<int>(leaves)) return -1;
  const std::uint32_t ka = keys[a], kb = keys[b];
  if (ka != kb) return __clz(ka ^ kb);
  return 32 + __clz(static_cast<std::uint32_t>(a) ^ static_cast<std::uint32_t>(b));
}

/// One thread per internal node i (0 = root): determineRange, findSplit, children, parents.
/// parent[k] = (parent node << 1) | slot, for internal nodes k < leaves - 1 and leaves at
/// leaves - 1 + leaf. Also clears the node's refit flag.
__global__ void build_kernel(const std::uint32_t* keys, std::uint32_t n, const scene* sc, node* nodes,
                             std::uint32_t* parent, std::uint32_t* flags) {
  const std::uint32_t leaves = tree_leaves(sc, n);
  const int i = static_cast<int>(blockIdx.x * blockDim.x + threadIdx.x);
  if (leaves < 2 || i >= static_cast<int>(leaves) - 1) return;
  // determineRange: the direction, then an exponential and a binary search for the other end.
  const int d = delta(keys, leaves, i, i + 1) - delta(keys, leaves, i, i - 1) > 0 ? 1 : -1;
  const int delta_min = delta(keys, leaves, i, i - d);
  long long lmax = 2;
  while (delta(keys, leaves, i, static_cast<int>(i + lmax * d)) > delta_min) lmax *= 2;
  long long l = 0;
  for (long long t = lmax / 2; t >= 1; t /= 2) {
    if (delta(keys, leaves, i, static_cast<int>(i + (l + t) * d)) > delta_min) l += t;
  }
  const int j = static_cast<int>(i + l * d);
  // findSplit: the highest position that shares more than delta_node bits with i.
  const int delta_node = delta(keys, leaves, i, j);
  long long s = 0;
  long long div = 2;
  long long t;
  do {
    t = (l + div - 1) / div;
    if (delta(keys, leaves, i, static_cast<int>(i + (s + t) * d)) > delta_node) s += t;
    div *= 2;
  } while (t > 1);
  const int gamma = static_cast<int>(i + s * d + (d < 0 ? d : 0));
  const int first = min(i, j), last = max(i, j);
  const bool left_leaf = first == gamma, right_leaf = last == gamma + 1;
  node& nd = nodes[i];
  nd.lo[0].w = __int_as_float(gamma);
  nd.hi[0].w = __int_as_float(left_leaf ? ~gamma : gamma);
  nd.lo[1].w = __int_as_float(last);
  nd.hi[1].w = __int_as_float(right_leaf ? ~(gamma + 1) : gamma + 1);
  const std::uint32_t internal = leaves - 1;
  parent[left_leaf ? internal + gamma : gamma] = static_cast<std::uint32_t>(i) << 1;
  parent[right_leaf ? internal + gamma + 1 : gamma + 1] = (static_cast<std::uint32_t>(i) << 1) | 1u;
  flags[i] = 0;
}

/// Writes a child's box (the w fields are the build's) and filter bits into its slot of the parent.
__device__ __forceinline__ void store_child(node* nodes, uint4* bits, std::uint32_t link, float4 lo, float4 hi,
                                            std::uint32_t category, std::uint32_t mask) {
  node& p = nodes[link >> 1];
  const std::uint32_t c = link & 1u;
  p.lo[c].x = lo.x;
  p.lo[c].y = lo.y;
  p.lo[c].z = lo.z;
  p.hi[c].x = hi.x;
  p.hi[c].y = hi.y;
  p.hi[c].z = hi.z;
  std::uint32_t* b = reinterpret_cast<std::uint32_t*>(&bits[link >> 1]) + 2 * c;
  b[0] = category;
  b[1] = mask;
}

/// Bottom-up boxes: one thread per leaf walks towards the root; at each node the first thread to
/// arrive stops (atomic flag), the second unites both children's boxes and goes on.
__global__ void refit_kernel(const float4* leaf_lo, const float4* leaf_hi, std::uint32_t n, const scene* sc,
                             const std::uint32_t* parent, node* nodes, uint4* bits, std::uint32_t* flags) {
  const std::uint32_t leaves = tree_leaves(sc, n);
  const std::uint32_t leaf = blockIdx.x * blockDim.x + threadIdx.x;
  if (leaves < 2 || leaf >= leaves) return;
  float4 lo = leaf_lo[leaf], hi = leaf_hi[leaf];
  std::uint32_t category = __float_as_uint(lo.w), mask = __float_as_uint(hi.w);
  std::uint32_t link = parent[leaves - 1 + leaf];
  while (true) {
    store_child(nodes, bits, link, lo, hi, category, mask);
    __threadfence();
    const std::uint32_t p = link >> 1;
    if (atomicAdd(&flags[p], 1u) == 0) return;  // the sibling is not done yet: it goes on
    __threadfence();
    if (p == 0) return;  // the root's own box is never read
    // Both children's boxes are in node p (written before the sibling's fence and atomic).
    const volatile node& v = nodes[p];
    lo = make_float4(fminf(v.lo[0].x, v.lo[1].x), fminf(v.lo[0].y, v.lo[1].y), fminf(v.lo[0].z, v.lo[1].z), 0.f);
    hi = make_float4(fmaxf(v.hi[0].x, v.hi[1].x), fmaxf(v.hi[0].y, v.hi[1].y), fmaxf(v.hi[0].z, v.hi[1].z), 0.f);
    const volatile uint4& vb = bits[p];
    category = vb.x | vb.z;
    mask = vb.y | vb.w;
    link = parent[p];
  }
}

/// Depth of each leaf (root = 0), reduced to the maximum (tests and reports only).
__global__ void depth_kernel(std::uint32_t n, const std::uint32_t* parent, scene* sc) {
  const std::uint32_t leaves = tree_leaves(sc, n);
  const std::uint32_t leaf = blockIdx.x * blockDim.x + threadIdx.x;
  if (leaves < 2 || leaf >= leaves) return;
  std::uint32_t depth = 1;
  std::uint32_t p = parent[leaves - 1 + leaf] >> 1;
  while (p != 0) {
    p = parent[p] >> 1;
    ++depth;
  }
  atomicMax(&sc->max_depth, depth);
}

// ---- traversal --------------------------------------------------------------------------------

__device__ __forceinline__ bool overlap(float4 alo, float4 ahi, float4 blo, float4 bhi) {
  return alo.x <= bhi.x && blo.x <= ahi.x && alo.y <= bhi.y && blo.y <= ahi.y && alo.z <= bhi.z && blo.z <= ahi.z;
}
__device__ __forceinline__ bool compatible(float4 alo, float4 ahi, float4 blo, float4 bhi) {
  return ((__float_as_uint(alo.w) & __float_as_uint(bhi.w)) | (__float_as_uint(blo.w) & __float_as_uint(ahi.w))) != 0;
}

/// Independent traversal for the leaf at sorted position q: every leaf j > q whose box overlaps
/// q's and passes the category/mask rule, in a fixed order (children left before right, the
/// right pushed). Subtrees whose rightmost leaf is not after q are skipped. Calls emit(j) for
/// each; returns false when the stack (stack_cap entries) would overflow.
template <class Emit>
__device__ __forceinline__ bool traverse_leaf(const traverse_args& a, std::uint32_t q, Emit&& emit) {
  const float4 qlo = a.leaf_lo[q], qhi = a.leaf_hi[q];
  const std::uint32_t qcat = __float_as_uint(qlo.w), qmask = __float_as_uint(qhi.w);
  // With more than one (category, mask) signature, subtrees whose OR-ed bits cannot pass the
  // filter with the query are skipped whole (the same for every thread: no divergence).
  const bool filter = a.sc->category_or != a.sc->category_and || a.sc->mask_or != a.sc->mask_and;
  std::int32_t stack[lbvh_tuning::max_stack];
  std::uint32_t sp = 0;
  std::int32_t current = 0;  // the root
  const std::int32_t query = static_cast<std::int32_t>(q);
  while (true) {
    const node* nd = a.nodes + current;
    std::int32_t next[2];
    bool go[2];
    bool pass[2] = {true, true};
    if (filter) {
      const uint4 b = __ldg(&a.node_bits[current]);
      pass[0] = ((qcat & b.y) | (b.x & qmask)) != 0;
      pass[1] = ((qcat & b.w) | (b.z & qmask)) != 0;
    }
#pragma unroll
    for (int c = 0; c < 2; ++c) {
      const float4 lo = __ldg(&nd->lo[c]), hi = __ldg(&nd->hi[c]);
      const std::int32_t rightmost = __float_as_int(lo.w);
      const std::int32_t ref = __float_as_int(hi.w);
      const bool hit = pass[c] && rightmost > query && overlap(qlo, qhi, lo, hi);
      next[c] = ref;
      go[c] = false;
      if (hit) {
        if (ref < 0) {
          const std::uint32_t j = static_cast<std::uint32_t>(~ref);
          if (compatible(qlo, qhi, __ldg(&a.leaf_lo[j]), __ldg(&a.leaf_hi[j]))) emit(j);
        } else {
          go[c] = true;
        }
      }
    }
    if (go[0] && go[1]) {
      if (sp >= a.stack_cap) return false;
      stack[sp++] = next[1];
      current = next[0];
    } else if (go[0]) {
      current = next[0];
    } else if (go[1]) {
      current = next[1];
    } else {
      if (sp == 0) return true;
      current = stack[--sp];
    }
  }
}

/// Counting pass over leaves [0, n]: pairs per leaf (0 past the tree and for overflowed queries)
/// and the overflow flags.
__global__ void count_kernel(traverse_args a) {
  const std::uint32_t q = blockIdx.x * blockDim.x + threadIdx.x;
  if (q > a.n) return;
  const std::uint32_t leaves = tree_leaves(a.sc, a.n);
  if (q >= leaves || leaves < 2) {
    a.counts[q] = 0;
    if (q < a.n) a.overflowed[q] = 0;
    return;
  }
  std::uint32_t count = 0;
  const bool ok = traverse_leaf(a, q, [&](std::uint32_t) { ++count; });
  a.counts[q] = ok ? count : 0;
  a.overflowed[q] = ok ? 0 : 1;
}

/// Writing pass over leaves [first, last): the same traversal writes {min id, max id} at the
/// leaf's scanned position.
__global__ void fill_kernel(traverse_args a) {
  const std::uint32_t q = a.first + blockIdx.x * blockDim.x + threadIdx.x;
  if (q >= a.last) return;
  if (a.counts[q] == 0) return;  // nothing, or an overflowed query (the brute pass redoes it)
  std::uint64_t at = a.pos[q];
  const std::uint32_t qid = a.ids[q];
  (void)traverse_leaf(a, q, [&](std::uint32_t j) {
    const std::uint32_t jid = a.ids[j];
    a.out[2 * at] = min(qid, jid);
    a.out[2 * at + 1] = max(qid, jid);
    ++at;
  });
}

/// rb->batch_pos[k] = pos[leaves * k / batches]; the counters.
__global__ void readback_kernel(const std::uint64_t* pos, std::uint32_t n, std::uint32_t batches, const scene* sc,
                                readback* rb) {
  const std::uint32_t k = threadIdx.x;
  if (k > batches) return;
  const std::uint64_t leaves = tree_leaves(sc, n);
  rb->batch_pos[k] = pos[leaves * k / batches];
  if (k == 0) {
    rb->large_count = sc->large_count;
    rb->max_depth = sc->max_depth;
  }
}

// ---- brute pass: large boxes and overflowed queries ---------------------------------------------

/// Query r of the brute pass: its sorted position and the range of sorted positions it tests,
/// [from, to) minus the band [skip_first, skip_last] (large boxes skip the large boxes before them).
struct brute_query {
  std::uint32_t pos, from, to, skip_first, skip_last;
};
__device__ __forceinline__ brute_query query_of(const brute_args& a, std::uint32_t r) {
  const std::uint32_t leaves = tree_leaves(a.sc, a.n);
  if (r < a.ov_count) {
    const std::uint32_t q = a.ov_list[r];
    return {q, q + 1, leaves, 1u, 0u};  // every later tree leaf
  }
  const std::uint32_t p = leaves + (r - a.ov_count);
  return {p, 0u, a.n, leaves, p};  // every tree leaf and every later large box
}

/// Tests of one thread in one item: boxes chunk_base + k * block + thread, k < per_thread.
template <class Hit>
__device__ __forceinline__ void brute_item(const brute_args& a, std::uint32_t item, Hit&& hit) {
  const std::uint32_t r = item / a.chunks;
  const brute_query bq = query_of(a, r);
  const float4 qlo = a.leaf_lo[bq.pos], qhi = a.leaf_hi[bq.pos];
  const std::uint32_t base = (item % a.chunks) * lbvh_tuning::brute_chunk;
#pragma unroll
  for (std::uint32_t k = 0; k < lbvh_tuning::brute_per_thread; ++k) {
    const std::uint32_t j = base + k * lbvh_tuning::block + threadIdx.x;
    if (j < bq.from || j >= bq.to || (j >= bq.skip_first && j <= bq.skip_last)) continue;
    const float4 lo = a.leaf_lo[j], hi = a.leaf_hi[j];
    if (overlap(qlo, qhi, lo, hi) && compatible(qlo, qhi, lo, hi)) hit(bq.pos, j);
  }
}

__global__ void brute_count_kernel(brute_args a) {
  using reduce = cub::BlockReduce<std::uint32_t, lbvh_tuning::block>;
  __shared__ typename reduce::TempStorage temp;
  const std::uint64_t items = static_cast<std::uint64_t>(a.queries) * a.chunks;
  const std::uint64_t item = blockIdx.x;
  if (item >= items) return;
  std::uint32_t count = 0;
  brute_item(a, static_cast<std::uint32_t>(item), [&](std::uint32_t, std::uint32_t) { ++count; });
  const std::uint32_t sum = reduce(temp).Sum(count);
  if (threadIdx.x == 0) a.item_counts[item] = sum;
}

__global__ void brute_fill_kernel(brute_args a) {
  using scan = cub::BlockScan<std::uint32_t, lbvh_tuning::block>;
  __shared__ typename scan::TempStorage temp;
  const std::uint64_t items = static_cast<std::uint64_t>(a.queries) * a.chunks;
  const std::uint64_t item = blockIdx.x;
  if (item >= items) return;
  std::uint32_t count = 0;
  brute_item(a, static_cast<std::uint32_t>(item), [&](std::uint32_t, std::uint32_t) { ++count; });
  std::uint32_t offset;
  scan(temp).ExclusiveSum(count, offset);
  std::uint64_t at = a.base + a.item_pos[item] + offset;
  brute_item(a, static_cast<std::uint32_t>(item), [&](std::uint32_t q, std::uint32_t j) {
    const std::uint32_t qid = a.ids[q], jid = a.ids[j];
    a.out[2 * at] = min(qid, jid);
    a.out[2 * at + 1] = max(qid, jid);
    ++at;
  });
}

}  // namespace zone::gpu::detail::lbvh
