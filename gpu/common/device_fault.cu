// TESTING ONLY: a real, sticky device fault (device_fault.h).
#include <stdexcept>

#include "gpu/common/cuda_check.h"
#include "gpu/device_fault.h"

namespace zone::gpu {
namespace {
__global__ void trap_kernel() { __trap(); }
}  // namespace

void raise_device_fault() {
  trap_kernel<<<1, 1>>>();
  CUDA_CHECK(cudaGetLastError());
  CUDA_CHECK(cudaDeviceSynchronize());
  throw std::runtime_error("raise_device_fault: the trapping kernel completed (no fault)");
}

}  // namespace zone::gpu
