// The overlapped upload of the GPU PBIG finder (pbig_options::overlap_min_boxes; docs/gpu.md,
// "Overlapped upload"): the host-to-device copy of the boxes and the device-to-host copy of the
// pairs run at once instead of one after the other (PCIe is full duplex).
//
// The boxes go up in k chunks of ids on their own stream (upload_). Stage j finds every pair whose
// larger id is in chunk j, so it needs only chunks 0..j on the device:
//  1. PLAN once, from chunk 0 (its bounds and sample; f = N alpha / M with the whole N). Later
//     chunks use the same grid; cell_of clamps coordinates outside it to the border cells, so any
//     two intersecting boxes still share a cell (the output-cell rule holds), only less balanced.
//  2. Per stage, on a stream of its own (stage_) once chunk j has landed: its validation (pinned
//     input), count, the stage's per-cell prefixes and totals (chunk j's count q and the earlier
//     chunks' count p in each cell: stage_layout, pbig_shared.h), the batch plan, one read-back;
//     then map chunk j into its own per-cell lists, sort each by id, and expand the stage's work
//     items. Stage j + 1's count is queued right after stage j's map, and its map as soon as the
//     host sees that read-back (polled between batches), so both run while stage j's pairs are
//     checked and copied out: a stage waits for its chunk and the device, not for the earlier
//     stages' copies (on the slots' streams, where the stages ran before).
//  3. The stage's batches check chunk j's lists against themselves and the earlier chunks' lists
//     of the same cells, never two earlier boxes (check_stage_kernel: a work item per W boxes of
//     chunk j in a cell, the stage width W chosen from the plan: stage_width), in the
//     direct-output pipeline of pbig_dispatch.cpp
//     (launch_direct / finish_direct on the two slots, the pairs copied into the pinned result),
//     which runs on across stages: while chunk j + 1 uploads, stage j's pairs are copied out.
//  4. After the last stage: the boxes handled apart (large), over all n boxes, as in check_direct.
// The pairs are those of the one-shot path (each pair in the one stage of its larger id and the
// one cell of check_kernel's rule); the order is stage by stage, then as the direct output.
#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <iterator>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "gpu/common/cuda_check.h"
#include "pbig_dispatch.h"
#include "pbig_launch.h"
#include "pbig_tuning.h"

namespace zone::gpu::detail {

namespace {

/// The arrays of boxes [first, first + count) of a set of n (their index 0 is box `first`).
box_arrays chunk_of(const box_arrays& all, std::uint32_t first) {
  box_arrays c = all;
  for (int d = 0; d < 3; ++d) {
    c.lo[d] += first;
    c.hi[d] += first;
  }
  c.category += first;
  c.mask += first;
  return c;
}

}  // namespace

std::uint32_t pbig_engine::overlap_chunks(const interest::box_set& boxes) const {
  const std::size_t min_boxes = opt_.overlap_min_boxes == 0 ? tuning::overlap_min_boxes : opt_.overlap_min_boxes;
  if (!opt_.direct_output || !opt_.pipelining || boxes.size() < min_boxes || !boxes_pinned(boxes)) return 0;
  if (!opt_.overlap_always) {
    // Only when it pays (pbig_tuning.h): the last call, on a set of about this size, wrote at
    // most overlap_max_out_in times what it uploaded. Nothing known: one-shot.
    const auto n = static_cast<double>(boxes.size());
    const auto last_n = static_cast<double>(last_call_.boxes);
    if (!last_call_.valid || std::abs(n - last_n) > tuning::overlap_size_tolerance * last_n) return 0;
    const double out_bytes = static_cast<double>(last_call_.pairs) * sizeof(interest::id_pair);
    if (out_bytes > tuning::overlap_max_out_in * static_cast<double>(last_call_.bytes_in)) return 0;
  }
  const std::uint32_t k = opt_.overlap_chunks == 0 ? tuning::overlap_chunks : opt_.overlap_chunks;
  const std::uint64_t chunks =
      std::min<std::uint64_t>({k, static_cast<std::uint64_t>(max_overlap_chunks), boxes.size()});
  return chunks > 1 ? static_cast<std::uint32_t>(chunks) : 0;
}

void pbig_engine::wait_bounded(cudaEvent_t done, const char* what, std::uint32_t stage, std::uint32_t n) const {
  // cudaEventSynchronize has no time limit: poll instead (the runtime's default wait spins too).
  using clock = std::chrono::steady_clock;
  const auto limit = std::chrono::duration<double>(tuning::overlap_wait_limit_s);
  const auto t0 = clock::now();
  for (std::uint64_t polls = 1;; ++polls) {
    const cudaError_t e = cudaEventQuery(done);
    if (e == cudaSuccess) return;
    if (e != cudaErrorNotReady) CUDA_CHECK(e);
    if (polls % 1024 == 0) {
      if (clock::now() - t0 > limit) {
        const std::string msg = fmt::format(
            "pbig: the overlapped upload's {} (stage {} of {}, {} boxes) did not finish within {} s: a kernel that "
            "does not end",
            what, stage, report_.overlap_chunks, n, tuning::overlap_wait_limit_s);
        spdlog::error("{}", msg);
        throw std::runtime_error(msg);
      }
      std::this_thread::yield();
    }
  }
}

std::uint32_t pbig_engine::stage_width(std::uint32_t n, std::uint32_t k) const {
  if (opt_.overlap_stage_width != 0) {
    for (const std::uint32_t w : stage_widths) {
      if (w >= opt_.overlap_stage_width) return w;
    }
    return stage_widths[std::size(stage_widths) - 1];
  }
  // A chunk's mean boxes in a cell (the plan's f = N alpha / M over k), and its spread.
  const double s = plan_.cells == 0 ? 0.0 : static_cast<double>(n) * plan_.alpha / static_cast<double>(plan_.cells) / k;
  const double fill = s + tuning::stage_width_spread * std::sqrt(s);
  if (fill <= 8.0) return 8;
  if (fill <= 16.0) return 16;
  return 64;
}

stage_lists pbig_engine::lists_of(std::uint32_t count) const {
  stage_lists l{};
  l.count = count;
  for (std::uint32_t i = 0; i < count; ++i) {
    l.prefix[i] = stages_[i].prefix.get();
    l.entries[i] = stages_[i].entries.get();
  }
  return l;
}

void pbig_engine::upload_chunk(const interest::box_set& boxes, std::uint32_t j, std::uint32_t first,
                               std::uint32_t count) {
  const std::size_t n = boxes.size();
  const float* src_f[6] = {boxes.lo_x.data(), boxes.lo_y.data(), boxes.lo_z.data(),
                           boxes.hi_x.data(), boxes.hi_y.data(), boxes.hi_z.data()};
  for (int a = 0; a < 6; ++a) {
    CUDA_CHECK(cudaMemcpyAsync(boxes_.coord() + a * n + first, src_f[a] + first, std::size_t{count} * 4,
                               cudaMemcpyHostToDevice, upload_));
  }
  // While the coordinates are copied: does the chunk share box 0's category and mask? Then those
  // arrays are filled on the device (as upload() does for the whole set), on the stage stream,
  // which reads them only after its wait for this chunk; the copy stream keeps copying.
  if (opt_.fill_uniform_classes && n >= tuning::uniform_classes_min_boxes &&
      uniform_classes(boxes, first, std::size_t{first} + count)) {
    CUDA_CHECK(launch_fill_u32(boxes_.bits() + first, count, boxes.category[0], stage_));
    CUDA_CHECK(launch_fill_u32(boxes_.bits() + n + first, count, boxes.mask[0], stage_));
    report_.bytes_in += 24ull * count;
  } else {
    CUDA_CHECK(cudaMemcpyAsync(boxes_.bits() + first, boxes.category.data() + first, std::size_t{count} * 4,
                               cudaMemcpyHostToDevice, upload_));
    CUDA_CHECK(cudaMemcpyAsync(boxes_.bits() + n + first, boxes.mask.data() + first, std::size_t{count} * 4,
                               cudaMemcpyHostToDevice, upload_));
    report_.bytes_in += 32ull * count;
    report_.classes_filled = false;
  }
  CUDA_CHECK(cudaEventRecord(ev_chunk_[j], upload_));
}

void pbig_engine::queue_stage_count(std::uint32_t n, std::uint32_t j, std::uint32_t first, std::uint32_t count,
                                    bool check) {
  const box_arrays chunk = chunk_of(boxes_.arrays(n), first);
  const auto cells = static_cast<std::uint32_t>(plan_.cells);
  CUDA_CHECK(cudaStreamWaitEvent(stage_, ev_chunk_[j], 0));
  CUDA_CHECK(cudaEventRecord(ev_staged_[j], stage_));
  if (check && j > 0)
    CUDA_CHECK(launch_validate(chunk, count, d_chunk_bounds_.get() + j, stage_));  // chunk 0: the plan's
  // queue_count's layout: counts[0, cells] (counts[cells] stays 0), the large-box counter, cursors.
  std::uint32_t* counts = d_counts_.get();
  std::uint32_t* large_counter = counts + cells + 1;
  CUDA_CHECK(cudaMemsetAsync(counts, 0, (2ull * cells + 2) * sizeof(std::uint32_t), stage_));
  CUDA_CHECK(
      launch_count(chunk, count, d_plan_.get(), cells, counts, d_is_large_.get() + first, large_counter, stage_));
  CUDA_CHECK(launch_pack_boxes(chunk, count, d_box_lo_.get() + first, d_box_hi_.get() + first, stage_));

  const stage_lists earlier = lists_of(j);
  cell_prefix* prefix = stages_[j].prefix.get();
  map_readback* rb = d_stage_rb_.get() + j;
  std::size_t scan_bytes = 0, reduce_bytes = 0;
  CUDA_CHECK(scan_stage_cells(nullptr, scan_bytes, counts, earlier, stage_width_, prefix, cells, stage_));
  CUDA_CHECK(reduce_stage_cells(nullptr, reduce_bytes, counts, earlier, stage_width_, &rb->totals, cells, stage_));
  if (std::max(scan_bytes, reduce_bytes) > d_temp_.capacity()) {
    throw std::logic_error("pbig: overlapped upload scratch not sized (internal error)");
  }
  CUDA_CHECK(scan_stage_cells(d_temp_.get(), scan_bytes, counts, earlier, stage_width_, prefix, cells, stage_));
  CUDA_CHECK(
      reduce_stage_cells(d_temp_.get(), reduce_bytes, counts, earlier, stage_width_, &rb->totals, cells, stage_));
  const std::uint32_t stages = static_cast<std::uint32_t>(report_.overlap_chunks);
  const std::uint32_t batches = std::max<std::uint32_t>(2, (tuning::max_batches + stages - 1) / stages);
  CUDA_CHECK(launch_batch_plan(d_plan_.get(), prefix, large_counter, rb, readback_limits(), tuning::min_tiles_per_batch,
                               batches, stage_));
  // The read-back written by the device into pinned memory: a copy would wait on the copy engine
  // behind the earlier stage's pairs, still being copied out, and hold this stage's map back.
  static_assert(sizeof(map_readback) % 4 == 0 && sizeof(bounds_dev) % 4 == 0);
  const bool bounds = check && j > 0;
  CUDA_CHECK(launch_to_host(rb, h_stage_rb_.get() + j, sizeof(map_readback), d_chunk_bounds_.get() + j,
                            h_chunk_bounds_.get() + j, bounds ? sizeof(bounds_dev) : 0, stage_));
  CUDA_CHECK(cudaEventRecord(ev_stage_counted_[j], stage_));
}

void pbig_engine::queue_stage_map(std::uint32_t n, std::uint32_t j, std::uint32_t first, std::uint32_t count) {
  const box_arrays chunk = chunk_of(boxes_.arrays(n), first);
  const auto cells = static_cast<std::uint32_t>(plan_.cells);
  overlap_stage& st = stages_[j];
  const map_readback& rb = st.rb;
  const map_readback* grid = d_stage_rb_.get() + j;
  // This call has not used these buffers yet (the other stages have their own), and the stage
  // stream has finished with d_entries_unsorted_ and d_temp_ (the host waited for this stage's
  // read-back, queued after the previous stage's map; the next stage's count comes after this).
  st.entries.reserve(rb.total.entry);
  st.items.reserve(rb.total.item);
  d_entries_unsorted_.reserve(rb.total.entry);
  CUDA_CHECK(cudaEventRecord(ev_map_begin_[j], stage_));
  if (rb.total.entry > 0) {
    CUDA_CHECK(launch_map(chunk, count, first, d_plan_.get(), grid, d_is_large_.get() + first, st.prefix.get(),
                          d_counts_.get() + cells + 2, d_entries_unsorted_.get(), stage_));
    // Each cell's list of the chunk by box id (determinism); a chunk's list is at most the cell's
    // boxes of chunks 0..j (max_count), so the one-kernel sort holds whenever that is small.
    if (rb.totals.max_count <= tuning::small_cell_sort) {
      CUDA_CHECK(
          launch_sort_small_cells(d_entries_unsorted_.get(), st.entries.get(), st.prefix.get(), cells, grid, stage_));
    } else {
      std::size_t sort_bytes = 0;
      CUDA_CHECK(sort_cells(nullptr, sort_bytes, d_entries_unsorted_.get(), st.entries.get(), rb.total.entry, cells,
                            st.prefix.get(), stage_));
      grow_temp(sort_bytes);
      CUDA_CHECK(sort_cells(d_temp_.get(), sort_bytes, d_entries_unsorted_.get(), st.entries.get(), rb.total.entry,
                            cells, st.prefix.get(), stage_));
    }
  }
  if (rb.total.item > 0) CUDA_CHECK(launch_expand(st.prefix.get(), cells, grid, st.items.get(), stage_));
  CUDA_CHECK(cudaEventRecord(ev_mapped_[j], stage_));
}

bool pbig_engine::run_overlapped(const interest::box_set& boxes, std::uint32_t n, std::uint32_t k, bool validate,
                                 std::uint64_t& pairs) {
  report_.overlap_chunks = k;
  report_.indirect_check = true;  // the stages read the boxes through their ids
  report_.classes_filled =
      opt_.fill_uniform_classes && n >= tuning::uniform_classes_min_boxes;  // until a chunk copies them
  indirect_ = true;
  validate_on_device_ = validate;
  std::uint32_t first[max_overlap_chunks + 1];
  for (std::uint32_t j = 0; j <= k; ++j) first[j] = static_cast<std::uint32_t>(std::uint64_t{n} * j / k);

  // A call that threw (an invalid grid, a wait past its limit) may have left its copies and class
  // fills queued: none of them may land under this call's (idle streams: no wait).
  CUDA_CHECK(cudaStreamSynchronize(upload_));
  CUDA_CHECK(cudaStreamSynchronize(stage_));
  // Everything the device writes before the plan is known is sized now (nothing grows under
  // queued work).
  boxes_.reserve(n);
  d_box_lo_.reserve(n);
  d_box_hi_.reserve(n);
  d_is_large_.reserve(n);

  // 1. Every chunk's upload, in order on upload_; the plan waits for chunk 0 only.
  CUDA_CHECK(cudaEventRecord(ev_start_, upload_));
  for (std::uint32_t j = 0; j < k; ++j) {
    upload_chunk(boxes, j, first[j], first[j + 1] - first[j]);
    if (j == 0) {
      CUDA_CHECK(cudaStreamWaitEvent(main_, ev_chunk_[0], 0));
      queue_plan(n, first[1]);
    }
  }
  CUDA_CHECK(cudaEventRecord(ev_in_, upload_));
  // Stop here with nothing pending on the caller's memory or on this call's buffers.
  auto abandon = [&] {
    CUDA_CHECK(cudaStreamSynchronize(upload_));
    CUDA_CHECK(cudaStreamSynchronize(stage_));
    for (auto& s : slot_) CUDA_CHECK(cudaStreamSynchronize(s.stream));
    CUDA_CHECK(cudaStreamSynchronize(main_));
    return false;
  };
  CUDA_CHECK(cudaEventRecord(ev_wait_, main_));
  wait_bounded(ev_wait_, "plan", 0, n);
  if (!read_plan()) return abandon();  // chunk 0 holds an invalid box
  const auto cells = static_cast<std::uint32_t>(plan_.cells);
  stage_width_ = stage_width(n, k);
  report_.stage_width = stage_width_;

  // 2. The per-cell arrays of every stage, and the scans' scratch, sized for the plan's grid.
  d_counts_.reserve(2ull * cells + 2);
  for (std::uint32_t j = 0; j < k; ++j) stages_[j].prefix.reserve(cells + 1ull);
  {
    std::size_t scan_bytes = 0, reduce_bytes = 0;
    const stage_lists all = lists_of(k - 1);
    CUDA_CHECK(scan_stage_cells(nullptr, scan_bytes, d_counts_.get(), all, stage_width_, stages_[0].prefix.get(), cells,
                                main_));
    CUDA_CHECK(reduce_stage_cells(nullptr, reduce_bytes, d_counts_.get(), all, stage_width_, &d_stage_rb_.get()->totals,
                                  cells, main_));
    grow_temp(std::max(scan_bytes, reduce_bytes));
  }

  // 3. Stage by stage; the direct-output pipeline (kernel g on one slot while batch g - 1's
  // pairs are copied out on the other) runs on across stages. The stage stream runs ahead: stage
  // j + 1's count is queued after stage j's map and waits for its chunk on the device; its map is
  // queued as soon as the host sees its read-back (map_next, polled between batches), so it is
  // ready when stage j's last batch has been launched.
  for (auto& s : slot_) {
    s.copy_pending = false;
    s.overcopied = false;
  }
  std::uint64_t base = 0;
  std::uint32_t launched = 0;  // batches launched so far (all stages)
  batch pending{};             // the last launched batch (number pending_index), not yet finished
  std::uint32_t pending_index = 0;
  bool has_pending = false;
  std::uint64_t entries = 0, checks = 0, large_total = 0;
  std::uint32_t max_count = 0;
  auto finish_pending = [&] {
    if (!has_pending) return;
    wait_bounded(slot_[pending_index % 2].totals_ready, "checks of a batch", static_cast<std::uint32_t>(pending.stage), n);
    base += finish_direct(pending, slot_[pending_index % 2], base, pending_index, pending_index + 1);
    has_pending = false;
  };
  std::uint32_t mapped = 0;  // stages whose map is queued; stage `mapped`'s count is queued (if < k)
  bool invalid = false;      // a later chunk's validation found an invalid box
  // Queues stage `mapped`'s map once its read-back is in (waiting for it when `wait`), then the
  // next stage's count. False when the read-back is not in yet, or its chunk is invalid.
  auto map_next = [&](bool wait) {
    const std::uint32_t j = mapped;
    if (!wait) {
      const cudaError_t e = cudaEventQuery(ev_stage_counted_[j]);
      if (e == cudaErrorNotReady) return false;
      if (e != cudaSuccess) CUDA_CHECK(e);
    }
    wait_bounded(ev_stage_counted_[j], "count and read-back", j, n);
    if (validate && j > 0 && h_chunk_bounds_.get()[j].bad != 0xffffffffu) {
      invalid = true;
      return false;
    }
    overlap_stage& st = stages_[j];
    st.rb = h_stage_rb_.get()[j];
    const map_readback& rb = st.rb;
    check_readback(rb, "stage " + std::to_string(j));
    entries += rb.totals.entries;
    checks += rb.totals.checks;
    max_count = std::max<std::uint32_t>(max_count, static_cast<std::uint32_t>(rb.totals.max_count));
    large_total += rb.large_count;
    queue_stage_map(n, j, first[j], first[j + 1] - first[j]);
    ++mapped;
    if (mapped < k) queue_stage_count(n, mapped, first[mapped], first[mapped + 1] - first[mapped], validate);
    return true;
  };
  queue_stage_count(n, 0, first[0], first[1] - first[0], validate);
  for (std::uint32_t j = 0; j < k; ++j) {
    if (mapped <= j) {
      // Stage j's read-back is not in yet: queue the previous stage's last copy before waiting.
      finish_pending();
      if (!map_next(true)) return abandon();
    }
    const std::vector<batch> batches = planned_batches(stages_[j].rb, static_cast<std::int32_t>(j));
    if (batches.empty()) continue;
    for (auto& s : slot_) CUDA_CHECK(cudaStreamWaitEvent(s.stream, ev_mapped_[j], 0));
    for (const batch& b : batches) {
      // One batch's checks at a time: the previous batch's (on the other slot) first, so each
      // batch's pairs are ready, and copied out, as soon as they can be (two batches' checks side by
      // side end together, and the first copy of a stage waits for both).
      if (launched > 0)
        CUDA_CHECK(cudaStreamWaitEvent(slot_[launched % 2].stream, slot_[(launched - 1) % 2].kernel_end, 0));
      launch_direct(b, slot_[launched % 2]);
      if (mapped < k && !map_next(false) && invalid) return abandon();
      finish_pending();
      pending = b;
      pending_index = launched++;
      has_pending = true;
    }
  }
  finish_pending();
  for (auto& s : slot_) account_copy(s);
  report_.batches = launched;
  // main_ runs the large-box passes below: after every stage's count (the large flags) and map.
  CUDA_CHECK(cudaStreamWaitEvent(main_, ev_mapped_[k - 1], 0));

  // 4. The boxes handled apart, over all n boxes (every chunk is on the device: main_ waited).
  rb_ = stages_[k - 1].rb;
  rb_.large_count = static_cast<std::uint32_t>(large_total);
  rb_.total.entry = static_cast<std::uint32_t>(entries);
  rb_.totals.entries = entries;
  rb_.totals.checks = checks;
  rb_.totals.max_count = max_count;
  if (large_total > 0) {
    d_large_.reserve(n);
    std::size_t select_bytes = 0;
    std::uint32_t* selected = &d_readback_.get()->large_count;
    CUDA_CHECK(select_large(nullptr, select_bytes, d_is_large_.get(), d_large_.get(), selected, n, main_));
    grow_temp(select_bytes);
    CUDA_CHECK(select_large(d_temp_.get(), select_bytes, d_is_large_.get(), d_large_.get(), selected, n, main_));
  }
  large_count_pass(n);
  CUDA_CHECK(cudaEventRecord(ev_wait_, main_));
  wait_bounded(ev_wait_, "count of the boxes handled apart", k - 1, n);
  CUDA_CHECK(cudaStreamSynchronize(main_));
  const std::uint64_t large_pairs = *h_large_total_.get();
  ensure_result(std::max<std::uint64_t>(1, base + large_pairs), base);
  large_write_pass(n, large_pairs, h_result_.get() + base);
  CUDA_CHECK(cudaStreamSynchronize(upload_));
  CUDA_CHECK(cudaStreamSynchronize(stage_));
  pairs = base + large_pairs;
  return true;
}

}  // namespace zone::gpu::detail
