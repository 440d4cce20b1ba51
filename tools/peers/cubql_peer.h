// The box-box self-join written the way a user of NVIDIA's cuBQL writes it (third_party/cubql:
// the vendored headers of github.com/NVIDIA/cuBQL, Apache-2.0): a peer for bench-peers. Plain
// C++ interface; the CUDA lives in cubql_peer.cu.
//
// Per call, on one stream: the boxes (page-locked AoS, 24 bytes a box) copied to the device,
// cuBQL's default GPU builder (cuBQL::gpuBuilder, BuildConfig defaults; or one of its Morton
// builders, cubql_builder) builds a binary BVH over them, then one thread per box queries the BVH
// with its own box (cuBQL::fixedBoxQuery), counting the boxes j > i it overlaps; a CUB exclusive scan gives each box its first slot and the total,
// which is read back; the same query fills the pairs (i, j) at those slots; the pairs are copied
// into page-locked host memory. Semantics as docs/architecture.md's: closed boxes (touching faces intersect,
// cuBQL's box_t::overlaps), no self pairs, each pair once with a < b, and, when category/mask
// arrays are given, the pair qualifies iff (category_a & mask_b) | (category_b & mask_a) != 0.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>

namespace zone::peers {

/// Where one call's time went (CUDA events on the stream; total is host wall time).
struct cubql_timing {
  double in_ms = 0;     ///< host-to-device copy of the boxes (and category/mask)
  double build_ms = 0;  ///< cuBQL::gpuBuilder (its allocations included)
  double count_ms = 0;  ///< counting query kernel
  double scan_ms = 0;   ///< CUB exclusive scan + read-back of the total (a synchronisation)
  double fill_ms = 0;   ///< filling query kernel
  double out_ms = 0;    ///< device-to-host copy of the pairs
  double total_ms = 0;  ///< wall time of run()
};

/// Which of cuBQL's GPU builders builds the BVH: cuBQL::gpuBuilder with the default BuildConfig
/// (an adaptive spatial-median builder; what its samples use), cuBQL::cuda::radixBuilder (Morton
/// codes) or cuBQL::cuda::rebinRadixBuilder (Morton codes, re-binned where the data needs it).
enum class cubql_builder { spatial_median, radix, rebin_radix };

/// Page-locked host memory for the peer's input (cudaMallocHost); freed by free_pinned.
[[nodiscard]] void* alloc_pinned(std::size_t bytes);
void free_pinned(void* p);

/// One cuBQL self-join engine: device and pinned buffers grow as needed and are kept between
/// calls (no allocation in a steady state except what cuBQL's builder allocates per build).
/// One call at a time. Throws std::runtime_error on a CUDA error.
class cubql_join {
 public:
  /// leaf_threshold: BuildConfig::makeLeafThreshold (0 = the builder's default).
  explicit cubql_join(int leaf_threshold = 0, cubql_builder builder = cubql_builder::spatial_median);
  ~cubql_join();
  cubql_join(const cubql_join&) = delete;
  cubql_join& operator=(const cubql_join&) = delete;

  /// boxes: n boxes of 6 floats (lo x, y, z, hi x, y, z) in page-locked memory (alloc_pinned);
  /// category, mask: n each in page-locked memory, or both null for the plain self-join (every
  /// overlapping pair qualifies). Returns the number of pairs; pairs() then points at 2 * that
  /// many ids (a, b, a, b, ...) in page-locked memory, valid until the next call.
  std::uint64_t run(const float* boxes, const std::uint32_t* category, const std::uint32_t* mask, std::size_t n);
  [[nodiscard]] const std::uint32_t* pairs() const;
  [[nodiscard]] const cubql_timing& timing() const;

  /// True when a CUDA device can be used.
  [[nodiscard]] static bool device_usable();

 private:
  struct impl;
  std::unique_ptr<impl> p_;
};

}  // namespace zone::peers
