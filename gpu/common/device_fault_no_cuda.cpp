// TESTING ONLY: device_fault.h in a build without CUDA.
#include <stdexcept>

#include "gpu/device_fault.h"

namespace zone::gpu {

void raise_device_fault() { throw std::runtime_error("raise_device_fault: this build has no CUDA"); }

}  // namespace zone::gpu
