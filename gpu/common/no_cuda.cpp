// The GPU layer in a build without CUDA: every entry point says so, callers fall back to the CPU.
#include <stdexcept>

#include "gpu/pbig.h"

namespace zone::gpu {

bool built_with_cuda() { return false; }

bool device_available(device_info* /*info*/, std::string* why) {
  if (why) *why = "this build has no GPU backend (configured without CUDA)";
  return false;
}

std::unique_ptr<interest::pair_finder> make_pbig_finder(const pbig_options& /*options*/, std::string* why) {
  (void)device_available(nullptr, why);  // always false here; it fills `why`
  return nullptr;
}

std::optional<interest::box_error> find_pairs_view(interest::pair_finder& /*finder*/,
                                                   const interest::box_set& /*boxes*/,
                                                   std::span<const interest::id_pair>& /*view*/) {
  throw std::invalid_argument("find_pairs_view: this build has no GPU backend");
}

const pbig_report* last_pbig_report(const interest::pair_finder& /*finder*/) { return nullptr; }

pinned_boxes::pinned_boxes(const interest::box_set& /*boxes*/) {}
pinned_boxes::~pinned_boxes() = default;
bool boxes_pinned(const interest::box_set& /*boxes*/) { return false; }

}  // namespace zone::gpu
