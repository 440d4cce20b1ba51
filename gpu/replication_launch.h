// Host-callable launchers of the GPU replication engine's kernels (gpu/replication.h; the shared
// arguments and the per-job code: replication_shared.h).
#pragma once

#include <cuda_runtime.h>

#include "replication_shared.h"

namespace zone::gpu::detail::rep {

/// Views of clients without a job into the new buffer (one warp per client).
cudaError_t launch_carry(const run_args& a, cudaStream_t stream);
/// One thread per job: the frame's decisions, its record, the client's new view (decide_job).
cudaError_t launch_decide(const run_args& a, cudaStream_t stream);

}  // namespace zone::gpu::detail::rep
