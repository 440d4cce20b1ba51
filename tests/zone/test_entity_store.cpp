// Entity storage against a plain std::map model under random operation sequences.
#include <doctest/doctest.h>

#include "../common/seeds.h"

#include <cmath>
#include <map>
#include <random>
#include <set>

#include "zone/zone.h"

using namespace zone;
namespace cb = zone::interest::category_bits;

namespace {

using zone::test::fresh_seed;

entity_desc random_desc(std::mt19937_64& rng) {
  std::uniform_real_distribution<float> u(-1000, 1000), e(0, 50);
  entity_desc d;
  d.position = {u(rng), u(rng), u(rng)};
  d.velocity = {u(rng) / 100, u(rng) / 100, 0};
  constexpr std::uint32_t classes[] = {cb::normal, cb::stealth, cb::team_red, cb::team_blue};
  d.visibility_class = classes[rng() % 4];
  d.sees = static_cast<std::uint32_t>(rng()) & (cb::normal | cb::stealth | cb::team_red | cb::team_blue);
  d.aoi_half_extent = {e(rng), e(rng), e(rng)};
  d.presence_half_extent = {e(rng) / 10, e(rng) / 10, e(rng) / 10};
  d.kind = static_cast<entity_kind>(rng() % 3);
  return d;
}

}  // namespace

TEST_SUITE("zone.entity_store") {
  TEST_CASE("random create/destroy/set sequences match a map model") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    std::mt19937_64 rng(seed);
    entity_store store(400);
    std::map<entity_id, entity_desc> model;
    std::vector<entity_id> dead;
    for (int op = 0; op < 20000; ++op) {
      CAPTURE(op);
      const int what = static_cast<int>(rng() % 10);
      if (what < 4) {
        const entity_desc d = random_desc(rng);
        std::string error;
        const entity_id id = store.create(d, &error);
        if (model.size() >= 400) {
          CHECK(id == null_entity);
          CHECK(error.find("full") != std::string::npos);
        } else {
          REQUIRE(id != null_entity);
          CHECK(error.empty());
          CHECK(model.count(id) == 0);
          model[id] = d;
        }
      } else if (what < 7 && !model.empty()) {
        auto it = model.begin();
        std::advance(it, static_cast<long>(rng() % model.size()));
        CHECK(store.destroy(it->first));
        dead.push_back(it->first);
        model.erase(it);
      } else if (what == 7 && !dead.empty()) {
        // Stale handles: destroy, set and get all refuse them, even after slot reuse.
        const entity_id stale = dead[rng() % dead.size()];
        if (model.count(stale) == 0) {
          CHECK_FALSE(store.alive(stale));
          CHECK_FALSE(store.destroy(stale));
          CHECK_FALSE(store.set_position(stale, {1, 2, 3}));
          CHECK_FALSE(store.get(stale).has_value());
        }
      } else if (!model.empty()) {
        auto it = model.begin();
        std::advance(it, static_cast<long>(rng() % model.size()));
        const entity_desc d = random_desc(rng);
        CHECK(store.set_position(it->first, d.position));
        CHECK(store.set_velocity(it->first, d.velocity));
        CHECK(store.set_aoi_half_extent(it->first, d.aoi_half_extent));
        CHECK(store.set_presence_half_extent(it->first, d.presence_half_extent));
        CHECK(store.set_visibility(it->first, d.visibility_class, d.sees));
        it->second.position = d.position;
        it->second.velocity = d.velocity;
        it->second.aoi_half_extent = d.aoi_half_extent;
        it->second.presence_half_extent = d.presence_half_extent;
        it->second.visibility_class = d.visibility_class;
        it->second.sees = d.sees;
        // Invalid values are refused and change nothing.
        CHECK_FALSE(store.set_position(it->first, {std::nanf(""), 0, 0}));
        CHECK_FALSE(store.set_aoi_half_extent(it->first, {-1, 0, 0}));
        CHECK_FALSE(store.set_visibility(it->first, cb::normal | cb::stealth, 0));
        CHECK_FALSE(store.set_visibility(it->first, cb::aoi, 0));
        CHECK_FALSE(store.set_visibility(it->first, cb::normal, cb::aoi));
      }
      if (op % 97 == 0 || op > 19900) {
        REQUIRE(store.size() == model.size());
        std::set<entity_id> seen;
        for (std::size_t i = 0; i < store.size(); ++i) {
          const entity_id id = store.ids()[i];
          CHECK(id != null_entity);
          CHECK(seen.insert(id).second);
          CHECK(store.index_of(id) == i);
        }
        for (const auto& [id, d] : model) {
          REQUIRE(store.alive(id));
          const auto got = store.get(id);
          REQUIRE(got.has_value());
          CHECK(*got == d);
          const std::size_t i = store.index_of(id);
          CHECK(store.positions()[i] == d.position);
          CHECK(store.aoi_half_extents()[i] == d.aoi_half_extent);
          CHECK(store.visibility_classes()[i] == d.visibility_class);
          CHECK(store.kinds()[i] == d.kind);
        }
      }
    }
    CHECK_FALSE(store.alive(null_entity));
    CHECK(store.index_of(null_entity) == entity_store::npos);
  }

  TEST_CASE("invalid descriptions are rejected with a reason") {
    entity_store store;
    entity_desc d;
    std::string error;
    d.position.y = std::numeric_limits<float>::infinity();
    CHECK(store.create(d, &error) == null_entity);
    CHECK(error.find("position") != std::string::npos);
    d = {};
    d.presence_half_extent.z = -0.1f;
    CHECK(store.create(d, &error) == null_entity);
    CHECK(error.find("presence") != std::string::npos);
    d = {};
    d.visibility_class = 0;
    CHECK(store.create(d, &error) == null_entity);
    d.visibility_class = cb::aoi;
    CHECK(store.create(d, &error) == null_entity);
    d = {};
    d.sees |= cb::aoi;
    CHECK(store.create(d, &error) == null_entity);
    CHECK(store.empty());
    CHECK(store.create(entity_desc{}) != null_entity);
  }

  TEST_CASE("more than 2^20 entities: slots past the old 20-bit cap, distinct handles, the cap at max_entities") {
    static_assert(max_entities == std::size_t{1} << 22);
    const std::size_t n = (std::size_t{1} << 20) + 4096;
    entity_store store;
    store.reserve(n);
    entity_id last = null_entity;
    for (std::size_t i = 0; i < n; ++i) {
      entity_desc d;
      d.position = {static_cast<float>(i % 4096), static_cast<float>(i / 4096), 0};
      last = store.create(d);
      REQUIRE(last != null_entity);
    }
    CHECK(slot_of(last) == n - 1);
    CHECK(generation_of(last) == 1);
    CHECK(store.get(last)->position.x == static_cast<float>((n - 1) % 4096));
    // The handle of slot 2^20 is not the handle of slot 0 (the 20-bit layout would have made it
    // slot 0 of generation 2).
    const entity_id first = store.ids()[0], past = store.ids()[std::size_t{1} << 20];
    CHECK(slot_of(past) == (std::uint32_t{1} << 20));
    CHECK(first != past);
    CHECK(store.destroy(first));
    CHECK(store.alive(past));
    CHECK_FALSE(store.alive(first));
    // A small store caps at its capacity; the default one at max_entities.
    CHECK(entity_store().capacity() == max_entities);
    CHECK(entity_store(max_entities + 5).capacity() == max_entities);
  }

  TEST_CASE("a reused slot gets a new generation; handles are never null") {
    // Freed slots reused at once (the default waits for 1,024 other frees; test_interest_space).
    entity_store store(max_entities, {.slot_reuse_after = 0});
    const entity_id keep = store.create({});
    std::set<entity_id> handles;
    entity_id prev = null_entity;
    for (std::uint32_t i = 0; i < max_generation; ++i) {
      const entity_id id = store.create({});
      REQUIRE(id != null_entity);
      CHECK(slot_of(id) == 1);  // the same slot every time
      CHECK(handles.insert(id).second);
      if (prev != null_entity) CHECK_FALSE(store.alive(prev));
      CHECK(store.destroy(id));
      prev = id;
    }
    // After max_generation (1,023) reuses the generation wraps (documented), skipping 0.
    const entity_id wrapped = store.create({});
    CHECK(generation_of(wrapped) == 1);
    CHECK(store.alive(keep));
    store.clear();
    CHECK_FALSE(store.alive(keep));
    CHECK_FALSE(store.alive(wrapped));
    CHECK(store.empty());
  }

  TEST_CASE("layout_version: changes with everything but positions and velocities, never repeats") {
    entity_store a, b;
    CHECK(a.layout_version() != b.layout_version());
    entity_desc d;
    d.sees = interest::category_bits::normal;
    std::uint64_t v = a.layout_version();
    const auto changed = [&] {
      const bool c = a.layout_version() != v;
      v = a.layout_version();
      return c;
    };
    const entity_id x = a.create(d);
    CHECK(changed());
    a.positions()[0] = {1, 2, 3};
    a.velocities()[0] = {1, 0, 0};
    CHECK(a.set_position(x, {4, 5, 6}));
    CHECK(a.set_velocity(x, {0, 1, 0}));
    CHECK_FALSE(changed());
    CHECK(a.set_aoi_half_extent(x, {5, 5, 5}));
    CHECK(changed());
    CHECK(a.set_presence_half_extent(x, {1, 1, 1}));
    CHECK(changed());
    CHECK(a.set_visibility(x, interest::category_bits::stealth, interest::category_bits::normal));
    CHECK(changed());
    CHECK_FALSE(a.set_aoi_half_extent(x, {-1, 0, 0}));  // refused: nothing changed
    CHECK_FALSE(changed());
    CHECK(a.destroy(x));
    CHECK(changed());
    (void)b.create(d);
    CHECK(b.layout_version() != a.layout_version());
  }

  TEST_CASE("class_changes_since: the set_visibility calls since a version, or false after anything else") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    std::mt19937_64 rng(seed);
    entity_store store(600);
    for (int k = 0; k < 300; ++k) REQUIRE(store.create(random_desc(rng)) != null_entity);
    // The model: every layout version seen, with what came after it (kind 0: a set_visibility of
    // that dense index; 1: anything else that changed the layout).
    struct step {
      std::uint64_t version;  // the layout before the operation
      int kind;
      std::size_t dense;
    };
    std::vector<step> steps;
    constexpr std::uint32_t classes[] = {cb::normal, cb::stealth, cb::team_red, cb::team_blue};
    std::size_t checked_true = 0, checked_false = 0, overflowed = 0;
    for (int op = 0; op < 6000; ++op) {
      CAPTURE(op);
      const std::uint64_t before = store.layout_version();
      // Mostly switches; ops 2,000-4,499 switches only: a run longer than the journal.
      const int what = op >= 2000 && op < 4500 ? 0 : static_cast<int>(rng() % 100);
      if (what < 85) {
        const std::size_t d = rng() % store.size();
        const bool bad = rng() % 20 == 0;  // a refused call (the aoi bit as a class) records nothing
        const bool ok = store.set_visibility(store.ids()[d], bad ? cb::aoi : classes[rng() % 4], cb::normal);
        REQUIRE(ok == !bad);
        if (ok) steps.push_back({before, 0, d});
        CHECK((store.layout_version() != before) == ok);
      } else if (what < 90) {
        REQUIRE(store.create(random_desc(rng)) != null_entity);
        steps.push_back({before, 1, 0});
      } else if (what < 95) {
        REQUIRE(store.destroy(store.ids()[rng() % store.size()]));
        steps.push_back({before, 1, 0});
      } else if (what < 98) {
        REQUIRE(store.set_aoi_half_extent(store.ids()[rng() % store.size()], {10, 10, 10}));
        steps.push_back({before, 1, 0});
      } else {
        store.positions()[rng() % store.size()] = {1, 2, 3};  // no layout change: no step
        CHECK(store.layout_version() == before);
      }
      // A few versions from the past, the current one and one never seen.
      for (int q = 0; q < 3; ++q) {
        const std::size_t back = q == 0 ? 0 : std::min<std::size_t>(steps.size(), rng() % (q == 1 ? 8 : 2500));
        const std::uint64_t since = back == 0 ? store.layout_version() : steps[steps.size() - back].version;
        bool expect = true;
        std::vector<std::size_t> want;
        for (std::size_t k = steps.size() - back; k < steps.size(); ++k) {
          if (steps[k].kind != 0) expect = false;
          want.push_back(steps[k].dense);
        }
        if (back > entity_store::class_journal_size) {
          overflowed += expect ? 1 : 0;
          expect = false;
        }
        std::vector<std::size_t> got;
        const bool ok = store.class_changes_since(since, [&](std::size_t d) { got.push_back(d); });
        CAPTURE(back);
        CHECK(ok == expect);
        if (ok) {
          CHECK(got == want);
        } else {
          CHECK(got.empty());
        }
        (expect ? checked_true : checked_false)++;
      }
      std::vector<std::size_t> none;
      CHECK_FALSE(store.class_changes_since(0x7fff'ffff'ffff'ffffull, [&](std::size_t d) { none.push_back(d); }));
      CHECK(none.empty());
    }
    CHECK(checked_true > 1000);
    CHECK(checked_false > 1000);
    CHECK(overflowed > 50);  // switches only, but more than the journal holds (about 380 expected)
    // clear() forgets the journal: no version from before it leads to now.
    const std::uint64_t old = store.layout_version();
    store.clear();
    CHECK_FALSE(store.class_changes_since(old, [](std::size_t) {}));
    CHECK(store.class_changes_since(store.layout_version(), [](std::size_t) {}));
  }
}
