// Public API of the zone layer: entity storage, the interest tracker (pairs -> per-observer
// visible sets -> enter/leave events with hysteresis) and replication (what each client is sent).
// See docs/zone.md.
//
// Later parts of the zone server (configuration, NPC behaviours, the tick loop, replication) build
// on these: the tick loop owns one entity_store and one interest_tracker and calls
// interest_tracker::update once per tick after moving entities.
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <atomic>
#include <memory>
#include <mutex>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "interest/interest.h"
#include "interest/replication_engine.h"
#include "interest/thread_pool.h"
#include "interest/visibility_engine.h"
#include "net/protocol.h"

namespace zone {

// ---------------------------------------------------------------------------------------------
// Entity storage.

/// A generation-checked entity handle: (generation << entity_index_bits) | slot. Generations run
/// 1 .. 2^(32 - entity_index_bits) - 1 and wrap back to 1, so a handle is never 0 (null_entity).
/// A stale handle (its entity destroyed, even if the slot was reused) is rejected by every lookup
/// until the slot's generation wraps around (max_generation = 1,023 reuses of that one slot).
/// 22 slot bits: up to 4,194,304 entities in one zone (20 bits capped a zone at 1,048,576, below
/// what the GPU interest engine steps in a tick; docs/zone-benchmarks.md, "Growth").
using entity_id = std::uint32_t;
inline constexpr entity_id null_entity = 0;
inline constexpr unsigned entity_index_bits = 22;
inline constexpr std::uint32_t entity_index_mask = (1u << entity_index_bits) - 1;
/// Most entities alive at once in one store.
inline constexpr std::size_t max_entities = std::size_t{1} << entity_index_bits;
/// The highest generation of a slot (then it wraps to 1).
inline constexpr std::uint32_t max_generation = (1u << (32 - entity_index_bits)) - 1;

[[nodiscard]] constexpr std::uint32_t slot_of(entity_id id) { return id & entity_index_mask; }
[[nodiscard]] constexpr std::uint32_t generation_of(entity_id id) { return id >> entity_index_bits; }

struct vec3 {
  float x = 0, y = 0, z = 0;
  friend bool operator==(const vec3&, const vec3&) = default;
};

enum class entity_kind : std::uint8_t { player, npc, boss };

/// Everything needed to create an entity. Visibility: `visibility_class` is the one category bit
/// of its presence box (category_bits::normal, stealth, team_red, ...; never category_bits::aoi);
/// `sees` is the set of classes its AOI box sees (its mask; never containing the aoi bit).
struct entity_desc {
  vec3 position{};
  vec3 velocity{};
  std::uint32_t visibility_class = interest::category_bits::normal;
  std::uint32_t sees = interest::category_bits::normal | interest::category_bits::team_red |
                       interest::category_bits::team_blue;
  vec3 aoi_half_extent{50, 50, 50};          ///< the AOI box is position +- this (metres)
  vec3 presence_half_extent{0.5f, 0.5f, 1};  ///< the presence box (body / footprint) is position +- this
  entity_kind kind = entity_kind::npc;
  friend bool operator==(const entity_desc&, const entity_desc&) = default;
};

/// Why a description is unacceptable (nothing when it is fine): non-finite numbers, negative
/// extents, a class that is not exactly one non-aoi bit, or `sees` containing the aoi bit.
[[nodiscard]] std::optional<std::string> validate(const entity_desc& d);

/// Dense structure-of-arrays entity storage with generation-checked handles (the sparse-set
/// layout: slot -> dense index, dense index -> handle). Live entities occupy dense indices
/// [0, size()); destroy() moves the last entity into the hole, so dense indices are not stable
/// across destroys, handles are. Not thread-safe for mutation; concurrent reads are fine.
class entity_store {
 public:
  /// `capacity`: most entities alive at once (at most max_entities).
  explicit entity_store(std::size_t capacity = max_entities);

  /// Creates an entity. Returns null_entity, with the reason in `*error` when given, if the
  /// description is invalid or the store is full.
  [[nodiscard]] entity_id create(const entity_desc& d, std::string* error = nullptr);
  /// Destroys a live entity; false (and nothing changes) for a null, stale or unknown handle.
  bool destroy(entity_id id);
  [[nodiscard]] bool alive(entity_id id) const { return index_of(id) != npos; }
  /// Dense index of a live entity, npos otherwise. Inline: replication looks up every entry of
  /// every client's view each tick.
  [[nodiscard]] std::size_t index_of(entity_id id) const {
    const std::uint32_t slot = slot_of(id);
    if (id == null_entity || slot >= slot_dense_.size()) return npos;
    const std::uint32_t dense = slot_dense_[slot];
    // An invalid slot holds 0xffffffff, never a valid dense index.
    if (dense >= ids_.size() || ids_[dense] != id) return npos;
    return dense;
  }
  static constexpr std::size_t npos = static_cast<std::size_t>(-1);

  [[nodiscard]] std::size_t size() const { return ids_.size(); }
  [[nodiscard]] bool empty() const { return ids_.empty(); }
  [[nodiscard]] std::size_t capacity() const { return capacity_; }
  void clear();
  void reserve(std::size_t n);

  /// The description of a live entity.
  [[nodiscard]] std::optional<entity_desc> get(entity_id id) const;

  // Checked setters (false for a dead handle or an invalid value; nothing changes then).
  bool set_position(entity_id id, const vec3& p);
  bool set_velocity(entity_id id, const vec3& v);
  bool set_aoi_half_extent(entity_id id, const vec3& h);
  bool set_presence_half_extent(entity_id id, const vec3& h);
  bool set_visibility(entity_id id, std::uint32_t visibility_class, std::uint32_t sees);

  // Dense columns, index = dense index. Positions and velocities are writable in bulk (the
  // movement systems); the interest tracker rejects non-finite values naming the entity.
  [[nodiscard]] std::span<const entity_id> ids() const { return ids_; }
  [[nodiscard]] std::span<vec3> positions() { return position_; }
  [[nodiscard]] std::span<const vec3> positions() const { return position_; }
  [[nodiscard]] std::span<vec3> velocities() { return velocity_; }
  [[nodiscard]] std::span<const vec3> velocities() const { return velocity_; }
  [[nodiscard]] std::span<const std::uint32_t> visibility_classes() const { return visibility_class_; }
  [[nodiscard]] std::span<const std::uint32_t> sees() const { return sees_; }
  [[nodiscard]] std::span<const vec3> aoi_half_extents() const { return aoi_half_; }
  [[nodiscard]] std::span<const vec3> presence_half_extents() const { return presence_half_; }
  [[nodiscard]] std::span<const entity_kind> kinds() const { return kind_; }

  /// One past the highest slot index ever used (sizes per-slot side tables of other systems).
  [[nodiscard]] std::size_t slot_count() const { return slot_generation_.size(); }

  /// Changes whenever anything but positions and velocities may have changed (an entity created
  /// or destroyed, an extent, class or sees set), to a value no other store ever had: equal
  /// versions mean equal ids, extents, classes and sees. (A GPU interest engine skips uploading
  /// them then.)
  [[nodiscard]] std::uint64_t layout_version() const { return layout_version_; }
  /// Dense index by slot (0xffffffff: none), slot_count() entries: the map index_of reads.
  [[nodiscard]] std::span<const std::uint32_t> slot_dense() const { return slot_dense_; }

 private:
  void bump_layout();
  std::size_t capacity_;
  std::uint64_t layout_version_ = 0;
  // Sparse side, by slot.
  std::vector<std::uint32_t> slot_dense_;       // dense index of the slot's entity, or invalid_dense
  std::vector<std::uint16_t> slot_generation_;  // generation of the slot's current (or next) entity
  std::vector<std::uint32_t> free_slots_;       // LIFO
  // Dense side.
  std::vector<entity_id> ids_;
  std::vector<vec3> position_, velocity_, aoi_half_, presence_half_;
  std::vector<std::uint32_t> visibility_class_, sees_;
  std::vector<entity_kind> kind_;
};

// ---------------------------------------------------------------------------------------------
// Interest tracking.

struct interest_options {
  /// Hysteresis margin h (metres, >= 0): an entity enters A's view when its presence box meets
  /// A's AOI box, and leaves only when it no longer meets A's AOI box grown by h on every side.
  float hysteresis = 4.0f;
  /// Keep at most this many entities per observer, the closest (0 = no cap). See docs/zone.md.
  std::uint32_t max_visible = 0;
  /// Observers per parallel task (fixed, so output never depends on the thread count).
  std::uint32_t rows_per_task = 256;
};

/// Counters and phase times of the last update.
struct interest_stats {
  std::uint64_t pairs = 0;       ///< pairs found with the grown AOI boxes
  std::uint64_t candidates = 0;  ///< (observer, target) candidates after the self/visibility filter
  std::uint64_t visible = 0;     ///< sum of visible-set sizes
  std::uint64_t enters = 0;
  std::uint64_t leaves = 0;
  std::uint64_t capped = 0;  ///< entities dropped by the max_visible cap
  double boxes_ms = 0, find_ms = 0, diff_ms = 0;
  /// Parts of diff_ms: counting candidates per row, row offsets, filling the rows, the per-row
  /// sort-and-merge with the previous sets (the rest: presence records, previous rows, stats).
  double count_ms = 0, offsets_ms = 0, fill_ms = 0, rows_ms = 0;
  /// The update ran on the visibility engine (set_engine): then find_ms is the engine's whole
  /// call, boxes_ms and the parts above are 0, diff_ms is the host's bookkeeping (previous rows,
  /// row map), and `engine_timing` says where the engine's time went.
  bool on_engine = false;
  interest::visibility_timing engine_timing;
};

/// Per-observer visible sets with enter/leave events and hysteresis, on top of any pair_finder.
///
/// Every entity is an observer (players and NPCs alike: NPC perception uses the same sets).
/// After update(), row r (= the entity's dense index in the store at that moment) holds the
/// observer's visible set and this tick's enter and leave events, each sorted ascending by handle.
/// A visible set never contains the observer itself. Output is deterministic: it depends only on
/// the store's contents and the previous tick, not on the finder's pair order or the thread count.
/// Memory is reused between ticks: no allocation in steady state beyond growth.
class interest_tracker {
 public:
  /// `finder` and `pool` must outlive the tracker; `pool` may be null (single-threaded).
  interest_tracker(interest::pair_finder& finder, interest::thread_pool* pool = nullptr, interest_options opt = {});

  /// One tick: builds the boxes, finds the pairs, updates visible sets and events. On error (a
  /// non-finite position or extent) nothing changes and the error names the entity.
  [[nodiscard]] std::optional<interest::box_error> update(const entity_store& store);

  /// The two halves of update(), for callers that find pairs themselves (e.g. a GPU pipeline):
  /// build_boxes writes entity k's AOI box grown by the hysteresis margin as box 2k (category
  /// aoi, mask = sees) and its presence box as box 2k+1 (category = class, mask 0);
  /// apply_pairs takes every qualifying pair of exactly those boxes (any order, each once). It
  /// refuses (error, nothing changes) a box set whose size is not 2 * store.size() or a pair with
  /// an id beyond it.
  void build_boxes(const entity_store& store, interest::box_set& out) const;
  [[nodiscard]] std::optional<interest::box_error> apply_pairs(const entity_store& store, const interest::box_set& boxes,
                                                               std::span<const interest::id_pair> pairs);

  /// Finds the pairs of a box set into a view the callee owns (valid until its next call).
  using pair_view_source = std::function<std::optional<interest::box_error>(const interest::box_set&,
                                                                            std::span<const interest::id_pair>&)>;
  /// When set, update() finds the pairs through `source` instead of finder.find into a list of
  /// its own: for the GPU finders, gpu::find_view hands over the finder's pinned result buffer
  /// and saves copying every pair once more (docs/zone.md). Empty: back to finder.find.
  void set_pair_view_source(pair_view_source source) { view_source_ = std::move(source); }

  /// When set (non-null; it must outlive the tracker or be unset first), update() runs the whole
  /// interest step on the engine (the GPU: gpu/visibility.h) instead of the finder and the host
  /// diff, with the same result. Not used while max_visible != 0 (the cap is host-only), and not
  /// after the engine failed once (engine_error() says why; the host path takes over).
  void set_engine(interest::visibility_engine* engine);
  /// Which observers' visible sets are read on the host right after an update (by slot: non-zero
  /// = read; slots beyond the vector: not read), so that an engine copies only those back; any
  /// other row's set is fetched from the engine on first access (visible() stays exact for every
  /// row). Null (the default): every row's. The vector must outlive the tracker or be unset.
  void set_view_demand(const std::vector<std::uint8_t>* by_slot) { view_demand_ = by_slot; }
  /// Why the engine was given up (empty while it works or when none is set).
  [[nodiscard]] const std::string& engine_error() const { return engine_error_; }
  /// Tells the engine (if any) that an update follows soon (see visibility_engine::prepare).
  void prepare() noexcept {
    if (engine_ != nullptr && engine_error_.empty()) engine_->prepare();
  }
  /// True when the last update ran on the engine.
  [[nodiscard]] bool last_update_on_engine() const { return last_by_engine_; }
  /// The last update's visible sets where the engine keeps them (its device), by this tracker's
  /// rows, for a replication engine on the same device to read in place; empty when the last
  /// update did not run on an engine or the engine keeps none.
  [[nodiscard]] interest::visibility_engine::resident_lists resident_visible() const {
    if (!last_by_engine_ || engine_ == nullptr || !engine_error_.empty()) return {};
    const auto r = engine_->resident_visible();
    return r.rows == ids_.size() ? r : interest::visibility_engine::resident_lists{};
  }

  /// Rows of the last update (= the store's size then).
  [[nodiscard]] std::size_t observer_count() const { return ids_.size(); }
  [[nodiscard]] entity_id observer(std::size_t row) const { return ids_[row]; }
  /// Row of an observer in the last update, or entity_store::npos.
  [[nodiscard]] std::size_t row_of(entity_id id) const;

  /// Safe to call from several threads at once (the first access to a row whose set the engine
  /// kept on the device fetches them all, once).
  [[nodiscard]] std::span<const entity_id> visible(std::size_t row) const {
    if (partial_ && demand_rows_[row] == 0) return fetched_row(row);
    return vis_list_.row(row);
  }
  [[nodiscard]] std::span<const entity_id> enters(std::size_t row) const { return enter_list_.row(row); }
  [[nodiscard]] std::span<const entity_id> leaves(std::size_t row) const { return leave_list_.row(row); }

  /// 64-bit hash of the last update's output (observers, visible sets, enters, leaves, in row
  /// order): equal across runs, finders and thread counts for equal inputs.
  [[nodiscard]] std::uint64_t digest() const;

  [[nodiscard]] const interest_stats& stats() const { return stats_; }
  [[nodiscard]] const interest_options& options() const { return opt_; }
  /// Takes effect at the next update (the margin applies to the sets kept from this tick).
  void set_options(const interest_options& opt) { opt_ = opt; }
  /// The boxes of the last update (build_boxes' layout).
  [[nodiscard]] const interest::box_set& boxes() const { return boxes_; }

 private:
  void process_rows(const entity_store& store, std::size_t first, std::size_t last);
  [[nodiscard]] std::optional<interest::box_error> update_on_engine(const entity_store& store);
  [[nodiscard]] std::optional<interest::box_error> update_on_host(const entity_store& store);
  [[nodiscard]] std::optional<interest::box_error> name_box_error(const entity_store& store,
                                                                  std::optional<interest::box_error> err) const;
  void adopt_engine_output();  // the engine's last output into the host path's arrays
  [[nodiscard]] std::span<const entity_id> fetched_row(std::size_t row) const;
  void point_lists_at_host();
  void map_rows(const entity_store& store);  // row_of_slot_ for the rows of this update
  void map_rows_into(const entity_store& store, const std::vector<entity_id>& ids,
                     std::vector<std::uint32_t>& row_of_slot) const;
  /// One kind of per-row list: row r is data[off[r], off[r] + len[r]) (len null: off[r + 1]).
  struct row_lists {
    const entity_id* data = nullptr;
    const std::uint32_t* off = nullptr;
    const std::uint32_t* len = nullptr;
    [[nodiscard]] std::span<const entity_id> row(std::size_t r) const {
      return {data + off[r], len != nullptr ? len[r] : off[r + 1] - off[r]};
    }
  };
  struct presence_box {
    float lo_x, lo_y, lo_z, hi_x, hi_y, hi_z;
  };

  interest::pair_finder* finder_;
  pair_view_source view_source_;
  interest::thread_pool* pool_;
  interest_options opt_;
  interest_stats stats_;
  interest::box_set boxes_;
  interest::pair_list pairs_;

  // This tick, by row. Visible sets and enters share the candidate offsets (capacity per row =
  // candidate count); leaves are laid out by the previous set's size.
  std::vector<entity_id> ids_;
  std::vector<std::uint32_t> vis_off_;  // size rows + 1
  std::vector<std::uint32_t> vis_len_, enter_len_, leave_off_, leave_len_;
  std::vector<entity_id> vis_, enter_, leave_;
  std::vector<std::uint64_t> cand_;         // candidates by row: (target handle << 32) | target dense index
  std::vector<std::uint32_t> task_cursor_;   // per (pair task, row): candidate count, then fill cursor
  std::vector<std::uint64_t> chunk_base_;    // per chunk of rows: its first candidate (a scan)
  std::vector<std::size_t> task_bad_;        // per pair task: first pair with an id beyond the set
  std::vector<std::uint64_t> cap_keys_;      // (distance key << 32) | handle, for the cap
  std::vector<std::uint32_t> prev_row_;    // previous row of each row's observer, or none
  std::vector<presence_box> presence_;     // presence box by dense index (from the box set)

  // The previous tick.
  std::vector<entity_id> prev_ids_;
  std::vector<std::uint32_t> prev_off_, prev_len_;
  std::vector<entity_id> prev_vis_;
  std::vector<std::uint32_t> row_of_slot_;  // slot -> row in the last update (checked against ids)
  std::uint64_t capped_pending_ = 0;        // summed by the row tasks (atomic_ref)

  // What the accessors read: the host path's arrays, or the engine's output.
  row_lists vis_list_, enter_list_, leave_list_;
  interest::visibility_engine* engine_ = nullptr;
  interest::visibility_output engine_out_;
  bool engine_synced_ = false;  // the engine holds the last update's sets
  std::vector<entity_id> next_ids_;                 // engine path: this update's rows, swapped in on success
  std::vector<std::uint32_t> spare_row_of_slot_;    // engine path: this update's slot map, likewise
  const std::vector<std::uint8_t>* view_demand_ = nullptr;
  std::vector<std::uint8_t> demand_rows_, next_demand_rows_;  // per row of the last / next update
  bool partial_ = false;  // vis_list_ holds the demanded rows only; the rest via fetched_row
  mutable std::mutex fetch_mutex_;
  mutable std::atomic<bool> fetched_{false};
  mutable row_lists full_list_;
  bool last_by_engine_ = false;
  std::string engine_error_;
};

// ---------------------------------------------------------------------------------------------
// Replication: one tick_update per client per tick.

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
  /// on the thread count).
  std::uint32_t clients_per_task = 16;
  /// build_many snapshots the entities (one quantization per entity instead of one per update
  /// sent) when clients * snapshot_entities_per_client >= entities; 0 = never. The frames are the
  /// same either way.
  std::uint32_t snapshot_entities_per_client = 16;
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
  /// The client's entity changed (respawn); its view is kept and converges as usual.
  void set_observer(client_id c, entity_id observer);
  /// The client lost frames: the next frame resets its view and starts it again.
  void resync(client_id c);

  /// Builds this tick's frame for client c into `writer`; the span is valid until the writer's
  /// next build. `stats`, when given, receives what was sent and deferred.
  [[nodiscard]] std::span<const std::uint8_t> build(client_id c, const entity_store& store,
                                                    const interest_tracker& tracker, std::uint64_t tick,
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
  void build_many(std::span<const replication_request> requests, const entity_store& store,
                  const interest_tracker& tracker, std::uint64_t tick, std::uint64_t server_time_us,
                  interest::thread_pool* pool, const frame_sink& sink, const chunk_sink& chunk_done = {});

  /// Runs build_many's decisions on `engine` (interest/replication_engine.h; the GPU:
  /// gpu/replication.h), which then holds the clients' views; null: back to the CPU. The frames
  /// are byte for byte those of the CPU path (tests/zone/test_zone_gpu.cpp). Every active client's
  /// next frame is a reset (the views start over on the new side). `engine` must outlive the
  /// replicator or be unset first. If the engine fails (a device error), build_many gives it up
  /// for good (engine_error() says why) and builds that tick and the next on the CPU, every
  /// client's next frame a reset. With an engine, build() must not be called, and view() is empty
  /// (the view lives on the engine); view_hash() and view_size() stay exact.
  void set_engine(interest::replication_engine* engine);
  /// True while build_many runs on the engine.
  [[nodiscard]] bool on_engine() const { return engine_ != nullptr && engine_error_.empty(); }
  /// Why the engine was given up (empty while it works or when none is set).
  [[nodiscard]] const std::string& engine_error() const { return engine_error_; }

  /// The client's view as sent so far (sorted ids; empty on an engine) and its digest hash.
  [[nodiscard]] std::span<const entity_id> view(client_id c) const { return clients_[c].view; }
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
    std::vector<entity_id> view;  // sorted
    std::vector<view_meta> meta;  // parallel to view
    std::uint64_t hash = 0;
    std::uint32_t engine_view_size = 0;  // with an engine: its view's size after the last frame
  };
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
                                           const interest_tracker& tracker, std::uint64_t tick,
                                           std::uint64_t server_time_us, std::uint32_t last_input_sequence,
                                           replication_writer& writer, replication_stats* stats);
  /// Starts loading what building client c will read first (its state and lists).
  void prefetch_client(client_id c) const;
  /// build_many on the engine (throws what the engine throws, before any frame reaches the sink).
  void build_on_engine(std::span<const replication_request> requests, const entity_store& store,
                       const interest_tracker& tracker, std::uint64_t tick, std::uint64_t server_time_us,
                       interest::thread_pool* pool, const frame_sink& sink, const chunk_sink& chunk_done);
  /// Every active client starts over (its next frame is a reset).
  void reset_all_clients();

  replication_options opt_;
  net::position_quantizer quantizer_;
  tier_bound near_, mid_;
  std::uint32_t mid_period_, far_period_;  // at least 1
  std::vector<client_state> clients_;
  std::vector<client_id> free_clients_;
  std::vector<std::unique_ptr<replication_writer>> writers_;  // one per build_many task (thread)
  std::vector<entity_snapshot> snapshot_;                     // build_many's, by dense index
  interest::replication_engine* engine_ = nullptr;
  std::string engine_error_;
  std::vector<std::uint32_t> job_visible_;  // build_on_engine: visible-set size, then offset, by request
};

// ---------------------------------------------------------------------------------------------
// Configuration.

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
  /// loop wakes the workers this long before a tick is due; -1 = auto: 1000 on hosts with at
  /// least 8 hardware threads, else 0 (a small machine's cores are better left to others).
  int worker_spin_us = -1;
  // Interest.
  /// Pair finder (gpu/finders.h): "auto" (chosen per tick: a GPU finder when a device is usable,
  /// else the CPU grid finder), "cpu", "gpu" (= "pbig"), "pbig", "lbvh", "brute".
  std::string finder = "auto";
  /// Where the interest step runs: "auto" (the GPU visibility engine, gpu/visibility.h, when a
  /// device is usable and max_visible is 0; else the host path), "gpu" (the engine, or refuse to
  /// start), "host" (the pair finder above and the host diff).
  std::string interest = "auto";
  /// Where replication's per-client decisions run: "auto" (the GPU replication engine,
  /// gpu/replication.h, when a device is usable; else the CPU replicator), "gpu" (the engine, or
  /// refuse to start), "cpu". The frames are the same either way (docs/zone.md).
  std::string replicate = "auto";
  /// With both engines on the GPU: copy the players' visible sets back to the host after every
  /// interest step (true), or let the replication engine read them on the device only (false:
  /// ~0.3 ms less per tick at 20,000 clients, docs/zone-benchmarks.md). With false a GPU that
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
  std::size_t socket_send_buffer = 0;  ///< SO_SNDBUF per client socket (bytes; 0 = the system's autotuning)
  /// The replication worker that built a frame writes it to the socket itself when nothing is
  /// queued ahead of it (net::server_options::direct_writes); false (the default): the I/O
  /// threads write. On the H100 host direct writes cut latency but doubled the replicate phase
  /// (the kernel's send is then the tick's CPU): docs/zone-benchmarks.md.
  bool direct_writes = false;
  int io_nice = 0;  ///< nice value of the I/O threads (net::server_options::io_thread_nice; 0-19)
  /// How the I/O threads write (net::server_options::batching): "auto" (io_uring where the kernel
  /// allows it, else sendmsg), "io_uring" (or refuse to start), "sendmsg".
  std::string write_batching = "auto";
  double inputs_per_second = 60;
  double pings_per_second = 10;  ///< per client; over it pings get no pong (net::server_options)
  /// Admission (net::server_options): a connection must complete its hello within hello_timeout_s
  /// of accept; connections without a hello are capped in total and per source address, apart
  /// from the max_clients player slots.
  double hello_timeout_s = 3;
  std::size_t max_pending = 1024;
  std::size_t max_pending_per_address = 256;
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
  /// Where populate() places NPCs and towns (x, y; z from world): the zone's region in a world.
  /// Empty (lo == hi) = the whole world.
  net::world_bounds spawn_area{};
  // The live viewer (docs/viewer.md), served beside /metrics: off unless enabled.
  bool viewer_enabled = false;   ///< serve /viewer and /viewer/ws
  bool viewer_remote = false;    ///< also to peers that are not on a loopback address
  std::size_t max_viewers = 4;   ///< viewer pages at once
  double viewer_hz = 10;         ///< snapshots a second while a page is open (at most the tick rate)
  // Correctness (docs/bots.md, the oracle).
  /// Publish every tick's ground truth on a loopback stream (127.0.0.1:oracle_port; 0 = an
  /// ephemeral port, told in the welcome): what an independent oracle checks each client's view
  /// against. Off: nothing is built or sent.
  bool oracle = false;
  std::uint16_t oracle_port = 0;
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

/// zone_config::worker_spin_us resolved (-1 = auto: 1000 us with >= 8 hardware threads, else 0).
[[nodiscard]] unsigned worker_spin(const zone_config& c);

/// Parses the command line; `--config FILE` reads an INI-style file of the same option names
/// (the command line wins). Unknown options and bad values are errors naming the option.
[[nodiscard]] config_result parse_config(int argc, const char* const* argv);
/// Checks a config's values (positive rates and sizes, ordered bounds, ...).
[[nodiscard]] std::optional<std::string> validate(const zone_config& c);

// ---------------------------------------------------------------------------------------------
// The simulated world: NPC behaviours, movement and interest, one deterministic step per tick.

/// Latency histogram with 4 logarithmic buckets per octave from about 1 microsecond to 16 s.
/// percentile() answers with the upper edge of the bucket holding that quantile (at most 19% above
/// the true value), never above the maximum recorded. Not thread-safe.
class latency_histogram {
 public:
  void record(double ms);
  [[nodiscard]] double percentile(double q) const;
  [[nodiscard]] double max() const { return max_; }
  [[nodiscard]] double sum() const { return sum_; }
  [[nodiscard]] std::uint64_t count() const { return count_; }
  void clear();
  static constexpr int bucket_count = 96;
  [[nodiscard]] static double bucket_upper_ms(int b);  ///< upper edge of bucket b
  [[nodiscard]] std::uint64_t bucket(int b) const { return counts_[static_cast<std::size_t>(b)]; }

 private:
  std::uint64_t counts_[bucket_count]{};
  std::uint64_t count_ = 0;
  double max_ = 0;
  double sum_ = 0;
};

/// Phase timings of zone_world::step (milliseconds).
struct tick_phases {
  latency_histogram behaviours, integrate, interest, total;
};

/// The ms of one step's phases (zone_world::last_step): what the step also recorded in tick_phases.
struct step_times {
  double behaviours = 0, integrate = 0, interest = 0, total = 0;
};

/// Entities, NPC behaviours and interest of one zone. step() is deterministic: the same config,
/// seed and calls give the same positions and visible sets whatever the thread count.
class zone_world {
 public:
  /// `finder` and `pool` must outlive the world; `pool` may be null.
  zone_world(const zone_config& cfg, interest::pair_finder& finder, interest::thread_pool* pool);

  /// Creates the NPCs and bosses of the config (deterministic in cfg.seed).
  void populate();
  /// A player entity at `at` (clamped into the world); null_entity when the zone is full.
  [[nodiscard]] entity_id spawn_player(const vec3& at);
  bool despawn(entity_id id);
  /// An entity with a given behaviour state (a world's ghost or handed-off entity); null_entity
  /// when the description is invalid or the zone is full.
  [[nodiscard]] entity_id adopt(const entity_desc& d, const behaviour_state& b);
  /// The behaviour state of a live entity.
  [[nodiscard]] std::optional<behaviour_state> behaviour_state_of(entity_id id) const;
  /// Replaces a live entity's behaviour state (false for a dead handle).
  bool set_behaviour_state(entity_id id, const behaviour_state& b);
  /// A player's movement intent: its length is clamped to 1 and scaled by player_speed, so a
  /// client can never move faster than allowed (any finite intent, however large, keeps its
  /// direction: no overflow to zero or infinity); its z is dropped unless player_fly. false
  /// (ignored) for a non-player or dead handle, or a non-finite intent.
  bool set_intent(entity_id player, const vec3& intent);
  /// A player's teleport jump to `to`, clamped into the world (`*clamped` says whether it was);
  /// the next step() integrates and finds interest from there, so the jump's enters and leaves
  /// come in that tick. false (nothing moves) for a non-player, a dead handle or a non-finite `to`.
  bool teleport(entity_id player, const vec3& to, bool* clamped = nullptr);

  /// One tick: behaviours decide velocities (from the previous tick's positions and visible sets),
  /// positions integrate inside the world bounds, interest updates.
  [[nodiscard]] std::optional<interest::box_error> step();

  [[nodiscard]] std::uint64_t tick() const { return tick_; }
  [[nodiscard]] entity_store& store() { return store_; }
  [[nodiscard]] const entity_store& store() const { return store_; }
  [[nodiscard]] const interest_tracker& tracker() const { return tracker_; }
  /// See interest_tracker::set_pair_view_source.
  void set_pair_view_source(interest_tracker::pair_view_source source) {
    tracker_.set_pair_view_source(std::move(source));
  }
  /// Entities whose visible sets a viewer reads after each step (net/viewer.h): with a GPU
  /// engine their rows are copied back with the players' from the next step on. Replaces the
  /// previous list; dead handles are ignored.
  void set_watched(std::span<const entity_id> ids);
  /// A tick follows soon: see interest_tracker::prepare.
  void prepare() noexcept { tracker_.prepare(); }
  /// See interest_tracker::set_engine.
  void set_visibility_engine(interest::visibility_engine* engine) { tracker_.set_engine(engine); }
  /// Whether the players' visible sets are copied back to the host after each interest step
  /// (interest_tracker::set_view_demand; default true: the CPU replicator reads them). A GPU
  /// replication engine that reads them in place on the device (replicator::set_engine) needs
  /// no copy; a row not copied is still fetched on first access, so the CPU path stays exact.
  void set_player_views_on_host(bool on);
  [[nodiscard]] behaviour behaviour_of(entity_id id) const;
  [[nodiscard]] const tick_phases& phases() const { return phases_; }
  /// The phases of the last step() alone (per-tick series: bench-zone --csv, zone-server --tick-csv).
  [[nodiscard]] const step_times& last_step() const { return last_step_; }
  [[nodiscard]] const zone_config& config() const { return cfg_; }
  [[nodiscard]] vec3 town(std::size_t t) const { return towns_[t]; }
  [[nodiscard]] std::size_t town_count() const { return towns_.size(); }
  /// Hash of every position and of the tracker's output after the last step.
  [[nodiscard]] std::uint64_t digest() const;

 private:
  using npc_state = behaviour_state;
  void decide(std::size_t first, std::size_t last);
  [[nodiscard]] std::uint64_t noise(entity_id id, std::uint64_t salt) const;
  [[nodiscard]] vec3 clamp_to_world(const vec3& p) const;
  [[nodiscard]] net::world_bounds spawn_area() const;

  zone_config cfg_;
  interest::thread_pool* pool_;
  entity_store store_;
  interest_tracker tracker_;
  std::vector<npc_state> by_slot_;  // indexed by slot_of(id)
  /// By slot: 1 where by_slot_'s kind is player. What the chasers' scan reads: a byte a slot
  /// (1 MB a million entities) instead of a 32-byte state.
  std::vector<std::uint8_t> is_player_;
  void set_state(entity_id id, const npc_state& st);
  std::vector<std::uint8_t> reads_view_;  // by slot: the entity's visible set is read each tick
  bool player_views_on_host_ = true;
  void set_reads_view(entity_id id, bool reads);
  std::vector<entity_id> watched_;  // set_watched
  std::vector<vec3> towns_;
  std::uint64_t tick_ = 0;
  tick_phases phases_;
  step_times last_step_;
};

}  // namespace zone
