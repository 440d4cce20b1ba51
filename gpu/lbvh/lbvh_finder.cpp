// Host API of the GPU LBVH finder: the pair_finder behind make_lbvh_finder.
#include <cstring>
#include <stdexcept>

#include "gpu/common/finder_glue.h"
#include "gpu/lbvh.h"
#include "lbvh_dispatch.h"
#include "lbvh_tuning.h"

namespace zone::gpu {
namespace {

/// The GPU LBVH finder. Output order: the tree's pairs by query leaf (key order: mask-0 boxes after
/// the others, each part in Morton order, equal keys by id), within a leaf in traversal order (left child first); then the brute pass's
/// pairs (overflowed queries in leaf order, then the large boxes in id order; each by chunk and
/// thread). All of it depends only on the input.
class lbvh_finder final : public detail::own_buffer_finder {
 public:
  explicit lbvh_finder(const lbvh_options& options) : own_buffer_finder("find_lbvh_view"), engine_(options) {}
  [[nodiscard]] std::string_view name() const override { return "lbvh"; }
  [[nodiscard]] const lbvh_report& report() const { return engine_.report(); }

 protected:
  std::optional<std::uint64_t> run_validated(const interest::box_set& boxes, interest::finder_stats& stats) override {
    return engine_.run(boxes, stats, /*validate=*/true);
  }
  [[nodiscard]] const interest::id_pair* view_data() const override { return engine_.result(); }
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
  return detail::start_finder("lbvh", "GPU LBVH finder", why, [&] { return std::make_unique<lbvh_finder>(options); });
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
