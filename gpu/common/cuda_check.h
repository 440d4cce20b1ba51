// CUDA_CHECK: every CUDA runtime call of the GPU layer goes through it. A failure is logged with
// the call's text, file and line through spdlog and thrown as std::runtime_error.
#pragma once

#include <cuda_runtime.h>

namespace zone::gpu::detail {

/// Logs (spdlog, error level) and throws std::runtime_error naming the call, file and line.
[[noreturn]] void cuda_fail(cudaError_t err, const char* call, const char* file, int line);

/// Milliseconds from event `begin` to event `end`, both recorded and completed (checked as
/// CUDA_CHECK does).
[[nodiscard]] float elapsed_ms(cudaEvent_t begin, cudaEvent_t end);

}  // namespace zone::gpu::detail

#define CUDA_CHECK(call)                                                                          \
  do {                                                                                            \
    const cudaError_t zone_cuda_err_ = (call);                                                    \
    if (zone_cuda_err_ != cudaSuccess) {                                                          \
      ::zone::gpu::detail::cuda_fail(zone_cuda_err_, #call, __FILE__, __LINE__);                  \
    }                                                                                             \
  } while (0)
