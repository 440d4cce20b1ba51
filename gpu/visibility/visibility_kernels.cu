// Kernels of the GPU visibility engine (visibility_launch.h; algorithm in docs/zone.md, "The
// interest step on the GPU").
//
// The float expressions of every box and test are those of zone::interest_tracker (build_boxes and
// process_rows): additions and subtractions only, so no contraction into FMAs can change them and
// the results equal the host path's bit for bit.
#include <cub/device/device_scan.cuh>

#include <algorithm>
#include <climits>

#include "visibility_launch.h"

namespace zone::gpu::detail::vis {
namespace {

constexpr unsigned full_mask = 0xffffffffu;
constexpr std::uint32_t block = 256;
constexpr std::uint32_t warps_per_block = block / 32;
/// A presence box covering more cells than this is kept out of the grid and tested by every
/// observer (a world boss's footprint; see docs/zone.md).
constexpr std::uint32_t large_cells = 64;
/// Previous-set entries a warp keeps in shared memory for its binary searches (longer rows are
/// searched in global memory).
constexpr std::uint32_t prev_cache = 128;

std::uint32_t blocks_for(std::uint64_t n, std::uint32_t per_block) {
  return static_cast<std::uint32_t>(std::max<std::uint64_t>(1, (n + per_block - 1) / per_block));
}

/// Float <-> int with the same order (for atomicMin / atomicMax on floats).
__device__ __forceinline__ int ordered(float f) {
  const int i = __float_as_int(f);
  return i >= 0 ? i : i ^ 0x7fffffff;
}
__device__ __forceinline__ float unordered(int i) { return __int_as_float(i >= 0 ? i : i ^ 0x7fffffff); }

__device__ __forceinline__ bool valid_box(const float4& lo, const float4& hi) {
  return lo.x <= hi.x && lo.y <= hi.y && lo.z <= hi.z && isfinite(lo.x) && isfinite(lo.y) && isfinite(lo.z) &&
         isfinite(hi.x) && isfinite(hi.y) && isfinite(hi.z);
}

/// Closed boxes meet (the contract's Eq. 1).
__device__ __forceinline__ bool meets(const float4& alo, const float4& ahi, const float4& blo, const float4& bhi) {
  return blo.x <= ahi.x && alo.x <= bhi.x && blo.y <= ahi.y && alo.y <= bhi.y && blo.z <= ahi.z && alo.z <= bhi.z;
}

/// The cell of a coordinate: monotone non-decreasing in v (a subtraction and a multiplication by
/// a positive constant, rounded, then clamped), which the output-cell rule relies on. NaN maps to 0.
__device__ __forceinline__ std::uint32_t cell_of(float v, float origin, float inv_edge, std::uint32_t cells) {
  float t = (v - origin) * inv_edge;
  t = fminf(fmaxf(t, 0.0f), static_cast<float>(cells - 1));
  return static_cast<std::uint32_t>(t);
}

__device__ __forceinline__ unsigned lanes_below(unsigned lane) { return (1u << lane) - 1u; }

template <class T>
__device__ __forceinline__ T warp_sum(T v) {
  for (int o = 16; o > 0; o >>= 1) v += __shfl_down_sync(full_mask, v, o);
  return v;
}
__device__ __forceinline__ int warp_min(int v) {
  for (int o = 16; o > 0; o >>= 1) v = min(v, __shfl_down_sync(full_mask, v, o));
  return v;
}
__device__ __forceinline__ int warp_max(int v) {
  for (int o = 16; o > 0; o >>= 1) v = max(v, __shfl_down_sync(full_mask, v, o));
  return v;
}

/// First index in sorted[0, len) whose value is not below v.
__device__ __forceinline__ std::uint32_t lower_bound(const std::uint32_t* sorted, std::uint32_t len, std::uint32_t v) {
  std::uint32_t lo = 0, hi = len;
  while (lo < hi) {
    const std::uint32_t mid = (lo + hi) >> 1;
    if (sorted[mid] < v) {
      lo = mid + 1;
    } else {
      hi = mid;
    }
  }
  return lo;
}

/// Width in 1/16 m units for the integer sums (capped: a box wider than the world only raises the
/// cell edge).
__device__ __forceinline__ unsigned long long sixteenths(float w) {
  return static_cast<unsigned long long>(fminf(fmaxf(w, 0.0f), 1.0e9f) * 16.0f);
}

__global__ void init_kernel(tick_state* st) {
  if (threadIdx.x != 0) return;
  st->min_x = st->min_y = INT_MAX;
  st->max_x = st->max_y = INT_MIN;
  st->aoi_width_sum = st->body_width_sum = 0;
  st->observers = st->bodies = st->self_pairs = 0;
  st->bad_box = no_box;
  st->large_count = 0;
  st->overflow = 0;
  st->entries = st->candidates = st->enter_count = 0;
  st->visible_total = st->enter_total = st->leave_total = st->download_total = 0;
}

__global__ void prep_kernel(input_arrays in, std::uint32_t n, float h, box_arrays box, previous_rows prev,
                            tick_state* st) {
  const std::uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  int mnx = INT_MAX, mny = INT_MAX, mxx = INT_MIN, mxy = INT_MIN;
  unsigned long long aw = 0, bw = 0;
  std::uint32_t obs = 0, bodies = 0, self = 0;
  if (i < n) {
    const float3 p = in.pos[i], a = in.aoi[i], b = in.body[i];
    // build_boxes: the AOI box grown by h, and the presence box.
    const float gx = a.x + h, gy = a.y + h, gz = a.z + h;
    const float4 glo = make_float4(p.x - gx, p.y - gy, p.z - gz, 0.0f);
    const float4 ghi = make_float4(p.x + gx, p.y + gy, p.z + gz, 0.0f);
    const float4 plo = make_float4(p.x - b.x, p.y - b.y, p.z - b.z, 0.0f);
    const float4 phi = make_float4(p.x + b.x, p.y + b.y, p.z + b.z, 0.0f);
    box.g_lo[i] = glo;
    box.g_hi[i] = ghi;
    box.p_lo[i] = plo;
    box.p_hi[i] = phi;
    const bool g_ok = valid_box(glo, ghi), p_ok = valid_box(plo, phi);
    if (!g_ok) {
      atomicMin(&st->bad_box, 2u * i);
    } else if (!p_ok) {
      atomicMin(&st->bad_box, 2u * i + 1u);
    }
    const std::uint32_t sees = in.sees[i];
    if (p_ok) {
      mnx = ordered(plo.x);
      mny = ordered(plo.y);
      mxx = ordered(phi.x);
      mxy = ordered(phi.y);
      bw = sixteenths(((phi.x - plo.x) + (phi.y - plo.y)) * 0.5f);
      bodies = 1;
    }
    if (g_ok && sees != 0) {
      aw = sixteenths(((ghi.x - glo.x) + (ghi.y - glo.y)) * 0.5f);
      obs = 1;
    }
    self = (sees & in.cls[i]) != 0 ? 1u : 0u;
    // The observer's row in the previous update (a reused slot holds another handle: none).
    const std::uint32_t id = in.ids[i];
    std::uint32_t r = prev.row_of_slot[id & prev.slot_mask];
    if (r >= prev.rows || prev.ids[r] != id) r = no_row;
    in.prev_row[i] = r;
  }
  mnx = warp_min(mnx);
  mny = warp_min(mny);
  mxx = warp_max(mxx);
  mxy = warp_max(mxy);
  aw = warp_sum(aw);
  bw = warp_sum(bw);
  obs = warp_sum(obs);
  bodies = warp_sum(bodies);
  self = warp_sum(self);
  if ((threadIdx.x & 31) == 0) {
    if (bodies != 0) {
      atomicMin(&st->min_x, mnx);
      atomicMin(&st->min_y, mny);
      atomicMax(&st->max_x, mxx);
      atomicMax(&st->max_y, mxy);
      atomicAdd(&st->body_width_sum, bw);
      atomicAdd(&st->bodies, bodies);
    }
    if (obs != 0) {
      atomicAdd(&st->aoi_width_sum, aw);
      atomicAdd(&st->observers, obs);
    }
    if (self != 0) atomicAdd(&st->self_pairs, self);
  }
}

__global__ void plan_kernel(tick_state* st, std::uint32_t max_cells) {
  if (threadIdx.x != 0 || blockIdx.x != 0) return;
  grid_params g{};
  g.ox = g.oy = 0;
  g.edge = g.inv_edge = 1;
  g.nx = g.ny = g.cells = 1;
  if (st->bodies != 0 && st->min_x <= st->max_x && st->min_y <= st->max_y) {
    const double lox = unordered(st->min_x), loy = unordered(st->min_y);
    const double ex = static_cast<double>(unordered(st->max_x)) - lox;
    const double ey = static_cast<double>(unordered(st->max_y)) - loy;
    const double mean_aoi = st->observers != 0 ? static_cast<double>(st->aoi_width_sum) / 16.0 / st->observers : 0.0;
    const double mean_body = static_cast<double>(st->body_width_sum) / 16.0 / st->bodies;
    // An average AOI box spans about 4 cells a side; a body at most a couple (docs/zone.md).
    double edge = fmax(mean_aoi / 4.0, mean_body * 2.0);
    edge = fmax(edge, fmax(ex, ey) / 4096.0);
    if (!(edge > 0.0) || !isfinite(edge)) edge = 1.0;
    double nx = 1, ny = 1;
    for (int k = 0; k < 200; ++k) {
      nx = floor(ex / edge) + 1.0;
      ny = floor(ey / edge) + 1.0;
      if (nx * ny <= static_cast<double>(max_cells)) break;
      edge *= 1.25;
    }
    if (nx * ny > static_cast<double>(max_cells)) nx = ny = 1;  // degenerate extents: one cell
    g.ox = static_cast<float>(lox);
    g.oy = static_cast<float>(loy);
    g.edge = static_cast<float>(edge);
    g.inv_edge = static_cast<float>(1.0 / edge);
    g.nx = static_cast<std::uint32_t>(nx);
    g.ny = static_cast<std::uint32_t>(ny);
    g.cells = g.nx * g.ny;
  }
  st->grid = g;
}

struct cell_range {
  std::uint32_t x0, x1, y0, y1;
};

__device__ __forceinline__ cell_range cells_of(const float4& lo, const float4& hi, const grid_params& g) {
  return {cell_of(lo.x, g.ox, g.inv_edge, g.nx), cell_of(hi.x, g.ox, g.inv_edge, g.nx),
          cell_of(lo.y, g.oy, g.inv_edge, g.ny), cell_of(hi.y, g.oy, g.inv_edge, g.ny)};
}

__device__ __forceinline__ bool is_large(const cell_range& r) {
  return static_cast<std::uint64_t>(r.x1 - r.x0 + 1) * (r.y1 - r.y0 + 1) > large_cells;
}

__global__ void count_kernel(pass_args a, std::uint32_t* counts) {
  const std::uint32_t j = blockIdx.x * blockDim.x + threadIdx.x;
  if (j >= a.n) return;
  const grid_params g = a.st->grid;
  const cell_range r = cells_of(a.box.p_lo[j], a.box.p_hi[j], g);
  if (is_large(r)) {
    const std::uint32_t k = atomicAdd(&a.st->large_count, 1u);
    if (k < a.n) a.grid.large[k] = j;
    return;
  }
  for (std::uint32_t y = r.y0; y <= r.y1; ++y) {
    for (std::uint32_t x = r.x0; x <= r.x1; ++x) atomicAdd(&counts[y * g.nx + x], 1u);
  }
}

__global__ void scatter_kernel(pass_args a, std::uint32_t* cursor) {
  const std::uint32_t j = blockIdx.x * blockDim.x + threadIdx.x;
  if (j >= a.n) return;
  const grid_params g = a.st->grid;
  const float4 lo = a.box.p_lo[j], hi = a.box.p_hi[j];
  const cell_range r = cells_of(lo, hi, g);
  if (is_large(r)) return;
  const float4 elo = make_float4(lo.x, lo.y, lo.z, __uint_as_float(a.in.cls[j]));
  const float4 ehi = make_float4(hi.x, hi.y, hi.z, __uint_as_float(j));
  for (std::uint32_t y = r.y0; y <= r.y1; ++y) {
    for (std::uint32_t x = r.x0; x <= r.x1; ++x) {
      const std::uint32_t c = y * g.nx + x;
      const std::uint64_t pos = static_cast<std::uint64_t>(a.grid.start[c]) + atomicAdd(&cursor[c], 1u);
      if (pos < a.grid.entry_capacity) {
        a.grid.e_lo[pos] = elo;
        a.grid.e_hi[pos] = ehi;
        a.grid.e_cx[pos] = x;
      } else {
        atomicOr(&a.st->overflow, 1u);
      }
    }
  }
}

/// Previous row of observer i: [first, first + len) of prev_vis.
struct prev_span {
  std::uint32_t first, len;
};
__device__ __forceinline__ prev_span previous_of(const pass_args& a, std::uint32_t i) {
  const std::uint32_t r = a.in.prev_row[i];
  if (r == no_row || r >= a.prev_rows) return {0, 0};
  const std::uint32_t b = a.prev_off[r];
  return {b, a.prev_off[r + 1] - b};
}

/// One warp per observer. Candidates: every presence box in the cells its grown AOI box covers
/// (each cell row is one contiguous range of entries), then the large ones. A presence box listed
/// in several cells counts only in the cell holding the lower corner of the two boxes'
/// intersection (PBIG's output-cell rule, on the lower corner): cell_of is monotone, so that cell
/// is (max(x0, cell(P.lo.x)), max(y0, cell(P.lo.y))). Each candidate is classified at once: found
/// in the previous set (binary search: it is sorted), it flags that entry (it stays); otherwise
/// it enters if its presence box meets the exact AOI box (appended to enter_pairs).
__global__ void __launch_bounds__(block) query_kernel(pass_args a) {
  const std::uint32_t i = (blockIdx.x * blockDim.x + threadIdx.x) >> 5;
  const unsigned lane = threadIdx.x & 31u;
  // The whole warp leaves together; after an overflow the host grows the buffers and runs again.
  if (i >= a.n || (__shfl_sync(full_mask, a.st->overflow, 0) & 1u) != 0) return;
  const prev_span ps = previous_of(a, i);
  __shared__ std::uint32_t cache[warps_per_block][prev_cache];
  const std::uint32_t* prev = a.prev_vis + ps.first;
  const bool cached = ps.len <= prev_cache;
  for (std::uint32_t q = lane; q < ps.len; q += 32) {
    a.flag[ps.first + q] = 0;
    if (cached) cache[threadIdx.x >> 5][q] = prev[q];
  }
  if (cached) prev = cache[threadIdx.x >> 5];
  __syncwarp();
  const std::uint32_t sees = a.in.sees[i];
  std::uint32_t found = 0;    // this lane's candidates
  std::uint32_t entered = 0;  // the warp's enters
  if (sees != 0) {
    // The exact AOI box (process_rows' expressions) and the grown one.
    const float3 p = a.in.pos[i], ae = a.in.aoi[i];
    const float4 alo = make_float4(p.x - ae.x, p.y - ae.y, p.z - ae.z, 0.0f);
    const float4 ahi = make_float4(p.x + ae.x, p.y + ae.y, p.z + ae.z, 0.0f);
    const float4 lo = a.box.g_lo[i], hi = a.box.g_hi[i];
    const auto visit = [&](bool hit, std::uint32_t j) {
      bool enter = false;
      std::uint32_t t = 0;
      if (hit) {
        ++found;
        t = a.in.ids[j];
        const std::uint32_t q = lower_bound(prev, ps.len, t);
        if (q < ps.len && prev[q] == t) {
          a.flag[ps.first + q] = 1;
        } else {
          enter = meets(alo, ahi, a.box.p_lo[j], a.box.p_hi[j]);
        }
      }
      const unsigned m = __ballot_sync(full_mask, enter);
      if (m == 0) return;
      unsigned long long base = 0;
      if (lane == 0) base = atomicAdd(&a.st->enter_count, static_cast<unsigned long long>(__popc(m)));
      base = __shfl_sync(full_mask, base, 0);
      if (enter) {
        const unsigned long long pos = base + __popc(m & lanes_below(lane));
        if (pos < a.enter_capacity) {
          a.enter_pairs[pos] = (static_cast<unsigned long long>(i) << 32) | t;
        } else {
          atomicOr(&a.st->overflow, 2u);
        }
      }
      entered += __popc(m);
    };
    const grid_params g = a.st->grid;
    const cell_range r = cells_of(lo, hi, g);
    for (std::uint32_t y = r.y0; y <= r.y1; ++y) {
      const std::uint32_t row = y * g.nx;
      const std::uint32_t b = a.grid.start[row + r.x0], e = a.grid.start[row + r.x1 + 1];
      for (std::uint32_t k0 = b; k0 < e; k0 += 32) {
        const std::uint32_t k = k0 + lane;
        bool hit = false;
        std::uint32_t j = 0;
        if (k < e) {
          const float4 plo = a.grid.e_lo[k], phi = a.grid.e_hi[k];
          j = __float_as_uint(phi.w);
          hit = (__float_as_uint(plo.w) & sees) != 0 && j != i && meets(lo, hi, plo, phi) &&
                a.grid.e_cx[k] == max(r.x0, cell_of(plo.x, g.ox, g.inv_edge, g.nx)) &&
                y == max(r.y0, cell_of(plo.y, g.oy, g.inv_edge, g.ny));
        }
        visit(hit, j);
      }
    }
    const std::uint32_t large = min(a.st->large_count, a.n);
    for (std::uint32_t k0 = 0; k0 < large; k0 += 32) {
      const std::uint32_t k = k0 + lane;
      bool hit = false;
      std::uint32_t j = 0;
      if (k < large) {
        j = a.grid.large[k];
        hit = (a.in.cls[j] & sees) != 0 && j != i && meets(lo, hi, a.box.p_lo[j], a.box.p_hi[j]);
      }
      visit(hit, j);
    }
  }
  __syncwarp();
  std::uint32_t kept = 0;
  for (std::uint32_t q0 = 0; q0 < ps.len; q0 += 32) {
    const std::uint32_t q = q0 + lane;
    kept += __popc(__ballot_sync(full_mask, q < ps.len && a.flag[ps.first + q] != 0));
  }
  found = warp_sum(found);
  if (lane == 0) {
    a.vis_len[i] = kept + entered;
    a.enter_len[i] = entered;
    a.leave_len[i] = ps.len - kept;
    if (found != 0) atomicAdd(&a.st->candidates, static_cast<unsigned long long>(found));
  }
}

__global__ void touch_kernel() {}

__global__ void capacity_kernel(pass_args a) {
  if (threadIdx.x != 0 || blockIdx.x != 0) return;
  // After a grid overflow the query did not run: the list sizes (and their scans) hold whatever
  // the buffers held before, so no total may be judged from them (the host grows the grid only).
  if ((a.st->overflow & 1u) != 0) return;
  if (a.vis_off[a.n] > a.vis_capacity) atomicOr(&a.st->overflow, 4u);
  if (a.st->enter_count > a.enter_capacity) atomicOr(&a.st->overflow, 2u);
}

__global__ void place_enters_kernel(pass_args a) {
  if (a.st->overflow != 0) return;
  const unsigned long long total = a.st->enter_count;
  for (unsigned long long k = blockIdx.x * static_cast<unsigned long long>(blockDim.x) + threadIdx.x; k < total;
       k += static_cast<unsigned long long>(gridDim.x) * blockDim.x) {
    const unsigned long long e = a.enter_pairs[k];
    const auto row = static_cast<std::uint32_t>(e >> 32);
    a.enter_tmp[a.enter_off[row] + atomicAdd(&a.enter_cursor[row], 1u)] = static_cast<std::uint32_t>(e);
  }
}

/// One warp per observer: enters sorted (by rank: handles are distinct), leaves and kept entries
/// in the previous (handle) order, and the visible set as the merge of kept entries and enters.
__global__ void __launch_bounds__(block) write_kernel(pass_args a) {
  const std::uint32_t i = (blockIdx.x * blockDim.x + threadIdx.x) >> 5;
  const unsigned lane = threadIdx.x & 31u;
  if (i >= a.n || a.st->overflow != 0) return;
  const std::uint32_t en = a.enter_len[i];
  const std::uint32_t* unsorted = a.enter_tmp + a.enter_off[i];
  std::uint32_t* enters = a.enter_out + a.enter_off[i];
  if (en <= 32) {
    const std::uint32_t x = lane < en ? unsorted[lane] : 0xffffffffu;
    std::uint32_t rank = 0;
    for (std::uint32_t k = 0; k < en; ++k) rank += __shfl_sync(full_mask, x, static_cast<int>(k)) < x ? 1u : 0u;
    if (lane < en) enters[rank] = x;
  } else {
    for (std::uint32_t b = lane; b < en; b += 32) {
      const std::uint32_t x = unsorted[b];
      std::uint32_t rank = 0;
      for (std::uint32_t k = 0; k < en; ++k) rank += unsorted[k] < x ? 1u : 0u;
      enters[rank] = x;
    }
  }
  __syncwarp();
  const prev_span ps = previous_of(a, i);
  const std::uint32_t* prev = a.prev_vis + ps.first;
  std::uint32_t* vis = a.vis_out + a.vis_off[i];
  std::uint32_t* leaves = a.leave_out + a.leave_off[i];
  std::uint32_t kept_before = 0, left_before = 0;
  for (std::uint32_t q0 = 0; q0 < ps.len; q0 += 32) {
    const std::uint32_t q = q0 + lane;
    const bool in = q < ps.len;
    const std::uint32_t v = in ? prev[q] : 0;
    const bool keep = in && a.flag[ps.first + q] != 0;
    const unsigned mk = __ballot_sync(full_mask, keep), ml = __ballot_sync(full_mask, in && !keep);
    const std::uint32_t kr = kept_before + __popc(mk & lanes_below(lane));
    if (in) a.kept_prefix[ps.first + q] = kr;
    if (keep) {
      vis[kr + lower_bound(enters, en, v)] = v;
    } else if (in) {
      leaves[left_before + __popc(ml & lanes_below(lane))] = v;
    }
    kept_before += __popc(mk);
    left_before += __popc(ml);
  }
  __syncwarp();
  for (std::uint32_t b = lane; b < en; b += 32) {
    const std::uint32_t x = enters[b];
    const std::uint32_t q = lower_bound(prev, ps.len, x);
    vis[b + (q < ps.len ? a.kept_prefix[ps.first + q] : kept_before)] = x;
  }
}

__global__ void wanted_sizes_kernel(pass_args a) {
  const std::uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i > a.n) return;
  a.dl_len[i] = i < a.n && a.in.wanted[i] != 0 && a.st->overflow == 0 ? a.vis_len[i] : 0u;
}

__global__ void __launch_bounds__(block) gather_kernel(pass_args a) {
  const std::uint32_t i = (blockIdx.x * blockDim.x + threadIdx.x) >> 5;
  const unsigned lane = threadIdx.x & 31u;
  if (i >= a.n || a.st->overflow != 0 || a.in.wanted[i] == 0) return;
  const std::uint32_t* src = a.vis_out + a.vis_off[i];
  std::uint32_t* dst = a.dl_out + a.dl_off[i];
  for (std::uint32_t k = lane, len = a.vis_off[i + 1] - a.vis_off[i]; k < len; k += 32) dst[k] = src[k];
}

__global__ void totals_kernel(pass_args a, std::uint32_t max_cells) {
  if (threadIdx.x != 0 || blockIdx.x != 0) return;
  a.st->entries = a.grid.start[max_cells];
  a.st->visible_total = a.vis_off[a.n];
  a.st->enter_total = a.enter_off[a.n];
  a.st->leave_total = a.leave_off[a.n];
  if (a.in.wanted != nullptr) a.st->download_total = a.dl_off[a.n];
}

__global__ void commit_kernel(pass_args a) {
  const std::uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= a.n || a.st->bad_box != no_box || a.st->overflow != 0) return;
  const std::uint32_t id = a.in.ids[i];
  a.prev.row_of_slot[id & a.prev.slot_mask] = i;
  a.prev.ids[i] = id;
}

__global__ void map_slots_kernel(const std::uint32_t* ids, std::uint32_t rows, std::uint32_t mask,
                                 std::uint32_t* row_of_slot) {
  const std::uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i < rows) row_of_slot[ids[i] & mask] = i;
}

}  // namespace

cudaError_t launch_init(tick_state* st, cudaStream_t stream) {
  init_kernel<<<1, 32, 0, stream>>>(st);
  return cudaGetLastError();
}

cudaError_t launch_prep(const input_arrays& in, std::uint32_t n, float hysteresis, const box_arrays& box,
                        const previous_rows& prev, tick_state* st, cudaStream_t stream) {
  if (n == 0) return cudaSuccess;
  prep_kernel<<<blocks_for(n, block), block, 0, stream>>>(in, n, hysteresis, box, prev, st);
  return cudaGetLastError();
}

cudaError_t launch_plan(tick_state* st, std::uint32_t max_cells, cudaStream_t stream) {
  plan_kernel<<<1, 32, 0, stream>>>(st, max_cells);
  return cudaGetLastError();
}

cudaError_t launch_count(const pass_args& a, std::uint32_t* counts, cudaStream_t stream) {
  if (a.n == 0) return cudaSuccess;
  count_kernel<<<blocks_for(a.n, block), block, 0, stream>>>(a, counts);
  return cudaGetLastError();
}

cudaError_t scan_cells(void* temp, std::size_t& temp_bytes, const std::uint32_t* counts, std::uint32_t* start,
                       std::uint32_t items, cudaStream_t stream) {
  return cub::DeviceScan::ExclusiveSum(temp, temp_bytes, counts, start, items, stream);
}

cudaError_t launch_scatter(const pass_args& a, std::uint32_t* cursor, cudaStream_t stream) {
  if (a.n == 0) return cudaSuccess;
  scatter_kernel<<<blocks_for(a.n, block), block, 0, stream>>>(a, cursor);
  return cudaGetLastError();
}

cudaError_t launch_query(const pass_args& a, cudaStream_t stream) {
  if (a.n == 0) return cudaSuccess;
  query_kernel<<<blocks_for(a.n, warps_per_block), block, 0, stream>>>(a);
  return cudaGetLastError();
}

cudaError_t launch_touch(cudaStream_t stream) {
  touch_kernel<<<1, 32, 0, stream>>>();
  return cudaGetLastError();
}

cudaError_t launch_capacity(const pass_args& a, cudaStream_t stream) {
  capacity_kernel<<<1, 32, 0, stream>>>(a);
  return cudaGetLastError();
}

cudaError_t launch_place_enters(const pass_args& a, cudaStream_t stream) {
  place_enters_kernel<<<264, block, 0, stream>>>(a);
  return cudaGetLastError();
}

cudaError_t scan_u32(void* temp, std::size_t& temp_bytes, const std::uint32_t* counts, std::uint32_t* off,
                     std::uint32_t items, cudaStream_t stream) {
  return cub::DeviceScan::ExclusiveSum(temp, temp_bytes, counts, off, items, stream);
}

cudaError_t launch_write(const pass_args& a, cudaStream_t stream) {
  if (a.n == 0) return cudaSuccess;
  write_kernel<<<blocks_for(a.n, warps_per_block), block, 0, stream>>>(a);
  return cudaGetLastError();
}

cudaError_t launch_wanted_sizes(const pass_args& a, cudaStream_t stream) {
  wanted_sizes_kernel<<<blocks_for(a.n + 1ull, block), block, 0, stream>>>(a);
  return cudaGetLastError();
}

cudaError_t launch_gather(const pass_args& a, cudaStream_t stream) {
  if (a.n == 0) return cudaSuccess;
  gather_kernel<<<blocks_for(a.n, warps_per_block), block, 0, stream>>>(a);
  return cudaGetLastError();
}

cudaError_t launch_totals(const pass_args& a, std::uint32_t max_cells, cudaStream_t stream) {
  totals_kernel<<<1, 32, 0, stream>>>(a, max_cells);
  return cudaGetLastError();
}

cudaError_t launch_commit(const pass_args& a, cudaStream_t stream) {
  if (a.n == 0) return cudaSuccess;
  commit_kernel<<<blocks_for(a.n, block), block, 0, stream>>>(a);
  return cudaGetLastError();
}

cudaError_t launch_map_slots(const std::uint32_t* ids, std::uint32_t rows, std::uint32_t slot_bits,
                             std::uint32_t* row_of_slot, cudaStream_t stream) {
  const cudaError_t err = cudaMemsetAsync(row_of_slot, 0xff, (std::size_t{1} << slot_bits) * sizeof(std::uint32_t), stream);
  if (err != cudaSuccess || rows == 0) return err;
  map_slots_kernel<<<blocks_for(rows, block), block, 0, stream>>>(ids, rows, (1u << slot_bits) - 1u, row_of_slot);
  return cudaGetLastError();
}

}  // namespace zone::gpu::detail::vis
