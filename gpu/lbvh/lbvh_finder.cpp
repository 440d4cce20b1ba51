// Host API of the GPU LBVH finder: the pair_finder behind make_lbvh_finder.
#include <spdlog/spdlog.h>

#include <cstring>
#include <stdexcept>

#include "gpu/device.h"
#include "gpu/lbvh.h"
#include "lbvh_dispatch.h"
#include "lbvh_tuning.h"

namespace zone::gpu {
namespace {

/// The GPU LBVH finder. Output order: the tree's pairs by query leaf (key order: mask-0 boxes after
/// the others, each part in Morton order, equal keys by id), within a leaf in traversal order (left child first); then the brute pass's
/// pairs (overflowed queries in leaf order, then the large boxes in id order; each by chunk and
/// thread). All of it depends only on the input.
class lbvh_finder final : public interest::pair_finder {
 public:
  explicit lbvh_finder(const lbvh_options& options) : engine_(options) {}
  [[nodiscard]] std::string_view name() const override { return "lbvh"; }
  [[nodiscard]] const lbvh_report& report() const { return engine_.report(); }

  /// pair_finder::find_view: the pairs stay in this finder's result buffer (`scratch` unused).
  std::optional<interest::box_error> find_view(const interest::box_set& boxes, interest::pair_list& /*scratch*/,
                                               std::span<const interest::id_pair>& view) override {
    return find_view(boxes, view);
  }
  [[nodiscard]] bool views_own_buffer() const override { return true; }
  std::optional<interest::box_error> find_view(const interest::box_set& boxes,
                                               std::span<const interest::id_pair>& view) {
    view = {};
    if (boxes.size() < 2) {
      if (auto err = interest::validate(boxes)) return err;
      stats_ = {};
      return std::nullopt;
    }
    interest::finder_stats found_stats;
    const auto found = engine_.run(boxes, found_stats, /*validate=*/true);
    if (!found) {
      if (auto err = interest::validate(boxes)) return err;
      throw std::logic_error("find_lbvh_view: packing check and interest::validate disagree");
    }
    stats_ = found_stats;
    view = std::span<const interest::id_pair>(engine_.result(), *found);
    return std::nullopt;
  }

 protected:
  [[nodiscard]] interest::thread_pool* worker_pool() const override { return engine_.pool(); }
  void find_valid(const interest::box_set& boxes, interest::pair_list& out) override {
    out.clear();
    if (boxes.size() < 2) return;
    const std::uint64_t count = *engine_.run(boxes, stats_, /*validate=*/false);
    out.resize(count);
    const interest::id_pair* src = engine_.result();
    interest::id_pair* dst = out.data();
    interest::thread_pool* pool = engine_.pool();
    const std::size_t parts = count < lbvh_tuning::parallel_copy_pairs ? 1 : pool->size() * 4;
    interest::run_tasks(parts > 1 ? pool : nullptr, parts, [&](std::size_t p) {
      const std::size_t b = count * p / parts, e = count * (p + 1) / parts;
      if (e > b) std::memcpy(static_cast<void*>(dst + b), src + b, (e - b) * sizeof(interest::id_pair));
    });
  }

 private:
  detail::lbvh::lbvh_engine engine_;
};

}  // namespace

std::unique_ptr<interest::pair_finder> make_lbvh_finder(const lbvh_options& options, std::string* why) {
  device_info info;
  if (!device_available(&info, why)) return nullptr;
  try {
    auto finder = std::make_unique<lbvh_finder>(options);
    spdlog::debug("lbvh: GPU finder on {} (sm_{}{}, {} SMs)", info.name, info.compute_major, info.compute_minor,
                  info.multiprocessors);
    return finder;
  } catch (const std::exception& e) {
    if (why) *why = std::string("cannot start the GPU LBVH finder: ") + e.what();
    return nullptr;
  }
}

const lbvh_report* last_lbvh_report(const interest::pair_finder& finder) {
  const auto* f = dynamic_cast<const lbvh_finder*>(&finder);
  return f != nullptr ? &f->report() : nullptr;
}

std::optional<interest::box_error> find_lbvh_view(interest::pair_finder& finder, const interest::box_set& boxes,
                                                  std::span<const interest::id_pair>& view) {
  auto* f = dynamic_cast<lbvh_finder*>(&finder);
  if (f == nullptr) throw std::invalid_argument("find_lbvh_view: not a finder made by make_lbvh_finder");
  return f->find_view(boxes, view);
}

}  // namespace zone::gpu
