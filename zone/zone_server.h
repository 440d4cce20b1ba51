// The zone server's composition root: the network server, the world and replication, driven by a
// fixed-rate tick loop. The `zone-server` executable is a thin main() around this class; tests run
// it in-process on an ephemeral port.
#pragma once

#include <array>
#include <atomic>
#include <chrono>
#include <deque>
#include <cstdio>
#include <memory>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include "engine_faults.h"
#include "fault_injection.h"
#include "net/metrics.h"
#include "net/os_limits.h"
#include "net/server.h"
#include "net/viewer.h"
#include "resume_book.h"
#include "truth_publisher.h"
#include "zone.h"
#include "zone/interest_setup.h"
#include "zone/viewer_columns.h"

namespace zone {

/// Counters and phase timings of the tick loop (game thread).
struct loop_stats {
  std::uint64_t ticks = 0;
  std::uint64_t overruns = 0;          ///< ticks that ended after the next tick was due
  std::uint64_t skipped_ticks = 0;     ///< ticks dropped to catch up after an overrun
  double grow_ahead_ms = 0;            ///< between ticks, growing GPU replication buffers ahead
  std::uint64_t clients = 0;           ///< clients with an entity
  std::uint64_t frames_sent = 0;       ///< tick updates handed to the network
  std::uint64_t bytes_sent = 0;
  std::uint64_t frames_held = 0;       ///< client-ticks without a frame: the client's backlog was full
  std::uint64_t client_stalls = 0;     ///< stalls: a backlog full for client_stall_s (queued state dropped, then a reset)
  std::uint64_t teleports = 0;          ///< teleport requests applied
  std::uint64_t teleports_clamped = 0;  ///< of which clamped into the world
  std::uint64_t teleports_refused = 0;  ///< refused: off, cooldown, another's entity, not finite
  std::uint64_t visibility_switches = 0;  ///< set_visibility requests applied
  std::uint64_t visibility_refused = 0;   ///< refused: a value the zone does not allow, cooldown, handed off
  std::uint64_t visibility_resyncs = 0;   ///< clients resynced because an entity they hold changed class
  std::uint64_t class_notes = 0;          ///< class notes sent instead (clients that said hello{class_changes})
  std::uint64_t joins = 0;              ///< players that joined (welcomed)
  std::uint64_t leaves = 0;             ///< players that left
  std::uint64_t logouts = 0;            ///< of the leaves: the client said leave (its entity removed at once)
  /// A single zone's resume tokens (--linger): players kept after a lost connection, those whose
  /// client came back for them, those whose wait ran out (removed), and hellos whose token took a
  /// player over from a connection still open (a client that reconnected before its loss was seen).
  std::uint64_t players_lingered = 0, players_resumed = 0, linger_expired = 0, takeovers = 0;
  std::uint64_t resumes_refused = 0;  ///< hellos with a token this zone did not know (auth_failed)
  /// Viewer snapshots filled while the replication engine waited for the device (the rest were
  /// filled in publish_viewer: CPU replication, no clients; or after the CPU's frames when the
  /// engine failed that tick).
  std::uint64_t viewer_snapshots_in_wait = 0;
  /// Viewer snapshots whose entity columns (positions, and ids, classes, kinds when changed) were
  /// copied while the GPU interest engine's device worked (single zone only).
  std::uint64_t viewer_columns_in_interest_wait = 0;
  /// Fills of the snapshot's entity columns (fill_viewer_columns) that copied the ids, classes and
  /// kinds too (entities created or destroyed, an extent set, a fresh buffer), and those that
  /// patched only the classes set_visibility changed; the others copied x and y alone.
  std::uint64_t viewer_columns_copied_all = 0;
  std::uint64_t viewer_columns_classes_patched = 0;
  /// --viewer-fill after: snapshots whose columns the copier's thread filled after their tick, the
  /// milliseconds it took there, and those the next tick spent waiting for it (part of that tick).
  std::uint64_t viewer_columns_after_tick = 0;
  double viewer_copy_ms = 0, viewer_copy_wait_ms = 0;
  latency_histogram inputs_ms, replicate_ms, tick_ms;  ///< plus zone_world::phases()
  /// Players' joins: the connection accepted to its hello read (net), and that to the welcome
  /// queued (the next tick's input phase, or a world's redirect token claimed).
  latency_histogram join_hello_ms, join_welcome_ms;
};

/// What a world of zones (world/, docs/world.md) plugs into the tick loop; a single zone has none.
/// Every call comes from the game thread.
class zone_extension {
 public:
  virtual ~zone_extension() = default;
  /// After start(): the port clients reach this zone on.
  virtual void started(std::uint16_t port) = 0;
  /// Before the step: what other zones sent (ghosts, handed-off entities, forwarded inputs).
  virtual void before_step(zone_world& w) = 0;
  /// A client whose entity moved to another zone: send it there.
  struct redirect {
    entity_id entity = null_entity;
    std::string host;
    std::uint16_t port = 0;
    std::string token;
  };
  /// After the step: hand entities off and send ghosts; `out` receives the clients to redirect.
  virtual void after_step(zone_world& w, std::vector<redirect>& out) = 0;
  /// A hello with a token (a redirected client): ready (its entity in `entity`), wait (its entity
  /// has not arrived yet: ask again next tick) or refused.
  enum class claim { ready, wait, refused };
  virtual claim claim_token(const std::string& token, zone_world& w, entity_id& entity) = 0;
  /// A client is welcomed to entity `e`: a new player (`claimed` empty) or the one a token it said
  /// claimed. Returns the token its welcome tells it to get the entity back with after this zone
  /// is lost (welcome.resume_token; "": none).
  virtual std::string resume_token(entity_id e, const std::string& claimed) {
    (void)e;
    (void)claimed;
    return {};
  }
  /// A client's connection was lost (it said no leave): true when the world keeps its entity for
  /// it to come back with its resume token (zone-server --linger); false: the zone removes it.
  virtual bool keep_for_resume(entity_id e, zone_world& w) {
    (void)e;
    (void)w;
    return false;
  }
  /// The entity is simulated here (false: another zone's, e.g. handed off after its client's last frame).
  [[nodiscard]] virtual bool owns(entity_id e) const = 0;
  /// An input for an entity handed off (its client has not moved yet): to its new zone.
  virtual void forward_input(entity_id e, const vec3& intent, std::uint32_t sequence) = 0;
  /// The classes before_step changed of entities that were already here (a ghost whose owner
  /// switched its visibility, a ghost adopted with another class): appended to `out`, and the
  /// list cleared. Clients holding them with the old class are resynced after the step, as for
  /// a player's own switch.
  virtual void take_class_changes(std::vector<class_change>& out) { (void)out; }
  /// After each step: the zone's players (clients that joined) and its player slots
  /// (--max-clients). A world tells them to its gate, which sends logins to the least loaded zone.
  virtual void clients(std::size_t players, std::size_t slots) {
    (void)players;
    (void)slots;
  }
  /// The zone must stop (e.g. it lost its region's lease): the loop ends.
  [[nodiscard]] virtual bool must_stop() const { return false; }
};

class zone_server {
 public:
  explicit zone_server(const zone_config& cfg);
  /// Plugs a world of zones in (before start(); must outlive the server).
  void set_extension(zone_extension* ext) { ext_ = ext; }
  ~zone_server();

  /// Populates the world and starts listening. A readable error on failure.
  [[nodiscard]] std::optional<std::string> start();
  /// Runs ticks at the configured rate until stop() (from any thread or a signal handler's flag).
  /// An overrun is logged and the loop catches up by skipping the missed ticks (no spiral).
  void run();
  /// One tick now, without waiting: drain inputs, step the world, replicate. (run() calls this.)
  void tick_once();
  /// Between ticks, for a caller that drives tick_once() itself (run() calls it after each tick):
  /// in the time left until `deadline`, what keeps the next ticks short (the GPU replication
  /// engine's buffers grown ahead of their needs: replicator::grow_ahead). The milliseconds it took.
  double between_ticks(std::chrono::steady_clock::time_point deadline);
  void stop() { stop_requested_ = true; }

  [[nodiscard]] std::uint16_t port() const { return net_.port(); }
  /// Port of /metrics (0 when disabled).
  [[nodiscard]] std::uint16_t metrics_port() const { return metrics_ ? metrics_->port() : 0; }
  /// The Prometheus text of the current state (what /metrics serves, refreshed once a second).
  [[nodiscard]] std::string metrics_text() const;
  [[nodiscard]] const zone_world& world() const { return *world_; }
  /// The pair finder's name ("auto", "cpu grid", ...).
  [[nodiscard]] std::string finder_name() const { return std::string(parts_.finder->name()); }
  /// Where the interest step runs: "gpu engine", "host (presence grid)" or "host (finder <name>)".
  [[nodiscard]] std::string interest_name() const;
  /// Where replication runs now: "gpu engine" or "cpu".
  [[nodiscard]] std::string replication_name() const;
  [[nodiscard]] const loop_stats& stats() const { return stats_; }
  /// The live viewer (null unless cfg.viewer_enabled); its page is on metrics_port().
  [[nodiscard]] const net::viewer_server* viewer() const { return viewer_.get(); }
  /// With --viewer-fill after: returns once the last tick's snapshot is published (its columns
  /// copied on the copier's thread); the next tick_once() does this first anyway. Otherwise nothing.
  void viewer_flush() { (void)viewer_copy_wait(); }
  [[nodiscard]] net::server_stats net_stats() const { return net_.stats(); }
  /// Port of the ground-truth stream (0 when --oracle is off).
  [[nodiscard]] std::uint16_t oracle_port() const { return truth_ ? truth_->port() : 0; }
  /// This process among the servers that listened on the same address: a random number drawn at
  /// construction, never 0, told in every welcome (a client tells a restarted server by it).
  [[nodiscard]] std::uint64_t instance() const { return instance_; }
  /// The zone's interest rules as the welcome tells them.
  [[nodiscard]] net::interest_rules rules() const;

 private:
  struct client {
    // The fields replicate()'s choice of the tick's clients reads come first (one cache line).
    client_id replica = 0;
    std::uint32_t last_input = 0;     ///< newest input sequence applied (serial-number order)
    bool redirected = false;          ///< its entity moved to another zone: no more frames, inputs forwarded
    bool holding = false;             ///< backlog full at its last turn, no byte written since held_since
    bool stalled = false;             ///< stalled (client_stall_s): no frame until the backlog is 0, then a reset
    bool any_input = false;           ///< last_input is set
    std::size_t row = 0;              ///< its place in rows_
    entity_id entity = null_entity;
    std::uint64_t last_teleport_tick = 0;  ///< world tick of the last applied teleport
    bool teleported = false;
    std::uint64_t last_visibility_tick = 0;  ///< world tick of the last applied set_visibility
    bool switched = false;
    std::uint64_t held_since = 0;
    std::uint64_t held_written = 0;  ///< *written at held_since
    std::shared_ptr<const std::atomic<std::uint64_t>> written;  ///< net::server::bytes_written
    std::shared_ptr<const std::atomic<std::uint32_t>> backlog;  ///< net::server::state_backlog
  };
  void drain_inputs();
  /// Validates and applies one client's teleport request (permission, own entity, cooldown,
  /// finite target clamped into the world).
  void teleport(net::session_id session, client& c, const net::teleport_msg& t);
  /// Validates and applies one client's set_visibility (allowed values, cooldown); a class change
  /// is queued for replicate_class_changes().
  void set_visibility(net::session_id session, client& c, const net::set_visibility_msg& v);
  /// Whether the zone allows a player's visibility choice; why not otherwise.
  [[nodiscard]] std::optional<std::string> check_visibility_choice(bool stealth, std::uint8_t team) const;
  /// After the step: every client that may hold an entity whose class changed this tick with its
  /// old class is sent a class_changes message with the new classes (clients that said
  /// hello{class_changes}) or resynced (replicator::resync_viewers_of): players' own switches
  /// and, in a world, ghosts' (zone_extension::take_class_changes). Before this tick's frames.
  void replicate_class_changes();
  std::vector<class_change> class_changes_;
  std::vector<replicator::class_note_target> class_notes_;
  /// Records an input's sequence as the client's last when it is newer (RFC 1982 serial-number
  /// order: a sequence 1 .. 2^31 - 1 ahead, wrapping past 2^32); older ones leave it.
  static void note_sequence(client& c, std::uint32_t sequence);
  void replicate();
  /// Every log_summary_s: one info line of joins, leaves and refused connections since the last
  /// (per-session lines are at debug: a flood of connections cannot flood the log).
  void log_summary();
  /// The live threads' CPU seconds of `u` by group: the tick's (the thread running the ticks and
  /// the pool's workers), the I/O threads', the rest.
  [[nodiscard]] std::array<double, 3> cpu_by_thread_group(const net::process_usage& u) const;
  /// What welcome() needs of a client's hello: its name, whether it takes class notes, and when
  /// its connection was accepted and the hello read (net::inbound_event's; 0: not known).
  struct hello_info {
    std::string name;
    bool class_changes = false;
    std::uint64_t accepted_us = 0, hello_us = 0;
  };
  /// Binds a session to an entity (a new player, or the one `token` claimed) and welcomes it.
  void welcome(net::session_id session, entity_id id, const hello_info& hello, const std::string& token = {});
  /// Hellos with a token whose entity has not arrived yet (retried each tick until the deadline).
  struct pending_hello {
    net::session_id session;
    std::string token;
    std::uint64_t deadline_tick;
    hello_info hello;
  };
  std::vector<pending_hello> pending_hellos_;
  void retry_pending_hellos();
  /// A single zone's resume tokens (--linger > 0 and no extension; a world keeps its own).
  std::unique_ptr<resume_book> resume_;
  std::vector<entity_id> expired_;
  /// A single zone's hello with a token: the player it names, back to this session (a kept one,
  /// or taken over from its old session), or auth_failed.
  void resume(const net::inbound_event& e, const net::hello_msg& hello);
  /// Unbinds a client from its session (its entity stays; the caller removes it or keeps it).
  void drop_client(std::unordered_map<net::session_id, client>::iterator it);
  zone_extension* ext_ = nullptr;
  std::vector<zone_extension::redirect> redirects_;
  std::unordered_map<entity_id, net::session_id> session_of_entity_;
  /// While a viewer page is open: collects the watched entities' events, publishes a snapshot at
  /// cfg.viewer_hz and stats twice a second, and takes the pages' selections for the next step.
  /// The events and the snapshot are taken by viewer_take_step(), here unless replicate() did.
  void publish_viewer();
  /// Whether this tick publishes a viewer snapshot (every tick_rate / viewer_hz ticks).
  [[nodiscard]] bool viewer_snapshot_due() const;
  /// The step's share of the viewer's work, once a tick while a page is open: the watched
  /// entities' enters and leaves, and the snapshot (into the viewer's free buffer) when one is
  /// due. It reads the store and the tracker, final once the step and after_step ran: in
  /// replicate() as build_many's side work (while the GPU replication engine waits for the
  /// device) on a tick with a snapshot due and frames to build on the engine, else in
  /// publish_viewer().
  void viewer_take_step(interest::thread_pool* pool);
  /// The snapshot (selections, and the entity columns unless viewer_copy_columns copied this
  /// tick's): the columns over `pool` when given (an idle pool: a device wait), else on this thread.
  void fill_viewer_snapshot(net::viewer_snapshot& s, interest::thread_pool* pool);
  /// Counts what a fill_viewer_columns copied (loop_stats::viewer_columns_copied_all, ...).
  void count_viewer_columns(viewer_columns_fill what);
  /// Inside the step, while the interest engine's device works (single zone only): a due
  /// snapshot's columns copied into the viewer's free buffer over the worker pool, idle then
  /// (fill_viewer_columns; the positions are final once integrated, and nothing after the step
  /// changes the store in a single zone); the snapshot's fill then leaves them.
  void viewer_copy_columns();
  /// --viewer-fill after: waits for the copier's snapshot in flight (at a tick's start: the store
  /// may change from then on) and counts it; returns the milliseconds waited (0: none in flight),
  /// which tick_once() counts as its own (viewer phase, viewer_fill_ms_, viewer_copy_wait_ms).
  double viewer_copy_wait();
  void fill_viewer_stats(net::viewer_stats& s) const;
  /// --test-fault: the client whose frames are broken (the lowest session with an entity).
  void choose_fault_victim();
  /// --test-fault gpu-*: when and how the wrapped GPU engine fails.
  [[nodiscard]] engine_fault gpu_fault(const zone_config& cfg) const;

  zone_config cfg_;
  std::unique_ptr<interest::thread_pool> pool_;
  /// The finder, the GPU engine and why either cannot run (start() reports it): before world_.
  interest_parts parts_;
  std::unique_ptr<zone_world> world_;
  std::unique_ptr<faulty_visibility_engine> faulty_engine_;  ///< --test-fault gpu-interest, gpu-lost: wraps engine_
  bool engine_failure_logged_ = false;
  std::string replicate_error_;  ///< why replicate = gpu cannot run here (start() reports it)
  std::string replicate_note_;   ///< why auto chose the CPU replicator
  std::unique_ptr<interest::replication_engine> replication_engine_;  ///< before replicator_: outlives it
  std::unique_ptr<faulty_replication_engine> faulty_replication_;     ///< --test-fault gpu-replication: wraps it
  bool replication_failure_logged_ = false;
  replicator replicator_;
  /// While the interest engine's device works: replication's entities staged and copied up
  /// (replicator::prestage) and a due viewer snapshot's columns copied (viewer_copy_columns), in
  /// a single zone (a world's link may move entities after the step).
  std::function<void()> interest_wait_work_;
  net::server net_;
  std::unique_ptr<net::viewer_server> viewer_;  // before metrics_, which hands it requests
  std::unique_ptr<net::metrics_server> metrics_;
  std::unique_ptr<viewer_copier>
      viewer_copier_;  // --viewer-fill after; destroyed first: it reads the store and viewer_
  // The viewer's state on the game thread: the entities watched during the last step (with their
  // latest events, in a ring: nothing allocated per tick) and the selection they came from.
  struct viewer_watch {
    static constexpr std::size_t max_events = 64;
    entity_id id = null_entity;
    std::array<net::viewer_snapshot::event, max_events> events{};
    std::size_t first = 0, count = 0;  // the oldest event's place in `events`, how many
    void add(const net::viewer_snapshot::event& e) {
      events[(first + count) % max_events] = e;
      if (count < max_events) ++count; else first = (first + 1) % max_events;
    }
  };
  std::vector<viewer_watch> viewer_watch_;
  std::vector<entity_id> viewer_watch_ids_;
  std::uint64_t viewer_selection_version_ = 0;
  double viewer_ms_ = 0;  // the last tick's publish_viewer
  double viewer_fill_ms_ = 0;  // this tick's snapshot fill on the tick's threads, wherever it ran (--tick-csv)
  bool viewer_copy_failure_logged_ = false;  // --viewer-fill after: a copy threw (logged once)
  bool viewer_step_taken_ = false;  // replicate() ran this tick's viewer_take_step (publish_viewer resets it)
  bool viewer_snapshot_filled_ = false;  // and filled a snapshot for publish_viewer to publish
  std::uint64_t viewer_columns_tick_ = ~std::uint64_t{0};  // the tick whose columns viewer_copy_columns copied
  std::chrono::steady_clock::time_point next_viewer_stats_{};
  std::unique_ptr<truth_publisher> truth_;  // --oracle
  std::uint64_t instance_ = 0;              // instance(): drawn in the constructor
  std::unique_ptr<fault_injector> fault_;   // --test-fault
  net::session_id fault_session_ = 0;
  bool fault_has_victim_ = false;
  // Replication scratch, reused every tick: one request per client, its session and its frame.
  std::vector<replication_request> requests_;
  std::vector<net::session_id> request_sessions_;
  double select_ms_ = 0;                  // the last replicate()'s choice of this tick's clients (--tick-csv)
  bool replicated_on_engine_ = false;     // the last replicate() built its frames on the GPU engine (--tick-csv)
  std::vector<std::size_t> frame_bytes_;  // by request: the frame's size
  std::vector<net::outgoing_frame> outgoing_;  // replicate(): frame k, handed on by chunk (send_many)
  net::encoder encoder_;
  std::vector<net::inbound_event> events_;
  std::unordered_map<net::session_id, client> clients_;
  /// Every client once, densely (client::row is its place; a leaving client's row takes the last
  /// one's): replicate() walks these, not the map's nodes. The map's elements do not move.
  struct client_row {
    net::session_id session;
    client* c;
    const std::atomic<std::uint32_t>* backlog;  ///< c->backlog, or null
  };
  std::vector<client_row> rows_;
  loop_stats stats_;
  std::atomic<bool> stop_requested_{false};
  // /metrics: the thread that runs the ticks (its CPU counts as the tick's, with the pool's), and
  // when this server was made (process_start_time_seconds).
  std::atomic<int> tick_thread_id_{0};
  double created_unix_s_ = 0;
  // --tick-csv: the file and the loop's start.
  std::FILE* tick_csv_ = nullptr;
  std::chrono::steady_clock::time_point started_{};
  // log_summary(): when it last wrote, and the counters then.
  std::chrono::steady_clock::time_point last_summary_{};
  loop_stats summary_loop_{};
  net::server_stats summary_net_{};
  void write_tick_line(double inputs_ms, double replicate_ms, double tick_ms, std::uint64_t frames, std::uint64_t bytes);
};

}  // namespace zone
