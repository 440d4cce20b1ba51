// libFuzzer: the binary box reader (interest/box_files.cpp) on any bytes behind the binary magic
// (so the header, counts, flags and columns are what varies). It must answer with a set of valid
// boxes or an error, allocating only what the file's size backs.
#include <sys/mman.h>
#include <unistd.h>

#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <string>

#include "interest/interest.h"

using namespace zone::interest;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const int fd = ::memfd_create("fuzz_boxes", 0);
  if (fd < 0) return 0;
  static const char magic[8] = {'Z', 'B', 'O', 'X', 'E', 'S', '0', '1'};
  if (::write(fd, magic, sizeof magic) != 8 || ::write(fd, data, size) != static_cast<ssize_t>(size)) std::abort();
  box_set boxes;
  const auto err = read_box_file("/proc/self/fd/" + std::to_string(fd), boxes);
  ::close(fd);
  if (err) {
    if (!boxes.empty()) std::abort();
    return 0;
  }
  if (boxes.size() * 24 > size) std::abort();  // every box was backed by the file's bytes
  for (std::size_t i = 0; i < boxes.size(); ++i) {
    const box b = boxes.get(static_cast<std::uint32_t>(i));
    for (int d = 0; d < 3; ++d) {
      if (!std::isfinite(b.lo[d]) || !std::isfinite(b.hi[d]) || b.lo[d] > b.hi[d]) std::abort();
    }
  }
  return 0;
}
