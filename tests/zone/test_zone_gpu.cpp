// Tick determinism with the GPU finder: the same seed and inputs give the same per-tick world
// digest (positions and the interest tracker's visible sets, enters and leaves) with the CPU grid
// finder and with the GPU finders (PBIG in both its output modes, LBVH, auto), with 1 and several
// threads, with the tracker reading the finder's own buffer (pair_finder::find_view, zone-server's way),
// and with an output buffer forced tiny (the overflow path runs inside the tick loop). The GPU
// visibility engine (the whole interest step on the device) against the brute-force oracle of
// tracker_harness.h, the hand-made scenarios, the host path's digests on zone worlds and on
// degenerate sets, and switching between the engine and the host path. Without a CUDA device the
// executable prints why and exits with 77 before any test case (CTest: Skipped).
#include <doctest/doctest.h>

#include <cstdio>
#include <cstdlib>
#include <string>

#include "../common/device_or_skip.h"
#include "../common/seeds.h"
#include "../interest/space_reference.h"
#include "gpu/finders.h"
#include "gpu/pbig.h"
#include "gpu/visibility.h"
#include "tracker_harness.h"
#include "world_script.h"
#include "zone/zone.h"

using namespace zone;
using zone::test::fresh_seed;
using zone::test::run_digests;
using zone::test::small_config;
using namespace zone::test;

namespace {

/// Runs before main (static initialisation): no device, no tests.
const bool device_present = zone::test::device_or_skip("test_zone_gpu");

std::unique_ptr<interest::pair_finder> make_gpu(const gpu::pbig_options& opt) {
  std::string why;
  auto f = gpu::make_pbig_finder(opt, &why);
  if (!f) FAIL("make_pbig_finder failed: " << why);
  return f;
}

std::unique_ptr<interest::visibility_engine> make_engine(interest::thread_pool* pool) {
  std::string why;
  auto e = gpu::make_visibility_engine(pool, &why);
  if (!e) FAIL("make_visibility_engine failed: " << why);
  return e;
}

/// Runs `ticks` ticks of the same store with the host path (grid finder) and with the engine,
/// moving entities between ticks with `move`, and checks that every tick's output is the same.
/// With `demand` (by slot), the engine copies back only those rows' visible sets: they are
/// compared first, then every row (the others fetched from the device on first access).
template <class Move>
void same_as_host(entity_store& store, interest::visibility_engine& engine, int ticks, float h, Move move,
                  const std::vector<std::uint8_t>* demand = nullptr) {
  interest::thread_pool pool(3);
  interest::grid_finder grid(&pool);
  interest_tracker host(grid, &pool, interest_options{h, 0, 64});
  interest_tracker dev(grid, &pool, interest_options{h, 0, 64});
  dev.set_engine(&engine);
  dev.set_view_demand(demand);
  for (int t = 0; t < ticks; ++t) {
    CAPTURE(t);
    REQUIRE_FALSE(host.update(store.columns()).has_value());
    REQUIRE_FALSE(dev.update(store.columns()).has_value());
    REQUIRE(dev.last_update_on_engine());
    if (demand != nullptr) {
      for (std::size_t r = 0; r < store.size(); ++r) {
        const std::uint32_t slot = slot_of(store.ids()[r]);
        if (slot < demand->size() && (*demand)[slot] != 0) {
          const auto a = host.visible(r), b = dev.visible(r);
          REQUIRE(id_list(a.begin(), a.end()) == id_list(b.begin(), b.end()));
        }
      }
    }
    CHECK(dev.stats().visible == host.stats().visible);
    CHECK(dev.stats().enters == host.stats().enters);
    CHECK(dev.stats().leaves == host.stats().leaves);
    CHECK(dev.stats().candidates == host.stats().candidates);
    CHECK(dev.digest() == host.digest());
    move(store, t);
  }
}

}  // namespace

TEST_SUITE("zone.gpu") {
  TEST_CASE("the tick API on the GPU backend: every step is the brute-force model's; switching backends mid-run") {
    for (const float h : {0.0f, 3.0f}) {
      const std::uint64_t seed = fresh_seed();
      CAPTURE(seed);
      CAPTURE(h);
      interest::thread_pool pool(4);
      interest::space_options o;
      o.where = interest::backend::gpu;
      o.gpu = gpu::make_visibility_engine;
      o.pool = &pool;
      o.hysteresis = h;
      interest::interest_space on_gpu(o);
      REQUIRE(on_gpu.current_backend() == interest::backend::gpu);
      CHECK(run_random_space(on_gpu, h, seed, 30, 300) > 100);
      CHECK(on_gpu.current_backend() == interest::backend::gpu);
      CHECK(on_gpu.tracker().last_update_on_engine());
    }
    // The same random run, its backend switched every few steps: the sets carry over.
    interest::thread_pool pool(2);
    interest::space_options o;
    o.where = interest::backend::automatic;
    o.gpu = gpu::make_visibility_engine;
    o.pool = &pool;
    interest::interest_space a(o), b(o);
    REQUIRE(a.current_backend() == interest::backend::gpu);
    std::mt19937_64 rng(fresh_seed());
    std::vector<interest::entity_id> ids;
    for (int k = 0; k < 400; ++k) {
      const interest::vec3 p{static_cast<float>(rng() % 200), static_cast<float>(rng() % 200), 0};
      ids.push_back(a.add({.position = p, .aoi_half = {12, 12, 12}}));
      REQUIRE(b.add({.position = p, .aoi_half = {12, 12, 12}}) == ids.back());
    }
    REQUIRE(b.set_backend(interest::backend::cpu));
    for (int t = 0; t < 24; ++t) {
      if (t % 3 == 0) REQUIRE(a.set_backend(t % 2 == 0 ? interest::backend::cpu : interest::backend::gpu));
      for (const auto id : ids) {
        const auto p = a.positions()[a.index_of(id)];
        const interest::vec3 q{p.x + static_cast<float>(rng() % 7) - 3, p.y + static_cast<float>(rng() % 7) - 3, 0};
        REQUIRE(a.move(id, q));
        REQUIRE(b.move(id, q));
      }
      REQUIRE_FALSE(a.step().has_value());
      REQUIRE_FALSE(b.step().has_value());
      for (const auto id : ids) {
        CHECK(as_vector(a.visible(id)) == as_vector(b.visible(id)));
        CHECK(as_vector(a.entered(id)) == as_vector(b.entered(id)));
        CHECK(as_vector(a.left(id)) == as_vector(b.left(id)));
      }
    }
  }

  TEST_CASE("GPU interest engine: events match the brute-force oracle over many ticks") {
    interest::thread_pool pool(4);
    auto engine = make_engine(&pool);
    const run_config configs[] = {
        {250, 4.0f, 0, false, 1},  {250, 4.0f, 0, true, 2}, {300, 0.0f, 0, false, 3}, {200, 10.0f, 0, true, 1},
        {1500, 4.0f, 0, false, 4},
        {250, 3.0f, 6, false, 2},  // a cap: the tracker runs these ticks on the host path
    };
    for (const auto& c : configs) run_against_oracle(fresh_seed(), c, 120, engine.get());
  }

  TEST_CASE("GPU interest engine: hysteresis, teleports, AOI and visibility changes, invalid input") {
    interest::thread_pool pool(2);
    auto engine = make_engine(&pool);
    scenario_hysteresis(engine.get());
    scenario_teleports(engine.get());
    scenario_visibility(engine.get());
    scenario_carry(engine.get());  // a handoff's carried set, through load_previous on the device
    scenario_non_finite(engine.get());
  }

  TEST_CASE("GPU interest engine: switching to and from the host path keeps the sets") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    interest::thread_pool pool(3);
    interest::grid_finder grid(&pool);
    auto engine = make_engine(&pool);
    world a(seed, 400, false), b(seed, 400, false);
    interest_tracker host(grid, &pool, interest_options{3.0f, 0, 64});
    interest_tracker mixed(grid, &pool, interest_options{3.0f, 0, 64});
    std::vector<std::uint8_t> demand(4096, 0);  // half the slots: the others stay on the device
    for (std::size_t k = 0; k < demand.size(); k += 2) demand[k] = 1;
    mixed.set_view_demand(&demand);
    for (int tick = 0; tick < 60; ++tick) {
      CAPTURE(tick);
      // Engine for 7 ticks, host path for 5, and so on.
      mixed.set_engine(tick % 12 < 7 ? engine.get() : nullptr);
      REQUIRE_FALSE(host.update(a.store.columns()).has_value());
      REQUIRE_FALSE(mixed.update(b.store.columns()).has_value());
      CHECK(mixed.last_update_on_engine() == (tick % 12 < 7));
      CHECK(mixed.digest() == host.digest());
      a.step();
      b.step();
    }
  }

  TEST_CASE("GPU interest engine: degenerate sets equal the host path") {
    interest::thread_pool pool(4);
    auto engine = make_engine(&pool);
    entity_desc d;
    d.aoi_half_extent = {30, 30, 30};
    d.presence_half_extent = {1, 1, 1};
    d.sees = cb::normal;
    SUBCASE("no entities, then one") {
      entity_store s;
      same_as_host(s, *engine, 3, 4.0f, [&](entity_store& st, int t) {
        if (t == 0) (void)st.create(d);
      });
    }
    SUBCASE("2,000 entities on one point (every pair; the buffers overflow and grow)") {
      entity_store s;
      for (int k = 0; k < 2000; ++k) (void)s.create(d);
      same_as_host(s, *engine, 4, 4.0f, [&](entity_store& st, int t) {
        auto pos = st.positions();
        for (std::size_t i = 0; i < st.size(); i += 3) pos[i].x += 20.0f * static_cast<float>(t + 1);
      });
    }
    SUBCASE("big bodies (kept out of the grid) among small ones, a world-wide AOI, blind observers") {
      std::mt19937_64 rng(fresh_seed());
      std::uniform_real_distribution<float> u(0, 2000);
      entity_store s;
      for (int k = 0; k < 3000; ++k) {
        entity_desc e = d;
        e.position = {u(rng), u(rng), 0};
        if (k % 100 == 0) e.presence_half_extent = {300, 250, 5};  // covers far more than 64 cells
        if (k % 500 == 1) e.aoi_half_extent = {2000, 2000, 10};    // sees the whole world
        if (k % 7 == 2) e.sees = 0;                                 // sees nothing
        if (k % 11 == 3) e.visibility_class = cb::stealth;
        (void)s.create(e);
      }
      same_as_host(s, *engine, 6, 4.0f, [&](entity_store& st, int) {
        auto pos = st.positions();
        std::uniform_real_distribution<float> step(-15, 15);
        for (std::size_t i = 0; i < st.size(); ++i) pos[i] = {pos[i].x + step(rng), pos[i].y + step(rng), 0};
      });
    }
    SUBCASE("rows growing by half every tick, a tenth with bodies over ~30 cells (the grid overflows as the rows grow)") {
      std::mt19937_64 rng(fresh_seed());
      std::uniform_real_distribution<float> u(0, 1500);
      entity_store s;
      const auto add = [&](entity_store& st, std::size_t count) {
        for (std::size_t k = 0; k < count; ++k) {
          entity_desc e = d;
          e.position = {u(rng), u(rng), 0};
          if (rng() % 10 == 0) e.presence_half_extent = {50, 50, 2};
          (void)st.create(e);
        }
      };
      add(s, 200);
      same_as_host(s, *engine, 9, 4.0f, [&](entity_store& st, int) { add(st, st.size() / 2); });
    }
    SUBCASE("only some rows' sets copied back (view demand); the rest fetched on access") {
      std::mt19937_64 rng(fresh_seed());
      std::uniform_real_distribution<float> u(0, 600);
      entity_store s;
      for (int k = 0; k < 4000; ++k) {
        entity_desc e = d;
        e.position = {u(rng), u(rng), 0};
        (void)s.create(e);
      }
      std::vector<std::uint8_t> demand(s.slot_count(), 0);
      for (std::size_t k = 0; k < demand.size(); k += 3) demand[k] = 1;
      same_as_host(
          s, *engine, 6, 4.0f,
          [&](entity_store& st, int) {
            auto pos = st.positions();
            std::uniform_real_distribution<float> step(-6, 6);
            for (std::size_t i = 0; i < st.size(); ++i) pos[i] = {pos[i].x + step(rng), pos[i].y + step(rng), 0};
          },
          &demand);
    }
    SUBCASE("entities spread in z, touching boxes on a lattice") {
      entity_store s;
      for (int x = 0; x < 30; ++x) {
        for (int y = 0; y < 30; ++y) {
          entity_desc e = d;
          e.position = {static_cast<float>(x) * 10.0f, static_cast<float>(y) * 10.0f, static_cast<float>((x + y) % 5) * 8.0f};
          e.aoi_half_extent = {9, 9, 4};
          e.presence_half_extent = {1, 1, 4};  // AOI + body = 10: neighbours touch exactly
          (void)s.create(e);
        }
      }
      same_as_host(s, *engine, 4, 0.0f, [&](entity_store& st, int t) {
        auto pos = st.positions();
        for (std::size_t i = t % 2; i < st.size(); i += 2) pos[i].x += 0.5f;
      });
    }
  }

  TEST_CASE("GPU interest engine: zone worlds give the host path's per-tick digests") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    interest::thread_pool pool(4);
    interest::grid_finder cpu(&pool);
    auto engine = make_engine(&pool);
    const zone_config small = small_config(seed);
    CHECK(run_digests(small, cpu, &pool, 60, 8, false, engine.get()) == run_digests(small, cpu, &pool, 60));
    zone_config cfg;  // the default world and NPC mix
    cfg.seed = seed;
    cfg.npc_count = 20000;
    cfg.npc_speed = 20;
    CHECK(run_digests(cfg, cpu, &pool, 20, 32, false, engine.get()) == run_digests(cfg, cpu, &pool, 20, 32));
  }

  TEST_CASE("small fast zone: CPU and GPU finders give the same per-tick digests") {
    REQUIRE(device_present);
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    const zone_config cfg = small_config(seed);
    interest::thread_pool one(1), four(4);
    interest::grid_finder cpu(&one);
    const auto reference = run_digests(cfg, cpu, &one, 60);

    gpu::pbig_options direct;
    direct.decode_pool = &four;
    auto gpu_direct = make_gpu(direct);
    CHECK(run_digests(cfg, *gpu_direct, &four, 60) == reference);
    CHECK(run_digests(cfg, *gpu_direct, nullptr, 60) == reference);  // the same finder again: plan reuse
    // zone-server's way: the tracker reads the finder's own result buffer (pair_finder::find_view).
    CHECK(run_digests(cfg, *gpu_direct, &four, 60, 8, true) == reference);

    gpu::pbig_options paper = direct;
    paper.direct_output = false;
    paper.initial_output_pairs = 64;  // overflow and re-run inside the tick loop
    auto gpu_paper = make_gpu(paper);
    CHECK(run_digests(cfg, *gpu_paper, &four, 60) == reference);
  }

  TEST_CASE("default-sized zone with 20,000 NPCs: CPU and GPU finders agree tick by tick") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    zone_config cfg;  // the default world and NPC mix
    cfg.seed = seed;
    cfg.npc_count = 20000;
    cfg.npc_speed = 20;
    interest::thread_pool pool(4);
    interest::grid_finder cpu(&pool);
    gpu::pbig_options opt;
    opt.decode_pool = &pool;
    auto gpu_finder = make_gpu(opt);
    const auto reference = run_digests(cfg, cpu, &pool, 20, 32);
    CHECK(run_digests(cfg, *gpu_finder, &pool, 20, 32) == reference);
    CHECK(run_digests(cfg, *gpu_finder, &pool, 20, 32, true) == reference);
    for (const char* name : {"lbvh", "auto"}) {
      CAPTURE(name);
      std::string why;
      auto f = gpu::make_finder(*gpu::parse_backend(name), &pool, &why);
      REQUIRE_MESSAGE(f != nullptr, why);
      CHECK(run_digests(cfg, *f, &pool, 20, 32, true) == reference);
    }
  }
}
