// The fast CPU finder against the brute-force reference, and the reference against the definition.
#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <random>
#include <set>

#include "../common/box_families.h"
#include "interest/interest.h"
#include "interest/thread_pool.h"

using namespace zone::interest;
using namespace zone::test;

namespace {

/// The definition, written as plainly as possible: every i < j, the contract's test.
pair_list definition_pairs(const box_set& s) {
  pair_list out;
  for (std::size_t i = 0; i < s.size(); ++i) {
    for (std::size_t j = i + 1; j < s.size(); ++j) {
      const box a = s.get(i), b = s.get(j);
      bool hit = true;
      for (int d = 0; d < 3; ++d) hit = hit && a.lo[d] <= b.hi[d] && b.lo[d] <= a.hi[d];
      if (hit && ((a.category & b.mask) != 0 || (b.category & a.mask) != 0)) {
        out.push_back({static_cast<box_id>(i), static_cast<box_id>(j)});
      }
    }
  }
  return out;
}

}  // namespace

TEST_SUITE("interest.finders") {
  TEST_CASE("brute force equals the plain definition (odd and even N, all families)") {
    thread_pool pool(3);
    brute_force_finder brute(&pool);
    for_each_family_set(brute, all_families, {0, 1, 2, 3, 4, 5, 10, 11, 64, 101, 256},
                        [&](const box_set& s, const pair_list& found) { CHECK(found == definition_pairs(s)); });
  }

  TEST_CASE("grid finder equals brute force on every family and many sizes") {
    thread_pool pool(4);
    brute_force_finder brute(&pool);
    grid_finder grid(&pool);
    for_each_family_set(brute, all_families, finder_sizes, [&](const box_set& s, const pair_list& expected) {
      CHECK(run(grid, s) == expected);
      if (s.size() >= 2) CHECK(grid.stats().cells >= 1);
    });
  }

  TEST_CASE("grid finder is exact whatever the cell size") {
    thread_pool pool(2);
    brute_force_finder brute(&pool);
    for_each_family_set(brute, cell_edge_families, {1500}, [&](const box_set& s, const pair_list& expected) {
      for (const double edge : {0.25, 1.0, 3.0, 7.5, 50.0, 1e4}) {
        CAPTURE(edge);
        grid_finder_options opt;
        opt.fixed_cell_edge = edge;
        grid_finder grid(&pool, opt);
        CHECK(run(grid, s) == expected);
      }
      for (const double w : {1.0, 2.0, 32.0, 1000.0}) {
        CAPTURE(w);
        grid_finder_options opt;
        opt.min_boxes_per_cell = w;
        grid_finder grid(&pool, opt);
        CHECK(run(grid, s) == expected);
      }
    });
  }

  TEST_CASE("large boxes are handled apart and stay exact") {
    thread_pool pool(2);
    brute_force_finder brute(&pool);
    grid_finder_options opt;
    opt.large_box_min_cells = 2;  // force many boxes onto the large-box path
    opt.large_box_alpha_factor = 1.0;
    grid_finder grid(&pool, opt);
    for_each_family_set(brute, {family::huge_over_tiny, family::long_thin, family::uniform, family::mask_mix}, {1200},
                        [&](const box_set& s, const pair_list& expected) {
                          CHECK(run(grid, s) == expected);
                          CHECK(grid.stats().large_boxes > 0);
                        });
  }

  TEST_CASE("a few world-spanning boxes over many small ones") {
    thread_pool pool(2);
    const auto seed = fresh_seed();
    CAPTURE(seed);
    const box_set s = uniform_with_spanning(20000, seed, 0.3);
    grid_finder grid(&pool);
    const pair_list got = run(grid, s);
    CHECK(grid.stats().large_boxes == 3);
    // Every small box pairs with each of the 3 spanning boxes; those 3 pair among themselves.
    brute_force_finder brute(&pool);
    CHECK(got == run(brute, s));
    CHECK(got.size() >= 3 * 20000 + 3);
  }

  TEST_CASE("same output for 1, 2 and many threads, and across repeated calls") {
    const auto seed = fresh_seed();
    CAPTURE(seed);
    const box_set s = generate_gaussian(30000, seed);
    pair_list single;
    grid_finder g1(nullptr);
    REQUIRE_FALSE(g1.find(s, single).has_value());
    for (const unsigned threads : {1u, 2u, 7u}) {
      thread_pool pool(threads);
      grid_finder g(&pool);
      pair_list out;
      REQUIRE_FALSE(g.find(s, out).has_value());
      CHECK(out == single);  // identical order, not only the same set
      REQUIRE_FALSE(g.find(s, out).has_value());
      CHECK(out == single);
    }
  }

  TEST_CASE("the generators give the paper's pair counts") {
    thread_pool pool(2);
    grid_finder grid(&pool);
    pair_list out;
    // Uniform 1e5: about 5.2e3 pairs (N^2/2 * (101/1e4)^3 minus edge effects).
    REQUIRE_FALSE(grid.find(generate_uniform(100000, 1), out).has_value());
    CHECK(out.size() > 4500);
    CHECK(out.size() < 5800);
    // DoC 1 at 1e5: the sum of volumes equals the domain volume.
    const double k = edge_scale_for_doc(100000, 1.0);
    CHECK(100000 * std::pow(50.5 * k, 3) == doctest::Approx(1e12).epsilon(1e-9));
  }

  TEST_CASE("MMO-like set: only AOI-vs-presence pairs count") {
    thread_pool pool(2);
    const box_set s = generate_mmo(6000, fresh_seed());
    REQUIRE(s.size() == 6000);
    grid_finder grid(&pool);
    brute_force_finder brute(&pool);
    const pair_list got = run(grid, s);
    CHECK(got == run(brute, s));
    CHECK(!got.empty());
    CHECK(std::all_of(got.begin(), got.end(), [&](const id_pair& p) {
      return (s.category[p.a] == category_bits::aoi) != (s.category[p.b] == category_bits::aoi);
    }));
    // Visibility: an AOI box pairs only with presence boxes of a class its mask holds (stealth
    // hides from all but detectors), and some stealthy presences exist and are hidden somewhere.
    std::size_t stealth_seen = 0;
    CHECK(std::all_of(got.begin(), got.end(), [&](const id_pair& p) {
      const box_id aoi = s.category[p.a] == category_bits::aoi ? p.a : p.b;
      const box_id presence = aoi == p.a ? p.b : p.a;
      stealth_seen += s.category[presence] == category_bits::stealth ? 1 : 0;
      return (s.mask[aoi] & s.category[presence]) != 0;
    }));
    box_set all_see = s;
    for (std::size_t i = 0; i < all_see.size(); i += 2) all_see.mask[i] |= category_bits::stealth;
    pair_list with_detectors;
    REQUIRE_FALSE(grid.find(all_see, with_detectors).has_value());
    CHECK(with_detectors.size() > got.size());  // stealthy presences were hidden from some AOIs
    CHECK(stealth_seen > 0);                    // and seen by the detectors
  }

  TEST_CASE("invalid boxes are rejected with the box named") {
    grid_finder grid(nullptr);
    brute_force_finder brute(nullptr);
    for (pair_finder* f : {static_cast<pair_finder*>(&grid), static_cast<pair_finder*>(&brute)}) {
      box_set s = generate_uniform(10, 3);
      pair_list out{{0, 1}};
      s.lo_y[4] = std::nanf("");
      auto err = f->find(s, out);
      REQUIRE(err.has_value());
      CHECK(err->index == 4);
      CHECK(err->message.find("box 4") != std::string::npos);
      CHECK(err->message.find("NaN") != std::string::npos);
      CHECK(out.empty());

      s = generate_uniform(10, 3);
      s.hi_z[7] = std::numeric_limits<float>::infinity();
      err = f->find(s, out);
      REQUIRE(err.has_value());
      CHECK(err->index == 7);
      CHECK(err->message.find("infinite") != std::string::npos);

      s = generate_uniform(10, 3);
      s.lo_x[2] = s.hi_x[2] + 1;
      err = f->find(s, out);
      REQUIRE(err.has_value());
      CHECK(err->index == 2);
      CHECK(err->message.find("lo.x") != std::string::npos);

      // Values that differ only past the 6th digit are shown exactly.
      s = generate_uniform(10, 3);
      s.lo_z[5] = 1.0000001f;
      s.hi_z[5] = 1.0f;
      err = f->find(s, out);
      REQUIRE(err.has_value());
      CHECK(err->message.find("1.0000001 > hi.z = 1") != std::string::npos);
    }
  }

  TEST_CASE("sort_canonical and to_adjacency") {
    pair_list p{{3, 1}, {0, 2}, {1, 2}, {0, 1}};
    sort_canonical(p, 4);
    CHECK(p == pair_list{{0, 1}, {0, 2}, {1, 2}, {1, 3}});
    const adjacency adj = to_adjacency(p, 5);
    REQUIRE(adj.box_count() == 5);
    CHECK(adj.offsets == std::vector<std::uint64_t>{0, 2, 5, 7, 8, 8});
    CHECK(adj.neighbors == std::vector<box_id>{1, 2, 0, 2, 3, 0, 1, 1});
    // Large random lists: the bucket path and std::sort agree.
    std::mt19937_64 rng(fresh_seed());
    pair_list big;
    for (int i = 0; i < 50000; ++i) {
      const auto a = static_cast<box_id>(rng() % 1000), b = static_cast<box_id>(rng() % 1000);
      if (a != b) big.push_back({a, b});
    }
    pair_list expect = big;
    for (auto& q : expect) {
      if (q.a > q.b) std::swap(q.a, q.b);
    }
    std::sort(expect.begin(), expect.end());
    pair_list big_parallel = big;
    sort_canonical(big, 1000);
    CHECK(big == expect);
    thread_pool pool(3);
    sort_canonical(big_parallel, 1000, &pool);
    CHECK(big_parallel == expect);
  }

  TEST_CASE("plan follows Eq. 6: f >= W at the planned edge, f < W just below it") {
    const box_set s = generate_uniform(50000, fresh_seed());
    grid_finder_options opt;
    opt.min_boxes_per_cell = 32;
    const grid_plan plan = plan_grid(s, opt);
    const double f = 50000.0 * plan.alpha / static_cast<double>(plan.cell_count());
    CHECK(f >= 32.0);
    opt.fixed_cell_edge = plan.cell_edge * 0.9;
    const grid_plan smaller = plan_grid(s, opt);
    CHECK(50000.0 * smaller.alpha / static_cast<double>(smaller.cell_count()) < 32.0);
  }
}
