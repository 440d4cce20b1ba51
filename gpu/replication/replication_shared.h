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

/// A scratch entry: a due update {view index, dense, d2 (then priority), staleness (then rank)} or
/// an enter candidate {distance, id, dense, rank}.
struct alignas(16) scratch_entry {
  std::uint32_t x, y, z, w;
};

/// Everything a run reads and writes (device pointers on the GPU).
struct run_args {
  interest::replication_rules rules;
  const interest::replication_entity* entities;
  std::uint32_t entity_count;
  std::uint32_t* updates;  // by dense index: 4 words, the entity's 16-byte wire update (quantize_entity)
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

/// At most every leave (4 bytes), enter (8) and update (16) of a job with a view of v entries and a
/// visible set of s, and never more bytes than the budget (each entry costs at least its record's).
ZONE_REP_HD std::uint64_t record_bound(std::uint64_t v, std::uint64_t s, std::uint64_t budget) {
  const std::uint64_t most = 20 * v + 8 * s;
  return most < budget ? most : budget;
}

/// Where each client's new view goes (staged sets: the sizes are on the host): a job's client gets
/// room for its view plus its visible set (the new view is a subset of their union), every other
/// client for its view as it is. Returns the total and sets `record_cap` to the records' bound.
inline std::uint64_t plan_staged(const interest::replication_job* jobs, const client_slot* clients,
                                 std::size_t client_count, std::uint64_t byte_budget, std::uint32_t* new_off,
                                 std::uint64_t& record_cap) {
  std::uint64_t total = 0;
  record_cap = 0;
  for (std::size_t c = 0; c < client_count; ++c) {
    new_off[c] = static_cast<std::uint32_t>(total);
    total += clients[c].old_len;
    if (clients[c].job != 0) {
      const auto& j = jobs[clients[c].job - 1];
      total += j.visible_len;
      record_cap += record_bound((j.flags & interest::job_reset) != 0 ? 0 : clients[c].old_len, j.visible_len, byte_budget);
    }
    if (total > 0xffffffffu) throw std::invalid_argument("replication engine: more than 2^32 view entries");
  }
  new_off[client_count] = static_cast<std::uint32_t>(total);
  return total;
}

inline constexpr std::uint32_t no_index = 0xffffffffu;

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
__device__ __forceinline__ void flag_overflow(std::uint32_t* flag) { atomicExch(flag, 1u); }
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
inline void flag_overflow(std::uint32_t* flag) { *flag = 1; }
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

ZONE_REP_HD void put_u32(std::uint8_t* p, std::uint32_t v) { std::memcpy(p, &v, 4); }

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
  record = record_bound((job.flags & interest::job_reset) != 0 ? 0 : s.old_len, len, a.rules.byte_budget);
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

/// Job t: its frame's decisions, its record, its client's new view and hash, its result.
ZONE_REP_HD void decide_job(const run_args& a, std::uint32_t t) {
  const interest::replication_job job = a.jobs[t];
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
  const std::uint32_t tick32 = static_cast<std::uint32_t>(r.tick);
  const std::uint32_t mid_period = r.mid_period > 1 ? r.mid_period : 1u;
  const std::uint32_t far_period = r.far_period > 1 ? r.far_period : 1u;

  // Pass 1: the merge. Leaves are counted; enters (in the store) and due updates are listed in
  // walk order.
  std::uint32_t L = 0, E = 0, D = 0;
  {
    std::uint32_t i = 0, j = 0;
    while (i < S || j < V) {
      if (j < V && (i == S || view[j] < vis[i])) {
        ++L;
        ++j;
      } else if (j == V || vis[i] < view[j]) {
        const std::uint32_t k = find_dense(a, vis[i]);
        if (k != no_index) {
          const float d = rn_sqrt(distance_sq(eye, a.entities[k]));
          enter[E++] = entry(float_bits(d), vis[i], k, 0);
        }
        ++i;
      } else {
        const std::uint32_t k = find_dense(a, view[j]);
        if (k != no_index) {
          const float d2 = distance_sq(eye, a.entities[k]);
          const bool near = tier_below(d2, r.near_limit, r.near_below_sq, r.near_above_sq);
          const bool mid = tier_below(d2, r.mid_limit, r.mid_below_sq, r.mid_above_sq);
          const std::uint32_t period = near ? 1u : mid ? mid_period : far_period;
          const std::uint32_t staleness = tick32 - sent[j];
          if (staleness >= period) due[D++] = entry(j, k, float_bits(d2), staleness);
        }
        ++i;
        ++j;
      }
    }
  }

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
  // priority = -staleness / max(distance, 1). By counting: the lists are a client's, short.
  if (n_e > 0) {
    for (std::uint32_t e = 0; e < E; ++e) {
      const float ke = bits_float(enter[e].x);
      const std::uint32_t ie = enter[e].y;
      std::uint32_t rank = 0;
      for (std::uint32_t f = 0; f < E; ++f) rank += before(bits_float(enter[f].x), enter[f].y, ke, ie) ? 1u : 0u;
      enter[e].w = rank;
    }
  }
  if (!all_fit && n_u > 0) {
    for (std::uint32_t u = 0; u < D; ++u) {
      const float d = rn_sqrt(bits_float(due[u].z));
      const float p = rn_div(-u32_to_float(due[u].w), d > 1.0f ? d : 1.0f);
      due[u].z = float_bits(p);
    }
    for (std::uint32_t u = 0; u < D; ++u) {
      const float pu = bits_float(due[u].z);
      const std::uint32_t iu = view[due[u].x];
      std::uint32_t rank = 0;
      for (std::uint32_t v = 0; v < D; ++v) rank += before(bits_float(due[v].z), view[due[v].x], pu, iu) ? 1u : 0u;
      due[u].w = rank;  // the staleness is no longer needed
    }
  }

  // The record: leaves, enters, updates.
  const std::uint32_t bytes = 4 * n_l + 8 * n_e + 16 * n_u;
  const std::uint32_t off = bytes == 0 ? 0 : reserve_bytes(a.cursor, bytes);
  if (std::uint64_t{off} + bytes > a.record_capacity) {
    flag_overflow(a.cursor + 1);
    return;
  }
  std::uint8_t* leaves_out = a.records + off;
  std::uint8_t* enters_out = leaves_out + 4 * n_l;
  std::uint8_t* updates_out = enters_out + 8 * n_e;

  // Pass 2: the same merge writes the record and the new view (kept entries and sent enters, in
  // id order) with the last-sent ticks, and moves the digest hash.
  std::uint64_t hash = reset ? 0 : a.hash[job.client];
  std::uint32_t* new_id = a.new_id + to;
  std::uint32_t* new_sent = a.new_sent + to;
  std::uint32_t w = 0;
  {
    std::uint32_t i = 0, j = 0, li = 0, di = 0, ei = 0;
    while (i < S || j < V) {
      if (j < V && (i == S || view[j] < vis[i])) {
        if (li < n_l) {
          put_u32(leaves_out + 4 * li, view[j]);
          hash -= digest_mix(view[j]);
        } else {
          new_id[w] = view[j];
          new_sent[w++] = sent[j];
        }
        ++li;
        ++j;
      } else if (j == V || vis[i] < view[j]) {
        if (ei < E && enter[ei].y == vis[i]) {
          const scratch_entry en = enter[ei++];
          if (en.w < n_e) {
            put_u32(enters_out + 8 * en.w, en.z);
            put_u32(enters_out + 8 * en.w + 4, en.y);
            hash += digest_mix(en.y);
            new_id[w] = en.y;
            new_sent[w++] = tick32;
          }
        }
        ++i;
      } else {
        std::uint32_t last = sent[j];
        if (di < D && due[di].x == j) {
          const std::uint32_t pos = all_fit ? di : (due[di].w < n_u ? due[di].w : no_index);
          if (pos != no_index) {
            std::memcpy(updates_out + 16 * pos, a.updates + 4 * std::size_t{due[di].y}, 16);
            last = tick32;
          }
          ++di;
        }
        new_id[w] = view[j];
        new_sent[w++] = last;
        ++i;
        ++j;
      }
    }
  }
  a.hash[job.client] = hash;
  interest::replication_result res;
  res.record_off = off;
  res.leaves = n_l;
  res.enters = n_e;
  res.updates = n_u;
  res.deferred_leaves = L - n_l;
  res.deferred_enters = E - n_e;
  res.deferred_updates = D - n_u;
  res.view_size = w;
  res.hash = hash;
  res.eye[0] = eye[0];
  res.eye[1] = eye[1];
  res.eye[2] = eye[2];
  res.flags = has_self ? interest::result_has_self : 0u;
  a.results[t] = res;
}

}  // namespace zone::gpu::detail::rep
