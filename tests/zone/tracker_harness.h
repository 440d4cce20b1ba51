// The interest tracker's test harness: a brute-force oracle that applies the rules of docs/zone.md
// literally, a random world of moving, teleporting, AOI-changing, stealthy and team entities, the
// per-tick check against the oracle, a two-entity fixture for hand-made scenarios, and per-tick
// digests. Shared by the host tests (test_interest_tracker.cpp) and the GPU engine's tests
// (test_zone_gpu.cpp): every helper takes an optional visibility engine for the tracker.
#pragma once

#include <doctest/doctest.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <map>
#include <random>

#include "../common/seeds.h"
#include "zone/zone.h"

namespace zone::test {
namespace cb = zone::interest::category_bits;

using id_list = std::vector<entity_id>;

// ---- the oracle ------------------------------------------------------------------------------

struct fbox {
  float lo[3], hi[3];
};
inline fbox around(const vec3& p, const vec3& half) {
  return {{p.x - half.x, p.y - half.y, p.z - half.z}, {p.x + half.x, p.y + half.y, p.z + half.z}};
}
inline fbox around_grown(const vec3& p, const vec3& half, float h) {
  return around(p, {half.x + h, half.y + h, half.z + h});
}
inline bool meets(const fbox& a, const fbox& b) {
  for (int d = 0; d < 3; ++d) {
    if (!(a.lo[d] <= b.hi[d] && b.lo[d] <= a.hi[d])) return false;
  }
  return true;
}

struct row_result {
  id_list visible, enters, leaves;
};

/// Every observer against every target, O(n^2), with the rules written out one by one.
class oracle {
 public:
  /// interest_tracker::carry_visible's rule: at the next step, `observer`'s previous set is exactly
  /// the targets carried for it since the last step (sorted, unique), less itself, null and
  /// handles not in the store then; an observer not in the store then is not carried.
  void carry(entity_id observer, const id_list& targets) {
    if (observer == null_entity) return;
    auto& p = pending_[observer];
    p.insert(p.end(), targets.begin(), targets.end());
  }

  std::map<entity_id, row_result> step(const entity_store& s, float h, std::uint32_t cap) {
    for (const auto& [o, targets] : pending_) {
      if (s.index_of(o) == entity_store::npos) continue;
      id_list t;
      for (const entity_id v : targets) {
        if (v != null_entity && v != o && s.index_of(v) != entity_store::npos) t.push_back(v);
      }
      std::sort(t.begin(), t.end());
      t.erase(std::unique(t.begin(), t.end()), t.end());
      prev_[o] = std::move(t);
    }
    pending_.clear();
    std::map<entity_id, row_result> out;
    std::map<entity_id, id_list> next;
    const auto ids = s.ids();
    const auto pos = s.positions();
    for (std::size_t i = 0; i < s.size(); ++i) {
      const fbox aoi = around(pos[i], s.aoi_half_extents()[i]);
      const fbox grown = around_grown(pos[i], s.aoi_half_extents()[i], h);
      const id_list& old = prev_[ids[i]];
      std::vector<std::pair<entity_id, std::size_t>> kept;
      for (std::size_t j = 0; j < s.size(); ++j) {
        if (j == i) continue;                                                // never itself
        if ((s.visibility_classes()[j] & s.sees()[i]) == 0) continue;       // visibility
        const fbox body = around(pos[j], s.presence_half_extents()[j]);
        const bool was = std::binary_search(old.begin(), old.end(), ids[j]);
        if (meets(body, aoi) || (was && meets(body, grown))) kept.emplace_back(ids[j], j);  // enter / stay
      }
      if (cap != 0 && kept.size() > cap) {
        const auto key = [&](const std::pair<entity_id, std::size_t>& e) {
          const float dx = pos[i].x - pos[e.second].x, dy = pos[i].y - pos[e.second].y, dz = pos[i].z - pos[e.second].z;
          return std::make_pair(std::bit_cast<std::uint32_t>(dx * dx + dy * dy + dz * dz), e.first);
        };
        std::sort(kept.begin(), kept.end(), [&](const auto& a, const auto& b) { return key(a) < key(b); });
        kept.resize(cap);
      }
      row_result r;
      for (const auto& e : kept) r.visible.push_back(e.first);
      std::sort(r.visible.begin(), r.visible.end());
      std::set_difference(r.visible.begin(), r.visible.end(), old.begin(), old.end(), std::back_inserter(r.enters));
      std::set_difference(old.begin(), old.end(), r.visible.begin(), r.visible.end(), std::back_inserter(r.leaves));
      next[ids[i]] = r.visible;
      out[ids[i]] = std::move(r);
    }
    prev_ = std::move(next);
    return out;
  }

 private:
  std::map<entity_id, id_list> prev_;
  std::map<entity_id, id_list> pending_;  // carry's, until the next step
};

// ---- a random world --------------------------------------------------------------------------

/// Entities moving in a box world, with teleports, AOI changes, visibility changes, creates and
/// destroys. In lattice mode every coordinate and extent is a multiple of 0.5, so boxes often
/// touch exactly (closed boxes: touching counts).
class world {
 public:
  world(std::uint64_t seed, std::size_t n, bool lattice) : rng_(seed), lattice_(lattice) {
    for (std::size_t k = 0; k < n; ++k) (void)store.create(random_desc());
  }

  // Freed slots reused at once, the most recently freed first (the default waits for 1,024 other
  // frees): every destroy then meets a reused slot, which the tracker must not take for the old entity.
  entity_store store{max_entities, {.slot_reuse_after = 0}};

  void step() {
    auto pos = store.positions();
    auto vel = store.velocities();
    for (std::size_t i = 0; i < store.size(); ++i) {
      vec3& p = pos[i];
      vec3& v = vel[i];
      p = {p.x + v.x, p.y + v.y, p.z + v.z};
      if (p.x < 0 || p.x > side_) v.x = -v.x;
      if (p.y < 0 || p.y > side_) v.y = -v.y;
      if (p.z < 0 || p.z > height_) v.z = -v.z;
      p = {std::clamp(p.x, 0.f, side_), std::clamp(p.y, 0.f, side_), std::clamp(p.z, 0.f, height_)};
    }
    // Random events on a snapshot of the handles.
    const std::vector<entity_id> ids(store.ids().begin(), store.ids().end());
    for (const entity_id id : ids) {
      const auto desc = store.get(id);
      if (!desc) continue;
      const double r = unit();
      if (r < 0.02) {  // teleport: anywhere, or a short hop (crosses AOI edges both ways)
        const vec3 p = desc->position;
        const vec3 to = unit() < 0.5 ? random_pos() : snap({p.x + uni(-30, 30), p.y + uni(-30, 30), p.z});
        store.set_position(id, clamp(to));
      } else if (r < 0.04) {
        store.set_aoi_half_extent(id, random_aoi());
      } else if (r < 0.05) {
        const auto [cls, sees] = random_visibility();
        store.set_visibility(id, cls, sees);
      } else if (r < 0.055) {
        store.set_presence_half_extent(id, random_body());
      } else if (r < 0.065) {
        store.destroy(id);
      }
    }
    const int births = static_cast<int>(rng_() % 4);
    for (int b = 0; b < births; ++b) (void)store.create(random_desc());
  }

 private:
  double unit() { return std::uniform_real_distribution<double>(0, 1)(rng_); }
  float uni(float lo, float hi) { return std::uniform_real_distribution<float>(lo, hi)(rng_); }
  float snap(float x) const { return lattice_ ? std::round(x * 2) / 2 : x; }
  vec3 snap(const vec3& v) const { return {snap(v.x), snap(v.y), snap(v.z)}; }
  vec3 clamp(const vec3& p) const {
    return {std::clamp(p.x, 0.f, side_), std::clamp(p.y, 0.f, side_), std::clamp(p.z, 0.f, height_)};
  }
  vec3 random_pos() { return snap({uni(0, side_), uni(0, side_), uni(0, height_)}); }
  vec3 random_aoi() {
    constexpr float tiers[] = {6, 15, 30, 60};
    const float t = tiers[rng_() % 4] * uni(0.8f, 1.2f);
    return snap({t, t, std::min(t, 20.f)});
  }
  vec3 random_body() {
    const float b = unit() < 0.03 ? uni(10, 25) : uni(0.5f, 2);  // a few boss-sized footprints
    return snap({b, b, 2 * b});
  }
  std::pair<std::uint32_t, std::uint32_t> random_visibility() {
    const double r = unit();
    const std::uint32_t cls = r < 0.7 ? cb::normal : r < 0.82 ? cb::stealth : r < 0.91 ? cb::team_red : cb::team_blue;
    std::uint32_t sees = cb::normal | cb::team_red | cb::team_blue;
    if (unit() < 0.15) sees = cb::normal | (cls & (cb::team_red | cb::team_blue));  // sees only its own team
    if (unit() < 0.1 || cls == cb::stealth) sees |= cb::stealth;
    if (unit() < 0.02) sees = 0;  // sees nothing at all
    return {cls, sees};
  }
  entity_desc random_desc() {
    entity_desc d;
    d.position = random_pos();
    const float speed = lattice_ ? 0.5f * static_cast<float>(rng_() % 5) : uni(0, 3);
    const float angle = uni(0, 6.2831853f);
    d.velocity = lattice_ ? vec3{speed * static_cast<float>(static_cast<int>(rng_() % 3) - 1),
                                 speed * static_cast<float>(static_cast<int>(rng_() % 3) - 1), 0}
                          : vec3{speed * std::cos(angle), speed * std::sin(angle), uni(-0.2f, 0.2f)};
    d.aoi_half_extent = random_aoi();
    d.presence_half_extent = random_body();
    std::tie(d.visibility_class, d.sees) = random_visibility();
    return d;
  }

  std::mt19937_64 rng_;
  bool lattice_;
  float side_ = 400, height_ = 30;
};

/// Checks one tick of the tracker against the oracle's result, and the rules directly.
inline void check_tick(const interest_tracker& t, const entity_store& s, std::map<entity_id, row_result>& expected, float h,
                bool capped) {
  REQUIRE(t.observer_count() == s.size());
  const auto pos = s.positions();
  for (std::size_t row = 0; row < s.size(); ++row) {
    const entity_id a = s.ids()[row];
    REQUIRE(t.observer(row) == a);
    REQUIRE(t.row_of(a) == row);
    const row_result& want = expected[a];
    const auto vis = t.visible(row), en = t.enters(row), lv = t.leaves(row);
    CHECK(id_list(vis.begin(), vis.end()) == want.visible);
    CHECK(id_list(en.begin(), en.end()) == want.enters);
    CHECK(id_list(lv.begin(), lv.end()) == want.leaves);
    // The rules, independently of the oracle's bookkeeping.
    const fbox aoi = around(pos[row], s.aoi_half_extents()[row]);
    const fbox grown = around_grown(pos[row], s.aoi_half_extents()[row], h);
    for (const entity_id b : vis) {
      const std::size_t j = s.index_of(b);
      REQUIRE(j != entity_store::npos);
      CHECK(b != a);
      CHECK((s.visibility_classes()[j] & s.sees()[row]) != 0);
      CHECK(meets(around(pos[j], s.presence_half_extents()[j]), grown));  // never visible beyond R + h
    }
    for (const entity_id b : en) {
      const std::size_t j = s.index_of(b);
      REQUIRE(j != entity_store::npos);
      CHECK(meets(around(pos[j], s.presence_half_extents()[j]), aoi));  // enters only at R
    }
    for (const entity_id b : lv) {
      const std::size_t j = s.index_of(b);
      // Leaves only when destroyed, beyond R + h, no longer allowed, or cut by the cap.
      const bool gone = j == entity_store::npos || !meets(around(pos[j], s.presence_half_extents()[j]), grown) ||
                        (s.visibility_classes()[j] & s.sees()[row]) == 0;
      CHECK((gone || capped));
    }
  }
}

struct run_config {
  std::size_t entities;
  float hysteresis;
  std::uint32_t cap;
  bool lattice;
  unsigned threads;
};

inline void run_against_oracle(std::uint64_t seed, const run_config& c, int ticks,
                        interest::visibility_engine* engine = nullptr) {
  CAPTURE(seed);
  CAPTURE(c.entities);
  CAPTURE(c.hysteresis);
  CAPTURE(c.cap);
  CAPTURE(c.lattice);
  CAPTURE(c.threads);
  world w(seed, c.entities, c.lattice);
  interest::thread_pool pool(c.threads);
  interest::grid_finder finder(&pool);
  interest_options opt;
  opt.hysteresis = c.hysteresis;
  opt.max_visible = c.cap;
  opt.rows_per_task = 7;  // many small tasks: exercises the chunking
  interest_tracker tracker(finder, &pool, opt);
  if (engine != nullptr) tracker.set_engine(engine);
  oracle o;
  std::uint64_t enters = 0, leaves = 0, stays_in_margin = 0;
  for (int tick = 0; tick < ticks; ++tick) {
    CAPTURE(tick);
    REQUIRE_FALSE(tracker.update(w.store.columns()).has_value());
    if (engine != nullptr && c.cap == 0) {
      REQUIRE(tracker.engine_error().empty());
      REQUIRE(tracker.last_update_on_engine());  // the engine, not the host path, is under test
    }
    auto expected = o.step(w.store, c.hysteresis, c.cap);
    check_tick(tracker, w.store, expected, c.hysteresis, c.cap != 0);
    enters += tracker.stats().enters;
    leaves += tracker.stats().leaves;
    // Count visible targets held only by the hysteresis (outside R, inside R + h).
    for (std::size_t row = 0; row < w.store.size(); ++row) {
      const fbox aoi = around(w.store.positions()[row], w.store.aoi_half_extents()[row]);
      for (const entity_id b : tracker.visible(row)) {
        const std::size_t j = w.store.index_of(b);
        if (!meets(around(w.store.positions()[j], w.store.presence_half_extents()[j]), aoi)) ++stays_in_margin;
      }
    }
    w.step();
  }
  // The run exercised what it claims to.
  CHECK(enters > 0);
  CHECK(leaves > 0);
  if (c.hysteresis > 0) CHECK(stays_in_margin > 0);
}

/// Two-entity fixture for hand-made scenarios: observer A at the origin, target B.
struct pair_fixture {
  // Freed slots reused at once, the most recently freed first (the default waits for 1,024 other
  // frees): every destroy then meets a reused slot, which the tracker must not take for the old entity.
  entity_store store{max_entities, {.slot_reuse_after = 0}};
  interest::brute_force_finder finder;
  interest_tracker tracker;
  entity_id a, b;
  bool on_engine = false;
  explicit pair_fixture(float h, interest::visibility_engine* engine = nullptr)
      : tracker(finder, nullptr, interest_options{h, 0, 256}) {
    if (engine != nullptr) tracker.set_engine(engine);
    on_engine = engine != nullptr;
    entity_desc da;
    da.aoi_half_extent = {10, 10, 10};
    da.presence_half_extent = {0.5f, 0.5f, 0.5f};
    da.sees = cb::normal;
    a = store.create(da);
    entity_desc db = da;
    db.position = {30, 0, 0};
    db.aoi_half_extent = {0, 0, 0};
    b = store.create(db);
  }
  struct seen {
    bool visible, entered, left;
  };
  /// Runs a tick and reports A's view of B.
  seen tick() {
    REQUIRE_FALSE(tracker.update(store.columns()).has_value());
    if (on_engine) REQUIRE(tracker.last_update_on_engine());
    const std::size_t r = tracker.row_of(a);
    REQUIRE(r != entity_store::npos);
    const auto has = [&](std::span<const entity_id> s) { return std::find(s.begin(), s.end(), b) != s.end(); };
    return {has(tracker.visible(r)), has(tracker.enters(r)), has(tracker.leaves(r))};
  }
  void move_b(float x) { REQUIRE(store.set_position(b, {x, 0, 0})); }
};

inline std::vector<std::uint64_t> digests(std::uint64_t seed, interest::pair_finder& finder, interest::thread_pool* pool,
                                   std::uint32_t rows_per_task, std::uint32_t cap, int ticks,
                                   interest::visibility_engine* engine = nullptr, std::size_t entities = 400) {
  world w(seed, entities, false);
  interest_tracker tracker(finder, pool, interest_options{3.0f, cap, rows_per_task});
  if (engine != nullptr) tracker.set_engine(engine);
  std::vector<std::uint64_t> out;
  for (int tick = 0; tick < ticks; ++tick) {
    REQUIRE_FALSE(tracker.update(w.store.columns()).has_value());
    out.push_back(tracker.digest());
    w.step();
  }
  return out;
}

// ---- hand-made scenarios (the tracker with or without an engine) --------------------------------

inline void scenario_hysteresis(interest::visibility_engine* engine = nullptr) {
  // A's AOI is [-10, 10]; B's body is +-0.5; h = 2. B enters when x - 0.5 <= 10 (x <= 10.5)
  // and leaves only when x - 0.5 > 12 (x > 12.5).
  pair_fixture f(2.0f, engine);
  CHECK_FALSE(f.tick().visible);
  f.move_b(11.0f);  // inside R + h but never entered: stays out
  CHECK_FALSE(f.tick().visible);
  f.move_b(10.5f);  // touches R exactly (closed boxes): enters
  auto s = f.tick();
  CHECK(s.visible);
  CHECK(s.entered);
  f.move_b(12.5f);  // touches R + h exactly: stays
  s = f.tick();
  CHECK(s.visible);
  CHECK_FALSE(s.entered);
  CHECK_FALSE(s.left);
  f.move_b(12.0f);
  CHECK(f.tick().visible);
  f.move_b(12.75f);  // beyond R + h: leaves
  s = f.tick();
  CHECK_FALSE(s.visible);
  CHECK(s.left);
  f.move_b(11.0f);  // back inside the margin only: does not re-enter
  CHECK_FALSE(f.tick().visible);
  f.move_b(-10.5f);  // the other side
  CHECK(f.tick().entered);
}

inline void scenario_teleports(interest::visibility_engine* engine = nullptr) {
  pair_fixture f(2.0f, engine);
  f.move_b(5.0f);
  CHECK(f.tick().entered);
  f.move_b(500.0f);  // teleport out: leaves now
  CHECK(f.tick().left);
  f.move_b(-5.0f);  // teleport in: enters now (body [-5.5, -4.5] meets [-10, 10])
  CHECK(f.tick().entered);
  REQUIRE(f.store.set_aoi_half_extent(f.a, {1, 1, 1}));  // shrink: [-3, 3] with the margin; -4.5 is beyond
  CHECK(f.tick().left);
  REQUIRE(f.store.set_aoi_half_extent(f.a, {4.6f, 4.6f, 4.6f}));  // grow: -4.5 is inside [-4.6, 4.6]
  CHECK(f.tick().entered);
  REQUIRE(f.store.set_aoi_half_extent(f.a, {2.6f, 2.6f, 2.6f}));  // outside R = 2.6, inside R + h = 4.6: stays
  auto s = f.tick();
  CHECK(s.visible);
  CHECK_FALSE(s.left);
  // The observer teleports away.
  REQUIRE(f.store.set_position(f.a, {1000, 0, 0}));
  CHECK(f.tick().left);
}

inline void scenario_visibility(interest::visibility_engine* engine = nullptr) {
  pair_fixture f(2.0f, engine);
  f.move_b(5.0f);
  CHECK(f.tick().entered);
  REQUIRE(f.store.set_visibility(f.b, cb::stealth, cb::normal));  // A does not see stealth
  auto s = f.tick();
  CHECK(s.left);
  CHECK_FALSE(s.visible);
  REQUIRE(f.store.set_visibility(f.a, cb::normal, cb::normal | cb::stealth));  // A becomes a detector
  CHECK(f.tick().entered);
  REQUIRE(f.store.set_visibility(f.b, cb::team_red, cb::normal));
  CHECK(f.tick().left);  // A sees normal and stealth only
  REQUIRE(f.store.set_visibility(f.a, cb::normal, cb::team_red));
  CHECK(f.tick().entered);
  const entity_id b = f.b;
  REQUIRE(f.store.destroy(b));
  REQUIRE_FALSE(f.tracker.update(f.store.columns()).has_value());
  const std::size_t r = f.tracker.row_of(f.a);
  REQUIRE(f.tracker.leaves(r).size() == 1);
  CHECK(f.tracker.leaves(r)[0] == b);
  CHECK(f.tracker.row_of(b) == entity_store::npos);
  // A new entity in the reused slot is a different handle and enters.
  entity_desc d;
  d.position = {1, 1, 1};
  d.visibility_class = cb::team_red;  // what A sees now
  const entity_id c = f.store.create(d);
  CHECK(slot_of(c) == slot_of(b));
  CHECK(c != b);
  REQUIRE_FALSE(f.tracker.update(f.store.columns()).has_value());
  const std::size_t r2 = f.tracker.row_of(f.a);
  REQUIRE(f.tracker.enters(r2).size() == 1);
  CHECK(f.tracker.enters(r2)[0] == c);
  CHECK(f.tracker.leaves(r2).empty());
}

inline void scenario_carry(interest::visibility_engine* engine = nullptr) {
  // A's AOI is [-10, 10]; B's body is +-0.5; h = 4: in the margin for 10.5 < x <= 14.5.
  pair_fixture f(4.0f, engine);
  f.move_b(12.0f);
  CHECK_FALSE(f.tick().visible);  // never entered
  const entity_id carried[] = {f.b, f.a, null_entity, f.b};  // itself, null and a repeat ignored
  f.tracker.carry_visible(f.a, carried);
  auto s = f.tick();
  CHECK(s.visible);  // held by the margin, as if it had entered before
  CHECK_FALSE(s.entered);
  CHECK_FALSE(s.left);
  f.move_b(14.0f);
  CHECK(f.tick().visible);
  f.move_b(15.0f);  // beyond R + h: leaves
  CHECK(f.tick().left);
  const entity_id just_b[] = {f.b};
  f.tracker.carry_visible(f.a, just_b);  // carried beyond R + h: leaves at once
  s = f.tick();
  CHECK_FALSE(s.visible);
  CHECK(s.left);
  f.move_b(12.0f);
  CHECK_FALSE(f.tick().visible);
  // A class A does not see: not kept.
  REQUIRE(f.store.set_visibility(f.b, cb::stealth, cb::normal));
  f.tracker.carry_visible(f.a, just_b);
  CHECK_FALSE(f.tick().visible);
  REQUIRE(f.store.set_visibility(f.b, cb::normal, cb::normal));
  // The carried set replaces A's previous one: B, visible in the margin, is dropped by an empty
  // carry, without a leave (the events are relative to the carried set).
  f.tracker.carry_visible(f.a, just_b);
  CHECK(f.tick().visible);
  f.tracker.carry_visible(f.a, {});
  s = f.tick();
  CHECK_FALSE(s.visible);
  CHECK_FALSE(s.left);
  f.move_b(9.0f);  // within the AOI: enters anew
  CHECK(f.tick().entered);
  f.move_b(12.0f);
  // Pending across a refused update.
  f.tracker.carry_visible(f.a, just_b);
  f.store.positions()[f.store.index_of(f.b)].x = std::nanf("");
  REQUIRE(f.tracker.update(f.store.columns()).has_value());
  CHECK(f.tracker.carried_pending() > 0);
  f.move_b(12.0f);
  s = f.tick();
  CHECK(s.visible);
  CHECK_FALSE(s.entered);
  CHECK(f.tracker.carried_pending() == 0);
}

inline void scenario_non_finite(interest::visibility_engine* engine = nullptr) {
  pair_fixture f(1.0f, engine);
  f.move_b(5.0f);
  CHECK(f.tick().entered);
  const std::uint64_t before = f.tracker.digest();
  f.store.positions()[f.store.index_of(f.b)].x = std::nanf("");
  const auto err = f.tracker.update(f.store.columns());
  REQUIRE(err.has_value());
  CHECK(err->message.find("entity " + std::to_string(f.b)) != std::string::npos);
  CHECK(f.tracker.digest() == before);
}

}  // namespace zone::test
