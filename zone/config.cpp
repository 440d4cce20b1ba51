// zone_config from the command line and an optional config file (Boost.Program_options).
#include <algorithm>
#include <thread>
#include <boost/program_options.hpp>
#include <cctype>
#include <cmath>
#include <fstream>
#include <sstream>

#include "net/os_limits.h"
#include "zone/zone_config.h"
#include "zone/replicator.h"

namespace zone {

namespace po = boost::program_options;

namespace {
/// A float default as --help shows it: 6 significant digits, so 0.45f reads 0.45, not 0.449999988.
std::string shown(float v) {
  std::ostringstream out;
  out << v;
  return out.str();
}
}  // namespace

std::optional<std::string> validate(const zone_config& c) {
  const auto bad = [](const std::string& what) { return std::optional<std::string>(what); };
  const float lo[3] = {c.world.lo.x, c.world.lo.y, c.world.lo.z};
  const float hi[3] = {c.world.hi.x, c.world.hi.y, c.world.hi.z};
  for (int d = 0; d < 3; ++d) {
    if (!std::isfinite(lo[d]) || !std::isfinite(hi[d]) || !(hi[d] > lo[d])) return bad("world bounds must be finite with hi > lo");
  }
  if (!(c.tick_rate_hz > 0 && c.tick_rate_hz <= 1000)) return bad("tick-rate must be in (0, 1000]");
  if (!(c.hysteresis >= 0 && std::isfinite(c.hysteresis))) return bad("hysteresis must be >= 0");
  for (const float a : c.aoi_tier) {
    if (!(a >= 0 && std::isfinite(a))) return bad("AOI tiers must be >= 0");
  }
  if (!(c.player_aoi >= 0 && std::isfinite(c.player_aoi))) return bad("player-aoi must be >= 0");
  if (c.viewer_enabled && !c.metrics_enabled) return bad("viewer needs the HTTP endpoint of /metrics (--metrics 1)");
  if (!(c.viewer_hz > 0 && c.viewer_hz <= 1000)) return bad("viewer-hz must be in (0, 1000]");
  if (c.viewer_fill != "wait" && c.viewer_fill != "after") return bad("viewer-fill must be wait or after");
  if (c.max_viewers < 1 || c.max_viewers > 64) return bad("max-viewers must be in [1, 64]");
  const float shares[4] = {c.share_wander, c.share_patrol, c.share_town, c.share_chase};
  float sum = 0;
  for (const float s : shares) {
    if (!(s >= 0 && std::isfinite(s))) return bad("behaviour shares must be >= 0");
    sum += s;
  }
  if (c.npc_count > 0 && !(sum > 0)) return bad("behaviour shares must not all be 0 when there are NPCs");
  // The players (max_clients) come on top at run time: a full store refuses them (server_full).
  if (c.npc_count > max_entities || c.npc_count + c.boss_count > max_entities) {
    return bad("npcs + bosses must be at most " + std::to_string(max_entities) + " (the most entities one zone holds: " +
               std::to_string(entity_index_bits) + " slot bits of a 32-bit handle); got " + std::to_string(c.npc_count) +
               " + " + std::to_string(c.boss_count));
  }
  if (!(c.npc_speed >= 0 && c.player_speed >= 0 && std::isfinite(c.npc_speed) && std::isfinite(c.player_speed))) {
    return bad("speeds must be >= 0");
  }
  if (!(c.boss_footprint >= 0 && std::isfinite(c.boss_footprint))) return bad("boss-footprint must be >= 0");
  if (c.io_threads == 0) return bad("io-threads must be >= 1");
  if (c.io_nice < 0 || c.io_nice > 19) return bad("io-nice must be 0 .. 19");
  if (c.viewer_nice < 0 || c.viewer_nice > 19) return bad("viewer-nice must be 0 .. 19");
  for (const auto& [name, list] : {std::pair{"worker-cpus", &c.worker_cpus}, std::pair{"io-cpus", &c.io_cpus}}) {
    std::string why;
    const auto cpus = net::parse_cpu_list(*list, &why);
    if (!cpus) return bad(std::string(name) + ": " + why);
    if (auto err = net::check_cpus_allowed(*cpus)) return bad(std::string(name) + " " + *list + ": " + *err);
  }
  static const char* batchings[] = {"auto", "io_uring", "sendmsg"};  // net::parse_write_batching
  if (std::find(std::begin(batchings), std::end(batchings), c.write_batching) == std::end(batchings)) {
    return bad("write-batching must be auto, io_uring or sendmsg");
  }
  if (c.write_slice < 1 || c.write_slice > 1000000) return bad("write-slice must be 1 .. 1000000");
  if (c.max_frame_bytes < 64) return bad("max-frame-bytes must be >= 64");
  if (!(c.client_stall_s >= 0 && c.client_stall_s <= 3600)) return bad("client-stall must be 0 .. 3600 seconds");
  if (c.socket_send_buffer > (std::size_t{1} << 30)) return bad("socket-send-buffer must be <= 1 GiB");
  if (c.client_byte_budget < 256) return bad("client-byte-budget must be >= 256");
  if (!(c.inputs_per_second > 0)) return bad("inputs-per-second must be > 0");
  if (!(c.pings_per_second > 0)) return bad("pings-per-second must be > 0");
  if (!(c.hello_timeout_s > 0 && c.hello_timeout_s <= 3600)) return bad("hello-timeout must be in (0, 3600] seconds");
  if (!(c.idle_timeout_s > 0 && c.idle_timeout_s <= 86400)) return bad("idle-timeout must be in (0, 86400] seconds");
  if (c.max_pending == 0 || c.max_pending_per_address == 0) return bad("max-pending and max-pending-per-address must be >= 1");
  if (!(c.connect_rate >= 0 && std::isfinite(c.connect_rate))) return bad("connect-rate must be >= 0 (0 = no limit)");
  if (!(c.connect_burst >= 1 && std::isfinite(c.connect_burst))) return bad("connect-burst must be >= 1");
  if (!(c.connect_min_session_s >= 0 && c.connect_min_session_s <= 3600)) return bad("connect-min-session must be 0 .. 3600 seconds");
  if (!(c.connect_refusal_hold_s >= 0 && c.connect_refusal_hold_s <= 60)) return bad("connect-refusal-hold must be 0 .. 60 seconds");
  if (c.max_name_bytes == 0 || c.max_name_bytes > 1024) return bad("max-name-bytes must be 1 .. 1024");
  if (!(c.log_summary_s >= 0 && std::isfinite(c.log_summary_s))) return bad("log-summary must be >= 0 seconds");
  if (c.metrics_max_connections == 0 || c.metrics_max_connections > 4096) return bad("metrics-max-connections must be 1 .. 4096");
  if (!(c.teleport_cooldown_s >= 0 && std::isfinite(c.teleport_cooldown_s))) return bad("teleport-cooldown must be >= 0");
  if (!(c.visibility_cooldown_s >= 0 && std::isfinite(c.visibility_cooldown_s))) return bad("visibility-cooldown must be >= 0");
  if (c.player_teams > 2) return bad("player-teams must be 0, 1 or 2");
  if (!(c.spawn_radius >= 0 && std::isfinite(c.spawn_radius))) return bad("spawn-radius must be >= 0");
  if (!(c.update_near >= 0 && c.update_mid >= c.update_near && std::isfinite(c.update_mid))) {
    return bad("update-near and update-mid must be >= 0 with update-mid >= update-near");
  }
  if (c.update_mid_period == 0 || c.update_far_period == 0) return bad("update periods must be >= 1");
  if (c.client_send_every == 0) return bad("client-send-every must be >= 1");
  // The digest goes in the frames of ticks that are multiples of digest-every: with staggered
  // clients some would never get one.
  if (c.client_send_every > 1 && c.digest_every > 1) return bad("client-send-every > 1 needs digest-every 0 or 1");
  if (c.host_grid != "auto" && c.host_grid != "on" && c.host_grid != "off") return bad("host-grid must be auto, on or off");
  static const char* finders[] = {"auto", "cpu", "gpu", "pbig", "lbvh", "brute"};
  if (std::find(std::begin(finders), std::end(finders), c.finder) == std::end(finders)) {
    return bad("finder must be auto, cpu, gpu (= pbig), pbig, lbvh or brute");
  }
  if (c.world_cols == 0 || c.world_rows == 0 || c.world_cols > 64 || c.world_rows > 64) {
    return bad("world-grid must be 1x1 .. 64x64");
  }
  if (!c.world_name.empty()) {
    if (c.world_name.size() > 64 || !std::all_of(c.world_name.begin(), c.world_name.end(), [](char ch) {
          return std::isalnum(static_cast<unsigned char>(ch)) || ch == '-' || ch == '_';
        })) {
      return bad("world must be 1-64 letters, digits, - or _");
    }
    if (c.nats_url.empty()) return bad("--world needs --nats URL");
  }
  if (c.world_name.empty() && !c.nats_url.empty()) return bad("--nats needs --world NAME");
  if (c.world_name.empty() && c.world_standby) return bad("--world-standby needs --world NAME");
  if (!(c.world_lease_ttl_s >= 0.2 && c.world_lease_ttl_s <= 600)) return bad("world-lease-ttl must be 0.2 .. 600 s");
  if (!(c.world_resume_s >= 0 && c.world_resume_s <= 3600)) return bad("world-resume-window must be 0 .. 3600 s");
  if (!(c.linger_s >= 0 && c.linger_s <= 3600)) return bad("linger must be 0 .. 3600 s");
  if (!(c.world_nats_timeout_s >= 0.05 && c.world_nats_timeout_s <= 60))
    return bad("world-nats-timeout must be 0.05 .. 60 s");
  if (c.worker_spin_us < -1 || c.worker_spin_us > 1000000) return bad("worker-spin-us must be -1 (auto) or 0 .. 1000000");
  static const char* interests[] = {"auto", "gpu", "host"};
  if (std::find(std::begin(interests), std::end(interests), c.interest) == std::end(interests)) {
    return bad("interest must be auto, gpu or host");
  }
  static const char* faults[] = {"", "drop", "extra", "stealth", "freeze", "class", "gpu-interest", "gpu-replication", "gpu-lost"};
  if (std::find(std::begin(faults), std::end(faults), c.test_fault) == std::end(faults)) {
    return bad("test-fault must be drop, extra, stealth, freeze, class, gpu-interest, gpu-replication or gpu-lost");
  }
  const bool gpu_fault = c.test_fault.rfind("gpu-", 0) == 0;
  if (!c.test_fault.empty() && !gpu_fault && !c.oracle) return bad("test-fault needs --oracle (it exists to prove the oracle)");
  if (c.oracle_subscribers < 1 || c.oracle_subscribers > 64) return bad("oracle-subscribers must be 1 to 64");
  static const char* replicates[] = {"auto", "gpu", "cpu"};
  if (std::find(std::begin(replicates), std::end(replicates), c.replicate) == std::end(replicates)) {
    return bad("replicate must be auto, gpu or cpu");
  }
  if (c.interest == "gpu" && c.max_visible != 0) return bad("interest gpu does not support max-visible (use auto or host)");
  static const char* levels[] = {"trace", "debug", "info", "warn", "error", "critical", "off"};
  if (std::find(std::begin(levels), std::end(levels), c.log_level) == std::end(levels)) {
    return bad("log-level must be one of trace, debug, info, warn, error, critical, off");
  }
  return std::nullopt;
}

replication_options replication_options_of(const zone_config& c) {
  replication_options o;
  o.world = c.world;
  o.byte_budget = c.client_byte_budget;
  o.near_distance = c.update_near;
  o.mid_distance = c.update_mid;
  o.mid_period = c.update_mid_period;
  o.far_period = c.update_far_period;
  o.send_digest = c.digest_every > 0;
  o.digest_period = std::max<std::uint32_t>(1, c.digest_every);
  return o;
}

unsigned worker_spin(const zone_config& c) {
  // Auto (-1) was 1000 us on 8+ hardware threads until issue 22: the spin did not pay there
  // either (docs/zone-benchmarks.md, "The pool's idle spin").
  return c.worker_spin_us > 0 ? static_cast<unsigned>(c.worker_spin_us) : 0u;
}

config_result parse_config(int argc, const char* const* argv) {
  zone_config c;
  float world_x = c.world.hi.x, world_y = c.world.hi.y, world_z = c.world.hi.z;
  std::string config_file;
  unsigned port = c.port, metrics_port = c.metrics_port, oracle_port = c.oracle_port;

  po::options_description general("General");
  general.add_options()                                                                   //
      ("help,h", "print this help and exit")                                              //
      ("config", po::value(&config_file), "read options from an INI-style file (name = value)")  //
      ("log-level", po::value(&c.log_level)->default_value(c.log_level), "trace, debug, info, warn, error, critical, off (per-session joins and leaves are at debug)")  //
      ("log-summary", po::value(&c.log_summary_s)->default_value(c.log_summary_s), "seconds between info lines summing up joins, leaves and refused connections (0 = none)")  //
      ("tick-csv", po::value(&c.tick_csv), "write one CSV line per tick to this file: tick, seconds since start, clients, frames, bytes, the phases' ms, the viewer snapshot's fill, the GPU interest engine's device wait, the choice of the tick's clients and the GPU replication engine's share (docs/operating.md)");
  po::options_description world("World and tick");
  world.add_options()                                                                                  //
      ("world-x", po::value(&world_x)->default_value(world_x), "world size along x (m), from 0")        //
      ("world-y", po::value(&world_y)->default_value(world_y), "world size along y (m), from 0")        //
      ("world-z", po::value(&world_z)->default_value(world_z), "world height (m), from 0")              //
      ("tick-rate", po::value(&c.tick_rate_hz)->default_value(c.tick_rate_hz), "ticks per second")      //
      ("seed", po::value(&c.seed)->default_value(c.seed), "seed of the NPC population and behaviours")  //
      ("threads", po::value(&c.worker_threads)->default_value(c.worker_threads), "worker threads (0 = all cores)")  //
      ("worker-spin-us", po::value(&c.worker_spin_us)->default_value(c.worker_spin_us), "microseconds an idle worker spins before it sleeps, and how early the loop wakes the workers before a tick (0 = no spin, the default: it cost more CPU than it saved tick time; -1 = auto, the same)");
  po::options_description interest("Interest");
  interest.add_options()                                                                                     //
      ("finder", po::value(&c.finder)->default_value(c.finder), "pair finder: auto (chosen per tick from the box statistics: GPU when usable, else CPU), cpu, gpu (= pbig), pbig, lbvh, brute")  //
      ("interest", po::value(&c.interest)->default_value(c.interest), "where the interest step runs: auto (the GPU visibility engine when a device is usable and max-visible is 0, else host), gpu, host (the pair finder and the host diff)")  //
      ("host-grid", po::value(&c.host_grid)->default_value(c.host_grid), "how the host path finds candidates: on (a grid of the presence boxes, observer by observer), off (the pair finder), auto (on when the finder is the CPU grid finder: cpu, or auto without a device); the same output")  //
      ("replicate", po::value(&c.replicate)->default_value(c.replicate), "where replication's per-client decisions run: auto (the GPU replication engine when a device is usable, else cpu), gpu, cpu; the frames are the same")  //
      ("host-views", po::value(&c.host_views)->default_value(c.host_views), "with interest and replication both on the GPU: 1 = copy the players' visible sets back every tick, so a GPU failing mid-run loses no client's history; 0 = read them on the device only (a little faster; a lost device then costs clients mismatches)")  //
      ("hysteresis", po::value(&c.hysteresis)->default_value(c.hysteresis), "leave margin beyond the AOI (m)")  //
      ("max-visible", po::value(&c.max_visible)->default_value(c.max_visible), "cap per observer (0 = none)")   //
      ("aoi-tiny", po::value(&c.aoi_tier[0])->default_value(c.aoi_tier[0]), "AOI half-extent of tier tiny (m)")  //
      ("aoi-small", po::value(&c.aoi_tier[1])->default_value(c.aoi_tier[1]), "AOI half-extent of tier small (m)")  //
      ("aoi-medium", po::value(&c.aoi_tier[2])->default_value(c.aoi_tier[2]), "AOI half-extent of tier medium (m)")  //
      ("aoi-large", po::value(&c.aoi_tier[3])->default_value(c.aoi_tier[3]), "AOI half-extent of tier large (m)")  //
      ("aoi-gigantic", po::value(&c.aoi_tier[4])->default_value(c.aoi_tier[4]), "AOI half-extent of tier gigantic (m)")  //
      ("player-aoi", po::value(&c.player_aoi)->default_value(c.player_aoi), "AOI half-extent of players (m)");
  po::options_description npcs("NPCs");
  npcs.add_options()                                                                                        //
      ("npcs", po::value(&c.npc_count)->default_value(c.npc_count), "number of NPCs")                       //
      ("share-wander", po::value(&c.share_wander)->default_value(c.share_wander, shown(c.share_wander)), "share of wandering NPCs")  //
      ("share-patrol", po::value(&c.share_patrol)->default_value(c.share_patrol, shown(c.share_patrol)), "share of patrolling NPCs")  //
      ("share-town", po::value(&c.share_town)->default_value(c.share_town, shown(c.share_town)), "share of NPCs gathering in towns")  //
      ("share-chase", po::value(&c.share_chase)->default_value(c.share_chase, shown(c.share_chase)), "share of NPCs chasing players")  //
      ("bosses", po::value(&c.boss_count)->default_value(c.boss_count), "number of world bosses")            //
      ("towns", po::value(&c.town_count)->default_value(c.town_count), "number of towns (hotspots; 0 = one per 2,000 NPCs)")         //
      ("npc-speed", po::value(&c.npc_speed)->default_value(c.npc_speed), "NPC speed (m/s)")                  //
      ("player-speed", po::value(&c.player_speed)->default_value(c.player_speed), "fastest a player moves (m/s)")  //
      ("boss-footprint", po::value(&c.boss_footprint)->default_value(c.boss_footprint), "boss presence half-extent (m)");
  po::options_description net("Network and limits");
  net.add_options()                                                                                 //
      ("listen", po::value(&c.listen_address)->default_value(c.listen_address), "listen address")   //
      ("port", po::value(&port)->default_value(port), "TCP port for clients")                       //
      ("io-threads", po::value(&c.io_threads)->default_value(c.io_threads), "network I/O threads")  //
      ("max-clients", po::value(&c.max_clients)->default_value(c.max_clients),
       "player slots: sessions past their hello (a hello over it: error server_full)")  //
      ("hello-timeout", po::value(&c.hello_timeout_s)->default_value(c.hello_timeout_s),
       "seconds from accept by which a connection must have completed its hello, whatever it sends (error timeout)")  //
      ("max-pending", po::value(&c.max_pending)->default_value(c.max_pending),
       "connections without a hello yet, in total, apart from the player slots; at the cap the oldest is closed for the new one")  //
      ("max-pending-per-address", po::value(&c.max_pending_per_address)->default_value(c.max_pending_per_address),
       "connections without a hello yet from one source address; at the cap the address's oldest is closed for the new one (raise it for a bot swarm on one host)")  //
      ("connect-rate", po::value(&c.connect_rate)->default_value(c.connect_rate),
       "reconnect churn per source address: connections a second that may end within connect-min-session of their accept (never said hello, refused, cut off, or left soon after joining); an address past it is refused at accept with error rate_limited until its bucket refills (connections that stay cost nothing: a bot swarm ramping from one host is not limited); 0 = no limit")  //
      ("connect-burst", po::value(&c.connect_burst)->default_value(c.connect_burst),
       "reconnect churn per source address: how many such short connections an address may make at once before connect-rate applies")  //
      ("connect-min-session", po::value(&c.connect_min_session_s)->default_value(c.connect_min_session_s),
       "seconds: a connection that ends sooner after its accept counts against its address's connect-rate")  //
      ("connect-refusal-hold", po::value(&c.connect_refusal_hold_s)->default_value(c.connect_refusal_hold_s),
       "seconds a connection refused for connect-rate is held unread before its error rate_limited and reset, so a client that waits for its answer retries once per hold rather than as fast as the server refuses (at most 64 held per address, 512 in all; 0 = answered at once)")  //
      ("linger", po::value(&c.linger_s)->default_value(c.linger_s),
       "seconds a player whose connection was lost (its client said no leave) is kept, standing, for its client to come back with the resume token its welcome told (a hello with it gets the same entity; 0 = removed at once, and a single zone tells no token; at most --max-clients wait)")  //
      ("max-name-bytes", po::value(&c.max_name_bytes)->default_value(c.max_name_bytes),
       "longest player name; names are printable ASCII without leading or trailing spaces (error bad_hello)")  //
      ("idle-timeout", po::value(&c.idle_timeout_s)->default_value(c.idle_timeout_s),
       "seconds a player may send no complete frame before it is closed (clients ping)")                             //
      ("max-frame-bytes", po::value(&c.max_frame_bytes)->default_value(c.max_frame_bytes), "largest inbound frame")  //
      ("socket-send-buffer", po::value(&c.socket_send_buffer)->default_value(c.socket_send_buffer),
       "SO_SNDBUF of each client socket in bytes (0 = the system's autotuning); bounds how much stale state the kernel holds for a slow client")  //
      ("direct-writes", po::value(&c.direct_writes)->default_value(c.direct_writes),
       "1: the replication worker that built a frame writes it to the client's socket itself when nothing is queued ahead of it (lower latency, but the sends then lengthen the tick); 0: the I/O threads write every frame")  //
      ("io-nice", po::value(&c.io_nice)->default_value(c.io_nice),
       "nice value of the I/O threads, 0-19 (above 0: lower priority than the tick's workers where they share cores)")  //
      ("worker-cpus", po::value(&c.worker_cpus)->default_value(c.worker_cpus),
       "CPUs of the tick's threads (the worker pool and the tick's own thread) as a CPU list, e.g. 0-5 (empty: not pinned); with --io-cpus on other CPUs no I/O thread preempts a tick's task (docs/operating.md)")  //
      ("io-cpus", po::value(&c.io_cpus)->default_value(c.io_cpus),
       "CPUs of the I/O threads as a CPU list, e.g. 6-9 (empty: not pinned)")  //
      ("write-batching", po::value(&c.write_batching)->default_value(c.write_batching),
       "how the I/O threads write: auto (io_uring where the kernel allows it, else sendmsg), io_uring (or refuse to start), sendmsg (one system call per session write)")  //
      ("write-slice", po::value(&c.write_slice)->default_value(c.write_slice),
       "sessions an I/O thread writes before it reads its clients again: on a busy server a new client's hello waits for one slice of writes, not for every waiting session's")  //
      ("inputs-per-second", po::value(&c.inputs_per_second)->default_value(c.inputs_per_second),
       "input rate limit per client (inputs and teleports; burst half a second's worth); over it inputs are dropped, 200 in a row: error rate_limited")  //
      ("pings-per-second", po::value(&c.pings_per_second)->default_value(c.pings_per_second),
       "ping rate limit per client (burst one second's worth); over it no pong, 200 in a row: error rate_limited")  //
      ("client-byte-budget", po::value(&c.client_byte_budget)->default_value(c.client_byte_budget),
       "bytes per client per tick")  //
      ("client-send-every", po::value(&c.client_send_every)->default_value(c.client_send_every),
       "each client gets a frame every K ticks, clients staggered (1 = every tick; 2 at 30 Hz = 15 frames a second each, half the frames built and sent per tick)")  //
      ("client-stall", po::value(&c.client_stall_s)->default_value(c.client_stall_s, "1"),
       "a client whose backlog stays full, its socket taking not one byte, this many seconds is stalled: its queued state frames are dropped, and once its socket drains it gets a reset of the current state instead of stale frames (0 = off; needs client-max-backlog > 0)")  //
      ("client-max-backlog", po::value(&c.client_max_backlog)->default_value(c.client_max_backlog),
       "a client with this many state frames still unwritten gets no new frame this tick (0 = off: always send; then a full queue drops frames and resyncs)")  //
      ("teleport", po::value(&c.teleport_enabled)->default_value(c.teleport_enabled),
       "players may teleport themselves (0 or 1; an ability the server grants, off by default)")  //
      ("player-fly", po::value(&c.player_fly)->default_value(c.player_fly),
       "players may move vertically (0: a movement intent's z is ignored)")  //
      ("teleport-cooldown", po::value(&c.teleport_cooldown_s)->default_value(c.teleport_cooldown_s),
       "least seconds between two teleports of one player")  //
      ("allow-stealth", po::value(&c.allow_stealth)->default_value(c.allow_stealth),
       "players may choose stealth in hello or set_visibility (0 or 1)")  //
      ("player-teams", po::value(&c.player_teams)->default_value(c.player_teams),
       "teams a player may join: 0 none, 1 red, 2 red and blue (a team sees its stealthed members)")  //
      ("visibility-cooldown", po::value(&c.visibility_cooldown_s)->default_value(c.visibility_cooldown_s),
       "least seconds between two visibility switches (set_visibility) of one player")  //
      ("spawn-radius", po::value(&c.spawn_radius)->default_value(c.spawn_radius),
       "players spawn within this distance of a town (m)")  //
      ("update-near", po::value(&c.update_near)->default_value(c.update_near),
       "updates every tick within this distance (m)")  //
      ("update-mid", po::value(&c.update_mid)->default_value(c.update_mid),
       "updates every update-mid-period ticks within this distance (m)")  //
      ("update-mid-period", po::value(&c.update_mid_period)->default_value(c.update_mid_period),
       "ticks between updates of mid-distance entities")  //
      ("update-far-period", po::value(&c.update_far_period)->default_value(c.update_far_period),
       "ticks between updates of entities beyond update-mid")  //
      ("digest-every", po::value(&c.digest_every)->default_value(c.digest_every),
       "a visible-set digest every K ticks (0 = none)")  //
      ("metrics", po::value(&c.metrics_enabled)->default_value(c.metrics_enabled),
       "serve Prometheus text at /metrics (0 or 1)")                                                               //
      ("metrics-port", po::value(&metrics_port)->default_value(metrics_port), "port of /metrics (0 = ephemeral)")  //
      ("metrics-address", po::value(&c.metrics_address)->default_value(c.metrics_address),
       "address /metrics listens on (loopback by default: it has no authentication; 0.0.0.0 opens it to all)")  //
      ("metrics-max-connections", po::value(&c.metrics_max_connections)->default_value(c.metrics_max_connections),
       "connections /metrics holds at once, apart from the players' (more are closed at accept)");
  std::string world_grid = std::to_string(c.world_cols) + "x" + std::to_string(c.world_rows);
  po::options_description zones("World of zones (docs/world.md; built with libnats)");
  zones.add_options()  //
      ("world", po::value(&c.world_name),
       "join the world of this name (letters, digits, - and _): take a free region of its layout in NATS KV and serve it; without it the server is one zone")  //
      ("nats", po::value(&c.nats_url),
       "NATS server URL of the world (e.g. nats://127.0.0.1:4222); needed with --world")  //
      ("world-grid", po::value(&world_grid)->default_value(world_grid),
       "regions COLSxROWS of a new world's layout (a layout already in KV wins)")  //
      ("world-lease-ttl", po::value(&c.world_lease_ttl_s)->default_value(c.world_lease_ttl_s),
       "seconds the region's lease lasts after this zone's last renewal (renewed every quarter of it); a restarted zone waits this long for its predecessor's")  //
      ("world-nats-timeout", po::value(&c.world_nats_timeout_s)->default_value(c.world_nats_timeout_s),
       "seconds a connect, or a KV or JetStream request, waits for NATS before the zone counts NATS unreachable")  //
      ("world-capacity", po::value(&c.world_capacity)->default_value(c.world_capacity),
       "most entities this zone owns (0 = its store's capacity); while it is full its neighbours keep the entities that would cross into it")  //
      ("world-checkpoint", po::value(&c.world_checkpoint_s)->default_value(c.world_checkpoint_s),
       "seconds between checkpoints of this zone's entities in JetStream (0 = none); a zone that claims a region restores its last checkpoint, so a killed zone's entities come back")  //
      ("world-resume-window", po::value(&c.world_resume_s)->default_value(c.world_resume_s),
       "seconds a player restored from a checkpoint (its zone was lost) waits for its client to come back with its resume token before it is removed")  //
      ("world-standby", po::bool_switch(&c.world_standby),
       "a hot standby: while every region is held, wait (listening nowhere) for one whose lease lapses, as long as it takes, then serve it from its checkpoint; without it a zone gives up after 20 s");
  po::options_description viewer("Live viewer (docs/viewer.md)");
  viewer.add_options()  //
      ("viewer", po::value(&c.viewer_enabled)->default_value(c.viewer_enabled),
       "serve the live viewer at /viewer beside /metrics (0 or 1; needs --metrics 1)")  //
      ("viewer-remote", po::value(&c.viewer_remote)->default_value(c.viewer_remote),
       "serve the viewer to peers that are not on a loopback address too (0 or 1)")  //
      ("max-viewers", po::value(&c.max_viewers)->default_value(c.max_viewers),
       "viewer pages at once (more are refused)")  //
      ("viewer-hz", po::value(&c.viewer_hz)->default_value(c.viewer_hz),
       "snapshots a second sent to viewer pages (at most the tick rate)")  //
      ("viewer-nice", po::value(&c.viewer_nice)->default_value(c.viewer_nice),
       "nice value of the viewer's thread, 0-19 (it encodes and writes every page's frames; 19: the tick's threads take a shared core back at once)")  //
      ("viewer-idle", po::value(&c.viewer_idle)->default_value(c.viewer_idle),
       "the viewer's thread at SCHED_IDLE (0 or 1): it runs only on cores the tick's threads leave free; where the OS refuses, the nice value alone (logged once)")  //
      ("viewer-fill", po::value(&c.viewer_fill)->default_value(c.viewer_fill),
       "where a due snapshot's entity columns are copied: after (a thread of its own after the tick; the next tick waits for it if it is not done) or wait (in the GPU interest engine's device wait, over the worker pool; elsewhere in the tick)");
  po::options_description correctness("Correctness (docs/bots.md)");
  correctness.add_options()  //
      ("oracle", po::bool_switch(&c.oracle), "publish every tick's ground truth (entities, boxes, classes) on a loopback stream for an independent oracle (bot-swarm --oracle); off by default, and costs nothing when off")  //
      ("oracle-port", po::value(&oracle_port)->default_value(oracle_port), "loopback port of the ground-truth stream (0 = ephemeral; the welcome tells clients)")  //
      ("oracle-subscribers", po::value(&c.oracle_subscribers)->default_value(c.oracle_subscribers), "truth-stream subscribers served at once, 1-64 (every oracle is one: in a world every swarm reads every zone, so a world of N zones needs N); one more is refused with a message naming this option")  //
      ("test-fault", po::value(&c.test_fault)->default_value(c.test_fault), "TESTING ONLY: break one client's view on purpose to prove the oracle: drop, extra, stealth, freeze or class (needs --oracle); or make a GPU engine fail mid-run: gpu-interest or gpu-replication (the engine reports a CUDA error), gpu-lost (a kernel traps: a real, sticky device fault)")  //
      ("test-fault-tick", po::value(&c.test_fault_tick)->default_value(c.test_fault_tick), "TESTING ONLY: the world tick from which --test-fault acts (for gpu-*: the tick whose step fails)");
  po::options_description all("zone-server options");
  all.add(general).add(world).add(interest).add(npcs).add(net).add(correctness).add(viewer).add(zones);

  config_result r;
  try {
    po::variables_map vm;
    po::store(po::parse_command_line(argc, argv, all), vm);
    if (vm.count("help")) {
      std::ostringstream out;
      out << "Usage: zone-server [options]\n" << all;
      r.message = out.str();
      r.help = true;
      return r;
    }
    if (vm.count("config")) {
      const std::string path = vm["config"].as<std::string>();
      std::ifstream in(path);
      if (!in) {
        r.message = "cannot read config file '" + path + "'";
        return r;
      }
      po::store(po::parse_config_file(in, all), vm);  // the command line, stored first, wins
    }
    po::notify(vm);
  } catch (const po::error& e) {
    r.message = e.what();
    return r;
  }
  if (port > 65535 || metrics_port > 65535 || oracle_port > 65535) {
    r.message = "ports must be <= 65535";
    return r;
  }
  c.port = static_cast<std::uint16_t>(port);
  c.metrics_port = static_cast<std::uint16_t>(metrics_port);
  c.oracle_port = static_cast<std::uint16_t>(oracle_port);
  c.world = {{0, 0, 0}, {world_x, world_y, world_z}};
  {
    unsigned cols = 0, rows = 0;
    char x = 0, extra = 0;
    std::istringstream grid(world_grid);
    if (!(grid >> cols >> x >> rows) || x != 'x' || (grid >> extra)) {
      r.message = "world-grid must be COLSxROWS, e.g. 2x2";
      return r;
    }
    c.world_cols = cols, c.world_rows = rows;
  }
  if (auto err = validate(c)) {
    r.message = *err;
    return r;
  }
  r.config = c;
  return r;
}

}  // namespace zone
