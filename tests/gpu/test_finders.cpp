// The finder factory (gpu/finders.h) and the auto finder. Runs with and without a CUDA device:
// without one the GPU backends must be refused with a reason and `auto` must run the CPU finder;
// with one they must exist and `auto` must pick a GPU finder. The fallback on a GPU failure is
// tested with injected finders, so it runs everywhere.
#include <doctest/doctest.h>

#include <cmath>
#include <span>
#include <stdexcept>
#include <string>

#include "../common/box_families.h"
#include "gpu/finders.h"
#include "gpu/lbvh.h"
#include "gpu/pbig.h"
#include "interest/interest.h"
#include "interest/thread_pool.h"

using namespace zone::interest;
using namespace zone::test;
namespace gpu = zone::gpu;

namespace {

/// A stand-in for a GPU finder that fails mid-call (a CUDA error), counting its calls.
class throwing_finder final : public pair_finder {
 public:
  int calls = 0;
  [[nodiscard]] std::string_view name() const override { return "throwing"; }

 protected:
  void find_valid(const box_set& /*boxes*/, pair_list& out) override {
    ++calls;
    out.push_back({0, 1});  // a partial result that must not leak out
    throw std::runtime_error("injected device failure");
  }
};

/// A stand-in for a working GPU finder: the brute-force reference, counting its calls.
class counting_finder final : public pair_finder {
 public:
  int calls = 0;
  [[nodiscard]] std::string_view name() const override { return "counting"; }

 protected:
  void find_valid(const box_set& boxes, pair_list& out) override {
    ++calls;
    brute_force_finder b;
    (void)b.find(boxes, out);
  }
};

/// A stand-in for a GPU finder with a result buffer of its own (pair_finder::views_own_buffer):
/// find_view points at its buffer and never touches the caller's scratch list.
class buffered_finder final : public pair_finder {
 public:
  pair_list own;
  int views = 0;
  bool scratch_touched = false;
  [[nodiscard]] std::string_view name() const override { return "buffered"; }
  [[nodiscard]] bool views_own_buffer() const override { return true; }
  std::optional<box_error> find_view(const box_set& boxes, pair_list& scratch, std::span<const id_pair>& view) override {
    ++views;
    scratch_touched |= !scratch.empty();
    view = {};
    brute_force_finder b;
    auto err = b.find(boxes, own);
    if (!err) view = own;
    return err;
  }

 protected:
  void find_valid(const box_set& boxes, pair_list& out) override {
    brute_force_finder b;
    (void)b.find(boxes, out);
  }
};

}  // namespace

TEST_SUITE("gpu.finders") {
  TEST_CASE("parse_backend accepts the documented names and nothing else") {
    CHECK(gpu::parse_backend("brute") == gpu::finder_backend::brute);
    CHECK(gpu::parse_backend("cpu") == gpu::finder_backend::cpu);
    CHECK(gpu::parse_backend("gpu") == gpu::finder_backend::pbig);
    CHECK(gpu::parse_backend("pbig") == gpu::finder_backend::pbig);
    CHECK(gpu::parse_backend("lbvh") == gpu::finder_backend::lbvh);
    CHECK(gpu::parse_backend("auto") == gpu::finder_backend::auto_select);
    for (const char* bad : {"", "GPU", "Auto", "bvh", "pbig ", "cpu1"}) {
      CAPTURE(bad);
      CHECK_FALSE(gpu::parse_backend(bad).has_value());
    }
    for (const auto b : {gpu::finder_backend::brute, gpu::finder_backend::cpu, gpu::finder_backend::pbig,
                         gpu::finder_backend::lbvh, gpu::finder_backend::auto_select}) {
      CHECK(gpu::parse_backend(gpu::backend_name(b)) == b);
    }
  }

  TEST_CASE("make_finder: CPU backends and auto always exist; GPU backends exactly when a device is usable") {
    thread_pool pool(2);
    std::string why;
    const bool device = gpu::device_available(nullptr, &why);
    for (const auto b : {gpu::finder_backend::brute, gpu::finder_backend::cpu, gpu::finder_backend::auto_select}) {
      CAPTURE(gpu::backend_name(b));
      CHECK(gpu::make_finder(b, &pool) != nullptr);
      CHECK(gpu::make_finder(b, nullptr) != nullptr);
    }
    for (const auto b : {gpu::finder_backend::pbig, gpu::finder_backend::lbvh}) {
      CAPTURE(gpu::backend_name(b));
      std::string reason;
      auto f = gpu::make_finder(b, &pool, &reason);
      if (device) {
        CHECK(f != nullptr);
      } else {
        CHECK(f == nullptr);
        CHECK_FALSE(reason.empty());
      }
    }
  }

  TEST_CASE("make_finder by name: every documented name, cpu-1t, grid options, readable errors") {
    thread_pool pool(2);
    const bool device = gpu::device_available(nullptr, nullptr);
    for (const char* name : {"brute", "cpu", "cpu-1t", "auto"}) {
      CAPTURE(name);
      std::string why;
      auto f = gpu::make_finder(std::string_view(name), &pool, &why);
      REQUIRE(f != nullptr);
      CHECK(why.empty());
      const std::string_view want = std::string_view(name) == "cpu-1t" ? "cpu" : std::string_view(name);
      CHECK(f->name() == want);
    }
    grid_finder_options g;
    g.min_boxes_per_cell = 5.0;
    for (const char* name : {"cpu", "cpu-1t"}) {
      CAPTURE(name);
      auto f = gpu::make_finder(std::string_view(name), &pool, nullptr, g);
      const auto* grid = dynamic_cast<const grid_finder*>(f.get());
      REQUIRE(grid != nullptr);
      CHECK(grid->options().min_boxes_per_cell == 5.0);
    }
    for (const char* name : {"gpu", "pbig", "lbvh"}) {
      CAPTURE(name);
      std::string why;
      auto f = gpu::make_finder(std::string_view(name), &pool, &why);
      if (device) {
        CHECK(f != nullptr);
      } else {
        CHECK(f == nullptr);
        CHECK(why.find(std::string("finder '") + name + "' cannot run here: ") == 0);
        CHECK(why.size() > std::string("finder '' cannot run here: ").size() + std::string(name).size());
      }
    }
    for (const char* bad : {"", "GPU", "cpu1", "cgal"}) {
      CAPTURE(bad);
      std::string why;
      CHECK(gpu::make_finder(std::string_view(bad), &pool, &why) == nullptr);
      CHECK(why == std::string("unknown finder '") + bad + "' (brute, cpu, cpu-1t, gpu, pbig, lbvh, auto)");
      CHECK(gpu::make_finder(std::string_view(bad), &pool) == nullptr);
    }
  }

  TEST_CASE("every finder make_finder builds equals brute force on every family") {
    thread_pool pool(3);
    brute_force_finder brute(&pool);
    std::vector<std::unique_ptr<pair_finder>> finders;
    for (const auto b : {gpu::finder_backend::cpu, gpu::finder_backend::pbig, gpu::finder_backend::lbvh,
                         gpu::finder_backend::auto_select}) {
      if (auto f = gpu::make_finder(b, &pool)) finders.push_back(std::move(f));
    }
    REQUIRE(finders.size() >= 2);
    for_each_family_set(brute, all_families, {0, 1, 2, 5, 64, 700}, [&](const box_set& s, const pair_list& expected) {
      for (auto& finder : finders) {
        CAPTURE(finder->name());
        CHECK(run(*finder, s) == expected);
      }
    });
  }

  TEST_CASE("auto: runs the CPU finder without a device and a GPU finder with one") {
    thread_pool pool(2);
    auto f = gpu::make_finder(gpu::finder_backend::auto_select, &pool);
    REQUIRE(f);
    CHECK_FALSE(gpu::last_auto_choice(*f).has_value());
    const box_set s = generate_uniform(5000, fresh_seed());
    pair_list out;
    REQUIRE_FALSE(f->find(s, out).has_value());
    REQUIRE(gpu::last_auto_choice(*f).has_value());
    if (gpu::device_available()) {
      CHECK(*gpu::last_auto_choice(*f) != gpu::finder_backend::cpu);
    } else {
      CHECK(*gpu::last_auto_choice(*f) == gpu::finder_backend::cpu);
    }
    grid_finder grid(&pool);
    CHECK(run(*f, s) == run(grid, s));
    // The zero-copy entry gives the same pairs.
    std::span<const id_pair> view;
    REQUIRE_FALSE(gpu::find_view(*f, s, view).has_value());
    CHECK(canonical(view, s.size()) == run(grid, s));
    CHECK_THROWS_AS((void)gpu::find_view(grid, s, view), std::invalid_argument);
  }

  TEST_CASE("auto: a crowded set goes to LBVH unpinned and to PBIG once pinned, same pairs") {
    thread_pool pool(2);
    if (!gpu::device_available()) return;  // needs both GPU finders
    auto f = gpu::make_finder(gpu::finder_backend::auto_select, &pool);
    REQUIRE(f);
    const box_set s = generate_gaussian(300000, fresh_seed());
    grid_finder grid(&pool);
    const pair_list expected = run(grid, s);
    std::span<const id_pair> view;
    REQUIRE_FALSE(gpu::find_view(*f, s, view).has_value());
    CHECK(*gpu::last_auto_choice(*f) == gpu::finder_backend::lbvh);
    CHECK(canonical(view, s.size()) == expected);
    {
      const gpu::pinned_boxes pin(s);
      REQUIRE(pin.active());
      REQUIRE_FALSE(gpu::find_view(*f, s, view).has_value());  // re-decided at once, not after 64 calls
      CHECK(*gpu::last_auto_choice(*f) == gpu::finder_backend::pbig);
      CHECK(canonical(view, s.size()) == expected);
    }
    REQUIRE_FALSE(gpu::find_view(*f, s, view).has_value());  // unpinned again
    CHECK(*gpu::last_auto_choice(*f) == gpu::finder_backend::lbvh);
    CHECK(canonical(view, s.size()) == expected);
  }

  TEST_CASE("auto: a GPU finder that throws mid-call is logged, and that call and all later ones run on the CPU") {
    thread_pool pool(2);
    brute_force_finder brute(&pool);
    auto failing = std::make_unique<throwing_finder>();
    throwing_finder* failing_ptr = failing.get();
    auto f = gpu::make_auto_finder(std::make_unique<grid_finder>(&pool), std::move(failing), nullptr, &pool);
    for (int call = 0; call < 3; ++call) {
      const auto seed = fresh_seed();
      CAPTURE(seed);
      CAPTURE(call);
      const box_set s = make_family(family::uniform, 400, seed);
      CHECK(run(*f, s) == run(brute, s));
      CHECK(gpu::last_auto_choice(*f) == gpu::finder_backend::cpu);
      std::span<const id_pair> view;
      REQUIRE_FALSE(gpu::find_view(*f, s, view).has_value());
      CHECK(canonical(view, s.size()) == run(brute, s));
    }
    CHECK(failing_ptr->calls == 1);  // never asked again after its failure

    // The same through the zero-copy entry first.
    auto failing2 = std::make_unique<throwing_finder>();
    throwing_finder* failing2_ptr = failing2.get();
    auto g = gpu::make_auto_finder(std::make_unique<grid_finder>(&pool), nullptr, std::move(failing2), &pool);
    const box_set s = make_family(family::mask_mix, 500, fresh_seed());
    std::span<const id_pair> view;
    REQUIRE_FALSE(gpu::find_view(*g, s, view).has_value());
    CHECK(canonical(view, s.size()) == run(brute, s));
    CHECK(failing2_ptr->calls == 1);
    CHECK(run(*g, s) == run(brute, s));
    CHECK(failing2_ptr->calls == 1);
  }

  TEST_CASE("auto: a working GPU candidate is used and its pairs are returned") {
    thread_pool pool(2);
    brute_force_finder brute(&pool);
    auto stand_in = std::make_unique<counting_finder>();
    counting_finder* ptr = stand_in.get();
    auto f = gpu::make_auto_finder(std::make_unique<grid_finder>(&pool), std::move(stand_in), nullptr, &pool);
    const box_set s = make_family(family::few_classes, 600, fresh_seed());
    CHECK(run(*f, s) == run(brute, s));
    CHECK(gpu::last_auto_choice(*f) == gpu::finder_backend::pbig);
    CHECK(ptr->calls == 1);
    CHECK_THROWS_AS((void)gpu::make_auto_finder(nullptr, nullptr, nullptr, &pool), std::invalid_argument);
  }

  TEST_CASE("find_view: any finder with a buffer of its own is viewed in place, through auto too; others are refused") {
    thread_pool pool(2);
    brute_force_finder brute(&pool);
    grid_finder grid(&pool);
    const box_set s = make_family(family::mask_mix, 700, fresh_seed());
    const pair_list expected = run(brute, s);
    // Which finders say they view a buffer of their own (gpu::find_view asks them, no type test).
    CHECK_FALSE(brute.views_own_buffer());
    CHECK_FALSE(grid.views_own_buffer());
    std::span<const id_pair> view;
    CHECK_THROWS_AS((void)gpu::find_view(brute, s, view), std::invalid_argument);
    buffered_finder alone;
    REQUIRE_FALSE(gpu::find_view(alone, s, view).has_value());
    CHECK(view.data() == alone.own.data());  // no copy
    CHECK(canonical(view, s.size()) == expected);
    // The auto finder hands over its candidate's own buffer.
    auto stand_in = std::make_unique<buffered_finder>();
    buffered_finder* ptr = stand_in.get();
    auto f = gpu::make_auto_finder(std::make_unique<grid_finder>(&pool), std::move(stand_in), nullptr, &pool);
    CHECK(f->views_own_buffer());
    REQUIRE_FALSE(gpu::find_view(*f, s, view).has_value());
    CHECK(gpu::last_auto_choice(*f) == gpu::finder_backend::pbig);
    CHECK(ptr->views == 1);
    CHECK(view.data() == ptr->own.data());
    CHECK(canonical(view, s.size()) == expected);
    CHECK(run(*f, s) == expected);  // find(): the candidate's view, copied into the caller's list
    CHECK(ptr->views == 2);
    CHECK_FALSE(ptr->scratch_touched);
    CHECK_FALSE(alone.scratch_touched);
  }

  TEST_CASE("auto: invalid boxes are rejected with the box named, whatever runs") {
    thread_pool pool(2);
    auto f = gpu::make_finder(gpu::finder_backend::auto_select, &pool);
    box_set s = generate_uniform(100, fresh_seed());
    s.hi_z[37] = s.lo_z[37] - 1;
    pair_list out{{0, 1}};
    const auto err = f->find(s, out);
    REQUIRE(err.has_value());
    CHECK(err->index == 37);
    CHECK(out.empty());
    std::span<const id_pair> view;
    const auto err2 = gpu::find_view(*f, s, view);
    REQUIRE(err2.has_value());
    CHECK(err2->index == 37);
  }

  TEST_CASE("summarize: sample statistics follow the set") {
    CHECK(gpu::summarize(box_set{}).n == 0);
    const box_set same = make_family(family::identical, 5000, 1);
    const auto a = gpu::summarize(same);
    CHECK(a.n == 5000);
    CHECK(a.sampled == std::min<std::size_t>(5000, gpu::auto_sample_boxes));
    CHECK(a.size_spread == doctest::Approx(1.0));
    CHECK(a.largest_cells == doctest::Approx(a.mean_cells));
    const box_set u = generate_uniform(100000, fresh_seed());
    const auto b = gpu::summarize(u);
    CHECK(b.sampled == gpu::auto_sample_boxes);
    CHECK(b.size_spread > 1.0);
    CHECK(b.size_spread < 3.0);  // edges U[1, 100]: max / median about 2
    CHECK(b.cell_edge > 0);
    CHECK(b.scene_extent[0] > 9000);
    // Eq. 6's f at the estimated edge is about W = 32: N * alpha / M.
    double m = 1;
    for (double e : b.scene_extent) m *= e / b.cell_edge + 1;
    CHECK(100000.0 * b.mean_cells / m == doctest::Approx(32.0).epsilon(0.05));
    // A few huge boxes among small ones: a wide spread, the largest occupying many cells.
    box_set h = generate_uniform(100000, fresh_seed(), 0.3);
    for (std::size_t i = 0; i < h.size(); i += 97) h.set(i, box{{0, 0, 0}, {1e4f, 1e4f, 1e4f}, 1, 1});
    const auto c = gpu::summarize(h);
    CHECK(c.size_spread > 100);
    CHECK(c.largest_cells > 20 * c.mean_cells);
  }

  TEST_CASE("choose_backend: CPU without a GPU finder; the rule between PBIG and LBVH") {
    const auto s = gpu::summarize(generate_uniform(100000, fresh_seed()));
    std::string reason;
    CHECK(gpu::choose_backend(s, false, false, &reason) == gpu::finder_backend::cpu);
    CHECK_FALSE(reason.empty());
    CHECK(gpu::choose_backend(s, true, false) == gpu::finder_backend::pbig);
    CHECK(gpu::choose_backend(s, false, true) == gpu::finder_backend::lbvh);
    // Uniform boxes at 1e5: no box apart from the grid, PBIG.
    CHECK(s.large_estimate == 0);
    CHECK(gpu::choose_backend(s, true, true, &reason) == gpu::finder_backend::pbig);
    CHECK(reason.find("PBIG") != std::string::npos);
    // Small sets of like-sized boxes: LBVH; small MMO-like sets (sizes spread ~58x): PBIG.
    const auto small = gpu::summarize(generate_uniform(gpu::auto_small_n - 1, fresh_seed()));
    CHECK(gpu::choose_backend(small, true, true) == gpu::finder_backend::lbvh);
    const auto small_mmo = gpu::summarize(generate_mmo(gpu::auto_small_n - 2, fresh_seed()));
    CHECK(small_mmo.size_spread > gpu::auto_even_spread);
    CHECK(gpu::choose_backend(small_mmo, true, true) == gpu::finder_backend::pbig);
    // The large-box pass estimate decides at the threshold.
    gpu::box_set_summary m = s;
    m.n = 1000000;
    m.large_estimate = gpu::auto_large_pass_tests / 1e6 * 1.01;
    CHECK(gpu::choose_backend(m, true, true, &reason) == gpu::finder_backend::lbvh);
    CHECK(reason.find("large-box pass") != std::string::npos);
    m.large_estimate = gpu::auto_large_pass_tests / 1e6 * 0.99;
    CHECK(gpu::choose_backend(m, true, true) == gpu::finder_backend::pbig);
    // Crowded cells of like-sized boxes (the Gaussian set): LBVH; evenly spread boxes: about 1.
    const auto gauss = gpu::summarize(generate_gaussian(300000, fresh_seed()));
    CHECK(gauss.crowding > 2 * gpu::auto_crowding);
    CHECK(gauss.size_spread < gpu::auto_even_spread);
    CHECK(gpu::choose_backend(gauss, true, true, &reason) == gpu::finder_backend::lbvh);
    CHECK(reason.find("crowded") != std::string::npos);
    CHECK(s.crowding == doctest::Approx(1.0).epsilon(0.25));
    // Boxes covering many cells each (degree of coverage 10): LBVH.
    const auto dense = gpu::summarize(*generate_named("doc:10", 300000, fresh_seed()));
    CHECK(dense.mean_cells > gpu::auto_many_cells);
    CHECK(gpu::choose_backend(dense, true, true) == gpu::finder_backend::lbvh);
    // The MMO-like set: its gigantic view boxes leave the grid; few at 1e5 (PBIG), many at 3e6 (LBVH).
    const auto mmo_small = gpu::summarize(generate_mmo(100000, fresh_seed()));
    CHECK(mmo_small.size_spread > 10);
    CHECK(gpu::choose_backend(mmo_small, true, true) == gpu::finder_backend::pbig);
    const auto mmo_big = gpu::summarize(generate_mmo(3000000, fresh_seed()));
    CHECK(mmo_big.large_estimate * 3e6 > gpu::auto_large_pass_tests);  // about 1.6e10, 3 sd above 4e9
    CHECK(gpu::choose_backend(mmo_big, true, true) == gpu::finder_backend::lbvh);
    // Pinned input (rule 3): PBIG where rules 4 and 5 would take LBVH; the small-set and large-box rules
    // still take LBVH; unpinned sets are decided as before.
    CHECK_FALSE(gauss.pinned);
    for (gpu::box_set_summary p : {gauss, dense}) {
      p.pinned = true;
      CHECK(gpu::choose_backend(p, true, true, &reason) == gpu::finder_backend::pbig);
      CHECK(reason.find("pinned") != std::string::npos);
      CHECK(gpu::choose_backend(p, false, true) == gpu::finder_backend::lbvh);
    }
    for (gpu::box_set_summary p : {small, mmo_big}) {
      p.pinned = true;
      CHECK(gpu::choose_backend(p, true, true) == gpu::finder_backend::lbvh);
    }
  }

  TEST_CASE("auto: keeps its choice between decisions, re-decides when N moves by more than 10%") {
    thread_pool pool(2);
    brute_force_finder brute(&pool);
    auto pbig_stand_in = std::make_unique<counting_finder>();
    auto lbvh_stand_in = std::make_unique<counting_finder>();
    counting_finder* p = pbig_stand_in.get();
    counting_finder* l = lbvh_stand_in.get();
    auto f = gpu::make_auto_finder(std::make_unique<grid_finder>(&pool), std::move(pbig_stand_in),
                                   std::move(lbvh_stand_in), &pool);
    const box_set small = make_family(family::uniform, 500, fresh_seed());  // N < auto_small_n: LBVH
    CHECK(run(*f, small) == run(brute, small));
    CHECK(gpu::last_auto_choice(*f) == gpu::finder_backend::lbvh);
    CHECK(l->calls == 1);
    const box_set larger = generate_uniform(gpu::auto_small_n * 2, fresh_seed());  // N moved: PBIG
    CHECK(run(*f, larger) == run(brute, larger));
    CHECK(gpu::last_auto_choice(*f) == gpu::finder_backend::pbig);
    CHECK(p->calls == 1);
    CHECK(l->calls == 1);
  }
}
