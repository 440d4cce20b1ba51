// interest/interest_space.h: the tick-level API a game server calls (docs/embedding.md, "The tick
// API"). Register each entity with its AOI box, presence box, visibility class and the classes it
// sees; move it, resize it, teleport it, remove it; call step() once a tick; read, per observer,
// the enter and leave events of that step (with hysteresis) and the visible set.
//
//   zone::interest::interest_space space({.where = zone::interest::backend::cpu});
//   const auto guard = space.add({.position = {10, 10, 0}});
//   const auto thief = space.add({.position = {30, 10, 0}, .visibility_class = category_bits::stealth});
//   space.move(thief, {12, 10, 0});
//   if (auto err = space.step()) { /* err->message names the entity */ }
//   for (auto seen : space.entered(guard)) { /* send `seen`'s full state to the guard's client */ }
//
// Rules of the step (docs/zone.md, "Interest tracker"): entity j is a candidate of observer i
// (i != j) when j's presence box meets i's AOI box grown by the hysteresis margin h on every side
// and j's class is among those i sees; a candidate that was in i's visible set after the previous
// step stays, any other enters only if its presence box meets i's exact AOI box; entries of the
// previous set that are no candidates leave. Boxes are closed; every list is sorted by handle.
//
// Threads and lifetimes: an interest_space is not thread-safe for mutation. add, remove, move,
// teleport, resize_*, set_classes, step and set_backend must not run concurrently with any other
// call on the same space; between two such calls the const reads (visible, entered, left, alive,
// get, the columns) may run from any number of threads at once. Spans returned by the reads stay
// valid until the next non-const call. The finder, pool and engine maker of space_options must
// outlive the space. Handles are generation-checked: a removed entity's handle is refused by every
// call (until its slot's generation wraps after 1,023 reuses, each after 1,024 other slots were
// freed: space_slot_reuse_after).
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "interest.h"
#include "interest_tracker.h"
#include "visibility_engine.h"

namespace zone::interest {

/// Slot bits of an interest_space's handles: (generation << space_slot_bits) | slot.
inline constexpr unsigned space_slot_bits = 22;
/// Most entities alive at once in one space (4,194,304).
inline constexpr std::size_t space_max_entities = std::size_t{1} << space_slot_bits;
/// The highest generation of a slot (then it wraps to 1).
inline constexpr std::uint32_t space_max_generation = (1u << (32 - space_slot_bits)) - 1;
/// By default a freed slot is reused only once this many other slots were freed after it (first
/// freed, first reused), or when no new slot is left: a destroyed entity's handle comes back only
/// after its slot's 1,023 reuses, so after at least 1,023 x 1,024 destroys in the space, however
/// few entities churn. It costs up to this many slots beyond the live entities (slot_count()).
/// space_options::slot_reuse_after sets it.
inline constexpr std::size_t space_slot_reuse_after = 1024;

/// Where the step runs. `gpu`: the GPU visibility engine (needs space_options::gpu); `cpu`: the
/// host engine (host_visibility_engine.h: candidates on the presence grid, or by space_options'
/// finder when one is given, then the diff); `automatic`: the GPU when an engine
/// can be made and max_visible is 0, else the CPU. The results are the same on either.
enum class backend { cpu, gpu, automatic };
/// "cpu", "gpu", "auto"; nothing for another name.
[[nodiscard]] std::optional<backend> parse_backend(std::string_view name);

/// Makes a visibility engine, or returns null with the reason in `*why`. The GPU library provides
/// one (gpu/visibility.h: gpu::make_visibility_engine); interest/ itself knows no device.
using engine_maker = std::function<std::unique_ptr<visibility_engine>(thread_pool* pool, std::string* why)>;

struct space_options {
  backend where = backend::cpu;
  /// The engine for backend gpu and automatic (e.g. zone::gpu::make_visibility_engine). Empty:
  /// automatic means cpu, gpu is refused.
  engine_maker gpu{};
  /// The CPU backend's pair finder (not owned). Null: the CPU backend finds the candidates on a
  /// grid of the presence boxes (interest_options::presence_grid), with a grid finder of the
  /// space's own behind it for the rare sets the presence grid declines.
  pair_finder* finder = nullptr;
  /// Worker threads for the step (not owned; null: the calling thread only).
  thread_pool* pool = nullptr;
  /// Hysteresis margin h (metres, >= 0).
  float hysteresis = 4.0f;
  /// Keep at most this many entities per observer, the closest (0: no cap). The cap runs on the
  /// CPU only: automatic then picks cpu, gpu is refused.
  std::uint32_t max_visible = 0;
  /// Most entities alive at once (at most space_max_entities).
  std::size_t capacity = space_max_entities;
  /// A freed slot is reused once this many others were freed after it (space_slot_reuse_after;
  /// 0: at once, the most recently freed first: a handle then recurs after 1,023 reuses of its
  /// slot, which one entity churning in and out reaches in 1,023 destroys).
  std::size_t slot_reuse_after = space_slot_reuse_after;
};

/// An entity as registered: both boxes are centred on `position`.
struct entity_spec {
  vec3 position{};
  vec3 aoi_half{50, 50, 50};          ///< the AOI box: position +- this (metres, >= 0)
  vec3 presence_half{0.5f, 0.5f, 1};  ///< the presence box (body, footprint): position +- this
  /// The one class bit of its presence box (never category_bits::aoi).
  std::uint32_t visibility_class = category_bits::normal;
  /// The classes its AOI box sees (never containing category_bits::aoi; 0: sees nothing).
  std::uint32_t sees = category_bits::normal | category_bits::team_red | category_bits::team_blue;
  friend bool operator==(const entity_spec&, const entity_spec&) = default;
};

/// Why a spec is unacceptable (nothing when it is fine): non-finite numbers, negative extents, a
/// class that is not exactly one non-aoi bit, or `sees` holding the aoi bit.
[[nodiscard]] std::optional<std::string> validate(const entity_spec& s);

/// The entities of one zone and their interest, stepped once a tick. Entities live in dense
/// columns (index 0 .. size() - 1); remove() moves the last entity into the hole, so indices
/// change on remove, handles do not.
class interest_space {
 public:
  /// Throws std::invalid_argument for backend gpu when no engine can be made (the reason in the
  /// message) or max_visible is set, and for a negative or non-finite hysteresis.
  explicit interest_space(space_options options = {});
  ~interest_space();
  interest_space(const interest_space&) = delete;
  interest_space& operator=(const interest_space&) = delete;

  // ---- Entities (take effect at the next step) ----
  /// Registers an entity; null_entity (the reason in `*error` when given) for an invalid spec or
  /// a full space.
  [[nodiscard]] entity_id add(const entity_spec& s, std::string* error = nullptr);
  /// false (nothing changes) for a null, stale or unknown handle. The entity's observers get it
  /// as a leave at the next step; its own lists are gone.
  bool remove(entity_id id);
  /// New position; false for a dead handle or a non-finite position.
  bool move(entity_id id, const vec3& position);
  /// A jump to `to`. The step has no notion of paths, so it is judged like move(): by where the
  /// entity is at the next step, with the same hysteresis. Named apart for callers' clarity.
  bool teleport(entity_id id, const vec3& to) { return move(id, to); }
  /// New AOI or presence half-extents; false for a dead handle or an extent not finite and >= 0.
  bool resize_aoi(entity_id id, const vec3& half);
  bool resize_presence(entity_id id, const vec3& half);
  /// New class and seen classes; false for a dead handle or invalid bits (see entity_spec).
  bool set_classes(entity_id id, std::uint32_t visibility_class, std::uint32_t sees);
  void clear();  ///< removes every entity (their handles are refused from then on)
  void reserve(std::size_t n);

  [[nodiscard]] bool alive(entity_id id) const { return index_of(id) != npos; }
  [[nodiscard]] std::optional<entity_spec> get(entity_id id) const;
  [[nodiscard]] std::size_t size() const { return ids_.size(); }
  [[nodiscard]] std::size_t capacity() const { return capacity_; }
  /// Dense index of a live entity, npos otherwise.
  [[nodiscard]] std::size_t index_of(entity_id id) const {
    const std::uint32_t slot = id & slot_mask;
    if (id == null_entity || slot >= slot_dense_.size()) return npos;
    const std::uint32_t dense = slot_dense_[slot];
    if (dense >= ids_.size() || ids_[dense] != id) return npos;  // a free slot holds 0xffffffff
    return dense;
  }
  static constexpr std::size_t npos = static_cast<std::size_t>(-1);
  static constexpr std::uint32_t slot_mask = (1u << space_slot_bits) - 1;

  // Dense columns (index = dense index). Positions are writable in bulk (a server's movement
  // pass); step() refuses non-finite ones, naming the entity.
  [[nodiscard]] std::span<const entity_id> ids() const { return ids_; }
  [[nodiscard]] std::span<vec3> positions() { return position_; }
  [[nodiscard]] std::span<const vec3> positions() const { return position_; }
  [[nodiscard]] std::span<const vec3> aoi_halves() const { return aoi_half_; }
  [[nodiscard]] std::span<const vec3> presence_halves() const { return presence_half_; }
  [[nodiscard]] std::span<const std::uint32_t> visibility_classes() const { return visibility_; }
  [[nodiscard]] std::span<const std::uint32_t> sees() const { return sees_; }
  /// One past the highest slot ever used (sizes per-slot tables).
  [[nodiscard]] std::size_t slot_count() const { return slot_dense_.size(); }
  /// Dense index by slot (0xffffffff: free), slot_count() entries.
  [[nodiscard]] std::span<const std::uint32_t> slot_dense() const { return slot_dense_; }
  /// Changes whenever anything but positions changed (an entity added or removed, an extent or
  /// class set), to a value no other space ever had.
  [[nodiscard]] std::uint64_t layout_version() const { return layout_version_; }
  /// The columns as the tracker takes them.
  [[nodiscard]] entity_columns columns() const;

  // ---- The step ----
  /// One tick: the visible sets and events of every entity from the current columns. On invalid
  /// input (a non-finite position, say) nothing changes and the error names the entity.
  [[nodiscard]] std::optional<box_error> step();

  /// The observer's visible set, entered and left entities of the last step (sorted handles);
  /// empty for an entity that was not alive at that step.
  [[nodiscard]] std::span<const entity_id> visible(entity_id observer) const;
  [[nodiscard]] std::span<const entity_id> entered(entity_id observer) const;
  [[nodiscard]] std::span<const entity_id> left(entity_id observer) const;

  // ---- Backend ----
  /// The backend the next step runs on (cpu or gpu, never automatic).
  [[nodiscard]] backend current_backend() const;
  /// Why automatic chose the CPU, or why the GPU engine was given up after a device error (the
  /// step then ran on the CPU, with the same result); empty otherwise.
  [[nodiscard]] std::string backend_note() const;
  /// Switches the backend between steps (the visible sets carry over: no spurious events).
  /// backend gpu: makes the engine if there is none yet; false (nothing changes) when it cannot,
  /// with the reason in `*why`. backend cpu always succeeds.
  bool set_backend(backend b, std::string* why = nullptr);

  // ---- In-tree extensions (the zone server, bench-zone) ----
  /// Runs the step on `engine` (not owned, must outlive the space or be replaced first; null:
  /// the CPU), e.g. a wrapper of the GPU engine that injects faults.
  void use_engine(visibility_engine* engine);
  /// The tracker behind the step (row-indexed lists, stats, the device view of the sets:
  /// interest_tracker::resident_visible).
  [[nodiscard]] const interest_tracker& tracker() const { return tracker_; }
  /// See interest_tracker::set_view_demand, set_options, prepare.
  void set_view_demand(const std::vector<std::uint8_t>* by_slot) { tracker_.set_view_demand(by_slot); }
  /// See interest_tracker::set_while_device_works.
  void set_while_device_works(const std::function<void()>* work) { tracker_.set_while_device_works(work); }
  void set_tracker_options(const interest_options& o) { tracker_.set_options(o); }
  void prepare() noexcept { tracker_.prepare(); }
  /// See interest_tracker::carry_visible: `observer` starts the next step with `targets` as its
  /// previous visible set (a handoff's view from the old zone).
  void carry_visible(entity_id observer, std::span<const entity_id> targets) { tracker_.carry_visible(observer, targets); }

 private:
  void bump_layout();
  [[nodiscard]] std::size_t row_of(entity_id observer) const;
  space_options opt_;
  std::size_t capacity_;
  std::uint64_t layout_version_ = 0;
  std::unique_ptr<pair_finder> own_finder_;
  std::unique_ptr<visibility_engine> own_engine_;
  visibility_engine* engine_ = nullptr;  // in use (own_engine_ or use_engine's), null: cpu
  std::string note_;
  interest_tracker tracker_;
  std::vector<std::uint32_t> slot_dense_;
  std::vector<std::uint16_t> slot_generation_;
  std::vector<std::uint32_t> free_slots_;  // first freed first: [free_head_, size())
  std::size_t free_head_ = 0;
  std::vector<entity_id> ids_;
  std::vector<vec3> position_, aoi_half_, presence_half_;
  std::vector<std::uint32_t> visibility_, sees_;
};

}  // namespace zone::interest
