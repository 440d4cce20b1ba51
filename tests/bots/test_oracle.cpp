// The oracle (bots/oracle.h) in-process: its visible sets equal the interest tracker's with the
// brute-force finder, tick after tick, on fresh random worlds (classes, masks, AOI sizes, moves
// across the hysteresis band, teleports, spawns and despawns, with and without the cap); and the
// views that the real replicator builds under a tight byte budget (deferrals every tick) pass its
// checks, while a view missing one entity, or holding one it must not, fails them.
#include <doctest/doctest.h>

#include "../common/seeds.h"

#include <algorithm>
#include <limits>
#include <map>
#include <bit>
#include <chrono>
#include <deque>
#include <future>
#include <random>
#include <thread>

#include "bots/oracle.h"
#include "net/truth.h"
#include "zone/truth_publisher.h"
#include "zone/zone.h"

using namespace zone;
namespace cb = interest::category_bits;

namespace {

std::span<const float> floats(std::span<const vec3> v) {
  return {reinterpret_cast<const float*>(v.data()), 3 * v.size()};
}

/// The store's truth frame bodies, as zone-server --oracle writes them (zone/truth_publisher.cpp:
/// the encoder is given the columns when the store's layout_version changed, and sends the whole
/// layout, the changed rows, or positions alone).
struct truth_writer {
  net::truth::encoder enc;
  std::uint64_t version = 0;
  bool any = false;
  std::size_t layouts = 0, changes = 0;
  std::vector<std::uint8_t> kinds, bytes;
  std::vector<std::uint8_t> body(const entity_store& store, std::uint64_t tick,
                                 const net::truth::carried_view* carried = nullptr) {
    const bool changed = !any || store.layout_version() != version;
    version = store.layout_version(), any = true;
    kinds.resize(store.size());
    for (std::size_t k = 0; k < store.size(); ++k) kinds[k] = static_cast<std::uint8_t>(store.kinds()[k]);
    const net::truth::layout_view lv{store.ids(),
                                     floats(store.aoi_half_extents()),
                                     floats(store.presence_half_extents()),
                                     store.visibility_classes(),
                                     store.sees(),
                                     kinds};
    const auto sent = enc.encode(bytes, tick, floats(store.positions()), changed ? &lv : nullptr, false, carried);
    layouts += sent == net::truth::encoder::sent::layout;
    changes += sent == net::truth::encoder::sent::changes;
    return {bytes.begin() + 4, bytes.end()};
  }
};

struct world_sim {
  std::mt19937_64 rng;
  entity_store store;
  net::world_bounds world{{0, 0, 0}, {400, 400, 40}};
  std::vector<entity_id> players;
  explicit world_sim(std::uint64_t seed) : rng(seed) {}
  float uni(float lo, float hi) { return std::uniform_real_distribution<float>(lo, hi)(rng); }
  vec3 anywhere() { return {uni(0, 400), uni(0, 400), uni(0, 40)}; }
  void add_npcs(int n) {
    const std::uint32_t classes[] = {cb::normal, cb::normal, cb::normal, cb::stealth, cb::team_red, cb::team_blue};
    for (int i = 0; i < n; ++i) {
      entity_desc d;
      d.position = anywhere();
      d.visibility_class = classes[rng() % 6];
      d.sees = (static_cast<std::uint32_t>(rng()) & (cb::normal | cb::stealth | cb::team_red | cb::team_blue)) | cb::normal;
      const float a = uni(5, 40);
      d.aoi_half_extent = {a, a, std::min(a, 20.0f)};
      const float b = i == 0 ? 30.0f : uni(0.3f, 3);  // one boss-sized footprint
      d.presence_half_extent = {b, b, b};
      d.kind = i == 0 ? entity_kind::boss : entity_kind::npc;
      REQUIRE(store.create(d) != null_entity);
    }
  }
  entity_id add_player() {
    entity_desc d;
    d.position = anywhere();
    d.aoi_half_extent = {30, 30, 30};
    d.kind = entity_kind::player;
    const entity_id id = store.create(d);
    REQUIRE(id != null_entity);
    players.push_back(id);
    return id;
  }
  /// The oldest player leaves.
  void remove_first_player() {
    REQUIRE(store.destroy(players.front()));
    players.erase(players.begin());
  }
  /// Everyone steps up to 2.5 m per axis (across the 4 m hysteresis band within a few ticks).
  void move() {
    for (auto& p : store.positions()) {
      p.x = std::clamp(p.x + uni(-2.5f, 2.5f), 0.0f, 400.0f);
      p.y = std::clamp(p.y + uni(-2.5f, 2.5f), 0.0f, 400.0f);
      p.z = std::clamp(p.z + uni(-1, 1), 0.0f, 40.0f);
    }
    if (!players.empty() && rng() % 4 == 0) store.set_position(players[rng() % players.size()], anywhere());  // a teleport
  }
};

/// world_sim with `npcs` NPCs and the interest tracker the oracle is held to: brute-force finder,
/// 4 m hysteresis, at most `cap` entities visible (0: no cap), and those rules as the oracle reads them.
struct tracked_world : world_sim {
  interest::brute_force_finder finder;
  interest_tracker tracker;
  net::interest_rules rules;
  carried_columns carried;
  bool write_carried = true;  ///< the truth names the sets the tracker's update carried, as zone-server's does
  tracked_world(std::uint64_t seed, int npcs, std::uint32_t cap = 0)
      : world_sim(seed), tracker(finder, nullptr, {4.0f, cap, 256}) {
    add_npcs(npcs);
    rules.hysteresis = 4;
    rules.max_visible = cap;
  }
  /// One tick: the tracker updates and `oracle` reads the tick's truth frame (from `truth`, with
  /// the carried sets unless write_carried is off); then compare(player, the tracker's visible
  /// set, the oracle's) for every player (the oracle's is empty for a player it has no history of yet).
  template <class Compare>
  void tick(bots::oracle& oracle, truth_writer& truth, std::uint64_t t, Compare&& compare) {
    REQUIRE_FALSE(tracker.update(store.columns()).has_value());
    carried.assign(tracker.carried_by_last_update());
    const auto cv = carried.view();
    REQUIRE_FALSE(oracle.feed(truth.body(store, t, write_carried ? &cv : nullptr)).has_value());
    for (const entity_id p : players) {
      const auto row = tracker.row_of(p);
      REQUIRE(row != entity_store::npos);
      compare(p, tracker.visible(row), oracle.visible(p, t));
    }
  }
};

/// A world written straight into truth frames (no store, no server rules on what a world may
/// hold): any position, extent, class and mask; entities leave by a swap with the last (their
/// dense indices move), so the oracle sees layouts, changes and positions as a server sends them.
struct raw_world {
  std::mt19937_64 rng;
  std::vector<std::uint32_t> ids, classes, sees;
  std::vector<float> pos, aoi, presence;  // 3 per entity
  std::vector<std::uint8_t> kinds;
  std::uint32_t next_id = 1;
  bool changed = true;
  net::truth::encoder enc;
  std::vector<std::uint8_t> bytes;
  explicit raw_world(std::uint64_t seed) : rng(seed) {}
  float uni(float lo, float hi) { return std::uniform_real_distribution<float>(lo, hi)(rng); }
  std::size_t size() const { return ids.size(); }
  std::uint32_t add(const float p[3], const float a[3], const float b[3], std::uint32_t cls, std::uint32_t mask,
                    net::entity_kind kind) {
    ids.push_back(next_id);
    pos.insert(pos.end(), p, p + 3);
    aoi.insert(aoi.end(), a, a + 3);
    presence.insert(presence.end(), b, b + 3);
    classes.push_back(cls);
    sees.push_back(mask);
    kinds.push_back(static_cast<std::uint8_t>(kind));
    changed = true;
    return next_id++;
  }
  void remove(std::size_t k) {
    const std::size_t last = size() - 1;
    ids[k] = ids[last], classes[k] = classes[last], sees[k] = sees[last], kinds[k] = kinds[last];
    for (int a = 0; a < 3; ++a) {
      pos[3 * k + a] = pos[3 * last + a], aoi[3 * k + a] = aoi[3 * last + a],
                  presence[3 * k + a] = presence[3 * last + a];
    }
    ids.pop_back(), classes.pop_back(), sees.pop_back(), kinds.pop_back();
    for (auto* v : {&pos, &aoi, &presence}) v->resize(3 * last);
    changed = true;
  }
  std::vector<std::uint8_t> body(std::uint64_t tick) {
    const net::truth::layout_view lv{ids, aoi, presence, classes, sees, kinds};
    (void)enc.encode(bytes, tick, pos, changed ? &lv : nullptr, false);
    changed = false;
    return {bytes.begin() + 4, bytes.end()};
  }
};

/// A frame the replicator built, decoded (frames up to 1 MiB).
net::tick_update_msg decode_update(std::span<const std::uint8_t> frame) {
  net::decoder_options o;
  o.max_frame_bytes = 1 << 20;
  auto decoded = net::decode_frame(frame, o);
  REQUIRE(decoded.value.has_value());
  return std::get<net::tick_update_msg>(*decoded.value);
}

/// The rules the oracle checks a replicator's views by: the tracker's hysteresis and the
/// replicator's update distances and periods (what zone-server's welcome tells the bots).
net::interest_rules rules_of(const replication_options& ro, float hysteresis) {
  net::interest_rules rules;
  rules.hysteresis = hysteresis;
  rules.update_near = ro.near_distance;
  rules.update_mid = ro.mid_distance;
  rules.update_mid_period = ro.mid_period;
  rules.update_far_period = ro.far_period;
  return rules;
}

}  // namespace

TEST_SUITE("bots.oracle") {
  TEST_CASE("the oracle's visible sets equal the interest tracker's (brute-force finder), tick after tick") {
    for (const std::uint32_t cap : {0u, 7u}) {
      for (const unsigned threads : {1u, 3u}) {
        for (const auto scan :
             {bots::oracle::scan_mode::full, bots::oracle::scan_mode::x_window, bots::oracle::scan_mode::grid}) {
          const std::uint64_t seed = zone::test::fresh_seed();
          CAPTURE(seed);
          CAPTURE(cap);
          CAPTURE(threads);
          tracked_world w(seed, 400, cap);
          bots::oracle oracle(w.world, w.rules, threads, nullptr, nullptr);
          oracle.scan = scan;
          const char* scan_name = scan == bots::oracle::scan_mode::full       ? "every target"
                                  : scan == bots::oracle::scan_mode::x_window ? "x window"
                                                                              : "grid";
          CAPTURE(scan_name);
          std::uint64_t compared = 0, visible_total = 0, differing = 0, in_band = 0;
          truth_writer truth;
          for (std::uint64_t tick = 0; tick < 150; ++tick) {
            if (tick > 0) w.move();
            // Players join over time (from the second tick: the oracle saw their whole history),
            // and some leave.
            if (tick >= 1 && tick < 100 && tick % 3 == 1) w.add_player();
            if (tick % 17 == 5 && w.players.size() > 3) w.remove_first_player();
            w.tick(oracle, truth, tick, [&](entity_id p, const auto& expect, const auto& got) {
              REQUIRE(got.has_value());
              ++compared;
              visible_total += expect.size();
              // Entries kept by the hysteresis alone (the presence box misses the exact AOI box).
              const auto o = *w.store.get(p);
              for (const entity_id t : expect) {
                const auto d = *w.store.get(t);
                for (int a = 0; a < 3; ++a) {
                  const float po[3] = {o.position.x, o.position.y, o.position.z},
                              pt[3] = {d.position.x, d.position.y, d.position.z};
                  const float ao[3] = {o.aoi_half_extent.x, o.aoi_half_extent.y, o.aoi_half_extent.z};
                  const float bt[3] = {d.presence_half_extent.x, d.presence_half_extent.y, d.presence_half_extent.z};
                  if (pt[a] - bt[a] > po[a] + ao[a] || po[a] - ao[a] > pt[a] + bt[a]) {
                    ++in_band;
                    break;
                  }
                }
              }
              if (!std::equal(expect.begin(), expect.end(), got->begin(), got->end())) ++differing;
            });
          }
          MESSAGE("cap " << cap << ", threads " << threads << ", " << std::string(scan_name) << ": " << compared
                         << " visible sets compared, " << visible_total << " entries, " << in_band
                         << " kept by the hysteresis alone");
          CHECK(compared > 2000);
          CHECK(in_band > 100);
          CHECK(visible_total > compared * 5);
          CHECK(differing == 0);
          CHECK(oracle.counters().mismatches() == 0);
        }
      }
    }
  }

  TEST_CASE("an observer given a carried set (a handoff): the oracle continues it from the set the truth carries") {
    // The tracker takes carried sets (interest_tracker::carry_visible, as a zone adopting a
    // handed-off player does) for random players at random ticks: targets near and far, some
    // not in the store. With the carried sets in the truth (zone-server --oracle writes them) the
    // oracle's sets equal the tracker's; without them it continues such an observer from its own
    // last set and differs where the carried set kept a target by the hysteresis.
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    for (const bool write_carried : {true, false}) {
      CAPTURE(write_carried);
      tracked_world w(seed, 400);
      w.write_carried = write_carried;
      bots::oracle oracle(w.world, w.rules, 2, nullptr, nullptr);
      truth_writer truth;
      std::uint64_t compared = 0, differing = 0, carried_observers = 0;
      for (std::uint64_t tick = 0; tick < 120; ++tick) {
        if (tick > 0) w.move();
        if (tick >= 1 && tick < 60 && tick % 3 == 1) w.add_player();
        if (tick >= 5 && !w.players.empty() && w.rng() % 3 == 0) {
          // A player carried with a set: every entity within 40 m of it (some beyond its AOI, in
          // reach of the band or not), one handle the store never had, and itself (ignored).
          const entity_id p = w.players[w.rng() % w.players.size()];
          const vec3 at = w.store.get(p)->position;
          std::vector<entity_id> set{p, 0x00ffffffu};
          for (const entity_id e : w.store.ids()) {
            const vec3 q = w.store.get(e)->position;
            if (e != p && std::abs(q.x - at.x) < 40 && std::abs(q.y - at.y) < 40) set.push_back(e);
          }
          w.tracker.carry_visible(p, set);
          ++carried_observers;
        }
        w.tick(oracle, truth, tick, [&](entity_id, const auto& expect, const auto& got) {
          REQUIRE(got.has_value());
          ++compared;
          if (!std::equal(expect.begin(), expect.end(), got->begin(), got->end())) ++differing;
        });
      }
      MESSAGE(std::string(write_carried ? "with" : "without")
              << " the carried sets: " << carried_observers << " observers carried, " << compared << " sets compared, "
              << differing << " differing");
      CHECK(carried_observers > 20);
      CHECK(compared > 1000);
      if (write_carried) {
        CHECK(differing == 0);
      } else {
        CHECK(differing > 0);  // the carried sets matter: the check above can fail
      }
    }
  }

  TEST_CASE("targets at a NaN x (a malformed truth): the x window's scan stays brute force's, none of them visible") {
    // The x window sorts the targets by x: a NaN there must not break the sort's order (undefined
    // behaviour in std::sort: targets missed, or worse).
    using mode = bots::oracle::scan_mode;
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    raw_world w(seed);
    const net::world_bounds bounds{{0, 0, 0}, {400, 400, 40}};
    net::interest_rules rules;
    rules.hysteresis = 4;
    bots::oracle full(bounds, rules, 1, nullptr, nullptr), xw(bounds, rules, 2, nullptr, nullptr);
    full.scan = mode::full, xw.scan = mode::x_window;
    std::vector<std::uint32_t> players, bad;
    const float a[3] = {30, 30, 30}, b[3] = {1, 1, 1};
    for (int k = 0; k < 400; ++k) {
      const bool nan = k % 3 == 0;
      const float p[3] = {nan ? std::numeric_limits<float>::quiet_NaN() : w.uni(0, 400), w.uni(0, 400), w.uni(0, 40)};
      const std::uint32_t id = w.add(p, a, b, 1u, 1u, net::entity_kind::npc);
      if (nan) bad.push_back(id);
    }
    std::uint64_t compared = 0, visible_total = 0, differing = 0, bad_seen = 0;
    for (std::uint64_t tick = 0; tick < 20; ++tick) {
      for (std::size_t k = 0; k < w.size(); ++k) w.pos[3 * k + 1] += w.uni(-2, 2);
      if (tick == 1) {  // players from the stream's second tick: the oracle checks entities it saw arrive
        for (int k = 0; k < 30; ++k) {
          const float p[3] = {w.uni(0, 400), w.uni(0, 400), w.uni(0, 40)};
          players.push_back(w.add(p, a, b, 1u, 1u, net::entity_kind::player));
        }
      }
      const auto body = w.body(tick);
      REQUIRE_FALSE(full.feed(body).has_value());
      REQUIRE_FALSE(xw.feed(body).has_value());
      for (const std::uint32_t id : players) {
        const auto expect = full.visible(id, tick), by_x = xw.visible(id, tick);
        REQUIRE(expect.has_value() == by_x.has_value());
        if (!expect) continue;
        ++compared;
        visible_total += expect->size();
        if (*expect != *by_x) ++differing;
        for (const std::uint32_t t : *by_x) bad_seen += std::count(bad.begin(), bad.end(), t);
      }
    }
    MESSAGE(compared << " sets compared, " << visible_total << " entries, " << differing << " differ");
    CHECK(compared == 19 * players.size());
    CHECK(visible_total > compared * 3);
    CHECK(differing == 0);
    CHECK(bad_seen == 0);
  }

  TEST_CASE(
      "the grid's scan gives brute force's sets: cell borders, boxes that just touch, huge AOIs, wide boxes, every class and mask, the hysteresis band, churn") {
    // Three oracles read the same frames: every target tested (brute force; itself held to the
    // interest tracker above), the x window, and the grid (a given cell side, and the oracle's own
    // choice). Their sets must be equal for every player at every tick.
    using mode = bots::oracle::scan_mode;
    for (const std::uint32_t cap : {0u, 5u}) {
      for (const float cell : {8.0f, 0.0f}) {
        const std::uint64_t seed = zone::test::fresh_seed();
        CAPTURE(seed);
        CAPTURE(cap);
        CAPTURE(cell);
        raw_world w(seed);
        const net::world_bounds bounds{{0, 0, 0}, {400, 400, 40}};
        net::interest_rules rules;
        rules.hysteresis = 4;
        rules.max_visible = cap;
        bots::oracle full(bounds, rules, 1, nullptr, nullptr), xw(bounds, rules, 2, nullptr, nullptr),
            grid(bounds, rules, 3, nullptr, nullptr);
        full.scan = mode::full, xw.scan = mode::x_window, grid.scan = mode::grid;
        grid.grid_cell = cell;
        const float c =
            8;  // positions snapped to multiples of it land on cell borders (of the 8 m grid, and of any multiple)
        const auto on_border = [&](float lo, float hi) { return c * std::floor(w.uni(lo, hi) / c); };
        const auto any_class = [&] { return static_cast<std::uint32_t>(w.rng() % 32); };  // 5 bits, 0 included
        const auto add_npc = [&] {
          const int kind = static_cast<int>(w.rng() % 10);
          float p[3] = {w.uni(-40, 440), w.uni(-40, 440), w.uni(0, 40)};
          if (kind < 4) p[0] = on_border(-40, 440), p[1] = on_border(-40, 440);
          const float half =
              kind == 9   ? (w.rng() % 2 ? 40.0f : 300.0f)  // wider than any cell: tested by every observer
              : kind == 8 ? (w.rng() % 2 ? c : c + 0.001f)  // either side of the grid's limit for an 8 m cell
                          : w.uni(0.1f, 3);
          const float a = w.uni(5, 60), b[3] = {half, half, std::min(half, 5.0f)}, e[3] = {a, a, a};
          w.add(p, e, b, any_class(), any_class(), net::entity_kind::npc);
        };
        std::vector<std::uint32_t> players;
        struct touching_pair {
          std::uint32_t player, enters, band;
          float aoi;
        };
        std::vector<touching_pair> pairs;
        const auto add_player = [&] {
          // The first two see (nearly) everything: AOI half-extents 1e6 and 1e4 m.
          const int kind = players.size() < 2 ? 11 - static_cast<int>(players.size()) : static_cast<int>(w.rng() % 10);
          float p[3] = {w.uni(0, 400), w.uni(0, 400), w.uni(0, 40)};
          if (kind < 6) p[0] = on_border(0, 400), p[1] = on_border(0, 400);
          const float a = kind == 11   ? 1e6f
                          : kind == 10 ? 1e4f
                          : kind < 6   ? c * static_cast<float>(1 + w.rng() % 6)
                                       : w.uni(5, 60);
          const float e[3] = {a, a, a}, b[3] = {0.5f, 0.5f, 1.0f};
          players.push_back(w.add(p, e, b, any_class() | 1u, any_class() | 1u, net::entity_kind::player));
          if (kind < 6) {
            // Two targets (class 1, seen by the player) that touch its boxes on x, kept so (touch()).
            const float q[3] = {0, 0, 0}, tb[3] = {1, 1, 1}, te[3] = {10, 10, 10};
            pairs.push_back({players.back(), w.add(q, te, tb, 1u, 1u, net::entity_kind::npc),
                             w.add(q, te, tb, 1u, 1u, net::entity_kind::npc), a});
          }
        };
        // Every other tick each such player jumps to a cell border and its targets to where their
        // presence boxes exactly touch its AOI box (visible: closed boxes) and its grown box
        // (visible only while it was last tick): exact in float (multiples of 8, plus 1).
        const auto touch = [&] {
          const auto at = [&](std::uint32_t id) {
            return static_cast<std::size_t>(std::find(w.ids.begin(), w.ids.end(), id) - w.ids.begin());
          };
          for (const auto& pr : pairs) {
            const std::size_t o = at(pr.player), t0 = at(pr.enters), t1 = at(pr.band);
            if (o == w.size() || t0 == w.size() || t1 == w.size()) continue;
            w.pos[3 * o] = on_border(0, 400), w.pos[3 * o + 1] = on_border(0, 400);
            for (const auto& [t, gap] : {std::pair{t0, 0.0f}, std::pair{t1, rules.hysteresis}}) {
              w.pos[3 * t] = w.pos[3 * o] + pr.aoi + gap + 1, w.pos[3 * t + 1] = w.pos[3 * o + 1],
                        w.pos[3 * t + 2] = w.pos[3 * o + 2];
              w.presence[3 * t] = 1, w.classes[t] = 1;
            }
          }
        };
        for (int k = 0; k < 500; ++k) add_npc();
        std::uint64_t compared = 0, visible_total = 0, differing = 0, touching = 0, huge = 0;
        for (std::uint64_t tick = 0; tick < 120; ++tick) {
          if (tick > 0) {
            for (std::size_t k = 0; k < w.size(); ++k) {
              for (int a = 0; a < 2; ++a)
                w.pos[3 * k + a] += w.uni(-2.5f, 2.5f);  // across the 4 m band within a few ticks
              if (w.rng() % 50 == 0) w.pos[3 * k] = on_border(-40, 440);
            }
          }
          if (tick >= 1 && tick < 60 && tick % 2 == 1) add_player();
          if (tick % 2 == 0) touch();
          if (tick % 13 == 6) {  // churn: a few leave (dense indices move), a few arrive
            for (int k = 0; k < 3; ++k) {
              const std::size_t at = w.rng() % w.size();
              std::erase(players, w.ids[at]);
              w.remove(at);
            }
            for (int k = 0; k < 3; ++k) add_npc();
          }
          if (tick % 7 == 3) {  // switches and resizes: sent as changes to the layout
            for (int k = 0; k < 4; ++k) {
              const std::size_t at = w.rng() % w.size();
              w.classes[at] = any_class(), w.sees[at] = any_class();
              if (w.kinds[at] != static_cast<std::uint8_t>(net::entity_kind::player))
                w.presence[3 * at] = w.uni(0.1f, 50);
              w.changed = true;
            }
          }
          const auto body = w.body(tick);
          REQUIRE_FALSE(full.feed(body).has_value());
          REQUIRE_FALSE(xw.feed(body).has_value());
          REQUIRE_FALSE(grid.feed(body).has_value());
          for (const std::uint32_t id : players) {
            const auto expect = full.visible(id, tick);
            const auto by_x = xw.visible(id, tick), by_grid = grid.visible(id, tick);
            REQUIRE(expect.has_value() == by_grid.has_value());
            REQUIRE(expect.has_value() == by_x.has_value());
            if (!expect) continue;
            ++compared;
            visible_total += expect->size();
            if (*expect != *by_grid || *expect != *by_x) ++differing;
            // The brute force's sets hold targets whose presence box exactly touches the AOI box.
            const std::size_t o = static_cast<std::size_t>(std::find(w.ids.begin(), w.ids.end(), id) - w.ids.begin());
            if (w.aoi[3 * o] >= 1e4f) huge += cap == 0 ? expect->size() > 200 : expect->size() == cap;
            for (const std::uint32_t t : *expect) {
              const std::size_t k = static_cast<std::size_t>(std::find(w.ids.begin(), w.ids.end(), t) - w.ids.begin());
              touching += w.pos[3 * k] - w.presence[3 * k] == w.pos[3 * o] + w.aoi[3 * o] ||
                          w.pos[3 * k] + w.presence[3 * k] == w.pos[3 * o] - w.aoi[3 * o];
            }
          }
        }
        MESSAGE("cap " << cap << ", cell " << cell << ": " << compared << " sets compared, " << visible_total
                       << " entries, " << touching << " of them touching the AOI box exactly, " << huge
                       << " sets of a huge AOI; " << differing << " differ");
        CHECK(compared > 1500);
        CHECK(visible_total > compared * 3);
        CHECK(touching > 100);
        CHECK(huge > 40);
        CHECK(differing == 0);
      }
    }
  }

  TEST_CASE(
      "the scan's order and the sets' blocks: every scan's sets equal a plain recompute's, tick after tick (zero-size boxes, boxes touching the AOI and grown boxes, the world's borders, classes, teams and stealth, tiny blocks, the ring reused)") {
    // The scans visit observers in the index's slot order on several threads and store the sets
    // one after another in blocks (here of 1, 7 and 50 entries: most sets cross a block, the
    // huge AOIs' hold every target); a tick of positions only finds last tick's set by the
    // observer's index. Each oracle's sets must equal a recompute written here from the rule
    // alone (every target tested, last tick's set by id), at every tick and 63 ticks later.
    using mode = bots::oracle::scan_mode;
    for (const std::uint32_t cap : {0u, 6u}) {
      const std::uint64_t seed = zone::test::fresh_seed();
      CAPTURE(seed);
      CAPTURE(cap);
      raw_world w(seed);
      const float side = 200;
      const net::world_bounds bounds{{0, 0, 0}, {side, side, 20}};
      net::interest_rules rules;
      rules.hysteresis = 3;
      rules.max_visible = cap;
      bots::oracle full(bounds, rules, 1, nullptr, nullptr), grid(bounds, rules, 3, nullptr, nullptr),
          grid4(bounds, rules, 3, nullptr, nullptr), xw(bounds, rules, 2, nullptr, nullptr);
      full.scan = mode::full, grid.scan = mode::grid, grid4.scan = mode::grid, xw.scan = mode::x_window;
      grid.set_block = 1, grid4.set_block = 50, xw.set_block = 7;
      grid4.grid_cell = 4;
      bots::oracle* const oracles[] = {&full, &grid, &grid4, &xw};
      const char* const names[] = {"every target", "grid (blocks of 1)", "grid of 4 m (blocks of 50)",
                                   "x window (blocks of 7)"};
      const std::uint32_t bits[] = {cb::normal, cb::stealth, cb::team_red, cb::team_blue};
      const auto some_bits = [&] {  // 0 to 4 of the classes: 0 included (seen by none, sees none)
        std::uint32_t b = 0;
        for (const std::uint32_t c : bits) b |= w.rng() % 3 == 0 ? c : 0u;
        return b;
      };
      const auto on_grid = [&](float lo, float hi) { return 4 * std::floor(w.uni(lo, hi) / 4); };  // cell borders
      const auto place = [&](float* p) {
        const int k = static_cast<int>(w.rng() % 8);
        p[0] = k < 3 ? on_grid(-8, side + 8) : w.uni(-10, side + 10);
        p[1] = k < 3 ? on_grid(-8, side + 8) : w.uni(-10, side + 10);
        p[2] = w.uni(0, 20);
        if (k == 3) p[0] = w.rng() % 2 ? 0 : side;  // on the world's border
        if (k == 4) p[1] = w.rng() % 2 ? 0 : side;
      };
      const auto add_npc = [&] {
        float p[3];
        place(p);
        const int k = static_cast<int>(w.rng() % 10);
        const float half = k < 2 ? 0.0f : k == 9 ? (w.rng() % 2 ? 12.0f : 150.0f) : w.uni(0.1f, 2);  // zero-size, wide
        const float b[3] = {half, half, std::min(half, 4.0f)}, a[3] = {10, 10, 10};
        const std::uint32_t cls = w.rng() % 4 == 0 ? some_bits() : bits[w.rng() % 4];
        w.add(p, a, b, cls, some_bits(), net::entity_kind::npc);
      };
      struct touching_pair {
        std::uint32_t player, enters, band, zero;
      };
      std::vector<touching_pair> pairs;
      std::vector<std::uint32_t> players;
      const auto add_player = [&] {
        float p[3];
        place(p);
        // The first two players have a huge AOI, the next four touching targets (below), so that
        // every world has both whatever the draws (a world with few touching players left only
        // 20 touching entries in 3% of the runs, under the bound checked at the end); then any.
        const int k = players.size() < 2   ? 10
                      : players.size() < 6 ? 1 + static_cast<int>(w.rng() % 4)
                                           : static_cast<int>(w.rng() % 10);
        // A huge AOI (every target: sets larger than any small block), none (only what sits on
        // the observer's point), multiples of 4 (exact arithmetic: the touching targets), any.
        const float a = k == 10 ? 1e4f : k == 0 ? 0.0f : k < 5 ? 4.0f * static_cast<float>(1 + w.rng() % 5) : w.uni(2, 30);
        const float e[3] = {a, a, a}, b[3] = {0.5f, 0.5f, 1.0f};
        players.push_back(w.add(p, e, b, bits[w.rng() % 4], some_bits() | cb::normal, net::entity_kind::player));
        if (k >= 1 && k < 5) {
          const float q[3] = {0, 0, 0}, tb[3] = {1, 1, 1}, zb[3] = {0, 0, 0}, te[3] = {10, 10, 10};
          pairs.push_back({players.back(), w.add(q, te, tb, cb::normal, cb::normal, net::entity_kind::npc),
                           w.add(q, te, tb, cb::normal, cb::normal, net::entity_kind::npc),
                           w.add(q, te, zb, cb::normal, cb::normal, net::entity_kind::npc)});
        }
      };
      const auto at = [&](std::uint32_t id) {
        return static_cast<std::size_t>(std::find(w.ids.begin(), w.ids.end(), id) - w.ids.begin());
      };
      // Every third tick each such player jumps to a point of the 4 m grid and its targets to
      // where their boxes exactly touch its AOI box on x (one of 1 m, one of none) and its grown
      // box on y (visible only while it was last tick): exact in float.
      const auto touch = [&] {
        for (const auto& pr : pairs) {
          const std::size_t o = at(pr.player), t0 = at(pr.enters), t1 = at(pr.band), t2 = at(pr.zero);
          if (o == w.size() || t0 == w.size() || t1 == w.size() || t2 == w.size()) continue;
          w.pos[3 * o] = on_grid(0, side), w.pos[3 * o + 1] = on_grid(0, side);
          const float a = w.aoi[3 * o];
          for (const std::size_t t : {t0, t1, t2}) {
            for (int c = 0; c < 3; ++c) w.pos[3 * t + c] = w.pos[3 * o + c];
          }
          w.pos[3 * t0] += a + 1, w.pos[3 * t2] -= a, w.pos[3 * t1 + 1] += a + rules.hysteresis + 1;
        }
      };
      // The rule, plainly: a target (not the observer) whose class the observer sees and whose
      // presence box meets the grown AOI box stays if it was in last tick's set, and enters if it
      // meets the exact AOI box; with a cap, the closest by squared distance (ties by id).
      std::map<std::uint32_t, std::vector<std::uint32_t>> last;  // by player id
      std::map<std::uint64_t, std::map<std::uint32_t, std::vector<std::uint32_t>>> history;
      const auto recompute = [&](std::size_t o) {
        std::vector<std::uint32_t> set;
        const auto& before = last[w.ids[o]];
        const float* p = &w.pos[3 * o];
        const float* e = &w.aoi[3 * o];
        const float h = rules.hysteresis;
        for (std::size_t t = 0; t < w.size(); ++t) {
          if (t == o || (w.classes[t] & w.sees[o]) == 0) continue;
          bool grown = true, exact = true;
          for (int c = 0; c < 3; ++c) {
            const float lo = w.pos[3 * t + c] - w.presence[3 * t + c], hi = w.pos[3 * t + c] + w.presence[3 * t + c];
            const float g = e[c] + h;
            grown = grown && lo <= p[c] + g && p[c] - g <= hi;
            exact = exact && lo <= p[c] + e[c] && p[c] - e[c] <= hi;
          }
          if (grown && (exact || std::binary_search(before.begin(), before.end(), w.ids[t]))) set.push_back(w.ids[t]);
        }
        std::sort(set.begin(), set.end());
        if (cap != 0 && set.size() > cap) {
          std::vector<std::pair<std::uint32_t, std::uint32_t>> keys;
          for (const std::uint32_t id : set) {
            const float* q = &w.pos[3 * at(id)];
            const float dx = p[0] - q[0], dy = p[1] - q[1], dz = p[2] - q[2];
            keys.emplace_back(std::bit_cast<std::uint32_t>(dx * dx + dy * dy + dz * dz), id);
          }
          std::sort(keys.begin(), keys.end());
          set.clear();
          for (std::size_t k = 0; k < cap; ++k) set.push_back(keys[k].second);
          std::sort(set.begin(), set.end());
        }
        return set;
      };
      for (int k = 0; k < 400; ++k) add_npc();
      std::uint64_t compared = 0, visible_total = 0, differing = 0, touching = 0, zero_size = 0, over_block = 0,
                    positions_only = 0, later = 0;
      for (std::uint64_t tick = 0; tick < 100; ++tick) {
        if (tick > 0) {
          for (std::size_t k = 0; k < w.size(); ++k) {
            for (int c = 0; c < 2; ++c) w.pos[3 * k + c] += w.uni(-2, 2);  // across the 3 m band in a few ticks
            if (w.rng() % 60 == 0) place(&w.pos[3 * k]);                    // a jump
          }
        }
        if (tick >= 1 && tick < 40 && tick % 2 == 1) add_player();
        if (tick % 3 == 0) touch();
        if (tick % 11 == 5) {  // churn: leaves move dense indices (players among them), arrivals append
          for (int k = 0; k < 3; ++k) {
            const std::size_t t = w.rng() % w.size();
            std::erase(players, w.ids[t]);
            last.erase(w.ids[t]);
            w.remove(t);
          }
          for (int k = 0; k < 2; ++k) add_npc();
        }
        if (tick % 7 == 3) {  // switches (stealth, teams) and resizes: sent as changes to the layout
          for (int k = 0; k < 5; ++k) {
            const std::size_t t = w.rng() % w.size();
            w.classes[t] = bits[w.rng() % 4], w.sees[t] = some_bits() | cb::normal;
            if (w.kinds[t] != static_cast<std::uint8_t>(net::entity_kind::player)) w.presence[3 * t] = w.uni(0, 3);
            w.changed = true;
          }
        }
        positions_only += !w.changed;
        const auto body = w.body(tick);
        for (auto* o : oracles) REQUIRE_FALSE(o->feed(body).has_value());
        std::map<std::uint32_t, std::vector<std::uint32_t>> now;
        for (const std::uint32_t id : players) {
          const std::size_t o = at(id);
          const auto expect = recompute(o);
          now[id] = expect;
          ++compared;
          visible_total += expect.size();
          over_block += expect.size() > 50;
          for (const std::uint32_t t : expect) {
            const std::size_t k = at(t);
            zero_size += w.presence[3 * k] == 0;
            touching += w.pos[3 * k] - w.presence[3 * k] == w.pos[3 * o] + w.aoi[3 * o] ||
                        w.pos[3 * k] + w.presence[3 * k] == w.pos[3 * o] - w.aoi[3 * o];
          }
          for (std::size_t i = 0; i < std::size(oracles); ++i) {
            CAPTURE(names[i]);
            const auto got = oracles[i]->visible(id, tick);
            REQUIRE(got.has_value());
            differing += *got != expect;
          }
        }
        last = now;
        history[tick] = std::move(now);
        // 63 ticks on, the sets are still there, intact (their blocks not reused); 64 on, gone.
        if (tick >= bots::oracle::ring_ticks - 1) {
          const std::uint64_t then = tick - (bots::oracle::ring_ticks - 1);
          for (const auto& [id, expect] : history[then]) {
            for (auto* o : oracles) {
              const auto got = o->visible(id, then);
              REQUIRE(got.has_value());
              differing += *got != expect;
              ++later;
            }
          }
          if (then > 0) {
            for (const auto& [id, expect] : history[then - 1]) {
              for (auto* o : oracles) CHECK_FALSE(o->visible(id, then - 1).has_value());
            }
          }
        }
      }
      MESSAGE("cap " << cap << ": " << compared << " sets of each scan compared at their tick and " << later
                     << " 63 ticks later, " << visible_total << " entries (" << touching << " touching the AOI box, "
                     << zero_size << " of zero size), " << over_block << " sets over 50 entries, " << positions_only
                     << " ticks of positions only; " << differing << " differ");
      CHECK(compared > 1000);
      CHECK(later > 1000);
      CHECK(visible_total > compared * 3);
      CHECK(touching > 50);
      CHECK(zero_size > 50);
      if (cap == 0) CHECK(over_block > 50);  // (with the cap, sets of 6 cross the blocks of 1 and 7)
      CHECK(positions_only > 30);
      CHECK(differing == 0);
    }
  }

  TEST_CASE(
      "a sparse world (the grid's cell grows): a target whose presence box is wider than the first cell is still found") {
    // Two entities 100 km apart make the grid's cell grow far beyond the 1 m asked for; each
    // player has a target whose 100 m presence box meets its AOI box though its position is 60 m
    // away, in the next cell for some of them. The grid's sets must equal brute force's.
    using mode = bots::oracle::scan_mode;
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    raw_world w(seed);
    const net::world_bounds bounds{{0, 0, 0}, {100000, 100000, 40}};
    net::interest_rules rules;
    rules.hysteresis = 4;
    bots::oracle full(bounds, rules, 1, nullptr, nullptr), grid(bounds, rules, 1, nullptr, nullptr);
    full.scan = mode::full, grid.scan = mode::grid;
    grid.grid_cell = 1;
    const float small[3] = {0.5f, 0.5f, 0.5f}, aoi[3] = {5, 5, 5}, wide[3] = {100, 100, 100};
    const float anchor[3] = {0, 0, 0}, far[3] = {100000, 100000, 0};
    w.add(anchor, aoi, small, 1, 1, net::entity_kind::npc);
    w.add(far, aoi, small, 1, 1, net::entity_kind::npc);
    std::vector<std::uint32_t> players;
    std::uint64_t compared = 0, visible_total = 0, differing = 0;
    for (std::uint64_t tick = 0; tick < 4; ++tick) {
      if (tick == 1) {  // from the second tick: the oracle sees their whole history
        for (int i = 0; i < 200; ++i) {
          const float x = 50.0f * static_cast<float>(i) + w.uni(0, 10);
          const float p[3] = {x, 0, 0}, q[3] = {x + 60, 0, 0};
          players.push_back(w.add(p, aoi, small, 1, 1, net::entity_kind::player));
          w.add(q, aoi, wide, 1, 1, net::entity_kind::npc);
        }
      }
      const auto body = w.body(tick);
      REQUIRE_FALSE(full.feed(body).has_value());
      REQUIRE_FALSE(grid.feed(body).has_value());
      for (const std::uint32_t id : players) {
        const auto expect = full.visible(id, tick), got = grid.visible(id, tick);
        REQUIRE(expect.has_value() == got.has_value());
        if (!expect) continue;
        ++compared;
        visible_total += expect->size();
        differing += *expect != *got;
      }
    }
    MESSAGE(compared << " sets compared, " << visible_total << " entries; " << differing << " differ");
    CHECK(compared == 3 * 200);
    CHECK(visible_total > compared * 3);
    CHECK(differing == 0);
  }

  TEST_CASE("a truth layout that names one id twice is a stream error, not a truth to check views by") {
    // With an id on two rows, a visible set could hold it twice, and a view holding it and one
    // more entity (not visible) would be read whole in the set's order: the extra never compared.
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    raw_world w(seed);
    const net::world_bounds bounds{{0, 0, 0}, {400, 400, 40}};
    net::interest_rules rules;
    rules.hysteresis = 4;
    bots::oracle oracle(bounds, rules, 1, nullptr, nullptr);
    const float small[3] = {0.5f, 0.5f, 0.5f}, aoi[3] = {10, 10, 10};
    const float at[3] = {w.uni(0, 400), w.uni(0, 400), 0};
    w.add(at, aoi, small, 1, 1, net::entity_kind::npc);
    REQUIRE_FALSE(oracle.feed(w.body(0)).has_value());
    const std::uint32_t player = w.add(at, aoi, small, 1, 1, net::entity_kind::player);
    w.add(at, aoi, small, 1, 1, net::entity_kind::npc);
    w.add(at, aoi, small, 1, 1, net::entity_kind::npc);
    REQUIRE_FALSE(oracle.feed(w.body(1)).has_value());  // distinct ids (appended to tick 0's)
    w.add(at, aoi, small, 1, 1, net::entity_kind::npc);
    w.ids.back() = w.ids[2];  // appended to tick 1's, one id twice
    const auto err = oracle.feed(w.body(2));
    REQUIRE(err.has_value());
    CHECK(err->find("twice") != std::string::npos);
    CHECK(oracle.feed(w.body(3)).has_value());  // positions for the layout it refused: refused too
    w.ids.back() = w.next_id++;
    w.ids[0] = w.ids[2];  // a new oracle's first layout, one id twice
    w.changed = true;
    bots::oracle other(bounds, rules, 1, nullptr, nullptr);
    CHECK(other.feed(w.body(4)).has_value());
    CHECK(other.visible(player, 4) == std::nullopt);
  }

  TEST_CASE(
      "after the truth stream ended, a frame whose truth never came is unchecked, not counted as an overflow of the waiting room") {
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    raw_world w(seed);
    const net::world_bounds bounds{{0, 0, 0}, {400, 400, 40}};
    net::interest_rules rules;
    rules.hysteresis = 4;
    bots::oracle oracle(bounds, rules, 1, nullptr, nullptr);
    const float small[3] = {0.5f, 0.5f, 0.5f}, aoi[3] = {10, 10, 10};
    const float at[3] = {w.uni(0, 400), w.uni(0, 400), 0};
    const std::uint32_t player = w.add(at, aoi, small, 1, 1, net::entity_kind::player);
    REQUIRE_FALSE(oracle.feed(w.body(0)).has_value());
    oracle.stop();
    const net::client_view view(bounds);
    oracle.check(player, 5, view, {}, std::nullopt, 0);  // tick 5's truth never came
    const auto r = oracle.report();
    CHECK(r.frames_checked + r.frames_unchecked + r.frames_unsampled == 1);
    CHECK(r.frames_unchecked == 1);
    CHECK(r.pending_overflow == 0);
  }

  TEST_CASE(
      "many switches and resizes a tick, sent as changes to the layout: the oracle's visible sets equal the tracker's at every tick") {
    // Every tick several players and NPCs switch class and mask (stealth, teams), some AOI and
    // presence boxes resize, now and then an entity spawns or leaves and, rarely, most of the
    // world switches at once (over the encoder's cap: the whole layout). The oracle reads the
    // frames the server's encoder writes and must hold every change: its visible sets equal the
    // interest tracker's (brute-force finder) for every player at every tick.
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    tracked_world w(seed, 500);
    bots::oracle oracle(w.world, w.rules, 1, nullptr, nullptr);
    truth_writer truth;
    const std::uint32_t classes[] = {cb::normal, cb::stealth, cb::team_red, cb::team_blue};
    const auto random_mask = [&] {
      return (static_cast<std::uint32_t>(w.rng()) & (cb::normal | cb::stealth | cb::team_red | cb::team_blue)) |
             cb::normal;
    };
    std::uint64_t compared = 0, differing = 0, switches = 0, resizes = 0, mass = 0;
    for (std::uint64_t tick = 0; tick < 200; ++tick) {
      if (tick > 0) w.move();
      if (tick == 1) {  // (from the second tick: the oracle saw their whole history)
        for (int k = 0; k < 30; ++k) w.add_player();
      }
      const auto ids = std::vector<entity_id>(w.store.ids().begin(), w.store.ids().end());
      if (tick > 1) {
        for (int k = 0; k < 6; ++k) {  // switches: players and NPCs
          const entity_id id = k < 3 ? w.players[w.rng() % w.players.size()] : ids[w.rng() % ids.size()];
          REQUIRE(w.store.set_visibility(id, classes[w.rng() % 4], random_mask()));
          ++switches;
        }
        if (w.rng() % 2 == 0) {  // a resize
          const entity_id id = ids[w.rng() % ids.size()];
          const float a = w.uni(5, 40), b = w.uni(0.3f, 6);
          REQUIRE(w.store.set_aoi_half_extent(id, {a, a, std::min(a, 20.0f)}));
          REQUIRE(w.store.set_presence_half_extent(id, {b, b, b}));
          ++resizes;
        }
        if (tick % 29 == 7) w.add_player();  // the ids change: the whole layout
        if (tick % 41 == 11) {
          w.remove_first_player();
        }
        if (tick % 67 == 33) {  // most of the world at once: over the cap
          for (const entity_id id : ids) REQUIRE(w.store.set_visibility(id, classes[w.rng() % 4], random_mask()));
          ++mass;
        }
      }
      w.tick(oracle, truth, tick, [&](entity_id, const auto& expect, const auto& got) {
        if (!got) return;  // a player joined this tick (its history starts next tick)
        ++compared;
        if (!std::equal(expect.begin(), expect.end(), got->begin(), got->end())) ++differing;
      });
    }
    const auto r = oracle.report();
    MESSAGE(switches << " switches, " << resizes << " resizes, " << mass << " mass switches: " << r.truth_layouts
                     << " frames with the whole layout, " << r.truth_changes << " with changes; " << compared
                     << " visible sets compared, " << differing << " differ");
    CHECK(compared > 190 * 28);
    CHECK(differing == 0);
    CHECK(r.truth_changes == truth.changes);
    CHECK(r.truth_layouts == truth.layouts);
    CHECK(r.truth_changes > 170);  // every tick changes something: all but the whole layouts
    CHECK(r.truth_layouts >= 1 + mass);
    CHECK(r.truth_layouts < 25);
  }

  TEST_CASE(
      "a subscriber that connects after the server's first step reads the first frames: it checks every observer from that step, those present then included") {
    // A zone restored from a checkpoint starts with its players in place, and the oracle that
    // follows it connects seconds later: the publisher's record of its first frames (and the
    // first step's flag) gives it their whole history there.
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    tracked_world w(seed, 200);
    for (int k = 0; k < 12; ++k) w.add_player();  // there before the first step
    truth_publisher pub;
    REQUIRE_FALSE(pub.start(0, 2).has_value());
    std::uint64_t tick = 0;
    std::map<std::uint64_t, std::map<entity_id, std::vector<entity_id>>> expect;
    const auto step = [&] {
      w.move();
      ++tick;
      REQUIRE_FALSE(w.tracker.update(w.store.columns()).has_value());
      pub.publish(w.store, tick, w.tracker.carried_by_last_update(), tick == 1);
      for (const entity_id p : w.players) {
        const auto v = w.tracker.visible(w.tracker.row_of(p));
        expect[tick][p].assign(v.begin(), v.end());
      }
    };
    for (int k = 0; k < 30; ++k) step();  // nobody reads yet
    bots::oracle late(w.world, w.rules, 1, nullptr, nullptr);
    {
      auto started = std::async(std::launch::async, [&] { return late.start(pub.port(), 10); });
      for (int k = 0; k < 2000 && started.wait_for(std::chrono::milliseconds(5)) != std::future_status::ready; ++k) {
        if (tick < 50) step();
      }
      const auto err = started.get();
      REQUIRE_MESSAGE(!err.has_value(), err.value_or(""));
    }
    while (tick < 50) step();
    std::uint64_t compared = 0, differing = 0;
    for (std::uint64_t t = 1; t <= tick; ++t) {
      for (const entity_id p : w.players) {
        std::optional<std::vector<std::uint32_t>> got;
        for (int wait = 0; wait < 2000 && !(got = late.visible(p, t)); ++wait) {
          std::this_thread::sleep_for(std::chrono::milliseconds(2));
        }
        REQUIRE_MESSAGE(got.has_value(), "tick " << t << ", player " << p);
        ++compared;
        const auto& want = expect[t][p];
        if (!std::equal(want.begin(), want.end(), got->begin(), got->end())) ++differing;
      }
    }
    CHECK(compared == 50 * w.players.size());
    CHECK(differing == 0);
    CHECK(pub.stats().prefix_subscribers == 1);
    late.stop();
    pub.stop();
  }

  TEST_CASE(
      "the server's truth stream over loopback: switches arrive as changes, the sets equal the tracker's; a subscriber over the limit is refused by name") {
    // zone-server's publisher (zone/truth_publisher.h) with room for one subscriber: an oracle
    // subscribes and reads the socket while players switch every tick; its visible sets equal
    // the tracker's at every tick. A second oracle is refused, and its error names the option.
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    tracked_world w(seed, 300);
    truth_publisher pub;
    REQUIRE_FALSE(pub.start(0, 1).has_value());
    bots::oracle first(w.world, w.rules, 1, nullptr, nullptr);
    std::uint64_t tick = 0;
    const auto step = [&] {
      REQUIRE_FALSE(w.tracker.update(w.store.columns()).has_value());
      pub.publish(w.store, tick);
      ++tick;
    };
    {  // ticks until the first oracle has one (it waits for its first tick)
      auto started = std::async(std::launch::async, [&] { return first.start(pub.port(), 10); });
      for (int k = 0; k < 2000 && started.wait_for(std::chrono::milliseconds(5)) != std::future_status::ready; ++k) {
        w.move();
        step();
      }
      const auto err = started.get();
      REQUIRE_MESSAGE(!err.has_value(), err.value_or(""));
    }
    bots::oracle second(w.world, w.rules, 1, nullptr, nullptr);
    const auto refused = second.start(pub.port(), 10);
    REQUIRE(refused.has_value());
    CHECK(refused->find("refused") != std::string::npos);
    CHECK(refused->find("--oracle-subscribers") != std::string::npos);
    for (int k = 0; k < 20; ++k) w.add_player();
    const std::uint32_t classes[] = {cb::normal, cb::stealth, cb::team_red, cb::team_blue};
    std::uint64_t compared = 0, differing = 0;
    for (int k = 0; k < 80; ++k) {
      w.move();
      for (int s2 = 0; s2 < 3; ++s2) {
        REQUIRE(
            w.store.set_visibility(w.players[w.rng() % w.players.size()], classes[w.rng() % 4],
                                   cb::normal | (static_cast<std::uint32_t>(w.rng()) & (cb::stealth | cb::team_red))));
      }
      const std::uint64_t t = tick;
      step();
      // Its truth is computed on the oracle's thread: wait for it (a player known from its first tick).
      std::optional<std::vector<std::uint32_t>> got;
      for (int wait = 0; wait < 2000 && !(got = first.visible(w.players.front(), t)); ++wait) {
        std::this_thread::sleep_for(std::chrono::milliseconds(2));
      }
      if (k == 0) continue;  // the players joined this tick: their history starts with it
      REQUIRE(got.has_value());
      for (const entity_id p : w.players) {
        const auto expect = w.tracker.visible(w.tracker.row_of(p));
        const auto v = first.visible(p, t);
        REQUIRE(v.has_value());
        ++compared;
        if (!std::equal(expect.begin(), expect.end(), v->begin(), v->end())) ++differing;
      }
    }
    first.stop();
    pub.stop();
    const auto r = first.report();
    MESSAGE(r.truth_ticks << " truth frames read: " << r.truth_layouts << " with the whole layout, " << r.truth_changes
                          << " with changes; " << compared << " sets compared, " << differing << " differ");
    CHECK(compared == 79 * 20);
    CHECK(differing == 0);
    CHECK(r.truth_changes >= 70);
    CHECK(r.truth_layouts <= 3);
    CHECK(pub.stats().refused_subscribers == 1);
    CHECK(pub.stats().changes >= r.truth_changes);
  }

  TEST_CASE("views the replicator builds under a tight budget pass; a view missing one entity or holding an extra one fails") {
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    tracked_world w(seed, 600);
    replication_options ro;
    ro.world = w.world;
    ro.byte_budget = 520;  // a few enters per frame: deferrals nearly every tick at first
    ro.near_distance = 10;
    ro.mid_distance = 25;
    ro.mid_period = 3;
    ro.far_period = 8;
    replicator rep(ro);
    const net::interest_rules rules = rules_of(ro, 4);
    std::vector<std::string> problems;
    bots::oracle oracle(w.world, rules, 1, [](void* ctx, std::string line) {
      static_cast<std::vector<std::string>*>(ctx)->push_back(std::move(line));
    }, &problems);
    struct client {
      entity_id id;
      client_id c;
      net::client_view view;
      bool broken = false;
    };
    std::vector<client> clients;
    replication_writer writer;
    truth_writer truth;
    std::uint64_t deferring = 0;
    std::uint64_t missing_before = 0, extra_before = 0;
    bool dropped = false, added = false;
    for (std::uint64_t tick = 0; tick < 120; ++tick) {
      if (tick > 0) w.move();
      if (tick >= 1 && tick <= 12) {
        const entity_id id = w.add_player();
        clients.push_back({id, rep.add_client(id), net::client_view(w.world)});
      }
      REQUIRE_FALSE(w.tracker.update(w.store.columns()).has_value());
      REQUIRE_FALSE(oracle.feed(truth.body(w.store, tick)).has_value());
      for (std::size_t i = 0; i < clients.size(); ++i) {
        client& cl = clients[i];
        replication_stats st;
        const auto frame = rep.build(cl.c, w.store, w.tracker, tick, 0, 0, writer, &st);
        auto m = decode_update(frame);
        if (m.deferred) ++deferring;
        // Late in the run, one client loses an entity (the first frame with an enter: a client's
        // frames may have none for the whole tail of the run) and client 1 gains one it cannot see.
        if (tick >= 80 && i != 1 && !dropped && !m.enters.empty()) {
          m.enters.erase(m.enters.begin());
          dropped = cl.broken = true;
          missing_before = oracle.counters().missing.load();
        }
        if (tick >= 80 && i == 1 && !added) {
          const auto row = w.tracker.row_of(cl.id);
          const auto vis = w.tracker.visible(row);
          for (const entity_id other : w.store.ids()) {
            if (other == cl.id || std::binary_search(vis.begin(), vis.end(), other) || cl.view.entities().count(other)) continue;
            const auto d = *w.store.get(other);
            m.enters.push_back({other, net::entity_kind::npc, d.visibility_class, {d.position.x, d.position.y, d.position.z},
                                {}, {d.presence_half_extent.x, d.presence_half_extent.y, d.presence_half_extent.z}, {}});
            break;
          }
          added = cl.broken = true;
          extra_before = oracle.counters().extra.load() + oracle.counters().leaked.load();
        }
        (void)cl.view.apply(m);
        const std::uint64_t before = oracle.counters().mismatches();
        const std::size_t logged = problems.size();
        oracle.check(cl.id, tick, cl.view, m.deferred.value_or(net::deferred_counts{}), m.self_position, i);
        if (!cl.broken) {
          INFO("problem: " << (problems.size() > logged ? problems[logged] : std::string("-")));
          REQUIRE(oracle.counters().mismatches() == before);
        }
      }
    }
    MESSAGE(oracle.counters().frames_checked.load() << " frames checked, " << deferring << " with deferrals, "
                                                    << oracle.counters().entities_checked.load() << " entities");
    CHECK(deferring > 100);
    CHECK(oracle.counters().frames_checked.load() > 1000);
    CHECK(oracle.counters().positions_checked.load() > 10000);
    REQUIRE(dropped);
    REQUIRE(added);
    CHECK(oracle.counters().missing.load() > missing_before);
    CHECK(oracle.counters().extra.load() + oracle.counters().leaked.load() > extra_before);
    // (The unbroken clients had no mismatch of any kind: checked after each of their frames above.
    // The broken ones may show others later, e.g. the extra entity becoming visible for real.)
  }

  TEST_CASE(
      "sample mode: exactly the sampled bots are recomputed and checked, every frame; a sampled bot's wrong view is caught") {
    // 30 clients of the real replicator, the oracle with a sample of 1 in 3: the frames of the
    // players sampled() picks are checked (each one, at its tick) and their sets equal the
    // tracker's; the others' frames are counted unsampled, and their sets are not computed. Late
    // in the run one sampled and one unsampled client each lose an entering entity: the sampled
    // one's loss is counted missing; the unsampled one is not looked at.
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    constexpr unsigned k = 3;
    tracked_world w(seed, 500);
    replication_options ro;
    ro.world = w.world;
    ro.byte_budget = 900;  // deferrals now and then
    ro.near_distance = 5;  // most held entities last sent some ticks before (positions checked in earlier ticks' truth)
    ro.mid_distance = 15;
    ro.mid_period = 3;
    ro.far_period = 8;
    replicator rep(ro);
    const net::interest_rules rules = rules_of(ro, 4);
    bots::oracle oracle(w.world, rules, 2, nullptr, nullptr);
    oracle.sample = k;
    struct client {
      entity_id id;
      client_id c;
      net::client_view view;
      bool sampled = false, broken = false;
    };
    std::vector<client> clients;
    replication_writer writer;
    truth_writer truth;
    std::uint64_t sampled_frames = 0, unsampled_frames = 0, compared = 0, differing = 0;
    bool broke_sampled = false, broke_unsampled = false;
    std::uint64_t missing_before = 0, npcs_removed = 0;
    for (std::uint64_t tick = 0; tick < 100; ++tick) {
      if (tick > 0) w.move();
      if (tick == 1) {
        for (int n = 0; n < 30; ++n) {  // a crowd: every player sees most of the others
          entity_desc d;
          d.position = {w.uni(180, 220), w.uni(180, 220), w.uni(0, 10)};
          d.aoi_half_extent = {30, 30, 30};
          d.kind = entity_kind::player;
          const entity_id id = w.store.create(d);
          REQUIRE(id != null_entity);
          w.players.push_back(id);
          clients.push_back({id, rep.add_client(id), net::client_view(w.world), bots::oracle::sampled(id, k)});
        }
      }
      if (tick >= 10 && tick % 3 == 0) {
        // An NPC leaves: the store moves its last entity, a player of the crowd, into the hole, so
        // dense indices differ from the ticks before (where the positions last sent are found by id).
        std::size_t at = 0;
        do {
          at = w.rng() % w.store.size();
        } while (w.store.kinds()[at] == entity_kind::player);
        REQUIRE(w.store.destroy(w.store.ids()[at]));
        ++npcs_removed;
      }
      REQUIRE_FALSE(w.tracker.update(w.store.columns()).has_value());
      REQUIRE_FALSE(oracle.feed(truth.body(w.store, tick)).has_value());
      for (std::size_t i = 0; i < clients.size(); ++i) {
        client& cl = clients[i];
        const auto frame = rep.build(cl.c, w.store, w.tracker, tick, 0, 0, writer, nullptr);
        auto m = decode_update(frame);
        if (tick >= 60 && !m.enters.empty() && !cl.broken && (cl.sampled ? !broke_sampled : !broke_unsampled)) {
          m.enters.erase(m.enters.begin());
          cl.broken = true;
          (cl.sampled ? broke_sampled : broke_unsampled) = true;
          if (cl.sampled) missing_before = oracle.counters().missing.load();
        }
        (void)cl.view.apply(m);
        const auto& c = oracle.counters();
        const std::uint64_t checked0 = c.frames_checked.load(), unchecked0 = c.frames_unchecked.load(),
                            unsampled0 = c.frames_unsampled.load(), mismatches0 = c.mismatches();
        oracle.check(cl.id, tick, cl.view, m.deferred.value_or(net::deferred_counts{}), m.self_position, i);
        const auto v = oracle.visible(cl.id, tick);
        if (cl.sampled) {
          ++sampled_frames;
          CHECK(c.frames_checked.load() == checked0 + 1);
          CHECK(c.frames_unsampled.load() == unsampled0);
          REQUIRE(v.has_value());
          const auto expect = w.tracker.visible(w.tracker.row_of(cl.id));
          ++compared;
          if (!std::equal(expect.begin(), expect.end(), v->begin(), v->end())) ++differing;
          if (!cl.broken) CHECK(c.mismatches() == mismatches0);
        } else {
          ++unsampled_frames;
          CHECK(c.frames_unsampled.load() == unsampled0 + 1);
          CHECK(c.frames_checked.load() == checked0);
          CHECK(c.mismatches() == mismatches0);  // never looked at, broken or not
          CHECK_FALSE(v.has_value());
        }
        CHECK(c.frames_unchecked.load() == unchecked0);
      }
    }
    const std::size_t n_sampled = static_cast<std::size_t>(
        std::count_if(clients.begin(), clients.end(), [](const client& cl) { return cl.sampled; }));
    const auto r = oracle.report();
    MESSAGE(n_sampled << " of " << clients.size() << " clients sampled: " << sampled_frames << " frames checked, "
                      << unsampled_frames << " unsampled; " << compared << " sets compared, " << differing
                      << " differ; missing " << r.missing << " (planted in a sampled client); " << npcs_removed
                      << " NPCs removed; positions checked " << r.positions_checked);
    REQUIRE(n_sampled > 0);
    REQUIRE(n_sampled < clients.size());
    CHECK(r.sample == k);
    CHECK(r.sampled_max == n_sampled);
    CHECK(r.observers_max == clients.size());
    CHECK(r.frames_checked == sampled_frames);
    CHECK(r.frames_unsampled == unsampled_frames);
    CHECK(differing == 0);
    CHECK(r.positions_checked > 3000);
    REQUIRE(broke_sampled);
    REQUIRE(broke_unsampled);
    CHECK(r.missing > missing_before);
  }

  TEST_CASE("players switch stealth and team mid-run: the replicator's views pass the oracle from the tick a switch takes effect") {
    // A crowd of players in teams switching visibility every few ticks beside NPCs of every class.
    // With replicator::resync_viewers_of (what zone_server does after the step: resets, or class
    // notes applied before the tick's frame for clients that take them), every client's view
    // passes the oracle's checks at every tick; without it, a teammate's view keeps the class an
    // entity entered with, and the oracle reports wrong classes (the check is not blind).
    enum class mode { resets, notes, neither };
    for (const mode how : {mode::resets, mode::notes, mode::neither}) {
      CAPTURE(static_cast<int>(how));
      const bool with_resync = how != mode::neither;
      const std::uint64_t seed = zone::test::fresh_seed();
      CAPTURE(seed);
      tracked_world w(seed, 300);
      replication_options ro;
      ro.world = w.world;
      ro.byte_budget = 4000;
      replicator rep(ro);
      const net::interest_rules rules = rules_of(ro, 4);
      bots::oracle oracle(w.world, rules, 1, nullptr, nullptr);
      struct client {
        entity_id id;
        client_id c;
        net::client_view view;
      };
      std::vector<client> clients;
      replication_writer writer;
      truth_writer truth;
      std::uint64_t switches = 0, resyncs = 0, notes = 0;
      std::uint64_t first_bad_tick = 0;
      std::vector<replicator::class_note_target> noted;
      for (std::uint64_t tick = 0; tick < 100; ++tick) {
        if (tick > 0) {
          for (auto& p : w.store.positions()) {
            p.x = std::clamp(p.x + w.uni(-1.5f, 1.5f), 0.0f, 400.0f);
            p.y = std::clamp(p.y + w.uni(-1.5f, 1.5f), 0.0f, 400.0f);
          }
        }
        if (tick == 1) {
          for (int k = 0; k < 24; ++k) {
            const auto v = visibility_for(k % 3 == 0, static_cast<std::uint8_t>(k % 3));
            entity_desc d;
            d.position = {w.uni(150, 210), w.uni(150, 210), w.uni(0, 10)};
            d.aoi_half_extent = {30, 30, 30};
            d.kind = entity_kind::player;
            d.visibility_class = v.visibility_class;
            d.sees = v.sees;
            const entity_id id = w.store.create(d);
            REQUIRE(id != null_entity);
            clients.push_back({id, rep.add_client(id), net::client_view(w.world)});
            rep.set_class_notes(clients.back().c, how == mode::notes);
          }
        }
        // Two players switch each tick: stealth toggled, sometimes another team.
        struct change {
          entity_id id;
          std::uint32_t old_class, old_sees;
        };
        std::vector<change> changed;
        for (int k = 0; k < 2 && tick > 3; ++k) {
          const entity_id id = clients[w.rng() % clients.size()].id;
          const auto d = *w.store.get(id);
          const bool stealthed = d.visibility_class != cb::normal;
          const std::uint8_t team = (d.sees & cb::team_red) ? 1 : (d.sees & cb::team_blue) ? 2 : 0;
          const auto v = visibility_for(!stealthed, w.rng() % 2 ? team : static_cast<std::uint8_t>(w.rng() % 3));
          REQUIRE(w.store.set_visibility(id, v.visibility_class, v.sees));
          if (v.visibility_class != d.visibility_class || v.sees != d.sees) changed.push_back({id, d.visibility_class, d.sees});
          ++switches;
        }
        REQUIRE_FALSE(w.tracker.update(w.store.columns()).has_value());
        noted.clear();
        if (with_resync) {
          std::vector<class_change> changes;
          for (const auto& ch : changed) changes.push_back({ch.id, ch.old_class, ch.old_sees});
          resyncs += rep.resync_viewers_of(w.store, w.tracker, tick, changes, nullptr, &noted);
          notes += noted.size();
        }
        REQUIRE_FALSE(oracle.feed(truth.body(w.store, tick)).has_value());
        for (std::size_t i = 0; i < clients.size(); ++i) {
          client& cl = clients[i];
          net::class_changes_msg msg{tick, {}};
          for (const auto& n : noted) {
            if (n.client == cl.c) msg.notes.push_back({n.entity, n.visibility_class});
          }
          if (!msg.notes.empty()) REQUIRE(cl.view.apply(msg) == net::client_view::status::ok);
          const auto frame = rep.build(cl.c, w.store, w.tracker, tick, 0, 0, writer, nullptr);
          const auto m = decode_update(frame);
          REQUIRE(cl.view.apply(m) == net::client_view::status::ok);
          const std::uint64_t before = oracle.counters().mismatches();
          oracle.check(cl.id, tick, cl.view, m.deferred.value_or(net::deferred_counts{}), m.self_position, i);
          if (oracle.counters().mismatches() != before && first_bad_tick == 0) first_bad_tick = tick;
        }
      }
      const auto& c = oracle.counters();
      MESSAGE(std::string(how == mode::resets  ? "resets"
                          : how == mode::notes ? "class notes"
                                               : "neither")
              << ": " << switches << " switches, " << resyncs << " clients resynced, " << notes << " notes, "
              << c.frames_checked.load() << " frames checked; wrong class " << c.wrong_class.load() << ", missing "
              << c.missing.load() << ", extra " << c.extra.load() << ", leaked " << c.leaked.load());
      CHECK(c.frames_checked.load() == 99 * clients.size());
      // The switches reached the oracle as changes to the layout, not whole layouts.
      CHECK(truth.changes > 80);
      CHECK(oracle.report().truth_changes == truth.changes);
      CHECK(truth.layouts <= 2);
      if (with_resync) {
        CHECK((how == mode::resets ? resyncs : notes) > 20);
        if (how == mode::notes) CHECK(resyncs == 0);
        CHECK(c.mismatches() == 0);
        CHECK(first_bad_tick == 0);
      } else {
        CHECK(c.wrong_class.load() > 0);
      }
    }
  }

  TEST_CASE(
      "a layout patched over many ticks (switches, resizes, kinds, creations, removals) equals the world's at every tick, "
      "the ring's earlier ticks keep theirs, and a wrong class or position after a patch is caught") {
    // The oracle's layouts share their ids and unchanged chunks of columns with the tick before;
    // a frame of changes copies only the chunks it touches. Whatever was shared or patched, the
    // layout of every tick must hold exactly that tick's columns (the world's, built here from
    // scratch), and writing one tick's patch must not reach into an earlier tick's layout.
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    raw_world w(seed);
    const net::world_bounds bounds{{0, 0, 0}, {300, 300, 40}};
    net::interest_rules rules;
    rules.hysteresis = 4;
    bots::oracle oracle(bounds, rules, 2, nullptr, nullptr);
    const std::uint32_t seen_all = cb::normal | cb::team_red | cb::team_blue;
    const std::uint32_t three[] = {cb::normal, cb::team_red, cb::team_blue};
    const auto add = [&](net::entity_kind kind) {
      const float p[3] = {w.uni(0, 300), w.uni(0, 300), w.uni(0, 40)};
      const float a = w.uni(10, 40), b = w.uni(0.3f, 3);
      const float e[3] = {a, a, a}, h[3] = {b, b, b};
      return w.add(p, e, h, three[w.rng() % 3], seen_all, kind);
    };
    for (int k = 0; k < 2500; ++k) add(net::entity_kind::npc);
    struct columns {
      std::uint64_t tick;
      std::vector<std::uint32_t> ids, classes, sees;
      std::vector<std::uint8_t> kinds;
      std::vector<float> aoi, presence;
    };
    const auto world_columns = [&](std::uint64_t tick) {
      return columns{tick, w.ids, w.classes, w.sees, w.kinds, w.aoi, w.presence};
    };
    const auto same = [](const columns& c, const bots::oracle::layout_columns& l) {
      return c.ids == l.ids && c.classes == l.classes && c.sees == l.sees && c.kinds == l.kinds && c.aoi == l.aoi &&
             c.presence == l.presence;
    };
    std::deque<columns> kept;  // the world's columns of the ticks the oracle's ring still holds
    std::uint64_t differing = 0, changes_ticks = 0, whole_ticks = 0, shared_on_changes = 0, chunks_on_changes = 0;
    std::uint64_t added = 0, removed = 0, kinds = 0;
    std::vector<std::uint32_t> players;
    const auto random_npc = [&] {
      for (;;) {
        const std::size_t k = w.rng() % w.size();
        if (w.kinds[k] != static_cast<std::uint8_t>(net::entity_kind::player)) return k;
      }
    };
    const auto feed = [&](std::uint64_t tick) {
      const auto before = oracle.report();
      REQUIRE_FALSE(oracle.feed(w.body(tick)).has_value());
      const auto after = oracle.report();
      const auto got = oracle.layout_at(tick);
      REQUIRE(got.has_value());
      kept.push_back(world_columns(tick));
      if (kept.size() > bots::oracle::ring_ticks) kept.pop_front();
      if (!same(kept.back(), *got)) ++differing;
      if (after.truth_changes > before.truth_changes) {
        ++changes_ticks;
        shared_on_changes += got->chunks_shared_with_prev, chunks_on_changes += got->chunks;
      }
      whole_ticks += after.truth_layouts > before.truth_layouts;
    };
    for (std::uint64_t tick = 0; tick < 300; ++tick) {
      if (tick > 0) {
        for (std::size_t k = 0; k < w.size(); ++k) {
          w.pos[3 * k] = std::clamp(w.pos[3 * k] + w.uni(-1, 1), 0.0f, 300.0f);
          w.pos[3 * k + 1] = std::clamp(w.pos[3 * k + 1] + w.uni(-1, 1), 0.0f, 300.0f);
        }
      }
      if (tick == 1) {
        for (int k = 0; k < 40; ++k) players.push_back(add(net::entity_kind::player));
      }
      if (tick > 1) {
        for (int k = 0; k < 5; ++k) w.classes[w.rng() % w.size()] = three[w.rng() % 3];  // switches
        // A resize, every other tick.
        if (w.rng() % 2 == 0) {
          const std::size_t k = w.rng() % w.size();
          const float a = w.uni(10, 40), b = w.uni(0.3f, 3);
          for (int i = 0; i < 3; ++i) w.aoi[3 * k + i] = a, w.presence[3 * k + i] = b;
        }
        if (tick % 13 == 5) {  // an NPC becomes a boss or back: a kind changed (the observers found again)
          const std::size_t k = random_npc();
          w.kinds[k] = static_cast<std::uint8_t>(w.kinds[k] == static_cast<std::uint8_t>(net::entity_kind::npc)
                                                     ? net::entity_kind::boss
                                                     : net::entity_kind::npc);
          ++kinds;
        }
        if (tick % 29 == 7) add(net::entity_kind::npc), ++added;  // appended: the whole layout, the same lineage
        if (tick % 41 == 11) w.remove(random_npc()), ++removed;   // the last moves into the hole
        if (tick % 67 == 33) {                                    // most of the world at once
          for (std::size_t k = 0; k < w.size(); ++k) w.classes[k] = three[w.rng() % 3];
        }
        w.changed = true;
      }
      feed(tick);
    }
    // Every tick the ring still holds has its own columns, patched or shared as they were.
    std::uint64_t ring_differing = 0;
    for (const columns& c : kept) {
      const auto got = oracle.layout_at(c.tick);
      REQUIRE(got.has_value());
      ring_differing += !same(c, *got);
    }
    MESSAGE(changes_ticks << " ticks of changes (" << shared_on_changes << " of " << chunks_on_changes
                          << " chunks shared with the tick before), " << whole_ticks << " whole layouts; " << added
                          << " added, " << removed << " removed, " << kinds << " kinds changed");
    CHECK(differing == 0);
    CHECK(kept.size() == bots::oracle::ring_ticks);
    CHECK(ring_differing == 0);
    CHECK(changes_ticks > 250);
    CHECK(whole_ticks >= 1 + added + removed);
    // A tick of changes copies at most the chunks its ~6 changed rows fall in; the rest are shared.
    CHECK(shared_on_changes > 0);
    CHECK(shared_on_changes + 7 * changes_ticks >= chunks_on_changes);

    // One more tick: a player's visible entity switches class (a frame of changes), nothing moves.
    const std::uint64_t last = 300;
    std::uint32_t observer = 0, target = 0;
    for (const std::uint32_t p : players) {
      const auto vis = oracle.visible(p, last - 1);
      if (vis && !vis->empty()) {
        observer = p, target = vis->front();
        break;
      }
    }
    REQUIRE(observer != 0);
    const auto index_of = [&](std::uint32_t id) {
      const auto it = std::find(w.ids.begin(), w.ids.end(), id);
      REQUIRE(it != w.ids.end());
      return static_cast<std::size_t>(it - w.ids.begin());
    };
    const std::size_t t = index_of(target);
    const std::uint32_t old_class = w.classes[t];
    w.classes[t] = old_class == cb::normal ? cb::team_red : cb::normal;
    w.changed = true;
    const auto changes_before = oracle.report().truth_changes;
    feed(last);
    REQUIRE(oracle.report().truth_changes == changes_before + 1);
    REQUIRE(same(kept.back(), *oracle.layout_at(last)));
    const auto vis = oracle.visible(observer, last);
    REQUIRE(vis.has_value());
    REQUIRE(std::find(vis->begin(), vis->end(), target) != vis->end());
    // The true view passes; the same view with the target's class of before the patch, or with it
    // 1 m away, fails, each under its own kind only.
    const std::size_t self = index_of(observer);
    const net::vec3f own{w.pos[3 * self], w.pos[3 * self + 1], w.pos[3 * self + 2]};
    const auto view_with = [&](std::uint32_t target_class, float dx) {
      net::client_view view(bounds);
      net::tick_update_msg m;
      m.server_tick = last;
      m.reset = true;
      for (const std::uint32_t id : *vis) {
        const std::size_t k = index_of(id);
        m.enters.push_back({id,
                            static_cast<net::entity_kind>(w.kinds[k]),
                            id == target ? target_class : w.classes[k],
                            {w.pos[3 * k] + (id == target ? dx : 0.0f), w.pos[3 * k + 1], w.pos[3 * k + 2]},
                            {},
                            {w.presence[3 * k], w.presence[3 * k + 1], w.presence[3 * k + 2]},
                            {}});
      }
      REQUIRE(view.apply(m) == net::client_view::status::ok);
      return view;
    };
    const auto& c = oracle.counters();
    oracle.check(observer, last, view_with(w.classes[t], 0), {}, own, 0);
    CHECK(c.frames_checked.load() == 1);
    CHECK(c.mismatches() == 0);
    oracle.check(observer, last, view_with(old_class, 0), {}, own, 1);
    CHECK(c.wrong_class.load() == 1);
    CHECK(c.mismatches() == 1);
    oracle.check(observer, last, view_with(w.classes[t], 1.0f), {}, own, 2);
    CHECK(c.position.load() == 1);
    CHECK(c.mismatches() == 2);
    // A position no comparison can hold (NaN) is a wrong position, not one within the tolerance.
    oracle.check(observer, last, view_with(w.classes[t], std::numeric_limits<float>::quiet_NaN()), {}, own, 3);
    CHECK(c.position.load() == 2);
    CHECK(c.mismatches() == 3);
    CHECK(c.frames_checked.load() == 4);
  }
}
