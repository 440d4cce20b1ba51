// Host API of the GPU PBIG finder: the pair_finder behind make_pbig_finder.
#include <spdlog/spdlog.h>

#include <atomic>
#include <cmath>
#include <stdexcept>

#include "gpu/pbig.h"
#include "pbig_dispatch.h"
#include "pbig_tuning.h"

namespace zone::gpu {
namespace {

/// The GPU PBIG finder. Output order: the grid's pairs batch by batch (batches in cell order),
/// within a batch tile by tile in (cell, row segment, column segment) order, within a tile by
/// row then column in the cell's box order (box ids ascending); then the pairs of the boxes
/// handled apart, by (large box, other box id). All of it depends only on the input.
class pbig_finder final : public interest::pair_finder {
 public:
  explicit pbig_finder(const pbig_options& options) : engine_(options), direct_(options.direct_output) {}
  [[nodiscard]] std::string_view name() const override { return "gpu"; }
  [[nodiscard]] const pbig_report& report() const { return engine_.report(); }

  /// pair_finder::find_view: the pairs stay in this finder's result buffer (`scratch` unused).
  std::optional<interest::box_error> find_view(const interest::box_set& boxes, interest::pair_list& /*scratch*/,
                                               std::span<const interest::id_pair>& view) override {
    return find_view(boxes, view);
  }
  [[nodiscard]] bool views_own_buffer() const override { return true; }
  std::optional<interest::box_error> find_view(const interest::box_set& boxes,
                                               std::span<const interest::id_pair>& view) {
    view = {};
    std::uint64_t count = 0;
    if (boxes.size() < 2) {
      if (auto err = interest::validate(boxes)) return err;
    } else {
      // Validation rides on the upload's packing pass (one read of the boxes, on the pool).
      interest::finder_stats found_stats;
      const auto found = engine_.run(boxes, pairs_, found_stats, /*keep_size=*/true, /*validate=*/true);
      if (!found) {
        if (auto err = interest::validate(boxes)) return err;
        throw std::logic_error("find_pairs_view: packing check and interest::validate disagree");
      }
      count = *found;
      stats_ = found_stats;
    }
    view = std::span<const interest::id_pair>(direct_ ? engine_.direct_data() : pairs_.data(), count);
    return std::nullopt;
  }

 protected:
  [[nodiscard]] interest::thread_pool* worker_pool() const override { return engine_.pool(); }
  void find_valid(const interest::box_set& boxes, interest::pair_list& out) override {
    out.clear();
    if (boxes.size() < 2) return;
    (void)engine_.run(boxes, out, stats_, /*keep_size=*/false, /*validate=*/false);
  }

 private:
  detail::pbig_engine engine_;
  interest::pair_list pairs_;  // find_pairs_view's buffer: kept at its largest size
  bool direct_;
};

}  // namespace

std::unique_ptr<interest::pair_finder> make_pbig_finder(const pbig_options& options, std::string* why) {
  device_info info;
  if (!device_available(&info, why)) return nullptr;
  try {
    auto finder = std::make_unique<pbig_finder>(options);
    spdlog::debug("pbig: GPU finder on {} (sm_{}{}, {} SMs)", info.name, info.compute_major, info.compute_minor,
                  info.multiprocessors);
    return finder;
  } catch (const std::exception& e) {
    if (why) *why = std::string("cannot start the GPU finder: ") + e.what();
    return nullptr;
  }
}

std::optional<interest::box_error> find_pairs_view(interest::pair_finder& finder, const interest::box_set& boxes,
                                                   std::span<const interest::id_pair>& view) {
  auto* f = dynamic_cast<pbig_finder*>(&finder);
  if (f == nullptr) throw std::invalid_argument("find_pairs_view: not a finder made by make_pbig_finder");
  return f->find_view(boxes, view);
}

const pbig_report* last_pbig_report(const interest::pair_finder& finder) {
  const auto* f = dynamic_cast<const pbig_finder*>(&finder);
  return f != nullptr ? &f->report() : nullptr;
}

}  // namespace zone::gpu
