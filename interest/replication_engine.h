// interest/replication_engine.h: replication's per-client decisions (zone::replicator, docs/zone.md
// "Replication") as one engine call for every client of a tick, run where the engine runs (the
// GPU: gpu/replication.h) and holding each client's view (sorted ids, last-sent tick) there.
// Plain arrays only, so that the GPU layer can implement it without knowing the zone's types (as
// interest/visibility_engine.h). zone::replicator uses an engine when one is set
// (set_engine) and is the reference it is tested against byte for byte (tests/zone/test_zone_gpu.cpp).
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>

#include "visibility_engine.h"

namespace zone::interest {

/// One entity by dense index, 32 bytes, as the store has it: position, handle, velocity. The engine
/// quantizes each entity's wire update itself (zone::replicator's net::position_quantizer and
/// net::quantize_velocity, the same double operations), so the host only copies.
struct replication_entity {
  float x, y, z;
  std::uint32_t id;
  float vx, vy, vz;
  std::uint32_t pad;
};
static_assert(sizeof(replication_entity) == 32);

/// The rules of a tick (zone::replication_options, resolved).
struct replication_rules {
  std::uint64_t tick = 0;  ///< last-sent ticks are kept modulo 2^32, as the CPU replicator does
  std::uint64_t server_time_us = 0;  ///< the frames' server_time_us
  /// Which frames carry the digest: 0 none, 1 reset frames only, 2 every frame.
  std::uint32_t digest = 0;
  std::uint64_t byte_budget = 0;
  /// net::frame_cost: header, self position, per enter, leave, update.
  std::uint32_t header_cost = 0, self_cost = 0, enter_cost = 0, leave_cost = 0, update_cost = 0;
  /// Tiers: sqrt(d2) < limit, decided on d2 below below_sq, false above above_sq, else by the root.
  float near_limit = 0, near_below_sq = 0, near_above_sq = 0;
  float mid_limit = 0, mid_below_sq = 0, mid_above_sq = 0;
  std::uint32_t mid_period = 1, far_period = 1;  ///< at least 1
  std::uint32_t slot_mask = 0;                   ///< handle -> slot (the slot map's index)
  /// Position quantization (net::position_quantizer): the world's low corner and the step per
  /// axis (0: that axis is always 0).
  float quant_lo[3] = {0, 0, 0};
  double quant_step[3] = {0, 0, 0};
};

/// The layout the engine writes each frame in: net::canonical_tick_update (docs/protocol.md) as
/// plain numbers, filled by zone::replicator from net/protocol.h so that the engine needs no
/// protocol header. The engine writes every byte of a frame except three fields of each enter's
/// table (visibility class, presence half extents, kind), which the caller fills in (enters are
/// few, and those fields are not on the device).
struct replication_frame_format {
  /// The tick_update table for one combination of optional parts: its place, its size, its
  /// vtable's size and each field's offset in it (0: absent), in schema order.
  struct table {
    std::uint16_t at = 0, size = 0, vtable = 0;
    std::uint16_t field[10] = {};
  };
  /// By parts: bit 0 enters, 1 leaves, 2 updates, 3 digest, 4 self position, 5 deferred, 6 reset.
  table tables[128];
  std::uint16_t enter_vtable[10] = {};  ///< the enters' shared vtable (its 20 bytes)
  std::uint32_t enter_table = 0;         ///< bytes of one enter's table (and then its empty name)
  std::uint32_t enter_name = 0;
  std::uint32_t prefix_bytes = 0;        ///< the length prefix (the frame's size minus this)
  std::uint32_t header_max = 0;          ///< the largest tables[i].at + size
  std::uint8_t identifier[4] = {};       ///< the file identifier after the root offset
  std::uint32_t message_type = 0;        ///< the envelope's type byte for a tick_update
};
inline constexpr std::uint32_t frame_part_enters = 1, frame_part_leaves = 2, frame_part_updates = 4,
                               frame_part_digest = 8, frame_part_self = 16, frame_part_deferred = 32,
                               frame_part_reset = 64;

/// One client's frame to decide.
struct replication_job {
  std::uint32_t client = 0;    ///< < client_count; at most one job per client per run
  std::uint32_t flags = 0;     ///< job_reset: drop the client's view first
  std::uint32_t observer = 0;  ///< its entity's handle: the eye is its position when it is live
  std::uint32_t last_input = 0;  ///< the frame's last_input_sequence
  /// Its visible set (sorted handles): staging.visible[visible_off, + visible_len); or, when run()
  /// is given resident rows, row visible_off of those (no_row: none) and visible_len unused.
  std::uint32_t visible_off = 0, visible_len = 0;
};
inline constexpr std::uint32_t no_row = 0xffffffffu;
inline constexpr std::uint32_t job_reset = 1u;
/// In replication_result::flags: the observer was live (eye is its position; else eye is 0).
inline constexpr std::uint32_t result_has_self = 1u;

/// What the engine decided for a job. Its frame (frame_size bytes at record_off into
/// output::records, 8-byte aligned) is the whole tick_update in the replication_frame_format,
/// except for the enters' class, half extents and kind (enters_at: the first enter's table; each
/// enter's table and name take enter_table + enter_name bytes, closest first).
struct replication_result {
  std::uint32_t record_off = 0;
  std::uint32_t frame_size = 0, enters_at = 0;
  std::uint32_t leaves = 0, enters = 0, updates = 0;
  std::uint32_t deferred_leaves = 0, deferred_enters = 0, deferred_updates = 0;
  std::uint32_t view_size = 0;  ///< the client's view after this frame
  std::uint64_t hash = 0;       ///< its digest hash (net::digest_add over the view)
  float eye[3] = {0, 0, 0};     ///< the observer's position (0 without result_has_self)
  std::uint32_t flags = 0;      ///< result_has_self
};
static_assert(sizeof(replication_result) == 64);

/// Where the engine's time went in the last run.
struct replication_timing {
  double upload_ms = 0, device_ms = 0, download_ms = 0, total_ms = 0;
  /// Of total_ms, the host waiting for the device (its synchronisations).
  double wait_ms = 0;
  std::uint64_t record_bytes = 0;  ///< bytes of records copied back
  bool resident = false;           ///< the visible sets were read in place (resident rows)
  std::uint32_t dozes = 0;         ///< waits that slept first (device_wait::doze)
  /// Of total_ms, growing the engine's device and pinned buffers (freeing the old, allocating
  /// the new: a cudaFree waits for the device, a cudaHostAlloc pins every page).
  double alloc_ms = 0;
  /// The frames were handed on in a pinned buffer the caller holds (records_keep: no copy on
  /// the host); false when every such buffer was still held (slow clients) and they were copied.
  bool kept = false;
};

class replication_engine {
 public:
  replication_engine() = default;
  replication_engine(const replication_engine&) = delete;
  replication_engine& operator=(const replication_engine&) = delete;
  virtual ~replication_engine() = default;

  /// Staging memory (pinned where the engine has a device) the caller fills before run(); valid
  /// until the next stage() call. entities by dense index; slot_dense by slot (0xffffffff: no
  /// entity); jobs; visible: the jobs' visible sets.
  struct staging {
    replication_entity* entities = nullptr;
    std::uint32_t* slot_dense = nullptr;
    replication_job* jobs = nullptr;
    std::uint32_t* visible = nullptr;
  };
  [[nodiscard]] virtual staging stage(std::size_t entities, std::size_t slots, std::size_t jobs,
                                      std::size_t visible) = 0;
  /// Ahead of stage() (optional: an engine without it returns nulls): staging for the entities
  /// and the slot map alone, which the caller fills and then hands over with upload_entities()
  /// (the engine copies them to its device at once, e.g. while another engine works). A stage()
  /// with the same two counts keeps them and run() does not copy them again; discard_entities(),
  /// or a stage() with other counts, drops them (then the caller fills them in stage()'s).
  [[nodiscard]] virtual staging stage_entities(std::size_t entities, std::size_t slots) {
    (void)entities, (void)slots;
    return {};
  }
  virtual void upload_entities() {}
  virtual void discard_entities() {}

  struct output {
    const replication_result* results = nullptr;  ///< one per job, in job order
    std::uint8_t* records = nullptr;  ///< the frames (the caller fills in the enters' three fields)
    /// When set: the engine will not reuse `records` while any copy of this lives, so the caller
    /// may hand the frames on without copying them (holding a copy per frame, or per group of
    /// frames, until each is sent). Null when the engine reuses its buffer on the next run (then
    /// copy what must outlive it).
    std::shared_ptr<const void> records_keep;
  };
  /// Decides every staged job's frame (zone::replicator's algorithm, the same integers and the same
  /// float operations) and moves each job's client view on. Clients are numbered below
  /// client_count; those without a job keep their views. The output stays valid until the next
  /// stage() or run(). Throws std::runtime_error on a device error (then call forget_all()), and
  /// std::invalid_argument when a client's view or visible set is longer than 2^29 entries.
  /// With `rows` (non-null, from visibility_engine::resident_visible of an engine on the same
  /// device; only when reads_resident()), each job's visible set is read there in place, by row.
  /// `while_waiting` (non-null and non-empty): host work that needs none of the output, called
  /// once on the calling thread after the device's work is queued and before run() waits for it
  /// (as visibility_input::while_waiting), so that it runs in the device's shadow. An engine
  /// without a device calls it once anywhere in run(). If run() throws, it may not have been
  /// called (zone::replicator then runs it itself); exceptions it throws pass through run().
  /// A pointer, so that the caller passes a std::function holding a std::ref (no allocation a tick).
  [[nodiscard]] virtual output run(const replication_rules& rules, std::size_t client_count,
                                   const visibility_engine::resident_lists* rows = nullptr,
                                   const std::function<void()>* while_waiting = nullptr) = 0;
  /// Whether run() can read a GPU visibility engine's resident rows.
  [[nodiscard]] virtual bool reads_resident() const { return false; }

  /// The layout of the frames run() writes; before the first run().
  virtual void set_frame_format(const replication_frame_format& format) = 0;
  /// How run() waits for the device (engines without a device ignore it):
  ///  - spin: in a busy loop (the CUDA default);
  ///  - block: the thread sleeps until the device signals: no CPU burnt while it waits, but on the
  ///    H100 host the wake-up put the wait's p99 at 4-6 ms against 2.3 spinning;
  ///  - doze: sleeps through most of the wait it expects (the shortest of that wait's last eight,
  ///    less a quarter of it and at least 0.15 ms, when that is 0.4 ms or more), then spins: the
  ///    spin's CPU time mostly saved, the wake-up's delay hidden inside the device's work (the
  ///    GPU engine's default: on the H200 host 0.28 against 0.32 us of CPU per client, the tick
  ///    no slower).
  enum class device_wait { spin, block, doze };
  virtual void set_device_wait(device_wait how) { (void)how; }

  /// Drops every client's view (the next job of each must have job_reset).
  virtual void forget_all() = 0;
  /// Between runs, with the caller idle until `deadline`: grows the engine's buffers ahead of the
  /// next runs' needs, as far as the time allows, so that their growth does not land in a run
  /// (on the GPU a cudaFree waits for the device and a cudaHostAlloc of megabytes pins every page:
  /// 7-13 ms at 20,000 clients on the H200 host). Returns the milliseconds it spent; nothing by
  /// default.
  virtual double grow_ahead(std::chrono::steady_clock::time_point deadline) {
    (void)deadline;
    return 0;
  }
  [[nodiscard]] virtual const replication_timing& timing() const = 0;
  [[nodiscard]] virtual const char* name() const = 0;
};

}  // namespace zone::interest
