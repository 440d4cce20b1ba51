// Kernels of the GPU replication engine (replication_launch.h): the per-job code is
// replication_shared.h's decide_job, one thread per job; see there for how the floats stay
// bit-identical to the host's.
#include <algorithm>

#include "replication_launch.h"

namespace zone::gpu::detail::rep {
namespace {

constexpr std::uint32_t block = 128;

std::uint32_t blocks_for(std::uint64_t n, std::uint32_t per_block) {
  return static_cast<std::uint32_t>(std::max<std::uint64_t>(1, (n + per_block - 1) / per_block));
}

__global__ void carry_kernel(run_args a) {
  const std::uint32_t warp = (blockIdx.x * blockDim.x + threadIdx.x) / 32, lane = threadIdx.x % 32;
  if (warp >= a.client_count) return;
  carry_client(a, warp, lane, 32);
}

__global__ void decide_kernel(run_args a) {
  const std::uint32_t t = blockIdx.x * blockDim.x + threadIdx.x;
  if (t >= a.job_count) return;
  decide_job(a, t);
}

}  // namespace

cudaError_t launch_carry(const run_args& a, cudaStream_t stream) {
  if (a.client_count == 0) return cudaSuccess;
  carry_kernel<<<blocks_for(std::uint64_t{a.client_count} * 32, 256), 256, 0, stream>>>(a);
  return cudaGetLastError();
}

cudaError_t launch_decide(const run_args& a, cudaStream_t stream) {
  if (a.job_count == 0) return cudaSuccess;
  decide_kernel<<<blocks_for(a.job_count, block), block, 0, stream>>>(a);
  return cudaGetLastError();
}

}  // namespace zone::gpu::detail::rep
