// zone/entity_store.h: the zone's entities, a dense structure-of-arrays store with
// generation-checked handles (docs/zone.md, "Entity storage").
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "interest/interest.h"
#include "interest/interest_space.h"
#include "interest/interest_tracker.h"

namespace zone {

/// A generation-checked entity handle: (generation << entity_index_bits) | slot. Generations run
/// 1 .. 2^(32 - entity_index_bits) - 1 and wrap back to 1, so a handle is never 0 (null_entity).
/// A stale handle (its entity destroyed, even if the slot was reused) is rejected by every lookup
/// until the slot's generation wraps around (max_generation = 1,023 reuses of that one slot; a
/// freed slot is reused only after 1,024 other frees: interest::space_slot_reuse_after).
/// 22 slot bits: up to 4,194,304 entities in one zone (20 bits capped a zone at 1,048,576, below
/// what the GPU interest engine steps in a tick; docs/zone-benchmarks.md, "Growth").
using interest::entity_id;
using interest::null_entity;
inline constexpr unsigned entity_index_bits = interest::space_slot_bits;
inline constexpr std::uint32_t entity_index_mask = (1u << entity_index_bits) - 1;
/// Most entities alive at once in one store.
inline constexpr std::size_t max_entities = interest::space_max_entities;
/// The highest generation of a slot (then it wraps to 1).
inline constexpr std::uint32_t max_generation = interest::space_max_generation;

[[nodiscard]] constexpr std::uint32_t slot_of(entity_id id) { return id & entity_index_mask; }
[[nodiscard]] constexpr std::uint32_t generation_of(entity_id id) { return id >> entity_index_bits; }

using interest::vec3;

enum class entity_kind : std::uint8_t { player, npc, boss };

/// An entity whose visibility class or mask was changed (its values before): a client may hold
/// it with its old class, so after the step the zone sends those clients a class note or resyncs
/// them (replicator::resync_viewers_of). A player's own set_visibility, and a world's ghost or
/// handed-off entity whose class its owner changed (world::zone_link), give one.
struct class_change {
  entity_id entity = null_entity;
  std::uint32_t old_class = 0, old_sees = 0;
};

/// A player's visibility from its choice (docs/zone.md, "Visibility classes and teams"): its
/// presence class is normal unless stealthed; stealthed, it is its team's class (team_red,
/// team_blue: seen by that team only) or, without a team, stealth (seen by no player). Its AOI
/// sees normal and its own team's class. team: 0 none, 1 red, 2 blue (others: treated as none;
/// the server validates before).
struct player_visibility {
  std::uint32_t visibility_class = interest::category_bits::normal;
  std::uint32_t sees = interest::category_bits::normal;
};
[[nodiscard]] constexpr player_visibility visibility_for(bool stealth, std::uint8_t team) {
  const std::uint32_t team_bit = team == 1   ? interest::category_bits::team_red
                                 : team == 2 ? interest::category_bits::team_blue
                                             : 0u;
  player_visibility v;
  v.visibility_class = !stealth ? interest::category_bits::normal : team_bit != 0 ? team_bit : interest::category_bits::stealth;
  v.sees = interest::category_bits::normal | team_bit;
  return v;
}

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

/// The zone's entities: an interest::interest_space (the tick-level API: handles, positions,
/// boxes, classes, the interest step) with the zone's own columns beside it (velocity, kind), in
/// the same dense order. Live entities occupy dense indices [0, size()); destroy() moves the last
/// entity into the hole, so dense indices are not stable across destroys, handles are. Not
/// thread-safe for mutation; concurrent reads are fine.
class entity_store {
 public:
  /// `capacity`: most entities alive at once (at most max_entities); `interest`: the space's
  /// step (its backend, finder, pool, hysteresis; its capacity is `capacity`).
  explicit entity_store(std::size_t capacity = max_entities, interest::space_options interest = {});

  /// Creates an entity. Returns null_entity, with the reason in `*error` when given, if the
  /// description is invalid or the store is full.
  [[nodiscard]] entity_id create(const entity_desc& d, std::string* error = nullptr);
  /// Destroys a live entity; false (and nothing changes) for a null, stale or unknown handle.
  bool destroy(entity_id id);
  [[nodiscard]] bool alive(entity_id id) const { return space_.alive(id); }
  /// Dense index of a live entity, npos otherwise. Inline: replication looks up every entry of
  /// every client's view each tick.
  [[nodiscard]] std::size_t index_of(entity_id id) const { return space_.index_of(id); }
  static constexpr std::size_t npos = interest::interest_space::npos;

  [[nodiscard]] std::size_t size() const { return space_.size(); }
  [[nodiscard]] bool empty() const { return space_.size() == 0; }
  [[nodiscard]] std::size_t capacity() const { return space_.capacity(); }
  void clear();
  void reserve(std::size_t n);

  /// The description of a live entity.
  [[nodiscard]] std::optional<entity_desc> get(entity_id id) const;

  // Checked setters (false for a dead handle or an invalid value; nothing changes then).
  bool set_position(entity_id id, const vec3& p) { return space_.move(id, p); }
  bool set_velocity(entity_id id, const vec3& v);
  bool set_aoi_half_extent(entity_id id, const vec3& h) { return space_.resize_aoi(id, h); }
  bool set_presence_half_extent(entity_id id, const vec3& h) { return space_.resize_presence(id, h); }
  /// Also records the change in the class journal (class_changes_since).
  bool set_visibility(entity_id id, std::uint32_t visibility_class, std::uint32_t sees);

  // Dense columns, index = dense index. Positions and velocities are writable in bulk (the
  // movement systems); the interest step rejects non-finite values naming the entity.
  [[nodiscard]] std::span<const entity_id> ids() const { return space_.ids(); }
  [[nodiscard]] std::span<vec3> positions() { return space_.positions(); }
  [[nodiscard]] std::span<const vec3> positions() const { return space_.positions(); }
  [[nodiscard]] std::span<vec3> velocities() { return velocity_; }
  [[nodiscard]] std::span<const vec3> velocities() const { return velocity_; }
  [[nodiscard]] std::span<const std::uint32_t> visibility_classes() const { return space_.visibility_classes(); }
  [[nodiscard]] std::span<const std::uint32_t> sees() const { return space_.sees(); }
  [[nodiscard]] std::span<const vec3> aoi_half_extents() const { return space_.aoi_halves(); }
  [[nodiscard]] std::span<const vec3> presence_half_extents() const { return space_.presence_halves(); }
  [[nodiscard]] std::span<const entity_kind> kinds() const { return kind_; }

  /// One past the highest slot index ever used (sizes per-slot side tables of other systems).
  [[nodiscard]] std::size_t slot_count() const { return space_.slot_count(); }

  /// Changes whenever anything but positions and velocities may have changed (an entity created
  /// or destroyed, an extent, class or sees set), to a value no other store ever had: equal
  /// versions mean equal ids, extents, classes and sees. (A GPU interest engine skips uploading
  /// them then.)
  [[nodiscard]] std::uint64_t layout_version() const { return space_.layout_version(); }
  /// Entries of the class journal: the latest set_visibility calls, each with the layout
  /// versions just before and after it.
  static constexpr std::size_t class_journal_size = 1024;
  /// For a consumer holding a copy of the classes as of layout version `since` (the live viewer's
  /// snapshot): calls `changed(dense)` for each entity whose class (or mask) was set since, in
  /// order (an entity may come more than once), and returns true, when the layout changed since
  /// `since` by set_visibility calls only (no entity created or destroyed, no extent set, so the
  /// ids and dense order are those of `since`) and all of them are still in the journal (the
  /// latest class_journal_size). Otherwise returns false without calling `changed`: copy all.
  /// `since` equal to layout_version(): true, no call.
  template <class F>
  bool class_changes_since(std::uint64_t since, F&& changed) const {
    const std::size_t n = std::min(journal_count_, journal_.size());
    std::uint64_t expect = layout_version();
    std::size_t k = 0;  // entries back from the newest that lead from `since` to now
    while (expect != since) {
      if (k == n) return false;
      const class_journal_entry& e = journal_[(journal_count_ - 1 - k) % journal_.size()];
      if (e.after != expect) return false;  // a change other than set_visibility in between
      expect = e.before;
      ++k;
    }
    for (std::size_t j = k; j-- > 0;) changed(std::size_t{journal_[(journal_count_ - 1 - j) % journal_.size()].dense});
    return true;
  }
  /// Dense index by slot (0xffffffff: none), slot_count() entries: the map index_of reads.
  [[nodiscard]] std::span<const std::uint32_t> slot_dense() const { return space_.slot_dense(); }
  /// The interest columns of the live entities (row = dense index), for interest_tracker::update;
  /// valid until the store changes.
  [[nodiscard]] interest::entity_columns columns() const { return space_.columns(); }

  /// The interest step of these entities (the tick API the zone is built on).
  [[nodiscard]] interest::interest_space& space() { return space_; }
  [[nodiscard]] const interest::interest_space& space() const { return space_; }

 private:
  struct class_journal_entry {
    std::uint64_t before = 0, after = 0;  ///< layout versions around one set_visibility
    std::uint32_t dense = 0;              ///< the entity's dense index
  };

  interest::interest_space space_;
  std::vector<vec3> velocity_;
  std::vector<entity_kind> kind_;
  /// A ring of the latest set_visibility calls (class_changes_since): journal_count_ calls ever
  /// recorded, the newest at (journal_count_ - 1) % size. Allocated once, at construction.
  std::vector<class_journal_entry> journal_ = std::vector<class_journal_entry>(class_journal_size);
  std::size_t journal_count_ = 0;
};

}  // namespace zone
