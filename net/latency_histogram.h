// net/latency_histogram.h: the log-bucketed latency histogram of the zone (tick phases, /metrics,
// handoffs) and of the bot swarm (end-to-end latency): net/ is the lowest layer both use.
#pragma once

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <cstdint>

namespace zone::net {

/// A histogram of non-negative values (durations) in logarithmic buckets: value v falls in bucket
/// floor((log2(v + Shift) - LowestLog2) * PerOctave), clamped to [0, Buckets); a value <= -Shift
/// (or NaN) counts as 0. Recording is lock-free (relaxed atomics), so one thread may read
/// (snapshot(), percentile()) while others record; the figures read while recording are each a
/// recent value, not one consistent instant.
template <int PerOctave, int Buckets, int LowestLog2, int Shift>
class log_histogram {
 public:
  static constexpr int buckets = Buckets;
  static constexpr int per_octave = PerOctave;
  using counts = std::array<std::uint64_t, Buckets>;

  /// The bucket of value `v`.
  [[nodiscard]] static int bucket_of(double v) {
    if (!(v >= 0)) v = 0;
    const double shifted = v + Shift;
    if (shifted <= 0) return 0;
    const double b = std::floor((std::log2(shifted) - LowestLog2) * PerOctave);
    return static_cast<int>(std::clamp(b, 0.0, static_cast<double>(Buckets - 1)));
  }
  /// The value at the upper edge of bucket b.
  [[nodiscard]] static double bucket_upper(int b) { return std::exp2((b + 1) / double(PerOctave) + LowestLog2) - Shift; }
  /// The value at the middle of bucket b (on the log scale).
  [[nodiscard]] static double bucket_mid(int b) { return std::exp2((b + 0.5) / double(PerOctave) + LowestLog2) - Shift; }

  log_histogram() = default;
  /// A copy of each figure (taken one by one while others may record: see above).
  log_histogram(const log_histogram& o) { *this = o; }
  log_histogram& operator=(const log_histogram& o) {
    if (this == &o) return *this;
    for (int b = 0; b < Buckets; ++b) count_[static_cast<std::size_t>(b)].store(o.bucket(b), std::memory_order_relaxed);
    n_.store(o.count(), std::memory_order_relaxed);
    sum_.store(o.sum(), std::memory_order_relaxed);
    max_.store(o.max(), std::memory_order_relaxed);
    return *this;
  }

  void record(double v) {
    if (!(v >= 0)) v = 0;
    count_[static_cast<std::size_t>(bucket_of(v))].fetch_add(1, std::memory_order_relaxed);
    n_.fetch_add(1, std::memory_order_relaxed);
    sum_.fetch_add(v, std::memory_order_relaxed);
    double m = max_.load(std::memory_order_relaxed);
    while (v > m && !max_.compare_exchange_weak(m, v, std::memory_order_relaxed)) {
    }
  }
  void clear() { *this = log_histogram{}; }
  /// Adds `o`'s figures to these (e.g. to sum per-thread histograms when read).
  void add(const log_histogram& o) {
    for (int b = 0; b < Buckets; ++b)
      count_[static_cast<std::size_t>(b)].fetch_add(o.bucket(b), std::memory_order_relaxed);
    n_.fetch_add(o.count(), std::memory_order_relaxed);
    sum_.fetch_add(o.sum(), std::memory_order_relaxed);
    const double v = o.max();
    double m = max_.load(std::memory_order_relaxed);
    while (v > m && !max_.compare_exchange_weak(m, v, std::memory_order_relaxed)) {}
  }

  [[nodiscard]] std::uint64_t count() const { return n_.load(std::memory_order_relaxed); }
  [[nodiscard]] double sum() const { return sum_.load(std::memory_order_relaxed); }
  [[nodiscard]] double max() const { return max_.load(std::memory_order_relaxed); }
  [[nodiscard]] std::uint64_t bucket(int b) const { return count_[static_cast<std::size_t>(b)].load(std::memory_order_relaxed); }
  /// Every bucket's count; two snapshots' difference is the histogram of what came between them.
  [[nodiscard]] counts snapshot() const {
    counts c{};
    for (int b = 0; b < Buckets; ++b) c[static_cast<std::size_t>(b)] = bucket(b);
    return c;
  }
  [[nodiscard]] static std::uint64_t total(const counts& c) {
    std::uint64_t n = 0;
    for (const auto v : c) n += v;
    return n;
  }
  /// The bucket that holds quantile q (0..1) of `c`: the first whose running count reaches
  /// ceil(q * total) (at least 1); -1 when `c` is empty.
  [[nodiscard]] static int quantile_bucket(const counts& c, double q) {
    const std::uint64_t n = total(c);
    if (n == 0) return -1;
    const auto rank = static_cast<std::uint64_t>(std::ceil(std::clamp(q, 0.0, 1.0) * static_cast<double>(n)));
    std::uint64_t seen = 0;
    for (int b = 0; b < Buckets; ++b) {
      seen += c[static_cast<std::size_t>(b)];
      if (seen >= std::max<std::uint64_t>(rank, 1)) return b;
    }
    return Buckets - 1;
  }
  /// Quantile q: the upper edge of its bucket, never above the largest value recorded (0 when
  /// empty). At most one bucket's width (2^(1/PerOctave)) above the true value.
  [[nodiscard]] double percentile(double q) const {
    const int b = quantile_bucket(snapshot(), q);
    return b < 0 ? 0 : std::min(bucket_upper(b), max());
  }
  /// Quantile q of a snapshot (or of two snapshots' difference): its bucket's middle (0 when empty).
  [[nodiscard]] static double percentile_mid(const counts& c, double q) {
    const int b = quantile_bucket(c, q);
    return b < 0 ? 0 : bucket_mid(b);
  }

 private:
  std::array<std::atomic<std::uint64_t>, Buckets> count_{};
  std::atomic<std::uint64_t> n_{0};
  std::atomic<double> sum_{0};
  std::atomic<double> max_{0};
};

/// The zone's tick phases, /metrics and the world's handoffs: milliseconds, 4 buckets an octave
/// from 2^-10 ms (about 1 microsecond) to 2^14 ms (16 s).
using latency_histogram_ms = log_histogram<4, 96, -10, 0>;
/// The bot swarm's end-to-end latencies: microseconds (plus 1, so that 0 us has a bucket), 16
/// buckets an octave (about 4% resolution) up to 2^40 us.
using latency_histogram_us = log_histogram<16, 640, 0, 1>;

}  // namespace zone::net
