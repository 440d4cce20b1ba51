// world/nats_node against a real nats-server (started by the test on a free loopback port, stopped
// by pid), with in-process zones: regions claimed by CAS, handoffs over JetStream with every
// entity owned exactly once (the zones' census and the ownership records in KV agree), replays
// refused, a failed ownership CAS read back, a player's redirect, a stalled neighbour, a full
// zone, nats-server stopped and started again. A zone-server process killed with SIGKILL and restarted is
// test_world_script_kill's (scripts/world.sh --kill). Without nats-server it fails (configuring says so).
#include <doctest/doctest.h>

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <nats/nats.h>

#include <array>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <functional>
#include <future>
#include <limits>
#include <map>
#include <memory>
#include <random>
#include <regex>
#include <set>

#include "../common/process.h"
#include "../common/seeds.h"
#include "net/codec.h"
#include "world/gate.h"
#include "world/nats_node.h"

using namespace zone;
using namespace zone::world;
using zone::test::child_process;
using zone::test::read_file;
using zone::test::temp_dir;
using namespace std::chrono_literals;

namespace {

/// nats-server with JetStream on a free loopback port, in its own directory.
struct nats_server {
  std::string dir = temp_dir();
  std::unique_ptr<child_process> proc;
  std::string url;
  std::string store = "js";  ///< JetStream's store directory, under `dir`
  int stores = 0;
  nats_server() { start("-1"); }
  ~nats_server() { stop(); }
  /// Stops it (SIGTERM: JetStream's state stays on disk in `dir`).
  void stop() {
    if (proc) proc->terminate(5000ms);
    proc.reset();
  }
  /// SIGSTOP / SIGCONT: a NATS that stops answering while its connections stay up (a stall, or a
  /// partition the clients cannot see).
  void pause() { ::kill(proc->pid(), SIGSTOP); }
  void resume() { ::kill(proc->pid(), SIGCONT); }
  /// Starts it again on the same port with the same JetStream state (a NATS restart), or
  /// (`empty_store`) with a new, empty one (a NATS that lost its store).
  bool restart(bool empty_store = false) {
    const auto colon = url.rfind(':');
    const std::string port = url.substr(colon + 1);
    stop();
    url.clear();
    if (empty_store) store = "js" + std::to_string(++stores);
    start(port);
    return !url.empty();
  }

 private:
  void start(const std::string& port) {
    proc =
        std::make_unique<child_process>(std::vector<std::string>{NATS_SERVER_EXE, "-a", "127.0.0.1", "-p", port, "-js",
                                                                 "-sd", dir + "/" + store, "--ports_file_dir", dir},
                                        dir + "/nats.log");
    const std::string ports = dir + "/nats-server_" + std::to_string(proc->pid()) + ".ports";
    const auto deadline = std::chrono::steady_clock::now() + 10s;
    const std::regex re(R"((nats://[0-9.]+:[0-9]+))");
    while (url.empty() && std::chrono::steady_clock::now() < deadline) {
      std::smatch m;
      const std::string text = read_file(ports);
      if (std::regex_search(text, m, re)) url = m[1].str();
      std::this_thread::sleep_for(20ms);
    }
  }
};

zone_config small_world(std::uint64_t seed) {
  zone_config c;
  c.world = {{0, 0, 0}, {400, 400, 40}};
  c.tick_rate_hz = 30;
  c.seed = seed;
  c.npc_count = 300;
  c.boss_count = 0;
  c.aoi_tier[0] = 4, c.aoi_tier[1] = 8, c.aoi_tier[2] = 14, c.aoi_tier[3] = 20, c.aoi_tier[4] = 30;
  c.player_aoi = 20;
  c.npc_speed = 12;
  c.hysteresis = 3;
  c.share_wander = 1, c.share_patrol = 0, c.share_town = 0, c.share_chase = 0;
  return c;
}

node_options options(const std::string& url, const std::string& world, std::uint32_t cols, std::uint32_t rows,
                     const zone_config& c) {
  node_options o;
  o.world = world;
  o.url = url;
  o.cols = cols;
  o.rows = rows;
  o.bounds = c.world;
  o.lease_ttl_s = 1;
  // In-process zones answer the census only while the test ticks them: the tests that join
  // beside running zones ask for it themselves (the join would otherwise wait for nobody).
  o.join_census_s = 0;
  return o;
}

/// A zone of the in-process world: a nats_node and the zone_world it drives.
struct node_zone {
  std::unique_ptr<nats_node> node;
  zone_config cfg;
  std::unique_ptr<interest::grid_finder> finder = std::make_unique<interest::grid_finder>(nullptr);
  std::unique_ptr<zone_world> world;
  std::vector<zone_extension::redirect> redirects;
  node_zone(std::unique_ptr<nats_node> n, const zone_config& base) : node(std::move(n)) {
    cfg = node->zone_for_region(base);
    world = std::make_unique<zone_world>(cfg, *finder, nullptr);
    if (cfg.populate) world->populate();
    node->started(7000 + static_cast<std::uint16_t>(node->region()));
  }
  void tick() {
    node->before_step(*world);
    REQUIRE_FALSE(world->step().has_value());
    node->after_step(*world, redirects);
  }
};

/// The ownership records in KV: gid -> region.
std::map<global_id, std::uint32_t> kv_owners(const std::string& url, const std::string& world) {
  std::map<global_id, std::uint32_t> out;
  natsConnection* nc = nullptr;
  jsCtx* js = nullptr;
  kvStore* kv = nullptr;
  REQUIRE(natsConnection_ConnectTo(&nc, url.c_str()) == NATS_OK);
  REQUIRE(natsConnection_JetStream(&js, nc, nullptr) == NATS_OK);
  REQUIRE(js_KeyValue(&kv, js, ("world-" + world).c_str()) == NATS_OK);
  kvKeysList keys{};
  if (kvStore_Keys(&keys, kv, nullptr) == NATS_OK) {
    for (int i = 0; i < keys.Count; ++i) {
      const std::string k = keys.Keys[i];
      if (k.rfind("e.", 0) != 0) continue;
      kvEntry* e = nullptr;
      REQUIRE(kvStore_Get(&e, kv, k.c_str()) == NATS_OK);
      out[std::stoull(k.substr(2), nullptr, 16)] = static_cast<std::uint32_t>(std::stoul(kvEntry_ValueString(e)));
      kvEntry_Destroy(e);
    }
    kvKeysList_Destroy(&keys);
  }
  kvStore_Destroy(kv);
  jsCtx_Destroy(js);
  natsConnection_Destroy(nc);
  return out;
}

/// A gid as the node spells it in KV keys (16 hex digits).
std::string hex_id(global_id g) {
  char b[17];
  std::snprintf(b, sizeof b, "%016llx", static_cast<unsigned long long>(g));
  return b;
}

using zone_list = std::vector<std::unique_ptr<node_zone>>;

/// NATS requests that time out after 0.25 s: the kill tests' zones notice a dead neighbour soon.
void fast_nats(node_options& o) { o.nats_timeout_s = 0.25; }

/// The entities `zones` hold between them (their stores' sizes summed).
std::size_t entities_of(const zone_list& zones) {
  std::size_t n = 0;
  for (const auto& z : zones) n += z->world->store().size();
  return n;
}

/// `count` zones of the world `name` (a cols x rows layout), each node's options changed by `tweak`.
zone_list join_zones(const std::string& url, const std::string& name, std::uint32_t cols, std::uint32_t rows,
                     const zone_config& c, int count, const std::function<void(node_options&)>& tweak = {}) {
  zone_list zones;
  for (int k = 0; k < count; ++k) {
    std::string err;
    auto o = options(url, name, cols, rows, c);
    if (tweak) tweak(o);
    auto n = nats_node::join(o, c, &err);
    REQUIRE_MESSAGE(n != nullptr, err);
    zones.push_back(std::make_unique<node_zone>(std::move(n), c));
  }
  return zones;
}

/// Two zones of a 2x1 world on a nats-server of their own, for the tests of NATS outages: a
/// lease of 1 s (options()), requests to a NATS that does not answer failing after 0.25 s.
struct outage_world {
  nats_server ns;
  std::uint64_t seed = zone::test::fresh_seed();
  zone_list zones;
  std::size_t total = 0;  ///< entities at the start
  explicit outage_world(const std::string& name) {
    REQUIRE_FALSE(ns.url.empty());
    zones = join_zones(ns.url, name, 2, 1, small_world(seed), 2, fast_nats);
    total = entities_of(zones);
  }
  /// Ticks every zone at 30 Hz for `d` (the lease and the NATS client's timeouts are in real
  /// time), or until `done` says so.
  void run(std::chrono::milliseconds d, const std::function<bool()>& done = {}) {
    const auto until = std::chrono::steady_clock::now() + d;
    while (std::chrono::steady_clock::now() < until && !(done && done())) {
      for (auto& z : zones) z->tick();
      std::this_thread::sleep_for(33ms);
    }
  }
};

/// Ticks every zone of `zones` at 30 Hz for `d` (the leases and the NATS client's timeouts are in
/// real time).
void run_zones(zone_list& zones, std::chrono::milliseconds d) {
  for (const auto until = std::chrono::steady_clock::now() + d; std::chrono::steady_clock::now() < until;) {
    for (auto& z : zones) z->tick();
    std::this_thread::sleep_for(33ms);
  }
}

/// The census of in-process zones (their game threads answer: pumped while it waits).
std::optional<std::vector<census_entry>> census_of(zone_list& zones, const std::string& url, const std::string& name,
                                                   std::string* err) {
  return take_census(url, name, 1500, err, [&] {
    for (auto& z : zones) {
      z->node->before_step(*z->world);
      z->node->after_step(*z->world, z->redirects);  // census answers go out at the end of a tick
    }
  });
}

/// The census of `zones` (every one answering): each id owned by one zone only (a failed check
/// names the id and both owners), and, with `kv`, KV in agreement. The ids owned.
std::set<global_id> owned_once(zone_list& zones, const std::string& url, const std::string& name, bool kv = true) {
  std::string err;
  const auto census = census_of(zones, url, name, &err);
  REQUIRE_MESSAGE(census.has_value(), err);
  REQUIRE(census->size() == zones.size());
  std::map<global_id, std::pair<std::uint32_t, std::uint64_t>> owner;
  for (const auto& z : *census) {
    for (const auto& [g, epoch] : z.owned) {
      const auto [it, fresh] = owner.emplace(g, std::pair{z.region, epoch});
      CHECK_MESSAGE(fresh, "entity " << hex_id(g) << " owned by region " << z.region << " at epoch " << epoch
                                     << " and by region " << it->second.first << " at epoch " << it->second.second);
    }
  }
  if (kv) {
    const auto owners = read_owners(url, name, &err);
    REQUIRE_MESSAGE(owners.has_value(), err);
    CHECK(check_world(*census, *owners).ok());
  }
  std::set<global_id> ids;
  for (const auto& [g, o] : owner) ids.insert(g);
  return ids;
}

/// The next zone of a region whose zone was killed: joined once the dead zone's lease lapsed
/// (within 10 s; `zones` tick meanwhile).
std::unique_ptr<nats_node> join_after_kill(zone_list& zones, const std::string& url, const std::string& name,
                                           const zone_config& c, const std::function<void(node_options&)>& tweak) {
  std::string err;
  std::unique_ptr<nats_node> next;
  for (const auto until = std::chrono::steady_clock::now() + 10s; !next && std::chrono::steady_clock::now() < until;) {
    auto o = options(url, name, 2, 1, c);
    tweak(o);
    next = nats_node::join(o, c, &err);
    if (!next) run_zones(zones, 250ms);
  }
  REQUIRE_MESSAGE(next != nullptr, err);
  return next;
}

/// Has zone `z` write a checkpoint at the end of its next tick (ticked here) and waits until its
/// checkpoint thread has written it (at most 5 s), calling `meanwhile` every 33 ms (the other
/// zones tick; `z` does not, so nothing of it changes after the copy).
void checkpoint_now(node_zone& z, const std::function<void()>& meanwhile = {}) {
  const std::uint64_t written = z.node->stats().checkpoints_written.load();
  z.node->checkpoint_next_tick_for_testing();
  z.tick();
  for (const auto until = std::chrono::steady_clock::now() + 5s;
       z.node->stats().checkpoints_written.load() == written && std::chrono::steady_clock::now() < until;) {
    if (meanwhile) meanwhile();
    std::this_thread::sleep_for(33ms);
  }
  REQUIRE(z.node->stats().checkpoints_written.load() > written);
}

/// One exchange with a world-gate on loopback `port`: connects, sends `bytes` (none: says
/// nothing), and reads until the gate closes (at most 5 s). The messages it sent.
std::vector<net::message> ask_gate(std::uint16_t port, const std::vector<std::uint8_t>& bytes) {
  std::vector<net::message> got;
  const int fd = zone::test::connect_loopback(port);
  REQUIRE(fd >= 0);
  if (!bytes.empty()) REQUIRE(::send(fd, bytes.data(), bytes.size(), MSG_NOSIGNAL) == static_cast<ssize_t>(bytes.size()));
  net::frame_decoder dec;
  for (;;) {
    auto buf = dec.prepare(4096);
    const ssize_t n = ::recv(fd, buf.data(), buf.size(), 0);
    if (n <= 0) break;
    dec.commit(static_cast<std::size_t>(n));
    for (auto step = dec.next(); step.is_frame(); step = dec.next()) {
      if (auto m = net::to_message(*step.frame.envelope)) got.push_back(*m);
    }
  }
  ::close(fd);
  return got;
}

/// A world-gate process for `world` (its port read from its log).
struct gate_process {
  std::string dir = temp_dir();
  std::unique_ptr<child_process> proc;
  std::uint16_t port = 0;
  gate_process(const std::string& url, const std::string& world) {
    proc = std::make_unique<child_process>(
        std::vector<std::string>{WORLD_GATE_EXE, "--nats", url, "--world", world, "--port", "0", "--hello-timeout",
                                 "0.5", "--max-per-address", "2", "--resume-wait", "1"},
        dir + "/gate.log");
    const std::regex re(R"(listening on 127\.0\.0\.1:([0-9]+))");
    for (const auto until = std::chrono::steady_clock::now() + 10s; port == 0 && std::chrono::steady_clock::now() < until;) {
      std::smatch m;
      const std::string text = read_file(dir + "/gate.log");
      if (std::regex_search(text, m, re)) port = static_cast<std::uint16_t>(std::stoi(m[1].str()));
      std::this_thread::sleep_for(20ms);
    }
  }
  [[nodiscard]] std::string log() const { return read_file(dir + "/gate.log"); }
};

/// Handoffs the zones decided, less those the ownership CAS refused or a stopping zone abandoned.
/// `stat(node)` summed over the zones.
template <class Stat>
std::uint64_t sum_over(const zone_list& zones, Stat&& stat) {
  std::uint64_t n = 0;
  for (const auto& z : zones) n += stat(*z->node);
  return n;
}

std::uint64_t handoffs_sent(const zone_list& zones) {
  return sum_over(zones, [](const nats_node& n) {
    return n.link().stats().handoffs_out - n.stats().handoff_cas_conflicts.load() - n.stats().handoffs_abandoned.load();
  });
}

std::uint64_t handoffs_applied(const zone_list& zones) {
  return sum_over(zones, [](const nats_node& n) { return n.stats().handoffs_applied.load(); });
}

/// Applies what is in flight without handing off more, until every handoff sent is applied and
/// confirmed, or `limit` passes. Handed-off entities stay "in transit" at their old zone until the
/// new owner's ghosts confirm them, so the drain publishes ghosts too (after_step; nothing moves,
/// so nothing new is handed off). A transit can outlive the drain only if its entity left the
/// ghost band before the new owner adopted it (then its copy expires with ticks, which do not
/// advance here).
void drain(zone_list& zones, std::chrono::seconds limit) {
  const auto unconfirmed = [&] {
    std::size_t n = 0;
    for (auto& z : zones) n += z->node->link().transit_ids().size();
    return n;
  };
  const auto deadline = std::chrono::steady_clock::now() + limit;
  while ((handoffs_applied(zones) < handoffs_sent(zones) || unconfirmed() > 0) &&
         std::chrono::steady_clock::now() < deadline) {
    for (auto& z : zones) z->node->before_step(*z->world);
    for (auto& z : zones) z->node->after_step(*z->world, z->redirects);
    std::this_thread::sleep_for(10ms);
  }
}

}  // namespace

/// The world's KV bucket and handoff stream, opened by the test itself (its own connection).
struct world_kv {
  natsConnection* nc = nullptr;
  jsCtx* js = nullptr;
  kvStore* kv = nullptr;
  std::string world;
  world_kv(const std::string& url, std::string w) : world(std::move(w)) {
    REQUIRE(natsConnection_ConnectTo(&nc, url.c_str()) == NATS_OK);
    REQUIRE(natsConnection_JetStream(&js, nc, nullptr) == NATS_OK);
    REQUIRE(js_KeyValue(&kv, js, ("world-" + world).c_str()) == NATS_OK);
  }
  ~world_kv() {
    kvStore_Destroy(kv);
    jsCtx_Destroy(js);
    natsConnection_Destroy(nc);
  }
  /// (value, revision) of `key`; revision 0 when it has no entry.
  std::pair<std::string, std::uint64_t> get(const std::string& key) const {
    kvEntry* e = nullptr;
    if (kvStore_Get(&e, kv, key.c_str()) != NATS_OK) return {"", 0};
    std::pair<std::string, std::uint64_t> out{kvEntry_ValueString(e), kvEntry_Revision(e)};
    kvEntry_Destroy(e);
    return out;
  }
  std::uint64_t stream_messages() const {
    jsStreamInfo* si = nullptr;
    jsErrCode jerr{};
    REQUIRE(js_GetStreamInfo(&si, js, ("WORLD_" + world).c_str(), nullptr, &jerr) == NATS_OK);
    const std::uint64_t n = si->State.Msgs;
    jsStreamInfo_Destroy(si);
    return n;
  }
};

TEST_SUITE("world.nats") {
  TEST_CASE(
      "judge_cas_readback: our value publishes, an unchanged entry retries, ours elsewhere rebases, anything else conflicts") {
    // An update by zone 0 (holding epoch 4) from revision 7 to "1 5".
    CHECK(judge_cas_readback("1 5", 7, "0 4", true, "1 5", 8) == cas_readback::publish);  // took effect, reply lost
    CHECK(judge_cas_readback("1 5", 7, "0 4", true, "1 5", 12) ==
          cas_readback::publish);  // our value (only we write epoch 5)
    CHECK(judge_cas_readback("1 5", 7, "0 4", true, "0 4", 7) == cas_readback::retry);  // unchanged
    CHECK(judge_cas_readback("1 5", 7, "0 4", true, "0 4", 9) ==
          cas_readback::rebase);  // ours, written again (put back)
    CHECK(judge_cas_readback("1 5", 7, "0 4", true, "0 3", 9) ==
          cas_readback::conflict);  // an older epoch: not what we hold
    CHECK(judge_cas_readback("1 5", 7, "0 4", true, "2 5", 9) == cas_readback::conflict);  // someone else's handoff
    CHECK(judge_cas_readback("1 5", 7, "0 4", false, "", 0) == cas_readback::conflict);    // the record gone
    CHECK(judge_cas_readback("1 15", 7, "0 14", true, "1 1", 9) ==
          cas_readback::conflict);  // a prefix is not our value
    // A create of "1 1" by zone 0 (holding epoch 0: no record yet).
    CHECK(judge_cas_readback("1 1", 0, "0 0", false, "", 0) == cas_readback::retry);       // still no entry
    CHECK(judge_cas_readback("1 1", 0, "0 0", true, "1 1", 3) == cas_readback::publish);   // took effect
    CHECK(judge_cas_readback("1 1", 0, "0 0", true, "2 1", 3) == cas_readback::conflict);  // someone else created it
  }

  TEST_CASE("read_running: the regions the census answered for, and the highest incarnation alive per region") {
    const auto gid = [](std::uint32_t region, std::uint32_t inc, std::uint32_t n) {
      return (global_id{region + 1} << 48) | (global_id{inc} << 32) | n;
    };
    census_entry a;  // region 0, incarnation 3: owns its own ids and one of region 2's
    a.region = 0, a.incarnation = 3;
    a.owned = {{gid(0, 3, 1), 0}, {gid(2, 4, 7), 2}};
    census_entry b;  // region 1: hands one of region 2's off, waits for one of region 3's player
    b.region = 1, b.incarnation = 1;
    b.transit = {gid(2, 6, 9)};
    b.awaiting = {gid(3, 2, 1)};
    census_entry stray;  // a region outside the layout: ignored
    stray.region = 9, stray.incarnation = 50;
    stray.owned = {{gid(9, 50, 1), 0}};
    const auto r = read_running({a, b, stray}, 4);
    CHECK(r.served == std::vector<bool>{true, true, false, false});
    CHECK(r.incarnation == std::vector<std::uint32_t>{3, 1, 6, 2});
    const auto none = read_running({}, 2);
    CHECK(none.served == std::vector<bool>{false, false});
    CHECK(none.incarnation == std::vector<std::uint32_t>{0, 0});
  }

  TEST_CASE("check_leases: a region answered by two zones, or by one its lease does not name, is a problem") {
    const auto zone = [](std::uint32_t region, std::uint32_t inc) {
      census_entry e;
      e.region = region, e.incarnation = inc;
      return e;
    };
    const auto lease = [](std::uint16_t port, std::uint32_t inc) {
      return parse_lease("127.0.0.1 " + std::to_string(port) + " " + std::to_string(inc));
    };
    std::map<std::uint32_t, lease_info> leases{{0, lease(7000, 1)}, {1, lease(7001, 2)}, {2, lease(7002, 4)}};
    // Every region answered by the zone its lease names (and a lease nobody answers for: a zone
    // joining, or one too busy to answer): nothing to say.
    auto c = check_leases({zone(0, 1), zone(1, 2)}, leases);
    CHECK(c.problems.empty());
    CHECK(c.notes.empty());
    // Region 1 taken over while its old zone (incarnation 1) still serves: both answer.
    c = check_leases({zone(0, 1), zone(1, 1), zone(1, 2)}, leases);
    REQUIRE(c.problems.size() == 1);
    CHECK(c.problems[0].find("region 1 answered by 2 zones (incarnations 1, 2)") != std::string::npos);
    // Only the old one answers (the new one busy): its incarnation is not the lease's.
    c = check_leases({zone(0, 1), zone(1, 1)}, leases);
    REQUIRE(c.problems.size() == 1);
    CHECK(c.problems[0].find("region 1 answered by incarnation 1, but its lease is '127.0.0.1 7001 2'") !=
          std::string::npos);
    // A lease claimed just now ("claiming") while the old zone answers: taken over too.
    leases[1] = parse_lease("claiming");
    c = check_leases({zone(1, 1)}, leases);
    CHECK(c.problems.size() == 1);
    // No lease at all (lapsed while NATS was unreachable): a note, not a problem.
    leases.erase(1);
    c = check_leases({zone(1, 1)}, leases);
    CHECK(c.problems.empty());
    REQUIRE(c.notes.size() == 1);
    CHECK(c.notes[0].find("region 1 answered by incarnation 1 without a lease") != std::string::npos);
  }

  TEST_CASE("lease_watch: a lease whose revision has not changed for half the TTL is left out until it changes") {
    using clock = lease_watch::clock;
    const auto lease = [](std::uint16_t port, std::uint64_t revision) {
      lease_info l = parse_lease("127.0.0.1 " + std::to_string(port) + " 1");
      l.revision = revision;
      return l;
    };
    lease_watch w;
    const auto t0 = clock::now();
    const auto half = std::chrono::duration_cast<clock::duration>(1500ms);
    const auto at = [&](int ms) {
      return t0 + std::chrono::duration_cast<clock::duration>(std::chrono::milliseconds(ms));
    };
    const auto regions = [](const std::map<std::uint32_t, lease_info>& m) {
      std::vector<std::uint32_t> r;
      for (const auto& [k, v] : m) r.push_back(k);
      return r;
    };
    // Two zones renewing every 750 ms (a 3 s TTL), a third whose revision is unknown (0: kept).
    std::map<std::uint32_t, lease_info> read{{0, lease(7000, 10)}, {1, lease(7001, 20)}, {2, lease(7002, 0)}};
    CHECK(regions(w.fresh(read, at(0), half)) == std::vector<std::uint32_t>{0, 1, 2});
    read[0].revision = 11, read[1].revision = 21;
    CHECK(regions(w.fresh(read, at(750), half)) == std::vector<std::uint32_t>{0, 1, 2});
    // Region 1's zone dies: its revision stays; 1.5 s after its last renewal it is left out,
    // while region 0 renews on.
    read[0].revision = 12;
    CHECK(regions(w.fresh(read, at(1500), half)) == std::vector<std::uint32_t>{0, 1, 2});
    read[0].revision = 13;
    CHECK(regions(w.fresh(read, at(2251), half)) == std::vector<std::uint32_t>{0, 2});
    CHECK(w.fresh(read, at(2251), half).at(0).port == 7000);
    // Its lease lapses (gone from KV), and a standby claims the region: fresh at once.
    read.erase(1);
    CHECK(regions(w.fresh(read, at(3000), half)) == std::vector<std::uint32_t>{0, 2});
    read[1] = lease(7005, 20);  // a revision number it happened to have before: still new
    CHECK(regions(w.fresh(read, at(3250), half)) == std::vector<std::uint32_t>{0, 1, 2});
    CHECK(w.fresh(read, at(3250), half).at(1).port == 7005);
    // A zone whose renewals were only late is back once one goes through.
    CHECK(regions(w.fresh(read, at(4900), half)) == std::vector<std::uint32_t>{2});
    read[0].revision = 14, read[1].revision = 21;
    CHECK(regions(w.fresh(read, at(5000), half)) == std::vector<std::uint32_t>{0, 1, 2});
  }

  TEST_CASE("gate_pick: the least loaded zone that serves and has room; ties and zones without a load in turn") {
    const auto lease = [](std::uint16_t port, std::uint32_t inc, std::int64_t players = -1, std::int64_t slots = 0) {
      lease_info l = parse_lease("127.0.0.1 " + std::to_string(port) + " " + std::to_string(inc));
      l.players = players, l.slots = slots;
      return l;
    };
    const auto port_of = [](const auto& pick) { return pick ? pick->second.port : std::uint16_t{0}; };
    std::map<std::uint32_t, lease_info> leases;
    CHECK_FALSE(gate_pick(leases, 0).has_value());  // no zone serves
    leases[0] = parse_lease("claiming");            // joining
    leases[1] = lease(0, 2);                        // claimed, its server not listening yet
    CHECK_FALSE(gate_pick(leases, 5).has_value());
    // No load told: round robin.
    leases[2] = lease(7002, 1);
    leases[3] = lease(7003, 4);
    std::map<std::uint16_t, int> seen;
    for (std::uint64_t n = 0; n < 10; ++n) ++seen[port_of(gate_pick(leases, n))];
    CHECK(seen == std::map<std::uint16_t, int>{{7002, 5}, {7003, 5}});
    CHECK(gate_pick(leases, 0)->first == 2);
    CHECK(gate_pick(leases, 1)->first == 3);
    // Loads told: the least loaded, counting what was sent since; a full one skipped.
    leases[2] = lease(7002, 1, 40, 100);
    leases[3] = lease(7003, 4, 10, 100);
    CHECK(port_of(gate_pick(leases, 0)) == 7003);
    CHECK(port_of(gate_pick(leases, 0, {{3, 29}})) == 7003);  // 39 < 40
    CHECK(port_of(gate_pick(leases, 0, {{3, 30}})) == 7002);  // a tie (40, 40): round robin from n
    CHECK(port_of(gate_pick(leases, 1, {{3, 30}})) == 7003);
    leases[3] = lease(7003, 4, 100, 100);  // full
    for (std::uint64_t n = 0; n < 4; ++n) CHECK(port_of(gate_pick(leases, n)) == 7002);
    CHECK_FALSE(gate_pick(leases, 0, {{2, 60}}).has_value());  // 40 + 60: both full
  }

  TEST_CASE("judge_lease_readback: our value renews on, no key is a lapse, another value is a take-over") {
    CHECK(judge_lease_readback("127.0.0.1 7000 3", true, true, "127.0.0.1 7000 3") == lease_readback::ours);
    CHECK(judge_lease_readback("127.0.0.1 7000 3", true, false, "") == lease_readback::lapsed);
    CHECK(judge_lease_readback("127.0.0.1 7000 3", true, true, "127.0.0.1 7000 4") == lease_readback::taken);
    CHECK(judge_lease_readback("127.0.0.1 7000 3", true, true, "claiming") == lease_readback::taken);
    CHECK(judge_lease_readback("127.0.0.1 7000 3", false, false, "") == lease_readback::unknown);
  }

  TEST_CASE("a zone asking for another lease TTL than the world's renews by the world's, and keeps its lease") {
    nats_server ns;
    REQUIRE_FALSE(ns.url.empty());
    const auto c = small_world(1);
    std::string err;
    auto a = nats_node::join(options(ns.url, "ttl", 2, 1, c), c, &err);  // the world's first: leases of 1 s
    REQUIRE_MESSAGE(a != nullptr, err);
    auto o = options(ns.url, "ttl", 2, 1, c);
    o.lease_ttl_s = 8;  // would renew every 2 s: its lease would lapse (and be taken back) between renewals
    auto b = nats_node::join(o, c, &err);
    REQUIRE_MESSAGE(b != nullptr, err);
    CHECK(a->lease_ttl_s() == doctest::Approx(1));
    CHECK(b->lease_ttl_s() == doctest::Approx(1));
    std::this_thread::sleep_for(3s);
    CHECK_FALSE(b->must_stop());
    CHECK(b->stats().lease_reclaims.load() == 0);  // renewed in time: never lapsed
  }

  TEST_CASE(
      "a refused lease renewal is read back: a lost reply renews on, a lapsed lease is taken back, another holder stops the zone") {
    nats_server ns;
    REQUIRE_FALSE(ns.url.empty());
    const auto c = small_world(1);
    std::string err;
    auto node = nats_node::join(options(ns.url, "lease", 1, 1, c), c, &err);  // a lease of 1 s, renewed every 250 ms
    REQUIRE_MESSAGE(node != nullptr, err);
    node->started(7100);
    natsConnection* nc = nullptr;
    jsCtx* js = nullptr;
    kvStore* kv = nullptr;
    REQUIRE(natsConnection_ConnectTo(&nc, ns.url.c_str()) == NATS_OK);
    REQUIRE(natsConnection_JetStream(&js, nc, nullptr) == NATS_OK);
    REQUIRE(js_KeyValue(&kv, js, "world-lease-lease") == NATS_OK);
    const auto lease = [&]() -> std::pair<std::string, std::uint64_t> {
      kvEntry* e = nullptr;
      if (kvStore_Get(&e, kv, "r.0") != NATS_OK) return {"", 0};
      std::pair<std::string, std::uint64_t> out{kvEntry_ValueString(e), kvEntry_Revision(e)};
      kvEntry_Destroy(e);
      return out;
    };
    // Until the node has renewed past `rev` (bounded: 5 s).
    const auto renewed_past = [&](std::uint64_t rev) {
      const auto until = std::chrono::steady_clock::now() + 5s;
      while (lease().second <= rev && std::chrono::steady_clock::now() < until) std::this_thread::sleep_for(20ms);
      return lease().second > rev;
    };
    const auto [value, rev0] = lease();
    CHECK(value == "127.0.0.1 7100 1");
    REQUIRE(renewed_past(rev0));
    // 1. A renewal that took effect but whose reply was lost: our value at a revision the node
    // does not know (the test writes it). Its next renewal is refused, read back, and goes on.
    std::uint64_t rev1 = 0;
    REQUIRE(kvStore_PutString(&rev1, kv, "r.0", value.c_str()) == NATS_OK);
    CHECK(renewed_past(rev1 + 1));  // renewed from rev1 (a refused renewal writes nothing)
    CHECK_FALSE(node->must_stop());
    CHECK(node->stats().lease_reclaims.load() == 0);
    // 2. The lease lapsed (the key gone, as its TTL does): taken back at the next renewal.
    REQUIRE(kvStore_Delete(kv, "r.0") == NATS_OK);
    const auto until = std::chrono::steady_clock::now() + 5s;
    while (node->stats().lease_reclaims.load() == 0 && std::chrono::steady_clock::now() < until)
      std::this_thread::sleep_for(20ms);
    CHECK(node->stats().lease_reclaims.load() == 1);
    CHECK(lease().first == value);
    CHECK_FALSE(node->must_stop());
    // 3. Another zone's claim (another incarnation): the node stops serving the region.
    std::uint64_t rev3 = 0;
    REQUIRE(kvStore_PutString(&rev3, kv, "r.0", "127.0.0.1 7200 2") == NATS_OK);
    const auto stop_by = std::chrono::steady_clock::now() + 5s;
    while (!node->must_stop() && std::chrono::steady_clock::now() < stop_by) std::this_thread::sleep_for(20ms);
    CHECK(node->must_stop());
    CHECK(lease() == std::pair<std::string, std::uint64_t>{"127.0.0.1 7200 2", rev3});  // untouched
    node.reset();  // leaves without deleting another zone's lease
    CHECK(lease() == std::pair<std::string, std::uint64_t>{"127.0.0.1 7200 2", rev3});
    kvStore_Destroy(kv);
    jsCtx_Destroy(js);
    natsConnection_Destroy(nc);
  }

  TEST_CASE("a failed ownership CAS is read back: taken effect publishes once, unchanged retries, another value conflicts") {
    nats_server ns;
    REQUIRE_FALSE(ns.url.empty());
    const auto c = small_world(1);
    std::string err;
    auto node = nats_node::join(options(ns.url, "cas", 2, 1, c), c, &err);
    REQUIRE_MESSAGE(node != nullptr, err);
    world_kv w(ns.url, "cas");
    const auto& st = node->stats();
    const std::uint32_t us = node->region(), them = 1 - us;
    const auto record = [&](global_id gid, std::uint64_t epoch, std::uint64_t from_revision) {
      handoff_record r;
      r.gid = gid;
      r.epoch = epoch;
      r.from = us;
      r.to = them;
      r.owner_revision = from_revision;
      return r;
    };
    const auto own = [&](global_id gid, std::uint64_t epoch) {  // KV names us at `epoch`: its revision
      std::uint64_t rev = 0;
      REQUIRE(kvStore_PutString(&rev, w.kv, ("e." + hex_id(gid)).c_str(),
                                (std::to_string(us) + " " + std::to_string(epoch)).c_str()) == NATS_OK);
      return rev;
    };
    const std::string wanted = std::to_string(them) + " 5";
    const std::uint64_t msgs0 = w.stream_messages();

    // 1. The CAS took effect but its reply was lost: we (the test) did it first, so the node's CAS
    // from the stale revision fails; the read-back finds our value and the record is published.
    {
      const global_id g = 0xA1;
      const std::uint64_t r0 = own(g, 4);
      std::uint64_t r1 = 0;
      REQUIRE(kvStore_UpdateString(&r1, w.kv, ("e." + hex_id(g)).c_str(), wanted.c_str(), r0) == NATS_OK);
      CHECK(node->send_handoff_for_testing(record(g, 5, r0)) == r1);
      CHECK(st.handoff_cas_confirmed.load() == 1);
      CHECK(st.handoffs_sent.load() == 1);
      CHECK(w.stream_messages() == msgs0 + 1);
      // The sender resolving it again (a second timeout) publishes again: the stream's dedupe keeps one.
      CHECK(node->send_handoff_for_testing(record(g, 5, r0)) == r1);
      CHECK(st.handoff_cas_confirmed.load() == 2);
      CHECK(w.stream_messages() == msgs0 + 1);
      CHECK(w.get("e." + hex_id(g)) == std::pair{wanted, r1});  // nothing written by the read-back
    }
    // 2. A CAS that changed nothing (two attempts lost before reaching NATS): retried, succeeds.
    {
      const global_id g = 0xB2;
      const std::uint64_t r0 = own(g, 4);
      const std::uint64_t got = node->send_handoff_for_testing(record(g, 5, r0), 2);
      const auto kv = w.get("e." + hex_id(g));
      CHECK(kv.first == wanted);
      CHECK(kv.second > r0);
      CHECK(got == kv.second);
      // A create (no record yet) likewise.
      const global_id h = 0xB3;
      const std::uint64_t got_h = node->send_handoff_for_testing(record(h, 1, 0), 1);
      const auto kvh = w.get("e." + hex_id(h));
      CHECK(kvh.first == std::to_string(them) + " 1");
      CHECK(got_h == kvh.second);
      CHECK(st.handoff_cas_confirmed.load() == 2);
      CHECK(st.handoff_cas_conflicts.load() == 0);
      CHECK(w.stream_messages() == msgs0 + 3);
    }
    // 3. Someone else's value: a conflict, nothing published, KV untouched.
    {
      const global_id g = 0xC3;
      const std::uint64_t r0 = own(g, 4);
      std::uint64_t r1 = 0;
      REQUIRE(kvStore_UpdateString(&r1, w.kv, ("e." + hex_id(g)).c_str(), (std::to_string(them) + " 9").c_str(), r0) ==
              NATS_OK);
      CHECK(node->send_handoff_for_testing(record(g, 5, r0)) == 0);
      CHECK(st.handoff_cas_conflicts.load() == 1);
      CHECK(w.get("e." + hex_id(g)) == std::pair{std::to_string(them) + " 9", r1});
      // A create whose key another zone holds: a conflict too.
      CHECK(node->send_handoff_for_testing(record(g, 1, 0)) == 0);
      CHECK(st.handoff_cas_conflicts.load() == 2);
      CHECK(w.stream_messages() == msgs0 + 3);
    }
    // 4. Every attempt of a round fails while KV stays unchanged: not settled, not published (the
    // sender keeps the record and comes back to it); the next round settles it.
    {
      const global_id g = 0xD4;
      const std::uint64_t r0 = own(g, 4);
      CHECK(node->send_handoff_for_testing(record(g, 5, r0), 100) == 0);
      CHECK(w.get("e." + hex_id(g)) == std::pair{std::to_string(us) + " 4", r0});
      CHECK(w.stream_messages() == msgs0 + 3);
      const std::uint64_t got = node->send_handoff_for_testing(record(g, 5, r0));
      CHECK(w.get("e." + hex_id(g)) == std::pair{wanted, got});
      CHECK(w.stream_messages() == msgs0 + 4);
    }
    CHECK(st.handoffs_sent.load() == 5);
    CHECK(st.handoff_cas_conflicts.load() == 2);
  }

  TEST_CASE("world-gate: a hello is sent on to a zone that serves; no zone, garbage or silence get an error") {
    nats_server ns;
    REQUIRE_FALSE(ns.url.empty());
    const auto c = small_world(zone::test::fresh_seed());
    gate_process gate(ns.url, "gate");  // before the world exists: it waits for it
    REQUIRE_MESSAGE(gate.port != 0, gate.log());
    const auto hello = net::encode_frame(net::hello_msg{"alice", "", net::protocol_version});
    const auto only = [](const std::vector<net::message>& got) {
      REQUIRE(got.size() == 1);
      return got.front();
    };
    // No zone serves the world yet.
    auto m = only(ask_gate(gate.port, hello));
    REQUIRE(std::holds_alternative<net::error_msg>(m));
    CHECK(std::get<net::error_msg>(m).code == net::error_code::server_full);
    // Two zones: the logins go to each in turn, a redirect without a token to its address.
    zone_list zones = join_zones(ns.url, "gate", 2, 1, c, 2);  // listening at 7000 + region
    std::map<std::uint16_t, int> sent;
    for (const auto until = std::chrono::steady_clock::now() + 5s;
         sent.size() < 2 && std::chrono::steady_clock::now() < until;) {
      m = only(ask_gate(gate.port, hello));
      if (std::holds_alternative<net::redirect_msg>(m)) {
        const auto& r = std::get<net::redirect_msg>(m);
        CHECK(r.host == "127.0.0.1");
        CHECK(r.token.empty());
        ++sent[r.port];
      } else {
        std::this_thread::sleep_for(100ms);  // the gate reads the leases every 250 ms
      }
    }
    CHECK(sent.size() == 2);
    CHECK(sent.count(7000) == 1);
    CHECK(sent.count(7001) == 1);
    // The zones tell their load beside their leases (players, slots): the gate's choice.
    zones[0]->node->clients(7, 10);
    zones[1]->node->clients(2, 10);
    std::string lerr;
    std::optional<std::map<std::uint32_t, lease_info>> leases;
    for (const auto until = std::chrono::steady_clock::now() + 3s; std::chrono::steady_clock::now() < until;) {
      leases = read_leases(ns.url, "gate", &lerr);
      REQUIRE_MESSAGE(leases.has_value(), lerr);
      if (leases->size() == 2 && leases->at(0).players == 7 && leases->at(1).players == 2) break;
      std::this_thread::sleep_for(50ms);
    }
    REQUIRE(leases->size() == 2);
    CHECK(leases->at(0).players == 7);
    CHECK(leases->at(0).slots == 10);
    CHECK(leases->at(1).players == 2);
    std::this_thread::sleep_for(300ms);  // the gate has read them too
    // The least loaded first: region 1 until it carries as many (2 + 5 = 7), then in turn.
    std::vector<std::uint16_t> order;
    for (int k = 0; k < 5; ++k) {
      m = only(ask_gate(gate.port, hello));
      REQUIRE(std::holds_alternative<net::redirect_msg>(m));
      order.push_back(std::get<net::redirect_msg>(m).port);
    }
    CHECK(order == std::vector<std::uint16_t>(5, 7001));
    // A client back with its resume token goes to the zone of the region the token names, with it
    // (whatever the loads); a token of a region no zone serves waits (--resume-wait 1), then an
    // error; a token that is none of the zones' is refused at once.
    const auto resume_hello = [](const std::string& token) {
      return net::encode_frame(net::hello_msg{"bob", token, net::protocol_version});
    };
    for (const std::uint32_t region : {0u, 1u}) {
      const std::string token = (region == 0 ? "0001" : "0002") + std::string("00c0ffee0042");
      REQUIRE(token_region(token) == std::optional<std::uint32_t>(region));
      m = only(ask_gate(gate.port, resume_hello(token)));
      REQUIRE(std::holds_alternative<net::redirect_msg>(m));
      CHECK(std::get<net::redirect_msg>(m).port == 7000 + region);
      CHECK(std::get<net::redirect_msg>(m).token == token);
    }
    const auto asked = std::chrono::steady_clock::now();
    m = only(ask_gate(gate.port, resume_hello("0006000000000001")));  // region 5 of a 2x1 world
    REQUIRE(std::holds_alternative<net::error_msg>(m));
    CHECK(std::get<net::error_msg>(m).code == net::error_code::timeout);
    CHECK(std::chrono::steady_clock::now() - asked >= 900ms);
    for (const char* bad : {"not-a-token", "0000c0ffee000042", "0001c0ffee00004g", "0001c0ffee0000420"}) {
      CAPTURE(bad);
      m = only(ask_gate(gate.port, resume_hello(bad)));
      REQUIRE(std::holds_alternative<net::error_msg>(m));
      CHECK(std::get<net::error_msg>(m).code == net::error_code::auth_failed);
    }
    // A first frame that is not a hello, bytes that are not a frame, and silence past the hello
    // timeout: an error each, then the connection closed.
    m = only(ask_gate(gate.port, net::encode_frame(net::ping_msg{1})));
    REQUIRE(std::holds_alternative<net::error_msg>(m));
    CHECK(std::get<net::error_msg>(m).code == net::error_code::unexpected_message);
    m = only(ask_gate(gate.port, std::vector<std::uint8_t>(64, 0xff)));
    REQUIRE(std::holds_alternative<net::error_msg>(m));
    CHECK(std::get<net::error_msg>(m).code == net::error_code::bad_frame);
    m = only(ask_gate(gate.port, {}));
    REQUIRE(std::holds_alternative<net::error_msg>(m));
    CHECK(std::get<net::error_msg>(m).code == net::error_code::timeout);
    // Two connections held from this address (--max-per-address 2): a third is closed at accept,
    // before any message.
    std::this_thread::sleep_for(300ms);  // the gate has closed the connections above (each read to its end)
    std::vector<int> held;
    for (int k = 0; k < 2; ++k) {
      held.push_back(zone::test::connect_loopback(gate.port));
      REQUIRE(held.back() >= 0);
    }
    CHECK(ask_gate(gate.port, {}).empty());
    for (const int fd : held) ::close(fd);
    // Stopped, it counts what it did.
    gate.proc->terminate(5000ms);
    const std::string log = gate.log();
    CHECK_MESSAGE(log.find("refused for want of a zone") != std::string::npos, log);
    CHECK(std::regex_search(
        log,
        std::regex(
            R"(world gate: [1-9][0-9]* logins redirected, [1-9][0-9]* refused for want of a zone, 6 bad, 1 timed out, 0 refused \(full\), 1 refused \(over --max-per-address\); 2 resumes redirected, 1 gave up)")));
  }

  TEST_CASE("regions are claimed by CAS: one zone each, a full world refuses, leaving frees a region") {
    nats_server ns;
    REQUIRE_FALSE(ns.url.empty());
    const auto c = small_world(1);
    std::string err;
    auto a = nats_node::join(options(ns.url, "claims", 2, 1, c), c, &err);
    REQUIRE_MESSAGE(a != nullptr, err);
    auto b = nats_node::join(options(ns.url, "claims", 3, 3, c), c, &err);  // the layout in KV wins
    REQUIRE_MESSAGE(b != nullptr, err);
    CHECK(b->map() == a->map());
    CHECK(a->map().count() == 2);
    CHECK(a->region() != b->region());
    CHECK_FALSE(nats_node::join(options(ns.url, "claims", 2, 1, c), c, &err));
    CHECK(err.find("every region") != std::string::npos);
    const std::uint32_t freed = b->region();
    const std::uint32_t inc = b->incarnation();
    b.reset();  // leaves: deletes its lease
    auto again = nats_node::join(options(ns.url, "claims", 2, 1, c), c, &err);
    REQUIRE_MESSAGE(again != nullptr, err);
    CHECK(again->region() == freed);
    CHECK(again->incarnation() == inc + 1);  // ids of the new zone differ from the old one's
    auto other = c;
    other.world.hi.x = 500;
    CHECK_FALSE(nats_node::join(options(ns.url, "claims", 2, 1, other), other, &err));
    CHECK(err.find("bounds") != std::string::npos);
    node_options bad = options("nats://127.0.0.1:1", "claims", 2, 1, c);
    CHECK_FALSE(nats_node::join(bad, c, &err));
    CHECK(err.find("cannot connect") != std::string::npos);
  }

  TEST_CASE("handoffs over JetStream: every entity owned exactly once, zones and KV agree, replays refused") {
    nats_server ns;
    REQUIRE_FALSE(ns.url.empty());
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    const auto c = small_world(seed);
    zone_list zones = join_zones(ns.url, "handoff", 2, 2, c, 4);
    const std::size_t total = entities_of(zones);  // world-wide ids come in after_step
    for (int t = 0; t < 240; ++t) {
      for (auto& z : zones) z->tick();
      std::this_thread::sleep_for(2ms);
    }
    drain(zones, 10s);
    CHECK(handoffs_sent(zones) > 100);
    CHECK(handoffs_applied(zones) == handoffs_sent(zones));
    std::uint64_t cas_conflicts = 0, dup = 0;
    for (auto& z : zones) {
      cas_conflicts += z->node->stats().handoff_cas_conflicts.load();
      dup += z->node->stats().handoff_duplicates.load();
      CHECK(z->node->stats().handoff_retries.load() == 0);
    }
    CHECK(cas_conflicts == 0);
    CHECK(dup == 0);  // JetStream's dedupe and one delivery each

    // The census (each zone answers on the game thread: pump them while waiting).
    std::string err;
    const auto census = census_of(zones, ns.url, "handoff", &err);
    REQUIRE_MESSAGE(census.has_value(), err);
    REQUIRE(census->size() == 4);
    std::map<global_id, std::uint32_t> owner;
    std::size_t count = 0;
    for (const auto& z : *census) {
      for (const auto& [g, epoch] : z.owned) {
        CHECK_MESSAGE(owner.emplace(g, z.region).second, "entity owned by two zones");
        ++count;
      }
    }
    // Every handoff has landed: an id still in transit somewhere awaits only its confirmation.
    for (const auto& z : *census) {
      for (const global_id g : z.transit) CHECK_MESSAGE(owner.contains(g), "in transit and owned by no zone after the drain");
    }
    const auto owners = read_owners(ns.url, "handoff", &err);
    REQUIRE_MESSAGE(owners.has_value(), err);
    const auto verdict = check_world(*census, *owners);
    CHECK(verdict.ok());
    CHECK(verdict.owned_twice == 0);
    CHECK(verdict.transit_only == 0);
    CHECK(count == total);  // none lost, none made up
    // Every entity that was ever handed off has a KV record naming the zone that owns it now.
    const auto kv = kv_owners(ns.url, "handoff");
    CHECK(kv.size() > 50);
    for (const auto& [g, region] : kv) {
      const auto it = owner.find(g);
      REQUIRE(it != owner.end());
      CHECK(it->second == region);
    }

    // The records read one by one (what world-check does for ids a listing missed): the same
    // records, and nothing for an id with none.
    {
      std::vector<global_id> ids;
      for (const auto& [g, region] : kv) ids.push_back(g);
      ids.push_back(0xdead0000beefull);
      const auto one_by_one = read_owners(ns.url, "handoff", &err, &ids);
      REQUIRE_MESSAGE(one_by_one.has_value(), err);
      CHECK(one_by_one->size() == kv.size());
      for (const auto& [g, rec] : *one_by_one) CHECK(rec.first == kv.at(g));
    }

    // A replay (an old record under a new message id, past the dedupe window): refused by epoch.
    const auto [replay_gid, replay_region] = *kv.begin();
    handoff_record r;
    r.gid = replay_gid;
    r.epoch = 1;
    r.from = (replay_region + 1) % 4;
    r.to = replay_region;
    r.desc.position = {1, 1, 0};
    r.behaviour.kind = behaviour::wander;
    natsConnection* nc = nullptr;
    jsCtx* js = nullptr;
    REQUIRE(natsConnection_ConnectTo(&nc, ns.url.c_str()) == NATS_OK);
    REQUIRE(natsConnection_JetStream(&js, nc, nullptr) == NATS_OK);
    const auto bytes = encode(r);
    jsPubOptions po;
    jsPubOptions_Init(&po);
    po.MsgId = "replay-1";
    const std::string subj = "world.handoff.handoff." + std::to_string(replay_region);
    REQUIRE(js_Publish(nullptr, js, subj.c_str(), bytes.data(), static_cast<int>(bytes.size()), &po, nullptr) == NATS_OK);
    // The same message id again: JetStream drops it (it is never delivered).
    REQUIRE(js_Publish(nullptr, js, subj.c_str(), bytes.data(), static_cast<int>(bytes.size()), &po, nullptr) == NATS_OK);
    jsCtx_Destroy(js);
    natsConnection_Destroy(nc);
    std::uint64_t dups = 0;
    const auto until = std::chrono::steady_clock::now() + 10s;  // fetched within 100 ms on a quiet host
    while (dups == 0 && std::chrono::steady_clock::now() < until) {
      for (auto& z : zones) z->node->before_step(*z->world);
      dups = 0;
      for (auto& z : zones) dups += z->node->stats().handoff_duplicates.load();
      std::this_thread::sleep_for(10ms);
    }
    std::this_thread::sleep_for(300ms);
    for (auto& z : zones) z->node->before_step(*z->world);
    dups = 0;
    for (auto& z : zones) dups += z->node->stats().handoff_duplicates.load();
    CHECK(dups == 1);
    std::size_t after = 0;
    for (auto& z : zones) after += z->node->link().owned_count();
    CHECK(after == total);
  }

  TEST_CASE("a player handed off: a redirect with a token, inputs sent meanwhile forwarded, the token claims it once") {
    nats_server ns;
    REQUIRE_FALSE(ns.url.empty());
    auto c = small_world(5);
    c.npc_count = 0;
    zone_list zones = join_zones(ns.url, "redirect", 2, 1, c, 2);
    auto& a = zones[0]->node->region() == 0 ? *zones[0] : *zones[1];
    auto& b = zones[0]->node->region() == 0 ? *zones[1] : *zones[0];
    // Both zones have ticked once (ids given).
    a.tick();
    b.tick();
    // A player of zone A that walked 20 m into B's region. Its redirect goes out once A knows B's
    // address (B's lease named its port after A read the table: A's heartbeat thread reads it
    // again when a redirect asks, a tick or two later).
    const entity_id player = a.world->spawn_player({220, 100, 0});
    REQUIRE(player != null_entity);
    a.redirects.clear();
    const auto addressed_by = std::chrono::steady_clock::now() + 5s;
    while (a.redirects.empty() && std::chrono::steady_clock::now() < addressed_by) {
      a.node->after_step(*a.world, a.redirects);
      std::this_thread::sleep_for(5ms);
    }
    REQUIRE(a.redirects.size() == 1);
    const auto r = a.redirects[0];
    CHECK(r.entity == player);
    CHECK(r.host == "127.0.0.1");
    CHECK(r.port == 7000 + b.node->region());
    CHECK(r.token.size() == 16);
    CHECK_FALSE(a.node->owns(player));  // a ghost here from now on
    // The client has not moved yet: its inputs go to A, which forwards them.
    a.node->forward_input(player, {0, 1, 0}, 41);
    a.node->forward_input(player, {-1, 0, 0}, 42);
    // B: the handoff lands, the forwarded inputs apply; the token claims the entity, once.
    entity_id there = null_entity;
    auto verdict = zone_extension::claim::wait;
    const auto deadline = std::chrono::steady_clock::now() + 5s;
    while (verdict == zone_extension::claim::wait && std::chrono::steady_clock::now() < deadline) {
      b.node->before_step(*b.world);
      verdict = b.node->claim_token(r.token, *b.world, there);
      std::this_thread::sleep_for(5ms);
    }
    REQUIRE(verdict == zone_extension::claim::ready);
    CHECK(b.node->owns(there));
    CHECK(b.world->behaviour_of(there) == behaviour::player);
    // Inputs forwarded before the entity arrived are kept and applied on arrival; later ones too.
    // Both are core NATS messages on their way to B (applied in before_step): wait until B got them.
    const auto inputs_by = std::chrono::steady_clock::now() + 5s;
    while (b.node->stats().inputs_received.load() < 2 && std::chrono::steady_clock::now() < inputs_by) {
      b.node->before_step(*b.world);
      std::this_thread::sleep_for(5ms);
    }
    const auto st = b.world->behaviour_state_of(there);
    REQUIRE(st.has_value());
    CHECK(st->intent == vec3{-1, 0, 0});  // the last input sent
    entity_id again = null_entity;
    CHECK(b.node->claim_token(r.token, *b.world, again) != zone_extension::claim::ready);
    CHECK(b.node->claim_token("not-a-token", *b.world, again) == zone_extension::claim::refused);
    CHECK(b.node->claim_token("0000000000000000", *b.world, again) == zone_extension::claim::refused);
    CHECK(b.node->stats().inputs_received.load() == 2);
  }

  TEST_CASE("a stalled neighbour: the other zone ticks on, its ghosts of it expire, a snapshot heals it afterwards") {
    nats_server ns;
    REQUIRE_FALSE(ns.url.empty());
    auto c = small_world(9);
    zone_list zones = join_zones(ns.url, "stall", 2, 1, c, 2);
    auto& a = *zones[0];
    auto& b = *zones[1];
    const auto ghosts = [](node_zone& z) {
      std::size_t n = 0;
      // Not counting its own in-transit copies (handoffs to the stalled zone wait on the stream).
      for (const entity_id id : z.world->store().ids()) n += z.node->owns(id) || z.node->link().in_transit(id) ? 0 : 1;
      return n;
    };
    // Ghost messages travel through nats-server and the receiver's NATS thread: on a loaded host
    // they come some ticks late. Tick both until each holds ghosts of the other (bounded in time).
    const auto until = std::chrono::steady_clock::now() + 10s;
    for (int t = 0; t < 30 || ((ghosts(a) == 0 || ghosts(b) == 0) && std::chrono::steady_clock::now() < until); ++t) {
      a.tick();
      b.tick();
      std::this_thread::sleep_for(3ms);
    }
    CHECK(ghosts(a) > 0);
    CHECK(ghosts(b) > 0);
    // Everything B sent is applied at A before B stalls (A's before_step alone: no tick passes), so
    // the silence A measures starts at this tick, not when a message late on a loaded host lands.
    const auto sent_by_b = b.node->link().stats().ghost_messages_out;  // A is B's only neighbour
    const auto drained_by = std::chrono::steady_clock::now() + 10s;
    while (a.node->link().stats().ghost_messages_in < sent_by_b && std::chrono::steady_clock::now() < drained_by) {
      a.node->before_step(*a.world);
      std::this_thread::sleep_for(2ms);
    }
    REQUIRE(a.node->link().stats().ghost_messages_in == sent_by_b);
    // B stalls (its game thread stops): A goes on ticking, nothing it does waits for B; after the
    // timeout (60 ticks) A holds no ghost of B.
    const auto stalled_at = b.world->tick();
    for (int t = 0; t < 80; ++t) a.tick();
    CHECK(b.world->tick() == stalled_at);
    CHECK(ghosts(a) == 0);
    CHECK(a.node->link().stats().ghosts_expired > 0);
    // B resumes: A needs a snapshot (its ghosts of B expired with the silence), asks, gets it: a
    // round trip through nats-server (the request, then the snapshot), some ticks on a loaded
    // host. Tick both until A holds ghosts of B again and waits for no snapshot (bounded in time).
    const auto healed_by = std::chrono::steady_clock::now() + 10s;
    for (int t = 0; t < 40 || ((ghosts(a) == 0 || !a.node->link().snapshot_wanted().empty()) &&
                               std::chrono::steady_clock::now() < healed_by);
         ++t) {
      a.tick();
      b.tick();
      std::this_thread::sleep_for(3ms);
    }
    CHECK(ghosts(a) > 0);
    CHECK(a.node->link().snapshot_wanted().empty());
  }

  TEST_CASE("a full zone: handoffs into it wait on the stream (retried, never lost or owned twice) until it has room") {
    nats_server ns;
    REQUIRE_FALSE(ns.url.empty());
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    // A's NPCs run fast (many walk into B); B's barely move (B stays full: it hands out almost none).
    auto fast = small_world(seed);
    auto slow = fast;
    slow.npc_speed = 0.05f;
    std::string err;
    // A hands off into B although B says it is full (hold_for_room off): the records' path
    // through the stream, which records still take when a neighbour's room is overrun.
    auto oa = options(ns.url, "full", 2, 1, fast);
    oa.hold_for_room = false;
    auto na = nats_node::join(oa, fast, &err);
    REQUIRE_MESSAGE(na != nullptr, err);
    auto ob = options(ns.url, "full", 2, 1, slow);
    ob.capacity = slow.npc_count;  // full from the start
    ob.no_room_retry_s = 0.05;
    auto nb = nats_node::join(ob, slow, &err);
    REQUIRE_MESSAGE(nb != nullptr, err);
    REQUIRE(na->region() == 0);
    node_zone a(std::move(na), fast), b(std::move(nb), slow);
    const std::size_t total = a.world->store().size() + b.world->store().size();
    // Until a dozen records into B went back to the stream for want of room (bounded: 600 ticks).
    for (int t = 0; t < 600 && (t < 150 || b.node->stats().handoffs_no_room.load() < 12); ++t) {
      a.tick();
      b.tick();
      CHECK(b.node->link().owned_count() <= slow.npc_count);  // never past its capacity
      std::this_thread::sleep_for(2ms);
    }
    const auto sent = [&] {
      return a.node->stats().handoffs_sent.load() + b.node->stats().handoffs_sent.load();
    };
    const auto applied = [&] {
      return a.node->stats().handoffs_applied.load() + b.node->stats().handoffs_applied.load();
    };
    // Records into B came and went back to the stream; none was applied while B was full.
    const std::uint64_t a_to_b = a.node->stats().handoffs_sent.load();
    CHECK(a_to_b > 3);
    CHECK(b.node->stats().handoffs_no_room.load() >= 12);
    CHECK(b.node->link().stats().handoffs_no_room > 0);
    CHECK(applied() < sent());
    const std::uint64_t waiting = sent() - applied();
    // Room in B: 2 x the waiting records' worth of its own NPCs leave the world (despawned by the zone).
    std::size_t removed = 0;
    for (const entity_id id : std::vector<entity_id>(b.world->store().ids().begin(), b.world->store().ids().end())) {
      if (removed >= 2 * waiting + 10) break;
      if (b.node->owns(id) && b.world->despawn(id)) ++removed;
    }
    b.node->after_step(*b.world, b.redirects);  // the zone's link sees them gone (at the end of its tick)
    // The waiting records are offered again and adopted: none lost.
    const auto deadline = std::chrono::steady_clock::now() + 10s;
    while (applied() < sent() && std::chrono::steady_clock::now() < deadline) {
      a.node->before_step(*a.world);
      b.node->before_step(*b.world);
      std::this_thread::sleep_for(10ms);
    }
    CHECK(applied() == sent());
    CHECK(a.node->stats().handoff_cas_conflicts.load() + b.node->stats().handoff_cas_conflicts.load() == 0);
    const auto census = take_census(ns.url, "full", 1500, &err, [&] {
      for (node_zone* z : {&a, &b}) {
        z->node->before_step(*z->world);
        z->node->after_step(*z->world, z->redirects);
      }
    });
    REQUIRE_MESSAGE(census.has_value(), err);
    REQUIRE(census->size() == 2);
    std::size_t owned = 0;
    std::set<global_id> ids;
    for (const auto& z : *census) {
      for (const auto& [g, epoch] : z.owned) {
        CHECK_MESSAGE(ids.insert(g).second, "entity owned by two zones");
        ++owned;
      }
    }
    const auto owners = read_owners(ns.url, "full", &err);
    REQUIRE_MESSAGE(owners.has_value(), err);
    const auto verdict = check_world(*census, *owners);
    CHECK(verdict.ok());
    CHECK(owned + verdict.transit_only == total - removed);  // every handed-off entity arrived
  }

  TEST_CASE(
      "NATS stalled, then restarted, each for three leases: the zones tick on, keep their regions, lose no entity") {
    outage_world w("outage");
    CAPTURE(w.seed);
    auto& ns = w.ns;
    auto& zones = w.zones;
    const std::size_t total = w.total;
    const auto sum = [&](auto stat) { return sum_over(zones, stat); };
    const auto retries = [](const nats_node& n) { return n.stats().handoff_retries.load(); };
    const auto holds = [](const nats_node& n) { return n.stats().handoff_hold_ticks.load(); };
    w.run(2s);
    CHECK(sum(holds) == 0);
    // 1. NATS stalls (SIGSTOP: the connections stay up, requests time out). The first record
    // decided after it cannot settle: the sender keeps it and tries again; meanwhile the zones
    // hand nothing off (entities past the border stay owned).
    ns.pause();
    w.run(3s);
    CHECK(sum(retries) > 0);
    const std::uint64_t held_in_stall = sum(holds);
    CHECK(held_in_stall > 0);
    ns.resume();
    w.run(2s);
    // 2. NATS stops (the connections close) and starts again on its port with its state.
    ns.stop();
    w.run(3s);
    CHECK(sum(holds) > held_in_stall + 60);  // every tick of the outage, in both zones
    REQUIRE(ns.restart());
    w.run(3s);
    for (auto& z : zones) CHECK_FALSE(z->node->must_stop());
    CHECK(sum([](const nats_node& n) { return n.stats().lease_reclaims.load(); }) >= 2);  // lapsed, taken back
    drain(zones, 20s);
    CHECK(handoffs_sent(zones) > 20);
    CHECK(handoffs_applied(zones) == handoffs_sent(zones));
    CHECK(sum([](const nats_node& n) {
            return n.stats().handoffs_abandoned.load() + n.stats().handoff_cas_conflicts.load();
          }) == 0);
    std::string err;
    const auto census = census_of(zones, ns.url, "outage", &err);
    REQUIRE_MESSAGE(census.has_value(), err);
    REQUIRE(census->size() == 2);
    std::set<global_id> ids;
    for (const auto& z : *census) {
      for (const auto& [g, epoch] : z.owned) CHECK_MESSAGE(ids.insert(g).second, "entity owned by two zones");
    }
    const auto owners = read_owners(ns.url, "outage", &err);
    REQUIRE_MESSAGE(owners.has_value(), err);
    const auto verdict = check_world(*census, *owners);
    CHECK(verdict.ok());
    CHECK(verdict.transit_only == 0);
    CHECK(ids.size() == total);  // none lost, none made up
  }

  TEST_CASE("ownership records put back after the world's state was made again: the highest epoch wins") {
    nats_server ns;
    REQUIRE_FALSE(ns.url.empty());
    const auto c = small_world(zone::test::fresh_seed());
    zone_list zones = join_zones(ns.url, "putback", 2, 1, c, 1);
    nats_node& n = *zones[0]->node;
    world_kv kv(ns.url, "putback");
    const global_id g = 0x0002000100000042ull, h = 0x0002000100000043ull;
    CHECK(n.put_record_for_testing(g, 1, 3));  // missing: created
    CHECK(kv.get("e." + hex_id(g)).first == "1 3");
    CHECK(n.put_record_for_testing(g, 0, 1));  // an older epoch (what a zone had published before): left
    CHECK(kv.get("e." + hex_id(g)).first == "1 3");
    CHECK(n.put_record_for_testing(g, 1, 3));  // the same: left
    CHECK(n.put_record_for_testing(g, 0, 5));  // a newer epoch (its owner's): replaces it
    CHECK(kv.get("e." + hex_id(g)).first == "0 5");
    CHECK(n.put_record_for_testing(h, 0, 2));
    CHECK(kv.get("e." + hex_id(h)).first == "0 2");
  }

  TEST_CASE(
      "NATS restarted without its store: the zones make the world's state again, hand off again, lose no entity") {
    outage_world w("lost");
    CAPTURE(w.seed);
    auto& zones = w.zones;
    const auto all = [&](auto pred) {
      return std::all_of(zones.begin(), zones.end(), [&](const auto& z) { return pred(*z->node); });
    };
    const auto remade = [&] { return all([](const nats_node& n) { return n.stats().world_remade.load() > 0; }); };
    const auto sent = [](const nats_node& n) { return n.stats().handoffs_sent.load(); };
    w.run(2s);
    CHECK(sum_over(zones, sent) > 0);
    // The ticks go on through the restart: records published just before it may be on the lost
    // stream, unfetched (the zones publish them again).
    REQUIRE(w.ns.restart(true));
    // Each zone finds the state gone at a failed lease renewal (every quarter of its 1 s lease)
    // once its client has reconnected, and makes it again (bounded: 15 s).
    w.run(15s, remade);
    REQUIRE(remade());
    for (auto& z : zones) {
      CHECK_FALSE(z->node->stats().jetstream_state_lost.load());
      CHECK_FALSE(z->node->must_stop());
    }
    // Handoffs go on: more are sent and every one is applied.
    const std::uint64_t sent_at_remake = sum_over(zones, sent);
    w.run(4s);
    CHECK(sum_over(zones, [](const nats_node& n) { return n.stats().owners_reput.load(); }) > 0);
    CHECK(sum_over(zones, sent) > sent_at_remake);
    drain(zones, 20s);
    CHECK(handoffs_applied(zones) == handoffs_sent(zones));  // each once: one published again is a duplicate
    CHECK(sum_over(zones, [](const nats_node& n) {
            return n.stats().handoffs_abandoned.load() + n.stats().handoff_cas_conflicts.load();
          }) == 0);
    // Every entity owned once, none lost, and KV agrees with the zones (its records put back).
    std::string err;
    const auto census = census_of(zones, w.ns.url, "lost", &err);
    REQUIRE_MESSAGE(census.has_value(), err);
    REQUIRE(census->size() == 2);
    std::set<global_id> ids;
    for (const auto& z : *census) {
      for (const auto& [g, epoch] : z.owned) CHECK_MESSAGE(ids.insert(g).second, "entity owned by two zones");
    }
    const auto owners = read_owners(w.ns.url, "lost", &err);
    REQUIRE_MESSAGE(owners.has_value(), err);
    const auto verdict = check_world(*census, *owners);
    CHECK(verdict.ok());
    CHECK(verdict.transit_only == 0);
    CHECK(ids.size() == w.total);
  }

  TEST_CASE(
      "a zone joining while the world's state is lost: it claims no region a running zone serves, and no id alive") {
    nats_server ns;
    REQUIRE_FALSE(ns.url.empty());
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    const auto c = small_world(seed);
    // Leases of 40 s: the running zones renew (and so find the state lost) 10 s after they joined,
    // long after the join below (about 6 s after theirs).
    const auto tweak = [](node_options& o) {
      o.lease_ttl_s = 40;
      o.nats_timeout_s = 0.25;
    };
    zone_list zones = join_zones(ns.url, "lostjoin", 3, 1, c, 3, tweak);
    const auto run = [&](std::chrono::milliseconds d) { run_zones(zones, d); };
    // Entities of region 2 (incarnation 1) cross into region 1; then region 2's zone leaves.
    run(2s);
    REQUIRE(zones[2]->node->region() == 2);
    zones.pop_back();
    run(500ms);
    std::size_t region2_alive = 0;
    for (auto& z : zones) {
      for (const global_id g : z->node->link().owned_ids()) region2_alive += region_of_gid(g) == 2;
    }
    REQUIRE(region2_alive > 0);
    // NATS loses its store: leases, incarnations, the layout, all gone.
    REQUIRE(ns.restart(true));
    run(1500ms);  // the zones' clients reconnect (they answer the census over core NATS)
    for (auto& z : zones) REQUIRE(z->node->stats().world_remade.load() == 0);  // not made again yet
    // A zone joins meanwhile (its own thread; the running zones answer its census as they tick).
    auto o = options(ns.url, "lostjoin", 3, 1, c);
    tweak(o);
    o.join_census_s = 1;
    std::string err;
    auto joining = std::async(std::launch::async, [&] { return nats_node::join(o, c, &err); });
    while (joining.wait_for(0ms) != std::future_status::ready) run(33ms);
    auto n = joining.get();
    REQUIRE_MESSAGE(n != nullptr, err);
    for (auto& z : zones) CHECK(z->node->stats().world_remade.load() == 0);  // the join saw the state lost
    CHECK(n->region() == 2);       // not region 0, the first without a lease, which zone 0 serves
    CHECK(n->incarnation() >= 2);  // above region 2's ids alive in regions 0 and 1
    zones.push_back(std::make_unique<node_zone>(std::move(n), c));
    // The running zones make the state again at their renewal and keep their regions.
    const auto remade = [&] {
      return std::all_of(zones.begin(), zones.begin() + 2,
                         [](const auto& z) { return z->node->stats().world_remade.load() > 0; });
    };
    for (const auto until = std::chrono::steady_clock::now() + 15s;
         !remade() && std::chrono::steady_clock::now() < until;)
      run(100ms);
    REQUIRE(remade());
    run(1s);
    for (auto& z : zones) CHECK_FALSE(z->node->must_stop());
    // Every id owned once: the new zone's ids are not those of region 2's entities still alive.
    (void)owned_once(zones, ns.url, "lostjoin", false);
  }

  TEST_CASE("a zone killed: its successor restores the region's checkpoint, every entity back once, KV agreeing") {
    nats_server ns;
    REQUIRE_FALSE(ns.url.empty());
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    const auto c = small_world(seed);
    zone_list zones = join_zones(ns.url, "ckpt", 2, 1, c, 2, fast_nats);
    const std::size_t total = entities_of(zones);
    const auto tick_all = [&](std::chrono::milliseconds d) { run_zones(zones, d); };
    tick_all(3s);
    CHECK(handoffs_sent(zones) > 0);
    for (auto& z : zones) CHECK(z->node->stats().checkpoints_written.load() > 0);  // one a second
    // Zone 1 writes a checkpoint at the end of its next tick, and is killed once it is written
    // (and its sender has published what it decided): nothing of it changes in between.
    nats_node& victim = *zones[1]->node;
    checkpoint_now(*zones[1], [&] { zones[0]->tick(); });
    const auto at_kill = victim.link().owned_ids();
    CHECK(victim.stats().checkpoint_entities.load() == at_kill.size());
    victim.crash_for_testing();
    zones.pop_back();
    // The other zone ticks on (handing entities to region 1: they wait on the stream); the lease
    // lapses (1 s); then the region's next zone joins.
    tick_all(1500ms);
    auto next = join_after_kill(zones, ns.url, "ckpt", c, fast_nats);
    CHECK(next->region() == 1);
    CHECK(next->incarnation() == 2);
    CHECK_FALSE(next->zone_for_region(c).populate);  // its entities come from the checkpoint
    zones.push_back(std::make_unique<node_zone>(std::move(next), c));
    zones[1]->tick();
    // Its checkpoint, and the records handed to region 1 meanwhile (waiting on the stream).
    CHECK(zones[1]->node->link().stats().restored - zones[1]->node->stats().restored_from_records.load() ==
          at_kill.size());
    CHECK(zones[1]->node->stats().restore_skipped.load() == 0);
    for (const global_id g : at_kill) CHECK(zones[1]->node->link().local_of(g) != null_entity);
    tick_all(3s);
    drain(zones, 20s);
    // Every entity of the world is there once: none lost with the killed zone, none made up.
    CHECK(owned_once(zones, ns.url, "ckpt").size() == total);
  }

  TEST_CASE("a zone killed with its players: a client back with its resume token gets its entity, the others go") {
    nats_server ns;
    REQUIRE_FALSE(ns.url.empty());
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    auto c = small_world(seed);
    c.npc_count = 50;
    const auto tweak = [](node_options& o) {
      fast_nats(o);
      o.resume_s = 2;
      o.linger_s = 2;
    };
    zone_list zones = join_zones(ns.url, "resume", 2, 1, c, 2, tweak);
    node_zone& v = *zones[1];
    REQUIRE(v.node->region() == 1);
    // Four players in region 1 (x 200..400), walking: three welcomed (each told a resume token, as
    // zone_server's welcome asks for it), one never (no client: left out of the checkpoint).
    std::vector<entity_id> players;
    std::vector<std::string> tokens;
    std::mt19937_64 rng(seed);
    for (int k = 0; k < 4; ++k) {
      const entity_id p =
          v.world->spawn_player({260.0f + static_cast<float>(rng() % 80), 100.0f + static_cast<float>(rng() % 200), 0});
      REQUIRE(p != null_entity);
      v.world->set_intent(p, {0, k % 2 ? 1.0f : -1.0f, 0});
      players.push_back(p);
      if (k < 3) {
        tokens.push_back(v.node->resume_token(p, ""));
        CHECK(tokens.back().size() == 16);
        CHECK(token_region(tokens.back()) == std::optional<std::uint32_t>(1));
      }
    }
    CHECK(tokens[0] != tokens[1]);
    v.tick();
    std::vector<global_id> gids;
    for (const entity_id p : players) gids.push_back(v.node->link().gid_of(p));
    for (const global_id g : gids) CHECK(g != 0);
    run_zones(zones, 500ms);
    // The victim's checkpoint written with the players where they are then; killed right after.
    checkpoint_now(v);
    std::vector<vec3> at_checkpoint;
    for (const entity_id p : players) at_checkpoint.push_back(v.world->store().get(p)->position);
    for (const entity_id p : players) REQUIRE(v.node->owns(p));  // none walked out of the region
    v.node->crash_for_testing();
    zones.pop_back();
    run_zones(zones, 1500ms);
    auto next = join_after_kill(zones, ns.url, "resume", c, tweak);
    REQUIRE(next->region() == 1);
    zones.push_back(std::make_unique<node_zone>(std::move(next), c));
    node_zone& n = *zones[1];
    n.tick();  // the checkpoint restored
    CHECK(n.node->stats().players_restored.load() == 3);
    CHECK(n.node->link().local_of(gids[3]) == null_entity);  // no client, no token: not kept
    // A token nobody was told waits (a handoff's record may still be on its way), then is refused.
    entity_id got = null_entity;
    CHECK(n.node->claim_token("0002123456789abc", *n.world, got) == zone_extension::claim::wait);
    // Clients 0 and 1 come back: each gets its own entity (same world-wide id), standing where the
    // checkpoint had it (it waits without moving), and keeps its token for the next loss.
    for (int k = 0; k < 2; ++k) {
      CAPTURE(k);
      entity_id e = null_entity;
      REQUIRE(n.node->claim_token(tokens[k], *n.world, e) == zone_extension::claim::ready);
      CHECK(n.node->link().gid_of(e) == gids[k]);
      CHECK(n.world->behaviour_of(e) == behaviour::player);
      const auto pos = n.world->store().get(e)->position;
      CHECK(std::abs(pos.x - at_checkpoint[k].x) < 0.01f);
      CHECK(std::abs(pos.y - at_checkpoint[k].y) < 0.01f);
      CHECK(n.world->behaviour_state_of(e)->intent == vec3{0, 0, 0});
      CHECK(n.node->resume_token(e, tokens[k]) == tokens[k]);
      entity_id again = null_entity;  // a token claims once
      CHECK(n.node->claim_token(tokens[k], *n.world, again) != zone_extension::claim::ready);
    }
    CHECK(n.node->stats().players_resumed.load() == 2);
    // Client 2 never comes: its entity is removed after the resume window (2 s here).
    const entity_id waiting = n.node->link().local_of(gids[2]);
    CHECK(waiting != null_entity);
    run_zones(zones, 2500ms);
    CHECK(n.node->link().local_of(gids[2]) == null_entity);
    CHECK(n.node->stats().players_abandoned.load() == 1);
    entity_id late = null_entity;
    CHECK(n.node->claim_token(tokens[2], *n.world, late) == zone_extension::claim::wait);
    CHECK(n.node->link().local_of(gids[0]) != null_entity);  // the resumed ones play on
    // Client 0's connection ends with its zone alive (--world-linger 2): its entity stands and
    // waits; back with its token, it gets it again; gone again and not back, it is removed.
    const entity_id e0 = n.node->link().local_of(gids[0]);
    n.world->set_intent(e0, {1, 0, 0});
    REQUIRE(n.node->keep_for_resume(e0, *n.world));
    CHECK(n.world->behaviour_state_of(e0)->intent == vec3{0, 0, 0});
    for (const entity_id id : n.world->store().ids()) {  // an NPC is no client's: never kept
      if (n.world->behaviour_of(id) != behaviour::player) {
        CHECK_FALSE(n.node->keep_for_resume(id, *n.world));
        break;
      }
    }
    run_zones(zones, 500ms);
    entity_id back = null_entity;
    REQUIRE(n.node->claim_token(tokens[0], *n.world, back) == zone_extension::claim::ready);
    CHECK(back == e0);
    CHECK(n.node->stats().players_back_after_linger.load() == 1);
    REQUIRE(n.node->keep_for_resume(e0, *n.world));
    run_zones(zones, 2500ms);
    CHECK(n.node->link().local_of(gids[0]) == null_entity);
    CHECK(n.node->stats().players_lingered.load() == 2);
    CHECK(n.node->stats().players_abandoned.load() == 2);
  }

  TEST_CASE("a zone killed seconds after its checkpoint: what it adopted since comes back from the handoff records") {
    nats_server ns;
    REQUIRE_FALSE(ns.url.empty());
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    const auto c = small_world(seed);
    // Checkpoints a minute apart: the one forced below is the last.
    const auto tweak = [](node_options& o) {
      fast_nats(o);
      o.checkpoint_s = 60;
    };
    zone_list zones = join_zones(ns.url, "cklate", 2, 1, c, 2, tweak);
    const std::size_t total = entities_of(zones);
    run_zones(zones, 1500ms);
    nats_node& victim = *zones[1]->node;
    checkpoint_now(*zones[1], [&] { zones[0]->tick(); });
    // Three more seconds: zone 1 adopts entities its checkpoint does not hold (and hands some on).
    const std::uint64_t adopted_before = victim.stats().handoffs_applied.load();
    run_zones(zones, 3s);
    REQUIRE(victim.stats().handoffs_applied.load() > adopted_before);
    for (int k = 0; k < 10; ++k) {  // its sender publishes what it decided; then it is killed
      zones[0]->tick();
      std::this_thread::sleep_for(33ms);
    }
    victim.crash_for_testing();
    zones.pop_back();
    run_zones(zones, 1500ms);
    auto next = join_after_kill(zones, ns.url, "cklate", c, tweak);
    zones.push_back(std::make_unique<node_zone>(std::move(next), c));
    zones[1]->tick();
    CHECK(zones[1]->node->stats().restored_from_records.load() > 0);
    run_zones(zones, 2s);
    drain(zones, 20s);
    // Every entity of the world once: the checkpoint's, and those adopted after it from their records.
    CHECK(owned_once(zones, ns.url, "cklate").size() == total);
  }

  TEST_CASE(
      "a standby waits while every region is held, takes a killed zone's region at once; a zone that fails to start "
      "leaves the checkpoint") {
    nats_server ns;
    REQUIRE_FALSE(ns.url.empty());
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    const auto c = small_world(seed);
    zone_list zones = join_zones(ns.url, "standby", 2, 1, c, 2, fast_nats);
    const std::size_t total = entities_of(zones);
    // A standby told to stop gives up with the reason, without a region.
    {
      int polls = 0;
      auto o = options(ns.url, "standby", 2, 1, c);
      fast_nats(o);
      o.claim_wait_s = std::numeric_limits<double>::infinity();
      o.keep_waiting = [&] { return ++polls < 4; };
      std::string err;
      CHECK(nats_node::join(o, c, &err) == nullptr);
      CHECK(polls == 4);
      CHECK(err.find("every region of the layout (2) is taken") != std::string::npos);
    }
    // Two standbys, each in a thread of its own, taking the census (the zones answer as they tick
    // here).
    using joined = std::pair<std::unique_ptr<nats_node>, std::string>;
    std::array<std::atomic<bool>, 2> stop{false, false};
    std::array<std::atomic<int>, 2> polls{0, 0};
    std::array<std::future<joined>, 2> standby;
    // Told to stop before the futures wait for them (a failed REQUIRE must not hang the test).
    struct stop_guard {
      std::array<std::atomic<bool>, 2>& flags;
      ~stop_guard() {
        for (auto& f : flags) f = true;
      }
    } guard{stop};
    for (int k = 0; k < 2; ++k) {
      standby[k] = std::async(std::launch::async, [&, k] {
        auto o = options(ns.url, "standby", 2, 1, c);
        fast_nats(o);
        o.join_census_s = 0.3;
        o.claim_wait_s = std::numeric_limits<double>::infinity();
        o.keep_waiting = [&, k] {
          ++polls[k];
          return !stop[k].load();
        };
        std::string err;
        auto n = nats_node::join(o, c, &err);
        return joined{std::move(n), err};
      });
    }
    const auto ready = [&](int k) { return standby[k].valid() && standby[k].wait_for(0ms) == std::future_status::ready; };
    // The first of them to hold a region, within `limit` (the zones ticking meanwhile); -1 if none.
    const auto first_claim = [&](std::chrono::seconds limit) {
      for (const auto until = std::chrono::steady_clock::now() + limit; std::chrono::steady_clock::now() < until;) {
        for (int k = 0; k < 2; ++k) {
          if (ready(k)) return k;
        }
        run_zones(zones, 33ms);
      }
      return -1;
    };
    run_zones(zones, 3s);  // every region held: they wait, polling the leases
    CHECK(handoffs_sent(zones) > 0);
    for (int k = 0; k < 2; ++k) {
      REQUIRE_FALSE(ready(k));
      CHECK(polls[k].load() >= 6);
    }
    nats_node& victim = *zones[1]->node;
    REQUIRE(victim.stats().checkpoints_written.load() > 0);
    victim.crash_for_testing();
    zones.pop_back();
    const auto killed = std::chrono::steady_clock::now();
    // The region's lease lapses (1 s) and one standby claims it: the next incarnation, restored.
    const int winner = first_claim(10s);
    REQUIRE(winner >= 0);
    const int other = 1 - winner;
    auto [next, err] = standby[winner].get();
    REQUIRE_MESSAGE(next != nullptr, err);
    const double took = std::chrono::duration<double>(std::chrono::steady_clock::now() - killed).count();
    CAPTURE(took);
    CHECK(took < 1.0 + 1.5);  // the lease's TTL, a poll and the census
    CHECK(next->region() == 1);
    CHECK(next->incarnation() == 2);
    CHECK_FALSE(next->zone_for_region(c).populate);
    // The other still waits: the region is held again.
    run_zones(zones, 1500ms);
    CHECK_FALSE(ready(other));
    // The winner's server fails to start (a port in use): it gives the region up before serving
    // it, and leaves the checkpoint to the next zone (given up with it, the killed zone's entities
    // would be lost and a new population made). The other standby takes the region then.
    next.reset();
    REQUIRE(first_claim(5s) == other);
    auto [again, err2] = standby[other].get();
    REQUIRE_MESSAGE(again != nullptr, err2);
    next = std::move(again);
    CHECK(next->region() == 1);
    CHECK(next->incarnation() == 3);
    CHECK_FALSE(next->zone_for_region(c).populate);
    zones.push_back(std::make_unique<node_zone>(std::move(next), c));
    zones[1]->tick();
    CHECK(zones[1]->node->link().stats().restored > 0);
    run_zones(zones, 3s);
    drain(zones, 20s);
    // Every entity of the world is there once (the checkpoint and the records read again).
    CHECK(owned_once(zones, ns.url, "standby").size() == total);
    // The leases name where each region is served now, and by which claim: region 1 by the
    // standby (incarnation 3, at the port it started with).
    std::string lerr;
    const auto leases = read_leases(ns.url, "standby", &lerr);
    REQUIRE_MESSAGE(leases.has_value(), lerr);
    REQUIRE(leases->size() == 2);
    CHECK(leases->at(0).incarnation == 1);
    CHECK(leases->at(0).port == 7000);
    CHECK(leases->at(1).incarnation == 3);
    CHECK(leases->at(1).port == 7001);
    CHECK(leases->at(1).host == "127.0.0.1");
    const auto census = census_of(zones, ns.url, "standby", &lerr);
    REQUIRE_MESSAGE(census.has_value(), lerr);
    CHECK(check_leases(*census, *leases).problems.empty());
  }

  TEST_CASE(
      "a zone that stops: the region's next zone starts a new population and gets only the records left unapplied") {
    nats_server ns;
    REQUIRE_FALSE(ns.url.empty());
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    const auto c = small_world(seed);
    zone_list zones = join_zones(ns.url, "ckstop", 2, 1, c, 2);
    const auto tick_all = [&](std::chrono::milliseconds d) { run_zones(zones, d); };
    tick_all(3s);
    drain(zones, 20s);
    CHECK(zones[1]->node->stats().handoffs_applied.load() > 0);
    const std::uint64_t sent_before = zones[0]->node->stats().handoffs_sent.load();  // all to region 1
    REQUIRE(zones[1]->node->stats().checkpoints_written.load() > 0);
    zones.pop_back();  // leave(): the lease and the checkpoint go, and the entities it owned
    tick_all(1s);
    zone_list again = join_zones(ns.url, "ckstop", 2, 1, c, 1);
    CHECK(again[0]->node->region() == 1);
    CHECK(again[0]->cfg.populate);
    CHECK(again[0]->world->store().size() == static_cast<std::size_t>(c.npc_count));
    zones.push_back(std::move(again[0]));
    zones[1]->tick();
    CHECK(zones[1]->node->link().stats().restored == 0);
    // None of the records the old zone applied comes again (its consumer kept its acks): an entity
    // it adopted and handed back would be owned twice.
    CHECK(zones[1]->node->stats().handoffs_applied.load() <=
          zones[0]->node->stats().handoffs_sent.load() - sent_before);
    tick_all(2s);
    drain(zones, 20s);
    std::string err;
    (void)owned_once(zones, ns.url, "ckstop", false);
  }
}
