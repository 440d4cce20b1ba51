// The GPU PBIG finder against the brute-force reference and the CPU grid finder, for every
// combination of its three optimisations, with output buffers forced tiny (overflow path), and on
// degenerate sets at full size. Without a CUDA device the executable prints why and exits with 77
// before any test case runs, so CTest reports it as skipped, never passed.
#include <doctest/doctest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <limits>
#include <random>
#include <span>
#include <stdexcept>
#include <string>

#include "../common/box_families.h"
#include "../common/device_or_skip.h"
#include "gpu/pbig.h"
#include "interest/interest.h"
#include "interest/thread_pool.h"

using namespace zone::interest;
using namespace zone::test;
namespace gpu = zone::gpu;

namespace {

/// Runs before main (static initialisation): no device, no tests.
const bool device_present = zone::test::device_or_skip("test_gpu");

std::unique_ptr<pair_finder> make_gpu(const gpu::pbig_options& opt = {}) {
  std::string why;
  return made_or_fail(gpu::make_pbig_finder(opt, &why), why);
}

/// The 8 combinations of (load balancing, compression, pipelining) with the paper's output path;
/// with `direct`, the same 8 with direct output too (compression only changes its initial buffer
/// size there: the direct output checks into plain chunks).
std::vector<gpu::pbig_options> all_combinations(thread_pool* pool, std::size_t initial_pairs = 0, bool direct = false) {
  std::vector<gpu::pbig_options> v;
  for (int mask = 0; mask < (direct ? 16 : 8); ++mask) {
    gpu::pbig_options o;
    o.load_balancing = (mask & 1) != 0;
    o.compression = (mask & 2) != 0;
    o.pipelining = (mask & 4) != 0;
    o.direct_output = mask >= 8;
    o.initial_output_pairs = initial_pairs;
    o.decode_pool = pool;
    v.push_back(o);
  }
  return v;
}

std::string describe(const gpu::pbig_options& o) {
  return std::string("lb=") + (o.load_balancing ? "1" : "0") + " comp=" + (o.compression ? "1" : "0") +
         " pipe=" + (o.pipelining ? "1" : "0") + " direct=" + (o.direct_output ? "1" : "0") + " init_pairs=" + std::to_string(o.initial_output_pairs);
}

}  // namespace

TEST_SUITE("gpu.pbig") {
  TEST_CASE("GPU finder equals brute force and the CPU grid finder: every family, size and option set") {
    thread_pool pool(4);
    brute_force_finder brute(&pool);
    grid_finder grid(&pool);
    std::vector<std::unique_ptr<pair_finder>> finders;
    const auto combos = all_combinations(&pool, 0, /*direct=*/true);
    for (const auto& o : combos) finders.push_back(make_gpu(o));
    for_each_family_set(brute, all_families, finder_sizes, [&](const box_set& s, const pair_list& expected) {
      CHECK(run(grid, s) == expected);
      for (std::size_t k = 0; k < finders.size(); ++k) {
        CAPTURE(describe(combos[k]));
        CHECK(run(*finders[k], s) == expected);
      }
    });
  }

  TEST_CASE("tiny output buffers: every overflowing batch is re-run, no pair lost") {
    thread_pool pool(3);
    brute_force_finder brute(&pool);
    const auto combos = all_combinations(&pool, 1, /*direct=*/true);
    for_each_family_set(brute, dense_families, {3000}, [&](const box_set& s, const pair_list& expected) {
      REQUIRE(!expected.empty());
      for (const auto& o : combos) {
        CAPTURE(describe(o));
        auto finder = make_gpu(o);
        CHECK(run(*finder, s) == expected);
        const auto* report = gpu::last_pbig_report(*finder);
        REQUIRE(report != nullptr);
        CHECK(report->reruns >= 1);
        CHECK(report->pairs == expected.size());
        CHECK(run(*finder, s) == expected);  // again, with the grown buffers
      }
    });
  }

  TEST_CASE("many batches with overflowing buffers: pipeline re-runs keep every pair and the order") {
    thread_pool pool(8);
    const auto seed = fresh_seed();
    CAPTURE(seed);
    const box_set s = generate_gaussian(1000000, seed);  // ~1.2e7 pairs, 11 batches
    pair_list reference[2];
    for (const bool lb : {false, true}) {
      auto direct = make_gpu(gpu::pbig_options{.load_balancing = lb, .decode_pool = &pool});
      REQUIRE_FALSE(direct->find(s, reference[lb]).has_value());
      REQUIRE(gpu::last_pbig_report(*direct)->batches > 4);
    }
    for (const auto& o : all_combinations(&pool, 20000, /*direct=*/true)) {
      CAPTURE(describe(o));
      auto finder = make_gpu(o);
      pair_list out;
      REQUIRE_FALSE(finder->find(s, out).has_value());
      const auto* report = gpu::last_pbig_report(*finder);
      CHECK(report->batches > 4);
      CHECK(report->reruns >= 1);
      CHECK(out == reference[o.load_balancing]);  // same pairs, same order as the direct output
    }
    pair_list cpu;
    grid_finder grid(&pool);
    REQUIRE_FALSE(grid.find(s, cpu).has_value());
    sort_canonical(cpu, s.size());
    sort_canonical(reference[1], s.size());
    CHECK(reference[1] == cpu);
  }

  TEST_CASE("exact whatever the cell size") {
    thread_pool pool(2);
    brute_force_finder brute(&pool);
    for_each_family_set(brute, cell_edge_families, {1500}, [&](const box_set& s, const pair_list& expected) {
      for (const double edge : {0.25, 1.0, 3.0, 7.5, 50.0, 1e4}) {
        for (const bool direct : {false, true}) {
          CAPTURE(edge);
          CAPTURE(direct);
          gpu::pbig_options o;
          o.fixed_cell_edge = edge;
          o.decode_pool = &pool;
          o.direct_output = direct;
          auto finder = make_gpu(o);
          CHECK(run(*finder, s) == expected);
        }
      }
      for (const double w : {1.0, 2.0, 1000.0}) {
        CAPTURE(w);
        gpu::pbig_options o;
        o.min_boxes_per_cell = w;
        o.decode_pool = &pool;
        auto finder = make_gpu(o);
        CHECK(run(*finder, s) == expected);
      }
    });
  }

  TEST_CASE("deterministic: same order across calls, finders, pipelining and compression") {
    thread_pool pool(4);
    const auto seed = fresh_seed();
    CAPTURE(seed);
    const box_set s = generate_gaussian(200000, seed);
    for (const bool lb : {false, true}) {
      CAPTURE(lb);
      pair_list first;
      for (const int mode : {0, 1, 2}) {  // plain, compressed, direct
        for (const bool pipe : {false, true}) {
          gpu::pbig_options o;
          o.load_balancing = lb;
          o.compression = mode == 1;
          o.direct_output = mode == 2;
          o.pipelining = pipe;
          o.decode_pool = &pool;
          o.initial_output_pairs = 50000;  // several batches overflow: re-runs must not change the order
          auto finder = make_gpu(o);
          pair_list out;
          REQUIRE_FALSE(finder->find(s, out).has_value());
          if (first.empty()) first = out;
          CHECK(out == first);
          REQUIRE_FALSE(finder->find(s, out).has_value());
          CHECK(out == first);
        }
      }
      pair_list cpu;
      grid_finder grid(&pool);
      REQUIRE_FALSE(grid.find(s, cpu).has_value());
      sort_canonical(cpu, s.size());
      sort_canonical(first, s.size());
      CHECK(first == cpu);
    }
  }

  TEST_CASE("plan: Eq. 6 holds at the planned edge, and the plan is reused while the statistics hold") {
    thread_pool pool(2);
    const box_set s = generate_uniform(300000, fresh_seed());
    for (const bool cost_aware : {false, true}) {
      CAPTURE(cost_aware);
      gpu::pbig_options o;
      o.decode_pool = &pool;
      o.cost_aware_plan = cost_aware;
      auto finder = make_gpu(o);
      pair_list out;
      REQUIRE_FALSE(finder->find(s, out).has_value());
      const auto* report = gpu::last_pbig_report(*finder);
      REQUIRE(report != nullptr);
      CHECK_FALSE(report->plan_reused);
      const double f = 300000.0 * report->alpha / static_cast<double>(finder->stats().cells);
      CHECK(f >= 32.0);             // Eq. 6's constraint holds for every candidate edge
      if (!cost_aware) CHECK(f < 64.0);  // the paper's edge: the smallest with f >= W
      const double edge = finder->stats().cell_edge;
      const pair_list first = out;
      REQUIRE_FALSE(finder->find(s, out).has_value());
      CHECK(report->plan_reused);
      CHECK(finder->stats().cell_edge == edge);
      CHECK(out == first);
      // A different distribution: planned afresh.
      REQUIRE_FALSE(finder->find(generate_uniform(300000, 7, 3.0), out).has_value());
      CHECK_FALSE(report->plan_reused);
      o.reuse_plan = false;
      auto fresh = make_gpu(o);
      REQUIRE_FALSE(fresh->find(s, out).has_value());
      CHECK(fresh->stats().cell_edge == edge);  // the same plan without reuse
      REQUIRE_FALSE(fresh->find(s, out).has_value());
      CHECK_FALSE(gpu::last_pbig_report(*fresh)->plan_reused);
      CHECK(out == first);
    }
  }

  TEST_CASE("cost-aware plan: never below Eq. 6's edge, same pairs as pure Eq. 6 and the CPU finder") {
    thread_pool pool(0);
    grid_finder grid(&pool);
    // Large boxes over small cells (DoC 10), clustered, uniform, identical, thin, and the families.
    std::vector<std::pair<std::string, box_set>> sets;
    const auto seed = fresh_seed();
    CAPTURE(seed);
    sets.emplace_back("uniform 2e5", generate_uniform(200000, seed));
    sets.emplace_back("gaussian 2e5", generate_gaussian(200000, seed + 1));
    sets.emplace_back("doc:10 2e5", *generate_named("doc:10", 200000, seed + 2));
    sets.emplace_back("doc:1 2e5", *generate_named("doc:1", 200000, seed + 3));
    sets.emplace_back("mmo 1e5", *generate_named("mmo", 100000, seed + 4));
    {
      box_set same;
      for (int i = 0; i < 5000; ++i) same.push_back(box{{3.5f, 3.5f, 3.5f}, {7.25f, 7.25f, 7.25f}, 1, 1});
      for (int i = 0; i < 2000; ++i) {
        const float x = static_cast<float>(i % 40) * 0.5f;
        same.push_back(box{{x, x, x}, {x + 0.25f, x + 0.25f, x + 0.25f}, 1, 1});
      }
      sets.emplace_back("identical and tiny", std::move(same));
    }
    {
      rng_box_maker r(seed + 5);
      box_set thin;
      for (int i = 0; i < 100000; ++i) thin.push_back(r.rod(1e4f, 2, -500, 1e4f, 200, 4000));
      sets.emplace_back("thin rods 1e5", std::move(thin));
    }
    for (const family f : all_families) sets.emplace_back(family_name(f) + " 2e4", make_family(f, 20000, seed + 6));
    int larger = 0;
    const std::size_t named = 7;  // the sets above the families: real scenes, whose plan is reused
    for (std::size_t k = 0; k < sets.size(); ++k) {
      const auto& [name, s] = sets[k];
      CAPTURE(name);
      const pair_list expected = run(grid, s);
      for (const bool direct : {true, false}) {
        if (!direct && k >= 3) continue;  // the paper's output path: on the first three sets only (time)
        CAPTURE(direct);
        auto eq6 = make_gpu(gpu::pbig_options{.decode_pool = &pool, .direct_output = direct, .cost_aware_plan = false});
        auto cost = make_gpu(gpu::pbig_options{.decode_pool = &pool, .direct_output = direct, .cost_aware_plan = true});
        CHECK(run(*eq6, s) == expected);
        CHECK(run(*cost, s) == expected);
        CHECK(run(*cost, s) == expected);  // the reused plan
        if (k < named) CHECK(gpu::last_pbig_report(*cost)->plan_reused);
        const double e0 = eq6->stats().cell_edge, e1 = cost->stats().cell_edge;
        CAPTURE(e0);
        CAPTURE(e1);
        CHECK(e1 >= e0);
        CHECK(e1 <= e0 * 4.0 * (1 + 1e-9));
        if (direct && e1 > e0) ++larger;
      }
    }
    MESSAGE("sets where the cost-aware plan chose a larger edge than Eq. 6: " << larger << " of " << sets.size());
    CHECK(larger >= 1);  // at least the DoC 10 set (boxes larger than Eq. 6's cells)
  }

  TEST_CASE("single queue: sizes from the last call; outgrown grids re-queued, overflow re-run, no pair lost") {
    thread_pool pool(4);
    grid_finder grid(&pool);
    const auto seed = fresh_seed();
    CAPTURE(seed);
    // Grows and shrinks: the same size again twice (fits), N x 4 (more cells), small again
    // (capacity far above the grid), a full cell (past the one-kernel sort), small, boxes handled
    // apart, more pairs on the same grid, then small and large alternating.
    struct step {
      box_set set;
      const char* what;
    };
    std::vector<step> steps;
    steps.push_back({generate_uniform(20000, seed), "uniform 2e4"});
    steps.push_back({generate_uniform(20000, seed + 1), "uniform 2e4, other seed"});
    steps.push_back({generate_uniform(20000, seed + 2), "uniform 2e4, third seed"});
    steps.push_back({generate_uniform(80000, seed + 3), "uniform 8e4"});
    steps.push_back({generate_uniform(3000, seed + 4), "uniform 3e3"});
    steps.push_back({make_family(family::identical, 3000, seed + 5), "identical 3e3"});
    steps.push_back({generate_uniform(3000, seed + 6), "uniform 3e3 after identical"});
    box_set spanning = uniform_with_spanning(6000, seed + 7);
    steps.push_back({spanning, "uniform 6e3 + 3 world-spanning boxes"});
    // The same geometry three times (the same plan and grid): 80% of the masks 0, again, then
    // every mask 1 (about 2.8x the pairs: past the output capacity of the last call).
    box_set masked = generate_uniform(20000, seed + 8, 2.0);
    const box_set unmasked = masked;
    for (std::size_t i = 0; i < masked.size(); ++i) masked.mask[i] = i % 5 == 0 ? 1u : 0u;
    steps.push_back({masked, "uniform 2e4 x2, masked, after large boxes"});
    steps.push_back({masked, "the same again"});
    steps.push_back({unmasked, "the same geometry unmasked"});
    for (int k = 0; k < 6; ++k) {
      steps.push_back({generate_uniform(k % 2 == 0 ? 4000 : 150000, seed + 10 + k), k % 2 == 0 ? "small" : "large"});
    }
    std::vector<pair_list> cpu;
    for (const auto& st : steps) cpu.push_back(run(grid, st.set));
    for (const std::size_t initial : {std::size_t{0}, std::size_t{1}}) {
      for (int mask = 0; mask < 4; ++mask) {
        gpu::pbig_options o;
        o.load_balancing = (mask & 1) != 0;
        o.compression = (mask & 2) != 0;
        o.initial_output_pairs = initial;
        o.decode_pool = &pool;
        CAPTURE(describe(o));
        auto finder = make_gpu(o);
        o.single_queue = false;
        auto reference = make_gpu(o);
        const auto* report = gpu::last_pbig_report(*finder);
        int queued = 0, requeued = 0;
        for (std::size_t i = 0; i < steps.size(); ++i) {
          CAPTURE(i);
          CAPTURE(steps[i].what);
          pair_list got, want;
          REQUIRE_FALSE(finder->find(steps[i].set, got).has_value());
          REQUIRE_FALSE(reference->find(steps[i].set, want).has_value());
          CHECK_FALSE(gpu::last_pbig_report(*reference)->single_queue);
          CHECK(got == want);  // same pairs, same order as read-back sizing
          CHECK(report->pairs == got.size());
          sort_canonical(got, steps[i].set.size());
          CHECK(got == cpu[i]);
          queued += report->single_queue && !report->requeued ? 1 : 0;
          requeued += report->requeued ? 1 : 0;
          if (i == 0) CHECK_FALSE(report->single_queue);  // no last call
          if (i == 1 || i == 9 || i == 10) CHECK((report->single_queue && !report->requeued));
          if (i == 3 || i == 5 || i == 7) CHECK(report->requeued);  // more cells, a full cell, large boxes
          if (i == 6 || i == 8) CHECK_FALSE(report->single_queue);  // the last call was not small
        }
        CHECK(queued >= 3);
        CHECK(requeued >= 3);
        // On a fresh finder, steps 8-10 alone: the unmasked call has ~2.8x the pairs of the masked
        // ones on the same grid, so with tiny initial buffers its chunks overflow inside a single
        // queue (re-run by finish_direct) and its pairs outrun the prefetched copy.
        o.single_queue = true;
        auto fresh = make_gpu(o);
        for (const std::size_t i : {std::size_t{8}, std::size_t{9}, std::size_t{10}}) {
          CAPTURE(i);
          pair_list got;
          REQUIRE_FALSE(fresh->find(steps[i].set, got).has_value());
          sort_canonical(got, steps[i].set.size());
          CHECK(got == cpu[i]);
        }
        const auto* last = gpu::last_pbig_report(*fresh);
        CHECK((last->single_queue && !last->requeued));
        if (initial == 1) CHECK(last->reruns >= 1);  // an overflowing chunk buffer inside a single queue
      }
    }
  }

  TEST_CASE("single queue: an invalid pinned set is reported from the one read-back, the next call unaffected") {
    thread_pool pool(4);
    gpu::pbig_options o;
    o.decode_pool = &pool;
    auto finder = make_gpu(o);
    const auto seed = fresh_seed();
    CAPTURE(seed);
    box_set s = generate_uniform(30000, seed);
    const pair_list expected = [&] {
      grid_finder grid(&pool);
      return run(grid, s);
    }();
    gpu::pinned_boxes pin(s);
    REQUIRE(pin.active());
    const auto* report = gpu::last_pbig_report(*finder);
    std::span<const id_pair> got;
    for (int call = 0; call < 2; ++call) {
      REQUIRE_FALSE(gpu::find_pairs_view(*finder, s, got).has_value());
      CHECK(canonical(got, s.size()) == expected);
    }
    CHECK((report->single_queue && !report->requeued));
    const std::size_t bad = 12345;
    const float keep = s.lo_y[bad];
    s.lo_y[bad] = std::nanf("");
    const auto err = gpu::find_pairs_view(*finder, s, got);
    REQUIRE(err.has_value());
    CHECK(err->index == bad);
    s.lo_y[bad] = keep;
    REQUIRE_FALSE(gpu::find_pairs_view(*finder, s, got).has_value());
    CHECK((report->single_queue && !report->requeued));
    CHECK(canonical(got, s.size()) == expected);
  }

  TEST_CASE("degenerate: 10^4 identical boxes in one cell") {
    thread_pool pool(4);
    box_set s;
    for (int i = 0; i < 10000; ++i) s.push_back(box{{3.5f, 3.5f, 3.5f}, {7.25f, 7.25f, 7.25f}, 1, 1});
    for (const auto& o : all_combinations(&pool, 0, /*direct=*/true)) {
      CAPTURE(describe(o));
      auto finder = make_gpu(o);
      pair_list out = run(*finder, s);
      REQUIRE(out.size() == 10000ull * 9999 / 2);
      CHECK(every_pair_in_order(out, 10000));  // sorted, distinct and a < b: exactly every pair
    }
  }

  TEST_CASE("degenerate: a few world-spanning boxes over 10^6 small ones") {
    thread_pool pool(0);
    const auto seed = fresh_seed();
    CAPTURE(seed);
    const box_set s = uniform_with_spanning(1000000, seed, 0.3);
    grid_finder grid(&pool);
    const pair_list expected = run(grid, s);
    for (const int mode : {0, 1, 2}) {
      gpu::pbig_options o;
      o.compression = mode == 1;
      o.direct_output = mode == 2;
      o.decode_pool = &pool;
      auto finder = make_gpu(o);
      CHECK(run(*finder, s) == expected);
      CHECK(finder->stats().large_boxes == 3);
      CHECK(expected.size() >= 3 * 1000000 + 3);
    }
  }

  TEST_CASE("degenerate: long thin boxes at full size, and large sets, against the CPU grid finder") {
    thread_pool pool(0);
    grid_finder grid(&pool);
    auto finder = make_gpu(gpu::pbig_options{.decode_pool = &pool});  // default: direct output
    auto encoded = make_gpu(gpu::pbig_options{.decode_pool = &pool, .direct_output = false});
    {
      // 2e5 rods in the paper's world: thin (0..4) on two axes, 500..3000 long on the third.
      const auto seed = fresh_seed();
      CAPTURE(seed);
      rng_box_maker r(seed);
      box_set s;
      for (int i = 0; i < 200000; ++i) s.push_back(r.rod(1e4f, 4, -500, 1e4f, 500, 3000));
      CHECK(run(*finder, s) == run(grid, s));
    }
    {
      // A flat world of 2e5 boxes: 95% small squares, 5% rods 2000..9000 long. With small cells
      // (edge 20, grown to respect the 2N+64 cell cap) the longer rods occupy more than
      // max(64, 16 alpha) cells and take the large-box path.
      const auto seed = fresh_seed();
      CAPTURE(seed);
      rng_box_maker r(seed);
      box_set s;
      for (int i = 0; i < 200000; ++i) {
        box b = r.make(1e4f, 20);
        b.lo[2] = r.uni(0, 1);
        b.hi[2] = b.lo[2] + 1;
        if (i % 20 == 0) {
          const int axis = static_cast<int>(r.rng() % 2);
          b.lo[axis] = r.uni(-500, 1e4f);
          b.hi[axis] = b.lo[axis] + r.uni(2000, 9000);
        }
        s.push_back(b);
      }
      auto small_cells = make_gpu(gpu::pbig_options{.fixed_cell_edge = 20, .decode_pool = &pool});
      const pair_list expected = run(grid, s);
      CHECK(run(*small_cells, s) == expected);
      CHECK(small_cells->stats().large_boxes > 0);
      CHECK(run(*finder, s) == expected);
    }
    for_each_family_set(grid, all_families, {30000},
                        [&](const box_set& s, const pair_list& expected) { CHECK(run(*finder, s) == expected); });
    for_each_named_set({"gaussian", "mmo", "doc:10", "uniform"}, 1000000, [&](const box_set& s) {
      const pair_list expected = run(grid, s);
      CHECK(run(*finder, s) == expected);
      CHECK(run(*encoded, s) == expected);
    });
  }

  TEST_CASE("find_pairs_view: same pairs in the same order as find, buffer reused") {
    thread_pool pool(4);
    auto finder = make_gpu(gpu::pbig_options{.decode_pool = &pool, .direct_output = false});
    auto direct = make_gpu(gpu::pbig_options{.decode_pool = &pool, .direct_output = true});
    for_each_named_set({"gaussian", "uniform", "mmo"}, 300000, [&](const box_set& s) {
      pair_list out;
      REQUIRE_FALSE(finder->find(s, out).has_value());
      std::span<const id_pair> view;
      REQUIRE_FALSE(gpu::find_pairs_view(*finder, s, view).has_value());
      CHECK(pair_list(view.begin(), view.end()) == out);
      REQUIRE_FALSE(gpu::find_pairs_view(*direct, s, view).has_value());
      CHECK(pair_list(view.begin(), view.end()) == out);
      pair_list direct_out;
      REQUIRE_FALSE(direct->find(s, direct_out).has_value());
      CHECK(direct_out == out);
    });
    box_set bad = generate_uniform(200000, 1);
    bad.hi_x[150001] = bad.lo_x[150001] - 1;
    std::span<const id_pair> view;
    const auto err = gpu::find_pairs_view(*finder, bad, view);
    REQUIRE(err.has_value());
    CHECK(err->index == 150001);
    CHECK(view.empty());
    grid_finder grid(&pool);
    CHECK_THROWS_AS((void)gpu::find_pairs_view(grid, bad, view), std::invalid_argument);
  }

  TEST_CASE("invalid boxes are rejected with the box named") {
    auto finder = make_gpu();
    box_set s = generate_uniform(10, 3);
    s.lo_y[4] = std::nanf("");
    pair_list out{{0, 1}};
    const auto err = finder->find(s, out);
    REQUIRE(err.has_value());
    CHECK(err->index == 4);
    CHECK(out.empty());
  }

  TEST_CASE("indirect checks (no gathered box array): the same pairs in the same order") {
    // pbig_options::indirect_check_min_boxes = 0 makes every call read the boxes through their ids;
    // SIZE_MAX never does. Small sets of every family against brute force with the paper's output
    // (plain and compressed) and the direct output, tiny buffers included (re-runs); larger sets
    // of the generators element by element against the gathered path, in several batches.
    thread_pool pool(4);
    brute_force_finder brute(&pool);
    constexpr std::size_t always = 0, never = std::numeric_limits<std::size_t>::max();
    std::vector<gpu::pbig_options> modes;
    for (const bool direct : {false, true}) {
      for (const bool comp : {false, true}) {
        for (const std::size_t init : {std::size_t{0}, std::size_t{1}}) {
          gpu::pbig_options o;
          o.direct_output = direct;
          o.compression = comp;
          o.initial_output_pairs = init;
          o.decode_pool = &pool;
          o.indirect_check_min_boxes = always;
          modes.push_back(o);
        }
      }
    }
    for (const family f : all_families) {
      // One finder per mode and family: with tiny buffers each larger set overflows them again.
      std::vector<std::unique_ptr<pair_finder>> finders;
      for (const auto& o : modes) finders.push_back(make_gpu(o));
      for_each_family_set(brute, {f}, {0, 1, 2, 33, 513, 4001}, [&](const box_set& s, const pair_list& expected) {
        for (std::size_t k = 0; k < modes.size(); ++k) {
          CAPTURE(describe(modes[k]));
          CHECK(run(*finders[k], s) == expected);
          // (Sets under 2 boxes never reach the device: no report of their own.)
          if (s.size() >= 2) CHECK(gpu::last_pbig_report(*finders[k])->indirect_check);
        }
      });
    }
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gpu::pbig_options on, off;
    on.decode_pool = off.decode_pool = &pool;
    on.indirect_check_min_boxes = always;
    off.indirect_check_min_boxes = never;
    auto finder_on = make_gpu(on);
    auto finder_off = make_gpu(off);
    for (const char* kind : {"uniform", "gaussian", "mmo", "doc:10"}) {
      for (const std::size_t n : {std::size_t{30000}, std::size_t{400000}}) {
        CAPTURE(kind);
        CAPTURE(n);
        const box_set s = *generate_named(kind, n, seed);
        for (int call = 0; call < 2; ++call) {  // the second call: reused plan, single queue where small
          std::span<const id_pair> a, b;
          REQUIRE_FALSE(gpu::find_pairs_view(*finder_off, s, a).has_value());
          const pair_list gathered(a.begin(), a.end());
          REQUIRE_FALSE(gpu::find_pairs_view(*finder_on, s, b).has_value());
          CHECK(pair_list(b.begin(), b.end()) == gathered);  // same pairs, same order
          CHECK(gpu::last_pbig_report(*finder_on)->indirect_check);
          CHECK_FALSE(gpu::last_pbig_report(*finder_off)->indirect_check);
        }
      }
    }
    // The default: gathered below 2^22 boxes, indirect from there on.
    auto finder_default = make_gpu(gpu::pbig_options{.decode_pool = &pool});
    const box_set big = *generate_named("uniform", std::size_t{1} << 22, seed);
    std::span<const id_pair> a, b;
    REQUIRE_FALSE(gpu::find_pairs_view(*finder_default, big, a).has_value());
    CHECK(gpu::last_pbig_report(*finder_default)->indirect_check);
    const pair_list by_default(a.begin(), a.end());
    REQUIRE_FALSE(gpu::find_pairs_view(*finder_off, big, b).has_value());
    CHECK(pair_list(b.begin(), b.end()) == by_default);
    CHECK(gpu::last_pbig_report(*finder_off)->batches > 1);
  }

  TEST_CASE("pinned input whose boxes share one category and one mask: the classes filled on the device") {
    // From tuning::uniform_classes_min_boxes (2^18) boxes on, a pinned set whose boxes all share
    // one category and one mask uploads the coordinates only; every variant below is compared
    // with the CPU grid finder, including sets that differ from uniform in their first or last box.
    thread_pool pool(4);
    grid_finder grid(&pool);
    gpu::pbig_options opt;
    opt.decode_pool = &pool;
    auto finder = make_gpu(opt);
    const std::uint64_t seed = std::random_device{}();
    CAPTURE(seed);
    const std::size_t n = 300000;
    struct variant {
      const char* name;
      std::uint32_t category, mask;
      long odd_box;  // -1: none; else this box gets category = mask = 2 (it then pairs with nobody)
      bool filled;
    };
    for (const variant v : {variant{"plain 1/1", 1, 1, -1, true}, variant{"2/2", 2, 2, -1, true},
                            variant{"4/0 (no pairs)", 4, 0, -1, true}, variant{"last box differs", 1, 1, long(n) - 1, false},
                            variant{"first box differs", 1, 1, 0, false},
                            variant{"middle box differs", 1, 1, long(n) / 2 + 3, false}}) {
      CAPTURE(v.name);
      box_set s = *generate_named("uniform", n, seed);
      std::fill(s.category.begin(), s.category.end(), v.category);
      std::fill(s.mask.begin(), s.mask.end(), v.mask);
      if (v.odd_box >= 0) {
        s.category[static_cast<std::size_t>(v.odd_box)] = 2;
        s.mask[static_cast<std::size_t>(v.odd_box)] = 2;
      }
      pair_list want;
      REQUIRE_FALSE(grid.find(s, want).has_value());
      for (auto& p : want) {
        if (p.a > p.b) std::swap(p.a, p.b);
      }
      std::sort(want.begin(), want.end());
      if (v.mask == 0) CHECK(want.empty());
      gpu::pinned_boxes pin(s);
      REQUIRE(pin.active());
      for (int call = 0; call < 2; ++call) {  // the second call reuses the plan and buffers
        std::span<const id_pair> got;
        REQUIRE_FALSE(gpu::find_pairs_view(*finder, s, got).has_value());
        pair_list sorted(got.begin(), got.end());
        std::sort(sorted.begin(), sorted.end());
        CHECK(sorted == want);
        const gpu::pbig_report* rep = gpu::last_pbig_report(*finder);
        REQUIRE(rep != nullptr);
        CHECK(rep->classes_filled == v.filled);
        CHECK(rep->bytes_in == (v.filled ? 24u : 32u) * n);
      }
    }
  }

  TEST_CASE("pinned input (pinned_boxes): DMA from the caller's arrays, validated on the device") {
    thread_pool pool(4);
    gpu::pbig_options opt;
    opt.decode_pool = &pool;
    auto finder = make_gpu(opt);
    auto plain = make_gpu(opt);
    const std::uint64_t seed = std::random_device{}();
    CAPTURE(seed);
    for (const char* kind : {"uniform", "gaussian", "mmo", "doc:10"}) {
      for (const std::size_t n : {std::size_t{20000}, std::size_t{300000}}) {
        CAPTURE(kind);
        CAPTURE(n);
        box_set s = *generate_named(kind, n, seed);
        std::span<const id_pair> want;
        REQUIRE_FALSE(gpu::find_pairs_view(*plain, s, want).has_value());
        const pair_list expected(want.begin(), want.end());
        {
          gpu::pinned_boxes pin(s);
          REQUIRE(pin.active());
          REQUIRE(gpu::boxes_pinned(s));
          std::span<const id_pair> got;
          REQUIRE_FALSE(gpu::find_pairs_view(*finder, s, got).has_value());
          CHECK(pair_list(got.begin(), got.end()) == expected);  // same pairs, same order
          // An invalid box: the same error as interest::validate's, and the next call still works.
          const std::size_t bad = n / 3 + 7;
          const float keep_z = s.hi_z[bad], keep_x = s.lo_x[bad / 2];
          s.hi_z[bad] = s.lo_z[bad] - 1.0f;
          const auto err = gpu::find_pairs_view(*finder, s, got);
          REQUIRE(err.has_value());
          CHECK(err->index == bad);
          CHECK(err->message == validate(s)->message);
          s.lo_x[bad / 2] = std::numeric_limits<float>::infinity();  // a lower one wins
          const auto err2 = gpu::find_pairs_view(*finder, s, got);
          REQUIRE(err2.has_value());
          CHECK(err2->index == bad / 2);
          s.hi_z[bad] = keep_z;
          s.lo_x[bad / 2] = keep_x;
          REQUIRE_FALSE(gpu::find_pairs_view(*finder, s, got).has_value());
          CHECK(pair_list(got.begin(), got.end()) == expected);
        }
        CHECK_FALSE(gpu::boxes_pinned(s));  // the guard is gone: the staging path again
        std::span<const id_pair> again;
        REQUIRE_FALSE(gpu::find_pairs_view(*finder, s, again).has_value());
        CHECK(pair_list(again.begin(), again.end()) == expected);
      }
    }
    // Small sets are not pinned (the staging copy costs less than the registration).
    const box_set small = generate_uniform(100, 1);
    gpu::pinned_boxes pin(small);
    CHECK_FALSE(pin.active());
    CHECK_FALSE(gpu::boxes_pinned(small));
  }
}
