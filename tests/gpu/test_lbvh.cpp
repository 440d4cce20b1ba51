// The GPU LBVH finder against the brute-force reference and the CPU grid finder: every family and
// size with several option sets, deep trees (all Morton codes equal; a caterpillar of codes with
// many copies of each), stack limits forcing the overflow pass, tiny output buffers, empty and
// one-box sets, the zero-copy entry, CSR output, large sets and the stadium set. Part of test_gpu:
// without a CUDA device the executable exits with 77 before any test case (CTest: Skipped).
#include <doctest/doctest.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <span>
#include <stdexcept>
#include <string>

#include "../common/box_families.h"
#include "../common/device_or_skip.h"
#include "gpu/device.h"
#include "gpu/finders.h"
#include "gpu/lbvh.h"
#include "interest/interest.h"
#include "interest/thread_pool.h"

using namespace zone::interest;
using namespace zone::test;
namespace gpu = zone::gpu;

namespace {

/// Runs before main (static initialisation): no device, no tests.
const bool lbvh_device_present = zone::test::device_or_skip("test_gpu (lbvh)");

std::unique_ptr<pair_finder> make_lbvh(const gpu::lbvh_options& opt = {}) {
  std::string why;
  return made_or_fail(gpu::make_lbvh_finder(opt, &why), why);
}

std::string describe(const gpu::lbvh_options& o) {
  return "stack=" + std::to_string(o.stack_entries) + " large=" + (o.separate_large ? "1" : "0") +
         " init_pairs=" + std::to_string(o.initial_output_pairs);
}

/// Option sets every family runs with: default, a stack of 2 (most queries overflow), no large
/// boxes apart, a 1-pair initial output buffer.
std::vector<gpu::lbvh_options> option_sets(thread_pool* pool) {
  std::vector<gpu::lbvh_options> v(4);
  v[1].stack_entries = 2;
  v[2].separate_large = false;
  v[3].initial_output_pairs = 1;
  for (auto& o : v) {
    o.pool = pool;
    o.measure_depth = true;
  }
  return v;
}

/// A caterpillar of Morton codes: one point per code 0 and 2^m (m < 30) in a [0, 1024]^3 scene,
/// plus the far corner, each repeated `copies` times: a spine of ~31 internal nodes with an
/// index-split subtree of depth log2(copies) under each, the deepest tree 30-bit codes allow.
box_set caterpillar(std::uint32_t copies) {
  box_set s;
  auto point = [&](float x, float y, float z) {
    for (std::uint32_t c = 0; c < copies; ++c) s.push_back(box{{x, y, z}, {x, y, z}, 1, 1});
  };
  point(0.5f, 0.5f, 0.5f);  // code 0
  for (int m = 0; m < 30; ++m) {
    float q[3] = {0.5f, 0.5f, 0.5f};
    q[2 - m % 3] = static_cast<float>(1u << (m / 3)) + 0.5f;  // bit m of the code: axis 2 - m % 3, bit m / 3
    point(q[0], q[1], q[2]);
  }
  s.push_back(box{{0, 0, 0}, {0, 0, 0}, 1, 1});
  s.push_back(box{{1024, 1024, 1024}, {1024, 1024, 1024}, 1, 1});
  return s;
}

}  // namespace

TEST_SUITE("gpu.lbvh") {
  TEST_CASE("LBVH equals brute force: every family, size and option set") {
    thread_pool pool(4);
    brute_force_finder brute(&pool);
    const auto opts = option_sets(&pool);
    std::vector<std::unique_ptr<pair_finder>> finders;
    for (const auto& o : opts) finders.push_back(make_lbvh(o));
    bool overflow_seen = false;
    for_each_family_set(brute, all_families, finder_sizes, [&](const box_set& s, const pair_list& expected) {
      for (std::size_t k = 0; k < finders.size(); ++k) {
        CAPTURE(describe(opts[k]));
        CHECK(run(*finders[k], s) == expected);
        if (s.size() >= 2) {
          const auto* r = gpu::last_lbvh_report(*finders[k]);
          REQUIRE(r != nullptr);
          CHECK(r->pairs == expected.size());
          CHECK(r->max_depth <= 64);
          if (opts[k].stack_entries == 0) CHECK(r->stack_overflows == 0);
          if (r->stack_overflows > 0) overflow_seen = true;
        }
      }
    });
    CHECK(overflow_seen);  // the 2-entry stack did force the overflow pass
  }

  TEST_CASE("deep trees: 10^4 identical boxes (all Morton codes equal), in the tree and as large boxes") {
    thread_pool pool(4);
    box_set s;
    for (int i = 0; i < 10000; ++i) s.push_back(box{{3.5f, 3.5f, 3.5f}, {7.25f, 7.25f, 7.25f}, 1, 1});
    for (const bool separate : {false, true}) {
      for (const std::uint32_t stack : {0u, 3u}) {
        CAPTURE(separate);
        CAPTURE(stack);
        gpu::lbvh_options o;
        o.pool = &pool;
        o.separate_large = separate;
        o.stack_entries = stack;
        o.measure_depth = true;
        auto finder = make_lbvh(o);
        const pair_list out = run(*finder, s);
        REQUIRE(out.size() == 10000ull * 9999 / 2);
        CHECK(every_pair_in_order(out, 10000));
        const auto* r = gpu::last_lbvh_report(*finder);
        if (separate) {
          CHECK(r->large_boxes == 10000);  // each expected to overlap all: the brute pass takes them
        } else {
          CHECK(r->large_boxes == 0);
          CHECK(r->tree_boxes == 10000);
          // Equal codes split by position: a balanced tree, depth about log2(10^4).
          CHECK(r->max_depth >= 14);
          CHECK(r->max_depth <= 20);
          if (stack == 0) CHECK(r->stack_overflows == 0);
          if (stack == 3) CHECK(r->stack_overflows > 0);
        }
      }
    }
  }

  TEST_CASE("deep trees: a caterpillar of Morton codes with 256 copies of each point; stack limits") {
    thread_pool pool(4);
    brute_force_finder brute(&pool);
    const box_set s = caterpillar(256);
    const pair_list expected = run(brute, s);
    REQUIRE(expected.size() == 31ull * 256 * 255 / 2);
    for (const std::uint32_t stack : {0u, 1u, 2u, 4u, 7u, 8u, 9u, 16u, 64u, 1000u}) {
      CAPTURE(stack);
      gpu::lbvh_options o;
      o.pool = &pool;
      o.stack_entries = stack;
      o.measure_depth = true;
      auto finder = make_lbvh(o);
      CHECK(run(*finder, s) == expected);
      const auto* r = gpu::last_lbvh_report(*finder);
      CHECK(r->large_boxes == 0);
      CHECK(r->max_depth >= 36);  // ~30 spine levels + log2(256) within a point's copies
      CHECK(r->max_depth <= 64);
      // A query pushes once per level where both children overlap it: about log2(256) levels.
      if (stack == 0 || stack >= 9) CHECK(r->stack_overflows == 0);
      if (stack >= 1 && stack <= 4) CHECK(r->stack_overflows > 0);
    }
  }

  TEST_CASE("tiny output buffers and repeated calls: buffers grow, no pair lost, same order") {
    thread_pool pool(3);
    brute_force_finder brute(&pool);
    for_each_family_set(brute, dense_families, {3000}, [&](const box_set& s, const pair_list& expected) {
      REQUIRE(!expected.empty());
      gpu::lbvh_options o;
      o.pool = &pool;
      o.initial_output_pairs = 1;
      auto finder = make_lbvh(o);
      pair_list first, second;
      REQUIRE_FALSE(finder->find(s, first).has_value());
      REQUIRE_FALSE(finder->find(s, second).has_value());
      CHECK(first == second);  // deterministic order
      sort_canonical(first, s.size());
      CHECK(first == expected);
    });
  }

  TEST_CASE("empty, one box, two boxes; invalid boxes rejected with the box named") {
    auto finder = make_lbvh();
    pair_list out{{0, 1}};
    REQUIRE_FALSE(finder->find(box_set{}, out).has_value());
    CHECK(out.empty());
    box_set one;
    one.push_back(box{{0, 0, 0}, {1, 1, 1}, 1, 1});
    out = {{0, 1}};
    REQUIRE_FALSE(finder->find(one, out).has_value());
    CHECK(out.empty());
    box_set two = one;
    two.push_back(box{{1, 1, 1}, {2, 2, 2}, 1, 1});  // touching corners intersect
    REQUIRE_FALSE(finder->find(two, out).has_value());
    CHECK(out == pair_list{{0, 1}});
    two.category[1] = 2;  // (1 & 2) | (2 & 1) == 0: filtered
    two.mask[1] = 2;
    REQUIRE_FALSE(finder->find(two, out).has_value());
    CHECK(out.empty());
    std::span<const id_pair> view;
    REQUIRE_FALSE(gpu::find_lbvh_view(*finder, one, view).has_value());
    CHECK(view.empty());

    box_set s = generate_uniform(10, 3);
    s.lo_y[4] = std::nanf("");
    out = {{0, 1}};
    auto err = finder->find(s, out);
    REQUIRE(err.has_value());
    CHECK(err->index == 4);
    CHECK(out.empty());
    box_set big = generate_uniform(200000, fresh_seed());
    big.hi_x[150001] = big.lo_x[150001] - 1;
    err = gpu::find_lbvh_view(*finder, big, view);
    REQUIRE(err.has_value());
    CHECK(err->index == 150001);
    CHECK(view.empty());
    big.hi_x[150001] = big.lo_x[150001] + 1;
    big.lo_z[7] = INFINITY;
    err = gpu::find_lbvh_view(*finder, big, view);
    REQUIRE(err.has_value());
    CHECK(err->index == 7);
    grid_finder grid;
    CHECK_THROWS_AS((void)gpu::find_lbvh_view(grid, big, view), std::invalid_argument);
  }

  TEST_CASE("find_lbvh_view and find give the same pairs in the same order; CSR equals the reference's") {
    thread_pool pool(4);
    gpu::lbvh_options o;
    o.pool = &pool;
    auto finder = make_lbvh(o);
    grid_finder grid(&pool);
    for_each_named_set({"gaussian", "uniform", "mmo", "doc:2"}, 200000, [&](const box_set& s) {
      pair_list out;
      REQUIRE_FALSE(finder->find(s, out).has_value());
      std::span<const id_pair> view;
      REQUIRE_FALSE(gpu::find_lbvh_view(*finder, s, view).has_value());
      CHECK(pair_list(view.begin(), view.end()) == out);
      const pair_list expected = run(grid, s);
      const adjacency a = to_adjacency(out, s.size());
      const adjacency b = to_adjacency(expected, s.size());
      CHECK(a.offsets == b.offsets);
      CHECK(a.neighbors == b.neighbors);
      sort_canonical(out, s.size());
      CHECK(out == expected);
    });
  }

  TEST_CASE("large sets and the stadium against the CPU grid finder; the auto finder on them") {
    thread_pool pool(0);
    grid_finder grid(&pool);
    gpu::lbvh_options o;
    o.pool = &pool;
    auto finder = make_lbvh(o);
    auto automatic = gpu::make_finder(gpu::finder_backend::auto_select, &pool);
    REQUIRE(automatic);
    for_each_named_set({"gaussian", "mmo", "doc:10", "uniform"}, 1000000, [&](const box_set& s) {
      const pair_list expected = run(grid, s);
      CHECK(run(*finder, s) == expected);
      CHECK(run(*automatic, s) == expected);
    });
    const auto seed = fresh_seed();
    CAPTURE(seed);
    const box_set s = uniform_with_spanning(1000000, seed, 0.3);
    const pair_list expected = run(grid, s);
    CHECK(run(*finder, s) == expected);
    CHECK(gpu::last_lbvh_report(*finder)->large_boxes == 3);
    CHECK(run(*automatic, s) == expected);
    gpu::lbvh_options in_tree = o;
    in_tree.separate_large = false;
    auto all_in_tree = make_lbvh(in_tree);
    CHECK(run(*all_in_tree, s) == expected);
    CHECK(gpu::last_lbvh_report(*all_in_tree)->large_boxes == 0);
  }
}
