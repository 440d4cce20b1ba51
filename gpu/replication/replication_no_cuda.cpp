// The GPU replication engine in a build without CUDA: it says so, and the zone replicates on the CPU.
#include "gpu/device.h"
#include "gpu/replication.h"

namespace zone::gpu {

std::unique_ptr<interest::replication_engine> make_replication_engine(std::string* why) {
  (void)device_available(nullptr, why);  // always false here; it fills `why`
  return nullptr;
}

}  // namespace zone::gpu
