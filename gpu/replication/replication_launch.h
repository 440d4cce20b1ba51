// Host-callable launchers of the GPU replication engine's kernels (gpu/replication.h; the shared
// arguments and the per-job code: replication_shared.h).
#pragma once

#include <cuda_runtime.h>

#include <cstddef>

#include "replication_shared.h"

namespace zone::gpu::detail::rep {

/// Resident rows: each client's room (rooms[c], and rooms[client_count] = 0) and record bound.
cudaError_t launch_rooms(const run_args& a, std::uint32_t* rooms, std::uint64_t* records, cudaStream_t stream);
/// Exclusive scan of `items` u32 (rooms -> new_off) and the sum of `n` u64 record bounds into *sum;
/// with temp == nullptr only temp_bytes is set (the larger of the two).
cudaError_t scan_rooms(void* temp, std::size_t& temp_bytes, const std::uint32_t* rooms, std::uint32_t* new_off,
                       std::uint32_t items, const std::uint64_t* records, std::uint64_t* sum, std::uint32_t n,
                       cudaStream_t stream);
/// Every entity's wire update (quantize_entity), before launch_decide.
cudaError_t launch_quantize(const run_args& a, cudaStream_t stream);
/// Views of clients without a job into the new buffer (one warp per client).
cudaError_t launch_carry(const run_args& a, cudaStream_t stream);
/// One warp per job: the frame's decisions, its record, the client's new view (decide_job).
cudaError_t launch_decide(const run_args& a, cudaStream_t stream);

}  // namespace zone::gpu::detail::rep
