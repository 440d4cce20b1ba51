// Public API of the world layer: several zone servers that together serve one seamless space
// (docs/world.md; docs/architecture.md, "Past one machine"). This header is transport-free: the
// layout of regions, the ghost and handoff wire formats, and zone_link, the per-zone logic that
// gives every entity a world-wide id, builds and applies ghost messages and hands entities off
// exactly once.
// world/nats_node.h carries these over NATS (built when libnats is found).
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <unordered_map>
#include <utility>
#include <vector>

#include "zone/token.h"
#include "zone/zone.h"

namespace zone::world {

/// A world-wide entity id: (region + 1) << 48 | incarnation << 32 | counter. The incarnation
/// (the region's claim count, from KV) makes ids of a restarted zone differ from its predecessor's.
using global_id = std::uint64_t;
[[nodiscard]] constexpr std::uint32_t region_of_gid(global_id g) { return static_cast<std::uint32_t>(g >> 48) - 1; }
[[nodiscard]] constexpr std::uint32_t incarnation_of_gid(global_id g) {
  return static_cast<std::uint32_t>(g >> 32) & 0xffffu;
}

/// A client's token (a redirect's, welcome.resume_token), read by zone::parse_token (zone/token.h):
/// (region + 1) << 48 | 48 random bits, naming the region whose zone holds the entity. The region
/// it names (nullopt: not a token, or none).
[[nodiscard]] std::optional<std::uint32_t> token_region(std::string_view token);

/// An axis-aligned rectangle in x, y: [lo, hi) on both axes (the last column / row also owns hi).
struct rect {
  float lo_x = 0, lo_y = 0, hi_x = 0, hi_y = 0;
  /// Per-axis distance from (x, y) to the rectangle (0 inside): the larger of the two.
  [[nodiscard]] float distance(float x, float y) const;
  friend bool operator==(const rect&, const rect&) = default;
};

/// The world split into cols x rows equal rectangular regions; region r = row * cols + col.
class layout {
 public:
  layout() = default;
  layout(const net::world_bounds& bounds, std::uint32_t cols, std::uint32_t rows);
  [[nodiscard]] std::uint32_t count() const { return cols_ * rows_; }
  [[nodiscard]] std::uint32_t cols() const { return cols_; }
  [[nodiscard]] std::uint32_t rows() const { return rows_; }
  [[nodiscard]] const net::world_bounds& bounds() const { return bounds_; }
  [[nodiscard]] rect region(std::uint32_t r) const;
  /// The region holding (x, y); points outside the bounds belong to the nearest region.
  [[nodiscard]] std::uint32_t region_at(float x, float y) const;
  /// The regions touching r (edges and corners), ascending.
  [[nodiscard]] std::vector<std::uint32_t> neighbours(std::uint32_t r) const;
  /// "cols rows lo.x lo.y lo.z hi.x hi.y hi.z" (what KV holds) and back (nullopt when malformed).
  [[nodiscard]] std::string encode() const;
  [[nodiscard]] static std::optional<layout> decode(std::string_view text);
  friend bool operator==(const layout&, const layout&) = default;

 private:
  net::world_bounds bounds_{};
  std::uint32_t cols_ = 1, rows_ = 1;
};

// ---------------------------------------------------------------------------------------------
// Wire formats (little-endian, versioned by a magic number; decoders reject anything malformed).

/// One ghost: an entity of the sender as its neighbour needs it for interest. Positions are
/// quantized like replication's (net::position_quantizer over the world bounds); half-extents in
/// 1/16 m (exact for the defaults).
struct ghost_entry {
  global_id gid = 0;
  std::array<std::uint16_t, 3> position{};
  std::array<std::uint16_t, 3> aoi_half{}, presence_half{};
  std::uint32_t visibility_class = 0, sees = 0;
  std::uint8_t kind = 0;
  std::uint8_t flags = 0;  ///< ghost_in_transit: handed off by the sender, not yet confirmed
  friend bool operator==(const ghost_entry&, const ghost_entry&) = default;
};
inline constexpr std::uint8_t ghost_in_transit = 1;
inline constexpr std::size_t ghost_entry_bytes = 36;

/// One message from a zone to one neighbour per tick: what changed since the last one (or, with
/// `snapshot`, the whole set). `seq` counts the messages to that neighbour from 1; a receiver that
/// sees a gap asks for a snapshot and applies nothing until it comes.
struct ghost_message {
  std::uint32_t from = 0, to = 0;
  std::uint64_t seq = 0, tick = 0;
  bool snapshot = false;
  /// Handoffs the sender can still adopt (link_options::capacity less what it owns; no_limit:
  /// no capacity set). A zone hands nothing to a neighbour that said 0 (it keeps the entity).
  std::uint32_t room = no_limit;
  static constexpr std::uint32_t no_limit = 0xffffffffu;
  std::vector<ghost_entry> entries;  ///< new or changed (snapshot: all)
  std::vector<global_id> removed;    ///< gone from the band since the last message (empty in a snapshot)
};
[[nodiscard]] std::vector<std::uint8_t> encode(const ghost_message& m);
[[nodiscard]] std::optional<ghost_message> decode_ghosts(std::span<const std::uint8_t> bytes);
inline constexpr std::size_t ghost_header_bytes = 40;

/// An entity moving from one zone to the next, with everything needed to go on simulating it.
struct handoff_record {
  global_id gid = 0;
  std::uint64_t epoch = 0;  ///< ownership epoch after this handoff (the first owner has 0)
  std::uint32_t from = 0, to = 0;
  entity_desc desc;
  behaviour_state behaviour;
  std::uint64_t token = 0;           ///< non-zero: a client follows with this token (a redirect)
  std::uint64_t owner_revision = 0;  ///< KV revision of the ownership record after the CAS (0: none)
  std::uint32_t last_input = 0;      ///< the client's last input sequence applied
  std::uint64_t sent_us = 0;         ///< CLOCK_MONOTONIC when the sender decided (latency on one host)
  std::uint64_t sent_tick = 0;       ///< the sender's tick then
  /// The entity's visible set at the old owner after its last step, as world-wide ids (at most
  /// max_handoff_visible): the new owner's tracker takes it as the entity's previous set, so
  /// targets held by hysteresis stay in view across the handoff (docs/world.md, "Handoff").
  std::vector<global_id> visible;
  friend bool operator==(const handoff_record&, const handoff_record&) = default;
};
/// Most world-wide ids a handoff record carries in `visible` (8 bytes each): collect_handoffs
/// keeps the first this many (ascending local handles), a decoder refuses a record with more.
inline constexpr std::size_t max_handoff_visible = 16384;
/// Wire format "HOF2" (with `visible`); a decoder also takes "HOF1" records (no `visible`: empty).
[[nodiscard]] std::vector<std::uint8_t> encode(const handoff_record& r);
[[nodiscard]] std::optional<handoff_record> decode_handoff(std::span<const std::uint8_t> bytes);

/// A part of a zone's checkpoint ("CKP1"): records to restore its entities from (link's
/// checkpoint()), a JetStream message each (docs/world.md, "Checkpoints").
struct checkpoint_chunk {
  std::uint32_t region = 0, incarnation = 0;
  std::uint64_t generation = 0;  ///< the checkpoint's number (the zone counts them from 1)
  std::uint64_t tick = 0;
  std::vector<handoff_record> records;
  friend bool operator==(const checkpoint_chunk&, const checkpoint_chunk&) = default;
};
[[nodiscard]] std::vector<std::uint8_t> encode(const checkpoint_chunk& c);
[[nodiscard]] std::optional<checkpoint_chunk> decode_checkpoint_chunk(std::span<const std::uint8_t> bytes);

/// A whole checkpoint's head ("CKH1"), written after its chunks: where they are (their stream
/// sequences), so a reader never mixes two checkpoints.
struct checkpoint_head {
  std::uint32_t region = 0, incarnation = 0;
  std::uint64_t generation = 0, tick = 0, entities = 0;
  std::vector<std::uint64_t> chunks;  ///< stream sequence of each chunk, in order
  friend bool operator==(const checkpoint_head&, const checkpoint_head&) = default;
};
[[nodiscard]] std::vector<std::uint8_t> encode(const checkpoint_head& h);
[[nodiscard]] std::optional<checkpoint_head> decode_checkpoint_head(std::span<const std::uint8_t> bytes);
/// Most chunks a head names (a decoder refuses more).
inline constexpr std::size_t max_checkpoint_chunks = 4096;

// ---------------------------------------------------------------------------------------------
// The per-zone logic.

struct link_options {
  layout map;
  std::uint32_t region = 0;
  std::uint32_t incarnation = 1;  ///< < 2^16
  /// Owned entities within this distance (per axis) of a neighbour's rectangle are its ghosts.
  /// It must cover the largest AOI + hysteresis + presence half-extent any entity can have, plus
  /// handoff_margin and a tick's movement: see ghost_band().
  float ghost_band = 0;
  /// An entity this far (per axis) outside its zone's rectangle moves to the zone it is in.
  float handoff_margin = 8;
  /// A neighbour silent this many ticks loses its ghosts here; an in-transit ghost that its new
  /// owner has not confirmed within it goes too.
  std::uint32_t ghost_timeout_ticks = 60;
  /// Most entities this zone owns: a handoff that would exceed it is not adopted (no_room: the
  /// record waits and is offered again; docs/world.md, "A full zone"). 0: only the store's
  /// capacity bounds it.
  std::size_t capacity = 0;
  /// Keep an entity past the border while the neighbour it would go to says it has no room (its
  /// ghost messages tell its room): the entity stays owned, simulated and served here, and is
  /// handed off once the neighbour has room. Off: it is handed off anyway and its record waits
  /// on the stream until the neighbour adopts it (the entity unseen meanwhile once its
  /// in-transit copy expires). Records can still meet a full zone (two neighbours filling its
  /// last room in one tick, a neighbour not heard yet): they wait on the stream.
  bool hold_for_room = true;
};

/// The band a zone config needs: the largest AOI its entities get (players, NPC tiers 0-2, and
/// with bosses the gigantic tier) + hysteresis + the largest presence half-extent (a boss's
/// footprint) + handoff margin + two ticks of the fastest movement + 1 m. Every zone of a world
/// must run the same entity config (docs/world.md).
[[nodiscard]] float ghost_band(const zone_config& c, float handoff_margin);

struct link_stats {
  std::uint64_t ghost_messages_out = 0, ghost_bytes_out = 0, ghost_messages_in = 0, ghost_bytes_in = 0;
  std::uint64_t snapshots_out = 0, snapshots_in = 0, gaps = 0, stale = 0, bad = 0;
  std::uint64_t handoffs_out = 0, handoffs_in = 0, handoff_duplicates = 0, handoffs_refused = 0;
  std::uint64_t handoffs_no_room = 0;  ///< offers of a record refused for want of room (each retry counts)
  /// Ticks an entity past the border stayed here because its neighbour said it had no room
  /// (hold_for_room), summed over the entities.
  std::uint64_t handoffs_held_for_room = 0;
  std::uint64_t ghosts_expired = 0;
  std::uint64_t restored = 0;  ///< entities taken back from a checkpoint (restore)
};

/// What apply_ghosts made of a message.
enum class ghost_status { applied, gap, stale, bad };
/// What apply_handoff made of a record. `no_room`: the zone is full (link_options::capacity or
/// its store's); nothing changed, and the same record must be offered again later (it is not
/// lost: KV already names this zone as its owner).
enum class handoff_status { adopted, duplicate, refused, no_room };

/// The world's view of one zone. Tick thread only (no locking): call apply_* before
/// zone_world::step, then collect_handoffs and build_ghosts after it.
class zone_link {
 public:
  explicit zone_link(link_options opt);

  /// Gives world-wide ids to entities created since the last call (populate, players) and
  /// forgets those the zone removed.
  void assign_ids(const zone_world& w);

  /// Owned entities the zone removed (a player who left) that had been handed off (so have an
  /// ownership record somewhere), since the last call; clears the list.
  [[nodiscard]] std::vector<global_id> take_departed() { return std::exchange(departed_, {}); }

  /// Applies a neighbour's ghost message. `gap`: deltas were missed, a snapshot is needed
  /// (snapshot_wanted() names the neighbours to ask); nothing of it applied.
  ghost_status apply_ghosts(zone_world& w, std::span<const std::uint8_t> bytes);
  /// Entities already here whose visibility class or mask apply_ghosts or apply_handoff changed
  /// (the owner switched it), with their old values, since the last call; clears the list. The
  /// zone must resync the clients that hold them (replicator::resync_viewers_of), or they keep
  /// the class the entity entered their view with.
  [[nodiscard]] std::vector<class_change> take_class_changes() { return std::exchange(class_changes_, {}); }
  /// Neighbours whose ghosts wait for a snapshot (ask them again every few ticks).
  [[nodiscard]] std::vector<std::uint32_t> snapshot_wanted() const;
  /// A neighbour asked for a snapshot: its next message is one.
  void snapshot_requested(std::uint32_t neighbour);

  /// Takes over a handed-off entity: idempotent in (gid, epoch) (a replay or a duplicate changes
  /// nothing); a ghost of it here becomes the entity itself (same local handle: clients see no
  /// leave and enter). `*local` receives its handle here. A full zone answers no_room and
  /// changes nothing (offer the record again later).
  handoff_status apply_handoff(zone_world& w, const handoff_record& r, entity_id* local = nullptr);

  /// Every entity this zone owns, as records to restore it from (gid, epoch, state; from = to =
  /// this region, `owner_revision` the ownership record's revision it holds): a checkpoint of the
  /// zone (docs/world.md, "Checkpoints"). A player is in it only with its client's resume token
  /// from `resume` (local handle -> token; the record's `token`): the zone that restores it waits
  /// for that client; players without one are left out.
  /// `out` is cleared first (a vector kept from the last checkpoint takes it without allocating).
  void checkpoint(const zone_world& w, std::vector<handoff_record>& out,
                  const std::unordered_map<entity_id, std::uint64_t>* resume = nullptr) const;
  /// Takes an entity back from a checkpoint of this region as owned here, with its id, epoch and
  /// ownership revision (the caller checked KV still names this region at that epoch). Refused
  /// when the id is already here or the record is another region's; no_room when the zone is full.
  handoff_status restore(zone_world& w, const handoff_record& r);

  /// Entities beyond handoff_margin outside this zone's rectangle: each becomes an in-transit
  /// ghost here and a record for its new zone (epoch + 1). `tick_us`: stamped as sent_us.
  [[nodiscard]] std::vector<handoff_record> collect_handoffs(zone_world& w, std::uint64_t now_us);
  /// The new owner's ownership revision for a record this zone sent (after its CAS), and the
  /// revision an adopted entity came with (next CAS from here starts from it).
  [[nodiscard]] std::uint64_t owner_revision(global_id g) const;

  /// This tick's message to every neighbour (one each, empty deltas included: they are the
  /// heartbeat). `out` is cleared first.
  void build_ghosts(const zone_world& w, std::vector<ghost_message>& out);

  /// Drops ghosts of silent neighbours and unconfirmed in-transit ghosts.
  void expire(zone_world& w);

  [[nodiscard]] global_id gid_of(entity_id local) const;
  [[nodiscard]] entity_id local_of(global_id g) const;
  /// The entity is simulated here (not a ghost).
  [[nodiscard]] bool owns(entity_id local) const;
  /// This zone handed the entity off and no neighbour has sent it back as a ghost yet.
  [[nodiscard]] bool in_transit(entity_id local) const;
  [[nodiscard]] std::size_t owned_count() const;
  /// World-wide ids of every entity this zone owns, ascending.
  [[nodiscard]] std::vector<global_id> owned_ids() const;
  /// Entities this zone handed off whose new owner has not confirmed them yet, ascending.
  [[nodiscard]] std::vector<global_id> transit_ids() const;
  /// The same with each one's ownership epoch (0: never handed off), ascending by id.
  [[nodiscard]] std::vector<std::pair<global_id, std::uint64_t>> owned_epochs() const;
  [[nodiscard]] const link_stats& stats() const { return stats_; }
  [[nodiscard]] const link_options& options() const { return opt_; }
  [[nodiscard]] const rect& area() const { return area_; }

 private:
  enum class role : std::uint8_t { none, owned, ghost, transit };
  struct slot_info {
    entity_id local = null_entity;
    global_id gid = 0;
    role what = role::none;
    std::uint32_t source = 0;      ///< transit: the new owner
    std::uint8_t claims = 0;       ///< ghosts: neighbours (by index in out_) that currently send it
    std::uint8_t owner_claims = 0;  ///< of which not in transit (their state wins)
    std::uint64_t since_tick = 0;  ///< transit: when it was handed off
    std::uint64_t epoch = 0;       ///< owned: ownership epoch
    std::uint64_t revision = 0;    ///< owned: KV revision of its ownership record (0: none yet)
  };
  struct neighbour_out {
    std::uint32_t region = 0;
    std::uint64_t seq = 0;
    bool snapshot_next = true;
    std::unordered_map<global_id, ghost_entry> sent;  ///< what the neighbour holds, as last sent
  };
  struct neighbour_in {
    std::uint64_t expected = 0;  ///< next seq; 0: waiting for a snapshot
    std::uint64_t last_tick = 0;  ///< our tick of its last message
    bool heard = false;
    std::uint32_t room = ghost_message::no_limit;  ///< as its last message said
    /// Records sent to it in the last room_lag_ticks ticks (by tick % room_lag_ticks): its
    /// room may not count them yet.
    std::array<std::uint64_t, 3> sent_tick{};
    std::array<std::uint32_t, 3> sent{};
  };
  /// Ticks a record may take to show in the room its zone tells (collect_handoffs counts the
  /// records of that many ticks as not counted yet).
  static constexpr std::uint64_t room_lag_ticks = 3;
  slot_info* info(entity_id local);
  const slot_info* info(entity_id local) const;
  slot_info& bind(entity_id local, global_id g, role what);
  void drop_ghost(zone_world& w, entity_id local);
  [[nodiscard]] ghost_entry make_entry(const entity_store& s, std::size_t dense, std::uint8_t flags) const;
  void place_ghost(zone_world& w, const ghost_entry& e, unsigned source);
  void unclaim(zone_world& w, entity_id local, unsigned source);
  [[nodiscard]] int neighbour_index(std::uint32_t region) const;

  link_options opt_;
  rect area_;
  net::position_quantizer quantizer_;
  std::vector<slot_info> by_slot_;
  std::unordered_map<global_id, entity_id> local_;
  std::unordered_map<global_id, std::uint64_t> last_epoch_;  ///< highest epoch applied per gid
  std::vector<neighbour_out> out_;
  std::unordered_map<std::uint32_t, neighbour_in> in_;
  std::vector<global_id> departed_;
  std::vector<class_change> class_changes_;
  /// set_visibility on an entity already here, the change recorded for take_class_changes.
  void set_classes(entity_store& st, std::size_t dense, entity_id id, std::uint32_t cls, std::uint32_t sees);
  std::uint32_t next_counter_ = 1;
  std::uint64_t tick_ = 0;  ///< the zone's tick at the last call
  link_stats stats_;
};

}  // namespace zone::world
