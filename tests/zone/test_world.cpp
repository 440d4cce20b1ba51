// Configuration parsing and the world step: determinism across thread counts and finders, bounds,
// the player speed limit, chasing, phase histograms.
#include <doctest/doctest.h>

#include "../common/seeds.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <limits>
#include <random>
#include <set>
#include <string>

#include "net/os_limits.h"
#include "world_script.h"
#include "zone/zone.h"

using namespace zone;

namespace {

using zone::test::fresh_seed;
using zone::test::run_digests;
using zone::test::small_config;

config_result parse(std::vector<std::string> args) {
  args.insert(args.begin(), "zone-server");
  std::vector<const char*> argv;
  for (const auto& a : args) argv.push_back(a.c_str());
  return parse_config(static_cast<int>(argv.size()), argv.data());
}

/// The first entity of `w` with behaviour `b`, or null_entity.
entity_id first_with(const zone_world& w, behaviour b) {
  for (const auto id : w.store().ids()) {
    if (w.behaviour_of(id) == b) return id;
  }
  return null_entity;
}

}  // namespace

TEST_SUITE("zone.config") {
  TEST_CASE("defaults need no file; --help; errors name the option; file values, command line wins") {
    const auto d = parse({});
    REQUIRE(d.config.has_value());
    CHECK(d.config->tick_rate_hz == 30);
    CHECK_FALSE(validate(*d.config).has_value());

    const auto h = parse({"--help"});
    CHECK(h.help);
    CHECK_FALSE(h.config.has_value());
    CHECK(h.message.find("--tick-rate") != std::string::npos);
    CHECK(h.message.find("--hysteresis") != std::string::npos);
    // Hardening defaults (docs/operating.md, Limits and hardening): teleports are granted, /metrics is
    // on loopback, and the admission and rate limits are options.
    CHECK_FALSE(d.config->teleport_enabled);
    CHECK_FALSE(d.config->player_fly);
    CHECK(d.config->metrics_address == "127.0.0.1");
    for (const char* o : {"--hello-timeout", "--max-pending", "--max-pending-per-address", "--pings-per-second",
                          "--max-name-bytes", "--metrics-address", "--metrics-max-connections", "--log-summary",
                          "--connect-rate", "--connect-burst", "--connect-min-session", "--connect-refusal-hold"}) {
      CAPTURE(o);
      CHECK(h.message.find(o) != std::string::npos);
    }
    CHECK_FALSE(parse({"--hello-timeout", "0"}).config.has_value());
    CHECK_FALSE(parse({"--max-pending", "0"}).config.has_value());
    CHECK_FALSE(parse({"--pings-per-second", "-1"}).config.has_value());
    CHECK_FALSE(parse({"--connect-rate", "-1"}).config.has_value());
    CHECK_FALSE(parse({"--connect-burst", "0.5"}).config.has_value());
    CHECK_FALSE(parse({"--connect-min-session", "-2"}).config.has_value());
    CHECK_FALSE(parse({"--connect-refusal-hold", "61"}).config.has_value());
    // A world of zones' NATS timing (docs/world.md): defaults, and bounds.
    CHECK(d.config->world_lease_ttl_s == 3);
    CHECK(d.config->world_nats_timeout_s == 2);
    CHECK(h.message.find("--world-lease-ttl") != std::string::npos);
    CHECK(h.message.find("--world-nats-timeout") != std::string::npos);
    CHECK_FALSE(parse({"--world-lease-ttl", "0.1"}).config.has_value());
    CHECK_FALSE(parse({"--world-nats-timeout", "0"}).config.has_value());
    REQUIRE(parse({"--world-lease-ttl", "10", "--world-nats-timeout", "0.5"}).config.has_value());
    CHECK(parse({"--world-lease-ttl", "10"}).config->world_lease_ttl_s == 10);
    // A standby needs a world to stand by for.
    CHECK(h.message.find("--world-standby") != std::string::npos);
    const auto lone = parse({"--world-standby"});
    CHECK_FALSE(lone.config.has_value());
    CHECK(lone.message.find("--world-standby needs --world") != std::string::npos);
    CHECK_FALSE(parse({}).config->world_standby);
    CHECK(parse({"--world", "w", "--nats", "nats://127.0.0.1:4222", "--world-standby"}).config->world_standby);
    CHECK(d.config->oracle_subscribers == 4);
    CHECK_FALSE(parse({"--oracle-subscribers", "0"}).config.has_value());
    CHECK_FALSE(parse({"--oracle-subscribers", "65"}).config.has_value());
    REQUIRE(parse({"--oracle-subscribers", "9"}).config.has_value());
    CHECK(parse({"--oracle-subscribers", "9"}).config->oracle_subscribers == 9);
    CHECK(d.config->connect_rate == 20);
    CHECK(d.config->connect_burst == 64);
    CHECK(d.config->connect_min_session_s == 10);
    REQUIRE(parse({"--connect-rate", "0"}).config.has_value());  // 0: no limit
    const auto limits = parse({"--hello-timeout", "1.5", "--max-pending-per-address", "4", "--teleport", "1"});
    REQUIRE(limits.config.has_value());
    CHECK(limits.config->hello_timeout_s == 1.5);
    CHECK(limits.config->max_pending_per_address == 4);
    CHECK(limits.config->teleport_enabled);

    const auto bad = parse({"--tick-rate", "fast"});
    CHECK_FALSE(bad.config.has_value());
    CHECK(bad.message.find("tick-rate") != std::string::npos);
    CHECK_FALSE(parse({"--no-such-option"}).config.has_value());
    const auto neg = parse({"--tick-rate", "-5"});
    CHECK_FALSE(neg.config.has_value());
    CHECK(neg.message.find("tick-rate") != std::string::npos);
    CHECK_FALSE(parse({"--port", "70000"}).config.has_value());
    CHECK(d.config->finder == "auto");
    for (const char* f : {"auto", "cpu", "gpu", "pbig", "lbvh", "brute"}) {
      const auto r = parse({"--finder", f});
      REQUIRE(r.config.has_value());
      CHECK(r.config->finder == f);
    }
    CHECK(d.config->replicate == "auto");
    for (const char* r : {"auto", "gpu", "cpu"}) {
      const auto parsed = parse({"--replicate", r});
      REQUIRE(parsed.config.has_value());
      CHECK(parsed.config->replicate == r);
    }
    const auto bad_replicate = parse({"--replicate", "fpga"});
    CHECK_FALSE(bad_replicate.config.has_value());
    CHECK(bad_replicate.message.find("replicate") != std::string::npos);
    CHECK(d.config->host_grid == "auto");
    for (const char* g : {"auto", "on", "off"}) {
      const auto parsed = parse({"--host-grid", g});
      REQUIRE(parsed.config.has_value());
      CHECK(parsed.config->host_grid == g);
    }
    const auto bad_grid = parse({"--host-grid", "maybe"});
    CHECK_FALSE(bad_grid.config.has_value());
    CHECK(bad_grid.message.find("host-grid") != std::string::npos);
    const auto bad_finder = parse({"--finder", "quantum"});
    CHECK_FALSE(bad_finder.config.has_value());
    CHECK(bad_finder.message.find("finder") != std::string::npos);

    CHECK(d.config->client_send_every == 1);
    const auto every3 = parse({"--client-send-every", "3"});
    REQUIRE(every3.config.has_value());
    CHECK(every3.config->client_send_every == 3);
    const auto every0 = parse({"--client-send-every", "0"});
    CHECK_FALSE(every0.config.has_value());
    CHECK(every0.message.find("client-send-every") != std::string::npos);
    // Staggered clients with a digest every K > 1 ticks: some clients would never get one.
    const auto staggered = parse({"--client-send-every", "2", "--digest-every", "3"});
    CHECK_FALSE(staggered.config.has_value());
    CHECK(staggered.message.find("digest-every") != std::string::npos);
    CHECK(parse({"--client-send-every", "2", "--digest-every", "0"}).config.has_value());

    // The most entities one zone holds: NPCs + bosses up to max_entities (2^22) pass, one more
    // is refused with the limit named.
    zone_config big = *d.config;
    big.npc_count = 2'000'000;
    CHECK_FALSE(validate(big).has_value());
    big.npc_count = max_entities - big.boss_count;
    CHECK_FALSE(validate(big).has_value());
    big.npc_count += 1;
    const auto over = validate(big);
    REQUIRE(over.has_value());
    CHECK(over->find(std::to_string(max_entities)) != std::string::npos);
    big.npc_count = static_cast<std::size_t>(-1);  // no wrap-around in the sum
    CHECK(validate(big).has_value());

    // CPU lists (--worker-cpus, --io-cpus): empty or CPUs this process may use pass; a bad list
    // or a CPU outside the process's set is refused, naming the option.
    const std::vector<int> allowed = zone::net::allowed_cpus();
    REQUIRE_FALSE(allowed.empty());
    const std::string one = std::to_string(allowed.front());
    CHECK(parse({"--worker-cpus", one, "--io-cpus", zone::net::format_cpu_list(allowed)}).config.has_value());
    for (const char* option : {"--worker-cpus", "--io-cpus"}) {
      CAPTURE(option);
      for (const std::string bad : {"a", "0-", "1,", "3-1"}) {
        const auto r = parse({option, bad});
        CHECK_FALSE(r.config.has_value());
        CHECK(r.message.find(option + 2) != std::string::npos);
      }
      if (allowed.back() != CPU_SETSIZE - 1) {
        const auto r = parse({option, std::to_string(CPU_SETSIZE - 1)});
        CHECK_FALSE(r.config.has_value());
        CHECK(r.message.find("may not run on") != std::string::npos);
      }
    }

    const std::string path = "zone_config_test_" + std::to_string(fresh_seed()) + ".ini";
    {
      std::ofstream f(path);
      f << "# a zone\nnpcs = 123\nhysteresis = 7.5\nworld-x = 2000\nport = 4000\n";
    }
    const auto fromfile = parse({"--config", path, "--port", "5000"});
    std::remove(path.c_str());
    REQUIRE(fromfile.config.has_value());
    CHECK(fromfile.config->npc_count == 123);
    CHECK(fromfile.config->hysteresis == 7.5f);
    CHECK(fromfile.config->world.hi.x == 2000.f);
    CHECK(fromfile.config->port == 5000);
    CHECK_FALSE(parse({"--config", "/nonexistent/zone.ini"}).config.has_value());
  }

  TEST_CASE("the shipped sample config/zone-server.ini loads, validates and is what it says") {
    const std::string path = std::string(ZONE_SOURCE_DIR) + "/config/zone-server.ini";
    // Every name in the file is an option of --help: an unknown one fails the parse.
    const auto sample = parse({"--config", path});
    INFO(sample.message);
    REQUIRE(sample.config.has_value());
    CHECK_FALSE(validate(*sample.config).has_value());
    // The values the sample sets apart from the defaults were read.
    CHECK(sample.config->npc_count == 10000);
    CHECK(sample.config->tick_rate_hz == 20);
    CHECK(sample.config->listen_address == "127.0.0.1");
    CHECK(sample.config->max_clients == 1100);
    // The command line wins over the file.
    const auto over = parse({"--config", path, "--npcs", "500", "--tick-rate", "30"});
    REQUIRE(over.config.has_value());
    CHECK(over.config->npc_count == 500);
    CHECK(over.config->tick_rate_hz == 30);
    // The file holds no option twice (the parser would take the first; the reader would not see it).
    std::ifstream in(path);
    REQUIRE(in);
    std::set<std::string> names;
    for (std::string line; std::getline(in, line);) {
      const auto first = line.find_first_not_of(" \t");
      if (first == std::string::npos || line[first] == '#') continue;
      const auto eq = line.find('=');
      REQUIRE(eq != std::string::npos);
      std::string name = line.substr(first, eq - first);
      name.erase(name.find_last_not_of(" \t") + 1);
      CAPTURE(name);
      CHECK(names.insert(name).second);
    }
    CHECK(names.size() >= 20);
  }
}

TEST_SUITE("zone.world") {
  TEST_CASE("determinism: same seed and inputs, same per-tick hash with 1 and several threads and any finder") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    const zone_config cfg = small_config(seed);
    interest::thread_pool one(1), three(3);
    interest::grid_finder grid_one(&one), grid_three(&three);
    interest::brute_force_finder brute(&three);
    const auto reference = run_digests(cfg, grid_one, &one, 40);
    // Everything stands on the ground, so the grid finder leaves z unsplit (its flat-grid plan):
    // that is the plan compared with brute force here.
    CHECK(grid_one.last_plan().dims[2] == 1);
    CHECK(grid_one.last_plan().dims[0] > 1);
    CHECK(run_digests(cfg, grid_three, &three, 40) == reference);
    CHECK(run_digests(cfg, brute, &three, 40) == reference);
    CHECK(run_digests(cfg, grid_one, nullptr, 40) == reference);
    // The host path's candidates on the presence grid instead of the finder's pairs.
    CHECK(run_digests(cfg, brute, &three, 40, 8, false, nullptr, true) == reference);
    CHECK(run_digests(cfg, grid_one, nullptr, 40, 8, false, nullptr, true) == reference);
    zone_config other = cfg;
    other.seed = seed + 1;
    CHECK(run_digests(other, grid_one, &one, 40) != reference);
  }

  TEST_CASE("everything stays inside the world; players never exceed their speed; NPCs chase players") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    zone_config cfg = small_config(seed);
    cfg.share_wander = cfg.share_patrol = cfg.share_town = 1;
    cfg.share_chase = 1;
    interest::thread_pool pool(2);
    interest::grid_finder finder(&pool);
    zone_world w(cfg, finder, &pool);
    w.populate();
    CHECK(w.store().size() == cfg.npc_count + cfg.boss_count);
    const entity_id player = w.spawn_player({400, 400, 0});
    REQUIRE(player != null_entity);
    CHECK(w.behaviour_of(player) == behaviour::player);
    // A chaser next to the player.
    const entity_id chaser = first_with(w, behaviour::chase);
    REQUIRE(chaser != null_entity);
    CHECK_FALSE(w.set_intent(chaser, {1, 0, 0}));  // a client can only steer a player
    REQUIRE(w.store().set_position(chaser, {450, 400, 0}));
    REQUIRE(w.set_intent(player, {100, 0, 0}));  // clamped to length 1
    const float max_step = cfg.player_speed / static_cast<float>(cfg.tick_rate_hz);
    float chaser_distance_start = 0, chaser_distance_end = 0;
    for (int t = 0; t < 30; ++t) {
      const vec3 before = w.store().get(player)->position;
      if (t == 5) REQUIRE(w.set_intent(player, {0, 0, 0}));  // the player stops; the chaser comes
      REQUIRE_FALSE(w.step().has_value());
      const vec3 after = w.store().get(player)->position;
      const float moved = std::hypot(after.x - before.x, after.y - before.y, after.z - before.z);
      CHECK(moved <= max_step * 1.0001f);
      const vec3 c = w.store().get(chaser)->position;
      const float d = std::hypot(c.x - after.x, c.y - after.y);
      if (t == 0) chaser_distance_start = d;
      chaser_distance_end = d;
      const auto& wb = cfg.world;
      for (const auto& p : w.store().positions()) {
        CHECK((p.x >= wb.lo.x && p.x <= wb.hi.x && p.y >= wb.lo.y && p.y <= wb.hi.y && p.z >= wb.lo.z && p.z <= wb.hi.z));
      }
    }
    CHECK(chaser_distance_start > 10);
    CHECK(chaser_distance_end < 1);  // caught up and stays with the (now still) player
    // Phase histograms saw every tick.
    CHECK(w.phases().total.count() == 30);
    CHECK(w.phases().interest.count() == 30);
    CHECK(w.phases().total.percentile(0.99) <= w.phases().total.max());
    CHECK(w.phases().total.percentile(0.5) > 0);
  }

  TEST_CASE(
      "a wanderer keeps one heading a wander period and takes a new one each period; a new entity in a freed slot takes its own") {
    // The heading is computed once a period and kept by slot for its entity (zone_world::decide):
    // what a stale or misfiled one would break. Velocities are compared by their components'
    // magnitudes (a bounce off the world's edge flips a sign).
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    zone_config cfg = small_config(seed);
    cfg.share_wander = 1;
    cfg.share_patrol = cfg.share_town = cfg.share_chase = 0;
    interest::thread_pool pool(2);
    interest::grid_finder finder(&pool);
    // Freed slots reused at once (the default waits for 1,024 other frees), so the new wanderer
    // lands in the old one's slot and its behaviour state's place.
    zone_world w(cfg, {.finder = &finder, .pool = &pool, .slot_reuse_after = 0});
    w.populate();
    const auto speed_of = [&](entity_id id) {
      const vec3 v = w.store().get(id)->velocity;
      return vec3{std::fabs(v.x), std::fabs(v.y), std::fabs(v.z)};
    };
    std::vector<entity_id> wanderers;
    for (const entity_id id : w.store().ids()) {
      if (w.behaviour_of(id) == behaviour::wander) wanderers.push_back(id);
    }
    REQUIRE(wanderers.size() >= 500);
    std::vector<vec3> last(wanderers.size());
    std::vector<std::size_t> changes_at;  // ticks at which headings changed: how many changed
    entity_id replaced = null_entity, replacement = null_entity;
    vec3 replaced_speed{};
    constexpr int ticks = 200;  // wander periods are 90 ticks: two changes
    for (int t = 0; t < ticks; ++t) {
      if (t == 45) {
        // Mid-period: a wanderer goes and a new one comes into its slot.
        replaced = wanderers.back();
        replaced_speed = speed_of(replaced);
        const entity_desc d = *w.store().get(replaced);
        const behaviour_state b = *w.behaviour_state_of(replaced);
        REQUIRE(w.despawn(replaced));
        replacement = w.adopt(d, b);
        REQUIRE(replacement != null_entity);
        REQUIRE(slot_of(replacement) == slot_of(replaced));
        REQUIRE(replacement != replaced);
        wanderers.pop_back();
        last.pop_back();
      }
      REQUIRE_FALSE(w.step().has_value());
      if (t == 45) CHECK_FALSE(speed_of(replacement) == replaced_speed);
      std::size_t changed = 0;
      for (std::size_t k = 0; k < wanderers.size(); ++k) {
        const vec3 v = speed_of(wanderers[k]);
        CHECK(std::hypot(v.x, v.y) == doctest::Approx(cfg.npc_speed).epsilon(1e-5));
        if (t > 0 && !(v == last[k])) ++changed;
        last[k] = v;
      }
      if (changed > 0) changes_at.push_back(changed);
    }
    // Two period boundaries, where (nearly) every wanderer turned; no turn between them.
    REQUIRE(changes_at.size() == 2);
    for (const std::size_t n : changes_at) CHECK(n >= wanderers.size() * 9 / 10);
  }

  TEST_CASE("players spawn near their town, deterministically, and never outside the spawn area (a world zone's region)") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    interest::thread_pool pool(1);
    interest::grid_finder finder(&pool);
    // The whole world: within spawn_radius of the key's town.
    zone_config open = small_config(seed);
    open.spawn_radius = 60;
    zone_world a(open, finder, &pool);
    float farthest = 0;
    for (std::uint64_t key = 0; key < 2000; ++key) {
      const vec3 p = a.player_spawn_point(key);
      const vec3 t = a.town(key % a.town_count());
      const float d = std::hypot(p.x - t.x, p.y - t.y);
      CHECK(d <= open.spawn_radius + 1e-3f);
      farthest = std::max(farthest, d);
      const vec3 again = a.player_spawn_point(key);
      CHECK((again.x == p.x && again.y == p.y && again.z == p.z));
    }
    CHECK(farthest > 0.8f * open.spawn_radius);  // spread over the disc, not piled on the town
    // A region of the world (what a world zone gets) narrower than the spawn disc: every point
    // inside the region, none on the neighbour's side of the border.
    zone_config region = small_config(seed);
    region.spawn_radius = 500;
    region.spawn_area = {{100, 200, 0}, {300, 260, 50}};
    zone_world b(region, finder, &pool);
    int on_border = 0;
    for (std::uint64_t key = 0; key < 2000; ++key) {
      const vec3 p = b.player_spawn_point(key);
      CAPTURE(key);
      CHECK(p.x >= 100);
      CHECK(p.x <= 300);
      CHECK(p.y >= 200);
      CHECK(p.y <= 260);
      on_border += (p.x == 100 || p.x == 300 || p.y == 200 || p.y == 260) ? 1 : 0;
    }
    CHECK(on_border > 0);  // the disc does reach past the region: the clamp is what holds it in
  }

  TEST_CASE("adopted entities (a world's ghosts, a handed-off player): chasers chase adopted players; players spawn after them") {
    // A world zone adopts entities between ticks (world/: ghosts, handoffs); the chasers' scan
    // reads is_player_ by slot, which must cover every adopted slot (it once grew with spawns
    // only, and a player spawned after adoptions wrote past its end).
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    zone_config cfg = small_config(seed);
    cfg.share_wander = cfg.share_patrol = cfg.share_town = 0;
    cfg.share_chase = 1;
    interest::grid_finder finder(nullptr);
    zone_world w(cfg, finder, nullptr);
    w.populate();
    // Ghosts of another zone's NPCs, far away: new slots past every populated one.
    for (int k = 0; k < 64; ++k) {
      entity_desc d;
      d.position = {10.0f + static_cast<float>(k), 10, 0};
      REQUIRE(w.adopt(d, behaviour_state{behaviour::ghost, d.position, 0, {}}) != null_entity);
    }
    // A player handed off to this zone (behaviour player, kind player), standing still.
    entity_desc pd;
    pd.position = {400, 400, 0};
    pd.kind = entity_kind::player;
    pd.aoi_half_extent = {cfg.player_aoi, cfg.player_aoi, cfg.player_aoi};
    const entity_id adopted = w.adopt(pd, behaviour_state{behaviour::player, pd.position, 0, {}});
    REQUIRE(adopted != null_entity);
    // A player who logs in here afterwards (its slot is past the adopted ones).
    const entity_id later = w.spawn_player({100, 100, 0});
    REQUIRE(later != null_entity);
    CHECK(w.behaviour_of(later) == behaviour::player);
    const entity_id chaser = first_with(w, behaviour::chase);
    REQUIRE(chaser != null_entity);
    REQUIRE(w.store().set_position(chaser, {440, 400, 0}));
    for (int t = 0; t < 40; ++t) REQUIRE_FALSE(w.step().has_value());
    const vec3 c = w.store().get(chaser)->position;
    CHECK(std::hypot(c.x - 400.0f, c.y - 400.0f) < 2);  // it came to the adopted player
  }

  TEST_CASE("input rules: any finite intent moves at most player_speed in its direction; walking is horizontal unless fly") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    for (const bool fly : {false, true}) {
      CAPTURE(fly);
      zone_config cfg = small_config(seed);
      cfg.npc_count = 0;
      cfg.boss_count = 0;
      cfg.player_fly = fly;
      interest::grid_finder finder(nullptr);
      zone_world w(cfg, finder, nullptr);
      w.populate();
      const vec3 start{400, 400, (cfg.world.lo.z + cfg.world.hi.z) / 2};
      const entity_id p = w.spawn_player(start);
      REQUIRE(p != null_entity);
      const float step = cfg.player_speed / static_cast<float>(cfg.tick_rate_hz);
      // {intent, expected unit direction of the horizontal move (or of the 3-D move when flying)}
      const float big = std::numeric_limits<float>::max();
      struct probe {
        vec3 intent;
        vec3 direction;  // unit, for the walking (z dropped) case
        vec3 fly_direction;
      };
      const float r2 = 1 / std::sqrt(2.0f), r3 = 1 / std::sqrt(3.0f);
      const probe probes[] = {
          {{1e30f, 1e30f, 0}, {r2, r2, 0}, {r2, r2, 0}},               // squares overflow: was a zero intent
          {{big, -big, big}, {r2, -r2, 0}, {r3, -r3, r3}},             // the largest finite floats
          {{-3e38f, 0, 0}, {-1, 0, 0}, {-1, 0, 0}},
          {{0, 0, 1e20f}, {0, 0, 0}, {0, 0, 1}},                      // upward: only when flying
          {{1e-30f, 0, 0}, {0, 0, 0}, {0, 0, 0}},                     // tiny: moves (almost) nothing
      };
      for (const auto& pr : probes) {
        CAPTURE(pr.intent.x);
        CAPTURE(pr.intent.z);
        REQUIRE(w.store().set_position(p, start));
        REQUIRE(w.set_intent(p, pr.intent));
        REQUIRE_FALSE(w.step().has_value());
        const vec3 at = w.store().get(p)->position;
        const vec3 d = fly ? pr.fly_direction : pr.direction;
        CHECK(at.x == doctest::Approx(start.x + d.x * step).epsilon(1e-4));
        CHECK(at.y == doctest::Approx(start.y + d.y * step).epsilon(1e-4));
        CHECK(at.z == doctest::Approx(start.z + d.z * step).epsilon(1e-4));
        const float moved = std::hypot(at.x - start.x, at.y - start.y, at.z - start.z);
        CHECK(moved <= step * 1.0001f);
      }
      const float nan = std::numeric_limits<float>::quiet_NaN(), inf = std::numeric_limits<float>::infinity();
      CHECK_FALSE(w.set_intent(p, {nan, 0, 0}));
      CHECK_FALSE(w.set_intent(p, {0, inf, 0}));
      CHECK_FALSE(w.set_intent(p, {0, 0, -inf}));
    }
  }

  TEST_CASE("latency histogram percentiles are within a bucket of the truth") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    std::mt19937_64 rng(seed);
    latency_histogram h;
    std::vector<double> v;
    std::lognormal_distribution<double> dist(0.0, 1.5);
    for (int i = 0; i < 10000; ++i) {
      v.push_back(dist(rng));
      h.record(v.back());
    }
    std::sort(v.begin(), v.end());
    for (const double q : {0.5, 0.9, 0.99}) {
      CAPTURE(q);
      const double truth = v[static_cast<std::size_t>(std::ceil(q * v.size())) - 1];
      CHECK(h.percentile(q) >= truth);
      CHECK(h.percentile(q) <= truth * std::exp2(0.25) * 1.0001);
    }
    CHECK(h.max() == v.back());
    CHECK(h.count() == 10000);
  }
}
