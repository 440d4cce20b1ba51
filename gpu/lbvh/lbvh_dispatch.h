// Dispatch of the GPU LBVH finder: owns the streams, events and the device and pinned buffers
// (sized once, grown only when a call needs more), uploads, builds the hierarchy, runs the
// counting and writing traversals and the brute pass, copies the pairs out. Host-side only; the
// kernels live in lbvh_kernels.cuh. Not thread-safe: one call at a time.
#pragma once

#include <cuda_runtime.h>

#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>

#include "gpu/common/finder_input.h"
#include "gpu/common/gpu_buffers.h"
#include "gpu/lbvh.h"
#include "interest/interest.h"
#include "interest/thread_pool.h"
#include "lbvh_shared.h"

namespace zone::gpu::detail::lbvh {

/// Grow-only device and page-locked host arrays (gpu_buffers.h; shared with the other engines).
template <class T>
using device_array = mem::device_array<T>;
template <class T>
using pinned_array = mem::pinned_array<T>;

/// The engine behind the LBVH finder.
class lbvh_engine {
 public:
  explicit lbvh_engine(const lbvh_options& options);
  ~lbvh_engine();
  lbvh_engine(const lbvh_engine&) = delete;
  lbvh_engine& operator=(const lbvh_engine&) = delete;

  /// Finds every qualifying pair of a set of at least 2 boxes into the pinned result buffer
  /// (result()) and returns their number. With `validate`, the boxes are checked
  /// (interest::validate's rule) while they are packed for the upload; an invalid set returns
  /// nothing. Throws std::runtime_error on a CUDA error, std::length_error past the 32-bit limits.
  std::optional<std::uint64_t> run(const interest::box_set& boxes, interest::finder_stats& stats, bool validate);

  [[nodiscard]] const interest::id_pair* result() const { return h_result_.get(); }
  [[nodiscard]] const lbvh_report& report() const { return report_; }
  [[nodiscard]] interest::thread_pool* pool() const { return pool_; }

 private:
  void grow_temp(std::size_t bytes);

  lbvh_options opt_;
  std::unique_ptr<interest::thread_pool> own_pool_;
  interest::thread_pool* pool_ = nullptr;
  cudaStream_t main_ = nullptr, copy_ = nullptr;
  cudaEvent_t ev_start_ = nullptr, ev_in_ = nullptr, ev_sort_begin_ = nullptr, ev_sort_end_ = nullptr,
              ev_built_ = nullptr, ev_counted_ = nullptr, ev_fill_begin_ = nullptr, ev_fill_end_ = nullptr,
              ev_copy_begin_ = nullptr, ev_copy_end_ = nullptr;
  static constexpr int max_batch_events = 18;
  cudaEvent_t ev_batch_[max_batch_events]{};

  device_boxes boxes_;  // the input boxes and their staging memory
  device_array<scene> d_scene_;
  device_array<std::uint32_t> d_keys_, d_keys_sorted_, d_ids_, d_ids_sorted_;
  device_array<float4> d_leaf_lo_, d_leaf_hi_;
  device_array<node> d_nodes_;
  device_array<uint4> d_node_bits_;
  device_array<std::uint32_t> d_parent_, d_flags_;
  device_array<std::uint32_t> d_counts_;
  device_array<std::uint8_t> d_overflowed_;
  device_array<std::uint64_t> d_pos_;
  device_array<std::uint32_t> d_ov_list_;
  device_array<readback> d_readback_;
  pinned_array<readback> h_readback_;
  device_array<std::uint32_t> d_item_counts_;
  device_array<std::uint64_t> d_item_pos_;
  pinned_array<std::uint64_t> h_brute_total_;
  device_array<std::uint32_t> d_pairs_;  // 2 x u32 per pair
  pinned_array<interest::id_pair> h_result_;
  device_array<unsigned char> d_temp_;

  lbvh_report report_{};
};

}  // namespace zone::gpu::detail::lbvh
