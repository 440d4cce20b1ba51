// Public API of the GPU PBIG pair finder (Lo, Lee, Chung & Chung 2013) on CUDA. Built only when
// CUDA is found; without it every entry point reports that the build has no GPU backend, so
// callers (the `auto` choice) fall back to the CPU finder. Device discovery and pinned box sets,
// which every GPU finder and engine shares, are in device.h (included here).
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>

#include "device.h"
#include "interest.h"

namespace zone::gpu {

/// Options of the PBIG finder (each optimisation can be switched off for ablation).
struct pbig_options {
  bool load_balancing = true;  ///< Eq. 7 / Algorithm 2 assignment of checks to threads
  bool compression = true;     ///< 3-level encoding of pairs (Eq. 8)
  bool pipelining = true;      ///< 3-stage pipeline: check, device-to-host copy, decode
  double fixed_cell_edge = 0;  ///< 0 = plan by Eq. 6
  std::size_t initial_output_pairs = 0;  ///< initial output buffer capacity (0 = default); tiny values force the overflow path
  interest::thread_pool* decode_pool = nullptr;  ///< threads that decode the output (null = own pool)
  /// Beyond the paper (default: the fastest measured on the H100, docs/gpu-benchmarks.md): one
  /// checking pass per batch writes plain chunks (the paper's plain output), then on the GPU a scan
  /// of the per-tile pair counts and a placing kernel put each tile's pairs at its position (tile
  /// order: deterministic), and each batch is copied straight into a pinned result buffer: no CPU
  /// decode, and `compression` is unused. false = the paper's output: chunks (3-level encoded when
  /// `compression`, else plain), copied through the Fig. 7 pipeline and decoded on the CPU.
  bool direct_output = true;
  bool reuse_plan = true;  ///< keep the previous cell edge while the box statistics barely move
  /// Beyond the paper (with direct_output and pipelining): after a call of one batch (a small
  /// set), the next call is queued whole on the device, its buffers sized by the last call's
  /// figures plus a margin, the plan and totals read by the kernels from device memory, with one
  /// host synchronisation at the end; a grid that outgrew that capacity is re-run with the sizes
  /// read back (pbig_report::requeued), an overflowing output buffer as always. false = every
  /// call reads the plan and the map totals back before sizing what follows (three synchronisations).
  bool single_queue = true;
  double min_boxes_per_cell = 32.0;  ///< Eq. 6's W (the warp width)
  /// Beyond the paper (default; docs/gpu.md, "PLAN"): Eq. 6's edge and a few larger ones (each
  /// still with f >= W) are scored on the sample by a cost calibrated on the H100 (cell entries
  /// mapped, grid cells, estimated pair checks) and the cheapest is used. false = the paper's
  /// pure Eq. 6 (smallest edge with f >= W), for the paper's figures and the ablation.
  bool cost_aware_plan = true;
  /// Beyond the paper: from this many boxes on, the checking kernel reads each box through its id
  /// from the id-ordered box array instead of a copy gathered in cell order, so no gather kernel
  /// runs between the mapping and the first check (about 1.1 ms of 3.6 ms of MAP at 10^7 uniform
  /// boxes), at the price of scattered reads in the checks, which large sets hide behind the
  /// output copy. 0 = always, SIZE_MAX = never (the paper's box array).
  std::size_t indirect_check_min_boxes = std::size_t{1} << 22;
  /// Beyond the paper: pinned input of at least 2^18 boxes that all share one category and one
  /// mask (checked on the host while the coordinates are copied) has those two arrays filled on
  /// the device instead of copied: 24 bytes a box in instead of 32. false = always copied.
  bool fill_uniform_classes = true;
  /// Beyond the paper (with direct_output and pipelining, for pinned input: `pinned_boxes`): from
  /// this many boxes on, the boxes go to the device in `overlap_chunks` chunks of ids and, once
  /// chunk j has landed, the pairs whose larger id is in chunk j are found and copied out while
  /// the later chunks upload, so the boxes-in and pairs-out copies run at once (docs/gpu.md,
  /// "Overlapped upload"). The grid is planned from the first chunk. The same pairs as without it,
  /// in another order that also depends only on the input (and on the chunk count). It is taken
  /// only when it pays: when the finder's previous call, on a set of about this size, wrote at most
  /// about 3x the bytes it uploaded (pbig_tuning.h, overlap_max_out_in); a first call runs one-shot.
  /// 0 = the default (2^22 boxes, pbig_tuning.h), SIZE_MAX = never.
  std::size_t overlap_min_boxes = 0;
  std::uint32_t overlap_chunks = 0;  ///< chunks of the overlapped upload: 0 = the default (3), at most 8
  /// true: the overlapped upload on every call from overlap_min_boxes on, whatever the previous
  /// call's output (tests and benchmarks force it so).
  bool overlap_always = false;
  /// The overlapped upload's stage width W (docs/gpu.md, "Overlapped upload"): W boxes of a
  /// chunk's cell list a work item of the stage checks, W columns a tile: 8, 16, 32 or 64 (another
  /// value: the next of those up, 64 past it). 0 = chosen per call from the plan's boxes per cell
  /// and the chunk count (pbig_tuning.h, stage_width_spread). The same pairs at every width; their
  /// order depends on it (tests and benchmarks force it).
  std::uint32_t overlap_stage_width = 0;
};

/// Where the time of the last call went (the paper's Table V/VI tasks) and what it moved.
/// Device phases are timed with CUDA events on the GPU timeline; REPORT is host time. With
/// pipelining, CHECK, DataOut and REPORT overlap: pipeline_ms is their wall time together.
struct pbig_report {
  double data_in_ms = 0;   ///< DataIn: pack into pinned memory + host-to-device copy of the boxes
  double plan_ms = 0;      ///< PLAN: bounds and Eq. 6 planning kernels, plan read back
  double map_ms = 0;       ///< MAP: count, scan, map, per-cell sort by id, gather
  double map_count_ms = 0;    ///<   of which: count kernel, select, scans, totals (up to the read-back)
  double map_scatter_ms = 0;  ///<   of which: totals read back, map kernel
  double map_sort_ms = 0;     ///<   of which: per-cell sort by box id (CUB segmented sort)
  double map_gather_ms = 0;   ///<   of which: gather of the packed box array
  double sched_ms = 0;     ///< SCHED: work items (cell, segment) for the checking blocks
  double check_ms = 0;     ///< CHECK: checking kernels (sum over batches, re-runs included)
  double data_out_ms = 0;  ///< DataOut: device-to-host copies (the copies' spans, overlaps counted once)
  double report_ms = 0;    ///< REPORT: CPU decode into the pair list (sum over batches)
  double large_ms = 0;     ///< boxes handled apart from the grid (host wall time)
  double pipeline_ms = 0;  ///< wall time of CHECK + DataOut + REPORT together
  double total_ms = 0;     ///< wall time of the whole call (after validation)
  std::uint64_t bytes_in = 0;   ///< host-to-device bytes
  std::uint64_t bytes_out = 0;  ///< device-to-host bytes (pairs output, tile index, box array)
  std::uint64_t pairs = 0;
  std::uint32_t batches = 0;
  std::uint32_t reruns = 0;     ///< batches re-run after an output buffer overflow
  bool plan_reused = false;
  bool single_queue = false;  ///< queued whole with the last call's capacity (one synchronisation)
  bool requeued = false;      ///< ... and the grid outgrew it: re-run with read-back sizing
  /// Pinned input of at least tuning::uniform_classes_min_boxes boxes that all share one category
  /// and one mask: those arrays were filled on the device, not copied (24 bytes a box in, not 32).
  bool classes_filled = false;
  bool indirect_check = false;  ///< the checks read boxes through their ids (no gather; indirect_check_min_boxes)
  /// The overlapped upload's chunk count (pbig_options::overlap_min_boxes), 0 when the call did
  /// not use it. Then plan_ms is from the first chunk's arrival to the plan, map_ms the stages'
  /// MAP summed, and CHECK, DataOut and the later chunks' DataIn overlap.
  std::uint32_t overlap_chunks = 0;
  std::uint32_t stage_width = 0;  ///< the overlapped upload's stage width W (pbig_options::overlap_stage_width), else 0
  double alpha = 0;
};

/// The report of the last successful call of a finder made by make_pbig_finder; null for any
/// other finder.
[[nodiscard]] const pbig_report* last_pbig_report(const interest::pair_finder& finder);

/// Zero-copy variant of `finder.find` for a finder made by make_pbig_finder: validates the boxes
/// (in parallel on the finder's decode threads; same rule and same first-error report as
/// interest::validate), then finds the same pairs in the same order as `find` would, decoded into
/// a buffer the finder owns and reuses across calls (grown only when a call needs more), so
/// neither a single-threaded validation pass nor the value-initialisation of a std::vector that
/// grows from empty is paid per call. `view` stays valid until the finder's next call or its
/// destruction. Throws std::invalid_argument for any other finder.
[[nodiscard]] std::optional<interest::box_error> find_pairs_view(interest::pair_finder& finder,
                                                                 const interest::box_set& boxes,
                                                                 std::span<const interest::id_pair>& view);

/// Creates the GPU PBIG finder, or returns null with the reason in `why` when no device can be used.
[[nodiscard]] std::unique_ptr<interest::pair_finder> make_pbig_finder(const pbig_options& options = {},
                                                                      std::string* why = nullptr);

}  // namespace zone::gpu
