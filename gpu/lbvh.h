// Public API of the GPU LBVH pair finder: Karras's linear bounding volume hierarchy ("Thinking
// Parallel", Parts I-III, and HPG 2012; ../shared/papers/) on CUDA. Built only when CUDA is found;
// without it make_lbvh_finder returns null with the reason, like make_pbig_finder. See docs/gpu.md, "LBVH".
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>

#include "interest.h"

namespace zone::gpu {

/// Options of the LBVH finder.
struct lbvh_options {
  /// Initial capacity of the device output buffers, in pairs (0 = default). Buffers grow to the
  /// exact size a call needs (count-then-fill); tiny values make every call grow them.
  std::size_t initial_output_pairs = 0;
  /// Entries of each traversal thread's explicit stack (0 = the default, tuning::stack_entries,
  /// which the tree's depth bound never exceeds). A query whose stack would overflow stops its
  /// traversal and is redone by the overflow pass (one block tests it against every later leaf),
  /// so no pair is lost whatever this is; tests set it tiny to force that path.
  std::uint32_t stack_entries = 0;
  /// Boxes expected to overlap many others (more than max(large_min_overlaps, N / 64) under a
  /// uniform-density estimate) are kept out of the tree and tested against every box by a
  /// separate pass (the serial tail of one thread per leaf otherwise). false: every box in the tree.
  bool separate_large = true;
  /// Measure the depth of the deepest leaf each call (lbvh_report::max_depth; one extra kernel).
  bool measure_depth = false;
  /// Threads that pack the upload (null = own pool with one thread per core).
  interest::thread_pool* pool = nullptr;
};

/// Where the time of the last call went (CUDA events on the GPU timeline; total is host wall time).
struct lbvh_report {
  double data_in_ms = 0;   ///< pack into pinned memory + host-to-device copy
  double build_ms = 0;     ///< scene bounds, Morton codes, radix sort, hierarchy, bottom-up boxes
  double sort_ms = 0;      ///<   of which: the CUB radix sort
  double count_ms = 0;     ///< traversal pass 1 (pairs per leaf) + scan + large-box count
  double fill_ms = 0;      ///< traversal pass 2 (writing pairs), all batches
  double data_out_ms = 0;  ///< device-to-host copies of the pairs
  double total_ms = 0;     ///< wall time of the whole call (after validation)
  std::uint64_t pairs = 0;
  std::uint64_t bytes_in = 0, bytes_out = 0;
  std::uint32_t tree_boxes = 0;      ///< boxes in the hierarchy
  std::uint32_t large_boxes = 0;     ///< boxes handled apart
  std::uint32_t stack_overflows = 0; ///< queries redone by the overflow pass
  std::uint32_t batches = 0;
  std::uint32_t max_depth = 0;       ///< depth of the deepest leaf (root = 0; with measure_depth)
};

/// Creates the GPU LBVH finder, or returns null with the reason in `why` when no device can be used.
[[nodiscard]] std::unique_ptr<interest::pair_finder> make_lbvh_finder(const lbvh_options& options = {},
                                                                      std::string* why = nullptr);

/// The report of the last successful call of a finder made by make_lbvh_finder; null otherwise.
[[nodiscard]] const lbvh_report* last_lbvh_report(const interest::pair_finder& finder);

/// Zero-copy variant of `finder.find` for a finder made by make_lbvh_finder (like
/// gpu::find_pairs_view for PBIG): validates the boxes while packing them for the upload (same
/// first-error report as interest::validate), finds the same pairs in the same order as `find`
/// into the finder's pinned result buffer, reused across calls; `view` stays valid until the
/// finder's next call. Throws std::invalid_argument for any other finder.
[[nodiscard]] std::optional<interest::box_error> find_lbvh_view(interest::pair_finder& finder,
                                                                const interest::box_set& boxes,
                                                                std::span<const interest::id_pair>& view);

}  // namespace zone::gpu
