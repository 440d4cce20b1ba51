// Who sees whom in one tick, with the CPU core of the installed `zone` package (docs/embedding.md).
// Every entity owns two boxes: its AOI box (what it looks at: category AOI, mask = the classes it
// sees) and its presence box (its body: category = its visibility class, mask 0). A pair of
// boxes qualifies iff they touch and one's category meets the other's mask, so "A sees B" is the
// pair (AOI of A, presence of B). Stealth and large bodies need no special case.
#include <zone/interest.h>
#include <zone/thread_pool.h>

#include <algorithm>
#include <cstdio>
#include <utility>
#include <vector>

namespace zi = zone::interest;
namespace bits = zone::interest::category_bits;

struct entity {
  const char* name;
  float x, y;             // centre on the ground
  float aoi, body;        // half-extents of the AOI box and the presence box
  std::uint32_t klass;    // visibility class of the presence box
  std::uint32_t sees;     // classes the AOI box sees
};

int main() {
  const std::vector<entity> world = {
      {"alice", 0, 0, 50, 1, bits::normal, bits::normal},
      {"bob", 30, 0, 50, 1, bits::normal, bits::normal},
      {"rogue", 10, 10, 50, 1, bits::stealth, bits::normal | bits::stealth},  // only rogues see rogues
      {"dragon", 120, 0, 20, 40, bits::normal, bits::normal},                 // a body seen from afar
      {"carol", 300, 300, 50, 1, bits::normal, bits::normal},                 // far from everyone
  };

  // Entity k owns box 2k (AOI) and box 2k+1 (presence); z spans the same [0, 2] for all.
  zi::box_set boxes;
  for (const entity& e : world) {
    boxes.push_back({{e.x - e.aoi, e.y - e.aoi, 0}, {e.x + e.aoi, e.y + e.aoi, 2}, bits::aoi, e.sees});
    boxes.push_back({{e.x - e.body, e.y - e.body, 0}, {e.x + e.body, e.y + e.body, 2}, e.klass, 0});
  }

  zi::thread_pool pool(2);        // the finder's worker threads (the caller included)
  zi::grid_finder finder(&pool);  // the fast CPU finder; keep it: it reuses its memory call to call
  zi::pair_list pairs;
  if (auto error = finder.find(boxes, pairs)) {  // invalid boxes are rejected, never dropped
    std::fprintf(stderr, "bad input: %s\n", error->message.c_str());
    return 2;
  }

  // Each qualifying pair is one AOI box and one presence box: observer -> target.
  std::vector<std::pair<std::uint32_t, std::uint32_t>> sees;
  for (const zi::id_pair& p : pairs) {
    const auto [aoi, presence] = p.a % 2 == 0 ? std::pair{p.a, p.b} : std::pair{p.b, p.a};
    if (aoi / 2 != presence / 2) sees.emplace_back(aoi / 2, presence / 2);  // not oneself
  }
  std::sort(sees.begin(), sees.end());
  for (const auto& [observer, target] : sees) std::printf("%s sees %s\n", world[observer].name, world[target].name);
  std::printf("%zu box pairs, %zu sightings\n", pairs.size(), sees.size());
  return 0;
}
