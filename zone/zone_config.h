// zone/zone_config.h: the zone server's configuration (command line and config file) and the
// NPC behaviours it populates the zone with.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>

#include "net/protocol.h"
#include "zone/entity_store.h"

namespace zone {

/// NPC behaviours (players have none: they move by their inputs).
/// `ghost`: a copy of another zone's entity (world/: BigWorld's ghosts); it has no velocity of its
/// own, its owner's messages place it.
enum class behaviour : std::uint8_t { player, wander, patrol, town, chase, boss, ghost };

/// What an entity's behaviour remembers between ticks (a world's handoff carries it to the next zone).
struct behaviour_state {
  behaviour kind = behaviour::player;
  vec3 home{};                 ///< town centre, patrol origin or boss lair
  std::uint32_t waypoint = 0;  ///< patrol
  vec3 intent{};               ///< players: clamped input
  friend bool operator==(const behaviour_state&, const behaviour_state&) = default;
};

/// Everything the zone server needs, with defaults that run without any file.
struct zone_config {
  // World and tick.
  net::world_bounds world{{0, 0, 0}, {4096, 4096, 256}};
  double tick_rate_hz = 30;
  std::uint64_t seed = 1;
  unsigned worker_threads = 0;  ///< interest and tick work; 0 = hardware concurrency
  /// Microseconds an idle worker spins before it sleeps (interest::thread_pool), and the tick
  /// loop wakes the workers this long before a tick is due. 0 (the default): no spin; on the
  /// 2-core VM and on the H100 host the spin cost more CPU than it saved tick time
  /// (docs/zone-benchmarks.md, "The pool's idle spin"). -1 (auto, the default before) is 0 too.
  int worker_spin_us = 0;
  // Interest.
  /// Pair finder (gpu/finders.h): "auto" (chosen per tick: a GPU finder when a device is usable,
  /// else the CPU grid finder), "cpu", "gpu" (= "pbig"), "pbig", "lbvh", "brute".
  std::string finder = "auto";
  /// Where the interest step runs: "auto" (the GPU visibility engine, gpu/visibility.h, when a
  /// device is usable and max_visible is 0; else the host path), "gpu" (the engine, or refuse to
  /// start), "host" (the pair finder above and the host diff).
  std::string interest = "auto";
  /// How the host path finds each observer's candidates: "on" (on a grid of the presence boxes,
  /// the GPU engine's query on the host threads: interest_options::presence_grid), "off" (through
  /// the pair finder above), "auto" (on when that finder is the CPU grid finder: "cpu", or "auto"
  /// without a usable device). The same output either way.
  std::string host_grid = "auto";
  /// Where replication's per-client decisions run: "auto" (the GPU replication engine,
  /// gpu/replication.h, when a device is usable; else the CPU replicator), "gpu" (the engine, or
  /// refuse to start), "cpu". The frames are the same either way (docs/zone.md).
  std::string replicate = "auto";
  /// With both engines on the GPU: copy the players' visible sets back to the host after every
  /// interest step (true), or let the replication engine read them on the device only (false:
  /// no per-tick copy of 20,000 sets; measured on the H100, 2026-11-25: ~0.3 ms less a tick;
  /// the figure is in the git history of docs/zone-benchmarks.md). With false a GPU that
  /// fails mid-run takes the players' last sets with it: their hysteresis history is lost and
  /// clients hold entities the rules say they should not (or lack ones they should) for a while;
  /// with true the fallback is exact (docs/zone.md, "A GPU that fails mid-run").
  bool host_views = true;
  float hysteresis = 4;
  std::uint32_t max_visible = 0;  ///< per observer, 0 = no cap
  /// AOI half-extents of the tiers tiny .. gigantic (metres).
  float aoi_tier[5] = {10, 30, 60, 150, 400};
  float player_aoi = 60;
  // Population and movement.
  std::size_t npc_count = 2000;
  /// Shares of wander, patrol, town, chase among NPCs (normalised); plus boss_count bosses.
  float share_wander = 0.45f, share_patrol = 0.2f, share_town = 0.3f, share_chase = 0.05f;
  std::size_t boss_count = 1;
  std::size_t town_count = 0;  ///< 0 = one town per 2,000 NPCs (at least one)
  float npc_speed = 2.0f;     ///< m/s
  float player_speed = 6.0f;  ///< m/s, the most a client's input can move its entity
  float boss_footprint = 40;  ///< presence half-extent of a boss (seen from far away)
  // Network and limits.
  std::string listen_address = "0.0.0.0";
  std::uint16_t port = 7777;
  unsigned io_threads = 2;
  std::size_t max_clients = 1000;
  std::size_t max_frame_bytes = 16 * 1024;
  /// SO_SNDBUF per client socket (bytes; 0 = the system's autotuning, up to 4 MiB). Small by
  /// default: what the kernel holds for a client that stops reading reaches it stale when it
  /// resumes (docs/zone.md, "Slow and stalled clients"); Linux doubles the value asked for.
  std::size_t socket_send_buffer = 32768;
  /// The replication worker that built a frame writes it to the socket itself when nothing is
  /// queued ahead of it (net::server_options::direct_writes); false (the default): the I/O
  /// threads write. Direct writes cut latency but lengthen the replicate phase: the kernel's
  /// send is then the tick's CPU (on the H100 host, 2026-11-25, it doubled; git history of
  /// docs/zone-benchmarks.md).
  bool direct_writes = false;
  int io_nice = 0;  ///< nice value of the I/O threads (net::server_options::io_thread_nice; 0-19)
  /// CPU lists ("0-5,8"; empty = not pinned): the tick's threads (the worker pool and the tick's
  /// own thread) and the I/O threads (net::server_options::io_thread_cpus).
  std::string worker_cpus, io_cpus;
  /// How the I/O threads write (net::server_options::batching): "auto" (io_uring where the kernel
  /// allows it, else sendmsg), "io_uring" (or refuse to start), "sendmsg".
  std::string write_batching = "auto";
  /// Ready sessions an I/O thread writes before it reads its clients again
  /// (net::server_options::write_slice; 1 .. 1,000,000).
  std::size_t write_slice = 256;
  double inputs_per_second = 60;
  double pings_per_second = 10;  ///< per client; over it pings get no pong (net::server_options)
  /// Admission (net::server_options): a connection must complete its hello within hello_timeout_s
  /// of accept; connections without a hello are capped in total and per source address, apart
  /// from the max_clients player slots.
  double hello_timeout_s = 3;
  std::size_t max_pending = 1024;
  std::size_t max_pending_per_address = 256;
  /// Reconnect churn per source address (net::server_options::connect_rate): connections that end
  /// within connect_min_session_s of their accept take a token from their address's bucket
  /// (connect_rate a second, burst connect_burst); an address without a token is refused at
  /// accept. Connections that stay cost nothing. connect_rate 0 = no limit.
  double connect_rate = 20;
  double connect_burst = 64;
  double connect_min_session_s = 10;
  double connect_refusal_hold_s = 2;  ///< a refused connection is held unanswered this long (0 = answered at once)
  std::size_t max_name_bytes = 32;  ///< longest player name (printable ASCII)
  double idle_timeout_s = 10;       ///< a player that sends no complete frame this long is closed
  /// Seconds between the info-level summary of joins, leaves and refusals (per-session lines are
  /// at debug level); 0 = none.
  double log_summary_s = 10;
  std::size_t client_byte_budget = 8 * 1024;
  /// A client with this many state frames still unwritten (net::server::state_backlog) gets no new
  /// frame this tick: a slow reader is sent fewer, fresher frames (its view catches up in the next
  /// one) instead of overflowing its queue into drops and resets. 0 = off (always send).
  std::uint32_t client_max_backlog = 2;
  /// Bounded staleness after a stall (docs/zone.md, "Slow and stalled clients"): a client whose
  /// backlog stays at client_max_backlog, its socket taking not one byte, for this long (seconds,
  /// in ticks rounded up; 0 = off) is
  /// stalled: its queued state frames that are not being written are dropped (they would be stale
  /// when read), it gets no frame until its socket has drained (backlog 0), and then a reset of
  /// the current state. Needs client_max_backlog > 0.
  double client_stall_s = 1.0;
  /// Each client gets a frame every this many ticks (1: every tick), the clients staggered by
  /// session so that each tick builds about 1/K of the frames. The world still steps every tick;
  /// a frame carries everything since the client's last one.
  std::uint32_t client_send_every = 1;
  /// Players may teleport themselves (the teleport message): an ability the server grants, off
  /// unless configured (a client could otherwise cross the world in a tick).
  bool teleport_enabled = false;
  /// Players may move vertically (fly). Off: a player's movement intent is horizontal (its z is
  /// ignored), players walk at the height they have.
  bool player_fly = false;
  float spawn_radius = 200;          ///< players spawn uniformly within this distance of a town centre (m)
  /// Replication's update-rate tiers (docs/zone.md): every tick within update_near metres, every
  /// update_mid_period ticks within update_mid, every update_far_period ticks beyond.
  float update_near = 12, update_mid = 30;
  std::uint32_t update_mid_period = 3, update_far_period = 8;
  std::uint32_t digest_every = 1;    ///< a visible-set digest every K ticks (0 = none)
  double teleport_cooldown_s = 0.5;  ///< least time between two jumps of one player (0 = none)
  /// Client-chosen visibility (hello, set_visibility; docs/zone.md "Visibility classes and
  /// teams"): players may choose stealth, and join one of `player_teams` teams (0 none, 1 red,
  /// 2 red and blue); a client switches at most once per visibility_cooldown_s.
  bool allow_stealth = true;
  std::uint32_t player_teams = 2;
  double visibility_cooldown_s = 1.0;
  bool metrics_enabled = true;        ///< serve Prometheus text at http://metrics_address:metrics_port/metrics
  std::uint16_t metrics_port = 9100;  ///< 0 = an ephemeral port
  /// Where /metrics listens: loopback by default (it has no authentication); "0.0.0.0" opens it.
  std::string metrics_address = "127.0.0.1";
  /// Connections /metrics holds at once (its own, apart from the game's descriptors); more are
  /// closed at accept. Each must send its request within 5 s.
  std::size_t metrics_max_connections = 16;
  std::string log_level = "info";
  /// When set, one CSV line per tick (its wall time, clients, frames and phase timings) goes to
  /// this file, so percentiles can be taken over any window (e.g. after a swarm's ramp-up).
  std::string tick_csv;
  // World of zones (world/, docs/world.md): empty world_name = a single zone.
  std::string world_name;  ///< --world: the world this zone joins
  std::string nats_url;    ///< --nats: the NATS server that holds the world's layout
  std::uint32_t world_cols = 2, world_rows = 2;  ///< --world-grid: regions of a new world's layout
  double world_lease_ttl_s = 3;     ///< --world-lease-ttl: the region's lease lapses this long after the last renewal
  double world_nats_timeout_s = 2;  ///< --world-nats-timeout: how long a connect or KV / JetStream request waits
  /// --world-capacity: most entities the zone owns (0: its store's capacity); a neighbour keeps an
  /// entity past the border while this zone is full (docs/world.md, "Faults": a full zone)
  std::size_t world_capacity = 0;
  /// --world-checkpoint: seconds between checkpoints of the zone's entities (0: none; docs/world.md, "Checkpoints")
  double world_checkpoint_s = 1;
  /// A player restored from a checkpoint (its zone lost) waits this long for its client's resume
  /// token, then is removed (docs/world.md, "Players after a zone's loss").
  double world_resume_s = 30;
  /// --linger: a player whose connection was lost (its client said no leave) is kept, standing,
  /// this long for its client to come back with its resume token (0: removed at once and no
  /// token told in a single zone; docs/protocol.md, "Coming back after a lost connection").
  double linger_s = 0;
  /// --world-standby: while every region is held, wait for one whose lease lapses (a zone died)
  /// and take it over, instead of giving up after 20 s (docs/world.md, "Standbys")
  bool world_standby = false;
  /// Start with the NPC population (false: a world zone that restores its region's checkpoint
  /// instead; docs/world.md, "Checkpoints").
  bool populate = true;
  /// Where populate() places NPCs and towns (x, y; z from world): the zone's region in a world.
  /// Empty (lo == hi) = the whole world.
  net::world_bounds spawn_area{};
  // The live viewer (docs/viewer.md), served beside /metrics: off unless enabled.
  bool viewer_enabled = false;   ///< serve /viewer and /viewer/ws
  bool viewer_remote = false;    ///< also to peers that are not on a loopback address
  std::size_t max_viewers = 4;   ///< viewer pages at once
  double viewer_hz = 10;         ///< snapshots a second while a page is open (at most the tick rate)
  int viewer_nice = 19;          ///< nice value of the viewer's thread (0-19; net::viewer_options::nice)
  bool viewer_idle = true;       ///< the viewer's thread at SCHED_IDLE where the OS allows it (net::viewer_options::idle)
  /// Entities per task of a snapshot's column copy over the worker pool (fill_viewer_columns; no
  /// option: tests set it small so that a small zone's copy is split too). 0: viewer_columns_chunk.
  std::size_t viewer_copy_chunk = 0;
  /// Where a due snapshot's entity columns are copied (docs/viewer.md): "after" (a thread of its
  /// own after the tick; the next tick waits for it if it is not done) or "wait" (in the GPU
  /// interest engine's device wait, over the worker pool; elsewhere in the tick's viewer phase).
  std::string viewer_fill = "after";
  // Correctness (docs/bots.md, the oracle).
  /// Publish every tick's ground truth on a loopback stream (127.0.0.1:oracle_port; 0 = an
  /// ephemeral port, told in the welcome): what an independent oracle checks each client's view
  /// against. Off: nothing is built or sent.
  bool oracle = false;
  std::uint16_t oracle_port = 0;
  /// Truth-stream subscribers served at once (each oracle is one: a world's every swarm reads
  /// every zone); one more is sent a refusal naming this limit and closed. Each may queue up to
  /// truth_publisher::max_queued_bytes.
  int oracle_subscribers = 4;
  /// Testing only: a deliberate replication fault for one client, to prove that the oracle
  /// catches it: "" (none), "drop", "extra", "stealth", "freeze" or "class" (zone/fault_injection.h).
  std::string test_fault;
  std::uint64_t test_fault_tick = 40;  ///< the world tick from which the fault acts
};

/// Result of parse_config: a config, or a message (the help text, or a readable error).
struct config_result {
  std::optional<zone_config> config;
  std::string message;
  bool help = false;  ///< --help was given: print message, exit 0
};

/// zone_config::worker_spin_us resolved (-1 = auto: 0).
[[nodiscard]] unsigned worker_spin(const zone_config& c);

struct replication_options;  // zone/replicator.h
/// The replicator's options from the configuration (world, byte budget, update distances and
/// periods, digests), as zone-server sets them; the rest keep their defaults.
[[nodiscard]] replication_options replication_options_of(const zone_config& c);

/// Parses the command line; `--config FILE` reads an INI-style file of the same option names
/// (the command line wins). Unknown options and bad values are errors naming the option.
[[nodiscard]] config_result parse_config(int argc, const char* const* argv);
/// Checks a config's values (positive rates and sizes, ordered bounds, ...).
[[nodiscard]] std::optional<std::string> validate(const zone_config& c);

}  // namespace zone
