// Host API of the GPU PBIG finder: the pair_finder behind make_pbig_finder.
#include <stdexcept>

#include "gpu/common/finder_glue.h"
#include "gpu/pbig.h"
#include "pbig_dispatch.h"
#include "pbig_tuning.h"

namespace zone::gpu {
namespace {

/// The GPU PBIG finder. Output order: the grid's pairs batch by batch (batches in cell order),
/// within a batch tile by tile in (cell, row segment, column segment) order, within a tile by
/// row then column in the cell's box order (box ids ascending); then the pairs of the boxes
/// handled apart, by (large box, other box id). All of it depends only on the input.
class pbig_finder final : public detail::own_buffer_finder {
 public:
  explicit pbig_finder(const pbig_options& options)
      : own_buffer_finder("find_pairs_view"), engine_(options), direct_(options.direct_output) {}
  [[nodiscard]] std::string_view name() const override { return "gpu"; }
  [[nodiscard]] const pbig_report& report() const { return engine_.report(); }

 protected:
  std::optional<std::uint64_t> run_validated(const interest::box_set& boxes, interest::finder_stats& stats) override {
    return engine_.run(boxes, pairs_, stats, /*keep_size=*/true, /*validate=*/true);
  }
  [[nodiscard]] const interest::id_pair* view_data() const override {
    return direct_ ? engine_.direct_data() : pairs_.data();
  }
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
  return detail::start_finder("pbig", "GPU finder", why, [&] { return std::make_unique<pbig_finder>(options); });
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
