// Teleport jumps: the world's checks (players only, finite targets, clamped into the world) and the
// zone server in-process on loopback, ticked by the test (no timing): a client's own jump applied
// with interest right the same tick and its own position in the tick update; hostile requests
// (another's entity, an NPC, NaN, out of the world, a flood, the cooldown, teleports off) refused
// or clamped, while every frame of every client stays consistent with its digest.
#include <doctest/doctest.h>

#include <cmath>
#include <limits>
#include <thread>

#include "../common/loopback_zone.h"
#include "../net/loopback_client.h"
#include "zone/zone_server.h"

using namespace zone;
using zone::net::testing::test_client;
using namespace std::chrono_literals;

namespace {

zone_config teleport_config() {
  zone_config c = zone::test::loopback_zone_config();
  c.npc_count = 300;
  c.town_count = 1;
  c.worker_threads = 1;
  c.io_threads = 1;
  c.player_aoi = 60;
  c.client_byte_budget = 64 * 1024;  // ample: every enter and leave goes out the tick it happens
  c.teleport_cooldown_s = 0.5;       // 15 ticks
  c.teleport_enabled = true;         // a server-granted ability, off by default
  c.metrics_enabled = false;
  return c;
}

/// One client of the test, with the view built from what it was sent.
struct player {
  std::unique_ptr<test_client> conn;
  entity_id id = null_entity;
  net::vec3f spawn{};
  std::optional<net::client_view> view;
  std::optional<net::tick_update_msg> last;
  std::uint64_t problems = 0;
};

/// Ticks the server itself (the test is the tick loop) and keeps every player's view current.
struct harness {
  zone_server& server;
  std::vector<player*> players;

  /// Reads every player's frames up to the world's current tick, applying and checking each.
  void catch_up() {
    for (player* p : players) {
      if (!p->view) continue;
      while (p->view->last_tick() < server.world().tick()) {
        const auto m = p->conn->read(3000ms);
        REQUIRE(m.has_value());
        if (!std::holds_alternative<net::tick_update_msg>(*m)) continue;
        const auto& u = std::get<net::tick_update_msg>(*m);
        if (p->view->apply(u) != net::client_view::status::ok) ++p->problems;
        p->last = u;
      }
    }
  }
  /// Waits until the I/O threads have written every frame built so far (each client's welcome
  /// and its tick updates; this test sends no pings), as they do within a tick period of a real
  /// tick loop. A tick that found two of a client's frames unwritten (the pacing default,
  /// client_max_backlog 2; a loaded host starves the I/O threads for that long) would build that
  /// client no frame, and catch_up() would wait in vain for the frame of the last tick.
  void settle() {
    const auto deadline = std::chrono::steady_clock::now() + 5s;
    while (server.net_stats().frames_out < server.stats().frames_sent + server.stats().clients) {
      REQUIRE_MESSAGE(std::chrono::steady_clock::now() < deadline, "the I/O threads did not write every frame built within 5 s");
      std::this_thread::sleep_for(1ms);
    }
  }
  /// Ticks n times, reading every frame after each tick, as a client of a real tick loop would
  /// (ticks 33 ms apart). Ticking many times without reading could fill a session's queue before
  /// its I/O thread has written anything; the frames after such a drop wait for the next tick's
  /// reset (docs/protocol.md), which catch_up() would wait for in vain.
  void tick(int n = 1) {
    for (int i = 0; i < n; ++i) {
      settle();
      server.tick_once();
      catch_up();
    }
  }
  /// Ticks until pred() holds (the network threads deliver messages asynchronously).
  template <class Pred>
  bool tick_until(Pred pred) {
    const auto deadline = std::chrono::steady_clock::now() + 5s;
    while (!pred()) {
      if (std::chrono::steady_clock::now() > deadline) return false;
      std::this_thread::sleep_for(2ms);
      tick();
    }
    return true;
  }
  void join(player& p, const std::string& name) {
    p.conn = std::make_unique<test_client>(server.port());
    REQUIRE(p.conn->send(net::hello_msg{name, "", net::protocol_version}));
    std::optional<net::message> w;
    const auto deadline = std::chrono::steady_clock::now() + 5s;
    while (!w && std::chrono::steady_clock::now() < deadline) {
      settle();  // the players already here get every tick's frame meanwhile
      server.tick_once();
      w = p.conn->read(10ms);
    }
    REQUIRE(w.has_value());
    REQUIRE(std::holds_alternative<net::welcome_msg>(*w));
    const auto& welcome = std::get<net::welcome_msg>(*w);
    p.id = welcome.entity_id;
    REQUIRE(welcome.spawn_position.has_value());
    p.spawn = *welcome.spawn_position;
    CHECK(welcome.host_clock);
    p.view.emplace(welcome.world);
    // Its frames start with the tick that handled the hello; the first one resets the view.
    players.push_back(&p);
    catch_up();
  }
};

vec3 position_of(const zone_server& s, entity_id id) {
  const auto d = s.world().store().get(id);
  REQUIRE(d.has_value());
  return d->position;
}

/// Does `observer` (a player at `at`) see everything whose presence meets its exact AOI box and
/// nothing beyond its AOI grown by the hysteresis? (Interest right at the new position.)
void check_interest_at(const zone_server& s, entity_id observer, const vec3& at) {
  const auto& store = s.world().store();
  const auto& tracker = s.world().tracker();
  const std::size_t row = tracker.row_of(observer);
  REQUIRE(row != entity_store::npos);
  const auto visible = tracker.visible(row);
  const auto aoi = s.world().config().player_aoi, h = s.world().config().hysteresis;
  const auto meets = [&](std::size_t k, float grow) {
    const vec3 p = store.positions()[k], half = store.presence_half_extents()[k];
    return std::fabs(p.x - at.x) <= aoi + grow + half.x && std::fabs(p.y - at.y) <= aoi + grow + half.y &&
           std::fabs(p.z - at.z) <= aoi + grow + half.z;
  };
  const auto obs = store.get(observer);
  for (std::size_t k = 0; k < store.size(); ++k) {
    const entity_id id = store.ids()[k];
    if (id == observer || (store.visibility_classes()[k] & obs->sees) == 0) continue;
    const bool in = std::binary_search(visible.begin(), visible.end(), id);
    // 1 cm either side of the boundaries, for the tracker's float rounding of the boxes.
    if (meets(k, -0.01f)) CHECK_MESSAGE(in, "entity " << id << " is inside the AOI but not visible");
    if (!meets(k, h + 0.01f)) CHECK_MESSAGE(!in, "entity " << id << " is beyond the AOI and its margin but visible");
  }
}

}  // namespace

TEST_SUITE("zone.teleport") {
  TEST_CASE("zone_world::teleport: players only, finite targets, clamped into the world") {
    zone_config cfg = teleport_config();
    interest::grid_finder finder(nullptr);
    zone_world world(cfg, finder, nullptr);
    world.populate();
    const entity_id p = world.spawn_player({100, 100, 0});
    REQUIRE(p != null_entity);
    bool clamped = true;
    CHECK(world.teleport(p, {300, 250, 5}, &clamped));
    CHECK_FALSE(clamped);
    CHECK(world.store().get(p)->position == vec3{300, 250, 5});
    CHECK(world.teleport(p, {-1e30f, 1e9f, 55}, &clamped));
    CHECK(clamped);
    CHECK(world.store().get(p)->position == vec3{0, 600, 40});
    const float nan = std::numeric_limits<float>::quiet_NaN(), inf = std::numeric_limits<float>::infinity();
    CHECK_FALSE(world.teleport(p, {nan, 1, 1}));
    CHECK_FALSE(world.teleport(p, {1, inf, 1}));
    CHECK_FALSE(world.teleport(p, {1, 1, -inf}));
    CHECK(world.store().get(p)->position == vec3{0, 600, 40});
    // An NPC never teleports; nor does a dead or null handle.
    const entity_id npc = world.store().ids()[0];
    REQUIRE(world.behaviour_of(npc) != behaviour::player);
    const vec3 npc_at = world.store().get(npc)->position;
    CHECK_FALSE(world.teleport(npc, {1, 1, 0}));
    CHECK(world.store().get(npc)->position == npc_at);
    CHECK_FALSE(world.teleport(null_entity, {1, 1, 0}));
    REQUIRE(world.despawn(p));
    CHECK_FALSE(world.teleport(p, {1, 1, 0}));
    // The step after a jump finds interest at the new place.
    const entity_id q = world.spawn_player({10, 10, 0});
    REQUIRE(!world.step().has_value());
    CHECK(world.teleport(q, {590, 590, 0}));
    REQUIRE(!world.step().has_value());
    const auto row = world.tracker().row_of(q);
    REQUIRE(row != entity_store::npos);
    for (const entity_id seen : world.tracker().visible(row)) {
      const vec3 at = world.store().get(seen)->position;
      CHECK(std::fabs(at.x - 590) <= cfg.player_aoi + cfg.hysteresis + 40);
      CHECK(std::fabs(at.y - 590) <= cfg.player_aoi + cfg.hysteresis + 40);
    }
  }

  TEST_CASE("a client's teleport: applied, interest right the same tick; hostile requests refused or clamped") {
    zone_server server(teleport_config());
    REQUIRE_FALSE(server.start().has_value());
    harness h{server, {}};
    player a, b;
    h.join(a, "alice");
    h.join(b, "bob");
    REQUIRE(a.id != b.id);
    h.tick(3);
    // Both spawned at the town and stand still (no inputs): where the welcome said.
    CHECK(position_of(server, b.id) == vec3{b.spawn.x, b.spawn.y, b.spawn.z});
    REQUIRE(a.last.has_value());
    REQUIRE(a.last->self_position.has_value());
    CHECK(*a.last->self_position == a.spawn);

    // 1. Alice jumps across the world (entity id 0 = her own).
    const vec3 target{520, 80, 0};
    REQUIRE(a.conn->send(net::teleport_msg{1, {target.x, target.y, target.z}, 0}));
    REQUIRE(h.tick_until([&] { return server.stats().teleports == 1; }));
    const std::uint64_t jump_tick = server.world().tick();
    CHECK(position_of(server, a.id) == target);
    check_interest_at(server, a.id, target);
    // Her frame of that tick says where she is, and her view (digest-checked) followed the jump:
    // whatever it holds now lies around the new place.
    REQUIRE(a.last.has_value());
    CHECK(a.last->server_tick == jump_tick);
    REQUIRE(a.last->self_position.has_value());
    CHECK(*a.last->self_position == net::vec3f{target.x, target.y, target.z});
    for (const auto& [id, e] : a.view->entities()) {
      CHECK(std::fabs(e.state.position.x - target.x) <= 60 + 4 + 40 + 1);
      CHECK(std::fabs(e.state.position.y - target.y) <= 60 + 4 + 40 + 1);
    }
    CHECK(a.last->last_input_sequence == 1);

    // 2. Hostile requests: another player's entity, an NPC, NaN, and a second jump within the cooldown.
    const entity_id npc = server.world().store().ids()[0];
    REQUIRE(server.world().behaviour_of(npc) != behaviour::player);
    const vec3 npc_before = position_of(server, npc);
    const std::uint64_t npc_tick = server.world().tick();
    const float nan = std::numeric_limits<float>::quiet_NaN();
    REQUIRE(a.conn->send(net::teleport_msg{2, {10, 10, 0}, b.id}));
    REQUIRE(a.conn->send(net::teleport_msg{3, {10, 10, 0}, npc}));
    REQUIRE(a.conn->send(net::teleport_msg{4, {nan, 10, 0}, 0}));
    REQUIRE(a.conn->send(net::teleport_msg{5, {10, 10, 0}, 0}));  // cooldown: 15 ticks
    REQUIRE(h.tick_until([&] { return server.stats().teleports_refused == 4; }));
    CHECK(server.stats().teleports == 1);
    CHECK(position_of(server, a.id) == target);
    CHECK(position_of(server, b.id) == vec3{b.spawn.x, b.spawn.y, b.spawn.z});
    // The NPC moves by its behaviour only (at most 1.5 x the NPC speed), never a jump to (10, 10).
    const vec3 npc_after = position_of(server, npc);
    const float npc_reach =
        1.5f * server.world().config().npc_speed * static_cast<float>(server.world().tick() - npc_tick) / 30.0f + 0.01f;
    CHECK(std::fabs(npc_after.x - npc_before.x) <= npc_reach);
    CHECK(std::fabs(npc_after.y - npc_before.y) <= npc_reach);

    // 3. After the cooldown, a target far outside the world is clamped into it.
    h.tick(16);
    REQUIRE(a.conn->send(net::teleport_msg{6, {1e9f, -5, 1e30f}, a.id}));
    REQUIRE(h.tick_until([&] { return server.stats().teleports == 2; }));
    CHECK(server.stats().teleports_clamped == 1);
    CHECK(position_of(server, a.id) == vec3{600, 0, 40});
    check_interest_at(server, a.id, {600, 0, 40});

    // 4. A flood of 40 jumps: the network's input rate drops what exceeds the burst, the
    // cooldown refuses the rest but one.
    h.tick(16);
    const auto st0 = server.stats();
    const auto dropped0 = server.net_stats().inputs_dropped;
    for (std::uint32_t k = 0; k < 40; ++k) {
      REQUIRE(a.conn->send(net::teleport_msg{100 + k, {static_cast<float>(10 * k), 300, 0}, 0}));
    }
    REQUIRE(h.tick_until([&] {
      const auto st = server.stats();
      return (st.teleports - st0.teleports) + (st.teleports_refused - st0.teleports_refused) +
                 (server.net_stats().inputs_dropped - dropped0) ==
             40;
    }));
    CHECK(server.stats().teleports - st0.teleports == 1);
    CHECK(position_of(server, a.id) == vec3{0, 300, 0});  // the first of the flood

    // Every frame of both clients was consistent and matched its digest; the server still serves.
    h.tick(5);
    CHECK(a.problems == 0);
    CHECK(b.problems == 0);
    CHECK(a.view->problems() == 0);
    CHECK(b.view->problems() == 0);
    CHECK(a.view->digests_checked() > 30);
    CHECK(server.stats().clients == 2);
    CHECK(server.net_stats().sessions_open == 2);
  }

  TEST_CASE("teleports off: every request is refused") {
    zone_config cfg = teleport_config();
    cfg.teleport_enabled = false;
    zone_server server(cfg);
    REQUIRE_FALSE(server.start().has_value());
    harness h{server, {}};
    player a;
    h.join(a, "alice");
    REQUIRE(a.conn->send(net::teleport_msg{1, {300, 300, 0}, 0}));
    REQUIRE(h.tick_until([&] { return server.stats().teleports_refused == 1; }));
    CHECK(server.stats().teleports == 0);
    CHECK(position_of(server, a.id) == vec3{a.spawn.x, a.spawn.y, a.spawn.z});
  }
}
