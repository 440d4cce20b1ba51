// The tick API (interest/interest_space.h) against a brute-force model of its contract: random
// entities and random calls (moves inside and across the hysteresis band, teleports, resizes,
// class changes, adds and removes), every step's visible sets, enters and leaves compared for
// every observer. Shared by the CPU tests (test_interest_space.cpp) and the GPU backend's
// (tests/zone/test_zone_gpu.cpp).
#pragma once

#include <doctest/doctest.h>

#include <algorithm>
#include <cstdint>
#include <map>
#include <random>
#include <set>
#include <vector>

#include "interest/interest_space.h"

namespace zone::test {

namespace ib = interest::category_bits;

/// The contract of interest_space::step, by brute force over every (observer, target) pair, with
/// the tracker's float expressions (AOI grown by h: p - (a + h), p + (a + h)).
class space_model {
 public:
  explicit space_model(float h) : h_(h) {}
  std::map<interest::entity_id, interest::entity_spec> live;

  struct lists {
    std::vector<interest::entity_id> visible, entered, left;
  };

  void step() {
    std::map<interest::entity_id, lists> next;
    for (const auto& [i, o] : live) {
      const auto prev_it = visible_.find(i);
      const std::set<interest::entity_id>* prev = prev_it != visible_.end() ? &prev_it->second : nullptr;
      lists l;
      for (const auto& [j, t] : live) {
        if (j == i || (t.visibility_class & o.sees) == 0) continue;
        const bool was = prev != nullptr && prev->count(j) != 0;
        if (was ? meets(o, t, h_) : meets(o, t, 0.0f)) l.visible.push_back(j);
      }
      std::set<interest::entity_id> now(l.visible.begin(), l.visible.end());
      for (const auto j : l.visible) {
        if (prev == nullptr || prev->count(j) == 0) l.entered.push_back(j);
      }
      if (prev != nullptr) {
        for (const auto j : *prev) {
          if (now.count(j) == 0) l.left.push_back(j);
        }
      }
      next[i] = std::move(l);
    }
    visible_.clear();
    for (const auto& [i, l] : next) visible_[i] = std::set<interest::entity_id>(l.visible.begin(), l.visible.end());
    last_ = std::move(next);
  }
  [[nodiscard]] const std::map<interest::entity_id, lists>& last() const { return last_; }

 private:
  static bool meets(const interest::entity_spec& o, const interest::entity_spec& t, float h) {
    const auto axis = [&](float p, float a, float q, float b) {
      const float g = h == 0.0f ? a : a + h;
      return q - b <= p + g && p - g <= q + b;
    };
    return axis(o.position.x, o.aoi_half.x, t.position.x, t.presence_half.x) &&
           axis(o.position.y, o.aoi_half.y, t.position.y, t.presence_half.y) &&
           axis(o.position.z, o.aoi_half.z, t.position.z, t.presence_half.z);
  }
  float h_;
  std::map<interest::entity_id, std::set<interest::entity_id>> visible_;
  std::map<interest::entity_id, lists> last_;
};

inline std::vector<interest::entity_id> as_vector(std::span<const interest::entity_id> s) { return {s.begin(), s.end()}; }

/// Every observer's lists of the last step, space against model; the number of events seen.
inline std::size_t check_against_model(const interest::interest_space& space, const space_model& model) {
  std::size_t events = 0;
  REQUIRE(space.size() == model.live.size());
  for (const auto& [id, l] : model.last()) {
    CAPTURE(id);
    REQUIRE(space.alive(id));
    CHECK(as_vector(space.visible(id)) == l.visible);
    CHECK(as_vector(space.entered(id)) == l.entered);
    CHECK(as_vector(space.left(id)) == l.left);
    events += l.entered.size() + l.left.size();
  }
  return events;
}

/// A random class bit and a random set of seen classes.
inline std::uint32_t random_class(std::mt19937_64& rng) {
  constexpr std::uint32_t classes[] = {ib::normal, ib::stealth, ib::team_red, ib::team_blue};
  return classes[rng() % 4];
}
inline std::uint32_t random_sees(std::mt19937_64& rng) {
  return static_cast<std::uint32_t>(rng() % 32) & ~ib::aoi;  // any subset of the four, sometimes none
}

/// `ticks` steps of random calls on `space` (empty at first) and the model side by side; returns
/// the events seen (so that a caller can check the run was not vacuous).
inline std::size_t run_random_space(interest::interest_space& space, float h, std::uint64_t seed, int ticks,
                                    std::size_t entities) {
  std::mt19937_64 rng(seed);
  space_model model(h);
  std::uniform_real_distribution<float> where(0, 120), step(-3, 3), extent(0, 20), body(0, 2);
  const auto random_spec = [&] {
    interest::entity_spec s;
    s.position = {where(rng), where(rng), where(rng) * 0.1f};
    s.aoi_half = {extent(rng), extent(rng), extent(rng)};
    s.presence_half = {body(rng), body(rng), body(rng)};
    s.visibility_class = random_class(rng);
    s.sees = random_sees(rng);
    return s;
  };
  const auto add = [&] {
    const auto s = random_spec();
    const auto id = space.add(s);
    REQUIRE(id != interest::null_entity);
    model.live[id] = s;
  };
  for (std::size_t k = 0; k < entities; ++k) add();
  std::vector<interest::entity_id> removed;
  std::size_t events = 0;
  for (int t = 0; t < ticks; ++t) {
    std::vector<interest::entity_id> ids(space.ids().begin(), space.ids().end());
    for (const auto id : ids) {
      auto& s = model.live[id];
      switch (rng() % 40) {
        case 0: {  // teleport anywhere
          s.position = {where(rng), where(rng), where(rng) * 0.1f};
          REQUIRE(space.teleport(id, s.position));
          break;
        }
        case 1:
          s.aoi_half = {extent(rng), extent(rng), extent(rng)};
          REQUIRE(space.resize_aoi(id, s.aoi_half));
          break;
        case 2:
          s.presence_half = {body(rng), body(rng), body(rng)};
          REQUIRE(space.resize_presence(id, s.presence_half));
          break;
        case 3:
          s.visibility_class = random_class(rng);
          s.sees = random_sees(rng);
          REQUIRE(space.set_classes(id, s.visibility_class, s.sees));
          break;
        case 4:
          REQUIRE(space.remove(id));
          model.live.erase(id);
          removed.push_back(id);
          break;
        default:  // a walk: small steps cross the hysteresis band often
          s.position = {s.position.x + step(rng), s.position.y + step(rng), s.position.z + 0.1f * step(rng)};
          REQUIRE(space.move(id, s.position));
      }
    }
    while (space.size() < entities && rng() % 3 != 0) add();
    // Stale handles are refused by every call.
    for (const auto id : removed) {
      REQUIRE_FALSE(space.alive(id));
      REQUIRE_FALSE(space.move(id, {1, 1, 1}));
      REQUIRE_FALSE(space.remove(id));
    }
    REQUIRE_FALSE(space.step().has_value());
    model.step();
    events += check_against_model(space, model);
    for (const auto id : removed) CHECK(space.visible(id).empty());
  }
  return events;
}

}  // namespace zone::test
