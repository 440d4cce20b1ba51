// Device discovery for the GPU layer.
#include <cuda_runtime.h>

#include "pbig.h"

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

std::unique_ptr<interest::pair_finder> make_pbig_finder(const pbig_options& /*options*/, std::string* why) {
  // The PBIG kernels arrive with the GPU issue; until then the GPU backend finds no pairs.
  if (!device_available(nullptr, why)) return nullptr;
  if (why) *why = "the GPU PBIG finder is not built yet";
  return nullptr;
}

}  // namespace zone::gpu
