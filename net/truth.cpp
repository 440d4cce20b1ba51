// The ground-truth stream's codec (truth.h).
#include "truth.h"

#include <bit>
#include <cstring>

namespace zone::net::truth {

static_assert(std::endian::native == std::endian::little, "the truth stream is written in host order");

namespace {

template <class T>
void put(std::uint8_t*& at, const T& v) {
  std::memcpy(at, &v, sizeof v);
  at += sizeof v;
}

void put_bytes(std::uint8_t*& at, const void* data, std::size_t bytes) {
  if (bytes != 0) std::memcpy(at, data, bytes);
  at += bytes;
}

std::size_t padded4(std::size_t n) { return (n + 3) & ~std::size_t{3}; }

std::size_t layout_bytes(std::size_t n) { return n * (4 + 12 + 12 + 4 + 4) + padded4(n); }

template <class T>
void take(const std::uint8_t*& at, std::vector<T>& v, std::size_t n) {
  v.resize(n);
  if (n != 0) std::memcpy(v.data(), at, n * sizeof(T));
  at += n * sizeof(T);
}

}  // namespace

void encode_tick(std::vector<std::uint8_t>& out, std::uint64_t tick, std::span<const float> positions,
                 const layout_view* layout) {
  const std::size_t n = positions.size() / 3;
  const std::size_t total = header_bytes + 12 * n + (layout ? layout_bytes(n) : 0);
  out.resize(total);
  std::uint8_t* at = out.data();
  put(at, static_cast<std::uint32_t>(total - 4));
  put(at, magic);
  put(at, layout ? flag_layout : 0u);
  put(at, tick);
  put(at, static_cast<std::uint32_t>(n));
  put(at, std::uint32_t{0});
  put_bytes(at, positions.data(), 12 * n);
  if (layout) {
    put_bytes(at, layout->ids.data(), 4 * n);
    put_bytes(at, layout->aoi_half.data(), 12 * n);
    put_bytes(at, layout->presence_half.data(), 12 * n);
    put_bytes(at, layout->classes.data(), 4 * n);
    put_bytes(at, layout->sees.data(), 4 * n);
    put_bytes(at, layout->kinds.data(), n);
    for (std::size_t k = n; k < padded4(n); ++k) *at++ = 0;
  }
}

std::optional<std::string> decode_tick(std::span<const std::uint8_t> body, tick_frame& out) {
  const std::size_t head = header_bytes - 4;
  if (body.size() < head) return "truth frame of " + std::to_string(body.size()) + " bytes is shorter than its header";
  std::uint32_t m = 0, flags = 0, count = 0;
  std::uint64_t tick = 0;
  std::memcpy(&m, body.data(), 4);
  std::memcpy(&flags, body.data() + 4, 4);
  std::memcpy(&tick, body.data() + 8, 8);
  std::memcpy(&count, body.data() + 16, 4);
  if (m != magic) return "not a truth frame (bad magic)";
  if ((flags & ~flag_layout) != 0) return "truth frame with unknown flags " + std::to_string(flags);
  const bool has_layout = (flags & flag_layout) != 0;
  const std::size_t n = count;
  const std::size_t expect = head + 12 * n + (has_layout ? layout_bytes(n) : 0);
  if (body.size() != expect) {
    return "truth frame of tick " + std::to_string(tick) + ": " + std::to_string(body.size()) + " bytes for " +
           std::to_string(n) + " entities, expected " + std::to_string(expect);
  }
  if (!has_layout && n != out.ids.size()) {
    return "truth frame of tick " + std::to_string(tick) + " has " + std::to_string(n) +
           " entities without a layout, the last layout had " + std::to_string(out.ids.size());
  }
  const std::uint8_t* at = body.data() + head;
  out.tick = tick;
  out.count = count;
  out.has_layout = has_layout;
  take(at, out.positions, 3 * n);
  if (has_layout) {
    take(at, out.ids, n);
    take(at, out.aoi_half, 3 * n);
    take(at, out.presence_half, 3 * n);
    take(at, out.classes, n);
    take(at, out.sees, n);
    take(at, out.kinds, n);
  }
  return std::nullopt;
}

}  // namespace zone::net::truth
