// libFuzzer: the truth stream's decoder (net/truth.h) on any bytes, as a stream: the input is a
// sequence of bodies, each after a 2-byte little-endian length, decoded in order into one reader
// (so changes and positions-only frames meet the layout a frame before gave). After every frame
// the reader's columns have the sizes its count says; a frame refused leaves the reader exactly as
// it was; and the columns of every accepted frame, written again by an encoder and read by a
// second reader, come back bit for bit. No crash, no sanitizer report.
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <span>
#include <vector>

#include "net/truth.h"

using namespace zone::net;

namespace {

template <class T>
bool same(const std::vector<T>& a, const std::vector<T>& b) {
  return a.size() == b.size() && (a.empty() || std::memcmp(a.data(), b.data(), a.size() * sizeof(T)) == 0);
}

bool same_state(const truth::tick_frame& a, const truth::tick_frame& b) {
  return a.tick == b.tick && a.count == b.count && a.layout_seq == b.layout_seq && a.layout_known == b.layout_known &&
         a.has_layout == b.has_layout && a.has_changes == b.has_changes && same(a.changed, b.changed) &&
         same(a.positions, b.positions) && same(a.ids, b.ids) && same(a.aoi_half, b.aoi_half) &&
         same(a.presence_half, b.presence_half) && same(a.classes, b.classes) && same(a.sees, b.sees) &&
         same(a.kinds, b.kinds);
}

bool columns_equal(const truth::tick_frame& a, const truth::tick_frame& b) {
  return a.count == b.count && same(a.positions, b.positions) && same(a.ids, b.ids) && same(a.aoi_half, b.aoi_half) &&
         same(a.presence_half, b.presence_half) && same(a.classes, b.classes) && same(a.sees, b.sees) &&
         same(a.kinds, b.kinds);
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  truth::tick_frame reader, before, echo;
  truth::encoder enc;
  std::vector<std::uint8_t> out;
  bool echo_started = false;
  for (std::size_t at = 0; at + 2 <= size;) {
    const std::size_t len = data[at] | (std::size_t{data[at + 1]} << 8);
    at += 2;
    const std::span<const std::uint8_t> body(data + at, std::min(len, size - at));
    at += body.size();
    before = reader;
    if (truth::decode_tick(body, reader)) {
      if (!same_state(reader, before)) std::abort();  // refused: untouched
      continue;
    }
    const std::size_t n = reader.count;
    if (reader.positions.size() != 3 * n || reader.ids.size() != n || reader.aoi_half.size() != 3 * n ||
        reader.presence_half.size() != 3 * n || reader.classes.size() != n || reader.sees.size() != n ||
        reader.kinds.size() != n || !reader.layout_known) {
      std::abort();
    }
    for (std::size_t c = 0; c < reader.changed.size(); ++c) {
      if (reader.changed[c] >= n || (c > 0 && reader.changed[c] <= reader.changed[c - 1])) std::abort();
    }
    // The encoder, told the layout may have changed, writes these columns; a second reader agrees.
    const truth::layout_view lv{reader.ids, reader.aoi_half, reader.presence_half, reader.classes, reader.sees, reader.kinds};
    const bool layout_news = reader.has_layout || reader.has_changes || !echo_started;
    (void)enc.encode(out, reader.tick, reader.positions, layout_news ? &lv : nullptr, !echo_started);
    echo_started = true;
    if (truth::decode_tick(std::span(out).subspan(4), echo) || !columns_equal(echo, reader)) std::abort();
  }
  return 0;
}
