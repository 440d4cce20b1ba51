#include "cuda_check.h"

#include <spdlog/spdlog.h>

#include <stdexcept>
#include <string>

namespace zone::gpu::detail {

void cuda_fail(cudaError_t err, const char* call, const char* file, int line) {
  const std::string msg = std::string("CUDA error ") + cudaGetErrorName(err) + " (" + cudaGetErrorString(err) +
                          ") in " + call + " at " + file + ":" + std::to_string(line);
  spdlog::error("{}", msg);
  // Clear the thread's last error: a failure that was thrown (and perhaps handled, e.g. by a
  // fallback to the CPU) must not be reported again by the next launch's cudaGetLastError.
  // (A sticky error, a device fault, stays: every later call reports it anyway.)
  (void)cudaGetLastError();
  throw std::runtime_error(msg);
}

float elapsed_ms(cudaEvent_t begin, cudaEvent_t end) {
  float ms = 0;
  CUDA_CHECK(cudaEventElapsedTime(&ms, begin, end));
  return ms;
}

}  // namespace zone::gpu::detail
