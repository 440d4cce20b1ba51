// The ground-truth stream of zone-server --oracle (docs/protocol.md): once per tick, every entity's
// position, and whenever the set of entities or their boxes changed, every entity's id, AOI and
// presence half-extents, visibility class, mask (what its AOI sees) and kind. A pure codec (bytes
// in, values or an error out; no sockets), shared by the server that writes the stream and the
// oracle that reads it (bots/oracle.h).
//
// One frame per tick, all little-endian:
//   u32 body_bytes (what follows this word)
//   u32 magic "ZTR1", u32 flags (bit 0: the layout columns follow the positions),
//   u64 tick, u32 count, u32 reserved (0),
//   count x (f32 x, f32 y, f32 z)                positions, in the server's dense order
//   if layout: count x u32 id, count x 3 f32 AOI half-extent, count x 3 f32 presence half-extent,
//              count x u32 class, count x u32 sees, count x u8 kind, zero padding to 4 bytes.
// A frame without the layout has the entities of the last frame that had one, in the same order.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <vector>

namespace zone::net::truth {

inline constexpr std::uint32_t magic = 0x3152545a;  // "ZTR1" read as little-endian bytes
inline constexpr std::uint32_t flag_layout = 1;
inline constexpr std::size_t header_bytes = 4 + 4 + 4 + 8 + 4 + 4;  ///< the length word included
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

/// Writes one tick's frame into `out` (replacing its contents). `positions` holds 3 floats per
/// entity; `layout`, when given, must have the same count.
void encode_tick(std::vector<std::uint8_t>& out, std::uint64_t tick, std::span<const float> positions,
                 const layout_view* layout);

/// One decoded frame. When has_layout, the layout columns are filled; otherwise they are left as
/// they were (a reader keeps the last layout in the same object).
struct tick_frame {
  std::uint64_t tick = 0;
  std::uint32_t count = 0;
  bool has_layout = false;
  std::vector<float> positions;  ///< 3 per entity
  std::vector<std::uint32_t> ids;
  std::vector<float> aoi_half, presence_half;
  std::vector<std::uint32_t> classes, sees;
  std::vector<std::uint8_t> kinds;
};

/// Decodes a body (the bytes after the length word). An error text for a bad magic, a size that
/// disagrees with the count, or a frame without a layout whose count differs from the last layout's.
[[nodiscard]] std::optional<std::string> decode_tick(std::span<const std::uint8_t> body, tick_frame& out);

}  // namespace zone::net::truth
