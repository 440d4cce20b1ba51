// The input side of both GPU finders' engines (pbig_dispatch.cpp, lbvh_dispatch.cpp; host code,
// header-only): the thread pool they pack and copy with, and the DataIn step, the staged,
// validated upload of a box set into the device arrays their kernels read (box_arrays.h).
#pragma once

#include <cuda_runtime.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <memory>

#include "box_arrays.h"
#include "cuda_check.h"
#include "gpu_buffers.h"
#include "interest/interest.h"
#include "interest/thread_pool.h"

namespace zone::gpu::detail {

/// The pool an engine's host work runs on: `given`, or, when that is null, a pool of every
/// hardware thread made into `own`.
inline interest::thread_pool* pool_or_own(interest::thread_pool* given, std::unique_ptr<interest::thread_pool>& own) {
  if (given != nullptr) return given;
  own = std::make_unique<interest::thread_pool>(0);
  return own.get();
}

/// Queues on `stream` the copy of `boxes` (n boxes) to the device: 6 arrays of n floats at
/// `d_coord` (lo x, y, z, then hi x, y, z) and 2 arrays of n bits at `d_bits` (category, then mask),
/// through `h_stage`, pinned host memory of at least 32 n bytes. The boxes go in parts of about
/// `part_boxes` (at most `max_parts` parts); each part is packed into the staging memory by `pool`'s
/// threads (by the caller alone for a part under 1 MiB) while the previous part's copies run.
/// With `check`, packing also applies interest::validate's rule to every coordinate (lo <= hi,
/// false for NaN, both finite). Returns false at the first part holding an invalid box: nothing of
/// that part is queued, and the caller synchronises `stream` before it reuses `h_stage`.
inline bool staged_upload(const interest::box_set& boxes, bool check, float* d_coord, std::uint32_t* d_bits,
                          unsigned char* h_stage, interest::thread_pool* pool, cudaStream_t stream,
                          std::size_t part_boxes, std::size_t max_parts) {
  const std::size_t n = boxes.size();
  const float* lo[3] = {boxes.lo_x.data(), boxes.lo_y.data(), boxes.lo_z.data()};
  const float* hi[3] = {boxes.hi_x.data(), boxes.hi_y.data(), boxes.hi_z.data()};
  const std::uint32_t* bits[2] = {boxes.category.data(), boxes.mask.data()};
  float* stage_f = reinterpret_cast<float*>(h_stage);                          // 6 arrays of n floats
  std::uint32_t* stage_u = reinterpret_cast<std::uint32_t*>(stage_f + 6 * n);  // then 2 of n bits
  const std::size_t parts = std::clamp<std::size_t>((n + part_boxes - 1) / part_boxes, 1, max_parts);
  const std::size_t sub = std::max<std::size_t>(1, (pool->size() + 3) / 4);
  std::atomic<bool> ok{true};
  for (std::size_t p = 0; p < parts; ++p) {
    const std::size_t b = n * p / parts, e = n * (p + 1) / parts;
    const std::size_t len = e - b;
    // Tasks: (axis d: copy lo_d and hi_d, checking them when asked) or (category and mask).
    interest::run_tasks(len * 32 >= (std::size_t{1} << 20) ? pool : nullptr, 4 * sub, [&](std::size_t t) {
      const std::size_t a = t % 4, k = t / 4;
      const std::size_t sb = b + len * k / sub, se = b + len * (k + 1) / sub;
      if (se <= sb) return;
      if (a == 3) {
        for (int q = 0; q < 2; ++q) std::memcpy(stage_u + q * n + sb, bits[q] + sb, (se - sb) * 4);
        return;
      }
      float* dst_lo = stage_f + a * n;
      float* dst_hi = stage_f + (3 + a) * n;
      if (!check) {
        std::memcpy(dst_lo + sb, lo[a] + sb, (se - sb) * 4);
        std::memcpy(dst_hi + sb, hi[a] + sb, (se - sb) * 4);
        return;
      }
      // Copy and check in one pass: interest::validate's rule on this axis.
      const float* src_lo = lo[a];
      const float* src_hi = hi[a];
      bool good = true;
      for (std::size_t i = sb; i < se; ++i) {
        const float l = src_lo[i], h = src_hi[i];
        dst_lo[i] = l;
        dst_hi[i] = h;
        good &= (l <= h) & std::isfinite(l) & std::isfinite(h);
      }
      if (!good) ok = false;
    });
    if (!ok) return false;
    for (int a = 0; a < 6; ++a) {
      CUDA_CHECK(cudaMemcpyAsync(d_coord + a * n + b, stage_f + a * n + b, len * 4, cudaMemcpyHostToDevice, stream));
    }
    for (int q = 0; q < 2; ++q) {
      CUDA_CHECK(cudaMemcpyAsync(d_bits + q * n + b, stage_u + q * n + b, len * 4, cudaMemcpyHostToDevice, stream));
    }
  }
  return true;
}

/// A finder call's boxes on the device, grow-only: 6 arrays of n floats (lo x, y, z, then hi x, y,
/// z) and 2 arrays of n bits (category, then mask), with the pinned staging memory of
/// staged_upload. Contents are lost when an array grows.
class device_boxes {
 public:
  /// Room for n boxes on the device (not the staging memory).
  void reserve(std::size_t n) {
    coord_.reserve(6 * n);
    bits_.reserve(2 * n);
  }
  /// reserve(n), then staged_upload of `boxes` on `stream` (see there), then `ready` recorded on
  /// `stream`. False at an invalid box: `stream` is synchronised first, so the staging memory is
  /// free again.
  bool upload_staged(const interest::box_set& boxes, bool check, interest::thread_pool* pool, cudaStream_t stream,
                     cudaEvent_t ready, std::size_t part_boxes, std::size_t max_parts) {
    const std::size_t n = boxes.size();
    reserve(n);
    stage_.reserve(32 * n);
    const bool ok = staged_upload(boxes, check, coord(), bits(), stage_.get(), pool, stream, part_boxes, max_parts);
    CUDA_CHECK(cudaEventRecord(ready, stream));
    if (!ok) CUDA_CHECK(cudaStreamSynchronize(stream));
    return ok;
  }
  /// The arrays of the first n boxes (n as at the last reserve or upload).
  [[nodiscard]] box_arrays arrays(std::size_t n) const {
    box_arrays b{};
    for (int d = 0; d < 3; ++d) {
      b.lo[d] = coord_.get() + d * n;
      b.hi[d] = coord_.get() + (3 + d) * n;
    }
    b.category = bits_.get();
    b.mask = bits_.get() + n;
    return b;
  }
  [[nodiscard]] float* coord() const { return coord_.get(); }
  [[nodiscard]] std::uint32_t* bits() const { return bits_.get(); }

 private:
  mem::device_array<float> coord_;
  mem::device_array<std::uint32_t> bits_;
  mem::pinned_array<unsigned char> stage_;
};

}  // namespace zone::gpu::detail
