// The pair_finder glue both GPU finders share (pbig/pbig_finder.cpp, lbvh/lbvh_finder.cpp; host
// code): find_view for a finder whose pairs stay in a result buffer of its own, and the start of
// their factories.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>

#include "interest/interest.h"

namespace zone::gpu::detail {

/// A GPU finder: its pairs stay in its engine's result buffer, and find_view shows them there.
class own_buffer_finder : public interest::pair_finder {
 public:
  /// pair_finder::find_view: the pairs stay in this finder's result buffer (`scratch` unused).
  std::optional<interest::box_error> find_view(const interest::box_set& boxes, interest::pair_list& /*scratch*/,
                                               std::span<const interest::id_pair>& view) override {
    return find_view(boxes, view);
  }
  [[nodiscard]] bool views_own_buffer() const override { return true; }
  /// The pairs of `boxes` in the result buffer (valid until the next call). The engine validates
  /// the boxes as it takes them in (the upload's packing pass: no extra read of the boxes); an
  /// invalid set returns interest::validate's error, with `view` empty and the statistics
  /// unchanged. Under 2 boxes: validation only, no pairs, statistics reset.
  std::optional<interest::box_error> find_view(const interest::box_set& boxes, std::span<const interest::id_pair>& view);

 protected:
  /// `view_function`: the public name of find_view (find_pairs_view, find_lbvh_view), for its errors.
  explicit own_buffer_finder(const char* view_function) : view_function_(view_function) {}
  /// The engine's call on at least 2 boxes, validating them on its upload: the number of pairs,
  /// then at view_data(); nothing when a box is invalid. Fills `stats`.
  virtual std::optional<std::uint64_t> run_validated(const interest::box_set& boxes, interest::finder_stats& stats) = 0;
  /// Where the last run_validated left its pairs.
  [[nodiscard]] virtual const interest::id_pair* view_data() const = 0;

 private:
  const char* view_function_;
};

/// The body of a GPU finder's factory (make_pbig_finder, make_lbvh_finder): the finder `make`
/// returns, logged at debug level with the device under `tag`; null with `why` set (when not null)
/// when no device can be used or `make` throws (then `why` names the finder by `what`).
[[nodiscard]] std::unique_ptr<interest::pair_finder> start_finder(
    const char* tag, const char* what, std::string* why,
    const std::function<std::unique_ptr<interest::pair_finder>()>& make);

}  // namespace zone::gpu::detail
