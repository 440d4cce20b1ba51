// The ground-truth stream of zone-server --oracle (docs/protocol.md): once per tick, every entity's
// position, and whenever the set of entities or their boxes changed, either every entity's id, AOI
// and presence half-extents, visibility class, mask (what its AOI sees) and kind (the layout), or,
// when the ids are the same and few entities changed, those entities' new values (the changes). A
// pure codec (bytes in, values or an error out; no sockets), shared by the server that writes the
// stream and the oracle that reads it (bots/oracle.h).
//
// One frame per tick, all little-endian:
//   u32 body_bytes (what follows this word)
//   u32 magic "ZTR2", u32 flags (bit 0: the layout follows the positions; bit 1: changes do; not both;
//                               bit 2: carried sets follow, after them; bit 3: this tick is the
//                               server's first step),
//   u64 tick, u32 count, u32 layout_seq,
//   count x (f32 x, f32 y, f32 z)                positions, in the server's dense order
//   if layout:  count x u32 id, count x 3 f32 AOI half-extent, count x 3 f32 presence half-extent,
//               count x u32 class, count x u32 sees, count x u8 kind, zero padding to 4 bytes.
//   if changes: u32 m, m x u32 index (ascending, < count), m x 3 f32 AOI half-extent,
//               m x 3 f32 presence half-extent, m x u32 class, m x u32 sees, m x u8 kind, padding.
//   if carried: u32 k, u32 t, k x u32 observer id (ascending), k x u32 target count (summing to t),
//               t x u32 target id (ascending within each observer's).
// Carried sets: the observers whose previous visible set in this tick's step was not the last
// step's but one the server was given (a handoff: the view the observer had in the zone it came
// from, docs/world.md "Handoff"), with that set as the server took it (ids the server did not hold
// then are ignored by the rules, as by the server). A reader checks such an observer's set from it
// instead of from its own last tick.
// The first step: no step came before it, so every observer's previous set was empty (those
// carried aside); a reader that has this frame knows every observer's whole history (a zone
// restored from a checkpoint starts with its entities in place: docs/world.md).
// layout_seq numbers the layouts: a frame with the layout starts from any value; a frame with
// changes carries the previous frame's + 1 (its entities are the previous layout's, those at the
// indices replaced); a frame with positions only carries the previous frame's (the entities of the
// last layout, in the same order). A reader that missed a frame that changed the layout stops at the
// next frame instead of checking against a wrong layout.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

namespace zone::net::truth {

inline constexpr std::uint32_t magic = 0x3252545a;  // "ZTR2" read as little-endian bytes
/// "ZTRX": the first word of a refusal's body (the server will not serve this subscriber; a text follows).
inline constexpr std::uint32_t refused_magic = 0x5852545a;
inline constexpr std::uint32_t flag_layout = 1;
inline constexpr std::uint32_t flag_changes = 2;
inline constexpr std::uint32_t flag_carried = 4;
inline constexpr std::uint32_t flag_first_step = 8;
inline constexpr std::size_t header_bytes = 4 + 4 + 4 + 8 + 4 + 4;  ///< the length word included
/// Bytes of one entity's layout, and of one change (its index included; the kinds' padding aside).
inline constexpr std::size_t layout_entity_bytes = 4 + 12 + 12 + 4 + 4 + 1;
inline constexpr std::size_t change_entity_bytes = 4 + 12 + 12 + 4 + 4 + 1;
/// An encoder sends changes only while they are at most count / max_changes_divisor entities;
/// beyond, the whole layout (about as cheap, and a reader's copy is refreshed).
inline constexpr std::size_t max_changes_divisor = 4;
/// Largest body a reader accepts (about 9 million entities with their layout).
inline constexpr std::size_t max_body_bytes = std::size_t{1} << 30;

/// What an encoder reads: columns of 3 floats per entity for vectors (x, y, z), one value per entity otherwise.
struct layout_view {
  std::span<const std::uint32_t> ids;
  std::span<const float> aoi_half;       ///< 3 per entity
  std::span<const float> presence_half;  ///< 3 per entity
  std::span<const std::uint32_t> classes, sees;
  std::span<const std::uint8_t> kinds;
};

/// Changed entities: their dense indices (ascending) and their new values, one row per index.
struct changes_view {
  std::span<const std::uint32_t> index;
  std::span<const float> aoi_half;       ///< 3 per change
  std::span<const float> presence_half;  ///< 3 per change
  std::span<const std::uint32_t> classes, sees;
  std::span<const std::uint8_t> kinds;
};

/// Carried sets: observer k's targets are targets[off[k], off[k + 1]); observers ascending, each
/// one's targets ascending (off has one more entry than observers).
struct carried_view {
  std::span<const std::uint32_t> observers;
  std::span<const std::uint32_t> off;
  std::span<const std::uint32_t> targets;
};

/// Writes one tick's frame into `out` (replacing its contents). `positions` holds 3 floats per
/// entity; `layout`, when given, must have the same count; `changes` (not with `layout`) the
/// changed rows; `carried`, when it names an observer, the carried sets. `layout_seq` as the
/// header above says (the caller numbers; see `encoder`).
void encode_tick(std::vector<std::uint8_t>& out, std::uint64_t tick, std::span<const float> positions,
                 const layout_view* layout, std::uint32_t layout_seq = 0, const changes_view* changes = nullptr,
                 const carried_view* carried = nullptr);

/// Marks an encoded frame (encode_tick's or encoder's `out`) as the server's first step.
void mark_first_step(std::vector<std::uint8_t>& frame);

/// A refusal (the body: "ZTRX" and a text, no tick): what a server writes to a subscriber it will
/// not serve before closing; a reader's decode_tick returns the text as its error.
void encode_refusal(std::vector<std::uint8_t>& out, std::string_view why);

/// The writing side of one stream: keeps a copy of the layout it last sent, numbers the layouts,
/// and chooses each tick's frame: the whole layout (the first frame, a forced one, or when the ids
/// changed: an entity created or destroyed, or reordered), the changes (the same ids, at most
/// count / max_changes_divisor entities with another extent, class, mask or kind, compared bit
/// for bit), or positions alone.
class encoder {
 public:
  enum class sent { positions, changes, layout };
  /// `layout` null: unchanged since the last call (the caller knows it: entity_store::layout_version).
  /// `force_layout`: the whole layout whatever changed (a subscriber joined). The first call must
  /// give a layout. `carried`: this tick's carried sets (encode_tick), if any.
  sent encode(std::vector<std::uint8_t>& out, std::uint64_t tick, std::span<const float> positions,
              const layout_view* layout, bool force_layout, const carried_view* carried = nullptr);
  /// Entities in the last frame's changes (0 unless it sent changes).
  [[nodiscard]] std::size_t last_changes() const { return changed_.size(); }

 private:
  bool have_ = false;
  std::uint32_t seq_ = 0;
  std::vector<std::uint32_t> ids_, classes_, sees_;
  std::vector<float> aoi_, presence_;
  std::vector<std::uint8_t> kinds_;
  // The changed rows of the current frame.
  std::vector<std::uint32_t> changed_, ch_classes_, ch_sees_;
  std::vector<float> ch_aoi_, ch_presence_;
  std::vector<std::uint8_t> ch_kinds_;
};

/// One decoded frame. When has_layout, the layout columns are filled; when has_changes, the rows
/// at `changed` are replaced; otherwise they are left as they were (a reader keeps the last layout
/// in the same object, changes applied).
struct tick_frame {
  std::uint64_t tick = 0;
  std::uint32_t count = 0;
  std::uint32_t layout_seq = 0;
  bool layout_known = false;  ///< a frame with the layout was decoded into this object
  bool has_layout = false;
  bool has_changes = false;
  bool first_step = false;  ///< the server's first step: every observer's previous set was empty (but carried ones)
  std::vector<std::uint32_t> changed;  ///< the indices the last frame's changes replaced (empty otherwise)
  std::vector<float> positions;  ///< 3 per entity
  std::vector<std::uint32_t> ids;
  std::vector<float> aoi_half, presence_half;
  std::vector<std::uint32_t> classes, sees;
  std::vector<std::uint8_t> kinds;
  /// This frame's carried sets (empty when it has none): observer k's are
  /// carried_targets[carried_off[k], carried_off[k + 1]).
  std::vector<std::uint32_t> carried_observers, carried_off, carried_targets;
};

/// Decodes a body (the bytes after the length word). An error text for a bad magic, unknown flags,
/// a size that disagrees with the counts, a frame without the layout before any layout or whose
/// count or layout_seq does not follow the last one, changes whose indices are not ascending
/// below the count, carried sets whose counts disagree with their total or whose ids do not
/// ascend, or a refusal (its text). `out` is left as it was on an error.
[[nodiscard]] std::optional<std::string> decode_tick(std::span<const std::uint8_t> body, tick_frame& out);

}  // namespace zone::net::truth
