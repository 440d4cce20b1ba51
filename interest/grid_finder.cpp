// The fast CPU finder: the PBIG algorithm's grid ideas, run on CPU threads.
//
// Why a uniform grid and not CGAL's streaming segment tree or a sweep: the boxes of a zone are
// many, small and evenly sized, so with the cell edge chosen by Eq. 6 a cell holds a handful of
// boxes, every step is a linear pass (count, scan, map) or a tiny all-pairs test, the work splits
// over threads without locks, and the output-cell rule makes each pair appear once without a
// de-duplication pass. docs/gpu-benchmarks.md ("The CPU pair finders") has the measurements
// against CGAL.
//
// Steps of one call:
//  1. bounds: the scene's bounding box (the grid's origin and extent);
//  2. plan (plan_grid): the cubic cell edge by Eq. 6, W = options.min_boxes_per_cell; an axis
//     on which nearly every box spans one common plane (a zone's ground) is left as one slab
//     and the other two are planned with 2W (flat_axis below);
//  3. classify: a box that would occupy far more cells than the average is "large" and kept out
//     of the grid (memory stays linear however big a few boxes are);
//  4. count, scan, map: (cell, box) entries of the other boxes, cell-sorted; each cell's list is
//     sorted by box id so the output order does not depend on thread timing;
//  5. check: per cell, every pair once; reported only in the cell holding the max corner of the
//     pair's intersection, i.e. the cell whose coordinate on each axis is min(hi-cell of a,
//     hi-cell of b): both boxes occupy that cell (monotone cell mapping), so exactly one cell
//     reports each intersecting pair;
//  6. large boxes: each walks the grid cells it covers (same output-cell rule against the grid's
//     boxes), and the large boxes are tested among themselves directly.
// Cells are split into a fixed number of chunks (independent of the thread count) and the chunks'
// outputs are concatenated in order: the same input gives the same output with any thread count.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <utility>
#include <limits>
#include <random>

#include "interest.h"
#include "thread_pool.h"

namespace zone::interest {
namespace {

/// run_tasks without a heap allocation per call: std::function keeps a reference_wrapper in
/// place, where a lambda capturing several references would be copied to the heap.
template <class F>
void run_each(thread_pool* pool, std::size_t n, F&& task) {
  run_tasks(pool, n, std::ref(task));
}

/// One box as the check loop reads it: bounds, filter bits and the cell of its max corner.
struct alignas(64) packed_box {
  float lo[3];
  float hi[3];
  std::uint32_t category;
  std::uint32_t mask;
  std::int32_t hi_cell[3];
  std::int32_t lo_cell[3];
  box_id id;  // the box's id in the caller's set
};

/// Stable LSD radix sort of 64-bit items by bits [32, 32 + key_bits) (the key; the low 32 bits
/// are the payload). Chunks count digits in parallel; stability makes the result unique.
void radix_sort_by_key(std::vector<std::uint64_t>& items, std::vector<std::uint64_t>& tmp, int key_bits,
                       thread_pool* pool, std::vector<std::size_t>& offsets) {
  constexpr int digit_bits = 11;
  constexpr std::size_t buckets = std::size_t{1} << digit_bits;
  const std::size_t n = items.size();
  tmp.resize(n);
  const std::size_t chunks = std::clamp<std::size_t>(n / 65536, 1, 32);
  offsets.resize(chunks * buckets);
  for (int shift = 32; shift < 32 + key_bits; shift += digit_bits) {
    std::fill(offsets.begin(), offsets.end(), 0);
    run_each(pool, chunks, [&](std::size_t c) {
      std::size_t* count = offsets.data() + c * buckets;
      for (std::size_t i = n * c / chunks, e = n * (c + 1) / chunks; i < e; ++i) ++count[(items[i] >> shift) & (buckets - 1)];
    });
    std::size_t running = 0;
    for (std::size_t d = 0; d < buckets; ++d) {
      for (std::size_t c = 0; c < chunks; ++c) running += std::exchange(offsets[c * buckets + d], running);
    }
    run_each(pool, chunks, [&](std::size_t c) {
      std::size_t* at = offsets.data() + c * buckets;
      for (std::size_t i = n * c / chunks, e = n * (c + 1) / chunks; i < e; ++i) {
        tmp[at[(items[i] >> shift) & (buckets - 1)]++] = items[i];
      }
    });
    items.swap(tmp);
  }
}

int bits_for(std::uint64_t values) {
  int bits = 1;
  while (bits < 63 && (std::uint64_t{1} << bits) < values) ++bits;
  return bits;
}

/// Cell coordinate of x on one axis: floor((x - origin) / edge), clamped to the grid. The same
/// function maps lo and hi corners everywhere, so it is monotone and consistent.
struct cell_mapper {
  double origin[3];
  double inv_edge[3];
  std::int32_t last[3];  // dims - 1
  [[nodiscard]] std::int32_t operator()(float x, int d) const {
    const double c = std::floor((static_cast<double>(x) - origin[d]) * inv_edge[d]);
    if (c <= 0.0) return 0;
    if (c >= static_cast<double>(last[d])) return last[d];
    return static_cast<std::int32_t>(c);
  }
};

cell_mapper make_mapper(const grid_plan& p) {
  cell_mapper m{};
  for (int d = 0; d < 3; ++d) {
    m.origin[d] = p.origin[d];
    m.inv_edge[d] = 1.0 / p.cell_edge;
    m.last[d] = static_cast<std::int32_t>(p.dims[d]) - 1;
  }
  return m;
}

struct bounds {
  float lo[3]{std::numeric_limits<float>::max(), std::numeric_limits<float>::max(), std::numeric_limits<float>::max()};
  float hi[3]{std::numeric_limits<float>::lowest(), std::numeric_limits<float>::lowest(), std::numeric_limits<float>::lowest()};
};

/// Scratch memory of planning, reused across calls.
struct plan_scratch {
  std::vector<bounds> part;         // per chunk of scene_bounds
  std::vector<std::size_t> sample;  // box indices of the planning sample
  std::vector<double> centre;       // flat_axis: sampled centres
  std::vector<double> rel;          // sampled corners relative to the origin, by axis and side
  std::vector<double> cells;        // cells per sampled box
};

bounds scene_bounds(const box_set& s, thread_pool* pool, plan_scratch& ps) {
  const std::size_t n = s.size();
  const std::size_t chunks = std::clamp<std::size_t>(n / 65536, 1, 64);
  auto& part = ps.part;
  part.assign(chunks, bounds{});
  const float* lo[3] = {s.lo_x.data(), s.lo_y.data(), s.lo_z.data()};
  const float* hi[3] = {s.hi_x.data(), s.hi_y.data(), s.hi_z.data()};
  run_each(pool, chunks, [&](std::size_t c) {
    const std::size_t b = n * c / chunks, e = n * (c + 1) / chunks;
    for (int d = 0; d < 3; ++d) {
      float mn = part[c].lo[d], mx = part[c].hi[d];
      for (std::size_t i = b; i < e; ++i) {
        mn = std::min(mn, lo[d][i]);
        mx = std::max(mx, hi[d][i]);
      }
      part[c].lo[d] = mn;
      part[c].hi[d] = mx;
    }
  });
  bounds all;
  for (const auto& p : part) {
    for (int d = 0; d < 3; ++d) {
      all.lo[d] = std::min(all.lo[d], p.lo[d]);
      all.hi[d] = std::max(all.hi[d], p.hi[d]);
    }
  }
  return all;
}

/// Grid dimensions for edge l over the given extents: floor(extent / l) + 1 cells per axis, and
/// one cell on the `flat` axis (-1: none).
void dims_for(const double extent[3], double l, double dims[3], int flat) {
  for (int d = 0; d < 3; ++d) dims[d] = d == flat ? 1.0 : std::floor(extent[d] / l) + 1.0;
}

grid_plan plan_with(const box_set& s, const bounds& b, const grid_finder_options& opt, int flat, plan_scratch& ps) {
  grid_plan plan;
  const std::size_t n = s.size();
  double extent[3];
  for (int d = 0; d < 3; ++d) {
    plan.origin[d] = b.lo[d];
    extent[d] = std::max(0.0, static_cast<double>(b.hi[d]) - static_cast<double>(b.lo[d]));
  }
  const double max_extent = std::max({extent[0], extent[1], extent[2]});
  // Cells are capped so the counter array stays linear in N, and the cell id fits 32 bits.
  const double max_cells = std::min(2.0 * static_cast<double>(n) + 64.0, 2147483647.0);

  // The planning sample: a fixed-seed simple random sample (with replacement) of box indices.
  auto& sample = ps.sample;
  sample.clear();
  if (n > 0) {
    const std::size_t k = std::min(n, std::max<std::size_t>(1, opt.alpha_samples));
    sample.resize(k);
    if (k == n) {
      for (std::size_t i = 0; i < k; ++i) sample[i] = i;
    } else {
      std::mt19937_64 rng(opt.sample_seed);
      for (auto& i : sample) i = static_cast<std::size_t>(rng() % n);
    }
  }

  // alpha(l): the average number of cells a sampled box occupies, counted exactly with the
  // candidate grid's cell mapping (the quantity Eq. 4-5 estimate from box and cell lengths).
  // The sampled boxes' corners relative to the origin, gathered once (the search below calls
  // alpha_for a few dozen times).
  const std::size_t k_sample = sample.size();
  auto& rel = ps.rel;
  rel.resize(6 * k_sample);
  {
    const float* lo[3] = {s.lo_x.data(), s.lo_y.data(), s.lo_z.data()};
    const float* hi[3] = {s.hi_x.data(), s.hi_y.data(), s.hi_z.data()};
    for (int d = 0; d < 3; ++d) {
      for (std::size_t j = 0; j < k_sample; ++j) {
        rel[(2 * d) * k_sample + j] = lo[d][sample[j]] - static_cast<double>(b.lo[d]);
        rel[(2 * d + 1) * k_sample + j] = hi[d][sample[j]] - static_cast<double>(b.lo[d]);
      }
    }
  }
  auto alpha_for = [&](double l, const double dims[3]) {
    if (sample.empty()) return 1.0;
    // Cells per sampled box, axis by axis (an axis of one cell contributes a factor of 1).
    auto& cells = ps.cells;
    cells.assign(k_sample, 1.0);
    for (int d = 0; d < 3; ++d) {
      if (dims[d] <= 1) continue;
      const double last = dims[d] - 1;
      const double* rlo = rel.data() + (2 * d) * k_sample;
      const double* rhi = rel.data() + (2 * d + 1) * k_sample;
      for (std::size_t j = 0; j < k_sample; ++j) {
        const double a = std::clamp(std::floor(rlo[j] / l), 0.0, last);
        const double z = std::clamp(std::floor(rhi[j] / l), 0.0, last);
        cells[j] *= z - a + 1;
      }
    }
    double total = 0;
    for (const double c : cells) total += c;
    return total / static_cast<double>(sample.size());
  };

  auto finish = [&](double l) {
    double dims[3];
    dims_for(extent, l, dims, flat);
    plan.cell_edge = l;
    for (int d = 0; d < 3; ++d) plan.dims[d] = static_cast<std::uint32_t>(dims[d]);
    plan.alpha = alpha_for(l, dims);
    return plan;
  };

  if (max_extent <= 0.0 || n < 2) return finish(std::max(1.0, max_extent));
  if (opt.fixed_cell_edge > 0) {
    // A fixed edge (the cell-size sweep) still respects the cell cap.
    double l = opt.fixed_cell_edge;
    double dims[3];
    for (;;) {
      dims_for(extent, l, dims, flat);
      if (dims[0] * dims[1] * dims[2] <= max_cells) break;
      l *= 1.25;
    }
    return finish(l);
  }

  // Eq. 6: minimise f = N alpha / M subject to f >= W. f grows with l, so the answer is the
  // smallest l with f(l) >= W (and within the cell cap): binary search on l.
  const double w = std::max(1.0, opt.min_boxes_per_cell);
  auto f_of = [&](double l) {  // f(l), or +inf past the cell cap
    double dims[3];
    dims_for(extent, l, dims, flat);
    const double m = dims[0] * dims[1] * dims[2];
    if (m > max_cells) return std::numeric_limits<double>::infinity();
    return static_cast<double>(n) * alpha_for(l, dims) / m;
  };
  // Smallest l in (lo, hi] with pred(l), assuming pred is false at lo and true at hi.
  auto bisect = [](double lo_l, double hi_l, auto&& pred) {
    for (int it = 0; it < 48 && hi_l - lo_l > hi_l * 1e-4; ++it) {
      const double mid = 0.5 * (lo_l + hi_l);
      (pred(mid) ? hi_l : lo_l) = mid;
    }
    return hi_l;
  };
  const double one_cell = max_extent * (1.0 + 1e-6) + 1e-6;  // one cell: f = N
  auto feasible = [&](double l) { const double f = f_of(l); return std::isfinite(f) && f >= w; };
  if (!feasible(one_cell)) return finish(one_cell);  // N < W: one cell is the best we can do
  double lo_l = one_cell;
  for (int k = 0; k < 200 && feasible(lo_l); ++k) lo_l /= 2;  // bracket from below
  const double best = bisect(lo_l, one_cell, feasible);
  // Ties: where f is flat (boxes that all cover each other, so alpha grows as fast as M), every
  // edge is a minimiser of Eq. 6; take the largest edge whose f is within 5% of the minimum, which
  // has the fewest redundant checks. Where f rises with l (the usual case) this moves l by ~1%.
  const double f_best = f_of(best);
  if (f_of(one_cell) <= f_best * 1.05) return finish(one_cell);
  const double tie = bisect(best, one_cell, [&](double l) { return f_of(l) > f_best * 1.05; });
  return finish(tie * (1.0 - 1e-4) > best ? tie * (1.0 - 1e-4) : best);
}

/// The axis to leave unsplit, or -1. On an axis where (nearly) every box contains one common
/// plane, as the ground of a zone where every AOI box and every body spans z = 0, cutting the
/// axis into cells separates no boxes and only multiplies the (cell, box) entries. Tested on the
/// planning sample: the plane is the median of the sampled centres on the axis of least scene
/// extent, and the axis is flat when at least 90% of the sampled boxes contain it.
int flat_axis(const box_set& s, const bounds& b, const grid_finder_options& opt, plan_scratch& ps) {
  const std::size_t n = s.size();
  if (n < 2) return -1;
  int d = 0;
  for (int k = 1; k < 3; ++k) {
    if (static_cast<double>(b.hi[k]) - b.lo[k] < static_cast<double>(b.hi[d]) - b.lo[d]) d = k;
  }
  const float* lo = d == 0 ? s.lo_x.data() : d == 1 ? s.lo_y.data() : s.lo_z.data();
  const float* hi = d == 0 ? s.hi_x.data() : d == 1 ? s.hi_y.data() : s.hi_z.data();
  const std::size_t k = std::min(n, std::max<std::size_t>(1, opt.alpha_samples));
  auto& sample = ps.sample;
  sample.resize(k);
  std::mt19937_64 rng(opt.sample_seed ^ 0x666c6174ull);
  for (std::size_t i = 0; i < k; ++i) sample[i] = k == n ? i : static_cast<std::size_t>(rng() % n);
  auto& centre = ps.centre;
  centre.resize(k);
  for (std::size_t i = 0; i < k; ++i) centre[i] = 0.5 * (static_cast<double>(lo[sample[i]]) + hi[sample[i]]);
  std::nth_element(centre.begin(), centre.begin() + static_cast<std::ptrdiff_t>(k / 2), centre.end());
  const double plane = centre[k / 2];
  std::size_t containing = 0;
  for (const std::size_t i : sample) containing += (lo[i] <= plane && plane <= hi[i]) ? 1 : 0;
  return static_cast<double>(containing) >= 0.9 * static_cast<double>(k) ? d : -1;
}

grid_plan plan_from_bounds(const box_set& s, const bounds& b, const grid_finder_options& opt, plan_scratch& ps) {
  const int flat = flat_axis(s, b, opt, ps);
  if (flat < 0) return plan_with(s, b, opt, -1, ps);
  // A cell of a flat grid is a column holding every box over its footprint; on the zone's boxes
  // the best W for it is about twice the 3D one (bench-zone --sweep-w, docs/zone-benchmarks.md).
  grid_finder_options flat_opt = opt;
  flat_opt.min_boxes_per_cell = 2.0 * opt.min_boxes_per_cell;
  return plan_with(s, b, flat_opt, flat, ps);
}

constexpr std::size_t check_chunk_limit = 512;  // fixed: output order must not depend on threads
constexpr std::size_t large_chunk_limit = 64;
constexpr std::uint32_t max_groups = 8;  // (category, mask) signatures grouped per cell

inline bool boxes_qualify(const packed_box& a, const packed_box& b) {
  return a.lo[0] <= b.hi[0] && b.lo[0] <= a.hi[0] && a.lo[1] <= b.hi[1] && b.lo[1] <= a.hi[1] && a.lo[2] <= b.hi[2] &&
         b.lo[2] <= a.hi[2] && ((a.category & b.mask) | (b.category & a.mask)) != 0;
}

}  // namespace

grid_plan plan_grid(const box_set& boxes, const grid_finder_options& opt) {
  plan_scratch ps;
  return plan_from_bounds(boxes, scene_bounds(boxes, nullptr, ps), opt, ps);
}

/// One cell's boxes as columns, for the branch-free check loop; one per check chunk, reused.
struct cell_columns {
  std::vector<float> lx, ly, lz, hx, hy, hz;
  std::vector<std::uint32_t> cat, msk, flag;
  std::vector<box_id> id;
  std::vector<std::uint8_t> group;  // signature group of the i-th box of the cell's list
  void resize(std::size_t n) {
    if (lx.size() >= n) return;
    // Geometric growth from 256: a chunk's largest cell creeps up over ticks, and each step
    // would otherwise reallocate eleven arrays in the tick.
    n = std::max({n, 2 * lx.size(), std::size_t{256}});
    for (auto* v : {&lx, &ly, &lz, &hx, &hy, &hz}) v->resize(n);
    for (auto* v : {&cat, &msk, &flag, &id}) v->resize(n);
    group.resize(n);
  }
};

struct grid_finder::scratch {
  std::vector<cell_columns> columns;            // per check chunk
  plan_scratch plan;
  std::vector<std::size_t> radix_offsets;       // per (chunk, digit) of radix_sort_by_key
  std::vector<std::size_t> gather_at;           // output offset per chunk's pair list

  std::vector<std::uint64_t> keyed, keyed_tmp;  // (cell << 32 | payload) items being radix-sorted
  std::vector<packed_box> unsorted;             // boxes in input order
  std::vector<packed_box> packed;               // boxes in spatial order
  std::vector<std::uint64_t> entry_offset;      // per packed box + 1: its first grid entry
  std::vector<std::uint32_t> cell_start;        // per cell + 1: offsets into entries
  std::vector<box_id> entries;                  // cell-sorted positions in `packed`
  std::vector<box_id> large;                    // positions in `packed` of large boxes, ascending
  std::vector<pair_list> chunk_pairs;      // per check chunk
  std::vector<pair_list> large_pairs;      // per large-box chunk
  std::vector<std::uint64_t> chunk_checks;
  std::vector<std::uint64_t> large_checks;
};

grid_finder::grid_finder(thread_pool* pool, grid_finder_options opt)
    : pool_(pool), opt_(opt), scratch_(std::make_unique<scratch>()) {}

grid_finder::~grid_finder() = default;

void grid_finder::find_valid(const box_set& boxes, pair_list& out) {
  out.clear();
  const std::size_t n = boxes.size();
  if (n < 2) return;
  if (n > std::numeric_limits<box_id>::max()) throw std::length_error("grid_finder: more boxes than 32-bit ids");
  auto& sc = *scratch_;
  using clock = std::chrono::steady_clock;
  auto lap = [last = clock::now()]() mutable {
    const auto now = clock::now();
    const double ms = std::chrono::duration<double, std::milli>(now - last).count();
    last = now;
    return ms;
  };

  // 1-2. Bounds and plan.
  plan_ = plan_from_bounds(boxes, scene_bounds(boxes, pool_, sc.plan), opt_, sc.plan);
  const cell_mapper cell = make_mapper(plan_);
  const std::uint32_t dx = plan_.dims[0], dy = plan_.dims[1];
  const std::size_t cells = plan_.cell_count();
  const double large_cells =
      std::max(static_cast<double>(opt_.large_box_min_cells), opt_.large_box_alpha_factor * plan_.alpha);

  // 3. Spatial order: sort the boxes by the cell of their min corner, so that every later pass
  //    (entries, checks) touches memory in nearly sequential order. Then pack them (one cache line
  //    each), find their cell ranges and classify the large ones.
  const std::size_t box_chunks = std::clamp<std::size_t>(n / 16384, 1, 256);
  // Pack in input order (sequential reads of the columns), then permute whole cache lines into
  // spatial order: one random read per box instead of one per column.
  sc.unsorted.resize(n);
  sc.keyed.resize(n);
  run_each(pool_, box_chunks, [&](std::size_t c) {
    for (std::size_t i = n * c / box_chunks, e = n * (c + 1) / box_chunks; i < e; ++i) {
      packed_box& p = sc.unsorted[i];
      p.lo[0] = boxes.lo_x[i];
      p.lo[1] = boxes.lo_y[i];
      p.lo[2] = boxes.lo_z[i];
      p.hi[0] = boxes.hi_x[i];
      p.hi[1] = boxes.hi_y[i];
      p.hi[2] = boxes.hi_z[i];
      p.category = boxes.category[i];
      p.mask = boxes.mask[i];
      p.id = static_cast<box_id>(i);
      for (int d = 0; d < 3; ++d) {
        p.lo_cell[d] = cell(p.lo[d], d);
        p.hi_cell[d] = cell(p.hi[d], d);
      }
      const std::uint64_t lo_cell = (static_cast<std::uint64_t>(p.lo_cell[2]) * dy + static_cast<std::uint64_t>(p.lo_cell[1])) * dx +
                                    static_cast<std::uint64_t>(p.lo_cell[0]);
      sc.keyed[i] = lo_cell << 32 | i;
    }
  });
  const int cell_bits = bits_for(cells);
  radix_sort_by_key(sc.keyed, sc.keyed_tmp, cell_bits, pool_, sc.radix_offsets);

  sc.packed.resize(n);
  sc.entry_offset.resize(n + 1);
  run_each(pool_, box_chunks, [&](std::size_t c) {
    for (std::size_t k = n * c / box_chunks, e = n * (c + 1) / box_chunks; k < e; ++k) {
      const packed_box& p = sc.packed[k] = sc.unsorted[sc.keyed[k] & 0xffffffffu];
      double occupied = 1;
      for (int d = 0; d < 3; ++d) occupied *= static_cast<double>(p.hi_cell[d] - p.lo_cell[d] + 1);
      // Entries this box adds to the grid (0 for a large box, handled apart).
      sc.entry_offset[k + 1] = occupied > large_cells ? 0 : static_cast<std::uint64_t>(occupied);
    }
  });
  sc.large.clear();
  sc.entry_offset[0] = 0;
  for (std::size_t k = 0; k < n; ++k) {
    if (sc.entry_offset[k + 1] == 0) sc.large.push_back(static_cast<box_id>(k));
    sc.entry_offset[k + 1] += sc.entry_offset[k];
  }
  const std::uint64_t entry_count = sc.entry_offset[n];
  if (entry_count > std::numeric_limits<std::uint32_t>::max()) {
    throw std::length_error("grid_finder: more than 2^32 cell entries");
  }

  stats_.plan_ms = lap();

  // 4. Map: every grid box writes its (cell, position) entries at its own offset (no atomics),
  //    then a stable radix sort by cell gives each cell's boxes in spatial-order position, the
  //    same on every run. (PBIG's GPU count/scan/map with atomics costs a full memory latency
  //    per entry on a CPU; this sort streams instead.)
  auto for_each_cell_of = [&](const packed_box& p, auto&& fn) {
    for (std::int32_t z = p.lo_cell[2]; z <= p.hi_cell[2]; ++z) {
      for (std::int32_t y = p.lo_cell[1]; y <= p.hi_cell[1]; ++y) {
        const std::size_t row = (static_cast<std::size_t>(z) * dy + static_cast<std::size_t>(y)) * dx;
        for (std::int32_t x = p.lo_cell[0]; x <= p.hi_cell[0]; ++x) fn(row + static_cast<std::size_t>(x));
      }
    }
  };
  sc.keyed.resize(entry_count);
  run_each(pool_, box_chunks, [&](std::size_t c) {
    for (std::size_t k = n * c / box_chunks, e = n * (c + 1) / box_chunks; k < e; ++k) {
      std::uint64_t at = sc.entry_offset[k];
      if (sc.entry_offset[k + 1] == at) continue;  // large box
      for_each_cell_of(sc.packed[k], [&](std::size_t id) { sc.keyed[at++] = static_cast<std::uint64_t>(id) << 32 | k; });
    }
  });
  radix_sort_by_key(sc.keyed, sc.keyed_tmp, cell_bits, pool_, sc.radix_offsets);
  sc.entries.resize(entry_count);
  sc.cell_start.resize(cells + 1);
  {
    // Cell starts from the sorted keys: cells before an entry's cell start at that entry.
    std::size_t next_cell = 0;
    for (std::size_t e = 0; e < entry_count; ++e) {
      const std::size_t c = sc.keyed[e] >> 32;
      while (next_cell <= c) sc.cell_start[next_cell++] = static_cast<std::uint32_t>(e);
      sc.entries[e] = static_cast<box_id>(sc.keyed[e] & 0xffffffffu);
    }
    while (next_cell <= cells) sc.cell_start[next_cell++] = static_cast<std::uint32_t>(entry_count);
  }

  stats_.map_ms = lap();

  // 5. Check, in fixed chunks of cells.
  const std::size_t chunks = std::min(cells, check_chunk_limit);
  sc.chunk_pairs.resize(chunks);
  sc.chunk_checks.assign(chunks, 0);
  if (sc.columns.size() < chunks) sc.columns.resize(chunks);
  run_each(pool_, chunks, [&](std::size_t k) {
    const std::size_t cb = cells * k / chunks, ce = cells * (k + 1) / chunks;
    pair_list& found = sc.chunk_pairs[k];
    // Output with a cursor of our own: a block of up to 64 candidates is written unconditionally
    // and the cursor advances by each hit bit (no branch on the hit, which is unpredictable where
    // a third of the tests hit, as in a zone). `found` always has room for one more block.
    std::size_t found_n = 0;
    found.resize(std::max<std::size_t>(found.capacity(), 1024));  // all of it: no element is initialised
    std::uint64_t checks = 0;
    for (std::size_t c = cb; c < ce; ++c) {
      const std::uint32_t begin = sc.cell_start[c], end = sc.cell_start[c + 1];
      if (end - begin < 2) continue;
      const box_id* list = sc.entries.data() + begin;
      const auto cx = static_cast<std::int32_t>(c % dx);
      const auto cy = static_cast<std::int32_t>((c / dx) % dy);
      const auto cz = static_cast<std::int32_t>(c / (static_cast<std::size_t>(dx) * dy));
      const std::uint32_t len = end - begin;
      // Group the cell's boxes by their (category, mask) signature (up to max_groups distinct
      // ones; more fall back to one mixed group). Pairs of groups that can never qualify, such
      // as AOI-vs-AOI or presence-vs-presence in a zone, are then skipped without a test.
      cell_columns& col = sc.columns[k];
      col.resize(len);
      std::uint32_t groups = 0;
      std::uint32_t group_cat[max_groups], group_mask[max_groups], group_size[max_groups + 1];
      for (std::uint32_t i = 0; i < len && groups <= max_groups; ++i) {
        const packed_box& p = sc.packed[list[i]];
        std::uint32_t g = 0;
        while (g < groups && !(group_cat[g] == p.category && group_mask[g] == p.mask)) ++g;
        if (g == groups) {
          if (groups == max_groups) {
            groups = max_groups + 1;  // too many signatures: one mixed group
            break;
          }
          group_cat[g] = p.category;
          group_mask[g] = p.mask;
          group_size[g] = 0;
          ++groups;
        }
        ++group_size[g];
        col.group[i] = static_cast<std::uint8_t>(g);
      }
      const bool mixed = groups > max_groups;
      if (mixed) {
        groups = 1;
        group_size[0] = len;
      }
      // Lay the groups out in (mask, category) order: in a zone the presence groups (mask 0)
      // come first and the AOI groups after them, adjacent, so each presence box meets all the
      // AOI boxes it can qualify with in one contiguous range (see the loop at the end).
      std::uint32_t order[max_groups], position[max_groups];  // order[pos] = group
      for (std::uint32_t g = 0; g < groups; ++g) {
        std::uint32_t pos = g;
        for (; pos > 0; --pos) {
          const std::uint32_t h = order[pos - 1];
          if (group_mask[h] < group_mask[g] || (group_mask[h] == group_mask[g] && group_cat[h] < group_cat[g])) break;
          order[pos] = h;
        }
        order[pos] = g;
      }
      if (mixed) order[0] = 0;
      std::uint32_t group_start[max_groups + 1];  // by position
      group_start[0] = 0;
      for (std::uint32_t pos = 0; pos < groups; ++pos) {
        position[order[pos]] = pos;
        group_start[pos + 1] = group_start[pos] + group_size[order[pos]];
      }
      // Load the boxes into small columns in group order, with one 3-bit flag per box: bit d set
      // when the box's max corner lies in this cell's slab on axis d. Both boxes of a pair occupy
      // this cell, so min(hi-cell a, hi-cell b) == c on axis d iff either box has bit d: the
      // output-cell rule is (flag_a | flag_b) == 7, and every test below is branch-free.
      std::uint32_t cursor[max_groups];
      for (std::uint32_t g = 0; g < groups; ++g) cursor[g] = group_start[position[g]];
      for (std::uint32_t i = 0; i < len; ++i) {
        const packed_box& p = sc.packed[list[i]];
        const std::uint32_t at = cursor[mixed ? 0 : col.group[i]]++;
        col.lx[at] = p.lo[0];
        col.ly[at] = p.lo[1];
        col.lz[at] = p.lo[2];
        col.hx[at] = p.hi[0];
        col.hy[at] = p.hi[1];
        col.hz[at] = p.hi[2];
        col.cat[at] = p.category;
        col.msk[at] = p.mask;
        col.flag[at] = static_cast<std::uint32_t>(p.hi_cell[0] == cx) | static_cast<std::uint32_t>(p.hi_cell[1] == cy) << 1 |
                       static_cast<std::uint32_t>(p.hi_cell[2] == cz) << 2;
        col.id[at] = p.id;
      }
      const float *lx = col.lx.data(), *ly = col.ly.data(), *lz = col.lz.data();
      const float *hx = col.hx.data(), *hy = col.hy.data(), *hz = col.hz.data();
      const std::uint32_t *cat = col.cat.data(), *msk = col.msk.data(), *flag = col.flag.data();
      // Box i against boxes [first, last) of the columns.
      auto test_range = [&](std::uint32_t i, std::uint32_t first, std::uint32_t last) {
        const float ax0 = lx[i], ay0 = ly[i], az0 = lz[i], ax1 = hx[i], ay1 = hy[i], az1 = hz[i];
        const std::uint32_t ac = cat[i], am = msk[i], af = flag[i];
        checks += last - first;
        for (std::uint32_t block = first; block < last; block += 64) {
          const std::uint32_t blen = std::min<std::uint32_t>(last - block, 64);
          alignas(64) std::uint8_t hit[64];
          for (std::uint32_t t = 0; t < blen; ++t) {
            const std::uint32_t j = block + t;
            hit[t] = static_cast<std::uint8_t>((ax0 <= hx[j]) & (lx[j] <= ax1) & (ay0 <= hy[j]) & (ly[j] <= ay1) &
                                               (az0 <= hz[j]) & (lz[j] <= az1) &
                                               (((ac & msk[j]) | (cat[j] & am)) != 0) & ((af | flag[j]) == 7));
          }
          if (found.size() - found_n < 64) found.resize(2 * found.size());
          id_pair* out = found.data() + found_n;
          const box_id a = col.id[i];
          std::size_t hits = 0;
          for (std::uint32_t t = 0; t < blen; ++t) {
            const box_id b = col.id[block + t];
            out[hits] = id_pair{std::min(a, b), std::max(a, b)};
            hits += hit[t];
          }
          found_n += hits;
        }
      };
      // Every pair of groups (positions pa <= pb) whose signatures can qualify, once: per group
      // pa, the qualifying groups from pa on are merged into runs of adjacent positions, and each
      // box i of pa is tested against each run (from i + 1 where the run starts with pa itself).
      const auto pair_can_qualify = [&](std::uint32_t pa, std::uint32_t pb) {
        if (mixed) return true;
        const std::uint32_t ga = order[pa], gb = order[pb];
        return ((group_cat[ga] & group_mask[gb]) | (group_cat[gb] & group_mask[ga])) != 0;
      };
      for (std::uint32_t pa = 0; pa < groups; ++pa) {
        std::uint32_t run_first[max_groups], run_last[max_groups], runs = 0;  // positions [first, last]
        for (std::uint32_t pb = pa; pb < groups; ++pb) {
          if (!pair_can_qualify(pa, pb)) continue;
          if (runs > 0 && run_last[runs - 1] + 1 == pb) {
            run_last[runs - 1] = pb;
          } else {
            run_first[runs] = run_last[runs] = pb;
            ++runs;
          }
        }
        for (std::uint32_t i = group_start[pa]; i < group_start[pa + 1]; ++i) {
          for (std::uint32_t r = 0; r < runs; ++r) {
            test_range(i, run_first[r] == pa ? i + 1 : group_start[run_first[r]], group_start[run_last[r] + 1]);
          }
        }
      }
    }
    found.resize(found_n);
    sc.chunk_checks[k] = checks;
  });

  // 6. Large boxes: against the grid's boxes through the cells they cover, then among themselves.
  const std::size_t large_count = sc.large.size();
  const std::size_t large_chunks = std::min(large_count, large_chunk_limit);
  sc.large_pairs.resize(large_chunks);
  sc.large_checks.assign(large_chunks, 0);
  run_each(pool_, large_chunks, [&](std::size_t k) {
    const std::size_t lb = large_count * k / large_chunks, le = large_count * (k + 1) / large_chunks;
    pair_list& found = sc.large_pairs[k];
    found.clear();
    std::uint64_t checks = 0;
    for (std::size_t li = lb; li < le; ++li) {
      const packed_box& big = sc.packed[sc.large[li]];
      const box_id big_id = big.id;
      for_each_cell_of(big, [&](std::size_t c) {
        const std::uint32_t begin = sc.cell_start[c], end = sc.cell_start[c + 1];
        checks += end - begin;
        if (begin == end) return;
        const auto cx = static_cast<std::int32_t>(c % dx);
        const auto cy = static_cast<std::int32_t>((c / dx) % dy);
        const auto cz = static_cast<std::int32_t>(c / (static_cast<std::size_t>(dx) * dy));
        // Output cell: min(hi-cell) == c per axis; for an axis where the big box's max corner
        // is in this cell that holds for every box here, elsewhere the other box's must be.
        const bool big_x = big.hi_cell[0] == cx, big_y = big.hi_cell[1] == cy, big_z = big.hi_cell[2] == cz;
        for (std::uint32_t e = begin; e < end; ++e) {
          const packed_box& b = sc.packed[sc.entries[e]];
          const bool hit = (big.lo[0] <= b.hi[0]) & (b.lo[0] <= big.hi[0]) & (big.lo[1] <= b.hi[1]) &
                           (b.lo[1] <= big.hi[1]) & (big.lo[2] <= b.hi[2]) & (b.lo[2] <= big.hi[2]) &
                           (((big.category & b.mask) | (b.category & big.mask)) != 0) & (big_x | (b.hi_cell[0] == cx)) &
                           (big_y | (b.hi_cell[1] == cy)) & (big_z | (b.hi_cell[2] == cz));
          if (hit) found.push_back(big_id < b.id ? id_pair{big_id, b.id} : id_pair{b.id, big_id});
        }
      });
      for (std::size_t lj = li + 1; lj < large_count; ++lj) {
        const packed_box& b = sc.packed[sc.large[lj]];
        ++checks;
        if (boxes_qualify(big, b)) found.push_back(big_id < b.id ? id_pair{big_id, b.id} : id_pair{b.id, big_id});
      }
    }
    sc.large_checks[k] = checks;
  });

  stats_.check_ms = lap();

  // Gather the chunks' output in chunk order.
  std::size_t total = 0;
  for (const auto& f : sc.chunk_pairs) total += f.size();
  for (const auto& f : sc.large_pairs) total += f.size();
  out.resize(total);
  {
    auto& at = sc.gather_at;
    at.clear();
    std::size_t pos = 0;
    for (const auto& f : sc.chunk_pairs) at.push_back(std::exchange(pos, pos + f.size()));
    for (const auto& f : sc.large_pairs) at.push_back(std::exchange(pos, pos + f.size()));
    const std::size_t parts = at.size();
    run_each(pool_, parts, [&](std::size_t k) {
      const pair_list& f = k < sc.chunk_pairs.size() ? sc.chunk_pairs[k] : sc.large_pairs[k - sc.chunk_pairs.size()];
      std::copy(f.begin(), f.end(), out.begin() + static_cast<std::ptrdiff_t>(at[k]));
    });
  }

  stats_.output_ms = lap();
  stats_.cells = cells;
  stats_.cell_entries = sc.entries.size();
  stats_.cell_edge = plan_.cell_edge;
  stats_.large_boxes = large_count;
  for (const auto c : sc.chunk_checks) stats_.checks += c;
  for (const auto c : sc.large_checks) stats_.checks += c;
}

}  // namespace zone::interest
