// zone/replicator.h: replication, one tick_update per client per tick (what each client is
// sent, within its byte budget; docs/zone.md, "Replication").
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "interest/interest_tracker.h"
#include "interest/replication_engine.h"
#include "interest/thread_pool.h"
#include "net/protocol.h"
#include "net/server.h"
#include "zone/entity_store.h"

namespace zone {

namespace detail {
/// Moves a sorted view on by sorted leaves (ids it may not hold are ignored) and sorted enters
/// (ids it does not hold): the view stays sorted; the ids after the first change move once for
/// the leaves and once for the enters, however many there are. What an engine's frame does to
/// the host's copy of a client's view (replicator::follow_view).
void move_view(std::vector<entity_id>& view, std::span<const entity_id> leaves, std::span<const entity_id> enters);
/// A view's changes not yet applied to it (sorted; an id in neither list, or it would have
/// cancelled out): how the host follows an engine's frames without moving a large view (a
/// crowd's thousands of ids) at every change of every frame.
struct view_changes {
  std::vector<entity_id> enters, leaves;
  [[nodiscard]] bool empty() const { return enters.empty() && leaves.empty(); }
  void clear() {
    enters.clear();
    leaves.clear();
  }
  /// One frame's leaves (ids the view holds with these changes) and enters (ids it does not),
  /// each in any order, the leaves taken first: a leave cancels an unsettled enter of the id, an
  /// enter an unsettled leave. True when they have grown past 1/32 of `view` (at least 16): settle now.
  bool note(std::span<const entity_id> frame_leaves, std::span<const entity_id> frame_enters,
            const std::vector<entity_id>& view);
  /// Applies them to `view` (move_view) and forgets them.
  void settle(std::vector<entity_id>& view);
};
}  // namespace detail

struct replication_options {
  /// World bounds for position quantization (sent to clients in welcome).
  net::world_bounds world{{0, 0, 0}, {4096, 4096, 256}};
  /// Most bytes of one client's frame per tick, prefix included (leave >= 256 for the header).
  std::size_t byte_budget = 8 * 1024;
  /// Update rate tiers by distance from the observer: every tick within near_distance, every
  /// mid_period ticks within mid_distance, every far_period ticks beyond.
  float near_distance = 60;
  float mid_distance = 200;
  std::uint32_t mid_period = 2;
  std::uint32_t far_period = 4;
  bool send_digest = true;
  /// With send_digest: a digest in the frames of every digest_period-th tick (and in every reset frame).
  std::uint32_t digest_period = 1;
  /// Clients handed out at a time to build_many's threads (the frames never depend on it, nor
  /// on the thread count). 64: on a replication engine at 20,000 clients, 16 cost 0.14 us more
  /// CPU per client (1,250 tasks a phase instead of 313; H200 host, 2026-11-29, in the git
  /// history of docs/zone-benchmarks.md).
  std::uint32_t clients_per_task = 64;
  /// On a replication engine: the most threads that hand the frames to the sink (0 = every pool
  /// thread). The hand-off reads the engine's frames and writes them where the sink wants them:
  /// bound by memory bandwidth, so fewer threads can do it in about the same time for less CPU.
  std::uint32_t wrap_threads = 0;
  /// build_many snapshots the entities (one quantization per entity instead of one per update
  /// sent) when clients * snapshot_entities_per_client >= entities; 0 = never. The frames are the
  /// same either way.
  std::uint32_t snapshot_entities_per_client = 16;
  /// On a replication engine: the pool's idle workers sleep after each of build_many's host
  /// phases (thread_pool::park) instead of spinning until their next run; the frames never
  /// depend on it.
  bool park_between_phases = true;
};

/// Where build_many's last call on a replication engine spent its time (ms): wall clock per
/// phase, and CPU time over each phase as the clock given to replicator::set_phase_cpu_clock
/// reads it (bench-zone: every thread of the process, each read exactly).
struct replication_phase_times {
  double stage_ms = 0;  ///< the staging: entities, slot map, jobs (one pool run)
  double engine_ms = 0;  ///< the engine's run (the device's work, copies and waits)
  double wrap_ms = 0;    ///< the frames from the engine's output, handed to the sink
  double stage_cpu_ms = 0, engine_cpu_ms = 0, wrap_cpu_ms = 0;
  bool cpu = false;  ///< the CPU figures were measured
  bool entities_ahead = false;  ///< the entities were staged and uploaded ahead (replicator::prestage)
};

/// What one build() did.
struct replication_stats {
  std::uint32_t enters = 0, leaves = 0, updates = 0;
  std::uint32_t deferred_enters = 0, deferred_leaves = 0, deferred_updates = 0;  ///< carried over
  std::size_t bytes = 0;
  bool reset = false;
};

using client_id = std::uint32_t;

/// One client's frame to build in replicator::build_many.
struct replication_request {
  client_id client = 0;
  std::uint32_t last_input_sequence = 0;
};

/// What one thread needs to build frames with replicator::build: the frame writer and the
/// build's scratch lists (pending enters, due updates, the next view). build() calls that run at
/// the same time need one each; reuse it from tick to tick (its lists keep their capacity, so a
/// steady tick allocates nothing). The scratch lives here, not per client, so that it stays in
/// this thread's cache from one client to the next.
class replication_writer {
 public:
  explicit replication_writer(std::size_t initial_bytes = 4096) : frame_(initial_bytes) {}
  [[nodiscard]] net::tick_update_writer& frame() { return frame_; }

 private:
  friend class replicator;
  struct pending {
    float priority;       // smaller first
    std::uint32_t index;  // into the view (updates) or the store (enters)
    entity_id id;
    std::uint32_t dense;  // the entity's dense index in the store
  };
  /// An entry of the view that may be due; its priority is computed only when the budget cannot
  /// hold all the due ones.
  struct due_update {
    std::uint32_t index;      // into the view
    std::uint32_t dense;      // the entity's dense index in the store
    float distance_sq;        // from the observer
    std::uint32_t staleness;  // ticks since it was last sent
  };
  /// Per view entry, beside the sorted ids: where the entity was in the store when last looked
  /// up (a hint, checked against the id before use) and the tick it was last sent, modulo 2^32
  /// (staleness is the difference modulo 2^32: exact while an entry goes unsent for under 2^32
  /// ticks, 4.5 years at 30 Hz).
  struct view_meta {
    std::uint32_t dense;
    std::uint32_t last_sent;
  };
  net::tick_update_writer frame_;
  std::vector<pending> enters_, ranked_;
  std::vector<due_update> due_;
  std::vector<std::uint32_t> left_;  // view indices sent as leaves this tick (ascending)
  std::vector<entity_id> next_view_;
  std::vector<view_meta> next_meta_;
};

/// Per-client replication state and the per-tick message builder.
///
/// The server keeps, per client, the view the client has been sent (sorted entity ids, with the
/// tick each was last sent). Each tick, build() moves that view toward the observer's visible set
/// (from the interest tracker): leaves first, then enters with full state (closest first), then
/// quantized updates of entities in the view that are due by their distance tier (highest
/// staleness / distance first), all within the byte budget; whatever does not fit stays pending
/// and is sent on a later tick (carry-over needs no queue: it is the difference between the view
/// and the visible set, recomputed each tick). The frame carries the digest of the view after it.
/// A client that lost frames is resync()ed: its next frame says reset and rebuilds the view.
///
/// Call build() after interest_tracker::update with the store unchanged in between. build() for
/// different clients may run concurrently, each with its own replication_writer; the other calls
/// may not.
class replicator {
 public:
  explicit replicator(replication_options opt = {});

  /// A client that sees through `observer` (its entity). Ids are reused after remove_client.
  [[nodiscard]] client_id add_client(entity_id observer);
  void remove_client(client_id c);
  /// The client's entity changed (respawn); its view is kept and converges as usual (the next
  /// resync_viewers_of judges it by its view: it was built with the old entity's mask).
  void set_observer(client_id c, entity_id observer);
  /// The client lost frames: the next frame resets its view and starts it again.
  void resync(client_id c);
  /// Whether client c applies class notes (it said hello{class_changes}): then a class change
  /// of an entity it may hold is sent to it as a note (resync_viewers_of's `notes`), not as a
  /// reset of its whole view. Off for a new client.
  void set_class_notes(client_id c, bool on);
  /// A class note for a client: `entity`, which it may hold, has class `visibility_class` now.
  struct class_note_target {
    client_id client;
    entity_id entity;
    std::uint32_t visibility_class;
    friend bool operator==(const class_note_target&, const class_note_target&) = default;
  };
  /// Entity `changed` switched visibility (from `old_class` and `old_sees` to its class and mask
  /// in `store` now). A frame enters an entity with its class once and never sends the class
  /// again, so the clients that hold it (in the view sent to them so far: a client not built in
  /// some ticks, or whose leaves its budget deferred, may hold an entity far outside its AOI) and
  /// whose observer's mask holds its new class are resync()ed: their next frame resets the view
  /// (enters carry the new class). So are, when its mask changed, the clients that see through
  /// the entity itself (a view built with another mask). Those that hold it and no longer see
  /// its class keep it until its leave is sent; it comes back into such a view only through
  /// another change, judged again. Returns how many. The views are the frames', so the CPU path
  /// and an engine (whose views the replicator follows from its frames) resync the same clients.
  std::size_t resync_viewers_of(const entity_store& store, const interest::interest_tracker& tracker,
                                std::uint64_t tick, entity_id changed, std::uint32_t old_class, std::uint32_t old_sees);
  /// The same for every change of a tick at once: the clients that resync_viewers_of(change)
  /// called for each change in turn would resync, in one pass over the clients (each client's
  /// observer looked up once, not once per change), spread over `pool` (null: this thread).
  /// Returns how many clients it resynced. A tick with 40 switches among 20,000 clients took
  /// the tick's thread milliseconds one change at a time.
  ///
  /// With `notes`, a client with class notes on (set_class_notes) is never resynced: for every
  /// changed entity (another than its own) that its view holds and whose new class its mask
  /// holds, it gets one note (client, entity, class now) in `*notes` (cleared first; by client,
  /// each client's in entity order, one per entity); and when its own mask changed, one for every entity its
  /// view holds whose class the new mask holds and its mask before the tick's first switch did not
  /// (an entity whose leave was not sent yet, which it sees again). A client whose next frame
  /// resets gets none. Call after the interest step and before the tick's frames (notes go first).
  ///
  /// Which clients hold an entity is decided by the box test where that is exact, and by the view
  /// elsewhere: a client built in the tick before without deferred leaves, and told of every
  /// change before, holds only entities of its visible set then, so one whose AOI box grown by
  /// the tracker's hysteresis (and a centimetre) misses the entity at `tick`'s positions does not
  /// keep it (its leave goes in this tick's frame); if that frame is not built, or defers leaves,
  /// the client's changes of `tick` are judged again by its view at the next call. Every other
  /// client (not built in the tick before, deferred leaves, or changes not yet judged) is judged
  /// by its view against every change since the last tick it was told of (a reset, after 128
  /// ticks). `tick`: the tick of the frames that follow (the builds' tick).
  std::size_t resync_viewers_of(const entity_store& store, const interest::interest_tracker& tracker,
                                std::uint64_t tick, std::span<const class_change> changes,
                                interest::thread_pool* pool = nullptr, std::vector<class_note_target>* notes = nullptr);

  /// Whether some client has not been told of an earlier class change yet: then call
  /// resync_viewers_of (with this tick's changes, or none) before every tick's frames.
  [[nodiscard]] bool class_changes_pending() const { return !change_history_.empty(); }

  /// Builds this tick's frame for client c into `writer`; the span is valid until the writer's
  /// next build. `stats`, when given, receives what was sent and deferred.
  [[nodiscard]] std::span<const std::uint8_t> build(client_id c, const entity_store& store,
                                                    const interest::interest_tracker& tracker, std::uint64_t tick,
                                                    std::uint64_t server_time_us, std::uint32_t last_input_sequence,
                                                    replication_writer& writer, replication_stats* stats = nullptr);

  /// Called by build_many once per request k with its frame (valid only during the call) and
  /// what was sent; calls for different k may run concurrently on different threads.
  using frame_sink = std::function<void(std::size_t k, std::span<const std::uint8_t> frame, const replication_stats& stats)>;

  /// build() for every request (distinct clients), spread over `pool` (null: this thread): the
  /// requests are handed out in chunks of options().clients_per_task to one task per thread,
  /// each with its own writer owned by the replicator (reused: no allocation in steady state).
  /// With many clients for the store's size it first takes a snapshot of every entity's
  /// position and quantized update, so that each update a client is sent is a 16-byte copy.
  /// Every frame and every client's state afterwards are exactly what calling build() for the
  /// requests one by one would give, for any thread count.
  /// `chunk_done` (when set) is called by the thread that built a chunk of requests [begin, end)
  /// right after the sink saw its last frame: a caller can hand a chunk's frames on together.
  using chunk_sink = std::function<void(std::size_t begin, std::size_t end)>;
  /// Where frame k is written (optional): given the frame's exact size, the caller returns
  /// writable memory of at least that size (net::frame_arena::reserve: the block the session
  /// will send it from), valid until the sink's call for k, which the same thread makes next.
  /// The frame is then written there once (no copy out of the replicator's buffer), and the
  /// sink's span is that memory. On an engine the frame is copied there from the engine's output.
  /// Unset: the sink's span is in the replicator's (or the engine's) own buffer.
  using frame_room = std::function<std::span<std::uint8_t>(std::size_t k, std::size_t bytes)>;
  /// Where frame k goes when it can go without a copy (optional): on an engine that keeps its
  /// output for as long as it is held (replication_engine::output::records_keep), each frame is
  /// handed over as a net::shared_frame of the engine's buffer (no copy, no room) through this
  /// instead of the sink; the engine reuses that buffer only once every such frame is released
  /// (it keeps a few, then copies again while all are held: a client that reads slowly holds one
  /// tick's buffer at most until its frames are dropped). Not called on the CPU path.
  using frame_share = std::function<void(std::size_t k, net::shared_frame frame, const replication_stats& stats)>;
  /// `side_work` (optional: null or empty for none): the caller's own host work, which needs
  /// none of the frames and must not change the store or the tracker; build_many runs it exactly
  /// once per call, on the calling thread, whatever path the call takes (also with no requests):
  /// on an engine, inside engine.run() while the device works (the thread would otherwise spin
  /// there: the work costs the tick nothing up to the device's time), counted in
  /// phase_times().engine_ms; on the CPU (no engine, or an engine that failed before calling
  /// it), after the last frame reached the sink and chunk_done. The pool's workers are parked
  /// or idle meanwhile; no sink (or share) call runs at the same time. What it throws leaves build_many
  /// after the frames (it is never taken for the engine's failure). Passed as a pointer so that
  /// the caller can hand a std::function holding a std::ref (no allocation a tick).
  void build_many(std::span<const replication_request> requests, const entity_store& store,
                  const interest::interest_tracker& tracker, std::uint64_t tick, std::uint64_t server_time_us,
                  interest::thread_pool* pool, const frame_sink& sink, const chunk_sink& chunk_done = {},
                  const frame_room& room = {}, const frame_share& share = {},
                  const std::function<void()>* side_work = nullptr);

  /// Runs build_many's decisions on `engine` (interest/replication_engine.h; the GPU:
  /// gpu/replication.h), which then holds the clients' views; null: back to the CPU. The frames
  /// are byte for byte those of the CPU path (tests/zone/test_zone_gpu.cpp). Every active client's
  /// next frame is a reset (the views start over on the new side). `engine` must outlive the
  /// replicator or be unset first. If the engine fails (a device error), build_many gives it up
  /// for good (engine_error() says why) and builds that tick and the next on the CPU, every
  /// client's next frame a reset. With an engine, build() must not be called; the engine holds the
  /// views, and view() is the host's copy, followed from the frames.
  void set_engine(interest::replication_engine* engine);
  /// A CPU clock (ms) that build_many on an engine reads at its phases' ends
  /// (replication_phase_times); null: none. (CLOCK_PROCESS_CPUTIME_ID lags: Linux leaves out the
  /// time other threads ran since their last tick or switch, so bench-zone passes a sum of the
  /// threads' own clocks.)
  void set_phase_cpu_clock(std::function<double()> clock) { phase_cpu_ = std::move(clock); }
  /// The phases of build_many's last call on the engine.
  [[nodiscard]] const replication_phase_times& phase_times() const { return phase_times_; }
  /// True while build_many runs on the engine.
  [[nodiscard]] bool on_engine() const { return engine_ != nullptr && engine_error_.empty(); }
  /// Between ticks, the caller idle until `deadline`: the engine's buffers grown ahead of the
  /// next builds' needs (interest::replication_engine::grow_ahead); the milliseconds it took, 0
  /// off an engine. A failure here is left to the next build, which meets it again and goes on
  /// on the CPU as with any engine error.
  double grow_ahead(std::chrono::steady_clock::time_point deadline) noexcept;
  /// On an engine that takes them ahead (replication_engine::stage_entities): stages the store's
  /// entities and slot map now and starts their copy to the device, so that the next build_many
  /// does neither (zone-server and bench-zone call it while the interest engine's device works:
  /// interest_space::set_while_device_works). Only a build_many for the same `tick` uses them,
  /// and only if the store's layout_version and size are still the same; the caller guarantees
  /// that no position or velocity changes in between. Nothing on the CPU path or on an engine
  /// without it; an engine error gives the engine up as in build_many (the next build_many runs
  /// on the CPU).
  void prestage(const entity_store& store, std::uint64_t tick, interest::thread_pool* pool);
  /// Why the engine was given up (empty while it works or when none is set).
  [[nodiscard]] const std::string& engine_error() const { return engine_error_; }

  /// The client's view as sent so far (sorted ids; on an engine followed from its frames) and its
  /// digest hash. Not const: on an engine it first applies the frames' changes that the host's
  /// copy has not taken yet (client_state::unsettled), so not concurrently with a build.
  [[nodiscard]] std::span<const entity_id> view(client_id c) {
    settle_view(clients_[c]);
    return clients_[c].view;
  }
  [[nodiscard]] std::size_t view_size(client_id c) const {
    return on_engine() ? clients_[c].engine_view_size : clients_[c].view.size();
  }
  [[nodiscard]] std::uint64_t view_hash(client_id c) const { return clients_[c].hash; }
  [[nodiscard]] entity_id observer(client_id c) const { return clients_[c].observer; }
  [[nodiscard]] const net::position_quantizer& quantizer() const { return quantizer_; }
  [[nodiscard]] const replication_options& options() const { return opt_; }

 private:
  using view_meta = replication_writer::view_meta;
  /// What build() touches per client is only this and its two lists (the scratch is in the
  /// writer): little memory per client, so that 20,000 clients' states stream through the cache.
  struct client_state {
    entity_id observer = null_entity;
    bool active = false;
    bool reset_pending = true;
    bool class_notes = false;     // set_class_notes
    std::vector<entity_id> view;  // sorted; on an engine, without its unsettled changes
    // On an engine: the frames' changes not yet applied to `view` (follow_view, settle_view).
    detail::view_changes unsettled;
    std::vector<view_meta> meta;  // parallel to view
    std::uint64_t hash = 0;
    std::uint32_t engine_view_size = 0;  // with an engine: its view's size after the last frame
    // For resync_viewers_of: the tick of its last frame that sent every leave; the last tick
    // whose class changes it has been told of all (a frame that deferred leaves does not advance
    // it); the tick it was box-tested for.
    std::uint64_t built_tick = 0;
    std::uint64_t told_through = 0;
    std::uint64_t boxed_tick = ~std::uint64_t{0};
  };
  /// After client s's frame of `tick` (both paths): what resync_viewers_of knows of its view.
  void after_frame(client_state& s, std::uint64_t tick, bool reset, bool deferred_leaves) const;
  /// One entity in build_many's snapshot, by dense index: what a view entry needs (the id to
  /// check the hint, the position for the tier, the update as sent) in half a cache line.
  struct alignas(32) entity_snapshot {
    vec3 position;
    entity_id id;
    net::wire::entity_update update;
  };
  /// Where build reads the entities: the store (quantizing each update sent) or the snapshot.
  struct store_source;
  struct snapshot_source;
  /// Squared-distance bounds of a tier: sqrt(d2) < limit is certain below below_sq and false
  /// above above_sq (a relative 1e-4 either side of limit^2); in between the root decides.
  struct tier_bound {
    float limit, below_sq, above_sq;
  };
  static bool tier_below(float d2, const tier_bound& b);
  template <class Source>
  std::span<const std::uint8_t> build_from(const Source& source, client_id c, const entity_store& store,
                                           const interest::interest_tracker& tracker, std::uint64_t tick,
                                           std::uint64_t server_time_us, std::uint32_t last_input_sequence,
                                           replication_writer& writer, replication_stats* stats,
                                           const frame_room* out_room = nullptr, std::size_t k = 0);
  /// Moves s.view on by an engine's frame: its enters (the ids, in any order) and,
  /// when `any_leaves`, the leaves read from the frame. The changes are held as unsettled ones
  /// until they are many (settle_view).
  static void follow_view(client_state& s, std::span<const entity_id> enters, const std::uint8_t* frame,
                          bool any_leaves);
  /// Applies s's unsettled changes to s.view; before anything reads s.view.
  static void settle_view(client_state& s);
  /// s's view and its unsettled changes dropped (a reset, a client removed).
  static void clear_view(client_state& s);
  /// Starts loading what building client c will read first (its state and lists).
  void prefetch_client(client_id c) const;
  /// build_many on the engine (throws what the engine throws, before any frame reaches the sink).
  void build_on_engine(std::span<const replication_request> requests, const entity_store& store,
                       const interest::interest_tracker& tracker, std::uint64_t tick, std::uint64_t server_time_us,
                       interest::thread_pool* pool, const frame_sink& sink, const chunk_sink& chunk_done,
                       const frame_room& room, const frame_share& share,
                       const std::function<void()>* while_waiting);
  /// Every active client starts over (its next frame is a reset).
  void reset_all_clients();
  /// The engine is given up (on_engine() false from now on): engine_error() says why.
  void note_engine_error(const std::exception& e);

  replication_options opt_;
  net::position_quantizer quantizer_;
  tier_bound near_, mid_;
  std::uint32_t mid_period_, far_period_;  // at least 1
  std::vector<client_state> clients_;
  /// resync_viewers_of's changes of one tick with their store values (kept: no allocation a tick).
  struct changed_entity {
    entity_id id;
    std::uint32_t cls, sees, old_class, old_sees;
    vec3 p, b;  // position and presence half extents at the tick
    std::uint64_t tick;
  };
  std::vector<changed_entity> changed_scratch_;
  /// The changes of earlier calls that some client may not have been told of, oldest first, and
  /// the last tick whose changes were dropped from it (a client told only up to before: reset).
  std::vector<changed_entity> change_history_;
  std::uint64_t forgotten_through_ = 0;
  std::uint64_t last_judged_tick_ = 0;  // the tick of the last resync_viewers_of with changes
  std::vector<changed_entity> window_;  // history and this call's changes, in order
  std::vector<std::pair<entity_id, std::uint32_t>> window_by_id_;  // (id, index into window_), by id
  std::vector<std::uint64_t> chunk_min_told_;                      // per chunk of clients: the least told_through
  std::vector<std::size_t> resync_counts_;
  std::vector<std::vector<class_note_target>> chunk_notes_;  // resync_viewers_of's notes, per chunk of clients
  std::vector<client_id> free_clients_;
  std::vector<std::unique_ptr<replication_writer>> writers_;  // one per build_many task (thread)
  std::vector<entity_snapshot> snapshot_;                     // build_many's, by dense index
  interest::replication_engine* engine_ = nullptr;
  std::string engine_error_;
  /// prestage's entities: on the engine, for a store of this layout version and size.
  bool prestaged_ = false;
  std::uint64_t prestaged_layout_ = 0, prestaged_tick_ = 0;
  std::size_t prestaged_n_ = 0, prestaged_slots_ = 0;
  std::vector<std::uint32_t> job_visible_;  // build_on_engine: visible-set size, then offset, by request
  replication_phase_times phase_times_;
  std::function<double()> phase_cpu_;
};

}  // namespace zone
