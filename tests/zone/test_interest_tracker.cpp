// The interest tracker against a brute-force oracle that applies the rules of docs/zone.md
// literally, over many ticks of moving, teleporting, AOI-changing, stealthy and team entities;
// hand-made scenarios for hysteresis, teleports, AOI changes and visibility; determinism across
// finders and thread counts; the host reference engine as the set engine, engines switched between
// ticks, and the output of fixed worlds pinned. The harness (oracle, world, checks) is tracker_harness.h.
#include <doctest/doctest.h>

#include <memory>

#include "tracker_harness.h"

using namespace zone;
using namespace zone::test;

TEST_SUITE("zone.interest_tracker") {
  TEST_CASE("events match the brute-force oracle over many ticks") {
    const run_config configs[] = {
        {250, 4.0f, 0, false, 1}, {250, 4.0f, 0, true, 2},  {300, 0.0f, 0, false, 3},
        {200, 10.0f, 0, true, 1}, {250, 3.0f, 6, false, 2}, {200, 2.5f, 3, true, 3},
    };
    for (const auto& c : configs) run_against_oracle(fresh_seed(), c, 120);
  }

  TEST_CASE("hysteresis: enter at R, leave only beyond R + h") {
    scenario_hysteresis();
  }

  TEST_CASE("teleports and AOI changes take effect the same tick") {
    scenario_teleports();
  }

  TEST_CASE("stealth, teams and destroyed entities") {
    scenario_visibility();
  }

  TEST_CASE("non-finite positions are rejected naming the entity, and nothing changes") {
    scenario_non_finite();
  }

  TEST_CASE("apply_pairs: external pairs give the same result; mismatched input is refused") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    world w(seed, 150, false);
    interest::grid_finder finder;
    interest::brute_force_finder brute;
    interest_tracker a(finder), b(finder);
    interest::box_set boxes;
    interest::pair_list pairs;
    for (int tick = 0; tick < 20; ++tick) {
      REQUIRE_FALSE(a.update(w.store.columns()).has_value());
      b.build_boxes(w.store.columns(), boxes);
      REQUIRE_FALSE(brute.find(boxes, pairs).has_value());
      std::shuffle(pairs.begin(), pairs.end(), std::mt19937_64(seed + tick));  // any order
      REQUIRE_FALSE(b.apply_pairs(w.store.columns(), boxes, pairs).has_value());
      CHECK(a.digest() == b.digest());
      w.step();
    }
    const std::uint64_t before = b.digest();
    b.build_boxes(w.store.columns(), boxes);
    boxes.resize(boxes.size() - 2);
    CHECK(b.apply_pairs(w.store.columns(), boxes, pairs).has_value());
    b.build_boxes(w.store.columns(), boxes);
    pairs.push_back({0, static_cast<interest::box_id>(boxes.size())});
    CHECK(b.apply_pairs(w.store.columns(), boxes, pairs).has_value());
    CHECK(b.digest() == before);
  }

  TEST_CASE("determinism: same seed, same per-tick hashes with 1 and several threads and any finder") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    for (const std::uint32_t cap : {0u, 5u}) {
      CAPTURE(cap);
      interest::thread_pool one(1), three(3);
      interest::grid_finder grid_one(&one), grid_three(&three);
      interest::brute_force_finder brute(&three);
      const auto reference = digests(seed, grid_one, &one, 256, cap, 60);
      CHECK(digests(seed, grid_one, &one, 256, cap, 60) == reference);  // same run twice
      CHECK(digests(seed, grid_three, &three, 256, cap, 60) == reference);
      CHECK(digests(seed, grid_three, &three, 13, cap, 60) == reference);
      CHECK(digests(seed, brute, &three, 64, cap, 60) == reference);
      CHECK(digests(seed, grid_three, nullptr, 256, cap, 60) == reference);
      // A different seed gives a different history (the hash is not trivially constant).
      CHECK(digests(seed + 1, grid_one, &one, 256, cap, 60) != reference);
    }
  }
}

namespace {

/// carry_visible on random worlds against the oracle's rule (tracker_harness.h, oracle::carry):
/// every tick a few observers get carried sets (targets around them, within and beyond AOI + h,
/// anywhere, with the observer itself, null, dead and unknown handles, shuffled; one observer in
/// two calls), one of them a new entity in the slot of one just destroyed (slot reuse), one a
/// new entity; the whole output is checked against the oracle and the run must have exercised
/// each case.
void run_carry_against_oracle(std::uint64_t seed, const run_config& c, int ticks,
                              interest::visibility_engine* engine = nullptr) {
  CAPTURE(seed);
  CAPTURE(c.hysteresis);
  CAPTURE(c.cap);
  CAPTURE(c.lattice);
  world w(seed, c.entities, c.lattice);
  interest::thread_pool pool(c.threads);
  interest::grid_finder finder(&pool);
  interest_tracker tracker(finder, &pool, interest_options{c.hysteresis, c.cap, 7});
  if (engine != nullptr) tracker.set_engine(engine);
  oracle o;
  std::mt19937_64 rng(seed ^ 0x9e3779b97f4a7c15ull);
  const float h = c.hysteresis;
  std::uint64_t kept_in_margin = 0, beyond = 0, filtered = 0, new_rows = 0, reused = 0;
  id_list dead;  // handles of destroyed entities
  for (int tick = 0; tick < ticks; ++tick) {
    CAPTURE(tick);
    struct carried {
      entity_id observer;
      id_list targets, before;  // before: its visible set in the last update
      bool had_row;
    };
    std::vector<carried> carries;
    if (tick > 0) {
      auto& st = w.store;
      // A new entity in the slot of one the last update had (another generation).
      const entity_id victim = st.ids()[rng() % st.size()];
      entity_desc d = *st.get(victim);
      REQUIRE(st.destroy(victim));
      dead.push_back(victim);
      const entity_id fresh = st.create(d);
      REQUIRE(fresh != null_entity);
      const bool reuse = slot_of(fresh) == slot_of(victim) && tracker.row_of(victim) != interest_tracker::npos;
      // And one more new entity (a new row).
      d.position = {d.position.x + 3, d.position.y, d.position.z};
      const entity_id other = st.create(d);
      REQUIRE(other != null_entity);
      const auto ids = st.ids();
      const auto pos = st.positions();
      for (int k = 0; k < 8; ++k) {
        const entity_id ob = k == 0 ? fresh : k == 1 ? other : ids[rng() % ids.size()];
        const std::size_t i = st.index_of(ob);
        const fbox around_ob = around_grown(pos[i], st.aoi_half_extents()[i], 2 * h + 2);
        carried cr{ob, {}, {}, tracker.row_of(ob) != interest_tracker::npos};
        for (std::size_t j = 0; j < st.size(); ++j) {
          if (meets(around(pos[j], st.presence_half_extents()[j]), around_ob) && rng() % 3 != 0) cr.targets.push_back(ids[j]);
        }
        cr.targets.push_back(ids[rng() % ids.size()]);  // anywhere
        cr.targets.push_back(ob);                       // itself
        cr.targets.push_back(null_entity);
        cr.targets.push_back(dead[rng() % dead.size()]);  // a dead handle
        cr.targets.push_back(0x7ffffffeu);                // never a handle here
        std::shuffle(cr.targets.begin(), cr.targets.end(), rng);
        if (cr.had_row) {
          const auto v = tracker.visible(tracker.row_of(ob));
          cr.before.assign(v.begin(), v.end());
        }
        if (k == 2) {  // two calls add up
          const std::size_t half = cr.targets.size() / 2;
          tracker.carry_visible(ob, std::span(cr.targets).first(half));
          tracker.carry_visible(ob, std::span(cr.targets).subspan(half));
        } else {
          tracker.carry_visible(ob, cr.targets);
        }
        o.carry(ob, cr.targets);
        if (k == 0 && reuse) ++reused;
        carries.push_back(std::move(cr));
      }
      CHECK(tracker.carried_pending() > 0);
    }
    REQUIRE_FALSE(tracker.update(w.store.columns()).has_value());
    if (engine != nullptr && c.cap == 0) REQUIRE(tracker.last_update_on_engine());
    CHECK(tracker.carried_pending() == 0);
    auto expected = o.step(w.store, h, c.cap);
    check_tick(tracker, w.store, expected, h, c.cap != 0);
    // What the carried sets did (the oracle judged them; these count that each case came up).
    const auto& st = w.store;
    for (const auto& cr : carries) {
      const std::size_t i = st.index_of(cr.observer);
      const auto vis = tracker.visible(tracker.row_of(cr.observer));
      const fbox aoi = around(st.positions()[i], st.aoi_half_extents()[i]);
      const fbox grown = around_grown(st.positions()[i], st.aoi_half_extents()[i], h);
      for (const entity_id t : cr.targets) {
        const std::size_t j = st.index_of(t);
        if (j == entity_store::npos || t == cr.observer) continue;
        const fbox body = around(st.positions()[j], st.presence_half_extents()[j]);
        const bool now = std::binary_search(vis.begin(), vis.end(), t);
        const bool was = std::binary_search(cr.before.begin(), cr.before.end(), t);
        const bool seen = (st.visibility_classes()[j] & st.sees()[i]) != 0;
        if (now && !was && !meets(body, aoi)) {
          ++kept_in_margin;
          if (!cr.had_row) ++new_rows;
        }
        if (!now && meets(body, grown) && !seen) ++filtered;
        if (!now && !meets(body, grown)) ++beyond;
      }
    }
    w.step();
  }
  CHECK(kept_in_margin > 0);
  CHECK(new_rows > 0);
  CHECK(beyond > 0);
  CHECK(filtered > 0);
  CHECK(reused > 0);
}

struct pinned_run {
  std::uint64_t seed;
  float hysteresis;
  std::uint32_t cap;
  bool lattice;
  std::uint64_t digest;  ///< of every tick's tracker digest, in order
};

/// Fixed worlds (seed, margin, cap, lattice) run for 60 ticks; the hash of every tick's digest.
std::uint64_t pinned_digest(const pinned_run& r, interest::pair_finder& finder, interest::thread_pool* pool,
                            interest::visibility_engine* engine = nullptr) {
  world w(r.seed, 300, r.lattice);
  interest_tracker tracker(finder, pool, interest_options{r.hysteresis, r.cap, 64});
  if (engine != nullptr) tracker.set_engine(engine);
  std::uint64_t h = 0xcbf29ce484222325ull;
  for (int tick = 0; tick < 60; ++tick) {
    REQUIRE_FALSE(tracker.update(w.store.columns()).has_value());
    h = (h ^ tracker.digest()) * 0x100000001b3ull;
    w.step();
  }
  return h;
}

}  // namespace

TEST_SUITE("zone.interest_tracker") {
  TEST_CASE("pinned: the output of fixed worlds is the one recorded before the host step became an engine") {
    // Recorded with the tracker of 2fbebfa, whose host path (pairs -> sets, events, cap) was
    // interest_tracker's own code; interest::host_visibility_engine took it over unchanged. Any
    // change of a visible set, enter, leave or row order in 60 ticks of these worlds shows here.
    const pinned_run runs[] = {{1, 4.0f, 0, false, 11469895698779576218ull},
                               {2, 0.0f, 0, true, 17716891122987042873ull},
                               {3, 2.5f, 5, false, 6758721431865836063ull},
                               {4, 10.0f, 3, true, 9299729432517542371ull}};
    interest::thread_pool pool(2);
    interest::grid_finder grid(&pool);
    interest::brute_force_finder brute;
    for (const auto& r : runs) {
      CAPTURE(r.seed);
      CHECK(pinned_digest(r, grid, &pool) == r.digest);
      CHECK(pinned_digest(r, brute, nullptr) == r.digest);
      // The host reference engine given to the tracker as its engine (the GPU engine's place).
      interest::host_visibility_engine engine(brute);
      CHECK(pinned_digest(r, grid, &pool, &engine) == r.digest);
      // The candidates found on the presence grid instead of by a pair finder.
      interest::host_visibility_engine on_presence(brute, &pool,
                                                   {.rows_per_task = 64, .finder_view = true, .presence_grid = true});
      CHECK(pinned_digest(r, grid, &pool, &on_presence) == r.digest);
      CHECK(on_presence.last_on_grid());
    }
  }

  TEST_CASE("the host reference engine as the tracker's set engine: the oracle's events, caps included") {
    const run_config configs[] = {{200, 4.0f, 0, false, 2}, {200, 0.0f, 0, true, 1}, {200, 3.0f, 4, false, 3}};
    for (const auto& c : configs) {
      interest::thread_pool pool(2);
      interest::brute_force_finder brute(&pool);
      interest::host_visibility_engine engine(brute, &pool, {.rows_per_task = 3, .finder_view = false});
      run_against_oracle(fresh_seed(), c, 50, &engine);
      interest::host_visibility_engine on_presence(brute, &pool,
                                                   {.rows_per_task = 3, .finder_view = false, .presence_grid = true});
      run_against_oracle(fresh_seed(), c, 50, &on_presence);
      CHECK(on_presence.last_on_grid());
    }
  }

  TEST_CASE("carry_visible: a carried target stays within AOI + h and leaves beyond it, class-filtered; self, null and unknown handles ignored; new rows; slot reuse") {
    scenario_carry();
    const run_config configs[] = {{250, 4.0f, 0, false, 2}, {250, 3.0f, 0, true, 1}, {250, 4.0f, 5, false, 3}};
    for (const auto& c : configs) run_carry_against_oracle(fresh_seed(), c, 40);
    // The host reference engine as the set engine (the GPU engine's place): the same path.
    interest::thread_pool pool(2);
    interest::brute_force_finder brute(&pool);
    interest::host_visibility_engine engine(brute, &pool, {.rows_per_task = 3, .finder_view = false});
    scenario_carry(&engine);
    interest::host_visibility_engine engine2(brute, &pool);
    run_carry_against_oracle(fresh_seed(), configs[0], 40, &engine2);
  }

  TEST_CASE("carry_visible through apply_pairs: the same output as update") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    world w(seed, 200, false);
    interest::grid_finder finder;
    interest::brute_force_finder brute;
    interest_tracker a(finder), b(finder);
    interest::box_set boxes;
    interest::pair_list pairs;
    std::mt19937_64 rng(seed);
    for (int tick = 0; tick < 20; ++tick) {
      const auto ids = w.store.ids();
      for (int k = 0; k < 5; ++k) {
        const entity_id ob = ids[rng() % ids.size()];
        id_list targets;
        for (int m = 0; m < 20; ++m) targets.push_back(ids[rng() % ids.size()]);
        a.carry_visible(ob, targets);
        b.carry_visible(ob, targets);
      }
      REQUIRE_FALSE(a.update(w.store.columns()).has_value());
      b.build_boxes(w.store.columns(), boxes);
      REQUIRE_FALSE(brute.find(boxes, pairs).has_value());
      REQUIRE_FALSE(b.apply_pairs(w.store.columns(), boxes, pairs).has_value());
      CHECK(a.digest() == b.digest());
      CHECK(b.carried_pending() == 0);
      w.step();
    }
  }

  TEST_CASE("engines switched between ticks (set_engine, the cap on and off): the sets carry over") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    world wa(seed, 250, false), wb(seed, 250, false);
    interest::thread_pool pool(2);
    interest::grid_finder grid(&pool);
    interest::brute_force_finder brute;
    interest_tracker plain(grid, &pool, interest_options{3.0f, 0, 64});
    interest_tracker switched(grid, &pool, interest_options{3.0f, 0, 64});
    auto one = std::make_unique<interest::host_visibility_engine>(brute);
    interest::host_visibility_engine two(grid, &pool);
    for (int tick = 0; tick < 40; ++tick) {
      CAPTURE(tick);
      if (tick == 5) switched.set_engine(one.get());
      if (tick == 12) {
        switched.set_engine(&two);
        one.reset();  // the tracker's lists no longer point into it
      }
      if (tick == 18) switched.set_engine(nullptr);
      if (tick == 24) switched.set_engine(&two);
      if (tick == 30 || tick == 35) {  // the cap on, then off again
        for (interest_tracker* t : {&plain, &switched}) {
          auto o = t->options();
          o.max_visible = tick == 30 ? 4 : 0;
          t->set_options(o);
        }
      }
      REQUIRE_FALSE(plain.update(wa.store.columns()).has_value());
      REQUIRE_FALSE(switched.update(wb.store.columns()).has_value());
      CHECK(switched.last_update_on_engine() == ((tick >= 5 && tick < 18) || tick >= 24));
      CHECK(switched.digest() == plain.digest());
      CHECK(switched.stats().visible == plain.stats().visible);
      CHECK(switched.stats().enters == plain.stats().enters);
      CHECK(switched.stats().leaves == plain.stats().leaves);
      CHECK(switched.stats().capped == plain.stats().capped);
      if (tick == 32) CHECK(plain.stats().capped > 0);
      wa.step();
      wb.step();
    }
  }
}
