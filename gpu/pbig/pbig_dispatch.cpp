// Dispatch of the GPU PBIG finder (see pbig_dispatch.h and docs/gpu.md).
//
// One call, on the main stream unless said otherwise:
//  1. DataIn: the box arrays are packed into pinned staging memory by the thread pool in parts,
//     each part's host-to-device copy overlapping the packing of the next.
//  2. PLAN: bounds kernel, then the one-block planning kernel (Eq. 6 on a GPU-side sample) and,
//     when Eq. 6's search ran, the cost kernel, which may take a larger edge (the cost-aware plan,
//     beyond the paper); the plan is read back (synchronisation 1 of the call).
//  3. MAP: count kernel (atomics; large boxes flagged), CUB select of the large boxes, CUB scan of
//     the per-cell (entries, work items, tiles), CUB reduce of the totals, batch planning; the
//     totals are read back (synchronisation 2); map kernel (atomics), CUB segmented sort of each
//     cell's list by box id (determinism), gather of the packed box array.
//  4. SCHED: one work item per (cell, row segment).
//  5. CHECK / DataOut / REPORT: batches of cells through the 3-stage pipeline of Fig. 7 on two
//     streams with double-buffered device and pinned host output buffers.
//  6. Boxes handled apart (large): two passes (count, scan, write), so their order is fixed.
// That is read-back sizing. Single queue (direct output, after a small call): the same steps
// queued at once with the last call's sizes as capacity and one synchronisation at the end; a
// grid past that capacity is re-run with read-back sizing (run_single_queue, docs/gpu.md).
#include <algorithm>
#if defined(__SSE2__)
#include <immintrin.h>
#endif
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>

#include "gpu/common/cuda_check.h"
#include "gpu/common/finder_input.h"
#include "interest/measure.h"
#include "pbig_dispatch.h"
#include "pbig_launch.h"
#include "pbig_tuning.h"

namespace zone::gpu::detail {

namespace {

using clock_type = std::chrono::steady_clock;

/// Writes one decoded pair. Streaming (non-temporal) stores where available: the pair list is
/// written once and not read back by the decoder, so skipping the read-for-ownership of each
/// cache line saves up to half the memory traffic of the REPORT stage.
inline void store_pair(interest::id_pair* dst, std::uint32_t a, std::uint32_t b) {
#if defined(__SSE2__) && defined(__x86_64__)
  _mm_stream_si64(reinterpret_cast<long long*>(dst),
                  static_cast<long long>((static_cast<std::uint64_t>(b) << 32) | a));
#else
  *dst = interest::id_pair{a, b};
#endif
}

std::uint32_t blocks_for(std::uint64_t n, std::uint32_t block) {
  return static_cast<std::uint32_t>(std::max<std::uint64_t>(1, (n + block - 1) / block));
}

}  // namespace

// ---- engine -----------------------------------------------------------------------------------

pbig_engine::pbig_engine(const pbig_options& options) : opt_(options) {
  CUDA_CHECK(cudaSetDevice(0));
  pool_ = pool_or_own(opt_.decode_pool, own_pool_);
  for (auto& s : slot_) {
    CUDA_CHECK(cudaStreamCreateWithFlags(&s.stream, cudaStreamNonBlocking));
    for (cudaEvent_t* e : {&s.kernel_begin, &s.kernel_end, &s.copy_begin, &s.copy_end, &s.totals_ready}) {
      CUDA_CHECK(cudaEventCreate(e));
    }
    s.d_cursor.reserve(1);
    s.h_cursor.reserve(1);
    s.h_total.reserve(1);
    const std::size_t pairs = opt_.initial_output_pairs > 0 ? opt_.initial_output_pairs : tuning::default_output_pairs;
    // Direct output checks into plain chunks (8 bytes a pair) whatever `compression` says.
    s.capacity = std::max<std::uint64_t>(64, pairs * (opt_.compression && !opt_.direct_output ? 2 : 8));
    s.d_out.reserve(s.capacity);
    s.h_out.reserve(s.capacity);
  }
  main_ = slot_[0].stream;
  for (cudaEvent_t* e : {&ev_start_, &ev_in_, &ev_plan_, &ev_counted_, &ev_scattered_, &ev_sorted_, &ev_map_, &ev_sched_,
                         &ev_entries_begin_, &ev_entries_}) {
    CUDA_CHECK(cudaEventCreate(e));
  }
  d_bounds_.reserve(1);
  d_state_.reserve(1);
  CUDA_CHECK(cudaMemset(d_state_.get(), 0, sizeof(plan_state)));
  d_plan_.reserve(1);
  h_plan_.reserve(1);
  h_bounds_.reserve(1);
  d_readback_.reserve(1);
  h_readback_.reserve(1);
  h_large_total_.reserve(1);
  CUDA_CHECK(cudaStreamCreateWithFlags(&upload_, cudaStreamNonBlocking));
  // At the default priority: at the greatest, a stage's map delayed the running checks (and so
  // their copies) as much as it gained (uniform 10^7 on the H200: 12.3-12.4 against 12.1 ms).
  CUDA_CHECK(cudaStreamCreateWithFlags(&stage_, cudaStreamNonBlocking));
  for (int j = 0; j < max_overlap_chunks; ++j) {
    for (cudaEvent_t* e : {&ev_chunk_[j], &ev_staged_[j], &ev_stage_counted_[j], &ev_map_begin_[j], &ev_mapped_[j]}) {
      CUDA_CHECK(cudaEventCreate(e));
    }
  }
  CUDA_CHECK(cudaEventCreateWithFlags(&ev_wait_, cudaEventDisableTiming));
  d_stage_rb_.reserve(max_overlap_chunks);
  h_stage_rb_.reserve(max_overlap_chunks);
  d_chunk_bounds_.reserve(max_overlap_chunks);
  h_chunk_bounds_.reserve(max_overlap_chunks);
}

pbig_engine::~pbig_engine() {
  // No throwing here: errors at teardown are logged and ignored.
  for (auto& s : slot_) {
    if (s.stream != nullptr) cudaStreamSynchronize(s.stream);
    for (cudaEvent_t e : {s.kernel_begin, s.kernel_end, s.copy_begin, s.copy_end, s.totals_ready}) {
      if (e != nullptr) cudaEventDestroy(e);
    }
    if (s.stream != nullptr) cudaStreamDestroy(s.stream);
  }
  for (cudaEvent_t e : {ev_start_, ev_in_, ev_plan_, ev_counted_, ev_scattered_, ev_sorted_, ev_map_, ev_sched_,
                        ev_entries_begin_, ev_entries_}) {
    if (e != nullptr) cudaEventDestroy(e);
  }
  for (cudaStream_t* st : {&upload_, &stage_}) {
    if (*st != nullptr) {
      cudaStreamSynchronize(*st);
      cudaStreamDestroy(*st);
    }
  }
  for (int j = 0; j < max_overlap_chunks; ++j) {
    for (cudaEvent_t e : {ev_chunk_[j], ev_staged_[j], ev_stage_counted_[j], ev_map_begin_[j], ev_mapped_[j]}) {
      if (e != nullptr) cudaEventDestroy(e);
    }
  }
  if (ev_wait_ != nullptr) cudaEventDestroy(ev_wait_);
}

void pbig_engine::grow_temp(std::size_t bytes) { d_temp_.reserve(std::max<std::size_t>(bytes, 256)); }

std::optional<std::uint64_t> pbig_engine::run(const interest::box_set& boxes, interest::pair_list& out,
                                               interest::finder_stats& stats, bool keep_size, bool validate) {
  const auto t0 = clock_type::now();
  const std::size_t count = boxes.size();
  if (count > std::numeric_limits<std::uint32_t>::max() / 2) throw std::length_error("pbig: too many boxes");
  const auto n = static_cast<std::uint32_t>(count);
  report_ = {};
  copy_spans_.clear();
  entries_ready_ = false;
  indirect_ = count >= opt_.indirect_check_min_boxes;
  report_.indirect_check = indirect_;

  auto t_pipe = clock_type::now();
  std::uint64_t grid_pairs = 0, large = 0;
  const std::uint32_t chunks = overlap_chunks(boxes);
  if (chunks > 1) {
    // The overlapped upload (pbig_overlap.cpp): large-box pairs included.
    if (!run_overlapped(boxes, n, chunks, validate, grid_pairs)) return std::nullopt;
  } else {
    CUDA_CHECK(cudaEventRecord(ev_start_, main_));
    if (!upload(boxes, validate)) return std::nullopt;
    queue_plan(n, n);

    bool queued_whole = false;
    if (opt_.direct_output && opt_.pipelining && opt_.single_queue && next_.valid) {
      // One queue of work, one synchronisation, sizes from the last call (see run_single_queue).
      report_.single_queue = true;
      const queue_result r = run_single_queue(n, grid_pairs);
      if (r == queue_result::invalid) return std::nullopt;
      queued_whole = r == queue_result::done;
      report_.requeued = !queued_whole;
    }
    if (!queued_whole) {
      // Read-back sizing: the plan, then the map's totals, are read back before what they size.
      if (!read_plan()) return std::nullopt;
      map_boxes(n);
      t_pipe = clock_type::now();
    }
    if (opt_.direct_output) {
      if (!queued_whole) grid_pairs = check_direct(n);  // large-box pairs included
    } else {
      grid_pairs = check_batches(out);
      report_.pipeline_ms = ms_since(t_pipe);
      const auto t_large = clock_type::now();
      large = large_pairs(n, out, grid_pairs);
      report_.large_ms = ms_since(t_large);
    }
  }
  if (opt_.direct_output) {
    report_.pipeline_ms = ms_since(t_pipe);
    if (!keep_size) {
      // Through pair_finder::find: copy the pinned result into the caller's list.
      const auto t_copy = clock_type::now();
      out.resize(grid_pairs);
      const interest::id_pair* src = h_result_.get();
      interest::id_pair* dst = out.data();
      const std::size_t parts = grid_pairs < tuning::parallel_decode_pairs ? 1 : pool_->size() * 4;
      interest::run_tasks(parts > 1 ? pool_ : nullptr, parts, [&](std::size_t p) {
        const std::size_t b = grid_pairs * p / parts, e = grid_pairs * (p + 1) / parts;
        std::memcpy(static_cast<void*>(dst + b), src + b, (e - b) * sizeof(interest::id_pair));
      });
      report_.report_ms = ms_since(t_copy);
    }
  }
  CUDA_CHECK(cudaStreamSynchronize(slot_[1].stream));
  CUDA_CHECK(cudaStreamSynchronize(main_));

  report_.data_in_ms = elapsed_ms(ev_start_, ev_in_);  // overlapped: the chunks' copies together
  if (chunks > 1) {
    // Stage by stage: MAP is the stages' counts and maps summed (not the stage stream's waits
    // for the host between them).
    report_.plan_ms = elapsed_ms(ev_chunk_[0], ev_plan_);
    for (std::uint32_t j = 0; j < chunks; ++j) {
      report_.map_ms += elapsed_ms(ev_staged_[j], ev_stage_counted_[j]) + elapsed_ms(ev_map_begin_[j], ev_mapped_[j]);
    }
  } else {
    report_.plan_ms = elapsed_ms(ev_in_, ev_plan_);
    report_.map_ms = elapsed_ms(ev_plan_, ev_map_);
    report_.sched_ms = elapsed_ms(ev_map_, ev_sched_);
    report_.map_count_ms = elapsed_ms(ev_plan_, ev_counted_);
    report_.map_scatter_ms = elapsed_ms(ev_counted_, ev_scattered_);
    report_.map_sort_ms = elapsed_ms(ev_scattered_, ev_sorted_);
    report_.map_gather_ms = elapsed_ms(ev_sorted_, ev_map_);
  }
  if (opt_.compression && !opt_.direct_output) report_.data_out_ms += elapsed_ms(ev_entries_begin_, ev_entries_);
  report_.data_out_ms += copy_spans_ms();
  report_.pairs = grid_pairs + large;
  report_.plan_reused = plan_.reused != 0;
  report_.alpha = plan_.alpha;
  report_.total_ms = ms_since(t0);

  stats.cells = plan_.cells;
  stats.cell_entries = rb_.total.entry;
  stats.cell_edge = plan_.edge;
  stats.large_boxes = rb_.large_count;
  stats.checks = rb_.totals.checks + static_cast<std::uint64_t>(rb_.large_count) * n;
  if (!keep_size && !opt_.direct_output) out.resize(report_.pairs);
  if (chunks > 1) {
    // The stages' sizes say nothing of a one-shot call's: the next small call reads its sizes back.
    next_.valid = false;
  } else {
    remember_sizes();
  }
  last_call_ = {true, n, report_.bytes_in, report_.pairs};
  return report_.pairs;
}

bool pbig_engine::uniform_classes(const interest::box_set& boxes, std::size_t begin, std::size_t end) const {
  if (end <= begin) return true;
  const std::size_t n = end - begin;
  const std::uint32_t c0 = boxes.category[0], m0 = boxes.mask[0];
  const std::size_t parts = (n + tuning::uniform_classes_part - 1) / tuning::uniform_classes_part;
  std::atomic<bool> differs{false};
  interest::run_tasks(pool_, parts, [&](std::size_t p) {
    if (differs.load(std::memory_order_relaxed)) return;
    const std::size_t b = begin + p * tuning::uniform_classes_part, e = std::min(end, b + tuning::uniform_classes_part);
    const std::uint32_t* cat = boxes.category.data();
    const std::uint32_t* mask = boxes.mask.data();
    std::uint32_t diff = 0;
    for (std::size_t i = b; i < e; ++i) diff |= (cat[i] ^ c0) | (mask[i] ^ m0);
    if (diff != 0) differs.store(true, std::memory_order_relaxed);
  });
  return !differs.load();
}

bool pbig_engine::upload(const interest::box_set& boxes, bool check) {
  const std::size_t n = boxes.size();
  validate_on_device_ = false;
  if (boxes_pinned(boxes)) {
    boxes_.reserve(n);
    // The caller's arrays are page-locked (pinned_boxes): DMA straight from them, no staging
    // copy; validation moves to the bounds kernel (read back with the plan).
    const float* src_f[6] = {boxes.lo_x.data(), boxes.lo_y.data(), boxes.lo_z.data(),
                             boxes.hi_x.data(), boxes.hi_y.data(), boxes.hi_z.data()};
    for (int a = 0; a < 6; ++a) {
      CUDA_CHECK(cudaMemcpyAsync(boxes_.coord() + a * n, src_f[a], n * 4, cudaMemcpyHostToDevice, main_));
    }
    // While the coordinates are copied: one category and one mask for every box (the plain
    // self-join)? Then those arrays are filled on the device instead of copied.
    if (opt_.fill_uniform_classes && n >= tuning::uniform_classes_min_boxes && uniform_classes(boxes, 0, n)) {
      const auto n32 = static_cast<std::uint32_t>(n);
      CUDA_CHECK(launch_fill_u32(boxes_.bits(), n32, boxes.category[0], main_));
      CUDA_CHECK(launch_fill_u32(boxes_.bits() + n, n32, boxes.mask[0], main_));
      report_.bytes_in += 24 * n;
      report_.classes_filled = true;
    } else {
      CUDA_CHECK(cudaMemcpyAsync(boxes_.bits(), boxes.category.data(), n * 4, cudaMemcpyHostToDevice, main_));
      CUDA_CHECK(cudaMemcpyAsync(boxes_.bits() + n, boxes.mask.data(), n * 4, cudaMemcpyHostToDevice, main_));
      report_.bytes_in += 32 * n;
    }
    CUDA_CHECK(cudaEventRecord(ev_in_, main_));
    validate_on_device_ = check;
    return true;
  }
  const bool ok =
      boxes_.upload_staged(boxes, check, pool_, main_, ev_in_, tuning::upload_part_boxes, tuning::max_upload_parts);
  report_.bytes_in += 32 * n;
  return ok;
}

void pbig_engine::queue_plan(std::uint32_t n, std::uint32_t sample_n) {
  const box_arrays boxes = boxes_.arrays(n);
  plan_params prm{};
  prm.n = n;
  prm.sample_n = sample_n;
  prm.samples = tuning::plan_samples;
  prm.seed = 0x5eed;
  prm.min_boxes_per_cell = opt_.min_boxes_per_cell;
  prm.fixed_edge = opt_.fixed_cell_edge;
  prm.allow_reuse = opt_.reuse_plan ? 1 : 0;
  prm.validate = validate_on_device_ ? 1 : 0;
  prm.cost_aware = opt_.cost_aware_plan ? 1 : 0;
  CUDA_CHECK(launch_plan(boxes, d_bounds_.get(), prm, d_state_.get(), d_plan_.get(), main_));
  CUDA_CHECK(cudaEventRecord(ev_plan_, main_));
}

bool pbig_engine::read_plan() {
  CUDA_CHECK(cudaMemcpyAsync(h_plan_.get(), d_plan_.get(), sizeof(grid_plan_dev), cudaMemcpyDeviceToHost, main_));
  if (validate_on_device_) {
    CUDA_CHECK(cudaMemcpyAsync(h_bounds_.get(), d_bounds_.get(), sizeof(bounds_dev), cudaMemcpyDeviceToHost, main_));
  }
  CUDA_CHECK(cudaStreamSynchronize(main_));
  if (validate_on_device_ && h_bounds_.get()->bad != 0xffffffffu) return false;  // an invalid box
  plan_ = *h_plan_.get();
  if (plan_.cells == 0 || plan_.cells > 2147483647ull) throw std::runtime_error("pbig: planning produced an invalid grid");
  return true;
}

void pbig_engine::queue_count(std::uint32_t n, const grid_capacity& cap) {
  const box_arrays boxes = boxes_.arrays(n);
  const auto cells = static_cast<std::uint32_t>(cap.cells);
  // One zeroed array, one memset: counts[0, cells] (counts[cells] stays 0 for the scan), the
  // large-box counter at counts[cells + 1], then the map kernel's per-cell cursors. A plan of
  // fewer cells than the capacity leaves the counts past it at 0: the scans see empty cells.
  d_counts_.reserve(2ull * cells + 2);
  std::uint32_t* large_counter = d_counts_.get() + cells + 1;
  d_prefix_.reserve(cells + 1ull);
  d_is_large_.reserve(n);
  CUDA_CHECK(cudaMemsetAsync(d_counts_.get(), 0, (2ull * cells + 2) * sizeof(std::uint32_t), main_));
  CUDA_CHECK(launch_count(boxes, n, d_plan_.get(), cap.cells, d_counts_.get(), d_is_large_.get(), large_counter, main_));
  d_box_lo_.reserve(n);
  d_box_hi_.reserve(n);
  CUDA_CHECK(launch_pack_boxes(boxes, n, d_box_lo_.get(), d_box_hi_.get(), main_));

  map_readback* rb = d_readback_.get();
  std::size_t scan_bytes = 0, reduce_bytes = 0;
  CUDA_CHECK(scan_cells(nullptr, scan_bytes, d_counts_.get(), d_prefix_.get(), cells, main_));
  CUDA_CHECK(reduce_cells(nullptr, reduce_bytes, d_counts_.get(), &rb->totals, cells, main_));
  grow_temp(std::max(scan_bytes, reduce_bytes));
  CUDA_CHECK(scan_cells(d_temp_.get(), scan_bytes, d_counts_.get(), d_prefix_.get(), cells, main_));
  CUDA_CHECK(reduce_cells(d_temp_.get(), reduce_bytes, d_counts_.get(), &rb->totals, cells, main_));
  CUDA_CHECK(launch_batch_plan(d_plan_.get(), d_prefix_.get(), large_counter, rb, cap, tuning::min_tiles_per_batch,
                               tuning::max_batches, main_));
  CUDA_CHECK(cudaEventRecord(ev_counted_, main_));
}

void pbig_engine::queue_map(std::uint32_t n, const grid_sizes& size, bool small_cells) {
  const box_arrays boxes = boxes_.arrays(n);
  const map_readback* grid = d_readback_.get();
  std::uint32_t* cursor = d_counts_.get() + size.cells + 2;  // queue_count's layout
  d_entries_unsorted_.reserve(size.entries);
  d_entries_.reserve(size.entries);
  if (!indirect_) {
    d_packed_lo_.reserve(size.entries);
    d_packed_hi_.reserve(size.entries);
  }
  d_items_.reserve(size.items);
  if (size.entries == 0) {
    CUDA_CHECK(cudaEventRecord(ev_scattered_, main_));
    CUDA_CHECK(cudaEventRecord(ev_sorted_, main_));
  } else {
    CUDA_CHECK(launch_map(boxes, n, 0, d_plan_.get(), grid, d_is_large_.get(), d_prefix_.get(), cursor,
                          d_entries_unsorted_.get(), main_));
    CUDA_CHECK(cudaEventRecord(ev_scattered_, main_));
    // Sort each cell's list by box id: the mapping's atomics give a timing-dependent order.
    if (small_cells) {
      CUDA_CHECK(launch_sort_small_cells(d_entries_unsorted_.get(), d_entries_.get(), d_prefix_.get(), size.cells, grid,
                                         main_));
    } else {
      // Read-back sizing only: CUB's sort takes exact sizes.
      std::size_t sort_bytes = 0;
      CUDA_CHECK(sort_cells(nullptr, sort_bytes, d_entries_unsorted_.get(), d_entries_.get(), size.entries, size.cells,
                            d_prefix_.get(), main_));
      grow_temp(sort_bytes);
      CUDA_CHECK(sort_cells(d_temp_.get(), sort_bytes, d_entries_unsorted_.get(), d_entries_.get(), size.entries,
                            size.cells, d_prefix_.get(), main_));
    }
    CUDA_CHECK(cudaEventRecord(ev_sorted_, main_));
    if (!indirect_) {  // else the checks read the id-ordered boxes through the ids
      CUDA_CHECK(launch_gather(d_box_lo_.get(), d_box_hi_.get(), d_entries_.get(), size.entries, grid,
                               d_packed_lo_.get(), d_packed_hi_.get(), main_));
    }
  }
  CUDA_CHECK(cudaEventRecord(ev_map_, main_));
  if (size.items > 0) {
    CUDA_CHECK(launch_expand(d_prefix_.get(), size.cells, grid, d_items_.get(), main_));
  }
  CUDA_CHECK(cudaEventRecord(ev_sched_, main_));
}

grid_capacity pbig_engine::readback_limits() const {
  return grid_capacity{plan_.cells,
                       std::numeric_limits<std::uint32_t>::max() / 2,
                       std::numeric_limits<std::uint32_t>::max(),
                       std::numeric_limits<std::uint32_t>::max(),
                       65535ull * tuning::segment,
                       1};
}

void pbig_engine::check_readback(const map_readback& rb, const std::string& what) {
  // 32-bit limits of the cell lists (prefixes wrap silently past them: refuse instead). The
  // device refused the same grids (fits = 0, nothing mapped).
  if (rb.totals.entries != rb.total.entry || rb.totals.tiles != rb.total.tile ||
      rb.totals.entries > std::numeric_limits<std::uint32_t>::max() / 2) {
    throw std::length_error("pbig: " + what + ": more than 2^31 (cell, box) entries or tiles");
  }
  if (rb.totals.max_count > 65535ull * tuning::segment) {
    throw std::length_error("pbig: " + what + ": a cell holds more than 65535 segments of boxes");
  }
  if (rb.fits == 0) throw std::logic_error("pbig: " + what + " does not fit its read-back sizes (internal error)");
}

void pbig_engine::map_boxes(std::uint32_t n) {
  // Read-back sizing: the counters sized by the plan, the rest by the totals read back.
  queue_count(n, readback_limits());
  map_readback* rb = d_readback_.get();
  CUDA_CHECK(cudaMemcpyAsync(h_readback_.get(), rb, sizeof(map_readback), cudaMemcpyDeviceToHost, main_));
  CUDA_CHECK(cudaStreamSynchronize(main_));
  rb_ = *h_readback_.get();
  check_readback(rb_, "the grid");

  if (rb_.large_count > 0) {
    // The large boxes' ids in id order (for the large-box passes at the end of the call).
    d_large_.reserve(n);
    std::size_t select_bytes = 0;
    CUDA_CHECK(select_large(nullptr, select_bytes, d_is_large_.get(), d_large_.get(), &rb->large_count, n, main_));
    grow_temp(select_bytes);
    CUDA_CHECK(select_large(d_temp_.get(), select_bytes, d_is_large_.get(), d_large_.get(), &rb->large_count, n, main_));
  }

  const grid_sizes exact{static_cast<std::uint32_t>(plan_.cells), rb_.total.entry, rb_.total.item, rb_.total.tile};
  queue_map(n, exact, rb_.totals.max_count <= tuning::small_cell_sort);

  // The decoder needs the box array (cell-sorted ids): copy it on the second stream, overlapping
  // the first checking kernels.
  cudaStream_t side = slot_[1].stream;
  CUDA_CHECK(cudaStreamWaitEvent(side, ev_sched_, 0));
  CUDA_CHECK(cudaEventRecord(ev_entries_begin_, side));
  if (opt_.compression && !opt_.direct_output && exact.entries > 0) {
    h_entries_.reserve(exact.entries);
    CUDA_CHECK(cudaMemcpyAsync(h_entries_.get(), d_entries_.get(), exact.entries * sizeof(std::uint32_t),
                               cudaMemcpyDeviceToHost, side));
    report_.bytes_out += exact.entries * sizeof(std::uint32_t);
  }
  CUDA_CHECK(cudaEventRecord(ev_entries_, side));
}

// ---- single queue -----------------------------------------------------------------------------
//
// When the last call was one batch with no boxes handled apart and no cell over
// tuning::small_cell_sort boxes (a small set), this call is queued whole before the host knows
// its plan or totals: counters, entry lists, work items and the tile index sized by the last
// call's figures plus a margin (next_), one batch over that capacity, batch 0's pairs copied
// sized by the last call's pairs, then one read-back and one synchronisation. The kernels read
// the plan and the totals from device memory and do nothing past them; the batch-planning kernel
// checks the grid against the capacity, and a grid past it is not mapped (fits = 0): the host
// re-runs the call from the count kernel with read-back sizing (pbig_report::requeued). An
// overflowing chunk buffer is re-run as in every direct batch (finish_direct).

pbig_engine::queue_result pbig_engine::run_single_queue(std::uint32_t n, std::uint64_t& pairs) {
  const grid_sizes cap = next_.sizes;
  queue_count(n, grid_capacity{cap.cells, cap.entries, cap.items, cap.tiles, tuning::small_cell_sort, 0});
  queue_map(n, cap, /*small_cells=*/true);
  for (auto& s : slot_) {
    s.copy_pending = false;
    s.overcopied = false;
  }
  pipeline_slot& s = slot_[0];
  const batch b{0, cap.items, 0, cap.tiles};
  ensure_result(next_.pairs, 0);
  launch_direct(b, s, next_.pairs);
  CUDA_CHECK(cudaMemcpyAsync(h_readback_.get(), d_readback_.get(), sizeof(map_readback), cudaMemcpyDeviceToHost, main_));
  if (validate_on_device_) {
    CUDA_CHECK(cudaMemcpyAsync(h_bounds_.get(), d_bounds_.get(), sizeof(bounds_dev), cudaMemcpyDeviceToHost, main_));
  }
  CUDA_CHECK(cudaStreamSynchronize(main_));  // the call's synchronisation
  if (validate_on_device_ && h_bounds_.get()->bad != 0xffffffffu) return queue_result::invalid;
  rb_ = *h_readback_.get();
  plan_ = rb_.plan;
  if (rb_.fits == 0) {
    account_copy(s);
    return queue_result::outgrown;
  }
  report_.batches = 1;
  pairs = finish_direct(b, s, 0, 0, 1);  // overflow re-run; the rest of the pairs if the copy was short
  for (auto& sl : slot_) account_copy(sl);
  *h_large_total_.get() = 0;
  return queue_result::done;
}

void pbig_engine::remember_sizes() {
  const auto grow = [](std::uint64_t x) {
    return static_cast<std::uint32_t>(std::min<std::uint64_t>(x + x / tuning::queue_margin_div + tuning::queue_margin_add,
                                                              std::numeric_limits<std::uint32_t>::max() / 2));
  };
  next_.valid = rb_.large_count == 0 && rb_.totals.max_count <= tuning::small_cell_sort &&
                rb_.total.tile <= tuning::min_tiles_per_batch;
  next_.sizes = {grow(plan_.cells), grow(rb_.total.entry), grow(rb_.total.item), grow(rb_.total.tile)};
  next_.pairs = grow(report_.pairs);
}

check_args pbig_engine::batch_args(const batch& b, const pipeline_slot& s) const {
  check_args a{};
  a.plan = d_plan_.get();
  if (b.stage >= 0) {
    // A stage of the overlapped upload: its lists and work items; boxes through their ids.
    const overlap_stage& st = stages_[b.stage];
    a.grid = d_stage_rb_.get() + b.stage;
    a.packed_lo = d_box_lo_.get();
    a.packed_hi = d_box_hi_.get();
    a.indirect = 1;
    a.entries = st.entries.get();
    a.prefix = st.prefix.get();
    a.items = st.items.get();
  } else {
    a.grid = d_readback_.get();
    a.packed_lo = indirect_ ? d_box_lo_.get() : d_packed_lo_.get();
    a.packed_hi = indirect_ ? d_box_hi_.get() : d_packed_hi_.get();
    a.indirect = indirect_ ? 1u : 0u;
    a.entries = d_entries_.get();
    a.prefix = d_prefix_.get();
    a.items = d_items_.get();
  }
  a.item_first = b.item_first;
  a.item_last = b.item_last;
  a.tile_off = s.d_tile_off.get();
  a.tile_pairs = s.d_tile_pairs.get();
  a.tile_first = b.tile_first;
  a.out = s.d_out.get();
  a.capacity = s.capacity;
  a.cursor = s.d_cursor.get();
  return a;
}

std::vector<pbig_engine::batch> pbig_engine::planned_batches(const map_readback& rb, std::int32_t stage) {
  std::vector<batch> batches;
  const batch_plan& bp = rb.batches;
  for (std::uint32_t k = 0; k < bp.count; ++k) {
    const batch b{bp.item[k], bp.item[k + 1], bp.tile[k], bp.tile[k + 1], stage};
    if (b.item_last > b.item_first) batches.push_back(b);
  }
  return batches;
}

void pbig_engine::launch(const batch& b, pipeline_slot& s) {
  const std::uint32_t tiles = b.tile_last - b.tile_first;
  s.d_tile_off.reserve(tiles);
  s.d_tile_pairs.reserve(tiles);
  CUDA_CHECK(cudaMemsetAsync(s.d_cursor.get(), 0, sizeof(unsigned long long), s.stream));
  const check_args a = batch_args(b, s);
  CUDA_CHECK(cudaEventRecord(s.kernel_begin, s.stream));
  CUDA_CHECK(launch_check(a, opt_.load_balancing, opt_.compression, s.stream));
  CUDA_CHECK(cudaEventRecord(s.kernel_end, s.stream));
  CUDA_CHECK(cudaMemcpyAsync(s.h_cursor.get(), s.d_cursor.get(), sizeof(unsigned long long), cudaMemcpyDeviceToHost,
                             s.stream));
}

void pbig_engine::prefetch(const batch& b, pipeline_slot& s, std::uint64_t bytes) {
  const std::uint32_t tiles = b.tile_last - b.tile_first;
  s.h_tile_off.reserve(tiles);
  s.h_tile_pairs.reserve(tiles);
  CUDA_CHECK(cudaEventRecord(s.copy_begin, s.stream));
  CUDA_CHECK(cudaMemcpyAsync(s.h_tile_off.get(), s.d_tile_off.get(), tiles * sizeof(std::uint64_t),
                             cudaMemcpyDeviceToHost, s.stream));
  CUDA_CHECK(cudaMemcpyAsync(s.h_tile_pairs.get(), s.d_tile_pairs.get(), tiles * sizeof(std::uint32_t),
                             cudaMemcpyDeviceToHost, s.stream));
  s.prefetched = std::min<std::uint64_t>(bytes, s.capacity);
  if (s.prefetched > 0) {
    CUDA_CHECK(cudaMemcpyAsync(s.h_out.get(), s.d_out.get(), s.prefetched, cudaMemcpyDeviceToHost, s.stream));
  }
  CUDA_CHECK(cudaEventRecord(s.copy_end, s.stream));
  report_.bytes_out += tiles * 12ull + s.prefetched;
}

void pbig_engine::finish(const batch& b, pipeline_slot& s) {
  // Synchronisation 1: the batch's kernel and its prefetched copy are done.
  CUDA_CHECK(cudaEventSynchronize(s.copy_end));
  report_.check_ms += elapsed_ms(s.kernel_begin, s.kernel_end);
  report_.data_out_ms += elapsed_ms(s.copy_begin, s.copy_end);
  std::uint64_t used = *s.h_cursor.get();
  if (used > s.capacity) {
    // Overflow: nothing past the capacity was written. Grow both buffers and re-run the batch.
    ++report_.reruns;
    s.capacity = used + used / 4;
    s.d_out.reserve(s.capacity);
    s.h_out.reserve(s.capacity);
    launch(b, s);
    prefetch(b, s, used);
    CUDA_CHECK(cudaEventSynchronize(s.copy_end));
    report_.check_ms += elapsed_ms(s.kernel_begin, s.kernel_end);
    report_.data_out_ms += elapsed_ms(s.copy_begin, s.copy_end);
    const std::uint64_t again = *s.h_cursor.get();
    if (again != used) throw std::runtime_error("pbig: a re-run batch produced a different output size");
    s.remainder_pending = false;
    return;
  }
  s.remainder_pending = used > s.prefetched;
  if (s.remainder_pending) {
    CUDA_CHECK(cudaEventRecord(s.copy_begin, s.stream));
    CUDA_CHECK(cudaMemcpyAsync(s.h_out.get() + s.prefetched, s.d_out.get() + s.prefetched, used - s.prefetched,
                               cudaMemcpyDeviceToHost, s.stream));
    CUDA_CHECK(cudaEventRecord(s.copy_end, s.stream));
    report_.bytes_out += used - s.prefetched;
  }
  s.prefetched = used;
}

std::uint64_t pbig_engine::decode(const batch& b, pipeline_slot& s, interest::pair_list& out, std::uint64_t base) {
  // Synchronisation 2: the batch's output is in host memory.
  CUDA_CHECK(cudaEventSynchronize(s.copy_end));
  if (s.remainder_pending) {
    report_.data_out_ms += elapsed_ms(s.copy_begin, s.copy_end);
    s.remainder_pending = false;
  }
  if (opt_.compression && !entries_ready_) {
    CUDA_CHECK(cudaEventSynchronize(ev_entries_));
    entries_ready_ = true;
  }
  const auto t0 = clock_type::now();
  const std::uint32_t tiles = b.tile_last - b.tile_first;
  const std::uint32_t* tile_pairs = s.h_tile_pairs.get();
  const std::uint64_t* tile_off = s.h_tile_off.get();
  tile_pos_.resize(tiles + 1);
  tile_pos_[0] = 0;
  for (std::uint32_t t = 0; t < tiles; ++t) tile_pos_[t + 1] = tile_pos_[t] + tile_pairs[t];
  const std::uint64_t total = tile_pos_[tiles];
  if (total == 0) {
    report_.report_ms += ms_since(t0);
    return 0;
  }
  if (out.size() < base + total) out.resize(base + total);
  interest::id_pair* dst = out.data() + base;
  const unsigned char* buf = s.h_out.get();
  const std::uint32_t* entries = h_entries_.get();
  const std::uint64_t used = s.prefetched;

  // Tasks of about equal pair counts; each decodes whole tiles into their final positions.
  const std::size_t tasks =
      total < tuning::parallel_decode_pairs ? 1 : std::min<std::size_t>(tiles, std::max<std::size_t>(1, pool_->size() * 4));
  task_tiles_.resize(tasks + 1);
  for (std::size_t q = 0; q <= tasks; ++q) {
    const std::uint64_t target = total * q / tasks;
    task_tiles_[q] = static_cast<std::uint32_t>(std::lower_bound(tile_pos_.begin(), tile_pos_.end(), target) -
                                                tile_pos_.begin());
  }
  task_tiles_[tasks] = tiles;
  std::atomic<bool> corrupt{false};
  const bool compressed = opt_.compression;
  interest::run_tasks(tasks > 1 ? pool_ : nullptr, tasks, [&](std::size_t q) {
    for (std::uint32_t t = task_tiles_[q]; t < task_tiles_[q + 1]; ++t) {
      const std::uint32_t pairs = tile_pairs[t];
      if (pairs == 0) continue;
      if (tile_off[t] + sizeof(chunk_header) > used) {
        corrupt = true;
        return;
      }
      chunk_header h;
      std::memcpy(&h, buf + tile_off[t], sizeof h);
      const unsigned char* body = buf + tile_off[t] + sizeof h;
      interest::id_pair* o = dst + tile_pos_[t];
      if (h.pairs != pairs || tile_off[t] + sizeof h + h.body_bytes > used) {
        corrupt = true;
        return;
      }
      if (compressed) {
        // Eq. 8: (cell, segment, local id) -> box id through the cell-sorted box array.
        const std::uint32_t* rows = entries + h.cell_begin + std::uint64_t{h.seg_v} * tuning::segment;
        const std::uint32_t* cols = entries + h.cell_begin + std::uint64_t{h.seg_h} * tuning::segment;
        std::uint32_t q2 = 0, written = 0;
        while (q2 < h.body_bytes) {
          const std::uint32_t a = rows[body[q2]];
          const std::uint32_t c = body[q2 + 1] + 1u;
          for (std::uint32_t k = 0; k < c; ++k) {
            const std::uint32_t other = cols[body[q2 + 2 + k]];
            store_pair(o + written++, a < other ? a : other, a < other ? other : a);
          }
          q2 += 2 + c;
        }
        if (written != pairs) corrupt = true;
      } else {
        const auto* src = reinterpret_cast<const std::uint32_t*>(body);
        for (std::uint32_t k = 0; k < pairs; ++k) store_pair(o + k, src[2 * k], src[2 * k + 1]);
      }
    }
#if defined(__SSE2__)
    _mm_sfence();  // order the streaming stores before the pool's completion signal
#endif
  });
  if (corrupt) throw std::runtime_error("pbig: malformed output chunk (internal error)");
  report_.report_ms += ms_since(t0);
  return total;
}

std::uint64_t pbig_engine::check_batches(interest::pair_list& out) {
  const std::vector<batch> batches = planned_batches(rb_);
  report_.batches = static_cast<std::uint32_t>(batches.size());
  // Slot 1's stream must see the mapped boxes.
  CUDA_CHECK(cudaStreamWaitEvent(slot_[1].stream, ev_sched_, 0));
  std::uint64_t base = 0;
  const std::size_t count = batches.size();
  if (!opt_.pipelining) {
    for (std::size_t k = 0; k < count; ++k) {
      pipeline_slot& s = slot_[k % 2];
      launch(batches[k], s);
      prefetch(batches[k], s, 0);
      finish(batches[k], s);
      base += decode(batches[k], s, out, base);
    }
  } else {
    // Fig. 7: in step k, kernel k runs while batch k-1's output is copied and batch k-2's is
    // decoded. Batch k's prefetched copy (sized by the last known batch output) is queued behind
    // its kernel once the CPU is done with that host buffer (batch k-2). Synchronisation 3 (a
    // device buffer is copied out before the next kernel reuses it) is the slot's stream order.
    std::uint64_t last_bytes = 0;
    for (std::size_t k = 0; k < count + 2; ++k) {
      if (k < count) launch(batches[k], slot_[k % 2]);
      if (k >= 2) base += decode(batches[k - 2], slot_[k % 2], out, base);
      if (k < count) prefetch(batches[k], slot_[k % 2], last_bytes);
      if (k >= 1 && k - 1 < count) {
        pipeline_slot& s = slot_[(k - 1) % 2];
        finish(batches[k - 1], s);
        last_bytes = s.prefetched;
      }
    }
  }
  return base;
}

void pbig_engine::large_count_pass(std::uint32_t n) {
  *h_large_total_.get() = 0;
  const std::uint32_t large = rb_.large_count;
  if (large == 0) return;
  const box_arrays boxes = boxes_.arrays(n);
  const std::uint32_t chunks = blocks_for(n, tuning::block);
  const std::uint64_t blocks = static_cast<std::uint64_t>(chunks) * large;
  if (blocks >= (1ull << 31)) throw std::length_error("pbig: too many large boxes for the large-box pass");
  d_large_counts_.reserve(blocks + 1);
  d_large_offsets_.reserve(blocks + 1);
  CUDA_CHECK(cudaMemsetAsync(d_large_counts_.get(), 0, (blocks + 1) * sizeof(std::uint32_t), main_));
  CUDA_CHECK(launch_large_count(boxes, n, d_large_.get(), large, d_is_large_.get(), chunks, d_large_counts_.get(),
                                main_));
  std::size_t scan_bytes = 0;
  CUDA_CHECK(scan_u32(nullptr, scan_bytes, d_large_counts_.get(), d_large_offsets_.get(), blocks + 1, main_));
  grow_temp(scan_bytes);
  CUDA_CHECK(scan_u32(d_temp_.get(), scan_bytes, d_large_counts_.get(), d_large_offsets_.get(), blocks + 1, main_));
  CUDA_CHECK(cudaMemcpyAsync(h_large_total_.get(), d_large_offsets_.get() + blocks, sizeof(std::uint32_t),
                             cudaMemcpyDeviceToHost, main_));
}

void pbig_engine::large_write_pass(std::uint32_t n, std::uint64_t total, void* host_dst) {
  if (total == 0) return;
  const box_arrays boxes = boxes_.arrays(n);
  const std::uint32_t chunks = blocks_for(n, tuning::block);
  d_large_pairs_.reserve(2 * total);
  CUDA_CHECK(launch_large_write(boxes, n, d_large_.get(), rb_.large_count, d_is_large_.get(), chunks,
                                d_large_offsets_.get(), d_large_pairs_.get(), main_));
  CUDA_CHECK(cudaMemcpyAsync(host_dst, d_large_pairs_.get(), 2 * total * sizeof(std::uint32_t), cudaMemcpyDeviceToHost,
                             main_));
  CUDA_CHECK(cudaStreamSynchronize(main_));
  report_.bytes_out += 8 * total;
}

std::uint64_t pbig_engine::large_pairs(std::uint32_t n, interest::pair_list& out, std::uint64_t base) {
  if (rb_.large_count == 0) return 0;
  large_count_pass(n);
  CUDA_CHECK(cudaStreamSynchronize(main_));
  const std::uint64_t total = *h_large_total_.get();
  if (total == 0) return 0;
  h_large_pairs_.reserve(2 * total);
  large_write_pass(n, total, h_large_pairs_.get());
  if (out.size() < base + total) out.resize(base + total);
  std::memcpy(static_cast<void*>(out.data() + base), h_large_pairs_.get(), total * sizeof(interest::id_pair));
  return total;
}

// ---- direct output ----------------------------------------------------------------------------
//
// One checking pass per batch (the paper's Algorithm 2 writing plain chunks at atomic offsets, as
// in the paper's output path), then on the device: a scan of the batch's per-tile pair counts and
// a placing kernel that moves every tile's pairs to its scanned position, so the batch's pairs are
// in tile order whatever order the blocks ran in. The host reads the batch's chunk bytes and pair
// count (synchronisation 1 of Fig. 7, while the next batch's kernel runs on the other stream), re-runs
// the batch with room if its chunks overflowed, and queues the device-to-host copy of its pairs
// straight into the result at the running total. Stream order protects a slot's buffers from the
// next batch on that slot until its copy is done (synchronisation 3); no CPU decode.

void pbig_engine::launch_direct(const batch& b, pipeline_slot& s, std::uint64_t prefetch_pairs) {
  const std::uint32_t tiles = b.tile_last - b.tile_first;
  s.d_tile_off.reserve(tiles);
  s.d_tile_pairs.reserve(tiles + 1);
  s.d_tile_pos.reserve(tiles + 1);
  s.d_direct.reserve(2 * (s.capacity / 8) + 2);  // a chunk holds 8 bytes a pair after its header
  std::size_t scan_bytes = 0;
  CUDA_CHECK(scan_tiles(nullptr, scan_bytes, s.d_tile_pairs.get(), s.d_tile_pos.get(), tiles + 1ull, s.stream));
  s.d_temp.reserve(std::max<std::size_t>(scan_bytes, 256));
  CUDA_CHECK(cudaMemsetAsync(s.d_cursor.get(), 0, sizeof(unsigned long long), s.stream));
  // Every tile count zeroed, the extra one for the scan's total too: a batch queued with a
  // capacity (single queue) has tiles past the grid's, which no checking block writes.
  CUDA_CHECK(cudaMemsetAsync(s.d_tile_pairs.get(), 0, (tiles + 1ull) * sizeof(std::uint32_t), s.stream));
  const check_args a = batch_args(b, s);
  CUDA_CHECK(cudaEventRecord(s.kernel_begin, s.stream));
  if (b.stage >= 0) {
    CUDA_CHECK(launch_check_stage(a, lists_of(static_cast<std::uint32_t>(b.stage) + 1), opt_.load_balancing,
                                  stage_width_, s.stream));
  } else {
    CUDA_CHECK(launch_check(a, opt_.load_balancing, /*compressed=*/false, s.stream));
  }
  CUDA_CHECK(scan_tiles(s.d_temp.get(), scan_bytes, s.d_tile_pairs.get(), s.d_tile_pos.get(), tiles + 1ull, s.stream));
  CUDA_CHECK(launch_place_chunks(s.d_out.get(), s.d_cursor.get(), s.capacity, s.d_tile_off.get(), s.d_tile_pairs.get(),
                                 s.d_tile_pos.get(), tiles, s.d_direct.get(), s.stream));
  CUDA_CHECK(cudaEventRecord(s.kernel_end, s.stream));
  // Written by the device into pinned memory: a copy would wait behind the other slot's pairs.
  CUDA_CHECK(launch_to_host(s.d_cursor.get(), s.h_cursor.get(), sizeof(unsigned long long), s.d_tile_pos.get() + tiles,
                            s.h_total.get(), sizeof(std::uint64_t), s.stream));
  CUDA_CHECK(cudaEventRecord(s.totals_ready, s.stream));
  // Batch 0 sits at the start of the result whatever its size: its copy, sized by the last
  // call's batch 0 (the paper's prefetch), is queued now rather than after the host has read the
  // total, so the copy engine does not wait for the host. finish_direct copies any rest.
  s.prefetched_pairs = std::min<std::uint64_t>({prefetch_pairs, s.capacity / 8, h_result_.capacity()});
  s.overcopied = false;
  if (s.prefetched_pairs > 0) {
    CUDA_CHECK(cudaEventRecord(s.copy_begin, s.stream));
    CUDA_CHECK(cudaMemcpyAsync(h_result_.get(), s.d_direct.get(), s.prefetched_pairs * sizeof(interest::id_pair),
                               cudaMemcpyDeviceToHost, s.stream));
    CUDA_CHECK(cudaEventRecord(s.copy_end, s.stream));
    s.copy_pending = true;
  }
}

void pbig_engine::account_copy(pipeline_slot& s) {
  if (!s.copy_pending) return;
  CUDA_CHECK(cudaEventSynchronize(s.copy_end));
  // A copy queued while the other slot's is running waits behind it: its span from the call's
  // start; DataOut is the spans' union (copy_spans_ms), the time the copy engine moved pairs.
  copy_spans_.emplace_back(elapsed_ms(ev_start_, s.copy_begin), elapsed_ms(ev_start_, s.copy_end));
  s.copy_pending = false;
}

double pbig_engine::copy_spans_ms() {
  std::sort(copy_spans_.begin(), copy_spans_.end());
  double total = 0, until = 0;
  for (const auto& [begin, end] : copy_spans_) {
    const double from = std::max<double>(begin, until);
    if (end > from) total += end - from;
    until = std::max<double>(until, end);
  }
  copy_spans_.clear();
  return total;
}

void pbig_engine::ensure_result(std::uint64_t needed, std::uint64_t keep) {
  if (needed <= h_result_.capacity()) return;
  // Grow the pinned result, keeping its first `keep` pairs: wait for every copy into it first.
  for (auto& s : slot_) CUDA_CHECK(cudaStreamSynchronize(s.stream));
  pinned_buffer<interest::id_pair> bigger;
  bigger.reserve(needed);
  if (keep > 0) std::memcpy(static_cast<void*>(bigger.get()), h_result_.get(), keep * sizeof(interest::id_pair));
  h_result_.swap(bigger);
}

std::uint64_t pbig_engine::finish_direct(const batch& b, pipeline_slot& s, std::uint64_t base, std::size_t done,
                                         std::size_t count) {
  // Synchronisation 1: the batch's kernels are done and its totals are in host memory.
  CUDA_CHECK(cudaEventSynchronize(s.totals_ready));
  if (s.prefetched_pairs == 0) account_copy(s);  // the previous batch on this slot (before these kernels)
  report_.check_ms += elapsed_ms(s.kernel_begin, s.kernel_end);
  const std::uint64_t used = *s.h_cursor.get();
  if (used > s.capacity) {
    // Overflow: no chunk past the capacity was written and nothing was placed. Grow and re-run.
    ++report_.reruns;
    account_copy(s);  // a prefetch of nothing useful: let it finish before the buffers move
    s.capacity = used + used / 4;
    s.d_out.reserve(s.capacity);
    launch_direct(b, s);
    CUDA_CHECK(cudaEventSynchronize(s.totals_ready));
    report_.check_ms += elapsed_ms(s.kernel_begin, s.kernel_end);
    if (*s.h_cursor.get() != used) throw std::runtime_error("pbig: a re-run batch produced a different output size");
  }
  const std::uint64_t total = *s.h_total.get();
  if (done == 0) last_first_batch_pairs_ = total;
  // A prefetch past this batch's pairs wrote stale pairs where the next batch's go: the next
  // batch's copy (on the other stream) must come after it.
  pipeline_slot& other = &s == &slot_[0] ? slot_[1] : slot_[0];
  if (other.overcopied) {
    CUDA_CHECK(cudaStreamWaitEvent(s.stream, other.copy_end, 0));
    other.overcopied = false;
  }
  const std::uint64_t already = std::min(s.prefetched_pairs, total);
  s.overcopied = s.prefetched_pairs > total;
  s.prefetched_pairs = 0;
  if (already < total) {
    // Room for this batch; when the result must grow, room for the rest at this batch's rate too.
    const std::uint64_t need = base + total;
    ensure_result(need > h_result_.capacity() ? need + need / (done + 1) * (count - done - 1) + need / 8 : need, base + already);
    if (already == 0) CUDA_CHECK(cudaEventRecord(s.copy_begin, s.stream));
    CUDA_CHECK(cudaMemcpyAsync(h_result_.get() + base + already, s.d_direct.get() + 2 * already,
                               (total - already) * sizeof(interest::id_pair), cudaMemcpyDeviceToHost, s.stream));
    CUDA_CHECK(cudaEventRecord(s.copy_end, s.stream));
    s.copy_pending = true;
  }
  report_.bytes_out += total * sizeof(interest::id_pair);
  return total;
}

std::uint64_t pbig_engine::check_direct(std::uint32_t n) {
  const std::vector<batch> batches = planned_batches(rb_);
  const std::size_t count = batches.size();
  report_.batches = static_cast<std::uint32_t>(count);
  // Slot 1's stream must see the mapped boxes.
  CUDA_CHECK(cudaStreamWaitEvent(slot_[1].stream, ev_sched_, 0));
  for (auto& s : slot_) {
    s.copy_pending = false;
    s.overcopied = false;
  }
  const std::uint64_t prefetch = opt_.pipelining ? last_first_batch_pairs_ : 0;
  if (prefetch > 0) ensure_result(prefetch, 0);
  std::uint64_t base = 0;
  if (!opt_.pipelining) {
    for (std::size_t k = 0; k < count; ++k) {
      pipeline_slot& s = slot_[k % 2];
      launch_direct(batches[k], s);
      base += finish_direct(batches[k], s, base, k, count);
      account_copy(s);
    }
  } else {
    // Fig. 7 without the decode stage: kernel k runs while batch k-1's pairs are copied out.
    for (std::size_t k = 0; k <= count; ++k) {
      if (k < count) launch_direct(batches[k], slot_[k % 2], k == 0 ? prefetch : 0);
      if (k >= 1) base += finish_direct(batches[k - 1], slot_[(k - 1) % 2], base, k - 1, count);
    }
    for (auto& s : slot_) account_copy(s);
  }
  // Boxes handled apart: two passes (count, write) on the main stream, after the grid's pairs.
  large_count_pass(n);
  CUDA_CHECK(cudaStreamSynchronize(main_));
  const std::uint64_t large_total = *h_large_total_.get();
  ensure_result(std::max<std::uint64_t>(1, base + large_total), base);
  large_write_pass(n, large_total, h_result_.get() + base);
  return base + large_total;
}

}  // namespace zone::gpu::detail
