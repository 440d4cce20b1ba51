// Kernels of the GPU PBIG finder: small and single-purpose, each starting with a bounds guard.
// Included only by pbig_kernels.cu, whose launchers (pbig_launch.h) pbig_dispatch.cpp and
// pbig_overlap.cpp call; the dispatch plans, sizes scratch memory and owns the streams.
#pragma once

#include <cub/block/block_reduce.cuh>
#include <cub/block/block_scan.cuh>
#include <cuda_runtime.h>

#include <cfloat>
#include <cstdint>
#include <type_traits>

#include "pbig_shared.h"
#include "pbig_tuning.h"

namespace zone::gpu::detail {


/// Order-preserving map between floats and signed ints (for atomicMin/atomicMax on floats).
__device__ __forceinline__ std::int32_t float_to_ordered(float f) {
  const std::int32_t i = __float_as_int(f);
  return i >= 0 ? i : i ^ 0x7FFFFFFF;
}
__host__ __device__ inline float ordered_to_float(std::int32_t i) {
  const std::int32_t b = i >= 0 ? i : i ^ 0x7FFFFFFF;
  float f;
  memcpy(&f, &b, sizeof f);
  return f;
}

/// The one cell mapping used by every kernel: monotone in x, so the output-cell rule holds.
/// Coordinates outside the plan's scene are clamped to its border cells (the overlapped upload
/// plans from its first chunk, and later chunks may stray out); a NaN (invalid input, whose call
/// is discarded) maps to cell 0, so no kernel indexes out of the grid.
__device__ __forceinline__ std::uint32_t cell_of(float x, int d, const grid_plan_dev& p) {
  const double c = floor((static_cast<double>(x) - p.origin[d]) * p.inv_edge);
  if (!(c > 0.0)) return 0;
  const double last = static_cast<double>(p.dims[d] - 1);
  if (c >= last) return p.dims[d] - 1;
  return static_cast<std::uint32_t>(c);
}

// ---- planning ---------------------------------------------------------------------------------

__global__ void init_bounds_kernel(bounds_dev* b) {
  if (threadIdx.x == 0) b->bad = 0xffffffffu;
  if (threadIdx.x >= 3) return;
  b->lo[threadIdx.x] = float_to_ordered(FLT_MAX);
  b->hi[threadIdx.x] = float_to_ordered(-FLT_MAX);
}

/// Scene bounds: min of lo and max of hi per axis (block reduction, then one atomic per block).
/// With `validate`, also interest::validate's rule per box (lo <= hi, both finite, every axis):
/// the lowest invalid index goes to out->bad.
__global__ void bounds_kernel(box_arrays boxes, std::uint32_t n, bounds_dev* out, bool validate) {
  using reduce = cub::BlockReduce<float, tuning::block>;
  __shared__ typename reduce::TempStorage temp;
  float lo[3] = {FLT_MAX, FLT_MAX, FLT_MAX}, hi[3] = {-FLT_MAX, -FLT_MAX, -FLT_MAX};
  for (std::uint32_t i = blockIdx.x * blockDim.x + threadIdx.x; i < n; i += gridDim.x * blockDim.x) {
    bool ok = true;
    for (int d = 0; d < 3; ++d) {
      const float l = boxes.lo[d][i], h = boxes.hi[d][i];
      lo[d] = fminf(lo[d], l);
      hi[d] = fmaxf(hi[d], h);
      ok = ok && l <= h && isfinite(l) && isfinite(h);
    }
    if (validate && !ok) atomicMin(&out->bad, i);
  }
  for (int d = 0; d < 3; ++d) {
    const float mn = reduce(temp).Reduce(lo[d], [](float a, float b) { return fminf(a, b); });
    __syncthreads();
    const float mx = reduce(temp).Reduce(hi[d], [](float a, float b) { return fmaxf(a, b); });
    __syncthreads();
    if (threadIdx.x == 0) {
      atomicMin(&out->lo[d], float_to_ordered(mn));
      atomicMax(&out->hi[d], float_to_ordered(mx));
    }
  }
}


__device__ __forceinline__ std::uint64_t splitmix64(std::uint64_t x) {
  x += 0x9e3779b97f4a7c15ull;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ull;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebull;
  return x ^ (x >> 31);
}

/// Scene origin and extent per axis from the bounds kernel's result.
__device__ __forceinline__ void scene_of(const bounds_dev* bounds, double origin[3], double extent[3]) {
  for (int d = 0; d < 3; ++d) {
    const float lo = ordered_to_float(bounds->lo[d]);
    const float hi = ordered_to_float(bounds->hi[d]);
    origin[d] = lo;
    extent[d] = fmax(0.0, static_cast<double>(hi) - static_cast<double>(lo));
  }
}

/// Index of sample box t of k among the first prm.sample_n boxes (all of them when k == sample_n):
/// a fixed-seed hash, with replacement.
__device__ __forceinline__ std::uint32_t sample_index(const plan_params& prm, std::uint32_t k, std::uint32_t t) {
  return (k == prm.sample_n) ? t : static_cast<std::uint32_t>(splitmix64(prm.seed + t) % prm.sample_n);
}

/// Planning (Eq. 6) in one block: each thread holds one box of a simple random sample; alpha(l)
/// is a block sum; a binary search on the cubic edge l finds the smallest l with f(l) >= W,
/// then, where f is flat (boxes covering each other), the largest edge whose f stays within 5%
/// of that minimum (the CPU planner's tie rule). Reuses the previous edge when the statistics
/// (N, scene extent, mean sampled box size) moved less than the tolerances.
__global__ void __launch_bounds__(tuning::plan_threads) plan_kernel(box_arrays boxes, const bounds_dev* bounds,
                                                                  plan_params prm, plan_state* state,
                                                                  grid_plan_dev* plan_out) {
  using reduce = cub::BlockReduce<double, tuning::plan_threads>;
  __shared__ typename reduce::TempStorage temp;
  __shared__ double bcast;
  if (blockDim.x != tuning::plan_threads) return;  // guard: launched with exactly one full block
  if (bounds->bad != 0xffffffffu) {
    // Invalid input (pinned path): no plan, and the reuse statistics stay as they were.
    if (threadIdx.x == 0) {
      plan_out->cells = 0;
      state->cost_pending = 0;
    }
    return;
  }
  const std::uint32_t t = threadIdx.x;
  const std::uint32_t n = prm.n;

  double origin[3], extent[3];
  scene_of(bounds, origin, extent);
  const double max_extent = fmax(extent[0], fmax(extent[1], extent[2]));
  const double max_cells = fmin(2.0 * n + 64.0, 2147483647.0);

  const std::uint32_t k = min(prm.sample_n, min(prm.samples, tuning::plan_threads));
  double blo[3] = {0, 0, 0}, bhi[3] = {0, 0, 0};
  const bool has = t < k;
  if (has) {
    const std::uint32_t idx = sample_index(prm, k, t);
    for (int d = 0; d < 3; ++d) {
      blo[d] = boxes.lo[d][idx];
      bhi[d] = boxes.hi[d][idx];
    }
  }
  auto block_sum = [&](double v) {
    const double s = reduce(temp).Sum(v);
    if (t == 0) bcast = s;
    __syncthreads();
    const double r = bcast;
    __syncthreads();
    return r;
  };
  auto dims_for = [&](double l, double dims[3]) {
    for (int d = 0; d < 3; ++d) dims[d] = floor(extent[d] / l) + 1.0;
  };
  auto alpha_for = [&](double l, const double dims[3]) {
    double cells = 0;
    if (has) {
      cells = 1;
      for (int d = 0; d < 3; ++d) {
        const double last = dims[d] - 1;
        const double a = fmin(fmax(floor((blo[d] - origin[d]) / l), 0.0), last);
        const double z = fmin(fmax(floor((bhi[d] - origin[d]) / l), 0.0), last);
        cells *= z - a + 1;
      }
    }
    return k == 0 ? 1.0 : block_sum(cells) / k;
  };
  auto f_of = [&](double l) {
    double dims[3];
    dims_for(l, dims);
    const double m = dims[0] * dims[1] * dims[2];
    const double alpha = alpha_for(l, dims);  // every thread takes part in the block sum
    if (m > max_cells) return static_cast<double>(INFINITY);
    return static_cast<double>(n) * alpha / m;
  };
  auto bisect = [](double lo_l, double hi_l, auto&& pred) {
    for (int it = 0; it < 48 && hi_l - lo_l > hi_l * 1e-4; ++it) {
      const double mid = 0.5 * (lo_l + hi_l);
      (pred(mid) ? hi_l : lo_l) = mid;
    }
    return hi_l;
  };
  double mean_size[3];
  for (int d = 0; d < 3; ++d) mean_size[d] = k == 0 ? 0.0 : block_sum(has ? bhi[d] - blo[d] : 0.0) / k;

  std::uint32_t reused = 0;
  bool searched = false;  // Eq. 6's search ran (no reuse, no fixed edge, a real scene)
  double edge;
  auto close = [](double a, double b, double tol) { return fabs(a - b) <= tol * fabs(b) + 1e-9; };
  if (max_extent <= 0.0 || n < 2) {
    edge = fmax(1.0, max_extent);
  } else if (prm.fixed_edge > 0) {
    edge = prm.fixed_edge;
    for (;;) {
      double dims[3];
      dims_for(edge, dims);
      if (dims[0] * dims[1] * dims[2] <= max_cells) break;
      edge *= 1.25;
    }
  } else {
    bool reuse = prm.allow_reuse && state->valid && close(n, state->count, tuning::reuse_count_tolerance);
    for (int d = 0; d < 3; ++d) {
      reuse = reuse && close(extent[d], state->extent[d], tuning::reuse_size_tolerance) &&
              close(mean_size[d], state->mean_size[d], tuning::reuse_size_tolerance);
    }
    if (reuse) {
      double dims[3];
      dims_for(state->edge, dims);
      reuse = dims[0] * dims[1] * dims[2] <= max_cells;
    }
    if (reuse) {
      edge = state->edge;
      reused = 1;
    } else {
      searched = true;
      const double w = fmax(1.0, prm.min_boxes_per_cell);
      const double one_cell = max_extent * (1.0 + 1e-6) + 1e-6;
      auto feasible = [&](double l) {
        const double f = f_of(l);
        return isfinite(f) && f >= w;
      };
      if (!feasible(one_cell)) {
        edge = one_cell;  // N < W: one cell is the best we can do
      } else {
        double lo_l = one_cell;
        for (int it = 0; it < 200 && feasible(lo_l); ++it) lo_l /= 2;
        const double best = bisect(lo_l, one_cell, feasible);
        const double f_best = f_of(best);
        if (f_of(one_cell) <= f_best * 1.05) {
          edge = one_cell;
        } else {
          const double tie = bisect(best, one_cell, [&](double l) { return f_of(l) > f_best * 1.05; });
          edge = tie * (1.0 - 1e-4) > best ? tie * (1.0 - 1e-4) : best;
        }
      }
    }
  }
  double dims[3];
  dims_for(edge, dims);
  const double alpha = alpha_for(edge, dims);
  if (t == 0) {
    grid_plan_dev p{};
    for (int d = 0; d < 3; ++d) {
      p.origin[d] = origin[d];
      p.dims[d] = static_cast<std::uint32_t>(dims[d]);
    }
    p.edge = edge;
    p.inv_edge = 1.0 / edge;
    p.alpha = alpha;
    p.large_cells = fmax(tuning::large_box_min_cells, tuning::large_box_alpha_factor * alpha);
    p.reused = reused;
    p.cells = static_cast<std::uint64_t>(p.dims[0]) * p.dims[1] * p.dims[2];
    *plan_out = p;
    if (!reused && prm.fixed_edge <= 0 && n >= 2 && max_extent > 0.0) {
      state->edge = edge;
      state->count = n;
      for (int d = 0; d < 3; ++d) {
        state->extent[d] = extent[d];
        state->mean_size[d] = mean_size[d];
      }
      state->valid = 1;
    }
    // Cost-aware choice (plan_cost_kernel, next in the stream): Eq. 6's edge and larger ones.
    const bool score = searched && prm.cost_aware != 0 && k >= 2 && edge <= max_extent;
    state->cost_pending = score ? 1u : 0u;
    state->cost_blocks_done = 0;
    for (int j = 0; j < max_plan_candidates; ++j) {
      const double l = edge * exp2(j / 3.0);
      const double prev = edge * exp2((j - 1) / 3.0);
      // A candidate past the one-cell edge only when the previous one still has several cells.
      state->cand_edge[j] = (score && j < static_cast<int>(tuning::plan_candidates) && (j == 0 || prev <= max_extent)) ? l : 0.0;
      state->cand_cells[j] = 0;
      state->cand_shared[j] = 0;
    }
  }
}

/// Cost-aware edge choice (beyond the paper; tuning::plan_cost_* says what is scored and where the
/// constants come from). Block b scores candidate b / plan_cost_chunks: every block maps the
/// plan's sample into the candidate's grid (cell ranges in shared memory) and sums, over its slice
/// of the sample's pairs, the cells both boxes occupy (sum over cells of m_c(m_c-1)/2 for the
/// sample; scaled by N^2/(k(k-1)) it estimates the pair checks sum n_c(n_c-1)/2); slice 0 also sums
/// the cells each sample box occupies (alpha). The last block to finish computes each candidate's
/// cost and, where one is cheaper than Eq. 6's edge by at least plan_min_saving_ns, rewrites the
/// plan (edge, dims, alpha, large-box threshold) and the edge kept for reuse. Does nothing unless
/// the planning kernel ran Eq. 6's search in this call (state->cost_pending).
__global__ void __launch_bounds__(tuning::plan_cost_threads) plan_cost_kernel(box_arrays boxes, const bounds_dev* bounds,
                                                                            plan_params prm, plan_state* state,
                                                                            grid_plan_dev* plan_out) {
  using reduce = cub::BlockReduce<unsigned long long, tuning::plan_cost_threads>;
  __shared__ typename reduce::TempStorage temp;
  __shared__ std::int32_t lo_s[3][tuning::plan_threads];
  __shared__ std::int32_t hi_s[3][tuning::plan_threads];
  __shared__ std::uint32_t idx_s[tuning::plan_threads];
  if (state->cost_pending == 0) return;  // the same for every block: all return
  const std::uint32_t tid = threadIdx.x;
  const std::uint32_t chunks = tuning::plan_cost_chunks;
  const std::uint32_t cand = blockIdx.x / chunks, chunk = blockIdx.x % chunks;
  const std::uint32_t n = prm.n;
  const std::uint32_t k = min(prm.sample_n, min(prm.samples, tuning::plan_threads));
  double origin[3], extent[3];
  scene_of(bounds, origin, extent);
  auto dims_for = [&](double l, double dims[3]) {
    for (int d = 0; d < 3; ++d) dims[d] = floor(extent[d] / l) + 1.0;
  };
  const double l = state->cand_edge[cand];
  const bool active = l > 0.0;
  unsigned long long my_cells = 0, my_shared = 0;
  if (active) {
    double dims[3];
    dims_for(l, dims);
    for (std::uint32_t i = tid; i < k; i += blockDim.x) {
      const std::uint32_t idx = sample_index(prm, k, i);
      unsigned long long cells = 1;
      for (int d = 0; d < 3; ++d) {
        const double last = dims[d] - 1;
        const double a = fmin(fmax(floor((static_cast<double>(boxes.lo[d][idx]) - origin[d]) / l), 0.0), last);
        const double z = fmin(fmax(floor((static_cast<double>(boxes.hi[d][idx]) - origin[d]) / l), 0.0), last);
        lo_s[d][i] = static_cast<std::int32_t>(a);
        hi_s[d][i] = static_cast<std::int32_t>(z);
        cells *= static_cast<unsigned long long>(z - a + 1);
      }
      idx_s[i] = idx;
      if (chunk == 0) my_cells += cells;
    }
  }
  __syncthreads();
  if (active) {
    // Unordered pairs (i, i+s mod k), s = 1..k/2: each pair once (for even k, s = k/2 from i < k/2).
    const std::uint32_t half = k / 2;
    const std::uint32_t r0 = static_cast<std::uint32_t>(static_cast<std::uint64_t>(k) * chunk / chunks);
    const std::uint32_t r1 = static_cast<std::uint32_t>(static_cast<std::uint64_t>(k) * (chunk + 1) / chunks);
    const std::uint32_t total = (r1 - r0) * half;
    for (std::uint32_t p = tid; p < total; p += blockDim.x) {
      const std::uint32_t i = r0 + p / half;
      const std::uint32_t s = 1 + p % half;
      if (2 * s == k && i >= half) continue;
      std::uint32_t j = i + s;
      if (j >= k) j -= k;
      if (idx_s[i] == idx_s[j]) continue;  // the same box drawn twice
      const std::int32_t ox = min(hi_s[0][i], hi_s[0][j]) - max(lo_s[0][i], lo_s[0][j]) + 1;
      if (ox <= 0) continue;
      const std::int32_t oy = min(hi_s[1][i], hi_s[1][j]) - max(lo_s[1][i], lo_s[1][j]) + 1;
      if (oy <= 0) continue;
      const std::int32_t oz = min(hi_s[2][i], hi_s[2][j]) - max(lo_s[2][i], lo_s[2][j]) + 1;
      if (oz <= 0) continue;
      my_shared += static_cast<unsigned long long>(ox) * static_cast<unsigned long long>(oy) * static_cast<unsigned long long>(oz);
    }
  }
  const unsigned long long block_shared = reduce(temp).Sum(my_shared);
  __syncthreads();
  const unsigned long long block_cells = reduce(temp).Sum(my_cells);
  if (tid != 0) return;
  if (active) {
    atomicAdd(&state->cand_shared[cand], block_shared);
    if (chunk == 0) atomicAdd(&state->cand_cells[cand], block_cells);
  }
  __threadfence();
  if (atomicAdd(&state->cost_blocks_done, 1u) + 1 != gridDim.x) return;
  __threadfence();
  // The last block: score the candidates and keep the cheapest.
  const double nd = static_cast<double>(n);
  const double max_cells = fmin(2.0 * n + 64.0, 2147483647.0);
  const double scale = (k == n) ? 1.0 : nd * nd / (static_cast<double>(k) * (k - 1));
  int best = 0;
  double best_cost = INFINITY, cost0 = INFINITY, best_alpha = 0;
  for (int j = 0; j < static_cast<int>(tuning::plan_candidates); ++j) {
    const double lj = state->cand_edge[j];
    if (!(lj > 0.0)) continue;
    double dims[3];
    dims_for(lj, dims);
    const double m = dims[0] * dims[1] * dims[2];
    if (m > max_cells) continue;
    const double alpha = static_cast<double>(atomicAdd(&state->cand_cells[j], 0ull)) / k;
    const double entries = nd * alpha;
    if (j > 0 && entries > tuning::plan_max_fill * m) continue;  // the fullest cell would pass small_cell_sort
    const double sampled = static_cast<double>(atomicAdd(&state->cand_shared[j], 0ull)) * scale;
    const double bound = 0.5 * (entries * entries / m - entries);  // Cauchy-Schwarz: sum n_c^2 >= (sum n_c)^2 / M
    const double checks = fmax(sampled, bound);
    const double cost = tuning::plan_cost_entry_ns * entries + tuning::plan_cost_cell_ns * m +
                        tuning::plan_cost_check_ns * checks;
    if (j == 0) cost0 = cost;
    if (cost < best_cost) {
      best_cost = cost;
      best = j;
      best_alpha = alpha;
    }
  }
  if (best == 0 || !(cost0 - best_cost >= tuning::plan_min_saving_ns)) return;  // Eq. 6's edge stays
  const double edge = state->cand_edge[best];
  double dims[3];
  dims_for(edge, dims);
  grid_plan_dev p = *plan_out;
  for (int d = 0; d < 3; ++d) p.dims[d] = static_cast<std::uint32_t>(dims[d]);
  p.edge = edge;
  p.inv_edge = 1.0 / edge;
  p.alpha = best_alpha;
  p.large_cells = fmax(tuning::large_box_min_cells, tuning::large_box_alpha_factor * best_alpha);
  p.cells = static_cast<std::uint64_t>(p.dims[0]) * p.dims[1] * p.dims[2];
  *plan_out = p;
  state->edge = edge;
}

// ---- mapping ----------------------------------------------------------------------------------

struct cell_range {
  std::uint32_t lo[3];
  std::uint32_t hi[3];
};

__device__ __forceinline__ cell_range cells_of(const box_arrays& b, std::uint32_t i, const grid_plan_dev& p) {
  cell_range r;
  for (int d = 0; d < 3; ++d) {
    r.lo[d] = cell_of(b.lo[d][i], d, p);
    r.hi[d] = cell_of(b.hi[d][i], d, p);
  }
  return r;
}

/// Box counting kernel: one thread per box; +1 (atomic) on every cell the box occupies. A box
/// that would occupy more than plan.large_cells cells is flagged large, counted in *large_count
/// and kept out of the grid. Reads the plan from device memory; a plan of more cells than the
/// counters were queued for (`cell_capacity`), or none (invalid input), counts nothing.
__global__ void count_kernel(box_arrays boxes, std::uint32_t n, const grid_plan_dev* plan, std::uint64_t cell_capacity,
                             std::uint32_t* counts, std::uint8_t* is_large, std::uint32_t* large_count) {
  const std::uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const grid_plan_dev p = *plan;
  if (p.cells == 0 || p.cells > cell_capacity) return;
  const cell_range r = cells_of(boxes, i, p);
  const double occupied = static_cast<double>(r.hi[0] - r.lo[0] + 1) * (r.hi[1] - r.lo[1] + 1) * (r.hi[2] - r.lo[2] + 1);
  const bool large = occupied > p.large_cells;
  is_large[i] = large ? 1 : 0;
  if (large) {
    atomicAdd(large_count, 1u);
    return;
  }
  for (std::uint32_t z = r.lo[2]; z <= r.hi[2]; ++z) {
    for (std::uint32_t y = r.lo[1]; y <= r.hi[1]; ++y) {
      const std::uint64_t row = (static_cast<std::uint64_t>(z) * p.dims[1] + y) * p.dims[0];
      for (std::uint32_t x = r.lo[0]; x <= r.hi[0]; ++x) atomicAdd(&counts[row + x], 1u);
    }
  }
}

/// Box mapping kernel: one thread per box; its slot in each cell's list is the cell's offset
/// plus an atomic ticket. (The lists are sorted by id afterwards, for a deterministic order.)
/// Box i of `boxes` has the id first_id + i (a chunk of the overlapped upload; else 0).
/// Nothing when the grid did not fit the call's capacity (grid->fits == 0).
__global__ void map_kernel(box_arrays boxes, std::uint32_t n, std::uint32_t first_id, const grid_plan_dev* plan,
                           const map_readback* grid, const std::uint8_t* is_large, const cell_prefix* prefix,
                           std::uint32_t* cursor, std::uint32_t* entries) {
  const std::uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= n || grid->fits == 0) return;
  if (is_large[i]) return;
  const grid_plan_dev p = *plan;
  const cell_range r = cells_of(boxes, i, p);
  for (std::uint32_t z = r.lo[2]; z <= r.hi[2]; ++z) {
    for (std::uint32_t y = r.lo[1]; y <= r.hi[1]; ++y) {
      const std::uint64_t row = (static_cast<std::uint64_t>(z) * p.dims[1] + y) * p.dims[0];
      for (std::uint32_t x = r.lo[0]; x <= r.hi[0]; ++x) {
        const std::uint64_t c = row + x;
        entries[prefix[c].entry + atomicAdd(&cursor[c], 1u)] = first_id + i;
      }
    }
  }
}

/// Boxes in id order as two 16-byte records (lo.xyz + category bits, hi.xyz + mask bits), so that
/// the gather below reads 2 sectors per entry instead of 8 scattered 4-byte values.
__global__ void pack_boxes_kernel(box_arrays boxes, std::uint32_t n, float4* box_lo, float4* box_hi) {
  const std::uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= n) return;
  box_lo[i] = make_float4(boxes.lo[0][i], boxes.lo[1][i], boxes.lo[2][i], __uint_as_float(boxes.category[i]));
  box_hi[i] = make_float4(boxes.hi[0][i], boxes.hi[1][i], boxes.hi[2][i], __uint_as_float(boxes.mask[i]));
}

/// Sorts each cell's list by box id (the mapping's atomics give a timing-dependent order), for
/// grids whose fullest cell holds at most tuning::small_cell_sort entries: one warp per cell, each
/// id's slot is its rank (ids in a cell are distinct). Fuller grids use CUB's segmented sort.
__global__ void sort_small_cells_kernel(const std::uint32_t* in, std::uint32_t* out, const cell_prefix* prefix,
                                        std::uint32_t cells, const map_readback* grid) {
  const std::uint64_t cell = (static_cast<std::uint64_t>(blockIdx.x) * blockDim.x + threadIdx.x) / 32;
  const std::uint32_t lane = threadIdx.x % 32;
  if (cell >= cells || cell >= grid->cells) return;
  const std::uint32_t b = prefix[cell].entry, e = prefix[cell + 1].entry;
  for (std::uint32_t i = b + lane; i < e; i += 32) {
    const std::uint32_t id = in[i];
    std::uint32_t rank = 0;
    for (std::uint32_t j = b; j < e; ++j) rank += in[j] < id ? 1u : 0u;
    out[b + rank] = id;
  }
}

/// The box array of the paper: each entry's box, packed for the checking kernel, in cell order.
__global__ void gather_kernel(const float4* box_lo, const float4* box_hi, const std::uint32_t* entries,
                              std::uint32_t count, const map_readback* grid, float4* packed_lo, float4* packed_hi) {
  const std::uint32_t e = blockIdx.x * blockDim.x + threadIdx.x;
  if (e >= count || e >= grid->total.entry) return;
  const std::uint32_t i = entries[e];
  packed_lo[e] = box_lo[i];
  packed_hi[e] = box_hi[i];
}

// ---- scheduling -------------------------------------------------------------------------------

/// Thread-block scheduling: one work item per (cell, row segment); items[k] = its cell.
__global__ void expand_items_kernel(const cell_prefix* prefix, std::uint32_t cells, const map_readback* grid,
                                    std::uint32_t* items) {
  const std::uint32_t c = blockIdx.x * blockDim.x + threadIdx.x;
  if (c >= cells || c >= grid->cells) return;
  for (std::uint32_t k = prefix[c].item; k < prefix[c + 1].item; ++k) items[k] = c;
}

/// Fills the read-back block (rb->totals is the reduce's): the plan, whether the grid fits the
/// capacity the call was queued with (`cap`; else cells and totals 0, so the later kernels of
/// the call do nothing), the totals at cell M and the batch boundaries (cells cut so that each
/// batch holds about the same number of tiles).
__global__ void batch_plan_kernel(const grid_plan_dev* plan, const cell_prefix* prefix, const std::uint32_t* large_count,
                                  map_readback* rb, grid_capacity cap, std::uint32_t min_tiles,
                                  std::uint32_t max_batches) {
  if (threadIdx.x >= 32) return;
  const grid_plan_dev p = *plan;
  const cell_totals t = rb->totals;
  const std::uint32_t large = *large_count;
  // Counted at all (the count kernel skips a plan past the capacity), then within every size.
  const bool counted = p.cells > 0 && p.cells <= cap.cells;
  const cell_prefix at_end = prefix[counted ? p.cells : 0];
  const bool fits = counted && t.entries == at_end.entry && t.tiles == at_end.tile && t.entries <= cap.entries &&
                    at_end.item <= cap.items && t.tiles <= cap.tiles && t.max_count <= cap.max_count &&
                    (cap.large != 0 || large == 0);
  const std::uint32_t cells = fits ? static_cast<std::uint32_t>(p.cells) : 0;
  const std::uint32_t tiles = fits ? at_end.tile : 0;
  std::uint32_t count = tiles == 0 ? 0 : (tiles + min_tiles - 1) / min_tiles;
  count = min(count, max_batches);
  __syncwarp();  // every lane has read rb->totals before lane 0 writes the block
  if (threadIdx.x == 0) {
    rb->plan = p;
    rb->fits = fits ? 1u : 0u;
    rb->cells = cells;
    rb->total = fits ? at_end : cell_prefix{0, 0, 0};
    rb->large_count = large;
    rb->batches.count = count;
  }
  for (std::uint32_t b = threadIdx.x; b <= count && b < static_cast<std::uint32_t>(max_batch_slots); b += 32) {
    const std::uint64_t target = count == 0 ? 0 : static_cast<std::uint64_t>(tiles) * b / count;
    std::uint32_t lo = 0, hi = cells;  // first c in [0, cells] with prefix[c].tile >= target
    while (lo < hi) {
      const std::uint32_t mid = lo + (hi - lo) / 2;
      if (prefix[mid].tile >= target) hi = mid; else lo = mid + 1;
    }
    if (b == count) lo = cells;
    rb->batches.cell[b] = lo;
    rb->batches.item[b] = prefix[lo].item;
    rb->batches.tile[b] = prefix[lo].tile;
  }
}

// ---- checking ---------------------------------------------------------------------------------


/// Flags of a box in cell (cx, cy, cz): bit d set when the box's hi corner lies in the cell's slab
/// on axis d. Both boxes of a pair occupy the cell, so min(hi-cell a, hi-cell b) == cell on axis d
/// iff either has bit d: the pair's output cell is this cell iff (flags_a | flags_b) == 7.
__device__ __forceinline__ std::uint32_t hi_flags(const float4& hi, const grid_plan_dev& p, const std::uint32_t c[3]) {
  return (cell_of(hi.x, 0, p) == c[0] ? 1u : 0u) | (cell_of(hi.y, 1, p) == c[1] ? 2u : 0u) |
         (cell_of(hi.z, 2, p) == c[2] ? 4u : 0u);
}

/// One tile's output chunk, for both checking kernels: called by the one thread that speaks for
/// the tile (of its block or warp) once the tile's scan gave its `pairs` (> 0) and `bytes` (the
/// chunk with its 12-byte header). Claims the chunk's place in the batch's buffer (one atomic on
/// the cursor), records the tile's offset and pair count, and writes the header when the chunk
/// fits (a chunk past the capacity is only counted: the host sees cursor > capacity and re-runs
/// the batch with room). Returns the chunk's first byte.
__device__ __forceinline__ std::uint64_t reserve_chunk(const check_args& a, std::uint32_t tile, std::uint32_t cell_begin,
                                                       std::uint32_t seg_v, std::uint32_t seg_h, std::uint32_t pairs,
                                                       std::uint32_t body, std::uint64_t bytes) {
  const std::uint64_t base = atomicAdd(a.cursor, static_cast<unsigned long long>(bytes));
  a.tile_off[tile] = base;
  a.tile_pairs[tile] = pairs;
  if (base + bytes <= a.capacity) {
    auto* w = reinterpret_cast<std::uint32_t*>(a.out + base);
    w[0] = cell_begin;
    w[1] = seg_v | (seg_h << 16);
    w[2] = body | (pairs << 16);
  }
  return base;
}

/// The pair rule of the stage kernel (check_kernel writes the same rule out inline; see there),
/// for box a (a row) and box b (a column), each as its
/// two 16-byte records (lo.xyz + category bits, hi.xyz + mask bits) and its hi_flags in the cell:
/// the boxes intersect (closed intervals), a's category meets b's mask or b's category meets a's
/// mask, and this cell is the pair's output cell ((flags_a | flags_b) == 7).
__device__ __forceinline__ bool box_pair_hit(const float4& a_lo, const float4& a_hi, std::uint32_t a_flags,
                                             const float4& b_lo, const float4& b_hi, std::uint32_t b_flags) {
  const std::uint32_t classes =
      (__float_as_uint(a_lo.w) & __float_as_uint(b_hi.w)) | (__float_as_uint(b_lo.w) & __float_as_uint(a_hi.w));
  return a_lo.x <= b_hi.x && b_lo.x <= a_hi.x && a_lo.y <= b_hi.y && b_lo.y <= a_hi.y && a_lo.z <= b_hi.z &&
         b_lo.z <= a_hi.z && classes != 0 && (a_flags | b_flags) == 7u;
}

/// The stage kernel's diagonal tile (check_kernel's, written out inline; see there), a segment
/// of m boxes against itself: calls
/// test(j) for the columns j that row r < m checks, so that every pair of the m boxes is tested
/// once over the rows. Balanced: Eq. 7 with n = m, row r checks the x(r) - 1 elements after the
/// diagonal, wrapping (x = ceil((m+1)/2) for the first ceil(m/2) rows, else floor((m+1)/2); the
/// first of the x elements is the diagonal, a box with itself, skipped); else the plain triangle,
/// row r checks columns r+1..m-1.
template <bool Balanced, class Test>
__device__ __forceinline__ void triangle_walk(std::uint32_t r, std::uint32_t m, Test&& test) {
  if constexpr (Balanced) {
    const std::uint32_t x = r < (m + 1) / 2 ? (m + 2) / 2 : (m + 1) / 2;
    std::uint32_t j = r;
    for (std::uint32_t k = 1; k < x; ++k) {
      if (++j == m) j = 0;
      test(j);
    }
  } else {
    for (std::uint32_t j = r + 1; j < m; ++j) test(j);
  }
}

/// Algorithm 2: one block of T threads per work item (cell c, row segment v). Thread i holds box
/// i of segment v and compares it with each column segment h >= v loaded into shared memory:
/// for h == v the triangle, with Eq. 7's balanced circular assignment when Balanced (thread i
/// checks the x(i) elements from the diagonal on, wrapping), else row i checks columns i+1..m-1;
/// for h > v the whole rectangle. A pair is kept when the boxes intersect, the category/mask rule
/// holds, and this cell holds the max corner of their intersection. Each tile's pairs become one
/// chunk: a 12-byte header then the 3-level encoded rows (Compressed) or plain id pairs, placed
/// by a block prefix sum plus one atomic per chunk. Chunks past the capacity are counted, not
/// written: the host sees cursor > capacity and re-runs the batch with room.
template <bool Balanced, bool Compressed>
__global__ void __launch_bounds__(tuning::segment) check_kernel(check_args a) {
  constexpr std::uint32_t T = tuning::segment;
  using scan = cub::BlockScan<std::uint32_t, T>;
  __shared__ typename scan::TempStorage scan_temp;
  __shared__ float4 col_lo[T];
  __shared__ float4 col_hi[T];
  __shared__ std::uint32_t col_id[T];
  __shared__ std::uint8_t col_flags[T];
  __shared__ std::uint64_t chunk_base;
  __shared__ grid_plan_dev plan;  // in shared memory, not registers: a register copy cost occupancy

  const std::uint32_t item = a.item_first + blockIdx.x;
  // guard (uniform over the block); a batch queued with a capacity has blocks past the grid's items
  if (item >= a.item_last || item >= a.grid->total.item || blockDim.x != T) return;
  const std::uint32_t tid = threadIdx.x;
  if (tid == 0) plan = *a.plan;
  __syncthreads();
  const std::uint32_t cell = a.items[item];
  const cell_prefix p0 = a.prefix[cell], p1 = a.prefix[cell + 1];
  const std::uint32_t segs = p1.item - p0.item;
  const std::uint32_t v = item - p0.item;
  const std::uint32_t count = p1.entry - p0.entry;
  const std::uint32_t tile0 = p0.tile + v * segs - v * (v - 1) / 2 - a.tile_first;
  const std::uint32_t cc[3] = {cell % plan.dims[0], (cell / plan.dims[0]) % plan.dims[1],
                               cell / (plan.dims[0] * plan.dims[1])};

  const std::uint32_t m = min(T, count - v * T);
  float4 row_lo = make_float4(0, 0, 0, 0), row_hi = make_float4(0, 0, 0, 0);
  std::uint32_t row_flags = 0, row_id = 0;
  if (tid < m) {
    const std::uint32_t e = p0.entry + v * T + tid;
    std::uint32_t at = e;
    if (a.indirect != 0 || !Compressed) {
      const std::uint32_t id = a.entries[e];
      if (!Compressed) row_id = id;
      if (a.indirect != 0) at = id;
    }
    row_lo = a.packed_lo[at];
    row_hi = a.packed_hi[at];
    row_flags = hi_flags(row_hi, plan, cc);
  }
  const std::uint32_t row_cat = __float_as_uint(row_lo.w), row_mask = __float_as_uint(row_hi.w);

  for (std::uint32_t h = v; h < segs; ++h) {
    const std::uint32_t n = min(T, count - h * T);
    __syncthreads();  // the previous tile's readers are done with shared memory
    if (tid < n) {
      const std::uint32_t e = p0.entry + h * T + tid;
      std::uint32_t at = e;
      if (a.indirect != 0 || !Compressed) {
        const std::uint32_t id = a.entries[e];
        if (!Compressed) col_id[tid] = id;
        if (a.indirect != 0) at = id;
      }
      col_lo[tid] = a.packed_lo[at];
      col_hi[tid] = a.packed_hi[at];
      col_flags[tid] = static_cast<std::uint8_t>(hi_flags(col_hi[tid], plan, cc));
    }
    __syncthreads();

    std::uint64_t hits = 0;
    // The pair rule and the diagonal walk written out here rather than through box_pair_hit and
    // triangle_walk (which the stage kernel uses): the shared forms made this kernel's check
    // slower on the H200 (docs/gpu-benchmarks.md, "Overlapped upload").
    auto test = [&](std::uint32_t j) {
      const float4 lo = col_lo[j], hi = col_hi[j];
      const bool hit = row_lo.x <= hi.x && lo.x <= row_hi.x && row_lo.y <= hi.y && lo.y <= row_hi.y &&
                       row_lo.z <= hi.z && lo.z <= row_hi.z &&
                       ((row_cat & __float_as_uint(hi.w)) | (__float_as_uint(lo.w) & row_mask)) != 0 &&
                       (row_flags | col_flags[j]) == 7u;
      if (hit) hits |= std::uint64_t{1} << j;
    };
    if (tid < m) {
      if (h == v) {
        if (Balanced) {
          // Eq. 7 with n = m: x = ceil((m+1)/2) for the first ceil(m/2) rows, else floor((m+1)/2);
          // the first of the x elements is the diagonal (a box with itself), skipped.
          const std::uint32_t x = tid < (m + 1) / 2 ? (m + 2) / 2 : (m + 1) / 2;
          std::uint32_t j = tid;
          for (std::uint32_t k = 1; k < x; ++k) {
            if (++j == m) j = 0;
            test(j);
          }
        } else {
          for (std::uint32_t j = tid + 1; j < m; ++j) test(j);
        }
      } else {
        for (std::uint32_t j = 0; j < n; ++j) test(j);
      }
    }

    const std::uint32_t pairs = static_cast<std::uint32_t>(__popcll(hits));
    const std::uint32_t bytes = Compressed ? (pairs ? 2 + pairs : 0) : 8 * pairs;
    std::uint32_t offset, total;
    scan(scan_temp).ExclusiveSum((pairs << 16) | bytes, offset, total);
    const std::uint32_t total_pairs = total >> 16, body = total & 0xFFFF;
    const std::uint32_t tile = tile0 + (h - v);
    if (total_pairs == 0) {
      if (tid == 0) a.tile_pairs[tile] = 0;
      continue;
    }
    const std::uint64_t chunk = sizeof(chunk_header) + ((body + 3u) & ~3u);
    if (tid == 0) chunk_base = reserve_chunk(a, tile, p0.entry, v, h, total_pairs, body, chunk);
    __syncthreads();
    const std::uint64_t base = chunk_base;
    if (pairs == 0 || base + chunk > a.capacity) continue;
    unsigned char* dst = a.out + base + sizeof(chunk_header) + (offset & 0xFFFF);
    if (Compressed) {
      dst[0] = static_cast<unsigned char>(tid);
      dst[1] = static_cast<unsigned char>(pairs - 1);
      std::uint32_t q = 2;
      while (hits) {
        dst[q++] = static_cast<unsigned char>(__ffsll(static_cast<long long>(hits)) - 1);
        hits &= hits - 1;
      }
    } else {
      auto* w = reinterpret_cast<std::uint32_t*>(dst);
      std::uint32_t q = 0;
      while (hits) {
        const std::uint32_t j = __ffsll(static_cast<long long>(hits)) - 1;
        hits &= hits - 1;
        const std::uint32_t other = col_id[j];
        w[q++] = min(row_id, other);
        w[q++] = max(row_id, other);
      }
    }
  }
}

/// The overlapped upload's checks (docs/gpu.md, "Overlapped upload"): stage j finds every pair
/// whose larger id is in chunk j. In each cell it tests chunk j's boxes (list j, Q of them: the
/// rows) against the earlier chunks' boxes of the cell (lists 0..j-1, P of them) and against each
/// other, never two earlier boxes, so the stages together test each cell's pairs once, as the
/// one-shot path does. Width W (stage_layout, pbig_shared.h; chosen on the host): a work item is
/// (cell, row segment u of W rows of chunk j's list), run by L = min(W, 32) lanes of a warp, each
/// on its own after the plan is loaded: W < 32 puts 32 / W items in a warp (sub-warp shuffles and
/// scans), W = 64 gives a lane two rows (lane and lane + 32), which share each column's load. The
/// item's tiles of W columns: the earlier boxes in ceil(P / W) segments (every pair), then chunk
/// j's own segments from u on (u: the triangle, triangle_walk; above: every pair). A pair is kept
/// by check_kernel's rule (box_pair_hit), so each pair is found in exactly one stage and one cell.
/// A tile's pairs are in row order (rows 0..W-1 of the segment), each row's by column: plain
/// chunks (direct output), boxes read through their ids (a.packed_lo/hi are by id); the header's
/// segment fields (not read in direct output) saturate at 65535.
template <std::uint32_t W, bool Balanced>
__global__ void __launch_bounds__(tuning::segment) check_stage_kernel(check_args a, stage_lists lists) {
  static_assert(is_stage_width(W), "a stage width (pbig_shared.h)");
  constexpr std::uint32_t L = W < 32 ? W : 32;          // lanes of a work item
  constexpr std::uint32_t R = W / L;                    // rows of a lane (1, or 2 when W = 64)
  constexpr std::uint32_t slots = tuning::segment / L;  // work items of a block
  static_assert(tuning::segment % 32 == 0 && L >= static_cast<std::uint32_t>(max_overlap_chunks),
                "whole warps; an item's lanes read the lists' ranges");
  using mask_t = std::conditional_t<(W > 32), std::uint64_t, std::uint32_t>;
  __shared__ float4 col_lo[slots][W];
  __shared__ float4 col_hi[slots][W];
  __shared__ std::uint32_t col_id[slots][W];
  __shared__ std::uint8_t col_flags[slots][W];
  __shared__ grid_plan_dev plan;
  __shared__ std::uint32_t list_first[slots][max_overlap_chunks];   // the cell's first entry in list i
  __shared__ std::uint32_t list_at[slots][max_overlap_chunks + 1];  // list i's first box among the cell's

  // guard (uniform over the block)
  if (blockDim.x != tuning::segment || lists.count == 0 || lists.count > static_cast<std::uint32_t>(max_overlap_chunks)) {
    return;
  }
  if (threadIdx.x == 0) plan = *a.plan;
  __syncthreads();  // the block's only barrier: from here each item's lanes work on their own
  const std::uint32_t slot = threadIdx.x / L, g = threadIdx.x % L;
  // The item's lanes (L of the warp's 32) for the sub-warp shuffles and barriers.
  const unsigned group = L == 32 ? 0xffffffffu : ((1u << L) - 1u) << (threadIdx.x % 32 / L * L);
  const std::uint32_t item = a.item_first + blockIdx.x * slots + slot;
  if (item >= a.item_last || item >= a.grid->total.item) return;  // guard (uniform over the item's lanes)
  const std::uint32_t cell = a.items[item];
  const std::uint32_t own = lists.count - 1;  // list j, the stage's chunk
  {
    // Lane i reads list i's range in the cell; a scan over the item's lanes places the lists one
    // after the other.
    std::uint32_t first = 0, len = 0;
    if (g < lists.count) {
      first = lists.prefix[g][cell].entry;
      len = lists.prefix[g][cell + 1].entry - first;
    }
    std::uint32_t upto = len;
    for (std::uint32_t o = 1; o < max_overlap_chunks; o <<= 1) {
      const std::uint32_t y = __shfl_up_sync(group, upto, o, L);
      if (g >= o) upto += y;
    }
    if (g < lists.count) {
      list_first[slot][g] = first;
      list_at[slot][g] = upto - len;
      if (g == own) list_at[slot][lists.count] = upto;
    }
    __syncwarp(group);
  }
  const std::uint32_t earlier_n = list_at[slot][own];                  // P
  const std::uint32_t own_n = list_at[slot][lists.count] - earlier_n;  // Q
  const std::uint32_t own_first = list_first[slot][own];
  const stage_cell_layout layout = stage_layout(own_n, earlier_n, W);
  const cell_prefix p0 = a.prefix[cell];  // the stage's prefix: own_first, the cell's first item and tile
  const std::uint32_t u = item - p0.item;
  if (u >= layout.items) return;  // guard (uniform over the item's lanes): the cell has layout.items items
  const std::uint32_t tile0 = p0.tile - a.tile_first + static_cast<std::uint32_t>(layout.first_tile(u));
  const std::uint32_t cc[3] = {cell % plan.dims[0], (cell / plan.dims[0]) % plan.dims[1],
                               cell / (plan.dims[0] * plan.dims[1])};
  const std::uint32_t* own_ids = lists.entries[own] + own_first;
  // The id of the earlier box at position pos < P (lists 0..j-1 one after the other).
  auto earlier_id = [&](std::uint32_t pos) {
    std::uint32_t i = 0;
    while (i + 1 < own && pos >= list_at[slot][i + 1]) ++i;
    return lists.entries[i][list_first[slot][i] + (pos - list_at[slot][i])];
  };

  // The item's rows: lane g holds rows g + r L of the segment (r < R), those below m.
  const std::uint32_t m = min(W, own_n - u * W);
  float4 row_lo[R], row_hi[R];
  std::uint32_t row_flags[R], row_id[R];
#pragma unroll
  for (std::uint32_t r = 0; r < R; ++r) {
    row_lo[r] = row_hi[r] = make_float4(0, 0, 0, 0);
    row_flags[r] = row_id[r] = 0;
    if (g + r * L < m) {
      row_id[r] = own_ids[u * W + g + r * L];
      row_lo[r] = a.packed_lo[row_id[r]];
      row_hi[r] = a.packed_hi[row_id[r]];
      row_flags[r] = hi_flags(row_hi[r], plan, cc);
    }
  }
  float4* const lo_s = col_lo[slot];
  float4* const hi_s = col_hi[slot];
  std::uint32_t* const id_s = col_id[slot];
  std::uint8_t* const flags_s = col_flags[slot];

  const std::uint32_t tiles = layout.tiles_of(u);
  for (std::uint32_t t = 0; t < tiles; ++t) {
    const bool earlier = t < layout.earlier;
    const std::uint32_t seg = earlier ? t : u + (t - layout.earlier);  // the column segment (earlier or own)
    const std::uint32_t n = min(W, (earlier ? earlier_n : own_n) - seg * W);
    __syncwarp(group);  // the previous tile's readers are done with the item's columns
#pragma unroll
    for (std::uint32_t r = 0; r < R; ++r) {
      const std::uint32_t c = g + r * L;
      if (c < n) {
        const std::uint32_t id = earlier ? earlier_id(seg * W + c) : own_ids[seg * W + c];
        id_s[c] = id;
        lo_s[c] = a.packed_lo[id];
        hi_s[c] = a.packed_hi[id];
        flags_s[c] = static_cast<std::uint8_t>(hi_flags(hi_s[c], plan, cc));
      }
    }
    __syncwarp(group);

    mask_t hits[R];
#pragma unroll
    for (std::uint32_t r = 0; r < R; ++r) hits[r] = 0;
    if (earlier || seg > u) {
      // The rectangle: every row against every column, each column read once for a lane's rows.
      for (std::uint32_t j = 0; j < n; ++j) {
        const float4 lo = lo_s[j], hi = hi_s[j];
        const std::uint32_t f = flags_s[j];
#pragma unroll
        for (std::uint32_t r = 0; r < R; ++r) {
          if (g + r * L < m && box_pair_hit(row_lo[r], row_hi[r], row_flags[r], lo, hi, f)) hits[r] |= mask_t{1} << j;
        }
      }
    } else {
      // The triangle of chunk j's own segment u (n == m).
#pragma unroll
      for (std::uint32_t r = 0; r < R; ++r) {
        const std::uint32_t row = g + r * L;
        if (row < m) {
          triangle_walk<Balanced>(row, m, [&](std::uint32_t j) {
            if (box_pair_hit(row_lo[r], row_hi[r], row_flags[r], lo_s[j], hi_s[j], flags_s[j])) {
              hits[r] |= mask_t{1} << j;
            }
          });
        }
      }
    }

    // The item's exclusive scan of the pairs per row (rows g + r L in field r, 16 bits each: at
    // most 32 lanes x 64 pairs), and the totals.
    std::uint32_t mine = 0;
#pragma unroll
    for (std::uint32_t r = 0; r < R; ++r) mine |= static_cast<std::uint32_t>(__popcll(hits[r])) << (16 * r);
    std::uint32_t upto = mine;
    for (std::uint32_t o = 1; o < L; o <<= 1) {
      const std::uint32_t y = __shfl_up_sync(group, upto, o, L);
      if (g >= o) upto += y;
    }
    const std::uint32_t total = __shfl_sync(group, upto, L - 1, L);
    const std::uint32_t total_pairs = (total & 0xffffu) + (total >> 16);
    const std::uint32_t tile = tile0 + t;
    if (total_pairs == 0) {
      if (g == 0) a.tile_pairs[tile] = 0;
      continue;
    }
    const std::uint32_t body = 8 * total_pairs;
    const std::uint64_t chunk = sizeof(chunk_header) + body;
    unsigned long long base = 0;
    if (g == 0) base = reserve_chunk(a, tile, own_first, min(u, 0xffffu), min(t, 0xffffu), total_pairs, body, chunk);
    base = __shfl_sync(group, base, 0, L);
    if (mine == 0 || base + chunk > a.capacity) continue;
    auto* out = reinterpret_cast<std::uint32_t*>(a.out + base + sizeof(chunk_header));
    const std::uint32_t before = upto - mine;  // the pairs of the earlier lanes' rows, per field
#pragma unroll
    for (std::uint32_t r = 0; r < R; ++r) {
      // Rows of field 0 (0..L-1) come first, then those of field 1 (L..2L-1).
      std::uint32_t q = 2 * ((r == 0 ? 0u : total & 0xffffu) + ((before >> (16 * r)) & 0xffffu));
      mask_t h = hits[r];
      while (h) {
        const std::uint32_t j = __ffsll(static_cast<long long>(h)) - 1;
        h &= h - 1;
        const std::uint32_t other = id_s[j];
        out[q++] = min(row_id[r], other);
        out[q++] = max(row_id[r], other);
      }
    }
  }
}

/// Direct output, after a batch's checking kernel wrote its plain chunks at atomic offsets: moves
/// each tile's pairs to the tile's scanned position in the batch's pair buffer, dropping the
/// headers, so the batch's pairs are in tile order (the same order on every run). One warp per
/// tile, coalesced 4-byte copies. Does nothing when the batch overflowed its chunk buffer (the
/// host re-runs the batch with room).
__global__ void place_chunks_kernel(const unsigned char* chunks, const unsigned long long* cursor, std::uint64_t capacity,
                                    const std::uint64_t* tile_off, const std::uint32_t* tile_pairs,
                                    const std::uint64_t* tile_pos, std::uint32_t tiles, std::uint32_t* out_pairs) {
  const std::uint64_t warp = (static_cast<std::uint64_t>(blockIdx.x) * blockDim.x + threadIdx.x) / 32;
  const std::uint32_t lane = threadIdx.x % 32;
  if (warp >= tiles || *cursor > capacity) return;
  const std::uint32_t pairs = tile_pairs[warp];
  if (pairs == 0) return;
  const auto* src = reinterpret_cast<const std::uint32_t*>(chunks + tile_off[warp] + sizeof(chunk_header));
  std::uint32_t* dst = out_pairs + 2 * tile_pos[warp];
  for (std::uint32_t w = lane; w < 2 * pairs; w += 32) dst[w] = src[w];
}

// ---- large boxes ------------------------------------------------------------------------------

/// Does large box l pair with box j on the large-box path? Each pair once: a large box meets every
/// grid box here, and another large box only when its id is higher.
__device__ __forceinline__ bool large_pair(const box_arrays& b, std::uint32_t l, std::uint32_t j,
                                           const std::uint8_t* is_large) {
  if (j == l || (is_large[j] && j < l)) return false;
  for (int d = 0; d < 3; ++d) {
    if (!(b.lo[d][l] <= b.hi[d][j] && b.lo[d][j] <= b.hi[d][l])) return false;
  }
  return ((b.category[l] & b.mask[j]) | (b.category[j] & b.mask[l])) != 0;
}

/// Large boxes, pass 1: pairs per (large box, block of boxes).
__global__ void large_count_kernel(box_arrays boxes, std::uint32_t n, const std::uint32_t* large,
                                   std::uint32_t large_count, const std::uint8_t* is_large, std::uint32_t chunks,
                                   std::uint32_t* counts) {
  using reduce = cub::BlockReduce<std::uint32_t, tuning::block>;
  __shared__ typename reduce::TempStorage temp;
  const std::uint64_t block = blockIdx.x;
  if (block >= static_cast<std::uint64_t>(chunks) * large_count) return;
  const std::uint32_t l = large[block / chunks];
  const std::uint32_t j = static_cast<std::uint32_t>(block % chunks) * blockDim.x + threadIdx.x;
  const std::uint32_t hit = (j < n && large_pair(boxes, l, j, is_large)) ? 1u : 0u;
  const std::uint32_t sum = reduce(temp).Sum(hit);
  if (threadIdx.x == 0) counts[block] = sum;
}

/// Large boxes, pass 2: writes the pairs at the scanned offsets (deterministic order).
__global__ void large_write_kernel(box_arrays boxes, std::uint32_t n, const std::uint32_t* large,
                                   std::uint32_t large_count, const std::uint8_t* is_large, std::uint32_t chunks,
                                   const std::uint32_t* offsets, std::uint32_t* pairs_out) {
  using scan = cub::BlockScan<std::uint32_t, tuning::block>;
  __shared__ typename scan::TempStorage temp;
  const std::uint64_t block = blockIdx.x;
  if (block >= static_cast<std::uint64_t>(chunks) * large_count) return;
  const std::uint32_t l = large[block / chunks];
  const std::uint32_t j = static_cast<std::uint32_t>(block % chunks) * blockDim.x + threadIdx.x;
  const std::uint32_t hit = (j < n && large_pair(boxes, l, j, is_large)) ? 1u : 0u;
  std::uint32_t pos;
  scan(temp).ExclusiveSum(hit, pos);
  if (hit) {
    const std::uint64_t at = 2ull * (static_cast<std::uint64_t>(offsets[block]) + pos);
    pairs_out[at] = min(l, j);
    pairs_out[at + 1] = max(l, j);
  }
}

}  // namespace zone::gpu::detail
