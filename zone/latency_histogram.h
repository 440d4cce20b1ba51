// zone/latency_histogram.h: a log-bucketed latency histogram (tick phases, metrics).
#pragma once

#include <cstdint>

namespace zone {

/// Latency histogram with 4 logarithmic buckets per octave from about 1 microsecond to 16 s.
/// percentile() answers with the upper edge of the bucket holding that quantile (at most 19% above
/// the true value), never above the maximum recorded. Not thread-safe.
class latency_histogram {
 public:
  void record(double ms);
  [[nodiscard]] double percentile(double q) const;
  [[nodiscard]] double max() const { return max_; }
  [[nodiscard]] double sum() const { return sum_; }
  [[nodiscard]] std::uint64_t count() const { return count_; }
  void clear();
  static constexpr int bucket_count = 96;
  [[nodiscard]] static double bucket_upper_ms(int b);  ///< upper edge of bucket b
  [[nodiscard]] std::uint64_t bucket(int b) const { return counts_[static_cast<std::size_t>(b)]; }

 private:
  std::uint64_t counts_[bucket_count]{};
  std::uint64_t count_ = 0;
  double max_ = 0;
  double sum_ = 0;
};

}  // namespace zone
