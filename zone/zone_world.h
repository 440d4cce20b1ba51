// zone/zone_world.h: the simulated world: NPC behaviours, movement and interest, one
// deterministic step per tick.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <vector>

#include "interest/interest.h"
#include "interest/thread_pool.h"
#include "zone/entity_store.h"
#include "interest/interest_tracker.h"
#include "net/latency_histogram.h"
#include "zone/zone_config.h"

namespace zone {

// The interest layer's tracker under the names zone code has always used.
using interest::interest_options;
using interest::interest_stats;
using interest::interest_tracker;

/// Latencies in milliseconds (tick phases, /metrics, handoffs): net/latency_histogram.h.
using latency_histogram = net::latency_histogram_ms;

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
  /// The interest step on `finder` (the CPU backend until set_visibility_engine); `finder` and
  /// `pool` must outlive the world; `pool` may be null.
  zone_world(const zone_config& cfg, interest::pair_finder& finder, interest::thread_pool* pool);
  /// The interest step as `interest` says (interest_setup.h builds it from the config: backend,
  /// finder, pool); its hysteresis and max_visible are the config's. Throws what
  /// interest::interest_space's constructor throws.
  zone_world(const zone_config& cfg, interest::space_options interest);

  /// Creates the NPCs and bosses of the config (deterministic in cfg.seed).
  void populate();
  /// A player entity at `at` (clamped into the world) with the visibility a player's choice
  /// gives (visibility_for); null_entity when the zone is full.
  [[nodiscard]] entity_id spawn_player(const vec3& at, bool stealth = false, std::uint8_t team = 0);
  /// Where the player keyed `key` (a session id) spawns: uniformly within spawn_radius of town
  /// `key % town_count()`, deterministic in the key, and inside the spawn area (a world zone's
  /// region, config.spawn_area), so no player is born on a neighbour's side of a border.
  [[nodiscard]] vec3 player_spawn_point(std::uint64_t key) const;
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
  [[nodiscard]] const interest_tracker& tracker() const { return store_.space().tracker(); }
  /// The interest step (the tick API, interest/interest_space.h): its backend can be switched here.
  [[nodiscard]] interest::interest_space& interest() { return store_.space(); }
  [[nodiscard]] const interest::interest_space& interest() const { return store_.space(); }
  /// Whether the host path reads the finder's own result buffer (interest_options::finder_view;
  /// default true).
  void set_finder_view(bool on) {
    auto o = tracker().options();
    o.finder_view = on;
    store_.space().set_tracker_options(o);
  }
  /// Whether the host path finds the candidates on a grid of the presence boxes instead of
  /// through the pair finder (interest_options::presence_grid; default false). The same output.
  void set_presence_grid(bool on) {
    auto o = tracker().options();
    o.presence_grid = on;
    store_.space().set_tracker_options(o);
  }
  /// Entities whose visible sets a viewer reads after each step (net/viewer.h): with a GPU
  /// engine their rows are copied back with the players' from the next step on. Replaces the
  /// previous list; dead handles are ignored.
  void set_watched(std::span<const entity_id> ids);
  /// A tick follows soon: see interest_tracker::prepare.
  void prepare() noexcept { store_.space().prepare(); }
  /// See interest::interest_space::use_engine.
  void set_visibility_engine(interest::visibility_engine* engine) { store_.space().use_engine(engine); }
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
  entity_store store_;  // with the interest step (store_.space())
  std::vector<npc_state> by_slot_;  // indexed by slot_of(id)
  /// By slot: 1 where the entity is a player (spawned as one, or adopted with kind player: a
  /// world's ghost of a player or a handed-off one; set_state and adopt keep it as long as
  /// by_slot_). What the chasers' scan reads: a byte a slot
  /// (1 MB a million entities) instead of a 32-byte state.
  std::vector<std::uint8_t> is_player_;
  /// By slot (as long as by_slot_): the heading a wanderer took for its current wander period,
  /// for the entity it was taken for. Computed once a period instead of every tick: the same
  /// floats (cos and sin of the same angle), so the world moves exactly as before.
  struct heading_cache {
    entity_id id = null_entity;
    std::uint64_t period = ~std::uint64_t{0};
    float cos = 0, sin = 0;
  };
  std::vector<heading_cache> headings_;
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
