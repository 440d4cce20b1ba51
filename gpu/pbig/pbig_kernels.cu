// The PBIG kernels' launchers and the CUB steps (declared in pbig_launch.h).
#include <cub/device/device_reduce.cuh>
#include <cub/device/device_scan.cuh>
#include <cub/device/device_segmented_sort.cuh>
#include <cub/device/device_select.cuh>
#include <thrust/iterator/counting_iterator.h>
#include <thrust/iterator/transform_iterator.h>

#include <algorithm>

#include "pbig_kernels.cuh"
#include "pbig_launch.h"

namespace zone::gpu::detail {
namespace {

std::uint32_t blocks_for(std::uint64_t n, std::uint32_t block) {
  return static_cast<std::uint32_t>(std::max<std::uint64_t>(1, (n + block - 1) / block));
}

/// Per-cell values scanned into cell_prefix: entries, work items (segments), tiles.
struct to_prefix {
  __host__ __device__ cell_prefix operator()(std::uint32_t count) const {
    const std::uint32_t segs = (count + tuning::segment - 1) / tuning::segment;
    return {count, segs, segs * (segs + 1) / 2};
  }
};
struct add_prefix {
  __host__ __device__ cell_prefix operator()(const cell_prefix& a, const cell_prefix& b) const {
    return {a.entry + b.entry, a.item + b.item, a.tile + b.tile};
  }
};
struct to_totals {
  __host__ __device__ cell_totals operator()(std::uint32_t count) const {
    const std::uint64_t c = count;
    const std::uint64_t segs = (c + tuning::segment - 1) / tuning::segment;
    return {c, segs * (segs + 1) / 2, c * (c - (c > 0 ? 1 : 0)) / 2, c};
  }
};
struct add_totals {
  __host__ __device__ cell_totals operator()(const cell_totals& a, const cell_totals& b) const {
    return {a.entries + b.entries, a.tiles + b.tiles, a.checks + b.checks,
            a.max_count > b.max_count ? a.max_count : b.max_count};
  }
};
/// The overlapped upload's stage j: chunk j's count q in a cell and the earlier chunks' boxes p
/// there (from their prefixes), as the stage's per-cell values (check_stage_kernel's layout at
/// width W, stage_layout in pbig_shared.h): entries q (chunk j's own list), work items ceil(q / W)
/// row segments of chunk j's list, their tiles; nothing when q == 0.
struct stage_cell {
  const std::uint32_t* counts;
  stage_lists earlier;  // chunks 0..j-1 (count = j)
  std::uint32_t cells;
  std::uint32_t width;  // W
  __host__ __device__ void sizes(std::uint32_t c, std::uint32_t& q, std::uint32_t& p) const {
    q = c < cells ? counts[c] : 0;
    p = 0;
    if (q == 0) return;
    for (std::uint32_t i = 0; i < earlier.count; ++i) p += earlier.prefix[i][c + 1].entry - earlier.prefix[i][c].entry;
  }
};
struct to_stage_prefix {
  stage_cell cell;
  __host__ __device__ cell_prefix operator()(std::uint32_t c) const {
    std::uint32_t q, p;
    cell.sizes(c, q, p);
    const stage_cell_layout l = stage_layout(q, p, cell.width);
    return {q, l.items, static_cast<std::uint32_t>(l.tiles())};  // 32-bit wrap caught by the totals' check
  }
};
/// The stage's totals: entries q, tiles as above, checks q p + q (q - 1) / 2 (chunk j's boxes
/// against the earlier ones and each other), and as max_count the cell's boxes of chunks 0..j
/// (what the segment indices must fit; the per-cell sort of chunk j's lists, never longer, takes
/// the one-kernel path when it is at most small_cell_sort).
struct to_stage_totals {
  stage_cell cell;
  __host__ __device__ cell_totals operator()(std::uint32_t c) const {
    std::uint32_t q32, p32;
    cell.sizes(c, q32, p32);
    if (q32 == 0) return {0, 0, 0, 0};
    const std::uint64_t q = q32, p = p32;
    return {q, stage_layout(q32, p32, cell.width).tiles(), q * p + q * (q - 1) / 2, p + q};
  }
};
struct entry_at {
  const cell_prefix* prefix;
  __host__ __device__ std::uint32_t operator()(std::uint32_t c) const { return prefix[c].entry; }
};

}  // namespace

cudaError_t launch_plan(const box_arrays& boxes, bounds_dev* bounds, const plan_params& prm, plan_state* state,
                        grid_plan_dev* plan, cudaStream_t stream) {
  init_bounds_kernel<<<1, 32, 0, stream>>>(bounds);
  bounds_kernel<<<std::min<std::uint32_t>(blocks_for(prm.sample_n, tuning::block), 1024), tuning::block, 0, stream>>>(
      boxes, prm.sample_n, bounds, prm.validate != 0);
  plan_kernel<<<1, tuning::plan_threads, 0, stream>>>(boxes, bounds, prm, state, plan);
  if (prm.cost_aware != 0 && prm.fixed_edge <= 0) {
    static_assert(tuning::plan_candidates <= max_plan_candidates);
    plan_cost_kernel<<<tuning::plan_candidates * tuning::plan_cost_chunks, tuning::plan_cost_threads, 0, stream>>>(
        boxes, bounds, prm, state, plan);
  }
  return cudaGetLastError();
}

cudaError_t launch_count(const box_arrays& boxes, std::uint32_t n, const grid_plan_dev* plan, std::uint64_t cell_capacity,
                         std::uint32_t* counts, std::uint8_t* is_large, std::uint32_t* large_count, cudaStream_t stream) {
  count_kernel<<<blocks_for(n, tuning::block), tuning::block, 0, stream>>>(boxes, n, plan, cell_capacity, counts, is_large,
                                                                           large_count);
  return cudaGetLastError();
}

cudaError_t select_large(void* temp, std::size_t& temp_bytes, const std::uint8_t* is_large, std::uint32_t* large,
                         std::uint32_t* large_count, std::uint32_t n, cudaStream_t stream) {
  const thrust::counting_iterator<std::uint32_t> ids(0);
  return cub::DeviceSelect::Flagged(temp, temp_bytes, ids, is_large, large, large_count, n, stream);
}

cudaError_t scan_cells(void* temp, std::size_t& temp_bytes, const std::uint32_t* counts, cell_prefix* prefix,
                       std::uint32_t cells, cudaStream_t stream) {
  const auto in = thrust::make_transform_iterator(counts, to_prefix{});
  return cub::DeviceScan::ExclusiveScan(temp, temp_bytes, in, prefix, add_prefix{}, cell_prefix{0, 0, 0},
                                        static_cast<std::int64_t>(cells) + 1, stream);
}

cudaError_t reduce_cells(void* temp, std::size_t& temp_bytes, const std::uint32_t* counts, cell_totals* totals,
                         std::uint32_t cells, cudaStream_t stream) {
  const auto in = thrust::make_transform_iterator(counts, to_totals{});
  return cub::DeviceReduce::Reduce(temp, temp_bytes, in, totals, static_cast<std::int64_t>(cells), add_totals{},
                                   cell_totals{0, 0, 0, 0}, stream);
}

cudaError_t scan_stage_cells(void* temp, std::size_t& temp_bytes, const std::uint32_t* counts,
                             const stage_lists& earlier, std::uint32_t width, cell_prefix* prefix, std::uint32_t cells,
                             cudaStream_t stream) {
  if (!is_stage_width(width)) return cudaErrorInvalidValue;
  const auto in = thrust::make_transform_iterator(thrust::counting_iterator<std::uint32_t>(0),
                                                  to_stage_prefix{stage_cell{counts, earlier, cells, width}});
  return cub::DeviceScan::ExclusiveScan(temp, temp_bytes, in, prefix, add_prefix{}, cell_prefix{0, 0, 0},
                                        static_cast<std::int64_t>(cells) + 1, stream);
}

cudaError_t reduce_stage_cells(void* temp, std::size_t& temp_bytes, const std::uint32_t* counts,
                               const stage_lists& earlier, std::uint32_t width, cell_totals* totals,
                               std::uint32_t cells, cudaStream_t stream) {
  if (!is_stage_width(width)) return cudaErrorInvalidValue;
  const auto in = thrust::make_transform_iterator(thrust::counting_iterator<std::uint32_t>(0),
                                                  to_stage_totals{stage_cell{counts, earlier, cells, width}});
  return cub::DeviceReduce::Reduce(temp, temp_bytes, in, totals, static_cast<std::int64_t>(cells), add_totals{},
                                   cell_totals{0, 0, 0, 0}, stream);
}

cudaError_t launch_validate(const box_arrays& boxes, std::uint32_t n, bounds_dev* result, cudaStream_t stream) {
  init_bounds_kernel<<<1, 32, 0, stream>>>(result);
  bounds_kernel<<<std::min<std::uint32_t>(blocks_for(n, tuning::block), 1024), tuning::block, 0, stream>>>(
      boxes, n, result, true);
  return cudaGetLastError();
}

cudaError_t launch_batch_plan(const grid_plan_dev* plan, const cell_prefix* prefix, const std::uint32_t* large_count,
                              map_readback* rb, const grid_capacity& cap, std::uint32_t min_tiles,
                              std::uint32_t max_batches, cudaStream_t stream) {
  batch_plan_kernel<<<1, 32, 0, stream>>>(plan, prefix, large_count, rb, cap, min_tiles, max_batches);
  return cudaGetLastError();
}

namespace {
__global__ void to_host_kernel(const std::uint32_t* a, std::uint32_t* host_a, std::uint32_t a_words,
                               const std::uint32_t* b, std::uint32_t* host_b, std::uint32_t b_words) {
  for (std::uint32_t i = threadIdx.x; i < a_words; i += blockDim.x) host_a[i] = a[i];
  for (std::uint32_t i = threadIdx.x; i < b_words; i += blockDim.x) host_b[i] = b[i];
  __threadfence_system();
}
}  // namespace

cudaError_t launch_to_host(const void* a, void* host_a, std::size_t a_bytes, const void* b, void* host_b,
                           std::size_t b_bytes, cudaStream_t stream) {
  const auto aligned = [](const void* p, std::size_t bytes) {
    return reinterpret_cast<std::uintptr_t>(p) % 4 == 0 && bytes % 4 == 0;
  };
  if (!aligned(a, a_bytes) || !aligned(host_a, a_bytes) ||
      (b_bytes > 0 && (!aligned(b, b_bytes) || !aligned(host_b, b_bytes)))) {
    return cudaErrorInvalidValue;
  }
  to_host_kernel<<<1, 32, 0, stream>>>(static_cast<const std::uint32_t*>(a), static_cast<std::uint32_t*>(host_a),
                                       static_cast<std::uint32_t>(a_bytes / 4), static_cast<const std::uint32_t*>(b),
                                       static_cast<std::uint32_t*>(host_b), static_cast<std::uint32_t>(b_bytes / 4));
  return cudaGetLastError();
}

cudaError_t launch_map(const box_arrays& boxes, std::uint32_t n, std::uint32_t first_id, const grid_plan_dev* plan,
                       const map_readback* grid, const std::uint8_t* is_large, const cell_prefix* prefix,
                       std::uint32_t* cursor, std::uint32_t* entries, cudaStream_t stream) {
  map_kernel<<<blocks_for(n, tuning::block), tuning::block, 0, stream>>>(boxes, n, first_id, plan, grid, is_large,
                                                                         prefix, cursor, entries);
  return cudaGetLastError();
}

cudaError_t sort_cells(void* temp, std::size_t& temp_bytes, const std::uint32_t* in, std::uint32_t* out,
                       std::uint32_t entries, std::uint32_t cells, const cell_prefix* prefix, cudaStream_t stream) {
  const auto begin = thrust::make_transform_iterator(thrust::counting_iterator<std::uint32_t>(0), entry_at{prefix});
  const auto end = thrust::make_transform_iterator(thrust::counting_iterator<std::uint32_t>(1), entry_at{prefix});
  return cub::DeviceSegmentedSort::SortKeys(temp, temp_bytes, in, out, static_cast<std::int64_t>(entries),
                                            static_cast<std::int64_t>(cells), begin, end, stream);
}

cudaError_t launch_sort_small_cells(const std::uint32_t* in, std::uint32_t* out, const cell_prefix* prefix,
                                    std::uint32_t cells, const map_readback* grid, cudaStream_t stream) {
  sort_small_cells_kernel<<<blocks_for(std::uint64_t{cells} * 32, tuning::block), tuning::block, 0, stream>>>(
      in, out, prefix, cells, grid);
  return cudaGetLastError();
}

cudaError_t launch_pack_boxes(const box_arrays& boxes, std::uint32_t n, float4* box_lo, float4* box_hi,
                              cudaStream_t stream) {
  pack_boxes_kernel<<<blocks_for(n, tuning::block), tuning::block, 0, stream>>>(boxes, n, box_lo, box_hi);
  return cudaGetLastError();
}

namespace {
/// Fills n 32-bit words with `value` (the category or mask array of a set whose boxes all share it).
__global__ void fill_u32_kernel(std::uint32_t* out, std::uint32_t n, std::uint32_t value) {
  const std::uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i < n) out[i] = value;
}
}  // namespace

cudaError_t launch_fill_u32(std::uint32_t* out, std::uint32_t n, std::uint32_t value, cudaStream_t stream) {
  fill_u32_kernel<<<blocks_for(n, tuning::block), tuning::block, 0, stream>>>(out, n, value);
  return cudaGetLastError();
}

cudaError_t launch_gather(const float4* box_lo, const float4* box_hi, const std::uint32_t* entries, std::uint32_t count,
                          const map_readback* grid, float4* packed_lo, float4* packed_hi, cudaStream_t stream) {
  gather_kernel<<<blocks_for(count, tuning::block), tuning::block, 0, stream>>>(box_lo, box_hi, entries, count, grid,
                                                                                packed_lo, packed_hi);
  return cudaGetLastError();
}

cudaError_t launch_expand(const cell_prefix* prefix, std::uint32_t cells, const map_readback* grid, std::uint32_t* items,
                          cudaStream_t stream) {
  expand_items_kernel<<<blocks_for(cells, tuning::block), tuning::block, 0, stream>>>(prefix, cells, grid, items);
  return cudaGetLastError();
}

cudaError_t launch_place_chunks(const unsigned char* chunks, const unsigned long long* cursor, std::uint64_t capacity,
                                const std::uint64_t* tile_off, const std::uint32_t* tile_pairs,
                                const std::uint64_t* tile_pos, std::uint32_t tiles, std::uint32_t* out_pairs,
                                cudaStream_t stream) {
  if (tiles == 0) return cudaSuccess;
  place_chunks_kernel<<<blocks_for(std::uint64_t{tiles} * 32, tuning::block), tuning::block, 0, stream>>>(
      chunks, cursor, capacity, tile_off, tile_pairs, tile_pos, tiles, out_pairs);
  return cudaGetLastError();
}

namespace {
struct widen {
  __host__ __device__ std::uint64_t operator()(std::uint32_t x) const { return x; }
};
}  // namespace

cudaError_t scan_tiles(void* temp, std::size_t& temp_bytes, const std::uint32_t* tile_pairs, std::uint64_t* tile_pos,
                       std::uint64_t count, cudaStream_t stream) {
  const auto in = thrust::make_transform_iterator(tile_pairs, widen{});
  return cub::DeviceScan::ExclusiveSum(temp, temp_bytes, in, tile_pos, static_cast<std::int64_t>(count), stream);
}

cudaError_t launch_check(const check_args& a, bool balanced, bool compressed, cudaStream_t stream) {
  const std::uint32_t grid = a.item_last - a.item_first;
  if (grid == 0) return cudaSuccess;
  if (balanced) {
    if (compressed) {
      check_kernel<true, true><<<grid, tuning::segment, 0, stream>>>(a);
    } else {
      check_kernel<true, false><<<grid, tuning::segment, 0, stream>>>(a);
    }
  } else {
    if (compressed) {
      check_kernel<false, true><<<grid, tuning::segment, 0, stream>>>(a);
    } else {
      check_kernel<false, false><<<grid, tuning::segment, 0, stream>>>(a);
    }
  }
  return cudaGetLastError();
}

namespace {
template <std::uint32_t W>
void launch_check_stage_w(const check_args& a, const stage_lists& lists, bool balanced, std::uint32_t items,
                          cudaStream_t stream) {
  constexpr std::uint32_t slots = tuning::segment / (W < 32 ? W : 32);  // work items a block
  const std::uint32_t grid = (items + slots - 1) / slots;
  if (balanced) {
    check_stage_kernel<W, true><<<grid, tuning::segment, 0, stream>>>(a, lists);
  } else {
    check_stage_kernel<W, false><<<grid, tuning::segment, 0, stream>>>(a, lists);
  }
}
}  // namespace

cudaError_t launch_check_stage(const check_args& a, const stage_lists& lists, bool balanced, std::uint32_t width,
                               cudaStream_t stream) {
  const std::uint32_t items = a.item_last - a.item_first;
  if (items == 0) return cudaSuccess;
  switch (width) {
    case 8: launch_check_stage_w<8>(a, lists, balanced, items, stream); break;
    case 16: launch_check_stage_w<16>(a, lists, balanced, items, stream); break;
    case 32: launch_check_stage_w<32>(a, lists, balanced, items, stream); break;
    case 64: launch_check_stage_w<64>(a, lists, balanced, items, stream); break;
    default: return cudaErrorInvalidValue;
  }
  return cudaGetLastError();
}

cudaError_t launch_large_count(const box_arrays& boxes, std::uint32_t n, const std::uint32_t* large,
                               std::uint32_t large_count, const std::uint8_t* is_large, std::uint32_t chunks,
                               std::uint32_t* counts, cudaStream_t stream) {
  const std::uint64_t blocks = static_cast<std::uint64_t>(chunks) * large_count;
  large_count_kernel<<<static_cast<std::uint32_t>(blocks), tuning::block, 0, stream>>>(boxes, n, large, large_count,
                                                                                        is_large, chunks, counts);
  return cudaGetLastError();
}

cudaError_t scan_u32(void* temp, std::size_t& temp_bytes, const std::uint32_t* in, std::uint32_t* out,
                     std::uint64_t n, cudaStream_t stream) {
  return cub::DeviceScan::ExclusiveSum(temp, temp_bytes, in, out, static_cast<std::int64_t>(n), stream);
}

cudaError_t launch_large_write(const box_arrays& boxes, std::uint32_t n, const std::uint32_t* large,
                               std::uint32_t large_count, const std::uint8_t* is_large, std::uint32_t chunks,
                               const std::uint32_t* offsets, std::uint32_t* pairs, cudaStream_t stream) {
  const std::uint64_t blocks = static_cast<std::uint64_t>(chunks) * large_count;
  large_write_kernel<<<static_cast<std::uint32_t>(blocks), tuning::block, 0, stream>>>(
      boxes, n, large, large_count, is_large, chunks, offsets, pairs);
  return cudaGetLastError();
}

}  // namespace zone::gpu::detail
