// Dispatch of the GPU LBVH finder (see lbvh_dispatch.h and docs/gpu.md, "LBVH").
//
// One call, on the main stream unless said otherwise (Karras's five steps, then the output):
//  1. DataIn: the box arrays are packed into pinned staging memory by the thread pool in parts,
//     each part's host-to-device copy overlapping the packing of the next (validated on the way
//     when asked).
//  2. Scene bounds, mean edges and the OR/AND of the filter bits (block reductions); per box a
//     30-bit Morton code of its centroid, bit 30 set for boxes of mask 0 (pure targets get their
//     own subtree), or, for a box expected to overlap very many others, a key after every other
//     ("large": kept out of the tree); CUB radix sort of (key, id) pairs (stable: equal keys stay
//     in id order).
//  3. Hierarchy: one thread per internal node (determineRange / findSplit with __clz, equal codes
//     told apart by their sorted position), then bottom-up boxes and OR-ed filter bits with one
//     atomic flag per node.
//  4. Counting traversal: one thread per leaf in leaf order, an explicit stack, subtrees whose
//     rightmost leaf is not after the query skipped; pairs per leaf, overflow flags; CUB scan of
//     the counts, CUB select of the overflowed queries; one read-back (synchronisation 1).
//  5. Brute pass (only when there are large boxes or overflowed queries): per (query, chunk of
//     boxes) counts, scan, read-back of the total (synchronisation 2).
//  6. Writing traversal in batches of leaves on the main stream, each batch's pairs copied into the
//     pinned result on the copy stream while the next batch is written; then the brute pass writes.
#include "lbvh_dispatch.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>

#include "gpu/common/cuda_check.h"
#include "gpu/common/finder_input.h"
#include "interest/measure.h"
#include "lbvh_launch.h"
#include "lbvh_tuning.h"

namespace zone::gpu::detail::lbvh {

namespace {

using clock_type = std::chrono::steady_clock;

}  // namespace

lbvh_engine::lbvh_engine(const lbvh_options& options) : opt_(options) {
  CUDA_CHECK(cudaSetDevice(0));
  pool_ = pool_or_own(opt_.pool, own_pool_);
  CUDA_CHECK(cudaStreamCreateWithFlags(&main_, cudaStreamNonBlocking));
  CUDA_CHECK(cudaStreamCreateWithFlags(&copy_, cudaStreamNonBlocking));
  for (cudaEvent_t* e : {&ev_start_, &ev_in_, &ev_sort_begin_, &ev_sort_end_, &ev_built_, &ev_counted_, &ev_fill_begin_,
                         &ev_fill_end_, &ev_copy_begin_, &ev_copy_end_}) {
    CUDA_CHECK(cudaEventCreate(e));
  }
  for (cudaEvent_t& e : ev_batch_) CUDA_CHECK(cudaEventCreateWithFlags(&e, cudaEventDisableTiming));
  d_scene_.reserve(1);
  d_readback_.reserve(1);
  h_readback_.reserve(1);
  h_brute_total_.reserve(1);
  const std::size_t pairs = opt_.initial_output_pairs > 0 ? opt_.initial_output_pairs : lbvh_tuning::default_output_pairs;
  d_pairs_.reserve(2 * pairs);
  h_result_.reserve(pairs);
}

lbvh_engine::~lbvh_engine() {
  // No throwing here: errors at teardown are ignored.
  for (cudaStream_t s : {main_, copy_}) {
    if (s != nullptr) cudaStreamSynchronize(s);
  }
  for (cudaEvent_t e : {ev_start_, ev_in_, ev_sort_begin_, ev_sort_end_, ev_built_, ev_counted_, ev_fill_begin_,
                        ev_fill_end_, ev_copy_begin_, ev_copy_end_}) {
    if (e != nullptr) cudaEventDestroy(e);
  }
  for (cudaEvent_t e : ev_batch_) {
    if (e != nullptr) cudaEventDestroy(e);
  }
  for (cudaStream_t s : {main_, copy_}) {
    if (s != nullptr) cudaStreamDestroy(s);
  }
}

void lbvh_engine::grow_temp(std::size_t bytes) { d_temp_.reserve(std::max<std::size_t>(bytes, 256)); }

std::optional<std::uint64_t> lbvh_engine::run(const interest::box_set& boxes, interest::finder_stats& stats,
                                               bool validate) {
  const auto t0 = clock_type::now();
  const std::size_t count = boxes.size();
  if (count > std::numeric_limits<std::int32_t>::max() / 2) throw std::length_error("lbvh: too many boxes (2^30 at most)");
  if (count < 2) throw std::logic_error("lbvh: run needs at least 2 boxes");
  const auto n = static_cast<std::uint32_t>(count);
  report_ = {};

  CUDA_CHECK(cudaEventRecord(ev_start_, main_));
  const bool uploaded = boxes_.upload_staged(boxes, validate, pool_, main_, ev_in_, lbvh_tuning::upload_part_boxes,
                                             lbvh_tuning::max_upload_parts);
  report_.bytes_in += 32 * count;
  if (!uploaded) return std::nullopt;
  const box_arrays arrays = boxes_.arrays(n);

  // Keys, sort.
  scene* sc = d_scene_.get();
  CUDA_CHECK(launch_scene(arrays, n, sc, main_));
  const double threshold = opt_.separate_large
                               ? std::max(lbvh_tuning::large_min_overlaps, n / lbvh_tuning::large_n_divisor)
                               : std::numeric_limits<double>::infinity();
  d_keys_.reserve(n);
  d_keys_sorted_.reserve(n);
  d_ids_.reserve(n);
  d_ids_sorted_.reserve(n);
  CUDA_CHECK(launch_morton(arrays, n, sc, threshold, d_keys_.get(), d_ids_.get(), main_));
  std::size_t sort_bytes = 0;
  CUDA_CHECK(sort_keys(nullptr, sort_bytes, d_keys_.get(), d_keys_sorted_.get(), d_ids_.get(), d_ids_sorted_.get(), n,
                       main_));
  grow_temp(sort_bytes);
  CUDA_CHECK(cudaEventRecord(ev_sort_begin_, main_));
  CUDA_CHECK(sort_keys(d_temp_.get(), sort_bytes, d_keys_.get(), d_keys_sorted_.get(), d_ids_.get(),
                       d_ids_sorted_.get(), n, main_));
  CUDA_CHECK(cudaEventRecord(ev_sort_end_, main_));

  // Hierarchy and bottom-up boxes.
  d_leaf_lo_.reserve(n);
  d_leaf_hi_.reserve(n);
  d_nodes_.reserve(n);
  d_node_bits_.reserve(n);
  d_parent_.reserve(2 * std::size_t{n});
  d_flags_.reserve(n);
  CUDA_CHECK(launch_build(arrays, n, sc, d_keys_sorted_.get(), d_ids_sorted_.get(), d_leaf_lo_.get(), d_leaf_hi_.get(),
                          d_nodes_.get(), d_parent_.get(), d_flags_.get(), main_));
  CUDA_CHECK(launch_refit(d_leaf_lo_.get(), d_leaf_hi_.get(), n, sc, d_parent_.get(), d_nodes_.get(),
                          d_node_bits_.get(), d_flags_.get(), opt_.measure_depth, sc, main_));
  CUDA_CHECK(cudaEventRecord(ev_built_, main_));

  // Counting traversal, scan, overflowed queries, read-back.
  d_counts_.reserve(std::size_t{n} + 1);
  d_overflowed_.reserve(n);
  d_pos_.reserve(std::size_t{n} + 1);
  d_ov_list_.reserve(n);
  traverse_args ta{};
  ta.nodes = d_nodes_.get();
  ta.node_bits = d_node_bits_.get();
  ta.leaf_lo = d_leaf_lo_.get();
  ta.leaf_hi = d_leaf_hi_.get();
  ta.ids = d_ids_sorted_.get();
  ta.sc = sc;
  ta.n = n;
  ta.stack_cap = opt_.stack_entries == 0 ? lbvh_tuning::max_stack
                                          : std::min<std::uint32_t>(opt_.stack_entries, lbvh_tuning::max_stack);
  ta.counts = d_counts_.get();
  ta.overflowed = d_overflowed_.get();
  ta.pos = d_pos_.get();
  CUDA_CHECK(launch_traverse(ta, /*count_only=*/true, main_));
  readback* rb = d_readback_.get();
  std::size_t scan_bytes = 0, select_bytes = 0;
  CUDA_CHECK(scan_counts(nullptr, scan_bytes, d_counts_.get(), d_pos_.get(), std::uint64_t{n} + 1, main_));
  CUDA_CHECK(select_overflowed(nullptr, select_bytes, d_overflowed_.get(), d_ov_list_.get(), &rb->overflow_count, n,
                               main_));
  grow_temp(std::max(scan_bytes, select_bytes));
  CUDA_CHECK(scan_counts(d_temp_.get(), scan_bytes, d_counts_.get(), d_pos_.get(), std::uint64_t{n} + 1, main_));
  CUDA_CHECK(select_overflowed(d_temp_.get(), select_bytes, d_overflowed_.get(), d_ov_list_.get(), &rb->overflow_count,
                               n, main_));
  const std::uint32_t batches = std::clamp<std::uint32_t>((n + lbvh_tuning::leaves_per_batch - 1) / lbvh_tuning::leaves_per_batch,
                                                          1, lbvh_tuning::max_batches);
  CUDA_CHECK(launch_readback(d_pos_.get(), n, batches, sc, rb, main_));
  CUDA_CHECK(cudaMemcpyAsync(h_readback_.get(), rb, sizeof(readback), cudaMemcpyDeviceToHost, main_));
  CUDA_CHECK(cudaEventRecord(ev_counted_, main_));
  CUDA_CHECK(cudaStreamSynchronize(main_));
  const readback r = *h_readback_.get();
  const std::uint64_t tree_total = r.batch_pos[batches];
  const std::uint32_t leaves = n - r.large_count;

  // Brute pass: counts and their total (synchronisation 2), only when it has queries.
  brute_args ba{};
  ba.leaf_lo = d_leaf_lo_.get();
  ba.leaf_hi = d_leaf_hi_.get();
  ba.ids = d_ids_sorted_.get();
  ba.sc = sc;
  ba.ov_list = d_ov_list_.get();
  ba.ov_count = r.overflow_count;
  ba.queries = r.overflow_count + r.large_count;
  ba.chunks = (n + lbvh_tuning::brute_chunk - 1) / lbvh_tuning::brute_chunk;
  ba.n = n;
  std::uint64_t brute_total = 0;
  const std::uint64_t items = static_cast<std::uint64_t>(ba.queries) * ba.chunks;
  if (items > 0) {
    if (items >= (1ull << 31)) throw std::length_error("lbvh: too many large boxes for the brute pass");
    d_item_counts_.reserve(items + 1);
    d_item_pos_.reserve(items + 1);
    ba.item_counts = d_item_counts_.get();
    CUDA_CHECK(cudaMemsetAsync(d_item_counts_.get() + items, 0, sizeof(std::uint32_t), main_));
    CUDA_CHECK(launch_brute(ba, /*count_only=*/true, main_));
    std::size_t bytes = 0;
    CUDA_CHECK(scan_counts(nullptr, bytes, d_item_counts_.get(), d_item_pos_.get(), items + 1, main_));
    grow_temp(bytes);
    CUDA_CHECK(scan_counts(d_temp_.get(), bytes, d_item_counts_.get(), d_item_pos_.get(), items + 1, main_));
    CUDA_CHECK(cudaMemcpyAsync(h_brute_total_.get(), d_item_pos_.get() + items, sizeof(std::uint64_t),
                               cudaMemcpyDeviceToHost, main_));
    CUDA_CHECK(cudaStreamSynchronize(main_));
    brute_total = *h_brute_total_.get();
  }
  const std::uint64_t total = tree_total + brute_total;

  // Writing passes; batch k's copy overlaps batch k + 1's traversal.
  d_pairs_.reserve(2 * std::max<std::uint64_t>(total, 1));
  h_result_.reserve(std::max<std::uint64_t>(total, 1));
  ta.out = d_pairs_.get();
  auto copy_out = [&](std::uint64_t first, std::uint64_t last, cudaEvent_t ready) {
    if (last <= first) return;
    CUDA_CHECK(cudaEventRecord(ready, main_));
    CUDA_CHECK(cudaStreamWaitEvent(copy_, ready, 0));
    CUDA_CHECK(cudaMemcpyAsync(h_result_.get() + first, d_pairs_.get() + 2 * first, (last - first) * sizeof(interest::id_pair),
                               cudaMemcpyDeviceToHost, copy_));
    report_.bytes_out += (last - first) * sizeof(interest::id_pair);
  };
  CUDA_CHECK(cudaEventRecord(ev_fill_begin_, main_));
  CUDA_CHECK(cudaStreamWaitEvent(copy_, ev_fill_begin_, 0));
  CUDA_CHECK(cudaEventRecord(ev_copy_begin_, copy_));
  if (tree_total > 0) {
    for (std::uint32_t k = 0; k < batches; ++k) {
      ta.first = static_cast<std::uint32_t>(std::uint64_t{leaves} * k / batches);
      ta.last = static_cast<std::uint32_t>(std::uint64_t{leaves} * (k + 1) / batches);
      if (r.batch_pos[k + 1] == r.batch_pos[k]) continue;
      CUDA_CHECK(launch_traverse(ta, /*count_only=*/false, main_));
      copy_out(r.batch_pos[k], r.batch_pos[k + 1], ev_batch_[k]);
    }
  }
  if (brute_total > 0) {
    ba.item_pos = d_item_pos_.get();
    ba.base = tree_total;
    ba.out = d_pairs_.get();
    CUDA_CHECK(launch_brute(ba, /*count_only=*/false, main_));
    copy_out(tree_total, total, ev_batch_[max_batch_events - 1]);
  }
  CUDA_CHECK(cudaEventRecord(ev_fill_end_, main_));
  CUDA_CHECK(cudaEventRecord(ev_copy_end_, copy_));
  CUDA_CHECK(cudaStreamSynchronize(copy_));
  CUDA_CHECK(cudaStreamSynchronize(main_));

  report_.data_in_ms = elapsed_ms(ev_start_, ev_in_);
  report_.build_ms = elapsed_ms(ev_in_, ev_built_);
  report_.sort_ms = elapsed_ms(ev_sort_begin_, ev_sort_end_);
  report_.count_ms = elapsed_ms(ev_built_, ev_counted_);
  report_.fill_ms = elapsed_ms(ev_fill_begin_, ev_fill_end_);
  report_.data_out_ms = elapsed_ms(ev_copy_begin_, ev_copy_end_);
  report_.pairs = total;
  report_.tree_boxes = leaves;
  report_.large_boxes = r.large_count;
  report_.stack_overflows = r.overflow_count;
  report_.batches = batches;
  report_.max_depth = r.max_depth;
  report_.total_ms = ms_since(t0);
  stats.large_boxes = r.large_count;
  return total;
}

}  // namespace zone::gpu::detail::lbvh
