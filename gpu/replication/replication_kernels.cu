// Kernels of the GPU replication engine (replication_launch.h): the per-job code is
// replication_shared.h's decide_job, one warp per job; see there for how the floats stay
// bit-identical to the host's.
#include <cub/device/device_reduce.cuh>
#include <cub/device/device_scan.cuh>

#include <algorithm>

#include "replication_launch.h"

namespace zone::gpu::detail::rep {
namespace {

// Threads per block of the decide kernel: four warps, one job each.
constexpr std::uint32_t block = 128;

/// A warp as decide_job's group of lanes (replication_shared.h, serial_lanes).
struct warp_lanes {
  static constexpr std::uint32_t width = 32;
  static constexpr unsigned all = 0xffffffffu;
  __device__ std::uint32_t lane() const { return threadIdx.x % 32; }
  __device__ std::uint32_t ballot(bool p) { return __ballot_sync(all, p); }
  __device__ std::uint32_t first(std::uint32_t v) { return __shfl_sync(all, v, 0); }
  __device__ std::uint64_t sum(std::uint64_t v) {
    for (int d = 16; d > 0; d /= 2) v += __shfl_xor_sync(all, v, d);
    return v;
  }
  __device__ void sync() { __syncwarp(); }
};

std::uint32_t blocks_for(std::uint64_t n, std::uint32_t per_block) {
  return static_cast<std::uint32_t>(std::max<std::uint64_t>(1, (n + per_block - 1) / per_block));
}

__global__ void rooms_kernel(run_args a, std::uint32_t* rooms, std::uint64_t* records) {
  const std::uint32_t c = blockIdx.x * blockDim.x + threadIdx.x;
  if (c > a.client_count) return;
  if (c == a.client_count) {
    rooms[c] = 0;
    return;
  }
  client_room(a, c, rooms[c], records[c]);
}

__global__ void quantize_kernel(run_args a) {
  const std::uint32_t k = blockIdx.x * blockDim.x + threadIdx.x;
  if (k < a.entity_count) quantize_entity(a, k);
}

__global__ void carry_kernel(run_args a) {
  const std::uint32_t warp = (blockIdx.x * blockDim.x + threadIdx.x) / 32, lane = threadIdx.x % 32;
  if (warp >= a.client_count) return;
  carry_client(a, warp, lane, 32);
}

__global__ void decide_kernel(run_args a) {
  const std::uint32_t job = (blockIdx.x * blockDim.x + threadIdx.x) / 32;  // the same in all of a warp
  if (job >= a.job_count) return;
  warp_lanes g;
  decide_job(a, job, g);
}

}  // namespace

cudaError_t launch_rooms(const run_args& a, std::uint32_t* rooms, std::uint64_t* records, cudaStream_t stream) {
  rooms_kernel<<<blocks_for(std::uint64_t{a.client_count} + 1, 256), 256, 0, stream>>>(a, rooms, records);
  return cudaGetLastError();
}

cudaError_t scan_rooms(void* temp, std::size_t& temp_bytes, const std::uint32_t* rooms, std::uint32_t* new_off,
                       std::uint32_t items, const std::uint64_t* records, std::uint64_t* sum, std::uint32_t n,
                       cudaStream_t stream) {
  if (temp == nullptr) {
    std::size_t scan = 0, reduce = 0;
    cudaError_t e = cub::DeviceScan::ExclusiveSum(nullptr, scan, rooms, new_off, items, stream);
    if (e != cudaSuccess) return e;
    e = cub::DeviceReduce::Sum(nullptr, reduce, records, sum, std::max<std::uint32_t>(n, 1), stream);
    temp_bytes = std::max(scan, reduce);
    return e;
  }
  cudaError_t e = cub::DeviceScan::ExclusiveSum(temp, temp_bytes, rooms, new_off, items, stream);
  if (e != cudaSuccess) return e;
  return cub::DeviceReduce::Sum(temp, temp_bytes, records, sum, std::max<std::uint32_t>(n, 1), stream);
}

cudaError_t launch_quantize(const run_args& a, cudaStream_t stream) {
  if (a.entity_count == 0) return cudaSuccess;
  quantize_kernel<<<blocks_for(a.entity_count, 256), 256, 0, stream>>>(a);
  return cudaGetLastError();
}

cudaError_t launch_carry(const run_args& a, cudaStream_t stream) {
  if (a.client_count == 0) return cudaSuccess;
  carry_kernel<<<blocks_for(std::uint64_t{a.client_count} * 32, 256), 256, 0, stream>>>(a);
  return cudaGetLastError();
}

cudaError_t launch_decide(const run_args& a, cudaStream_t stream) {
  if (a.job_count == 0) return cudaSuccess;
  decide_kernel<<<blocks_for(std::uint64_t{a.job_count} * 32, block), block, 0, stream>>>(a);
  return cudaGetLastError();
}

}  // namespace zone::gpu::detail::rep
