#include "finder_glue.h"

#include <spdlog/spdlog.h>

#include <exception>
#include <stdexcept>

#include "gpu/device.h"

namespace zone::gpu::detail {

std::optional<interest::box_error> own_buffer_finder::find_view(const interest::box_set& boxes,
                                                                std::span<const interest::id_pair>& view) {
  view = {};
  if (boxes.size() < 2) {
    if (auto err = interest::validate(boxes)) return err;
    stats_ = {};
    return std::nullopt;
  }
  interest::finder_stats found_stats;
  const auto found = run_validated(boxes, found_stats);
  if (!found) {
    if (auto err = interest::validate(boxes)) return err;
    throw std::logic_error(std::string(view_function_) + ": packing check and interest::validate disagree");
  }
  stats_ = found_stats;
  view = std::span<const interest::id_pair>(view_data(), *found);
  return std::nullopt;
}

std::unique_ptr<interest::pair_finder> start_finder(const char* tag, const char* what, std::string* why,
                                                    const std::function<std::unique_ptr<interest::pair_finder>()>& make) {
  device_info info;
  if (!device_available(&info, why)) return nullptr;
  try {
    auto finder = make();
    spdlog::debug("{}: GPU finder on {} (sm_{}{}, {} SMs)", tag, info.name, info.compute_major, info.compute_minor,
                  info.multiprocessors);
    return finder;
  } catch (const std::exception& e) {
    if (why) *why = std::string("cannot start the ") + what + ": " + e.what();
    return nullptr;
  }
}

}  // namespace zone::gpu::detail
