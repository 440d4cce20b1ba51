// What the GPU replication engine's host dispatch and kernels share (gpu/replication.h; algorithm
// in docs/zone.md, "Replication on the GPU"): the run's arguments, the client table's planning and
// the per-job decision itself. Free of CUDA headers: compiled by nvcc for the kernels and by the
// host compiler for the host dispatch and for tests/zone's emulated engine, which runs this very
// code on the CPU against zone::replicator in every CI run (the device is checked the same way in
// tests/zone/test_zone_gpu.cpp).
//
// One job walks the client's view and visible set exactly as zone::replicator does
// (replication.cpp): the same merge, the same tiers, the same closed-form byte budget, the same
// order of enters (distance, then id) and of updates when the budget binds (staleness per metre,
// then id). Every float that decides anything is computed with explicitly rounded operations on
// the device (__fmul_rn, __fadd_rn, __fsqrt_rn, __fdiv_rn) in the host's order of evaluation, so
// nvcc cannot contract them into FMAs and the decisions equal the host's bit for bit.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>
#include <stdexcept>

#include "interest/replication_engine.h"

#if defined(__CUDACC__)
#define ZONE_REP_HD __host__ __device__ __forceinline__
#else
#define ZONE_REP_HD inline
#endif

namespace zone::gpu::detail::rep {

/// Per client slot: where its view is now (old) and its job (index + 1; 0: no job this run, the
/// view is copied as it is). Where the view goes is run_args::new_off.
struct client_slot {
  std::uint32_t old_off, old_len, job, pad;
};

/// A scratch entry: a due update {union place, dense, d2 (then priority), staleness (then rank, or
/// its id for the sort)} or an enter candidate {distance, id, dense, union place (then rank)}.
struct alignas(16) scratch_entry {
  std::uint32_t x, y, z, w;
};

/// Everything a run reads and writes (device pointers on the GPU).
struct run_args {
  interest::replication_rules rules;
  const interest::replication_entity* entities;
  std::uint32_t entity_count;
  std::uint32_t* updates;  // by dense index: 4 words, the entity's 16-byte wire update (quantize_entity)
  const interest::replication_frame_format* format;  // the frames' layout
  const std::uint32_t* slot_dense;
  std::uint32_t slot_count;
  const interest::replication_job* jobs;
  std::uint32_t job_count;
  const std::uint32_t* visible;   // the jobs' visible sets, staged (rows_off null)
  const std::uint32_t* rows_data;  // or resident rows: row r = rows_data[rows_off[r], rows_off[r + 1])
  const std::uint32_t* rows_off;
  std::uint32_t row_count;
  const client_slot* clients;
  const std::uint32_t* new_off;  // by client: where its view goes in new_id / new_sent (and its scratch)
  std::uint32_t client_count;
  const std::uint32_t* old_id;  // views now: ids (sorted per client) and last-sent ticks
  const std::uint32_t* old_sent;
  std::uint32_t* new_id;  // views after this run
  std::uint32_t* new_sent;
  scratch_entry* scratch;  // per job at its new_off: due updates (up to its view), then enter candidates
  std::uint64_t* hash;     // by client
  std::uint8_t* records;
  std::uint64_t record_capacity;
  std::uint32_t* cursor;  // [0]: record bytes used, [1]: overflow flag
  interest::replication_result* results;
};

/// The client table of a run (host side): each client's view now and its job. Throws
/// std::invalid_argument on a job whose client is out of range or repeated, or (staged sets,
/// `rows` 0) whose visible set is out of range of `visible_count` entries, or (resident rows) whose
/// row is not below `rows` and not interest::no_row.
inline void table_clients(const interest::replication_job* jobs, std::size_t job_count, std::size_t visible_count,
                          std::size_t rows, const std::uint32_t* len, const std::uint32_t* off, std::size_t client_count,
                          client_slot* out) {
  for (std::size_t c = 0; c < client_count; ++c) out[c] = {off[c], len[c], 0, 0};
  for (std::size_t k = 0; k < job_count; ++k) {
    const auto& j = jobs[k];
    if (j.client >= client_count) throw std::invalid_argument("replication engine: a job's client is out of range");
    if (out[j.client].job != 0) throw std::invalid_argument("replication engine: two jobs for one client");
    if (rows == 0 && std::uint64_t{j.visible_off} + j.visible_len > visible_count) {
      throw std::invalid_argument("replication engine: a job's visible set is out of range");
    }
    if (rows != 0 && j.visible_off != interest::no_row && j.visible_off >= rows) {
      throw std::invalid_argument("replication engine: a job's row is out of range");
    }
    out[j.client].job = static_cast<std::uint32_t>(k + 1);
  }
}

/// Bytes of a frame with these parts and counts (net::canonical_tick_update::size).
ZONE_REP_HD std::uint64_t frame_size(const interest::replication_frame_format& f, std::uint32_t parts, std::uint64_t enters,
                                     std::uint64_t leaves, std::uint64_t updates) {
  const interest::replication_frame_format::table& t = f.tables[parts];
  const std::uint64_t n = std::uint64_t{t.at} + t.size +
                          (enters != 0 ? 4 + 4 * enters + sizeof f.enter_vtable + (f.enter_table + f.enter_name) * enters : 0) +
                          (leaves != 0 ? 4 + 4 * leaves : 0) + (updates != 0 ? 4 + 16 * updates : 0);
  return (n + 7) & ~std::uint64_t{7};
}

/// The most bytes a job's frame can take with a view of v entries and a visible set of s: every
/// leave, enter and update with the largest header, and never more than the budget allows (the
/// decisions keep net::frame_cost's estimate, an upper bound on the size, within the budget, or
/// at the header's alone when that is over it).
ZONE_REP_HD std::uint64_t frame_bound(const interest::replication_rules& r, const interest::replication_frame_format& f,
                                      std::uint64_t v, std::uint64_t s) {
  const std::uint64_t most = f.header_max + (4 + 4 * s + sizeof f.enter_vtable + (f.enter_table + f.enter_name) * s) +
                             (4 + 4 * v) + (4 + 16 * v) + 7;
  const std::uint64_t header = std::uint64_t{r.header_cost} + r.self_cost;
  const std::uint64_t budget = (r.byte_budget > header ? r.byte_budget : header) + 7;
  return (most < budget ? most : budget) & ~std::uint64_t{7};
}

/// Where each client's new view goes (staged sets: the sizes are on the host): a job's client gets
/// room for its view plus its visible set (the new view is a subset of their union), every other
/// client for its view as it is. Returns the total and sets `record_cap` to the frames' bound.
inline std::uint64_t plan_staged(const interest::replication_job* jobs, const client_slot* clients,
                                 std::size_t client_count, const interest::replication_rules& rules,
                                 const interest::replication_frame_format& format, std::uint32_t* new_off,
                                 std::uint64_t& record_cap) {
  std::uint64_t total = 0;
  record_cap = 0;
  for (std::size_t c = 0; c < client_count; ++c) {
    new_off[c] = static_cast<std::uint32_t>(total);
    total += clients[c].old_len;
    if (clients[c].job != 0) {
      const auto& j = jobs[clients[c].job - 1];
      total += j.visible_len;
      record_cap += frame_bound(rules, format, (j.flags & interest::job_reset) != 0 ? 0 : clients[c].old_len, j.visible_len);
    }
    if (total > 0xffffffffu) throw std::invalid_argument("replication engine: more than 2^32 view entries");
  }
  new_off[client_count] = static_cast<std::uint32_t>(total);
  return total;
}

inline constexpr std::uint32_t no_index = 0xffffffffu;
/// What a run's cursor[1] says when it is not 0: the records' bound was wrong (a bug), or a job's
/// view or visible set is longer than max_job_list.
inline constexpr std::uint32_t flag_records_overflow = 1, flag_list_too_long = 2;

#if defined(__CUDA_ARCH__)
__device__ __forceinline__ float rn_sub(float a, float b) { return __fsub_rn(a, b); }
__device__ __forceinline__ float rn_add(float a, float b) { return __fadd_rn(a, b); }
__device__ __forceinline__ float rn_mul(float a, float b) { return __fmul_rn(a, b); }
__device__ __forceinline__ float rn_div(float a, float b) { return __fdiv_rn(a, b); }
__device__ __forceinline__ float rn_sqrt(float a) { return __fsqrt_rn(a); }
__device__ __forceinline__ float u32_to_float(std::uint32_t v) { return __uint2float_rn(v); }
__device__ __forceinline__ double rn_dsub(double a, double b) { return __dsub_rn(a, b); }
__device__ __forceinline__ double rn_dmul(double a, double b) { return __dmul_rn(a, b); }
__device__ __forceinline__ double rn_ddiv(double a, double b) { return __ddiv_rn(a, b); }
__device__ __forceinline__ std::uint32_t float_bits(float f) { return __float_as_uint(f); }
__device__ __forceinline__ float bits_float(std::uint32_t u) { return __uint_as_float(u); }
__device__ __forceinline__ std::uint32_t reserve_bytes(std::uint32_t* cursor, std::uint32_t n) { return atomicAdd(cursor, n); }
__device__ __forceinline__ void raise_flag(std::uint32_t* flag, std::uint32_t code) { atomicExch(flag, code); }
#else
// The host: each operation is rounded on its own (no -ffast-math, no FMA contraction on x86-64
// without -mfma), as in replication.cpp.
inline float rn_sub(float a, float b) { return a - b; }
inline float rn_add(float a, float b) { return a + b; }
inline float rn_mul(float a, float b) { return a * b; }
inline float rn_div(float a, float b) { return a / b; }
inline float rn_sqrt(float a) { return std::sqrt(a); }
inline float u32_to_float(std::uint32_t v) { return static_cast<float>(v); }
inline double rn_dsub(double a, double b) { return a - b; }
inline double rn_dmul(double a, double b) { return a * b; }
inline double rn_ddiv(double a, double b) { return a / b; }
inline std::uint32_t float_bits(float f) {
  std::uint32_t u;
  std::memcpy(&u, &f, 4);
  return u;
}
inline float bits_float(std::uint32_t u) {
  float f;
  std::memcpy(&f, &u, 4);
  return f;
}
inline std::uint32_t reserve_bytes(std::uint32_t* cursor, std::uint32_t n) {  // single-threaded emulation
  const std::uint32_t at = *cursor;
  *cursor += n;
  return at;
}
inline void raise_flag(std::uint32_t* flag, std::uint32_t code) { *flag = code; }
#endif

/// net::digest_mix (splitmix64's finaliser).
ZONE_REP_HD std::uint64_t digest_mix(std::uint32_t id) {
  std::uint64_t z = std::uint64_t{id} + 0x9e3779b97f4a7c15ull;
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}

/// net::detail::round_half_up (std::lround for 0 <= t < 2^31).
ZONE_REP_HD std::uint32_t round_half_up(double t) {
  const auto i = static_cast<std::uint32_t>(t);
  return i + (rn_dsub(t, static_cast<double>(i)) >= 0.5 ? 1u : 0u);
}

/// net::position_quantizer::quantize on one axis.
ZONE_REP_HD std::uint16_t quantize_axis(float v, float lo, double step) {
  if (step <= 0) return 0;
  const double t = rn_ddiv(rn_dsub(static_cast<double>(v), static_cast<double>(lo)), step);
  return !(t > 0) ? std::uint16_t{0} : t >= 65535.0 ? std::uint16_t{65535} : static_cast<std::uint16_t>(round_half_up(t));
}

/// net::quantize_velocity on one axis.
ZONE_REP_HD std::int16_t quantize_speed(float x) {
  const double t = rn_dmul(static_cast<double>(x), 100.0);
  if (!(t == t)) return 0;  // NaN
  const double c = t < -32767.0 ? -32767.0 : t > 32767.0 ? 32767.0 : t;
  const auto r = static_cast<std::int32_t>(round_half_up(c < 0 ? -c : c));
  return static_cast<std::int16_t>(c < 0 ? -r : r);
}

/// Entity k's wire update (net::wire::entity_update: id, qpos3, qvel3, 16 bytes) into a.updates,
/// as zone::replicator's wire_update makes it.
ZONE_REP_HD void quantize_entity(const run_args& a, std::uint32_t k) {
  const interest::replication_entity e = a.entities[k];
  const interest::replication_rules& r = a.rules;
  const std::uint16_t q[3] = {quantize_axis(e.x, r.quant_lo[0], r.quant_step[0]),
                              quantize_axis(e.y, r.quant_lo[1], r.quant_step[1]),
                              quantize_axis(e.z, r.quant_lo[2], r.quant_step[2])};
  const std::int16_t v[3] = {quantize_speed(e.vx), quantize_speed(e.vy), quantize_speed(e.vz)};
  std::uint32_t* u = a.updates + 4 * std::size_t{k};
  u[0] = e.id;
  u[1] = std::uint32_t{q[0]} | std::uint32_t{q[1]} << 16;
  u[2] = std::uint32_t{q[2]} | std::uint32_t{static_cast<std::uint16_t>(v[0])} << 16;
  u[3] = std::uint32_t{static_cast<std::uint16_t>(v[1])} | std::uint32_t{static_cast<std::uint16_t>(v[2])} << 16;
}

/// entity_store::index_of through the slot map.
ZONE_REP_HD std::uint32_t find_dense(const run_args& a, std::uint32_t id) {
  if (id == 0) return no_index;
  const std::uint32_t slot = id & a.rules.slot_mask;
  if (slot >= a.slot_count) return no_index;
  const std::uint32_t d = a.slot_dense[slot];
  if (d >= a.entity_count || a.entities[d].id != id) return no_index;
  return d;
}

/// replication.cpp's distance_sq: ((dx * dx + dy * dy) + dz * dz), each operation rounded.
ZONE_REP_HD float distance_sq(const float* eye, const interest::replication_entity& e) {
  const float dx = rn_sub(eye[0], e.x), dy = rn_sub(eye[1], e.y), dz = rn_sub(eye[2], e.z);
  return rn_add(rn_add(rn_mul(dx, dx), rn_mul(dy, dy)), rn_mul(dz, dz));
}

/// replicator::tier_below.
ZONE_REP_HD bool tier_below(float d2, float limit, float below_sq, float above_sq) {
  const bool below = d2 < below_sq;
  if (!below && !(d2 > above_sq)) return rn_sqrt(d2) < limit;
  return below;
}

/// (key, id) before (key', id'): the replicator's by_priority.
ZONE_REP_HD bool before(float ka, std::uint32_t ia, float kb, std::uint32_t ib) {
  return ka < kb || (ka == kb && ia < ib);
}

/// min(count, room).
ZONE_REP_HD std::uint32_t fit(std::uint32_t count, std::uint64_t room) {
  return room < count ? static_cast<std::uint32_t>(room) : count;
}

// Stores into a frame. Every u32 field of the canonical layout is 4-byte aligned in a frame that
// starts 8-byte aligned (the engine's frames do), so the device stores words; the host copies bytes.
#if defined(__CUDA_ARCH__)
__device__ __forceinline__ void put_u32(std::uint8_t* p, std::uint32_t v) { *reinterpret_cast<std::uint32_t*>(p) = v; }
#else
inline void put_u32(std::uint8_t* p, std::uint32_t v) { std::memcpy(p, &v, 4); }
#endif
ZONE_REP_HD void put_u16(std::uint8_t* p, std::uint16_t v) {
  p[0] = static_cast<std::uint8_t>(v);
  p[1] = static_cast<std::uint8_t>(v >> 8);
}
ZONE_REP_HD void put_u64(std::uint8_t* p, std::uint64_t v) {
  put_u32(p, static_cast<std::uint32_t>(v));
  put_u32(p + 4, static_cast<std::uint32_t>(v >> 32));
}
ZONE_REP_HD void put_f32(std::uint8_t* p, float v) { put_u32(p, float_bits(v)); }

ZONE_REP_HD scratch_entry entry(std::uint32_t x, std::uint32_t y, std::uint32_t z, std::uint32_t w) {
  scratch_entry e;
  e.x = x;
  e.y = y;
  e.z = z;
  e.w = w;
  return e;
}

/// A job's visible set: staged, or its row of the resident rows (none: empty).
ZONE_REP_HD const std::uint32_t* job_visible(const run_args& a, const interest::replication_job& job, std::uint32_t& len) {
  if (a.rows_off == nullptr) {
    len = job.visible_len;
    return a.visible + job.visible_off;
  }
  if (job.visible_off == interest::no_row || job.visible_off >= a.row_count) {
    len = 0;
    return a.rows_data;
  }
  len = a.rows_off[job.visible_off + 1] - a.rows_off[job.visible_off];
  return a.rows_data + a.rows_off[job.visible_off];
}

/// Client c's room in the new buffer (resident rows: the sizes are on the device): its view, plus
/// its visible set when it has a job; and its job's record bound (0 without).
ZONE_REP_HD void client_room(const run_args& a, std::uint32_t c, std::uint32_t& room, std::uint64_t& record) {
  const client_slot s = a.clients[c];
  room = s.old_len;
  record = 0;
  if (s.job == 0) return;
  const interest::replication_job& job = a.jobs[s.job - 1];
  std::uint32_t len = 0;
  (void)job_visible(a, job, len);
  room += len;
  record = frame_bound(a.rules, *a.format, (job.flags & interest::job_reset) != 0 ? 0 : s.old_len, len);
}

/// Client c's view into the new buffer when it has no job (lanes `first`, `first + stride`, ...).
ZONE_REP_HD void carry_client(const run_args& a, std::uint32_t c, std::uint32_t first, std::uint32_t stride) {
  const client_slot s = a.clients[c];
  if (s.job != 0) return;
  const std::uint32_t to = a.new_off[c];
  for (std::uint32_t k = first; k < s.old_len; k += stride) {
    a.new_id[to + k] = a.old_id[s.old_off + k];
    a.new_sent[to + k] = a.old_sent[s.old_off + k];
  }
}

/// Set bits of a lane mask.
ZONE_REP_HD std::uint32_t popcount32(std::uint32_t m) {
#if defined(__CUDA_ARCH__)
  return static_cast<std::uint32_t>(__popc(m));
#else
  std::uint32_t n = 0;
  for (; m != 0; m &= m - 1) ++n;
  return n;
#endif
}

/// The first place in p[0, n) (ascending) whose value is not below x.
ZONE_REP_HD std::uint32_t lower_bound_u32(const std::uint32_t* p, std::uint32_t n, std::uint32_t x) {
  std::uint32_t lo = 0, hi = n;
  while (lo < hi) {
    const std::uint32_t mid = lo + (hi - lo) / 2;
    if (p[mid] < x) {
      lo = mid + 1;
    } else {
      hi = mid;
    }
  }
  return lo;
}

/// Lists longer than this are ranked by sorting them (sort_entries), shorter ones by counting (each
/// entry against all: quadratic, but a pass without synchronisation for the few a frame usually
/// ranks). Counting a flash crowd's ~2,000 due updates a client took the engine's device work to
/// ~21 ms a tick at p99 (bench-zone, H200, 2026-11-30; 2.1 ms sorted).
inline constexpr std::uint32_t rank_by_sort_above = 32;

/// Sorts e[0, n) ascending by (key, id) (before()), in place, by the lanes of group g together: a
/// bitonic network in the form whose comparators all point one way, padded to a power of two with
/// entries past n taken as larger than any (so they never move and are never read). The keys are
/// (x, y) or, with by_z, (z, w), x and z a float's bits. Unique ids: the order is total, so any
/// width sorts to the same list.
template <class G>
ZONE_REP_HD void sort_entries(scratch_entry* e, std::uint32_t n, bool by_z, G& g) {
  constexpr std::uint32_t W = G::width;
  const std::uint32_t lane = g.lane();
  std::uint32_t padded = 1;
  while (padded < n) padded *= 2;
  const auto greater = [&](const scratch_entry& a, const scratch_entry& b) {
    return by_z ? before(bits_float(b.z), b.w, bits_float(a.z), a.w)
                : before(bits_float(b.x), b.y, bits_float(a.x), a.y);
  };
  for (std::uint32_t k = 2; k <= padded; k *= 2) {
    // j == k: the block's two halves, the second one reversed (i against k - 1 - i); then the
    // half-cleaners (i against i + j).
    for (std::uint32_t j = k; j >= 2; j /= 2) {
      const std::uint32_t half = j / 2;
      for (std::uint32_t t = lane; t < padded / 2; t += W) {
        const std::uint32_t block = t / half, off = t % half;
        const std::uint32_t i = block * j + off;
        const std::uint32_t l = j == k ? block * j + j - 1 - off : i + half;
        if (l < n && greater(e[i], e[l])) {
          const scratch_entry s = e[i];
          e[i] = e[l];
          e[l] = s;
        }
      }
      g.sync();
    }
  }
}

/// One lane deciding a job alone: the host's way (tests emulate wider groups with threads; the
/// device's group is a warp, replication_kernels.cu). A group G gives: `width` lanes (at most 32),
/// this lane's `lane()`, `ballot(p)` (bit l set when lane l's p holds), `first(v)` (lane 0's v),
/// `sum(v)` (every lane's v added, wrapping) and `sync()` (memory written by one lane before it is
/// seen by every lane after it). Every lane calls them in the same order.
struct serial_lanes {
  static constexpr std::uint32_t width = 1;
  ZONE_REP_HD std::uint32_t lane() const { return 0; }
  ZONE_REP_HD std::uint32_t ballot(bool p) { return p ? 1u : 0u; }
  ZONE_REP_HD std::uint32_t first(std::uint32_t v) { return v; }
  ZONE_REP_HD std::uint64_t sum(std::uint64_t v) { return v; }
  ZONE_REP_HD void sync() {}
};

// A union entry's tag (decide_job below): which lists hold it; for one in the view its index there,
// except for a listed entry of a sorted list, whose index bits hold its rank there (decide_job).
inline constexpr std::uint32_t tag_view = 0x80000000u, tag_visible = 0x40000000u, tag_listed = 0x20000000u,
                               tag_index = 0x1fffffffu;
/// The longest view or visible set a job may have: the union's tags keep view indices (or ranks) in
/// 29 bits.
inline constexpr std::uint32_t max_job_list = tag_index;

/// Job job_index, decided by the lanes of group g together: its frame's decisions, the frame itself,
/// its client's new view and hash, its result. The view and the visible set are sorted and free of
/// repeats; their union is first laid out, in id order, where the new view goes (new_id: the id,
/// new_sent: its tag), then walked in order in steps of g.width, each lane one entry, the lanes'
/// places in the lists taken from ballots; the new view is written back over the union, never ahead
/// of what is still to be read. The result is the same whatever the width (the host runs width 1).
template <class G>
ZONE_REP_HD void decide_job(const run_args& a, std::uint32_t job_index, G& g) {
  constexpr std::uint32_t W = G::width;
  const std::uint32_t lane = g.lane();
  const std::uint32_t below = lane == 0 ? 0u : (0xffffffffu >> (32 - lane));  // lanes before this one
  const interest::replication_job job = a.jobs[job_index];
  const client_slot cs = a.clients[job.client];
  const interest::replication_rules& r = a.rules;
  const bool reset = (job.flags & interest::job_reset) != 0;
  // The eye: the observer's position when it is live (the replicator's store.index_of), else 0.
  const std::uint32_t self = find_dense(a, job.observer);
  const bool has_self = self != no_index;
  float eye[3] = {0, 0, 0};
  if (has_self) {
    eye[0] = a.entities[self].x;
    eye[1] = a.entities[self].y;
    eye[2] = a.entities[self].z;
  }
  std::uint32_t S = 0;
  const std::uint32_t* vis = job_visible(a, job, S);
  const std::uint32_t V = reset ? 0 : cs.old_len;
  const std::uint32_t* view = a.old_id + cs.old_off;
  const std::uint32_t* sent = a.old_sent + cs.old_off;
  const std::uint32_t to = a.new_off[job.client];
  scratch_entry* due = a.scratch + to;        // up to V
  scratch_entry* enter = a.scratch + to + V;  // up to S
  std::uint32_t* const u_id = a.new_id + to;  // the union (up to V + S, the client's room), then the new view
  std::uint32_t* const u_tag = a.new_sent + to;
  const std::uint32_t tick32 = static_cast<std::uint32_t>(r.tick);
  const std::uint32_t mid_period = r.mid_period > 1 ? r.mid_period : 1u;
  const std::uint32_t far_period = r.far_period > 1 ? r.far_period : 1u;
  if (S > max_job_list || V > max_job_list) {  // run() refuses such sets before any job runs
    if (lane == 0) raise_flag(a.cursor + 1, flag_list_too_long);
    return;
  }

  // Pass 1, over the visible set: enters (in the store) and due updates listed in id order; each
  // entry's place in the union: its index plus the leaves below it (the view's entries below it
  // less those also visible, which are all among the visible set's entries before it). Then over
  // the view: each leave's place, its index among the leaves plus the visible entries below it.
  std::uint32_t E = 0, D = 0, B = 0;
  for (std::uint32_t base = 0; base < S; base += W) {
    const std::uint32_t i = base + lane;
    const std::uint32_t id = i < S ? vis[i] : 0u;
    const std::uint32_t j = i < S ? lower_bound_u32(view, V, id) : 0u;
    const bool both = i < S && j < V && view[j] == id;
    const std::uint32_t mb = g.ballot(both);
    bool listed_enter = false, listed_due = false;
    scratch_entry item = entry(0, 0, 0, 0);
    if (i < S) {
      const std::uint32_t k = find_dense(a, id);
      const std::uint32_t u = i + j - (B + popcount32(mb & below));
      if (k != no_index && !both) {
        const float d = rn_sqrt(distance_sq(eye, a.entities[k]));
        item = entry(float_bits(d), id, k, u);
        listed_enter = true;
      } else if (k != no_index) {
        const float d2 = distance_sq(eye, a.entities[k]);
        const bool near = tier_below(d2, r.near_limit, r.near_below_sq, r.near_above_sq);
        const bool mid = tier_below(d2, r.mid_limit, r.mid_below_sq, r.mid_above_sq);
        const std::uint32_t period = near ? 1u : mid ? mid_period : far_period;
        const std::uint32_t staleness = tick32 - sent[j];
        if (staleness >= period) {
          item = entry(u, k, float_bits(d2), staleness);
          listed_due = true;
        }
      }
      u_id[u] = id;
      u_tag[u] = tag_visible | (both ? tag_view | j : 0u) | (listed_enter || listed_due ? tag_listed : 0u);
    }
    const std::uint32_t me = g.ballot(listed_enter), md = g.ballot(listed_due);
    if (listed_enter) enter[E + popcount32(me & below)] = item;
    if (listed_due) due[D + popcount32(md & below)] = item;
    E += popcount32(me);
    D += popcount32(md);
    B += popcount32(mb);
  }
  for (std::uint32_t base = 0, leaves = 0; base < V; base += W) {
    const std::uint32_t j = base + lane;
    const std::uint32_t id = j < V ? view[j] : 0u;
    const std::uint32_t i = j < V ? lower_bound_u32(vis, S, id) : 0u;
    const bool leave = j < V && (i == S || vis[i] != id);
    const std::uint32_t ml = g.ballot(leave);
    if (leave) {
      const std::uint32_t u = i + leaves + popcount32(ml & below);
      u_id[u] = id;
      u_tag[u] = tag_view | j;
    }
    leaves += popcount32(ml);
  }
  const std::uint32_t L = V - B, U = S + V - B;
  g.sync();

  // The budget, in the closed form of net::frame_cost: leaves first, then enters, then updates.
  std::uint64_t est = r.header_cost + (has_self ? r.self_cost : 0);
  const std::uint64_t budget = r.byte_budget;
  const std::uint32_t n_l = budget >= est ? fit(L, (budget - est) / r.leave_cost) : 0;
  est += std::uint64_t{n_l} * r.leave_cost;
  const std::uint32_t n_e = budget >= est ? fit(E, (budget - est) / r.enter_cost) : 0;
  est += std::uint64_t{n_e} * r.enter_cost;
  const std::uint64_t room = est >= budget ? 0 : (budget - est) / r.update_cost;
  const bool all_fit = room >= D;
  const std::uint32_t n_u = all_fit ? D : static_cast<std::uint32_t>(room);

  // Ranks: enters by (distance, id); due updates, when the budget binds, by (priority, id) with
  // priority = -staleness / max(distance, 1). Short lists by counting (the rank in the entry);
  // longer ones sorted, and then each sent entry's rank goes into its union tag's index bits (a
  // due update's view index there is read only when it is not sent) and an unsent one's listed
  // bit is cleared: pass 2 finds a sent entry at its rank in the sorted list.
  const bool sort_enters = n_e > 0 && E > rank_by_sort_above;
  const bool sort_due = !all_fit && n_u > 0 && D > rank_by_sort_above;
  if (n_e > 0 && !sort_enters) {
    for (std::uint32_t e = lane; e < E; e += W) {
      const float ke = bits_float(enter[e].x);
      const std::uint32_t ie = enter[e].y;
      std::uint32_t rank = 0;
      for (std::uint32_t f = 0; f < E; ++f) rank += before(bits_float(enter[f].x), enter[f].y, ke, ie) ? 1u : 0u;
      enter[e].w = rank;
    }
  }
  if (!all_fit && n_u > 0) {
    for (std::uint32_t u = lane; u < D; u += W) {
      const float d = rn_sqrt(bits_float(due[u].z));
      const float p = rn_div(-u32_to_float(due[u].w), d > 1.0f ? d : 1.0f);
      due[u].z = float_bits(p);
      if (sort_due) due[u].w = u_id[due[u].x];  // the sort's id (the staleness is no longer needed)
    }
    g.sync();
    for (std::uint32_t u = lane; !sort_due && u < D; u += W) {
      const float pu = bits_float(due[u].z);
      const std::uint32_t iu = u_id[due[u].x];
      std::uint32_t rank = 0;
      for (std::uint32_t v = 0; v < D; ++v) rank += before(bits_float(due[v].z), u_id[due[v].x], pu, iu) ? 1u : 0u;
      due[u].w = rank;  // the staleness is no longer needed
    }
  }
  // A sorted list's entries into their union tags: the first `sent` by rank, the rest unlisted. The
  // union place is an enter's w and a due update's x (the other fields are the sort's key).
  const auto sort_into_tags = [&](scratch_entry* list, std::uint32_t count, std::uint32_t sent, bool due_list) {
    sort_entries(list, count, due_list, g);
    for (std::uint32_t e = lane; e < count; e += W) {
      const std::uint32_t u = due_list ? list[e].x : list[e].w;
      u_tag[u] = e < sent ? (u_tag[u] & ~tag_index) | e : u_tag[u] & ~tag_listed;
    }
  };
  if (sort_enters) sort_into_tags(enter, E, n_e, false);
  if (sort_due) sort_into_tags(due, D, n_u, true);
  g.sync();

  // The frame, in the canonical layout: its parts and size are known now (the digest's values
  // only after the second pass; they do not change its size).
  const interest::replication_frame_format& fmt = *a.format;
  const std::uint32_t DL = L - n_l, DE = E - n_e, DU = D - n_u;
  const bool digest = r.digest == 2 || (r.digest == 1 && reset);
  const std::uint32_t parts = (n_e != 0 ? interest::frame_part_enters : 0u) | (n_l != 0 ? interest::frame_part_leaves : 0u) |
                              (n_u != 0 ? interest::frame_part_updates : 0u) | (digest ? interest::frame_part_digest : 0u) |
                              (has_self ? interest::frame_part_self : 0u) |
                              ((DL | DE | DU) != 0 ? interest::frame_part_deferred : 0u) |
                              (reset ? interest::frame_part_reset : 0u);
  const interest::replication_frame_format::table& tl = fmt.tables[parts];
  const std::uint32_t bytes = static_cast<std::uint32_t>(frame_size(fmt, parts, n_e, n_l, n_u));
  const std::uint32_t off = g.first(lane == 0 ? reserve_bytes(a.cursor, bytes) : 0u);
  if (std::uint64_t{off} + bytes > a.record_capacity) {
    if (lane == 0) raise_flag(a.cursor + 1, flag_records_overflow);
    return;
  }
  std::uint8_t* const f = a.records + off;
  const std::uint32_t t = tl.at;
  // The vectors' places: the enters' offsets, the leaves, the updates, then the enters' shared
  // vtable and their tables (each followed by its empty name).
  const std::uint32_t enters_vec = t + tl.size;
  const std::uint32_t leaves_vec = enters_vec + (n_e != 0 ? 4 + 4 * n_e : 0);
  const std::uint32_t updates_vec = leaves_vec + (n_l != 0 ? 4 + 4 * n_l : 0);
  const std::uint32_t evt = updates_vec + (n_u != 0 ? 4 + 16 * n_u : 0);
  const std::uint32_t first_enter = evt + static_cast<std::uint32_t>(sizeof fmt.enter_vtable);
  const std::uint32_t enter_step = fmt.enter_table + fmt.enter_name;
  std::uint8_t* leaves_out = f + leaves_vec + 4;
  std::uint8_t* updates_out = f + updates_vec + 4;
  // Zeros first, as tick_update_writer::finish: the header's gaps and the tail padding (which
  // the vectors written below may partly cover).
  for (std::uint32_t b = 4 * lane; b < t + tl.size; b += 4 * W) put_u32(f + b, 0);
  if (lane == 0) {
    put_u32(f + bytes - 8, 0);
    put_u32(f + bytes - 4, 0);
  }
  g.sync();

  // Pass 2, over the union in id order: the frame's leaves, enters and updates, the new view
  // (kept entries and sent enters) with the last-sent ticks, and the digest hash's move. Each
  // entry's place among the leaves, the listed enters, the listed updates and the new view is the
  // count of those before it; an entry of the new view lands at or before its union place.
  std::uint64_t moved = 0;
  std::uint32_t li = 0, ei = 0, di = 0, w = 0;
  for (std::uint32_t base = 0; base < U; base += W) {
    const std::uint32_t u = base + lane;
    const std::uint32_t id = u < U ? u_id[u] : 0u, tag = u < U ? u_tag[u] : 0u;
    const bool in_view = (tag & tag_view) != 0, in_vis = (tag & tag_visible) != 0, listed = (tag & tag_listed) != 0;
    const bool leave = in_view && !in_vis, listed_enter = in_vis && !in_view && listed, listed_due = in_view && in_vis && listed;
    const std::uint32_t ml = g.ballot(leave), me = g.ballot(listed_enter), md = g.ballot(listed_due);
    bool keep = false;
    std::uint32_t last = 0;
    if (leave) {
      const std::uint32_t at = li + popcount32(ml & below);
      if (at < n_l) {
        put_u32(leaves_out + 4 * at, id);
        moved -= digest_mix(id);
      } else {
        keep = true;
        last = sent[tag & tag_index];
      }
    } else if (listed_enter) {
      // Sorted: its rank in the tag (listed: sent), the entry there; else the entry in list order.
      const scratch_entry en = sort_enters ? enter[tag & tag_index] : enter[ei + popcount32(me & below)];
      const std::uint32_t rank = sort_enters ? tag & tag_index : en.w;
      if (rank < n_e) {
        // Its offset slot and its table: id, position, velocity (the class, half extents and
        // kind are the caller's), the name's offset, then the empty name.
        const std::uint32_t slot = enters_vec + 4 + 4 * rank, at = first_enter + enter_step * rank;
        const interest::replication_entity& e = a.entities[en.z];
        put_u32(f + slot, at - slot);
        put_u32(f + at, at - evt);
        put_u32(f + at + 4, en.y);
        put_u32(f + at + 8, 0);
        put_f32(f + at + 12, e.x);
        put_f32(f + at + 16, e.y);
        put_f32(f + at + 20, e.z);
        put_f32(f + at + 24, e.vx);
        put_f32(f + at + 28, e.vy);
        put_f32(f + at + 32, e.vz);
        for (std::uint32_t b = 36; b < fmt.enter_table - 8; b += 4) put_u32(f + at + b, 0);
        put_u32(f + at + fmt.enter_table - 8, 8);  // the name's offset (the name follows the table)
        put_u32(f + at + fmt.enter_table - 4, 0);
        for (std::uint32_t b = 0; b < fmt.enter_name; b += 4) put_u32(f + at + fmt.enter_table + b, 0);
        moved += digest_mix(en.y);
        keep = true;
        last = tick32;
      }
    } else if (in_view) {  // kept: visible now and in the view
      keep = true;
      // Sorted and listed: sent, its rank in the tag (not the view index); else as listed.
      const bool ranked_in_tag = sort_due && listed_due;
      last = ranked_in_tag ? tick32 : sent[tag & tag_index];
      if (listed_due) {
        const std::uint32_t at = ranked_in_tag ? tag & tag_index : di + popcount32(md & below);
        const std::uint32_t pos = ranked_in_tag || all_fit ? at : (due[at].w < n_u ? due[at].w : no_index);
        if (pos != no_index) {
          const std::uint32_t* up = a.updates + 4 * std::size_t{due[at].y};
          std::uint8_t* o = updates_out + 16 * pos;
          put_u32(o, up[0]);
          put_u32(o + 4, up[1]);
          put_u32(o + 8, up[2]);
          put_u32(o + 12, up[3]);
          last = tick32;
        }
      }
    }
    const std::uint32_t mk = g.ballot(keep);
    g.sync();  // every lane has read its union entry before the new view overwrites the union
    if (keep) {
      const std::uint32_t at = w + popcount32(mk & below);
      u_id[at] = id;
      u_tag[at] = last;
    }
    li += popcount32(ml);
    ei += popcount32(me);
    di += popcount32(md);
    w += popcount32(mk);
  }
  const std::uint64_t hash = (reset ? 0 : a.hash[job.client]) + g.sum(moved);
  if (lane != 0) return;
  a.hash[job.client] = hash;

  // The header (tick_update_writer::finish): prefix, root offset, identifier, the envelope, the
  // tick_update's vtable and table, the vectors' lengths and offsets, the enters' vtable.
  put_u32(f, bytes - fmt.prefix_bytes);
  put_u32(f + 4, 16);
  for (int b = 0; b < 4; ++b) f[8 + b] = fmt.identifier[b];
  put_u16(f + 12, 8);
  put_u16(f + 14, 12);
  put_u16(f + 16, 8);
  put_u16(f + 18, 4);
  put_u32(f + 20, 8);
  put_u32(f + 24, t - 24);
  f[28] = static_cast<std::uint8_t>(fmt.message_type);
  put_u16(f + 32, tl.vtable);
  put_u16(f + 34, tl.size);
  for (std::uint32_t k = 0; 4 + 2 * k < tl.vtable; ++k) put_u16(f + 36 + 2 * k, tl.field[k]);
  put_u32(f + t, t - 32);
  put_u64(f + t + tl.field[0], r.tick);
  put_u64(f + t + tl.field[1], r.server_time_us);
  put_u32(f + t + tl.field[2], job.last_input);
  if (digest) {
    put_u64(f + t + tl.field[6], r.tick);
    put_u64(f + t + tl.field[6] + 8, hash);
    put_u32(f + t + tl.field[6] + 16, w);
  }
  if (has_self) {
    put_f32(f + t + tl.field[8], eye[0]);
    put_f32(f + t + tl.field[8] + 4, eye[1]);
    put_f32(f + t + tl.field[8] + 8, eye[2]);
  }
  if ((parts & interest::frame_part_deferred) != 0) {
    put_u32(f + t + tl.field[9], DE);
    put_u32(f + t + tl.field[9] + 4, DL);
    put_u32(f + t + tl.field[9] + 8, DU);
  }
  if (reset) f[t + tl.field[7]] = 1;
  if (n_e != 0) {
    put_u32(f + t + tl.field[3], enters_vec - (t + tl.field[3]));
    put_u32(f + enters_vec, n_e);
    for (int k = 0; k < 10; ++k) put_u16(f + evt + 2 * k, fmt.enter_vtable[k]);
  }
  if (n_l != 0) {
    put_u32(f + t + tl.field[4], leaves_vec - (t + tl.field[4]));
    put_u32(f + leaves_vec, n_l);
  }
  if (n_u != 0) {
    put_u32(f + t + tl.field[5], updates_vec - (t + tl.field[5]));
    put_u32(f + updates_vec, n_u);
  }

  interest::replication_result res;
  res.record_off = off;
  res.frame_size = bytes;
  res.enters_at = n_e != 0 ? first_enter : 0;
  res.leaves = n_l;
  res.enters = n_e;
  res.updates = n_u;
  res.deferred_leaves = DL;
  res.deferred_enters = DE;
  res.deferred_updates = DU;
  res.view_size = w;
  res.hash = hash;
  res.eye[0] = eye[0];
  res.eye[1] = eye[1];
  res.eye[2] = eye[2];
  res.flags = has_self ? interest::result_has_self : 0u;
  a.results[job_index] = res;
}

/// Job job_index decided by one lane (the host's emulation of the engine).
inline void decide_job(const run_args& a, std::uint32_t job_index) {
  serial_lanes one;
  decide_job(a, job_index, one);
}

}  // namespace zone::gpu::detail::rep
