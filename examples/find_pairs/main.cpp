// The offline finder API of the installed `zone` package: boxes in, pairs out (docs/embedding.md).
//   find-pairs BOXES PAIRS   reads a box file (CSV `minx,miny,minz,maxx,maxy,maxz[,category,mask]`
//                            or the binary format), writes every qualifying pair to PAIRS as a
//                            line "i j" (i < j), sorted, and prints how many there are.
// With the GPU target (a package built with CUDA) the finder is `auto`: PBIG or LBVH on a usable
// device, the CPU grid finder otherwise; without it, the CPU grid finder.
#include <zone/interest.h>
#include <zone/thread_pool.h>
#ifdef EXAMPLE_WITH_GPU
#include <zone/finders.h>
#include <zone/pbig.h>
#endif

#include <cstdio>
#include <fstream>
#include <span>
#include <string>

namespace zi = zone::interest;

int main(int argc, char** argv) {
  if (argc != 3) {
    std::fprintf(stderr, "usage: find-pairs BOXES PAIRS   (writes every qualifying pair of the boxes to PAIRS)\n");
    return argc == 2 && std::string(argv[1]) == "--help" ? 0 : 2;
  }
  zi::box_set boxes;
  if (auto error = zi::read_box_file(argv[1], boxes)) {
    std::fprintf(stderr, "%s:%zu: %s\n", argv[1], error->line, error->message.c_str());
    return 2;
  }

  zi::thread_pool pool;  // all cores; the finder keeps its memory from call to call: make it once
  std::span<const zi::id_pair> pairs;
#ifdef EXAMPLE_WITH_GPU
  namespace zg = zone::gpu;
  auto finder = zg::make_finder(zg::finder_backend::auto_select, &pool);
  const zg::pinned_boxes pinned(boxes);  // page-locks the arrays while it lives: no staging copy
  auto error = zg::find_view(*finder, boxes, pairs);  // the pairs stay in the finder's buffer
#else
  zi::grid_finder finder(&pool);
  zi::pair_list list;
  auto error = finder.find(boxes, list);
  pairs = list;
#endif
  if (error) {  // invalid boxes (NaN, lo > hi) are rejected, never dropped
    std::fprintf(stderr, "%s: %s\n", argv[1], error->message.c_str());
    return 2;
  }

  zi::pair_list sorted(pairs.begin(), pairs.end());  // each pair once, a < b, in no fixed order:
  zi::sort_canonical(sorted, boxes.size(), &pool);   // sort for a canonical listing
  std::ofstream out(argv[2]);
  for (const zi::id_pair& p : sorted) out << p.a << ' ' << p.b << '\n';
  if (!out.flush()) {
    std::fprintf(stderr, "%s: cannot write\n", argv[2]);
    return 2;
  }
  std::printf("%zu pairs among %zu boxes\n", sorted.size(), boxes.size());
  return 0;
}
