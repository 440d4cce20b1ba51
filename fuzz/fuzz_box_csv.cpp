// libFuzzer: the CSV box parser (interest/box_files.cpp) on any text, whole and streamed from a
// file (1 MiB chunks, lines across them). Both must agree; an accepted set holds only finite
// boxes with lo <= hi; an error names a line and leaves the set empty.
#include <sys/mman.h>
#include <unistd.h>

#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <string>
#include <string_view>

#include "interest/interest.h"

using namespace zone::interest;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  box_set whole;
  const auto err = parse_csv(text, whole);
  if (err) {
    if (!whole.empty()) std::abort();
  } else {
    for (std::size_t i = 0; i < whole.size(); ++i) {
      const box b = whole.get(static_cast<std::uint32_t>(i));
      for (int d = 0; d < 3; ++d) {
        if (!std::isfinite(b.lo[d]) || !std::isfinite(b.hi[d]) || b.lo[d] > b.hi[d]) std::abort();
      }
    }
  }
  // The same bytes through the file reader (a memory file; CSV unless they start with the binary magic).
  const int fd = ::memfd_create("fuzz_csv", 0);
  if (fd < 0) return 0;
  if (::write(fd, data, size) != static_cast<ssize_t>(size)) std::abort();
  box_set streamed;
  const auto err2 = read_box_file("/proc/self/fd/" + std::to_string(fd), streamed);
  ::close(fd);
  if (text.starts_with("ZBOXES01")) return 0;
  if (err.has_value() != err2.has_value()) std::abort();
  if (err && err->line != err2->line) std::abort();
  if (!err && (streamed.size() != whole.size() || streamed.lo_x != whole.lo_x || streamed.mask != whole.mask)) std::abort();
  return 0;
}
