// libFuzzer: the frame decoder (net/protocol.h) on any bytes, fed in pieces of a size the input's
// first byte picks. Every frame it accepts must convert to a message (or be reported unknown),
// and a message must survive encode -> decode -> encode byte for byte. No crash, no sanitizer
// report, no unbounded buffer (max_frame_bytes bounds what it holds).
#include <cstdint>
#include <cstdlib>
#include <span>

#include "net/protocol.h"

using namespace zone::net;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size == 0) return 0;
  const std::size_t piece = data[0] == 0 ? size : data[0];
  const std::span<const std::uint8_t> bytes(data + 1, size - 1);
  decoder_options opt;
  opt.max_frame_bytes = 4096;
  frame_decoder dec(opt);
  for (std::size_t at = 0; at < bytes.size() && !dec.failed(); at += piece) {
    dec.feed(bytes.subspan(at, std::min(piece, bytes.size() - at)));
    for (;;) {
      const decode_step s = dec.next();
      if (!s.is_frame()) break;
      if (s.frame.bytes.size() > opt.max_frame_bytes + 4) std::abort();
      const auto m = to_message(*s.frame.envelope);
      if (!m) continue;  // a kind this build cannot convert
      const auto once = encode_frame(*m);
      frame_decoder again;
      again.feed(once);
      const decode_step r = again.next();
      if (!r.is_frame()) std::abort();
      const auto m2 = to_message(*r.frame.envelope);
      if (!m2 || encode_frame(*m2) != once) std::abort();
    }
  }
  (void)dec.close();
  return 0;
}
