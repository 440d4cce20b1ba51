// The bot swarm: many real TCP clients of the zone server in one process (docs/bots.md).
// Each bot speaks the FlatBuffers protocol through net/'s codec, moves by a scripted behaviour,
// measures update latency and checks what the server tells it (client_view, digests, AOI bounds).
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <mutex>
#include <string>
#include <vector>

#include "oracle.h"
#include "net/latency_histogram.h"
#include "net/protocol.h"

namespace zone::bots {

/// Scripted behaviours, mixable per swarm (shares need not sum to 1; they are normalised).
enum class behaviour : std::uint8_t { walk, patrol, follow, crowd, teleport };
inline constexpr std::size_t behaviour_count = 5;
inline constexpr std::array<const char*, behaviour_count> behaviour_names = {"walk", "patrol", "follow", "crowd", "teleport"};

struct swarm_options {
  std::string host = "127.0.0.1";
  std::uint16_t port = 7777;
  unsigned bots = 100;
  double duration_s = 30;    ///< from the first connection attempt to the end (ramp included)
  double ramp = 200;         ///< new bots per second during ramp-up
  /// At most this many sessions connecting at once (from the connect until the welcome): the ramp
  /// waits for welcomes rather than run ahead of them. A swarm whose threads lag behind its ramp
  /// (or a server behind on reading hellos) otherwise holds hundreds of connections that the
  /// server has not yet heard a hello from, and the
  /// server's cap on connections without a hello (zone-server --max-pending, 1,024 by default;
  /// --max-pending-per-address, 256) closes the oldest of them. 0 = no limit.
  unsigned max_connecting = 128;
  double input_hz = 10;      ///< intent evaluations (steering) per second per bot
  /// true: an input is sent only when the intent differs from the last one sent, or when
  /// input_keepalive_s has passed since it (the server keeps a player's last intent until the next
  /// input); evaluated as frames arrive. false: an input at every evaluation, on its own timer.
  bool inputs_on_change = true;
  double input_keepalive_s = 1;  ///< with inputs_on_change: resend an unchanged intent this often
  double ping_hz = 1;        ///< pings per second per bot (clock offset, RTT, keep-alive)
  std::array<double, behaviour_count> mix{1, 0, 0, 0, 0};  ///< shares by behaviour
  double teleport_hz = 0.2;  ///< teleport bots: jumps per second per bot (random times, random targets in the world)
  /// Client-chosen visibility (docs/bots.md): the share of bots that join stealthed, and the share
  /// that join a team (red or blue, half each), chosen per session at random; those bots switch
  /// (set_visibility: stealth toggled, the team changed half the time) at visibility_switch_hz
  /// each (random times; 0 = never).
  double stealth_share = 0.1;
  double team_share = 0.2;
  double visibility_switch_hz = 0.2;
  /// Say hello{class_changes}: a class change of an entity a bot holds comes as a class_changes
  /// note. false: as an older client, which the server resets instead.
  bool class_changes = true;
  double churn = 0;          ///< logouts per second across the swarm (each logged-out bot logs in again)
  double churn_for_s = 0;    ///< churn stops this many seconds into the run (0 = until the end)
  /// Connections dropped per second across the swarm as a network would drop them: a random
  /// playing bot closes its socket without a leave and logs in again after relogin_delay_s with
  /// its resume token (when `resume` and the zone told one: zone-server --linger), else anew.
  /// Stops with churn_for_s too.
  double cut = 0;
  double relogin_delay_s = 0.2;
  /// After an unexpected disconnect, log in again (a new session for the slot, at the address it
  /// was connected to) after relogin_delay_s, retrying refused connects for up to
  /// connect_timeout_s: a zone restarted on the same port (docs/world.md) gets its players back.
  bool reconnect = false;
  /// With `reconnect`: logins again go to this port on `host` (a world's gate, docs/world.md: it
  /// redirects each to a zone that serves now) instead of the zone the bot was in. 0: the zone.
  std::uint16_t relogin_port = 0;
  /// With `reconnect`: a bot whose welcome told a resume token (a world's zone) says it in its
  /// hello when it logs in again, to get its entity back from the zone that restored its region
  /// (docs/world.md, "Players after a zone's loss"); a token refused: it logs in anew.
  bool resume = true;
  bool verify = false;       ///< compare the server's visible-set digests with the tracked view
  /// Check every bot's view against the server's ground truth (oracle.h; the server runs with
  /// --oracle): a probe connection reads the welcome (rules, truth port) before any bot starts.
  bool oracle = false;
  unsigned oracle_threads = 0;  ///< threads recomputing the visible sets (0 = 1 per 8 hardware threads)
  /// The oracle's scale knob (oracle::sample): 1 in K bots (a fixed subset, by entity id) is
  /// recomputed and checked on every frame; the others' frames count as unsampled (1 = every bot).
  unsigned oracle_sample = 1;
  /// A world of zones (docs/world.md): the client ports of the other zones (on `host`). With
  /// `oracle`, each gets an oracle of its own (its truth stream), and a bot is checked against the
  /// truth of the zone it is connected to now: it follows redirects across borders, its view
  /// (ghosts of the neighbours included) judged in every zone. A bot in a zone not named here is
  /// not checked (its frames count as unchecked).
  std::vector<std::uint16_t> oracle_zones;
  /// Zones that may start after the swarm (a world's standby): their truth is read once they
  /// answer; a bot sent to one before (a gate's redirect) waits for it (at most 10 s).
  std::vector<std::uint16_t> oracle_zones_later;
  unsigned threads = 0;      ///< I/O threads (0 = auto: one per 2,500 bots, at least 2, at most half the cores)
  // What the AOI check assumes of a server whose welcome does not tell its rules (older servers;
  // a welcome's rules always win, so a current server's flags need no matching ones here).
  float aoi = 60;            ///< the players' AOI half-extent (--player-aoi)
  float hysteresis = 4;      ///< leave margin (--hysteresis)
  float max_speed = 6;       ///< fastest any entity moves (m/s; max of --player-speed, 1.5 x --npc-speed)
  bool hotspot_set = false;
  net::vec3f hotspot{};      ///< the flash crowd's target; default: where the leader first is
  double crowd_at_s = 0;     ///< crowd bots walk until this many seconds into the run, then converge
  double connect_timeout_s = 10;  ///< connect + welcome
  std::size_t max_frame_bytes = 1 << 22;
};

/// End-to-end latencies in microseconds, lock-free for concurrent recording (net/latency_histogram.h).
using latency_histogram_us = net::latency_histogram_us;
/// Percentile (0..1) of a snapshot or of the difference of two, in milliseconds (its bucket's middle).
[[nodiscard]] inline double percentile_ms(const latency_histogram_us::counts& c, double q) {
  return latency_histogram_us::percentile_mid(c, q) / 1000.0;
}

/// Counters of the whole swarm (relaxed atomics; read by the progress line while bots run).
struct swarm_counters {
  /// Sessions started and not yet welcomed (connecting, the hello not yet written, or written and
  /// not yet read by the server): the ramp holds new connects while max_connecting of them are
  /// outstanding, so the server never holds more of the swarm's connections without a hello read.
  std::atomic<std::uint64_t> connecting_now{0};
  std::atomic<std::uint64_t> connect_attempts{0}, connected_now{0}, welcomes{0}, connect_failures{0},
      unexpected_disconnects{0}, server_errors{0}, logouts{0}, teleports_sent{0};
  std::atomic<std::uint64_t> cuts{0};  ///< connections dropped by --cut (no leave)
  std::atomic<std::uint64_t> stealth_joins{0}, team_joins{0}, visibility_switches_sent{0};
  std::atomic<std::uint64_t> class_notes{0};  ///< class_changes notes received (held or not)
  /// A world of zones (docs/world.md): redirects followed (a new connection with the token).
  std::atomic<std::uint64_t> redirects{0};
  /// Logins a world's gate sent on to a zone (a redirect without a token).
  std::atomic<std::uint64_t> gate_redirects{0};
  std::atomic<std::uint64_t> reconnects{0};  ///< logins again after an unexpected disconnect (--reconnect)
  /// Logins again with a resume token that got the entity back (resumes), and those refused (the
  /// token unknown or expired, or no zone for its region: the bot logs in anew).
  std::atomic<std::uint64_t> resumes{0}, resumes_refused{0};
  std::atomic<std::uint64_t> frames_in{0}, bytes_in{0}, tick_updates{0}, enters{0}, leaves{0}, updates{0}, resets{0};
  std::atomic<std::uint64_t> inputs_sent{0}, inputs_unchanged{0}, pings_sent{0}, pongs{0};
  std::atomic<std::uint64_t> digests_checked{0}, digest_mismatches{0}, inconsistent{0};
  std::atomic<std::uint64_t> aoi_checked{0}, aoi_unchecked{0}, aoi_violations{0};
  std::atomic<std::uint64_t> latency_unsynced{0};
  std::atomic<std::uint64_t> self_positions{0};  ///< frames that carried the bot's own position
  [[nodiscard]] std::uint64_t mismatches() const {
    return digest_mismatches.load() + inconsistent.load() + aoi_violations.load();
  }
};

/// Per bot slot (a slot is one bot; churn logs it out and in again), written by its own strand.
struct slot_stats {
  std::uint64_t bytes_in = 0, frames_in = 0;
  double connected_s = 0;  ///< total time with a welcome, over all its sessions
  bool ever_connected = false;
  behaviour kind = behaviour::walk;
};

/// One line per second of the run (for the CSV, the JSON and the plot).
struct second_sample {
  double t = 0;
  std::uint64_t connected = 0, frames = 0, bytes = 0, enters = 0, leaves = 0, updates = 0, mismatches = 0;
  double p50_ms = 0, p99_ms = 0, max_window_ms = 0;
};

/// Everything the run produced.
struct swarm_result {
  swarm_options options;
  double elapsed_s = 0;
  std::vector<slot_stats> slots;
  std::vector<second_sample> series;
  latency_histogram_us::counts latency{};
  double latency_max_ms = 0;
  /// The latencies from the first once-a-second sample with every bot connected to the end (the
  /// ramp-up left out); steady_from_s < 0 when that never happened (then steady_latency is empty).
  double steady_from_s = -1;
  latency_histogram_us::counts steady_latency{};
  /// How long logins took (every session, churn and redirects included): from the launch (the
  /// ramp's or churn's decision) to the TCP connection, and from there to the welcome. A slow
  /// connect ramp shows in one or the other.
  latency_histogram_us::counts connect_time{}, welcome_time{};
  double connect_max_ms = 0, welcome_max_ms = 0;
  std::vector<std::string> problems;  ///< first mismatches and failures, readable (tick and ids)
  std::uint64_t problems_total = 0;
  // Copies of the counters at the end.
  std::uint64_t connect_attempts = 0, welcomes = 0, connect_failures = 0, unexpected_disconnects = 0, server_errors = 0,
                logouts = 0, frames_in = 0, bytes_in = 0, tick_updates = 0, enters = 0, leaves = 0, updates = 0,
                resets = 0, inputs_sent = 0, inputs_unchanged = 0, pongs = 0, digests_checked = 0,
                digest_mismatches = 0, inconsistent = 0, aoi_checked = 0, aoi_unchecked = 0, aoi_violations = 0,
                latency_unsynced = 0, teleports_sent = 0, self_positions = 0, redirects = 0, reconnects = 0,
                gate_redirects = 0, resumes = 0, resumes_refused = 0, cuts = 0;
  std::uint64_t stealth_joins = 0, team_joins = 0, visibility_switches_sent = 0, class_notes = 0;
  bool host_clock = false;  ///< latency timed on the host's clock (same host), not by ping sync
  bool rules_from_server = false;  ///< the welcome told the zone's interest rules (the AOI check used them)
  bool oracle_on = false;
  oracle_report oracle;  ///< with oracle_on
  std::uint64_t bots_connected = 0;  ///< slots that got a welcome at least once
  double min_rtt_ms = 0;
  double cpu_s = 0;  ///< CPU time of the bot-swarm process (user + system), to judge a shared machine
  /// Every failed check; an oracle whose stream broke counts one (its checks are incomplete).
  [[nodiscard]] std::uint64_t mismatches() const {
    return digest_mismatches + inconsistent + aoi_violations +
           (oracle_on ? oracle.mismatches() + (oracle.stream_error.empty() ? 0 : 1) : 0);
  }
};

/// Runs the swarm for options.duration_s; calls `progress` once a second (from the calling thread)
/// with the latest sample. Returns an error text instead when the host cannot be resolved.
struct run_outcome {
  swarm_result result;
  std::string error;
};
using progress_fn = void (*)(const second_sample&, const swarm_counters&, const swarm_options&);
[[nodiscard]] run_outcome run_swarm(const swarm_options& opt, progress_fn progress);

}  // namespace zone::bots
