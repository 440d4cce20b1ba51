// The LBVH finder in a build without CUDA: every entry point says so, callers fall back to the CPU.
#include <stdexcept>

#include "gpu/device.h"
#include "gpu/lbvh.h"

namespace zone::gpu {

std::unique_ptr<interest::pair_finder> make_lbvh_finder(const lbvh_options& /*options*/, std::string* why) {
  (void)device_available(nullptr, why);  // always false here; it fills `why`
  return nullptr;
}

const lbvh_report* last_lbvh_report(const interest::pair_finder& /*finder*/) { return nullptr; }

std::optional<interest::box_error> find_lbvh_view(interest::pair_finder& /*finder*/, const interest::box_set& /*boxes*/,
                                                  std::span<const interest::id_pair>& /*view*/) {
  throw std::invalid_argument("find_lbvh_view: this build has no GPU backend");
}

}  // namespace zone::gpu
