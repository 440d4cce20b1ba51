// Dispatch of the GPU PBIG finder: owns the streams, events and the device and pinned buffers
// (sized once, grown only when a call needs more), plans, maps, schedules and runs the checking
// pipeline. Host-side only; the kernels live in pbig_kernels.cuh. Not thread-safe: one call at a time.
#pragma once

#include <cuda_runtime.h>

#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "gpu/common/finder_input.h"
#include "gpu/common/gpu_buffers.h"
#include "gpu/pbig.h"
#include "interest/interest.h"
#include "interest/thread_pool.h"
#include "pbig_shared.h"

namespace zone::gpu::detail {

/// Grow-only device and page-locked host arrays (gpu_buffers.h; shared with the other engines).
template <class T>
using device_buffer = mem::device_array<T>;
template <class T>
using pinned_buffer = mem::pinned_array<T>;

/// One slot of the double-buffered pipeline: a device and a pinned host output buffer, the
/// batch's per-tile index (device and host), the batch's byte cursor, its stream and events.
struct pipeline_slot {
  cudaStream_t stream = nullptr;
  device_buffer<unsigned char> d_out;
  pinned_buffer<unsigned char> h_out;
  device_buffer<std::uint64_t> d_tile_off;
  device_buffer<std::uint32_t> d_tile_pairs;
  pinned_buffer<std::uint64_t> h_tile_off;
  pinned_buffer<std::uint32_t> h_tile_pairs;
  device_buffer<unsigned long long> d_cursor;
  pinned_buffer<unsigned long long> h_cursor;
  // Direct output: per-tile pair positions (scan), the batch's pairs in tile order, their count.
  device_buffer<std::uint64_t> d_tile_pos;
  device_buffer<std::uint32_t> d_direct;
  device_buffer<unsigned char> d_temp;  // the slot's own scan scratch (the two streams overlap)
  pinned_buffer<std::uint64_t> h_total;
  cudaEvent_t kernel_begin = nullptr, kernel_end = nullptr, copy_begin = nullptr, copy_end = nullptr;
  cudaEvent_t totals_ready = nullptr;  // direct output: h_cursor and h_total are readable
  bool copy_pending = false;           // direct output: a copy whose time is not yet accounted
  std::uint64_t prefetched_pairs = 0;  // direct output: pairs copied before the batch's total was known
  bool overcopied = false;             // direct output: the prefetch copied past the batch's pairs
  std::uint64_t capacity = 0;    // usable bytes of d_out / h_out
  std::uint64_t prefetched = 0;  // bytes of the current batch already copied
  bool remainder_pending = false;
};

/// The engine behind the pbig finder.
class pbig_engine {
 public:
  explicit pbig_engine(const pbig_options& options);
  ~pbig_engine();
  pbig_engine(const pbig_engine&) = delete;
  pbig_engine& operator=(const pbig_engine&) = delete;

  /// Finds every qualifying pair of a validated set with at least 2 boxes into out[0, count) and
  /// returns count. `out`'s previous contents are overwritten; it only grows (value-initialising
  /// the new part). With keep_size it is not shrunk to count afterwards (a reused buffer then
  /// never pays the value-initialisation again). Throws std::runtime_error on a CUDA error,
  /// std::length_error past the 32-bit limits of the cell lists.
  /// With `validate`, the boxes are checked (interest::validate's rule) while they are packed for
  /// the upload; an invalid set returns nothing, with no pair found.
  std::optional<std::uint64_t> run(const interest::box_set& boxes, interest::pair_list& out,
                                   interest::finder_stats& stats, bool keep_size, bool validate);

  [[nodiscard]] const pbig_report& report() const { return report_; }
  /// The threads that pack the upload and decode the output.
  [[nodiscard]] interest::thread_pool* pool() const { return pool_; }
  /// With pbig_options::direct_output: the pairs of the last call, in pinned host memory.
  [[nodiscard]] const interest::id_pair* direct_data() const { return h_result_.get(); }

 private:
  struct batch {
    std::uint32_t item_first, item_last, tile_first, tile_last;
    std::int32_t stage = -1;  ///< the overlapped upload's stage whose lists it checks; -1: the one-shot grid
  };
  /// One chunk of the overlapped upload: its per-cell lists and its stage's work items.
  struct overlap_stage {
    device_buffer<cell_prefix> prefix;  // per cell: the chunk's first entry; the stage's first work item and tile
    device_buffer<std::uint32_t> entries;  // the chunk's ids, by cell, sorted in each cell
    device_buffer<std::uint32_t> items;    // the stage's work items (cell per row segment)
    map_readback rb{};                      // the stage's read-back (totals, batches)
  };
  /// The grid sizes the map and check steps are queued with: exact (read back) or capacities.
  struct grid_sizes {
    std::uint32_t cells, entries, items, tiles;
  };
  enum class queue_result { done, invalid, outgrown };
  bool upload(const interest::box_set& boxes, bool check);
  /// True when every box of [begin, end) has boxes.category[0] and boxes.mask[0] (checked on the
  /// pool, early exit).
  [[nodiscard]] bool uniform_classes(const interest::box_set& boxes, std::size_t begin, std::size_t end) const;
  /// Queues the bounds and planning kernels for n boxes, bounds and sample from the first
  /// sample_n of them: the plan is in d_plan_ (device memory).
  void queue_plan(std::uint32_t n, std::uint32_t sample_n);
  /// Read-back sizing, synchronisation 1: the plan into plan_. False when the device found an
  /// invalid box (pinned input validated there).
  bool read_plan();
  /// Queues count, pack, scans, reduce and the batch-planning kernel (fills d_readback_ and
  /// checks the grid against `cap`).
  void queue_count(std::uint32_t n, const grid_capacity& cap);
  /// Queues map, per-cell sort, gather and work items for `size` (an upper bound: the kernels
  /// stop at d_readback_'s sizes). small_cells: the one-kernel sort (else CUB's, exact sizes only).
  void queue_map(std::uint32_t n, const grid_sizes& size, bool small_cells);
  /// Read-back sizing of the map: queue_count, synchronisation 2 (totals into rb_), queue_map.
  void map_boxes(std::uint32_t n);
  /// Read-back sizing's capacity (queue_count's and each stage's): the plan's cells and the 32-bit
  /// limits of the cell lists.
  [[nodiscard]] grid_capacity readback_limits() const;
  /// Refuses a read-back (of map_boxes or of a stage) past the 32-bit limits of the cell lists
  /// (std::length_error: prefixes would wrap) or that the device did not map (std::logic_error);
  /// `what` names the grid in the message ("the grid", "stage 2").
  static void check_readback(const map_readback& rb, const std::string& what);
  /// The whole call as one queue sized by next_ (docs/gpu.md, "Single queue"); `pairs` when done.
  queue_result run_single_queue(std::uint32_t n, std::uint64_t& pairs);
  /// Keeps this call's figures (with a margin) as the next call's single-queue capacity.
  void remember_sizes();
  // The overlapped upload (pbig_overlap.cpp; docs/gpu.md, "Overlapped upload").
  /// Its chunk count for this call, or 0 when the one-shot path runs (pbig_tuning.h's rule: the
  /// previous call's output against its input, on a set of about this size).
  [[nodiscard]] std::uint32_t overlap_chunks(const interest::box_set& boxes) const;
  /// Waits for `done` (recorded on this call's streams) at most tuning::overlap_wait_limit_s;
  /// past it logs and throws std::runtime_error naming `what` (a kernel that does not end).
  void wait_bounded(cudaEvent_t done, const char* what, std::uint32_t stage, std::uint32_t n) const;
  /// The whole call in k chunks into h_result_: false when the device found an invalid box.
  bool run_overlapped(const interest::box_set& boxes, std::uint32_t n, std::uint32_t k, bool validate,
                      std::uint64_t& pairs);
  /// Queues chunk j's upload on upload_ (classes filled when they are box 0's), then ev_chunk_[j].
  void upload_chunk(const interest::box_set& boxes, std::uint32_t j, std::uint32_t first, std::uint32_t count);
  /// Queues stage j's validation (when asked), count, prefixes, totals, batch plan and read-back
  /// on the stage stream (after chunk j has landed), then ev_stage_counted_[j].
  void queue_stage_count(std::uint32_t n, std::uint32_t j, std::uint32_t first, std::uint32_t count, bool check);
  /// Queues stage j's map, per-cell sort and work items (stage stream) after its read-back;
  /// ev_mapped_[j] after.
  void queue_stage_map(std::uint32_t n, std::uint32_t j, std::uint32_t first, std::uint32_t count);
  /// Lists 0..count-1 of the stages.
  [[nodiscard]] stage_lists lists_of(std::uint32_t count) const;
  /// The stage width W of this call's stages (stage_layout): pbig_options::overlap_stage_width,
  /// else from the plan's boxes per cell and the chunk count k (tuning::stage_width_spread).
  [[nodiscard]] std::uint32_t stage_width(std::uint32_t n, std::uint32_t k) const;
  std::uint64_t check_batches(interest::pair_list& out);
  /// The checking kernel's arguments for batch b on slot s (its buffers, cursor and capacity).
  [[nodiscard]] check_args batch_args(const batch& b, const pipeline_slot& s) const;
  /// The non-empty batches of a map read-back's batch plan, in order (of stage `stage`, or -1).
  [[nodiscard]] static std::vector<batch> planned_batches(const map_readback& rb, std::int32_t stage = -1);
  void launch(const batch& b, pipeline_slot& s);
  void prefetch(const batch& b, pipeline_slot& s, std::uint64_t bytes);
  void finish(const batch& b, pipeline_slot& s);
  std::uint64_t decode(const batch& b, pipeline_slot& s, interest::pair_list& out, std::uint64_t base);
  std::uint64_t large_pairs(std::uint32_t n, interest::pair_list& out, std::uint64_t base);
  void large_count_pass(std::uint32_t n);  // queues the count; total in *h_large_total_ after a sync
  void large_write_pass(std::uint32_t n, std::uint64_t total, void* host_dst);
  std::uint64_t check_direct(std::uint32_t n);
  void launch_direct(const batch& b, pipeline_slot& s, std::uint64_t prefetch_pairs = 0);
  std::uint64_t finish_direct(const batch& b, pipeline_slot& s, std::uint64_t base, std::size_t done, std::size_t count);
  /// Direct output: waits for slot s's pending copy and keeps its span (copy_spans_).
  void account_copy(pipeline_slot& s);
  /// The union of the kept copy spans in ms (overlapping spans counted once); clears them.
  double copy_spans_ms();
  void ensure_result(std::uint64_t needed, std::uint64_t keep);
  void grow_temp(std::size_t bytes);

  pbig_options opt_;
  std::unique_ptr<interest::thread_pool> own_pool_;
  interest::thread_pool* pool_ = nullptr;
  cudaStream_t main_ = nullptr;  // = slot_[0].stream
  pipeline_slot slot_[2];
  cudaEvent_t ev_start_ = nullptr, ev_in_ = nullptr, ev_plan_ = nullptr, ev_counted_ = nullptr, ev_scattered_ = nullptr,
              ev_sorted_ = nullptr, ev_map_ = nullptr, ev_sched_ = nullptr,
              ev_entries_begin_ = nullptr, ev_entries_ = nullptr;

  // input and planning
  device_boxes boxes_;  // the input boxes and their staging memory
  device_buffer<bounds_dev> d_bounds_;
  device_buffer<plan_state> d_state_;
  device_buffer<grid_plan_dev> d_plan_;
  pinned_buffer<grid_plan_dev> h_plan_;
  pinned_buffer<bounds_dev> h_bounds_;
  bool validate_on_device_ = false;  // this call's boxes came straight from pinned memory
  grid_plan_dev plan_{};
  // mapping
  device_buffer<std::uint32_t> d_counts_;  // per-cell counts, the large-box counter, per-cell cursors
  device_buffer<cell_prefix> d_prefix_;
  device_buffer<std::uint8_t> d_is_large_;
  device_buffer<std::uint32_t> d_large_;
  device_buffer<map_readback> d_readback_;
  pinned_buffer<map_readback> h_readback_;
  map_readback rb_{};
  device_buffer<std::uint32_t> d_entries_unsorted_, d_entries_, d_items_;
  device_buffer<float4> d_box_lo_, d_box_hi_;        // boxes in id order, 2 x 16 bytes
  device_buffer<float4> d_packed_lo_, d_packed_hi_;  // the box array: boxes in cell order
  bool indirect_ = false;  // this call's checks read d_box_lo_/hi_ through the ids (no gather)
  pinned_buffer<std::uint32_t> h_entries_;
  device_buffer<unsigned char> d_temp_;
  // large boxes
  device_buffer<std::uint32_t> d_large_counts_, d_large_offsets_, d_large_pairs_;
  pinned_buffer<std::uint32_t> h_large_pairs_, h_large_total_;
  // direct output: every pair of the call, in pinned host memory (kept across calls)
  pinned_buffer<interest::id_pair> h_result_;
  std::uint64_t last_first_batch_pairs_ = 0;  // batch 0's pairs in the last call: its prefetch size
  // single queue: the capacity the next call is queued with (the last call's figures + margin)
  struct queue_capacity {
    bool valid = false;  // the last call was small enough: one batch, no large boxes, small cells
    grid_sizes sizes{};
    std::uint64_t pairs = 0;  // batch 0's copy
  } next_;
  // decode scratch
  std::vector<std::uint64_t> tile_pos_;
  std::vector<std::uint32_t> task_tiles_;
  bool entries_ready_ = false;

  // overlapped upload
  cudaStream_t upload_ = nullptr;  // the chunks' host-to-device copies
  /// The stages' count, read-back and map, in stage order: off the slots' streams, so a stage's
  /// count waits for its chunk only, not behind the earlier stages' pair copies.
  cudaStream_t stage_ = nullptr;
  cudaEvent_t ev_chunk_[max_overlap_chunks] = {};          // chunk j is on the device
  cudaEvent_t ev_staged_[max_overlap_chunks] = {};         // stage j's MAP begins (stage stream)
  cudaEvent_t ev_stage_counted_[max_overlap_chunks] = {};  // stage j's read-back is in host memory
  cudaEvent_t ev_map_begin_[max_overlap_chunks] = {};      // stage j's map is queued from here
  cudaEvent_t ev_mapped_[max_overlap_chunks] = {};         // stage j's lists and work items are ready
  overlap_stage stages_[max_overlap_chunks];
  std::uint32_t stage_width_ = 64;          // this call's stage width (stage_width())
  device_buffer<map_readback> d_stage_rb_;  // per stage (the stage's checks read theirs while later stages map)
  pinned_buffer<map_readback> h_stage_rb_;
  device_buffer<bounds_dev> d_chunk_bounds_;  // per chunk: its validation
  pinned_buffer<bounds_dev> h_chunk_bounds_;
  cudaEvent_t ev_wait_ = nullptr;  // a stream's point to wait for (wait_bounded)
  /// The last successful call's size and output (the overlapped upload's rule).
  struct call_record {
    bool valid = false;
    std::uint64_t boxes = 0, bytes_in = 0, pairs = 0;
  } last_call_;

  pbig_report report_{};
  std::vector<std::pair<float, float>> copy_spans_;  // direct output: this call's pair copies, ms from ev_start_
};

}  // namespace zone::gpu::detail
