// The tick API (interest/interest_space.h): random runs against the brute-force model of its
// contract (space_reference.h) on the CPU backend with its own finder, the brute-force finder and
// a thread pool; the edge cases one by one (enter and leave with hysteresis, teleport, remove,
// resize, classes, bad input); the backend choice.
#include <doctest/doctest.h>

#include <cmath>
#include <stdexcept>
#include <unordered_set>
#include <utility>
#include <vector>

#include "../common/seeds.h"
#include "interest/interest_space.h"
#include "interest/thread_pool.h"
#include "space_reference.h"

using namespace zone;
using namespace zone::interest;
using zone::test::as_vector;
using zone::test::fresh_seed;
using ids = std::vector<entity_id>;

namespace {

/// One observer at the origin with an AOI half-extent of 10 (h = 4) and one target.
struct pair_case {
  explicit pair_case(space_options o = {.hysteresis = 4.0f}) : space(std::move(o)) {}
  interest_space space;
  entity_id eye = space.add({.position = {0, 0, 0}, .aoi_half = {10, 10, 10}, .presence_half = {0, 0, 0}});
  entity_id it = space.add({.position = {30, 0, 0}, .aoi_half = {0, 0, 0}, .presence_half = {0.5f, 0.5f, 0.5f}});
  void step() { REQUIRE_FALSE(space.step().has_value()); }
};

}  // namespace

TEST_SUITE("interest.space") {
  TEST_CASE("random calls: every step's sets and events are the brute-force model's") {
    for (const float h : {0.0f, 3.0f}) {
      const std::uint64_t seed = fresh_seed();
      CAPTURE(seed);
      CAPTURE(h);
      interest_space own{space_options{.hysteresis = h}};
      CHECK(zone::test::run_random_space(own, h, seed, 30, 150) > 100);

      thread_pool pool(3);
      brute_force_finder brute(&pool);
      interest_space on_brute{space_options{.finder = &brute, .pool = &pool, .hysteresis = h}};
      CHECK(zone::test::run_random_space(on_brute, h, seed, 30, 150) > 100);
    }
  }

  TEST_CASE("enter at the exact AOI box, stay inside the margin, leave beyond it") {
    pair_case c;
    c.step();
    CHECK(c.space.visible(c.eye).empty());
    REQUIRE(c.space.move(c.it, {12, 0, 0}));  // body from 11.5: inside the margin, outside the AOI
    c.step();
    CHECK(c.space.entered(c.eye).empty());
    REQUIRE(c.space.move(c.it, {10.4f, 0, 0}));  // body from 9.9: meets the AOI
    c.step();
    CHECK(as_vector(c.space.entered(c.eye)) == ids{c.it});
    CHECK(as_vector(c.space.visible(c.eye)) == ids{c.it});
    REQUIRE(c.space.move(c.it, {14.4f, 0, 0}));  // body from 13.9 <= 14: stays, no event
    c.step();
    CHECK(as_vector(c.space.visible(c.eye)) == ids{c.it});
    CHECK(c.space.entered(c.eye).empty());
    CHECK(c.space.left(c.eye).empty());
    REQUIRE(c.space.move(c.it, {14.6f, 0, 0}));  // body from 14.1 > 14: leaves
    c.step();
    CHECK(as_vector(c.space.left(c.eye)) == ids{c.it});
    CHECK(c.space.visible(c.eye).empty());
    REQUIRE(c.space.move(c.it, {13, 0, 0}));  // back into the margin: not visible, so no enter
    c.step();
    CHECK(c.space.visible(c.eye).empty());
    // The target sees nothing (AOI of size 0 meets the observer's body only at its centre).
    CHECK(c.space.visible(c.it).empty());
  }

  TEST_CASE("teleport: a far jump leaves, a jump back enters, in the step after each") {
    pair_case c;
    REQUIRE(c.space.teleport(c.it, {5, 5, 5}));
    c.step();
    CHECK(as_vector(c.space.entered(c.eye)) == ids{c.it});
    REQUIRE(c.space.teleport(c.it, {5000, 5000, 5}));
    CHECK(as_vector(c.space.visible(c.eye)) == ids{c.it});  // unchanged until the step
    c.step();
    CHECK(as_vector(c.space.left(c.eye)) == ids{c.it});
    REQUIRE(c.space.teleport(c.eye, {4998, 5000, 5}));  // the observer jumps to it
    c.step();
    CHECK(as_vector(c.space.entered(c.eye)) == ids{c.it});
    CHECK_FALSE(c.space.teleport(c.it, {std::nanf(""), 0, 0}));
  }

  TEST_CASE("remove: observers get a leave, the handle is refused, its slot's next handle differs") {
    pair_case c({.hysteresis = 4.0f, .slot_reuse_after = 0});  // the freed slot reused at once
    REQUIRE(c.space.move(c.it, {1, 0, 0}));
    c.step();
    REQUIRE(as_vector(c.space.visible(c.eye)) == ids{c.it});
    REQUIRE(c.space.remove(c.it));
    CHECK_FALSE(c.space.alive(c.it));
    CHECK_FALSE(c.space.remove(c.it));
    CHECK_FALSE(c.space.move(c.it, {0, 0, 0}));
    CHECK_FALSE(c.space.get(c.it).has_value());
    const entity_id again = c.space.add({.position = {1, 0, 0}});
    CHECK(again != c.it);
    CHECK((again & interest_space::slot_mask) == (c.it & interest_space::slot_mask));
    c.step();
    CHECK(as_vector(c.space.left(c.eye)) == ids{c.it});
    CHECK(as_vector(c.space.entered(c.eye)) == ids{again});
    CHECK(c.space.visible(c.it).empty());
    CHECK(c.space.size() == 2);
  }

  TEST_CASE(
      "slot reuse: a freed slot waits for 1,024 other frees, first freed first; a handle recurs after 1,023 x 1,025 churns") {
    interest_space space;
    const entity_id keep = space.add({});
    // One entity churning: each add takes a new slot until more than 1,024 wait.
    std::vector<entity_id> first_round;
    for (std::size_t k = 0; k <= space_slot_reuse_after; ++k) {
      const entity_id id = space.add({});
      REQUIRE(id != null_entity);
      CHECK((id & interest_space::slot_mask) == k + 1);
      first_round.push_back(id);
      REQUIRE(space.remove(id));
    }
    CHECK(space.slot_count() == space_slot_reuse_after + 2);
    // Then the first freed comes back first, a generation on.
    std::vector<entity_id> again;
    for (std::size_t k = 0; k < 3; ++k) {
      const entity_id id = space.add({});
      again.push_back(id);
      CHECK((id & interest_space::slot_mask) == (first_round[k] & interest_space::slot_mask));
      CHECK((id >> space_slot_bits) == (first_round[k] >> space_slot_bits) + 1);
      CHECK_FALSE(space.alive(first_round[k]));
      REQUIRE(space.remove(id));
    }
    CHECK(space.slot_count() == space_slot_reuse_after + 2);  // no slot more
    // Every handle is new until slot 1's generation wraps: after 1,023 uses of each of the 1,025
    // slots in turn.
    std::unordered_set<entity_id> seen(first_round.begin(), first_round.end());
    seen.insert(again.begin(), again.end());
    std::size_t churns = first_round.size() + again.size(), repeat_at = 0;
    seen.reserve(1100000);
    for (; churns < 1100000 && repeat_at == 0; ++churns) {
      const entity_id id = space.add({});
      if (!seen.insert(id).second) repeat_at = churns;
      REQUIRE(space.remove(id));
    }
    CHECK(repeat_at == space_max_generation * (space_slot_reuse_after + 1));
    CHECK(space.alive(keep));
    CHECK(space.size() == 1);
  }

  TEST_CASE(
      "slot reuse at once (slot_reuse_after 0): the most recently freed slot, its handle back after 1,023 churns") {
    interest_space space({.slot_reuse_after = 0});
    const entity_id first = space.add({});
    REQUIRE(space.remove(first));
    std::size_t churns = 1;
    for (;; ++churns) {
      const entity_id id = space.add({});
      CHECK((id & interest_space::slot_mask) == (first & interest_space::slot_mask));
      REQUIRE(space.remove(id));
      if (id == first || churns > 2 * space_max_generation) break;
    }
    CHECK(churns == space_max_generation);
    CHECK(space.slot_count() == 1);
  }

  TEST_CASE("resize: a grown AOI enters, a shrink inside the margin stays, a shrink beyond leaves") {
    pair_case c;
    REQUIRE(c.space.move(c.it, {20, 0, 0}));
    c.step();
    REQUIRE(c.space.resize_aoi(c.eye, {20, 20, 20}));
    c.step();
    CHECK(as_vector(c.space.entered(c.eye)) == ids{c.it});
    REQUIRE(c.space.resize_aoi(c.eye, {17, 17, 17}));  // body from 19.5 <= 17 + 4
    c.step();
    CHECK(as_vector(c.space.visible(c.eye)) == ids{c.it});
    CHECK(c.space.left(c.eye).empty());
    REQUIRE(c.space.resize_aoi(c.eye, {15, 15, 15}));  // 19.5 > 19
    c.step();
    CHECK(as_vector(c.space.left(c.eye)) == ids{c.it});
    REQUIRE(c.space.resize_presence(c.it, {6, 1, 1}));  // body from 14: meets the AOI again
    c.step();
    CHECK(as_vector(c.space.entered(c.eye)) == ids{c.it});
    CHECK_FALSE(c.space.resize_aoi(c.eye, {-1, 1, 1}));
    CHECK_FALSE(c.space.resize_presence(c.it, {1, INFINITY, 1}));
  }

  TEST_CASE("classes: a stealthy target is seen only by an observer that sees stealth") {
    pair_case c;
    REQUIRE(c.space.move(c.it, {1, 0, 0}));
    REQUIRE(c.space.set_classes(c.it, category_bits::stealth, 0));
    c.step();
    CHECK(c.space.visible(c.eye).empty());
    REQUIRE(c.space.set_classes(c.eye, category_bits::normal, category_bits::normal | category_bits::stealth));
    c.step();
    CHECK(as_vector(c.space.entered(c.eye)) == ids{c.it});
    REQUIRE(c.space.set_classes(c.it, category_bits::team_red, 0));  // a class the observer does not see
    c.step();
    CHECK(as_vector(c.space.left(c.eye)) == ids{c.it});
    CHECK_FALSE(c.space.set_classes(c.it, category_bits::aoi, 0));
    CHECK_FALSE(c.space.set_classes(c.it, category_bits::normal | category_bits::stealth, 0));
    CHECK_FALSE(c.space.set_classes(c.it, category_bits::normal, category_bits::aoi));
  }

  TEST_CASE("bad input: add refuses with a reason; a non-finite bulk position fails the step and changes nothing") {
    pair_case c;
    std::string why;
    CHECK(c.space.add({.position = {NAN, 0, 0}}, &why) == null_entity);
    CHECK(why.find("position") != std::string::npos);
    CHECK(c.space.add({.aoi_half = {-1, 0, 0}}, &why) == null_entity);
    CHECK(why.find("AOI") != std::string::npos);
    CHECK(c.space.add({.visibility_class = 0}, &why) == null_entity);
    CHECK(why.find("class") != std::string::npos);
    REQUIRE(c.space.move(c.it, {1, 0, 0}));
    c.step();
    REQUIRE(as_vector(c.space.visible(c.eye)) == ids{c.it});
    c.space.positions()[c.space.index_of(c.it)].y = INFINITY;
    const auto err = c.space.step();
    REQUIRE(err.has_value());
    CHECK(err->message.find(std::to_string(c.it)) != std::string::npos);
    CHECK(as_vector(c.space.visible(c.eye)) == ids{c.it});  // the last good step's sets
    CHECK(as_vector(c.space.entered(c.eye)) == ids{c.it});

    interest_space tiny{space_options{.capacity = 1}};
    CHECK(tiny.add({}) != null_entity);
    CHECK(tiny.add({}, &why) == null_entity);
    CHECK(why.find("full") != std::string::npos);
  }

  TEST_CASE("backend: cpu by default, auto without an engine maker stays on the cpu, gpu without one is refused") {
    CHECK(parse_backend("cpu") == backend::cpu);
    CHECK(parse_backend("gpu") == backend::gpu);
    CHECK(parse_backend("auto") == backend::automatic);
    CHECK_FALSE(parse_backend("GPU").has_value());
    interest_space plain;
    CHECK(plain.current_backend() == backend::cpu);
    CHECK(plain.backend_note().empty());
    interest_space automatic{space_options{.where = backend::automatic}};
    CHECK(automatic.current_backend() == backend::cpu);
    CHECK_FALSE(automatic.backend_note().empty());
    CHECK_THROWS_AS(interest_space{space_options{.where = backend::gpu}}, std::invalid_argument);
    CHECK_THROWS_AS(interest_space{space_options{.hysteresis = -1}}, std::invalid_argument);
    // A maker that fails: gpu is refused with its reason; set_backend(gpu) says why and keeps the cpu.
    space_options failing{.where = backend::gpu};
    failing.gpu = [](thread_pool*, std::string* why) -> std::unique_ptr<visibility_engine> {
      *why = "no device in this test";
      return nullptr;
    };
    try {
      interest_space s{failing};
      FAIL("constructed");
    } catch (const std::invalid_argument& e) {
      CHECK(std::string(e.what()).find("no device in this test") != std::string::npos);
    }
    failing.where = backend::cpu;
    interest_space s{failing};
    std::string why;
    CHECK_FALSE(s.set_backend(backend::gpu, &why));
    CHECK(why == "no device in this test");
    CHECK(s.current_backend() == backend::cpu);
    CHECK(s.set_backend(backend::cpu));
    space_options capped{.where = backend::gpu, .max_visible = 3};
    CHECK_THROWS_AS(interest_space{capped}, std::invalid_argument);
  }
}
