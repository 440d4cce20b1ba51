// Device discovery for the GPU layer (gpu/device.h).
#include <cuda_runtime.h>

#include "gpu/device.h"

namespace zone::gpu {

bool built_with_cuda() { return true; }

bool device_available(device_info* info, std::string* why) {
  int count = 0;
  const cudaError_t err = cudaGetDeviceCount(&count);
  if (err != cudaSuccess) {
    if (why) *why = std::string("no usable CUDA device: ") + cudaGetErrorString(err);
    cudaGetLastError();  // clear the sticky-free error state
    return false;
  }
  if (count == 0) {
    if (why) *why = "no CUDA device present";
    return false;
  }
  if (info) {
    cudaDeviceProp prop{};
    if (cudaGetDeviceProperties(&prop, 0) == cudaSuccess) {
      info->name = prop.name;
      info->compute_major = prop.major;
      info->compute_minor = prop.minor;
      info->multiprocessors = prop.multiProcessorCount;
      info->global_memory_bytes = prop.totalGlobalMem;
    }
  }
  return true;
}

}  // namespace zone::gpu
