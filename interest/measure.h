// Small measuring helpers shared by the layers and the tools (not installed): elapsed time on the
// steady clock, the median and the quantile of a sample.
#pragma once

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstddef>
#include <vector>

namespace zone {

/// Milliseconds on the steady clock from `t0` to now.
inline double ms_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

/// The median of a sample (the mean of the two middle values of an even one); 0 for an empty one.
inline double median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  const std::size_t m = v.size() / 2;
  return v.size() % 2 ? v[m] : 0.5 * (v[m - 1] + v[m]);
}

/// The q-quantile of a sample by the nearest-rank rule: the smallest value with at least a share q
/// of the sample at or below it (q <= 0: the minimum, q >= 1: the maximum); 0 for an empty sample.
inline double quantile(std::vector<double> v, double q) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  const double rank = std::ceil(std::clamp(q, 0.0, 1.0) * static_cast<double>(v.size()));
  return v[std::clamp<std::size_t>(static_cast<std::size_t>(rank), 1, v.size()) - 1];
}

}  // namespace zone
