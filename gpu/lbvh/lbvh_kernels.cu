// The LBVH kernels' launchers and the CUB steps (declared in lbvh_launch.h).
#include <cub/device/device_radix_sort.cuh>
#include <cub/device/device_scan.cuh>
#include <cub/device/device_select.cuh>
#include <thrust/iterator/counting_iterator.h>
#include <thrust/iterator/transform_iterator.h>

#include <algorithm>

#include "lbvh_kernels.cuh"
#include "lbvh_launch.h"

namespace zone::gpu::detail::lbvh {
namespace {

std::uint32_t blocks_for(std::uint64_t n, std::uint32_t block) {
  return static_cast<std::uint32_t>(std::max<std::uint64_t>(1, (n + block - 1) / block));
}

struct widen {
  __host__ __device__ std::uint64_t operator()(std::uint32_t v) const { return v; }
};

}  // namespace

cudaError_t launch_scene(const box_arrays& boxes, std::uint32_t n, scene* sc, cudaStream_t stream) {
  init_scene_kernel<<<1, 32, 0, stream>>>(sc);
  scene_kernel<<<std::min<std::uint32_t>(blocks_for(n, lbvh_tuning::block), 1024), lbvh_tuning::block, 0, stream>>>(
      boxes, n, sc);
  return cudaGetLastError();
}

cudaError_t launch_morton(const box_arrays& boxes, std::uint32_t n, scene* sc, double large_threshold,
                          std::uint32_t* keys, std::uint32_t* ids, cudaStream_t stream) {
  morton_kernel<<<blocks_for(n, lbvh_tuning::block), lbvh_tuning::block, 0, stream>>>(boxes, n, sc, large_threshold,
                                                                                       keys, ids);
  return cudaGetLastError();
}

cudaError_t sort_keys(void* temp, std::size_t& temp_bytes, const std::uint32_t* keys_in, std::uint32_t* keys_out,
                      const std::uint32_t* ids_in, std::uint32_t* ids_out, std::uint32_t n, cudaStream_t stream) {
  return cub::DeviceRadixSort::SortPairs(temp, temp_bytes, keys_in, keys_out, ids_in, ids_out, n, 0, 32, stream);
}

cudaError_t launch_build(const box_arrays& boxes, std::uint32_t n, const scene* sc, const std::uint32_t* keys,
                         const std::uint32_t* ids, float4* leaf_lo, float4* leaf_hi, node* nodes,
                         std::uint32_t* parent, std::uint32_t* flags, cudaStream_t stream) {
  gather_kernel<<<blocks_for(n, lbvh_tuning::block), lbvh_tuning::block, 0, stream>>>(boxes, n, ids, leaf_lo, leaf_hi);
  build_kernel<<<blocks_for(n, lbvh_tuning::block), lbvh_tuning::block, 0, stream>>>(keys, n, sc, nodes, parent,
                                                                                      flags);
  return cudaGetLastError();
}

cudaError_t launch_refit(const float4* leaf_lo, const float4* leaf_hi, std::uint32_t n, const scene* sc,
                         const std::uint32_t* parent, node* nodes, uint4* bits, std::uint32_t* flags,
                         bool measure_depth, scene* sc_out, cudaStream_t stream) {
  refit_kernel<<<blocks_for(n, lbvh_tuning::block), lbvh_tuning::block, 0, stream>>>(leaf_lo, leaf_hi, n, sc, parent,
                                                                                      nodes, bits, flags);
  if (measure_depth) {
    depth_kernel<<<blocks_for(n, lbvh_tuning::block), lbvh_tuning::block, 0, stream>>>(n, parent, sc_out);
  }
  return cudaGetLastError();
}

cudaError_t launch_traverse(const traverse_args& args, bool count_only, cudaStream_t stream) {
  if (count_only) {
    count_kernel<<<blocks_for(std::uint64_t{args.n} + 1, lbvh_tuning::block), lbvh_tuning::block, 0, stream>>>(args);
  } else if (args.last > args.first) {
    fill_kernel<<<blocks_for(args.last - args.first, lbvh_tuning::block), lbvh_tuning::block, 0, stream>>>(args);
  }
  return cudaGetLastError();
}

cudaError_t scan_counts(void* temp, std::size_t& temp_bytes, const std::uint32_t* counts, std::uint64_t* pos,
                        std::uint64_t count, cudaStream_t stream) {
  const auto in = thrust::make_transform_iterator(counts, widen{});
  return cub::DeviceScan::ExclusiveSum(temp, temp_bytes, in, pos, static_cast<std::int64_t>(count), stream);
}

cudaError_t select_overflowed(void* temp, std::size_t& temp_bytes, const std::uint8_t* flags, std::uint32_t* list,
                              std::uint32_t* count, std::uint32_t n, cudaStream_t stream) {
  const thrust::counting_iterator<std::uint32_t> ids(0);
  return cub::DeviceSelect::Flagged(temp, temp_bytes, ids, flags, list, count, n, stream);
}

cudaError_t launch_readback(const std::uint64_t* pos, std::uint32_t n, std::uint32_t batches, const scene* sc,
                            readback* rb, cudaStream_t stream) {
  readback_kernel<<<1, 32, 0, stream>>>(pos, n, batches, sc, rb);
  return cudaGetLastError();
}

cudaError_t launch_brute(const brute_args& args, bool count_only, cudaStream_t stream) {
  const std::uint64_t items = static_cast<std::uint64_t>(args.queries) * args.chunks;
  if (items == 0) return cudaSuccess;
  if (items >= (1ull << 31)) return cudaErrorInvalidValue;
  const auto grid = static_cast<std::uint32_t>(items);
  if (count_only) {
    brute_count_kernel<<<grid, lbvh_tuning::block, 0, stream>>>(args);
  } else {
    brute_fill_kernel<<<grid, lbvh_tuning::block, 0, stream>>>(args);
  }
  return cudaGetLastError();
}

}  // namespace zone::gpu::detail::lbvh
