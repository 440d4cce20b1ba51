// The shared measuring helpers (interest/measure.h): median and nearest-rank quantile against a
// sort-and-count reference on fresh random samples, and their edge cases.
#include <doctest/doctest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <random>
#include <thread>
#include <vector>

#include "../common/seeds.h"
#include "interest/measure.h"

TEST_SUITE("measure") {
  TEST_CASE("quantile: edge cases") {
    CHECK(zone::quantile({}, 0.5) == 0.0);
    CHECK(zone::quantile({7.0}, 0.0) == 7.0);
    CHECK(zone::quantile({7.0}, 1.0) == 7.0);
    const std::vector<double> v{5, 1, 4, 2, 3};
    CHECK(zone::quantile(v, 0.0) == 1.0);
    CHECK(zone::quantile(v, -1.0) == 1.0);
    CHECK(zone::quantile(v, 1.0) == 5.0);
    CHECK(zone::quantile(v, 2.0) == 5.0);
    CHECK(zone::quantile(v, 0.5) == 3.0);  // rank ceil(2.5) = 3
    CHECK(zone::quantile(v, 0.6) == 3.0);  // rank 3: exactly 60% at or below
    CHECK(zone::quantile(v, 0.61) == 4.0);
    // 100 values 1..100: p99 is 99, p50 is 50.
    std::vector<double> h(100);
    for (int i = 0; i < 100; ++i) h[i] = 100 - i;
    CHECK(zone::quantile(h, 0.99) == 99.0);
    CHECK(zone::quantile(h, 0.5) == 50.0);
  }

  TEST_CASE("quantile: the smallest value with at least a share q at or below it (random samples)") {
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    std::mt19937_64 rng(seed);
    std::uniform_int_distribution<int> size(1, 300), value(-50, 50);
    std::uniform_real_distribution<double> share(0.0, 1.0);
    for (int round = 0; round < 200; ++round) {
      std::vector<double> v(static_cast<std::size_t>(size(rng)));
      for (double& x : v) x = value(rng);  // many ties
      const double q = round % 10 == 0 ? 1.0 : share(rng);
      const double got = zone::quantile(v, q);
      const auto n = static_cast<double>(v.size());
      const auto at_or_below = [&](double x) {
        return static_cast<double>(std::count_if(v.begin(), v.end(), [&](double y) { return y <= x; }));
      };
      CHECK(std::find(v.begin(), v.end(), got) != v.end());
      CHECK(at_or_below(got) >= q * n - 1e-9);
      for (const double x : v) {
        if (x < got) CHECK(at_or_below(x) < q * n - 1e-9);
      }
    }
  }

  TEST_CASE("median: middle value, mean of the two middle values, 0 when empty") {
    CHECK(zone::median({}) == 0.0);
    CHECK(zone::median({3.0}) == 3.0);
    CHECK(zone::median({3.0, 1.0, 2.0}) == 2.0);
    CHECK(zone::median({4.0, 1.0, 3.0, 2.0}) == 2.5);
  }

  TEST_CASE("ms_since: grows with the steady clock") {
    const auto t0 = std::chrono::steady_clock::now();
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
    const double ms = zone::ms_since(t0);
    CHECK(ms >= 5.0);
    CHECK(ms < 60000.0);
  }
}
