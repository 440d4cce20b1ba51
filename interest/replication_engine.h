// interest/replication_engine.h: replication's per-client decisions (zone::replicator, docs/zone.md
// "Replication") as one engine call for every client of a tick, run where the engine runs (the
// GPU: gpu/replication.h) and holding each client's view (sorted ids, last-sent tick) there.
// Plain arrays only, so that the GPU layer can implement it without knowing the zone's types (as
// interest/visibility_engine.h). zone::replicator uses an engine when one is set
// (set_engine) and is the reference it is tested against byte for byte (tests/zone/test_zone_gpu.cpp).
#pragma once

#include <cstddef>
#include <cstdint>

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

/// One client's frame to decide.
struct replication_job {
  std::uint32_t client = 0;    ///< < client_count; at most one job per client per run
  std::uint32_t flags = 0;     ///< job_reset: drop the client's view first
  std::uint32_t observer = 0;  ///< its entity's handle: the eye is its position when it is live
  /// Its visible set (sorted handles): staging.visible[visible_off, + visible_len); or, when run()
  /// is given resident rows, row visible_off of those (no_row: none) and visible_len unused.
  std::uint32_t visible_off = 0, visible_len = 0;
};
inline constexpr std::uint32_t no_row = 0xffffffffu;
inline constexpr std::uint32_t job_reset = 1u;
/// In replication_result::flags: the observer was live (eye is its position; else eye is 0).
inline constexpr std::uint32_t result_has_self = 1u;

/// What the engine decided for a job. Its record (at record_off bytes into output::records, 4-byte
/// aligned) holds the leaves sent (ids, view order), then the enters sent (dense index, id: pairs of
/// u32, closest first), then the updates sent (16-byte wire updates, in frame order).
struct replication_result {
  std::uint32_t record_off = 0;
  std::uint32_t leaves = 0, enters = 0, updates = 0;
  std::uint32_t deferred_leaves = 0, deferred_enters = 0, deferred_updates = 0;
  std::uint32_t view_size = 0;  ///< the client's view after this frame
  std::uint64_t hash = 0;       ///< its digest hash (net::digest_add over the view)
  float eye[3] = {0, 0, 0};     ///< the observer's position (0 without result_has_self)
  std::uint32_t flags = 0;      ///< result_has_self
};
static_assert(sizeof(replication_result) == 56);

/// Where the engine's time went in the last run.
struct replication_timing {
  double upload_ms = 0, device_ms = 0, download_ms = 0, total_ms = 0;
  /// Of total_ms, the host waiting for the device (its synchronisations).
  double wait_ms = 0;
  std::uint64_t record_bytes = 0;  ///< bytes of records copied back
  bool resident = false;           ///< the visible sets were read in place (resident rows)
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

  struct output {
    const replication_result* results = nullptr;  ///< one per job, in job order
    const std::uint8_t* records = nullptr;
  };
  /// Decides every staged job's frame (zone::replicator's algorithm, the same integers and the same
  /// float operations) and moves each job's client view on. Clients are numbered below
  /// client_count; those without a job keep their views. The output stays valid until the next
  /// stage() or run(). Throws std::runtime_error on a device error (then call forget_all()).
  /// With `rows` (non-null, from visibility_engine::resident_visible of an engine on the same
  /// device; only when reads_resident()), each job's visible set is read there in place, by row.
  [[nodiscard]] virtual output run(const replication_rules& rules, std::size_t client_count,
                                   const visibility_engine::resident_lists* rows = nullptr) = 0;
  /// Whether run() can read a GPU visibility engine's resident rows.
  [[nodiscard]] virtual bool reads_resident() const { return false; }

  /// How run() waits for the device: blocking (the thread sleeps until the device signals; no CPU
  /// burnt, a wake-up's latency added) or spinning (the CUDA default). Engines without a device
  /// ignore it.
  virtual void set_blocking_wait(bool blocking) { (void)blocking; }

  /// Drops every client's view (the next job of each must have job_reset).
  virtual void forget_all() = 0;
  [[nodiscard]] virtual const replication_timing& timing() const = 0;
  [[nodiscard]] virtual const char* name() const = 0;
};

}  // namespace zone::interest
