// The GPU PBIG finder's overlapped upload (pbig_options::overlap_min_boxes / overlap_chunks /
// overlap_always; docs/gpu.md, "Overlapped upload") against the CPU references: the brute-force
// finder up to 2x10^4 boxes, the CPU grid finder above (the sorted pair lists equal), and the
// one-shot GPU path. The pipeline is forced (overlap_always) onto sets of 1.6x10^4-3x10^5 boxes
// (pinned: pinned_boxes pins from 16384 boxes) with 2, 3 and 7 chunks, chunk sizes that do not
// divide n, and the sets that stress its decomposition: boxes straddling cells, duplicates and
// identical boxes, zero-extent boxes, cells crowded chunk by chunk around the stage kernel's
// segments at every stage width (8, 16, 32, 64 and the plan's choice; its layout replayed on the
// host at every width), later chunks far outside the first chunk's bounds (the grid
// is planned from chunk 0), stages without pairs or without grid boxes, boxes handled apart,
// invalid boxes in a later chunk, overflowing output buffers, and all of those at once on a set
// giving every stage several batches (the next stage counted and mapped on the stage stream while
// the earlier stage's batches run). Then the default rule: the pipeline
// only after a call of about the same size whose output was small against its input. About 30 s
// on the H200 (`test-gpu -ts=gpu.pbig.overlap -d`). Part of test_gpu: without a device the
// executable exits with 77 (Skipped).
#include <doctest/doctest.h>

#include <algorithm>
#include <cstdint>
#include <limits>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "../common/box_families.h"
#include "gpu/pbig.h"
#include "gpu/pbig/pbig_shared.h"  // stage_layout: the stage kernel's work in a cell
#include "interest/interest.h"
#include "interest/thread_pool.h"

using namespace zone::interest;
using namespace zone::test;
namespace gpu = zone::gpu;

namespace {

/// The overlapped upload forced on every call from 2 boxes on, in k chunks.
gpu::pbig_options overlapped(std::uint32_t k, thread_pool* pool) {
  gpu::pbig_options o;
  o.decode_pool = pool;
  o.overlap_min_boxes = 2;
  o.overlap_chunks = k;
  o.overlap_always = true;
  return o;
}

/// The one-shot path (the overlapped upload never).
gpu::pbig_options one_shot(thread_pool* pool) {
  gpu::pbig_options o;
  o.decode_pool = pool;
  o.overlap_min_boxes = std::numeric_limits<std::size_t>::max();
  return o;
}

std::unique_ptr<pair_finder> make_gpu(const gpu::pbig_options& opt) {
  std::string why;
  auto f = gpu::make_pbig_finder(opt, &why);
  if (!f) FAIL("make_pbig_finder failed: " << why);
  return f;
}

/// Chunk j of the overlapped upload holds the ids [n j / k, n (j + 1) / k).
std::size_t chunk_start(std::size_t n, std::size_t k, std::size_t j) { return n * j / k; }

/// find_pairs_view on a pinned set: the pairs as they came (each checked a < b).
pair_list view_of(pair_finder& f, const box_set& s) {
  REQUIRE(gpu::boxes_pinned(s));
  std::span<const id_pair> got;
  const auto err = gpu::find_pairs_view(f, s, got);
  REQUIRE_FALSE(err.has_value());
  REQUIRE(std::all_of(got.begin(), got.end(), [](const id_pair& p) { return p.a < p.b; }));
  return pair_list(got.begin(), got.end());
}

pair_list sorted(pair_list v) {
  std::sort(v.begin(), v.end());
  return v;
}

/// The CPU grid finder's pairs, sorted (a < b).
pair_list cpu_pairs(const box_set& s, thread_pool* pool) {
  grid_finder grid(pool);
  return sorted(run(grid, s));
}

/// The overlapped call on a pinned set, against `want` (sorted): same count, same sorted pairs,
/// no pair twice, and the call took the overlapped upload with k chunks.
void check_overlapped(pair_finder& f, const box_set& s, const pair_list& want, std::uint32_t k) {
  const pair_list got = sorted(view_of(f, s));
  CHECK(got.size() == want.size());
  CHECK(std::adjacent_find(got.begin(), got.end()) == got.end());
  CHECK(got == want);
  const gpu::pbig_report* rep = gpu::last_pbig_report(f);
  REQUIRE(rep != nullptr);
  CHECK(rep->overlap_chunks == k);
  CHECK(rep->pairs == want.size());
  const std::uint32_t w = rep->stage_width;
  CHECK((w == 8 || w == 16 || w == 32 || w == 64));
}

box make_box(float x, float y, float z, float ex, float ey, float ez, std::uint32_t category = 1,
             std::uint32_t mask = 1) {
  box b;
  b.lo[0] = x;
  b.lo[1] = y;
  b.lo[2] = z;
  b.hi[0] = x + ex;
  b.hi[1] = y + ey;
  b.hi[2] = z + ez;
  b.category = category;
  b.mask = mask;
  return b;
}

/// Sets that stress the stages, n boxes each, built for k chunks (boxes placed by chunk).
box_set far_chunks(std::size_t n, std::size_t k, std::uint64_t seed) {
  // Chunk 0 in [0, 100]^3 (the plan's bounds); each later chunk mixes boxes inside, boxes far
  // outside on every side (clamped into the border cells), boxes straddling the bounds and rods
  // from inside to far outside.
  rng_box_maker r(seed);
  box_set s;
  const std::size_t first = chunk_start(n, k, 1);
  for (std::size_t i = 0; i < n; ++i) {
    if (i < first) {
      s.push_back(r.make(100, 5));
      continue;
    }
    switch (i % 5) {
      case 0: s.push_back(r.make(100, 5)); break;
      case 1: s.push_back(r.make(100, 6, 1e4f)); break;   // far above: [1e4, 1e4 + 106]
      case 2: s.push_back(r.make(100, 6, -3e4f)); break;  // far below
      case 3: s.push_back(r.make(60, 30, 70)); break;     // across the upper bound
      default: {
        box b = r.make(100, 3);
        const int d = static_cast<int>(r.rng() % 3);
        b.hi[d] = b.lo[d] + r.uni(100, 2e4f);  // a rod from inside to far out
        s.push_back(b);
      }
    }
  }
  return s;
}

box_set duplicates(std::size_t n, std::uint64_t seed) {
  // A base set repeated three times (every box has two identical copies, in other chunks), one
  // group of identical boxes spread over every chunk, and zero-extent copies of box corners.
  rng_box_maker r(seed);
  const std::size_t third = n / 3;
  std::vector<box> base;
  for (std::size_t i = 0; i < third; ++i) base.push_back(r.make(150, 8));
  box_set s;
  for (std::size_t i = 0; i < n; ++i) {
    if (i % 97 == 5) {
      s.push_back(make_box(40.5f, 40.5f, 40.5f, 2.25f, 2.25f, 2.25f));  // the identical group
    } else if (i % 31 == 7) {
      const box& b = base[i % third];
      s.push_back(make_box(b.hi[0], b.lo[1], b.hi[2], 0, 0, 0));  // a point on a corner of another box
    } else {
      s.push_back(base[i % third]);
    }
  }
  return s;
}

box_set degenerate(std::size_t n, std::uint64_t seed) {
  // Points, flat boxes and unit cubes on an integer lattice: coinciding points, faces and edges
  // that touch exactly, many of them on cell faces.
  rng_box_maker r(seed);
  box_set s;
  for (std::size_t i = 0; i < n; ++i) {
    box b;
    for (int d = 0; d < 3; ++d) {
      b.lo[d] = static_cast<float>(r.rng() % 40);
      const auto kind = r.rng() % 4;
      b.hi[d] = b.lo[d] + (kind == 0 ? 1.0f : 0.0f);
    }
    s.push_back(b);
  }
  return s;
}

box_set straddling(std::size_t n, std::uint64_t seed) {
  // Integer-aligned boxes of 0-24 units in a 300-unit world: bounds on cell faces, boxes over
  // several cells.
  rng_box_maker r(seed);
  box_set s;
  for (std::size_t i = 0; i < n; ++i) {
    box b;
    for (int d = 0; d < 3; ++d) {
      b.lo[d] = static_cast<float>(r.rng() % 300);
      b.hi[d] = b.lo[d] + static_cast<float>(r.rng() % 25);
    }
    s.push_back(b);
  }
  return s;
}

box_set lonely_stages(std::size_t n, std::size_t k, std::uint64_t seed) {
  // Chunk j in its own region (no pair between chunks); chunk 1 pairs with nothing (category and
  // mask 0); the last chunk is only world-spanning boxes handled apart (no grid entry in its
  // stage) whose classes pair them with chunk 0's boxes only.
  rng_box_maker r(seed);
  box_set s;
  for (std::size_t j = 0; j < k; ++j) {
    const std::size_t b = chunk_start(n, k, j), e = chunk_start(n, k, j + 1);
    for (std::size_t i = b; i < e; ++i) {
      if (j + 1 == k) {
        box w = make_box(-10, -10, -10, 1e5f, 1e5f, 1e5f, 8, i % 50 == 0 ? 2 : 0);
        s.push_back(w);
      } else {
        box x = r.make(100, 6, 1000.0f * static_cast<float>(j));
        if (j == 1) x.category = x.mask = 0;
        if (j == 0) x.category = 3;
        s.push_back(x);
      }
    }
  }
  return s;
}

box_set crowded_cells(std::size_t n, std::size_t k, std::uint64_t seed) {
  // The stage kernel's cases: groups of identical boxes (each group in one cell, or the few cells
  // whose faces it straddles) with chosen counts per chunk around its warp's 32 rows and its
  // 32-box column segments (0, 1, 31, 32, 33, 63, 64, 65, 97): cells whose boxes are all in
  // chunk 0, all in the last chunk, all in one middle chunk, in chunk 0 and the last with none
  // between, in every chunk; a group of consecutive ids across the boundary of chunks 0 and 1; a
  // group of zero-extent points and one of flat boxes touching face to face; a group whose chunk-0
  // boxes pair only with later boxes (classes). Background boxes fill [0, 500] x [0, 1000]^2;
  // the groups sit 200 apart in [600, 1000] x [0, 1000]^2, mostly alone in their cells.
  rng_box_maker r(seed);
  std::vector<box> all(n);
  for (box& b : all) {
    b = r.make(1000, 6);
    if (b.lo[0] > 497) {
      b.lo[0] -= 500;
      b.hi[0] -= 500;
    }
  }
  std::vector<std::size_t> cursor(k);  // the next free id of each chunk (from 60 in)
  for (std::size_t j = 0; j < k; ++j) cursor[j] = chunk_start(n, k, j) + 60;
  auto put = [&](std::size_t j, const box& b) {
    REQUIRE(cursor[j] + 60 < chunk_start(n, k, j + 1));  // clear of the straddling group
    all[cursor[j]++] = b;
  };
  std::size_t g = 0;
  auto spot = [&](float edge) {  // a box of `edge` at the next group's place
    const float x = 650.0f + 200.0f * static_cast<float>(g % 2), y = 100.0f + 200.0f * static_cast<float>((g / 2) % 5),
                z = 100.0f + 200.0f * static_cast<float>((g / 10) % 5);
    ++g;
    return make_box(x, y, z, edge, edge, edge);
  };
  const std::size_t counts[] = {0, 1, 31, 32, 33, 63, 64, 65, 97};
  const std::size_t last = k - 1, middle = k / 2;
  // Every chunk, counts cycling through the list (nine groups, each starting elsewhere in it).
  for (std::size_t start = 0; start < 9; ++start) {
    const box b = spot(1.5f);
    for (std::size_t j = 0; j < k; ++j) {
      for (std::size_t i = 0; i < counts[(start + j) % 9]; ++i) put(j, b);
    }
  }
  for (const std::size_t c : {std::size_t{33}, std::size_t{70}}) {
    const box only0 = spot(1.0f), only_last = spot(1.0f), only_middle = spot(1.0f), ends = spot(1.0f);
    for (std::size_t i = 0; i < c; ++i) {
      put(0, only0);
      put(last, only_last);
      put(middle, only_middle);
      put(0, ends);
      put(last, ends);
    }
  }
  // Zero-extent points, and flat boxes touching face to face (x = 5 exactly), in every chunk.
  const box point = spot(0.0f);
  box flat = spot(0.0f);
  flat.hi[1] += 2;
  flat.hi[2] += 2;
  box touching = flat;
  flat.lo[0] -= 5;
  touching.hi[0] += 5;
  for (std::size_t j = 0; j < k; ++j) {
    for (std::size_t i = 0; i < 20 + 7 * j; ++i) put(j, point);
    for (std::size_t i = 0; i < 12; ++i) put(j, i % 2 == 0 ? flat : touching);
  }
  // Classes: chunk 0's boxes (category 1, mask 2) pair only with the later ones (2, 0).
  box cross = spot(1.0f);
  cross.category = 1;
  cross.mask = 2;
  for (std::size_t i = 0; i < 40; ++i) put(0, cross);
  cross.category = 2;
  cross.mask = 0;
  for (std::size_t j = 1; j < k; ++j) {
    for (std::size_t i = 0; i < 35; ++i) put(j, cross);
  }
  // Consecutive ids across the boundary of chunks 0 and 1.
  const box across = spot(2.0f);
  const std::size_t b1 = chunk_start(n, k, 1);
  for (std::size_t i = b1 - 40; i < b1 + 40; ++i) all[i] = across;
  // Chunk 0 spans the whole scene (the plan's bounds): corners of [0, 1000]^3.
  all[0] = make_box(0, 0, 0, 1, 1, 1);
  all[1] = make_box(999, 999, 999, 1, 1, 1);
  box_set s;
  for (const box& b : all) s.push_back(b);
  return s;
}

box_set busy_stages(std::size_t n, std::size_t k, std::uint64_t seed) {
  // Built for a fixed cell edge of 12.5 in [0, 1000]^3 (about 5x10^5 cells): small boxes (edges up
  // to 10) all over, so each stage's cells give it about 10^5 tiles or more, several batches
  // a stage (the cap, tuning::max_batches over k), and stage j + 1's count and map are queued
  // (map_next, polled between batches) while stage j's batches run. Every chunk also holds boxes
  // of edge 100 (over 64 cells: handled apart); every chunk from 1 on, 260 identical boxes at one
  // spot (a cell past tuning::small_cell_sort: that stage's map takes CUB's segmented sort, whose
  // scratch may grow, freeing the old one, while the earlier stage's batches run). Category 1,
  // mask 1 throughout.
  rng_box_maker r(seed);
  box_set s;
  for (std::size_t j = 0; j < k; ++j) {
    const std::size_t b = chunk_start(n, k, j), e = chunk_start(n, k, j + 1);
    for (std::size_t i = b; i < e; ++i) {
      const std::size_t at = i - b;
      if (j > 0 && at >= 100 && at < 360) {
        s.push_back(make_box(500.5f, 500.5f, 500.5f, 2, 2, 2));
      } else if (at % 4001 == 17) {
        s.push_back(make_box(r.uni(0, 900), r.uni(0, 900), r.uni(0, 900), 100, 100, 100));
      } else {
        s.push_back(r.make(1000, 10));
      }
    }
  }
  return s;
}

}  // namespace

TEST_SUITE("gpu.pbig.overlap") {
  TEST_CASE("overlapped upload: the stage kernel's layout tests each pair with a box of the chunk once") {
    // check_stage_kernel's loops over stage_layout, replayed on the host at every width W for a
    // cell of q boxes of chunk j (positions p..p+q-1) and p earlier ones: an item's L = min(W, 32)
    // lanes hold rows lane + r L (r < W / L), each tile's columns are loaded by the same lanes;
    // every pair with at least one box of chunk j is tested exactly once (with Eq. 7 on the
    // triangles and without), no pair of two earlier boxes, every column of a tile is loaded once,
    // and the tiles are numbered 0..tiles()-1 without gaps.
    namespace d = zone::gpu::detail;
    const std::uint32_t sizes[] = {0, 1, 2, 7, 8, 9, 15, 16, 17, 31, 32, 33, 63, 64, 65, 96, 97, 130, 257};
    for (const std::uint32_t W : d::stage_widths) {
      const std::uint32_t L = std::min(W, 32u), R = W / L;
      REQUIRE(L * R == W);
      for (const std::uint32_t q : sizes) {
        for (const std::uint32_t p : sizes) {
          for (const bool balanced : {true, false}) {
            CAPTURE(W);
            CAPTURE(q);
            CAPTURE(p);
            CAPTURE(balanced);
            const d::stage_cell_layout l = d::stage_layout(q, p, W);
            REQUIRE(l.items == (q + W - 1) / W);
            REQUIRE(l.earlier == (q == 0 ? 0 : (p + W - 1) / W));
            std::vector<int> tile_seen(l.tiles(), 0);
            std::vector<std::uint32_t> tested(std::size_t{p + q} * (p + q), 0);  // [min * (p + q) + max]
            std::uint64_t past_tile = 0;                                         // columns tested past the tile's n
            for (std::uint32_t u = 0; u < l.items; ++u) {
              const std::uint32_t m = std::min(W, q - u * W);
              for (std::uint32_t t = 0; t < l.tiles_of(u); ++t) {
                REQUIRE(l.first_tile(u) + t < tile_seen.size());
                ++tile_seen[l.first_tile(u) + t];
                const bool earlier = t < l.earlier;
                const std::uint32_t seg = earlier ? t : u + (t - l.earlier);
                const std::uint32_t n = std::min(W, (earlier ? p : q) - seg * W);
                std::vector<int> loaded(W, 0);
                for (std::uint32_t lane = 0; lane < L; ++lane) {
                  for (std::uint32_t r = 0; r < R; ++r) {
                    if (lane + r * L < n) ++loaded[lane + r * L];
                  }
                }
                REQUIRE(std::count(loaded.begin(), loaded.begin() + n, 1) == static_cast<std::ptrdiff_t>(n));
                for (std::uint32_t lane = 0; lane < L; ++lane) {
                  for (std::uint32_t r = 0; r < R; ++r) {
                    const std::uint32_t row = lane + r * L;
                    if (row >= m) continue;
                    const std::uint32_t at = p + u * W + row;
                    auto test = [&](std::uint32_t j) {
                      if (j >= n) {
                        ++past_tile;
                        return;
                      }
                      const std::uint32_t c = earlier ? seg * W + j : p + seg * W + j;
                      ++tested[std::size_t{std::min(at, c)} * (p + q) + std::max(at, c)];
                    };
                    if (earlier || seg > u) {
                      for (std::uint32_t j = 0; j < n; ++j) test(j);
                    } else if (balanced) {
                      REQUIRE(n == m);
                      const std::uint32_t x = row < (m + 1) / 2 ? (m + 2) / 2 : (m + 1) / 2;
                      std::uint32_t j = row;
                      for (std::uint32_t k = 1; k < x; ++k) {
                        if (++j == m) j = 0;
                        test(j);
                      }
                    } else {
                      for (std::uint32_t j = row + 1; j < m; ++j) test(j);
                    }
                  }
                }
              }
            }
            CHECK(std::all_of(tile_seen.begin(), tile_seen.end(), [](int c) { return c == 1; }));
            CHECK(past_tile == 0);
            // Each pair (a, b), a < b, with b a box of chunk j (b >= p) once; nothing else.
            std::uint64_t once = 0, wrong = 0;
            for (std::uint32_t x = 0; x < p + q; ++x) {
              for (std::uint32_t y = 0; y < p + q; ++y) {
                const std::uint32_t c = tested[std::size_t{x} * (p + q) + y];
                const bool wanted = x < y && y >= p;
                once += (wanted && c == 1) ? 1 : 0;
                wrong += ((wanted && c != 1) || (!wanted && c != 0)) ? 1 : 0;
              }
            }
            CHECK(once == std::uint64_t{q} * p + std::uint64_t{q} * (q - (q > 0 ? 1 : 0)) / 2);
            CHECK(wrong == 0);
          }
        }
      }
    }
  }

  TEST_CASE("overlapped upload: families in 2, 3 and 7 chunks against brute force and the one-shot path") {
    thread_pool pool(4);
    brute_force_finder brute(&pool);
    auto whole = make_gpu(one_shot(&pool));
    // One finder per chunk count (the plan's stage width), then 3 chunks at widths 8 and 32,
    // reused from set to set (sizes and plans change between calls).
    const std::uint32_t chunk_counts[] = {2, 3, 7, 3, 3};
    const std::uint32_t widths[] = {0, 0, 0, 8, 32};
    std::vector<std::unique_ptr<pair_finder>> finders;
    for (std::size_t i = 0; i < std::size(chunk_counts); ++i) {
      gpu::pbig_options o = overlapped(chunk_counts[i], &pool);
      o.overlap_stage_width = widths[i];
      finders.push_back(make_gpu(o));
    }
    std::size_t set = 0;
    for (const family f : {family::uniform, family::huge_over_tiny, family::long_thin, family::negative_large,
                           family::mask_mix, family::integer_grid, family::flat_world, family::few_classes}) {
      // A size per family (a message naming the size names the family), none that 2, 3 or 7 divides.
      const std::size_t n = 16411 + 420 * set++;
      const auto seed = fresh_seed();
      CAPTURE(family_name(f));
      CAPTURE(n);
      CAPTURE(seed);
      const box_set s = make_family(f, n, seed);
      const gpu::pinned_boxes pin(s);
      REQUIRE(pin.active());
      const pair_list want = sorted(run(brute, s));
      CHECK(sorted(view_of(*whole, s)) == want);
      for (std::size_t i = 0; i < finders.size(); ++i) {
        const std::uint32_t k = chunk_counts[i];
        CAPTURE(k);
        CAPTURE(widths[i]);
        check_overlapped(*finders[i], s, want, k);
      }
      check_overlapped(*finders[1], s, want, 3);  // again: plan reused, buffers kept
    }
  }

  TEST_CASE("overlapped upload: far chunks, duplicates, zero extents, straddling boxes, stages without pairs") {
    thread_pool pool(4);
    brute_force_finder brute(&pool);
    for (const std::uint32_t k : {2u, 3u, 7u}) {
      const std::size_t n = 19001 + k;  // chunk sizes not dividing n
      const auto seed = fresh_seed();
      CAPTURE(k);
      CAPTURE(seed);
      struct named {
        const char* name;
        box_set set;
      };
      const named sets[] = {{"far chunks", far_chunks(n, k, seed)},
                            {"duplicates", duplicates(n, seed)},
                            {"degenerate", degenerate(n, seed)},
                            {"straddling", straddling(n, seed)},
                            {"lonely stages", lonely_stages(n, k, seed)}};
      auto finder = make_gpu(overlapped(k, &pool));
      for (const named& t : sets) {
        CAPTURE(t.name);
        const gpu::pinned_boxes pin(t.set);
        REQUIRE(pin.active());
        const pair_list want = sorted(run(brute, t.set));
        check_overlapped(*finder, t.set, want, k);
        if (std::string(t.name) == "lonely stages") {
          // No pair across chunks and none in chunk 1; the last chunk's boxes are handled apart.
          const std::size_t c1 = chunk_start(n, k, 1), c2 = chunk_start(n, k, 2), last = chunk_start(n, k, k - 1);
          CHECK(std::none_of(want.begin(), want.end(), [&](const id_pair& p) { return p.a >= c1 && p.a < c2; }));
          CHECK(std::any_of(want.begin(), want.end(), [&](const id_pair& p) { return p.b >= last; }));
          const gpu::pbig_report* rep = gpu::last_pbig_report(*finder);
          REQUIRE(rep != nullptr);
          CHECK(rep->pairs == want.size());
        }
      }
    }
  }

  TEST_CASE("overlapped upload: crowded cells, chunk by chunk (the stage kernel's row and column segments)") {
    thread_pool pool(4);
    brute_force_finder brute(&pool);
    for (const std::uint32_t k : {2u, 3u, 7u}) {
      const std::size_t n = 20011 + k;
      const auto seed = fresh_seed();
      CAPTURE(k);
      CAPTURE(seed);
      const box_set s = crowded_cells(n, k, seed);
      const gpu::pinned_boxes pin(s);
      REQUIRE(pin.active());
      const pair_list want = sorted(run(brute, s));
      for (const bool balanced : {true, false}) {
        for (const std::uint32_t width : {0u, 8u, 16u, 32u, 64u}) {  // 0: the plan's choice
          CAPTURE(balanced);
          CAPTURE(width);
          gpu::pbig_options o = overlapped(k, &pool);
          o.load_balancing = balanced;
          o.overlap_stage_width = width;
          auto finder = make_gpu(o);
          check_overlapped(*finder, s, want, k);
          CHECK(finder->stats().large_boxes == 0);  // every pair came from the stages' checks
          if (width != 0) CHECK(gpu::last_pbig_report(*finder)->stage_width == width);
        }
      }
    }
  }

  TEST_CASE("overlapped upload: deterministic order, overflowing buffers re-run, find() and no load balancing") {
    thread_pool pool(4);
    const auto seed = fresh_seed();
    CAPTURE(seed);
    const box_set s = *generate_named("uniform", 60000, seed);
    const gpu::pinned_boxes pin(s);
    REQUIRE(pin.active());
    const pair_list want = cpu_pairs(s, &pool);
    REQUIRE(!want.empty());
    auto a = make_gpu(overlapped(3, &pool));
    auto b = make_gpu(overlapped(3, &pool));
    const pair_list first = view_of(*a, s);
    CHECK(sorted(first) == want);
    CHECK(view_of(*a, s) == first);  // same order on the next call
    CHECK(view_of(*b, s) == first);  // and on another finder
    // 1-pair buffers: every batch overflows and is re-run; the same pairs in the same order.
    gpu::pbig_options tiny = overlapped(3, &pool);
    tiny.initial_output_pairs = 1;
    auto t = make_gpu(tiny);
    CHECK(view_of(*t, s) == first);
    const gpu::pbig_report* rep = gpu::last_pbig_report(*t);
    REQUIRE(rep != nullptr);
    CHECK(rep->reruns >= 1);
    CHECK(rep->overlap_chunks == 3);
    // Through pair_finder::find (the pinned result copied into the caller's list).
    pair_list listed;
    REQUIRE_FALSE(a->find(s, listed).has_value());
    CHECK(listed == first);
    // Without Eq. 7's balanced assignment (another order, the same pairs).
    gpu::pbig_options plain = overlapped(7, &pool);
    plain.load_balancing = false;
    auto p = make_gpu(plain);
    check_overlapped(*p, s, want, 7);
  }

  TEST_CASE("overlapped upload: an invalid box in chunk 0 or a later chunk is reported, the next call unaffected") {
    thread_pool pool(4);
    const auto seed = fresh_seed();
    CAPTURE(seed);
    const std::size_t n = 30000;
    box_set s = *generate_named("uniform", n, seed);
    const gpu::pinned_boxes pin(s);
    REQUIRE(pin.active());
    const pair_list want = cpu_pairs(s, &pool);
    auto finder = make_gpu(overlapped(3, &pool));
    check_overlapped(*finder, s, want, 3);
    for (const std::size_t bad : {std::size_t{17}, chunk_start(n, 3, 1) + 5, n - 1}) {  // chunks 0, 1 and 2
      CAPTURE(bad);
      const float keep = s.lo_y[bad];
      s.lo_y[bad] = s.hi_y[bad] + 1.0f;
      std::span<const id_pair> got;
      const auto err = gpu::find_pairs_view(*finder, s, got);
      REQUIRE(err.has_value());
      CHECK(err->index == bad);
      CHECK(err->message == validate(s)->message);
      CHECK(got.empty());
      s.lo_y[bad] = std::numeric_limits<float>::quiet_NaN();
      const auto err2 = gpu::find_pairs_view(*finder, s, got);
      REQUIRE(err2.has_value());
      CHECK(err2->index == bad);
      s.lo_y[bad] = keep;
      check_overlapped(*finder, s, want, 3);
    }
  }

  TEST_CASE("overlapped upload: stages mapped while the earlier stages' batches run, with boxes handled apart, "
            "classes filled per chunk, overflowing buffers and an invalid box in a later chunk") {
    // The stage stream's hazards at once (docs/gpu.md, "Overlapped upload"): several batches a
    // stage, so stage j + 1's count, read-back (written by a kernel into pinned memory) and map run
    // on the stage stream while stage j's checks and copies run on the slots; boxes handled apart
    // in every chunk (the count's large flags, read by main_'s passes after the last map); classes
    // filled on the stage stream for chunks 0 and 2.. and copied for chunk 1 (one other box); every
    // batch overflowing its 1-pair buffer and re-run; then an invalid box in chunk 1, chunk 2 and
    // the last chunk, found by a stage's read-back while earlier stages' batches are in flight,
    // each call followed by a valid one whose pairs and order are the first call's.
    thread_pool pool(4);
    for (const std::uint32_t k : {3u, 7u}) {
      const std::size_t n = 300007 + k;  // from 2^18 boxes: classes filled when uniform
      const auto seed = fresh_seed();
      CAPTURE(k);
      CAPTURE(seed);
      box_set s = busy_stages(n, k, seed);
      const std::size_t odd = chunk_start(n, k, 1) + 1000;  // chunk 1 copies its classes
      s.category[odd] = 2;
      s.mask[odd] = 2;
      std::size_t large = 0;
      for (std::size_t i = 0; i < n; ++i) large += s.hi_x[i] - s.lo_x[i] > 99.0f ? 1 : 0;
      REQUIRE(large >= 2 * k);
      const gpu::pinned_boxes pin(s);
      REQUIRE(pin.active());
      const pair_list want = cpu_pairs(s, &pool);
      gpu::pbig_options o = overlapped(k, &pool);
      o.fixed_cell_edge = 12.5;
      auto a = make_gpu(o);
      gpu::pbig_options tiny = o;
      tiny.initial_output_pairs = 1;
      auto t = make_gpu(tiny);

      const pair_list first = view_of(*a, s);
      CHECK(sorted(first) == want);
      const gpu::pbig_report* rep = gpu::last_pbig_report(*a);
      REQUIRE(rep != nullptr);
      CHECK(rep->overlap_chunks == k);
      CHECK(rep->pairs == want.size());
      CHECK(rep->batches >= 2 * k);  // more than one batch a stage: the next stage mapped between them
      CHECK_FALSE(rep->classes_filled);
      CHECK(rep->bytes_in == 24u * n + 8u * (chunk_start(n, k, 2) - chunk_start(n, k, 1)));
      CHECK(a->stats().large_boxes == large);
      // DataOut is the union of the copies' spans, all within the call.
      CHECK(rep->data_out_ms > 0);
      CHECK(rep->data_out_ms <= rep->total_ms + 0.05);
      CHECK(rep->map_ms > 0);

      CHECK(view_of(*t, s) == first);  // every batch re-run: the same pairs in the same order
      const gpu::pbig_report* trep = gpu::last_pbig_report(*t);
      REQUIRE(trep != nullptr);
      CHECK(trep->reruns >= 2);  // each slot's first batch at least
      CHECK(trep->batches == rep->batches);

      for (const std::size_t bad : {chunk_start(n, k, 1) + 5, chunk_start(n, k, 2) + 5, n - 1}) {
        CAPTURE(bad);
        for (auto* f : {a.get(), t.get()}) {
          const float keep = s.lo_z[bad];
          s.lo_z[bad] = s.hi_z[bad] + 1.0f;
          std::span<const id_pair> got;
          const auto err = gpu::find_pairs_view(*f, s, got);
          REQUIRE(err.has_value());
          CHECK(err->index == bad);
          CHECK(err->message == validate(s)->message);
          CHECK(got.empty());
          s.lo_z[bad] = keep;
          CHECK(view_of(*f, s) == first);
          CHECK(gpu::last_pbig_report(*f)->overlap_chunks == k);
        }
      }
    }
  }

  TEST_CASE("overlapped upload: classes filled per chunk when they are box 0's") {
    // From 2^18 boxes on, a chunk whose boxes share box 0's category and mask uploads 24 bytes a
    // box; a chunk with one other box uploads 32.
    thread_pool pool(4);
    const auto seed = fresh_seed();
    CAPTURE(seed);
    const std::size_t n = 300001, k = 3;
    box_set s = *generate_named("uniform", n, seed);
    std::fill(s.category.begin(), s.category.end(), 1u);
    std::fill(s.mask.begin(), s.mask.end(), 1u);
    auto finder = make_gpu(overlapped(k, &pool));
    {
      const gpu::pinned_boxes pin(s);
      REQUIRE(pin.active());
      check_overlapped(*finder, s, cpu_pairs(s, &pool), k);
      const gpu::pbig_report* rep = gpu::last_pbig_report(*finder);
      REQUIRE(rep != nullptr);
      CHECK(rep->classes_filled);
      CHECK(rep->bytes_in == 24u * n);
    }
    const std::size_t odd = chunk_start(n, k, 1) + 11;
    s.category[odd] = 2;
    s.mask[odd] = 2;
    const gpu::pinned_boxes pin(s);
    REQUIRE(pin.active());
    check_overlapped(*finder, s, cpu_pairs(s, &pool), k);
    const gpu::pbig_report* rep = gpu::last_pbig_report(*finder);
    REQUIRE(rep != nullptr);
    CHECK_FALSE(rep->classes_filled);
    CHECK(rep->bytes_in == 24u * n + 8u * (chunk_start(n, k, 2) - chunk_start(n, k, 1)));
  }

  TEST_CASE("overlapped upload by default from 2^22 pinned boxes, after a first call: the one-shot path's pairs") {
    thread_pool pool(8);
    const auto seed = fresh_seed();
    CAPTURE(seed);
    const std::size_t n = std::size_t{1} << 22;
    const box_set s = *generate_named("uniform", n, seed);
    // Heap arrays of two sets may share a page, and pinned_boxes does not pin pages another live
    // guard holds (gpu/device.h): the first set's guard ends before the second set's starts.
    auto pin = std::make_unique<gpu::pinned_boxes>(s);
    REQUIRE(pin->active());
    gpu::pbig_options defaults;
    defaults.decode_pool = &pool;
    auto finder = make_gpu(defaults);
    auto whole = make_gpu(one_shot(&pool));
    const pair_list want = sorted(view_of(*whole, s));
    CHECK(gpu::last_pbig_report(*whole)->overlap_chunks == 0);
    // The first call knows nothing of the output: one-shot. Its output is small against its
    // input (about 2 pairs a box: 17 bytes out for 24 in), so the next call takes the pipeline.
    CHECK(sorted(view_of(*finder, s)) == want);
    CHECK(gpu::last_pbig_report(*finder)->overlap_chunks == 0);
    const pair_list got = view_of(*finder, s);
    const gpu::pbig_report* rep = gpu::last_pbig_report(*finder);
    REQUIRE(rep != nullptr);
    CHECK(rep->overlap_chunks == 3);  // the default chunk count
    CHECK(rep->stage_width == 64);    // f >= 32 boxes a cell: a chunk's share past 16 (pbig_tuning.h)
    CHECK(sorted(got) == want);
    grid_finder grid(&pool);
    pair_list cpu;
    REQUIRE_FALSE(grid.find(s, cpu).has_value());
    CHECK(cpu.size() == want.size());
    // One box fewer: below the threshold, the one-shot path.
    box_set smaller = s;
    smaller.resize(n - 1);
    pin.reset();
    const gpu::pinned_boxes pin2(smaller);
    REQUIRE(pin2.active());
    (void)view_of(*finder, smaller);
    CHECK(gpu::last_pbig_report(*finder)->overlap_chunks == 0);
  }

  TEST_CASE("overlapped upload's rule: only after a call of about this size whose output was at most 3x its input") {
    // Threshold lowered to 2 boxes, the rule itself as by default. Sparse: a few pairs for 20,000
    // boxes (out << in); dense: about 110 pairs a box (out about 28x in).
    thread_pool pool(4);
    brute_force_finder brute(&pool);
    gpu::pbig_options o;
    o.decode_pool = &pool;
    o.overlap_min_boxes = 2;
    auto finder = make_gpu(o);
    const std::size_t n = 20000;
    const auto seed = fresh_seed();
    CAPTURE(seed);
    const box_set sparse = make_family(family::negative_large, n, seed);
    const box_set dense = make_family(family::mask_mix, n, seed + 1);
    const box_set bigger = make_family(family::negative_large, n + n / 2, seed + 2);  // 1.5x: not about this size
    const gpu::pinned_boxes pin_s(sparse), pin_d(dense), pin_b(bigger);
    REQUIRE(pin_s.active());
    REQUIRE(pin_d.active());
    REQUIRE(pin_b.active());
    const pair_list want_sparse = sorted(run(brute, sparse)), want_dense = sorted(run(brute, dense));
    const pair_list want_bigger = cpu_pairs(bigger, &pool);
    REQUIRE(want_dense.size() * 8 > 3 * 32 * n);
    REQUIRE(want_sparse.size() * 8 < 3 * 32 * n);
    struct call {
      const box_set* set;
      const pair_list* want;
      std::uint32_t chunks;  // what the rule gives
    };
    const call calls[] = {
        {&sparse, &want_sparse, 0},  // nothing known
        {&sparse, &want_sparse, 3},  // the last call's output was small
        {&dense, &want_dense, 3},    // ... still (the rule reads the last call)
        {&dense, &want_dense, 0},    // the last call's output was large
        {&sparse, &want_sparse, 0},  // ... still
        {&sparse, &want_sparse, 3},
        {&bigger, &want_bigger, 0},  // another size
        {&bigger, &want_bigger, 3},
    };
    for (std::size_t i = 0; i < std::size(calls); ++i) {
      CAPTURE(i);
      const pair_list got = sorted(view_of(*finder, *calls[i].set));
      CHECK(got == *calls[i].want);
      const gpu::pbig_report* rep = gpu::last_pbig_report(*finder);
      REQUIRE(rep != nullptr);
      CHECK(rep->overlap_chunks == calls[i].chunks);
    }
    // An invalid call leaves the record as it was.
    box_set bad = bigger;
    bad.hi_x[5] = bad.lo_x[5] - 1.0f;
    const gpu::pinned_boxes pin_bad(bad);
    std::span<const id_pair> none;
    REQUIRE(gpu::find_pairs_view(*finder, bad, none).has_value());
    CHECK(sorted(view_of(*finder, bigger)) == want_bigger);
    CHECK(gpu::last_pbig_report(*finder)->overlap_chunks == 3);
  }
}
