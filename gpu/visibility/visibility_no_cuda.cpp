// The GPU visibility engine in a build without CUDA: it says so, and the zone keeps its host path.
#include "gpu/device.h"
#include "gpu/visibility.h"

namespace zone::gpu {

std::unique_ptr<interest::visibility_engine> make_visibility_engine(interest::thread_pool* /*pool*/, std::string* why) {
  (void)device_available(nullptr, why);  // always false here; it fills `why`
  return nullptr;
}

}  // namespace zone::gpu
