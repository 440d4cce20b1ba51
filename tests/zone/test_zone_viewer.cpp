// The zone server's live viewer (net/viewer.h): the tick publishes snapshots only while a page is
// open, a page's frames hold every entity of the zone, and a selected entity's visible set, tiers
// and events are the interest tracker's.
#include <doctest/doctest.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <map>
#include <optional>
#include <random>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "../common/loopback_zone.h"
#include "../common/seeds.h"
#include "interest/thread_pool.h"
#include "tests/net/loopback_client.h"
#include "tests/net/ws_client.h"
#include "zone/viewer_columns.h"
#include "zone/zone_server.h"

using namespace zone;
using zone::net::testing::at;
using zone::net::testing::eventually;
using zone::net::testing::request_bytes;
using zone::net::testing::test_client;
using zone::net::testing::ws_client;

namespace {

zone_config viewer_config() {
  zone_config c = zone::test::loopback_zone_config();
  c.npc_count = 400;
  c.town_count = 2;
  c.worker_threads = 2;
  c.metrics_enabled = true;
  c.viewer_enabled = true;
  c.viewer_hz = 30;  // a snapshot every tick
  return c;
}

/// Every column copied whole from the store, single-threaded, as the fill did before it copied
/// only what changed: the reference for fill_viewer_columns.
void full_copy_columns(const entity_store& store, net::viewer_snapshot& s) {
  const std::size_t n = store.size();
  const auto pos = store.positions();
  s.xy.resize(2 * n);
  for (std::size_t i = 0; i < n; ++i) {
    s.xy[2 * i] = pos[i].x;
    s.xy[2 * i + 1] = pos[i].y;
  }
  const auto ids = store.ids();
  s.ids.assign(ids.begin(), ids.end());
  const auto cls = store.visibility_classes();
  s.classes.assign(cls.begin(), cls.end());
  s.kind.resize(n);
  if (n > 0) std::memcpy(s.kind.data(), store.kinds().data(), n);
  s.layout = store.layout_version();
}

/// The snapshot's columns, byte for byte (x and y bit patterns, not float equality).
bool same_columns(const net::viewer_snapshot& a, const net::viewer_snapshot& b) {
  const auto bytes_equal = [](const auto& x, const auto& y) {
    return x.size() == y.size() && (x.empty() || std::memcmp(x.data(), y.data(), x.size() * sizeof(x[0])) == 0);
  };
  return a.layout == b.layout && bytes_equal(a.xy, b.xy) && bytes_equal(a.ids, b.ids) &&
         bytes_equal(a.classes, b.classes) && bytes_equal(a.kind, b.kind);
}

/// The columns equal the store's, entity by entity (independent of both copies).
void check_columns_are_store(const entity_store& store, const net::viewer_snapshot& s) {
  REQUIRE(s.size() == store.size());
  REQUIRE(s.xy.size() == 2 * store.size());
  CHECK(s.layout == store.layout_version());
  std::size_t bad = 0;
  for (std::size_t i = 0; i < store.size(); ++i) {
    const vec3 p = store.positions()[i];
    bad += s.ids[i] != store.ids()[i] || s.classes[i] != store.visibility_classes()[i] ||
           s.kind[i] != static_cast<std::uint8_t>(store.kinds()[i]) || std::memcmp(&s.xy[2 * i], &p.x, 4) != 0 ||
           std::memcmp(&s.xy[2 * i + 1], &p.y, 4) != 0;
  }
  CHECK(bad == 0);
}

void add_random_entities(entity_store& store, std::size_t count, std::mt19937& rng) {
  std::uniform_real_distribution<float> coord(-100.0f, 5000.0f);
  const std::uint32_t classes[] = {interest::category_bits::normal, interest::category_bits::stealth,
                                   interest::category_bits::team_red, interest::category_bits::team_blue};
  std::size_t refused = 0;
  for (std::size_t k = 0; k < count; ++k) {
    entity_desc d;
    d.position = {coord(rng), coord(rng), coord(rng) * 0.01f};
    d.visibility_class = classes[rng() % 4];
    d.kind = static_cast<entity_kind>(rng() % 3);
    refused += store.create(d) == null_entity ? 1 : 0;
  }
  REQUIRE(refused == 0);
}

/// A world extension that churns the store: a player spawned every step and, from the fifth step
/// on, the oldest one despawned (the count stays, the ids do not).
struct churn final : zone_extension {
  std::vector<entity_id> spawned;
  int step = 0;
  void started(std::uint16_t) override {}
  void before_step(zone_world& w) override {
    ++step;
    if (step > 4) {
      CHECK(w.despawn(spawned.front()));
      spawned.erase(spawned.begin());
    }
    spawned.push_back(w.spawn_player({50.0f + 3.0f * static_cast<float>(step % 150), 300, 0}, step % 4 == 1));
  }
  void after_step(zone_world&, std::vector<redirect>&) override {}
  claim claim_token(const std::string&, zone_world&, entity_id&) override { return claim::refused; }
  [[nodiscard]] bool owns(entity_id) const override { return true; }
  void forward_input(entity_id, const vec3&, std::uint32_t) override {}
};

/// Record k of an entities frame (docs/viewer.md): its id, its position back from the frame's
/// 16-bit grid over the frame's bounds, how far that may be from the true one (a grid step and a
/// float's rounding), its class bit and kind.
struct entity_record {
  std::uint32_t id;
  float x, y, tolerance_x, tolerance_y;
  std::uint8_t class_bit, kind;
};
entity_record record_of(const std::vector<std::uint8_t>& f, std::size_t k) {
  const float x0 = at<float>(f, 16), y0 = at<float>(f, 20), x1 = at<float>(f, 24), y1 = at<float>(f, 28);
  const std::size_t o = net::viewer_frame_header_bytes + k * net::viewer_entity_record_bytes;
  return {at<std::uint32_t>(f, o),
          x0 + at<std::uint16_t>(f, o + 4) * (x1 - x0) / 65535,
          y0 + at<std::uint16_t>(f, o + 6) * (y1 - y0) / 65535,
          (x1 - x0) / 65535 + 1e-3f,
          (y1 - y0) / 65535 + 1e-3f,
          f[o + 8],
          f[o + 9]};
}

}  // namespace

TEST_SUITE("zone.viewer") {
  TEST_CASE("the snapshot's columns over a pool are a full single-threaded copy's bytes (sizes 0, 1, odd, large)") {
    std::mt19937 rng(20261129);
    interest::thread_pool pool2(2), pool5(5);
    interest::thread_pool* pools[] = {nullptr, &pool2, &pool5};
    for (const std::size_t n : {std::size_t{0}, std::size_t{1}, std::size_t{2}, std::size_t{777}, viewer_columns_chunk - 1,
                                viewer_columns_chunk, viewer_columns_chunk + 1, 2 * viewer_columns_chunk + 4097,
                                std::size_t{100003}}) {
      for (const std::size_t chunk : {viewer_columns_chunk, std::size_t{7}, std::size_t{1000}}) {
        if (chunk < 1000 && n > 40000) continue;  // 14,000 tasks a fill: long on a small host, nothing more to see
        CAPTURE(n);
        CAPTURE(chunk);
        entity_store store(n + 64);
        add_random_entities(store, n, rng);
        // Holes filled from the end (destroy moves the last entity into them): ids out of order.
        for (std::size_t k = 0; k < n / 10; ++k) (void)store.destroy(store.ids()[rng() % store.size()]);
        add_random_entities(store, n - store.size(), rng);
        REQUIRE(store.size() == n);
        for (interest::thread_pool* pool : pools) {
          CAPTURE(pool != nullptr ? pool->size() : 0u);
          net::viewer_snapshot fresh, full_fresh;
          fill_viewer_columns(store, fresh, pool, chunk);
          full_copy_columns(store, full_fresh);
          CHECK(same_columns(fresh, full_fresh));
          check_columns_are_store(store, fresh);

          // A buffer filled before (a larger store's, then this one's), reused as the tick reuses
          // the viewer's three: positions moved (same layout: the ids, classes and kinds are kept),
          // then entities destroyed and created (a new layout: all copied again).
          net::viewer_snapshot s, full_s;
          entity_store other(n + 200);
          add_random_entities(other, n + 100, rng);
          fill_viewer_columns(other, s, pool, chunk);
          full_copy_columns(other, full_s);
          REQUIRE(same_columns(s, full_s));
          fill_viewer_columns(store, s, pool, chunk);
          full_copy_columns(store, full_s);
          CHECK(same_columns(s, full_s));
          check_columns_are_store(store, s);
          std::uniform_real_distribution<float> step(-2.0f, 2.0f);
          for (vec3& p : store.positions()) p = {p.x + step(rng), p.y + step(rng), p.z + step(rng)};
          fill_viewer_columns(store, s, pool, chunk);
          full_copy_columns(store, full_s);
          CHECK(same_columns(s, full_s));
          check_columns_are_store(store, s);
          if (n > 0) {
            (void)store.destroy(store.ids()[rng() % store.size()]);
            add_random_entities(store, 1, rng);
            if (n > 2) (void)store.set_visibility(store.ids()[n / 2], interest::category_bits::stealth, interest::category_bits::normal);
          }
          fill_viewer_columns(store, s, pool, chunk);
          full_copy_columns(store, full_s);
          CHECK(same_columns(s, full_s));
          check_columns_are_store(store, s);
        }
      }
    }
  }

  TEST_CASE(
      "three rotating buffers filled incrementally hold a full copy's columns (creations, removals, switches, extents)") {
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    std::mt19937 rng(static_cast<std::uint32_t>(seed));
    interest::thread_pool pool2(2), pool5(5);
    const std::uint32_t classes[] = {interest::category_bits::normal, interest::category_bits::stealth,
                                     interest::category_bits::team_red, interest::category_bits::team_blue};
    std::size_t seen[3] = {0, 0, 0};  // fills by viewer_columns_fill
    for (const std::size_t n : {std::size_t{0}, std::size_t{1}, std::size_t{2}, std::size_t{777},
                                viewer_columns_chunk + 1, std::size_t{100003}}) {
      for (interest::thread_pool* pool : {static_cast<interest::thread_pool*>(nullptr), &pool2, &pool5}) {
        const std::size_t chunk = n < 1000 ? 7 : n < 20000 ? 1000 : viewer_columns_chunk;
        CAPTURE(n);
        CAPTURE(pool != nullptr ? pool->size() : 0u);
        entity_store store(n + 64);
        add_random_entities(store, n, rng);
        for (std::size_t k = 0; k < n / 10; ++k)
          (void)store.destroy(store.ids()[rng() % store.size()]);  // ids out of order
        add_random_entities(store, n - store.size(), rng);
        REQUIRE(store.size() == n);
        // What changed since each buffer was last filled: the switches (set_visibility calls) and
        // whether anything else changed the layout; never filled: all.
        struct since_fill {
          bool filled = false, other = false;
          std::size_t switches = 0;
        } since[3];
        net::viewer_snapshot buffers[3];
        std::uniform_real_distribution<float> step(-2.0f, 2.0f);
        // 24 ticks of random changes, then 8 of a fixed schedule that takes each path whatever the
        // random ones did (the random ticks alone took classes_patched only 18 times in all for
        // seed 681644664565031617). A fill at tick t sees ticks t-2..t: positions only at 24-27,
        // one switch at 28 (n > 0), positions only at 29-31; so the fills at 26, 27 and 31 find
        // positions only and those at 28-30 patch classes (n > 0). With the first 3 (all) of each
        // of the 18 runs: each path at least 45 times.
        constexpr int random_ticks = 24, ticks = random_ticks + 8;
        for (int t = 0; t < ticks; ++t) {
          CAPTURE(t);
          for (vec3& p : store.positions()) p = {p.x + step(rng), p.y + step(rng), p.z + step(rng)};  // every tick
          std::size_t switches = 0;
          bool other = false;
          const unsigned change = t < random_ticks ? static_cast<unsigned>(rng() % 6)
                                  : t == random_ticks + 4 ? 6u
                                                          : 5u;
          switch (change) {
            case 6:  // exactly one visibility switch
              if (n > 0) {
                REQUIRE(store.set_visibility(store.ids()[rng() % n], classes[rng() % 4], interest::category_bits::normal));
                switches = 1;
              }
              break;
            case 0:  // a few visibility switches, an entity switched twice now and then
              for (std::size_t k = 0, m = 1 + rng() % 5; k < m && n > 0; ++k) {
                const entity_id id = store.ids()[rng() % n];
                REQUIRE(store.set_visibility(id, classes[rng() % 4], interest::category_bits::normal));
                ++switches;
                if (rng() % 3 == 0) {
                  REQUIRE(store.set_visibility(id, classes[rng() % 4], interest::category_bits::normal));
                  ++switches;
                }
              }
              break;
            case 1:  // one destroyed, one created: the dense order moves
              if (n > 0) REQUIRE(store.destroy(store.ids()[rng() % n]));
              add_random_entities(store, 1, rng);
              if (n == 0) REQUIRE(store.destroy(store.ids()[0]));
              other = true;
              break;
            case 2:  // an extent (not a viewer column, but the layout changes: copied whole)
              if (n > 0) {
                REQUIRE(store.set_aoi_half_extent(store.ids()[rng() % n], {20, 20, 20}));
                other = true;
              }
              break;
            case 3:  // more switches than the journal holds
              if (n > 0 && rng() % 2 == 0) {
                for (std::size_t k = 0; k < entity_store::class_journal_size + 3; ++k) {
                  REQUIRE(store.set_visibility(store.ids()[rng() % n], classes[rng() % 4],
                                               interest::category_bits::normal));
                }
                switches = entity_store::class_journal_size + 3;
              }
              break;
            default:  // positions only
              break;
          }
          for (auto& f : since) {
            f.switches += switches;
            f.other = f.other || other;
          }
          const std::size_t b = static_cast<std::size_t>(t) % 3;
          const viewer_columns_fill expect =
              !since[b].filled || since[b].other || since[b].switches > entity_store::class_journal_size
                  ? viewer_columns_fill::all
              : since[b].switches > 0 ? viewer_columns_fill::classes_patched
                                      : viewer_columns_fill::positions;
          const viewer_columns_fill got = fill_viewer_columns(store, buffers[b], pool, chunk);
          CHECK(static_cast<int>(got) == static_cast<int>(expect));
          ++seen[static_cast<int>(got)];
          since[b] = {true, false, 0};
          net::viewer_snapshot full;
          full_copy_columns(store, full);
          CHECK(same_columns(buffers[b], full));
          check_columns_are_store(store, buffers[b]);
        }
      }
    }
    CHECK(seen[0] > 20);  // each path taken
    CHECK(seen[1] > 20);
    CHECK(seen[2] > 20);
  }

  TEST_CASE(
      "the copier's thread fills a snapshot's columns as the tick would, then publishes it; wait() returns once") {
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    std::mt19937 rng(static_cast<std::uint32_t>(seed));
    net::viewer_server viewer;
    viewer_copier copier;
    CHECK_FALSE(copier.wait().has_value());  // nothing started
    std::uint64_t published = viewer.stats().snapshots_published;
    for (const std::size_t n : {std::size_t{0}, std::size_t{1}, std::size_t{1001}, std::size_t{100003}}) {
      CAPTURE(n);
      entity_store store(n + 8);
      add_random_entities(store, n, rng);
      std::uniform_real_distribution<float> step(-2.0f, 2.0f);
      for (int t = 0; t < 7; ++t) {
        CAPTURE(t);
        for (vec3& p : store.positions()) p = {p.x + step(rng), p.y + step(rng), p.z + step(rng)};
        if (t == 3 && n > 0) (void)store.destroy(store.ids()[rng() % n]), add_random_entities(store, 1, rng);
        net::viewer_snapshot& s = viewer.next_snapshot();
        // What the tick's own fill would give this buffer: the reference.
        net::viewer_snapshot want = s;
        const viewer_columns_fill expect = fill_viewer_columns(store, want, nullptr);
        copier.start(store, s, viewer, 0);
        const auto done = copier.wait();
        REQUIRE(done.has_value());
        CHECK(static_cast<int>(done->what) == static_cast<int>(expect));
        CHECK(done->copy_ms >= 0);
        CHECK_FALSE(copier.wait().has_value());  // once
        CHECK(viewer.stats().snapshots_published == ++published);
        CHECK(&viewer.next_snapshot() != &s);  // published: the producer moved on to another buffer
        CHECK(same_columns(s, want));
        check_columns_are_store(store, s);
      }
    }
  }

  TEST_CASE("config: the viewer needs the HTTP endpoint; rates and caps are checked") {
    auto c = viewer_config();
    c.metrics_enabled = false;
    CHECK(validate(c).has_value());
    c = viewer_config();
    c.viewer_hz = 0;
    CHECK(validate(c).has_value());
    c = viewer_config();
    c.max_viewers = 0;
    CHECK(validate(c).has_value());
    CHECK_FALSE(validate(viewer_config()).has_value());
    const char* argv[] = {"zone-server", "--viewer", "1", "--max-viewers", "2", "--viewer-hz", "5"};
    const auto parsed = parse_config(7, argv);
    REQUIRE(parsed.config);
    CHECK(parsed.config->viewer_enabled);
    CHECK(parsed.config->max_viewers == 2);
    CHECK(parsed.config->viewer_hz == 5);
    CHECK_FALSE(parse_config(1, argv).config->viewer_enabled);  // off by default
  }

  TEST_CASE("a page sees every entity and the tracker's visible set of the entity it selects") {
    zone_server server(viewer_config());
    REQUIRE_FALSE(server.start().has_value());
    REQUIRE(server.viewer() != nullptr);
    // No page: the tick publishes nothing.
    for (int k = 0; k < 5; ++k) server.tick_once();
    CHECK(server.viewer()->stats().snapshots_published == 0);

    const auto& store = server.world().store();
    // The entity that sees the most (a selection worth checking), as of the last tick.
    entity_id chosen = null_entity;
    std::size_t most = 0;
    for (std::size_t r = 0; r < server.world().tracker().observer_count(); ++r) {
      if (server.world().tracker().visible(r).size() > most) {
        most = server.world().tracker().visible(r).size();
        chosen = server.world().tracker().observer(r);
      }
    }
    REQUIRE(most > 5);
    ws_client page(server.metrics_port());
    REQUIRE_FALSE(page.error);
    REQUIRE(page.send(request_bytes({-10, -10, 610, 610, chosen, 100000})));
    REQUIRE(eventually([&] { return server.viewer()->selected() == std::vector<std::uint32_t>{chosen}; }));
    for (int k = 0; k < 40; ++k) server.tick_once();
    CHECK(server.viewer()->stats().snapshots_published >= 39);

    // The newest frames are those of the last tick (nothing ticks while we read).
    const auto tick = static_cast<std::uint32_t>(server.world().tick());
    std::optional<std::vector<std::uint8_t>> entities, selection;
    for (int k = 0; k < 200 && !(entities && selection); ++k) {
      auto m = page.read();
      REQUIRE(m);
      if (m->first || m->second.empty()) continue;
      const auto& f = m->second;
      if (at<std::uint32_t>(f, 4) != tick) continue;
      if (f[0] == net::viewer_frame_entities) entities = f;
      if (f[0] == net::viewer_frame_selection) selection = f;
    }
    REQUIRE(entities);
    REQUIRE(selection);
    // Every entity, once.
    CHECK(at<std::uint32_t>(*entities, 8) == store.size());
    REQUIRE(at<std::uint32_t>(*entities, 12) == store.size());
    std::set<std::uint32_t> seen;
    for (std::size_t k = 0; k < store.size(); ++k) {
      seen.insert(record_of(*entities, k).id);
    }
    CHECK(seen == std::set<std::uint32_t>(store.ids().begin(), store.ids().end()));
    // The selection: the tracker's visible set, in order, with the replicator's distance tiers.
    const auto& tr = server.world().tracker();
    const auto row = tr.row_of(chosen);
    REQUIRE(row != entity_store::npos);
    const auto visible = tr.visible(row);
    CHECK(visible.size() > 5);
    CHECK(at<std::uint32_t>(*selection, 8) == chosen);
    CHECK((*selection)[1] == 1);  // alive
    REQUIRE(at<std::uint32_t>(*selection, 56) == visible.size());
    const auto me = *store.get(chosen);
    for (std::size_t k = 0; k < visible.size(); ++k) {
      CHECK(at<std::uint32_t>(*selection, 64 + 4 * k) == visible[k]);
      const auto other = *store.get(visible[k]);
      const float dx = other.position.x - me.position.x, dy = other.position.y - me.position.y,
                  dz = other.position.z - me.position.z, d = std::sqrt(dx * dx + dy * dy + dz * dz);
      const std::uint8_t tier = (*selection)[64 + 4 * visible.size() + k];
      if (std::fabs(d - 12) > 0.01f && std::fabs(d - 30) > 0.01f) CHECK(tier == (d < 12 ? 0 : d < 30 ? 1 : 2));
    }
    CHECK(at<float>(*selection, 24) == me.aoi_half_extent.x);
    CHECK(at<float>(*selection, 12) == me.position.x);

    // The page leaves: the tick stops publishing.
    page.ws.next_layer().close();
    REQUIRE(eventually([&] { return server.viewer()->viewers() == 0; }));
    server.tick_once();
    const auto published = server.viewer()->stats().snapshots_published;
    for (int k = 0; k < 5; ++k) server.tick_once();
    CHECK(server.viewer()->stats().snapshots_published == published);
  }

  TEST_CASE("entities created and destroyed while a page is open: every frame holds the store's entities, where they are") {
    // The snapshot copies ids, classes and kinds only when the store's layout changed since that
    // snapshot was filled (positions always): churn every tick must show in every frame.
    churn ext;
    // The columns copied in the tick (--viewer-fill wait) or on the copier's thread after it.
    std::string fill;
    SUBCASE("filled in the tick") { fill = "wait"; }
    SUBCASE("filled after the tick") { fill = "after"; }
    CAPTURE(fill);
    auto cfg = viewer_config();
    cfg.viewer_fill = fill;
    zone_server server(cfg);
    server.set_extension(&ext);
    REQUIRE_FALSE(server.start().has_value());
    ws_client page(server.metrics_port());
    REQUIRE_FALSE(page.error);
    REQUIRE(page.send(request_bytes({-10, -10, 610, 610, 0, 100000})));
    REQUIRE(eventually([&] { return server.viewer()->viewers() == 1; }));
    const auto& store = server.world().store();
    int checked = 0;
    for (int round = 0; round < 12; ++round) {
      server.tick_once();
      server.viewer_flush();
      const auto tick = static_cast<std::uint32_t>(server.world().tick());
      std::optional<std::vector<std::uint8_t>> f;
      for (int k = 0; k < 200 && !f; ++k) {
        auto m = page.read();
        REQUIRE(m);
        if (!m->first && !m->second.empty() && m->second[0] == net::viewer_frame_entities && at<std::uint32_t>(m->second, 4) == tick) {
          f = m->second;
        }
      }
      if (!f) continue;  // the session wrote an older frame meanwhile: the next round has this one's successor
      ++checked;
      REQUIRE(at<std::uint32_t>(*f, 12) == store.size());
      std::set<std::uint32_t> seen;
      for (std::size_t k = 0; k < store.size(); ++k) {
        const entity_record r = record_of(*f, k);
        seen.insert(r.id);
        const auto e = store.get(r.id);
        REQUIRE(e);
        CHECK(std::fabs(r.x - e->position.x) <= r.tolerance_x);
        CHECK(std::fabs(r.y - e->position.y) <= r.tolerance_y);
        CHECK(r.kind == static_cast<std::uint8_t>(e->kind));
        CHECK(r.class_bit == std::countr_zero(e->visibility_class));
      }
      CHECK(seen == std::set<std::uint32_t>(store.ids().begin(), store.ids().end()));
    }
    CHECK(checked >= 6);
    CHECK(ext.spawned.size() >= 4);
  }

  TEST_CASE("--viewer-fill after, ticks back to back as run() does (no viewer_flush): every frame is its tick's store, every copy counted once") {
    // The other server tests wait for the copier after each tick (viewer_flush); here the next
    // tick's own wait is all that keeps its step (churn: an entity out and one in, the NPCs
    // moving) off the copy of the last tick's snapshot (ThreadSanitizer sees a missing wait), and
    // its accounting is all that counts the copies.
    churn ext;
    auto cfg = viewer_config();
    cfg.viewer_fill = "after";
    zone_server server(cfg);
    server.set_extension(&ext);
    REQUIRE_FALSE(server.start().has_value());
    ws_client page(server.metrics_port());
    REQUIRE_FALSE(page.error);
    REQUIRE(page.send(request_bytes({-10, -10, 610, 610, 0, 100000})));
    REQUIRE(eventually([&] { return server.viewer()->viewers() == 1; }));
    const auto& store = server.world().store();
    // Each tick's store as the tick left it (read beside the copier: both only read it).
    struct row {
      float x, y;
      std::uint8_t cls, kind;
    };
    std::map<std::uint32_t, std::map<std::uint32_t, row>> at_tick;
    const std::uint64_t after0 = server.stats().viewer_columns_after_tick;
    const std::uint64_t published0 = server.viewer()->stats().snapshots_published;
    std::uint64_t ticks = 0;
    int checked = 0;
    for (int round = 0; round < 40; ++round) {
      std::uint32_t last = 0;
      for (int k = 0; k < 3; ++k) {  // back to back: the copy of one overlaps the next one's start
        server.tick_once();
        ++ticks;
        last = static_cast<std::uint32_t>(server.world().tick());
        auto& m = at_tick[last];
        for (std::size_t d = 0; d < store.size(); ++d) {
          const vec3 p = store.positions()[d];
          m[store.ids()[d]] = {p.x, p.y, static_cast<std::uint8_t>(std::countr_zero(store.visibility_classes()[d])),
                               static_cast<std::uint8_t>(store.kinds()[d])};
        }
      }
      // The frames that came meanwhile, up to the last tick's (published by the copier).
      for (int k = 0; k < 50; ++k) {
        auto msg = page.read();
        REQUIRE(msg);
        const auto& f = msg->second;
        if (msg->first || f.empty() || f[0] != net::viewer_frame_entities) continue;
        const std::uint32_t tick = at<std::uint32_t>(f, 4);
        const auto it = at_tick.find(tick);
        REQUIRE(it != at_tick.end());
        CAPTURE(tick);
        const auto& want = it->second;
        REQUIRE(at<std::uint32_t>(f, 12) == want.size());
        std::size_t bad = 0;
        for (std::size_t e = 0; e < want.size(); ++e) {
          const entity_record r = record_of(f, e);
          const auto w = want.find(r.id);
          if (w == want.end()) {
            ++bad;
            continue;
          }
          bad += std::fabs(r.x - w->second.x) > r.tolerance_x || std::fabs(r.y - w->second.y) > r.tolerance_y ||
                 r.class_bit != w->second.cls || r.kind != w->second.kind;
        }
        CHECK(bad == 0);
        ++checked;
        if (tick == last) break;
      }
    }
    server.viewer_flush();
    // Every tick's snapshot due (viewer_hz = tick rate): each copied after its tick, counted once,
    // published once.
    CHECK(server.stats().viewer_columns_after_tick - after0 == ticks);
    CHECK(server.viewer()->stats().snapshots_published - published0 == ticks);
    CHECK(checked >= 20);
    CHECK(ext.spawned.size() >= 4);
  }

  TEST_CASE("--viewer-fill after: a tick's wait for the copier is in its viewer phase and viewer_fill_ms, not its inputs") {
    // Ticks back to back with a large zone: each tick starts while the copier still copies the
    // last one's snapshot, so its wait is long enough to tell where it was counted.
    const std::string csv_path = "test_zone_viewer_wait_ticks.csv";
    std::map<std::uint64_t, double> waited;  // tick -> its wait for the copier (loop_stats)
    {
      auto cfg = viewer_config();
      cfg.viewer_fill = "after";
      cfg.npc_count = 60000;
      cfg.world = {{0, 0, 0}, {8000, 8000, 40}};
      cfg.tick_csv = csv_path;
      zone_server server(cfg);
      REQUIRE_FALSE(server.start().has_value());
      ws_client page(server.metrics_port());
      REQUIRE_FALSE(page.error);
      REQUIRE(page.send(request_bytes({0, 0, 8000, 8000, 0, 1000})));
      REQUIRE(eventually([&] { return server.viewer()->viewers() == 1; }));
      for (int k = 0; k < 30; ++k) {
        const double before = server.stats().viewer_copy_wait_ms;
        server.tick_once();
        waited[server.world().tick()] = server.stats().viewer_copy_wait_ms - before;
      }
    }  // the tick CSV is complete once the server is gone
    std::ifstream in(csv_path);
    REQUIRE(in.good());
    std::string line;
    REQUIRE(std::getline(in, line));
    std::size_t rows = 0;
    double longest = 0;
    while (std::getline(in, line)) {
      std::vector<double> v;
      std::istringstream row(line);
      for (std::string cell; std::getline(row, cell, ',');) v.push_back(std::stod(cell));
      REQUIRE(v.size() == 18);  // the columns of --tick-csv (docs/operating.md)
      const auto it = waited.find(static_cast<std::uint64_t>(v[0]));
      if (it == waited.end()) continue;
      ++rows;
      CAPTURE(it->first);
      const double wait = it->second, inputs = v[5], tick = v[10], viewer = v[11], fill = v[12];
      CAPTURE(wait);
      longest = std::max(longest, wait);
      constexpr double rounding = 0.002;  // the CSV's 3 decimals (4 for viewer_fill_ms)
      CHECK(viewer + rounding >= wait);   // the viewer's cost to the tick: its phase
      CHECK(fill + rounding >= wait);     // and the snapshot's fill on the tick's threads
      CHECK(inputs + viewer <= tick + rounding);  // counted once: not in the inputs phase too
    }
    CHECK(rows == waited.size());
    CHECK(longest > 0.02);  // a wait long enough to show (else the checks above could not fail)
    std::remove(csv_path.c_str());
  }

  TEST_CASE("with clients (frames every tick): each snapshot is its tick's store and tracker, filled in the engines' waits or after") {
    const std::string csv_path = "test_zone_viewer_ticks.csv";
    // The columns copied in the tick (--viewer-fill wait) or on the copier's thread after it.
    std::string fill;
    SUBCASE("columns in the tick") { fill = "wait"; }
    SUBCASE("columns after the tick") { fill = "after"; }
    CAPTURE(fill);
    std::uint64_t first_tick = 0, last_tick = 0;  // the ticks with the page open
    {
      // On the GPU interest engine the snapshot's columns are copied while its device works (inside
      // the step); with clients on the GPU replication engine, the rest (the selection, the step's
      // watched events) while that device works; publish_viewer then only publishes. On the host,
      // publish_viewer fills it all. Either way a snapshot due every third tick (viewer_hz 10) holds
      // the store and the tracker as the tick left them, and the selection's events (taken on every
      // tick, in a wait or not) are the tracker's.
      auto cfg = viewer_config();
      cfg.viewer_hz = 10;
      cfg.tick_csv = csv_path;
      cfg.viewer_copy_chunk = 37;  // the columns copied in a dozen tasks over the pool where a device wait allows it
      cfg.viewer_fill = fill;
      zone_server server(cfg);
      REQUIRE_FALSE(server.start().has_value());
      constexpr int count = 3;
      std::vector<std::unique_ptr<test_client>> clients;
      for (int i = 0; i < count; ++i) {
        clients.push_back(std::make_unique<test_client>(server.port()));
        REQUIRE(clients.back()->send(net::hello_msg{"viewed" + std::to_string(i), "", net::protocol_version}));
      }
      std::vector<entity_id> me(count, null_entity);
      std::uint32_t seq = 0;
      const auto tick_and_read = [&] {
        server.tick_once();
        server.viewer_flush();  // after the tick: its snapshot published once the copier is done
        ++seq;
        for (int i = 0; i < count; ++i) {
          while (auto m = clients[i]->read(std::chrono::milliseconds(1))) {
            if (const auto* w = std::get_if<net::welcome_msg>(&*m)) me[i] = w->entity_id;
          }
          // Steered: the selected player moves, so that its visible set changes (enters, leaves).
          if (me[i] != null_entity) (void)clients[i]->send(net::input_msg{seq, {1, 0.3f, 0}});
        }
      };
      const auto joined_by = std::chrono::steady_clock::now() + std::chrono::seconds(10);
      while (server.stats().clients < count && std::chrono::steady_clock::now() < joined_by) {
        tick_and_read();
        std::this_thread::sleep_for(std::chrono::milliseconds(3));
      }
      REQUIRE(server.stats().clients == count);
      for (int i = 0; i < count; ++i) {
        while (me[i] == null_entity) {
          const auto m = clients[i]->read(std::chrono::milliseconds(5000));
          REQUIRE(m);
          if (const auto* w = std::get_if<net::welcome_msg>(&*m)) me[i] = w->entity_id;
        }
      }
      const entity_id chosen = me[0];
      REQUIRE(chosen != null_entity);

      ws_client page(server.metrics_port());
      REQUIRE_FALSE(page.error);
      REQUIRE(page.send(request_bytes({-10, -10, 610, 610, chosen, 100000})));
      REQUIRE(eventually([&] { return server.viewer()->selected() == std::vector<std::uint32_t>{chosen}; }));
      tick_and_read();  // the tick takes the selection (its snapshots hold it from the next on)
      const auto& store = server.world().store();
      const auto& tr = server.world().tracker();
      struct event {
        std::uint32_t tick, id;
        bool enter;
        bool operator==(const event&) const = default;
      };
      std::vector<event> events;  // the tracker's, every tick from here on
      const std::uint64_t in_wait0 = server.stats().viewer_snapshots_in_wait;
      const std::uint64_t columns0 = server.stats().viewer_columns_in_interest_wait;
      const std::uint64_t after0 = server.stats().viewer_columns_after_tick;
      std::uint64_t due_ticks = 0;
      std::size_t checked = 0, events_checked = 0;
      first_tick = server.world().tick() + 1;
      for (int round = 0; round < 150; ++round) {
        const auto published = server.viewer()->stats().snapshots_published;
        tick_and_read();
        const auto tick = static_cast<std::uint32_t>(server.world().tick());
        CAPTURE(tick);
        const std::size_t row = tr.row_of(chosen);
        REQUIRE(row != entity_store::npos);
        for (const entity_id id : tr.enters(row)) events.push_back({tick, id, true});
        for (const entity_id id : tr.leaves(row)) events.push_back({tick, id, false});
        const bool due = tick % 3 == 0;
        due_ticks += due ? 1 : 0;
        CHECK(server.viewer()->stats().snapshots_published == published + (due ? 1 : 0));
        if (!due) continue;
        std::optional<std::vector<std::uint8_t>> entities, selection;
        for (int k = 0; k < 200 && !(entities && selection); ++k) {
          auto m = page.read();
          if (!m) break;  // nothing newer (the session skipped this tick's snapshot)
          if (m->first || m->second.empty() || at<std::uint32_t>(m->second, 4) != tick) continue;
          if (m->second[0] == net::viewer_frame_entities) entities = m->second;
          if (m->second[0] == net::viewer_frame_selection) selection = m->second;
        }
        if (!entities || !selection) continue;  // the session wrote an older frame meanwhile
        ++checked;
        // Every entity where the store has it after the tick.
        REQUIRE(at<std::uint32_t>(*entities, 12) == store.size());
        for (std::size_t k = 0; k < store.size(); ++k) {
          const entity_record r = record_of(*entities, k);
          const auto e = store.get(r.id);
          REQUIRE(e);
          CHECK(std::fabs(r.x - e->position.x) <= r.tolerance_x);
          CHECK(std::fabs(r.y - e->position.y) <= r.tolerance_y);
        }
        // The selection: the tracker's visible set after the tick, and its latest events.
        const auto& f = *selection;
        CHECK(at<std::uint32_t>(f, 8) == chosen);
        CHECK(f[1] == 1);
        CHECK(at<float>(f, 12) == store.get(chosen)->position.x);
        const auto visible = tr.visible(row);
        REQUIRE(at<std::uint32_t>(f, 56) == visible.size());
        for (std::size_t k = 0; k < visible.size(); ++k) CHECK(at<std::uint32_t>(f, 64 + 4 * k) == visible[k]);
        const std::size_t n_events = at<std::uint32_t>(f, 60);
        REQUIRE(n_events <= events.size());
        const std::size_t at_events = 64 + 5 * visible.size();
        REQUIRE(f.size() == at_events + 9 * n_events);
        // The server watches from the step after it took the selection: its events are the tail of ours.
        for (std::size_t k = 0; k < n_events; ++k) {
          const std::size_t o = at_events + 9 * k;
          CHECK(event{at<std::uint32_t>(f, o), at<std::uint32_t>(f, o + 4), f[o + 8] == 1} ==
                events[events.size() - n_events + k]);
        }
        events_checked += n_events;
      }
      last_tick = server.world().tick();
      CHECK(checked >= 20);
      CHECK(events_checked > 0);
      // Filled in the wait exactly when replication ran on an engine (the GPU); else after replicate().
      const std::uint64_t in_wait = server.stats().viewer_snapshots_in_wait - in_wait0;
      MESSAGE("replication on " << server.replication_name() << ": " << in_wait << " of " << due_ticks
                                << " snapshots filled in the engine's wait");
      // The columns (positions, ids, classes, kinds) copied while the GPU interest engine's device
      // worked, on every due tick (a single zone); never on the host.
      const std::uint64_t columns = server.stats().viewer_columns_in_interest_wait - columns0;
      MESSAGE("interest on " << server.interest_name() << ": " << columns << " of " << due_ticks
                             << " snapshots' columns copied in the interest engine's wait");
      // After the tick, on the copier's thread, every due tick's instead.
      const std::uint64_t after = server.stats().viewer_columns_after_tick - after0;
      if (fill == "after") {
        CHECK(columns == 0);
        CHECK(after == due_ticks);
      } else if (server.interest_name().find("engine") == std::string::npos) {
        CHECK(columns == 0);
        CHECK(after == 0);
      } else {
        CHECK(columns == due_ticks);
        CHECK(after == 0);
      }
      if (server.replication_name() == "cpu") {
        CHECK(in_wait == 0);
      } else {
        // Every due tick with a client's frame to build (all of them, unless every client's backlog
        // was full on one: a tick without requests fills it after).
        CHECK(in_wait <= due_ticks);
        CHECK(in_wait * 10 >= due_ticks * 9);
      }
    }  // the tick CSV is complete once the server is gone
    // --tick-csv's viewer_fill_ms: the snapshot's fill on the tick's threads, wherever it ran: on
    // the due ticks only (every third), and there (the columns and a selection) more than nothing.
    std::ifstream in(csv_path);
    REQUIRE(in.good());
    std::string line;
    REQUIRE(std::getline(in, line));
    REQUIRE(line.find(",viewer_ms,viewer_fill_ms,interest_wait_ms") != std::string::npos);
    std::size_t rows = 0, filled = 0, stray = 0;
    while (std::getline(in, line)) {
      std::vector<double> v;
      std::istringstream row(line);
      for (std::string cell; std::getline(row, cell, ',');) v.push_back(std::stod(cell));
      REQUIRE(v.size() == 18);  // the columns of --tick-csv (docs/operating.md)
      const auto tick = static_cast<std::uint64_t>(v[0]);
      if (tick < first_tick || tick > last_tick) continue;
      ++rows;
      if (tick % 3 == 0) {
        filled += v[12] > 0 ? 1 : 0;
      } else {
        stray += v[12] != 0 ? 1 : 0;
      }
    }
    CHECK(rows == last_tick - first_tick + 1);
    CHECK(filled == (last_tick / 3 - (first_tick - 1) / 3));
    CHECK(stray == 0);
    std::remove(csv_path.c_str());
  }
}
