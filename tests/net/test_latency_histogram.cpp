// net/latency_histogram.h, the one histogram of the zone (milliseconds) and the bot swarm
// (microseconds), against the two it replaced (zone/latency_histogram.h and bots/swarm.h's
// latency_histogram_us as of 2fbebfa, copied below as references): the same buckets and the same
// figures, bit for bit, on fresh random values and edge cases; and recording from several threads.
#include <doctest/doctest.h>

#include "../common/seeds.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <random>
#include <thread>
#include <vector>

#include "net/latency_histogram.h"

namespace {

using zone::test::fresh_seed;

/// The zone's histogram before (zone/latency_histogram.h, zone/world.cpp).
struct old_zone_histogram {
  static constexpr int bucket_count = 96;
  std::uint64_t counts[bucket_count]{};
  std::uint64_t count = 0;
  double max = 0, sum = 0;
  static double bucket_upper_ms(int b) { return std::exp2((b + 1) / 4.0 - 10.0); }
  static int bucket_of(double ms) {
    if (!(ms >= 0)) ms = 0;
    return ms <= 0 ? 0 : std::clamp(static_cast<int>(std::floor((std::log2(ms) + 10.0) * 4.0)), 0, bucket_count - 1);
  }
  void record(double ms) {
    if (!(ms >= 0)) ms = 0;
    ++counts[bucket_of(ms)];
    ++count;
    max = std::max(max, ms);
    sum += ms;
  }
  [[nodiscard]] double percentile(double q) const {
    if (count == 0) return 0;
    const auto rank = static_cast<std::uint64_t>(std::ceil(std::clamp(q, 0.0, 1.0) * static_cast<double>(count)));
    std::uint64_t seen = 0;
    for (int b = 0; b < bucket_count; ++b) {
      seen += counts[b];
      if (seen >= std::max<std::uint64_t>(rank, 1)) return std::min(bucket_upper_ms(b), max);
    }
    return max;
  }
};

/// The bots' histogram before (bots/swarm.h, bots/swarm.cpp), single-threaded here.
struct old_bots_histogram {
  static constexpr int buckets = 16 * 40;
  using counts = std::array<std::uint64_t, buckets>;
  counts count{};
  std::uint64_t max = 0;
  static int bucket_of(std::uint64_t us) {
    const double b = std::log2(static_cast<double>(us) + 1.0) * 16.0;
    return std::clamp(static_cast<int>(b), 0, buckets - 1);
  }
  static double bucket_mid_us(int b) { return std::exp2((b + 0.5) / 16.0) - 1.0; }
  void record(std::uint64_t us) {
    ++count[static_cast<std::size_t>(bucket_of(us))];
    max = std::max(max, us);
  }
  static double percentile_ms(const counts& c, double q) {
    std::uint64_t n = 0;
    for (const auto v : c) n += v;
    if (n == 0) return 0;
    const auto rank = static_cast<std::uint64_t>(std::ceil(q * static_cast<double>(n)));
    std::uint64_t seen = 0;
    for (int b = 0; b < buckets; ++b) {
      seen += c[static_cast<std::size_t>(b)];
      if (seen >= std::max<std::uint64_t>(rank, 1)) return bucket_mid_us(b) / 1000.0;
    }
    return bucket_mid_us(buckets - 1) / 1000.0;
  }
};

constexpr double quantiles[] = {0.0, 0.001, 0.25, 0.5, 0.9, 0.95, 0.99, 0.999, 1.0};

}  // namespace

TEST_SUITE("net") {

TEST_CASE("latency histogram (ms): the zone's buckets and figures as before") {
  using h_ms = zone::net::latency_histogram_ms;
  static_assert(h_ms::buckets == old_zone_histogram::bucket_count);
  for (int b = 0; b < h_ms::buckets; ++b) CHECK(h_ms::bucket_upper(b) == old_zone_histogram::bucket_upper_ms(b));
  const std::uint64_t seed = fresh_seed();
  CAPTURE(seed);
  std::mt19937_64 rng(seed);
  std::lognormal_distribution<double> wide(0.0, 4.0);  // ~1e-7 .. 1e7 ms: past both ends
  std::vector<double> values = {0.0, -1.0, -0.0, std::numeric_limits<double>::quiet_NaN(), 1e-300, 1e300,
                                std::numeric_limits<double>::denorm_min(), 65536.0};
  for (int e = -12; e <= 16; ++e) {  // bucket edges and their neighbours
    for (int k = 0; k < 4; ++k) {
      const double edge = std::exp2(e + k / 4.0);
      values.insert(values.end(), {edge, std::nextafter(edge, 0.0), std::nextafter(edge, 1e300)});
    }
  }
  for (int i = 0; i < 20000; ++i) values.push_back(wide(rng));
  h_ms now;
  old_zone_histogram before;
  for (const double v : values) {
    CAPTURE(v);
    REQUIRE(h_ms::bucket_of(v) == old_zone_histogram::bucket_of(v));
    now.record(v);
    before.record(v);
  }
  for (int b = 0; b < h_ms::buckets; ++b) CHECK(now.bucket(b) == before.counts[b]);
  CHECK(now.count() == before.count);
  CHECK(now.max() == before.max);
  CHECK(now.sum() == before.sum);
  for (const double q : quantiles) {
    CAPTURE(q);
    CHECK(now.percentile(q) == before.percentile(q));
  }
  const h_ms copy = now;  // loop_stats and tick_phases are copied whole
  for (int b = 0; b < h_ms::buckets; ++b) CHECK(copy.bucket(b) == now.bucket(b));
  CHECK(copy.count() == now.count());
  CHECK(copy.max() == now.max());
  CHECK(copy.sum() == now.sum());
  now.clear();
  CHECK(now.count() == 0);
  CHECK(now.snapshot() == h_ms::counts{});
  CHECK(now.percentile(0.5) == 0);
  CHECK(now.max() == 0);
}

TEST_CASE("latency histogram (us): the bots' buckets and figures as before, windows included") {
  using h_us = zone::net::latency_histogram_us;
  static_assert(h_us::buckets == old_bots_histogram::buckets);
  const std::uint64_t seed = fresh_seed();
  CAPTURE(seed);
  std::mt19937_64 rng(seed);
  std::lognormal_distribution<double> wide(std::log(2000.0), 3.0);  // microseconds, ~1 us .. ~10 s
  h_us now;
  old_bots_histogram before;
  old_bots_histogram::counts first_half{};
  std::vector<std::uint64_t> values = {0, 1, 2, 3, (std::uint64_t{1} << 40) - 2, std::uint64_t{1} << 40,
                                       std::uint64_t{1} << 50};
  for (int i = 0; i < 30000; ++i) values.push_back(static_cast<std::uint64_t>(wide(rng)));
  for (std::size_t i = 0; i < values.size(); ++i) {
    const std::uint64_t us = values[i];
    CAPTURE(us);
    REQUIRE(h_us::bucket_of(static_cast<double>(us)) == old_bots_histogram::bucket_of(us));
    now.record(static_cast<double>(us));
    before.record(us);
    if (i == values.size() / 2) {
      const auto s = now.snapshot();
      CHECK(s == before.count);
      first_half = s;
    }
  }
  const auto all = now.snapshot();
  CHECK(all == before.count);
  CHECK(now.max() / 1000.0 == static_cast<double>(before.max) / 1000.0);
  old_bots_histogram::counts window{};
  for (std::size_t b = 0; b < window.size(); ++b) window[b] = all[b] - first_half[b];
  for (const double q : quantiles) {
    CAPTURE(q);
    CHECK(h_us::percentile_mid(all, q) / 1000.0 == old_bots_histogram::percentile_ms(before.count, q));
    CHECK(h_us::percentile_mid(window, q) / 1000.0 == old_bots_histogram::percentile_ms(window, q));
  }
  CHECK(h_us::percentile_mid(old_bots_histogram::counts{}, 0.5) == 0);
}

TEST_CASE("latency histogram: recording from several threads loses nothing") {
  zone::net::latency_histogram_us h;
  constexpr int threads = 4, per_thread = 50000;
  std::vector<std::thread> pool;
  for (int t = 0; t < threads; ++t) {
    pool.emplace_back([&h, t] {
      for (int i = 0; i < per_thread; ++i) h.record(static_cast<double>((i * 7 + t) % 100000));
    });
  }
  std::uint64_t seen_while_recording = 0;
  for (int k = 0; k < 100; ++k) seen_while_recording = std::max(seen_while_recording, h.total(h.snapshot()));
  for (auto& th : pool) th.join();
  CHECK(seen_while_recording <= std::uint64_t{threads} * per_thread);
  CHECK(h.count() == std::uint64_t{threads} * per_thread);
  CHECK(h.total(h.snapshot()) == std::uint64_t{threads} * per_thread);
  CHECK(h.max() == 99999.0);
}

TEST_CASE("latency histogram: add() of per-thread histograms equals one that recorded every value") {
  const std::uint64_t seed = fresh_seed();
  CAPTURE(seed);
  std::mt19937_64 rng(seed);
  std::lognormal_distribution<double> value(1.0, 2.0);
  zone::net::latency_histogram_ms parts[3], all, sum;
  for (int i = 0; i < 20000; ++i) {
    const double v = i % 97 == 0 ? 0.0 : value(rng);
    parts[i % 3].record(v);
    all.record(v);
  }
  sum.add(parts[0]);
  sum.add(parts[1]);
  sum.add(zone::net::latency_histogram_ms{});  // an empty one changes nothing
  sum.add(parts[2]);
  CHECK(sum.snapshot() == all.snapshot());
  CHECK(sum.count() == all.count());
  CHECK(sum.max() == all.max());
  CHECK(sum.sum() == doctest::Approx(all.sum()).epsilon(1e-9));
  for (const double q : {0.0, 0.5, 0.9, 0.99, 1.0}) CHECK(sum.percentile(q) == all.percentile(q));
}

}  // TEST_SUITE
