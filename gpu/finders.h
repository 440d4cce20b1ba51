// Choosing a pair finder by name: the brute-force reference, the CPU grid finder, the GPU PBIG
// finder, the GPU LBVH finder, or `auto`, a finder that picks one of them per call. Plain C++:
// works in builds without CUDA (then only the CPU finders exist and `auto` is the CPU finder).
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>

#include "interest.h"

namespace zone::gpu {

/// The finders make_finder can build. `auto_select` decides per call (see make_auto_finder).
enum class finder_backend { brute, cpu, pbig, lbvh, auto_select };

/// "brute", "cpu", "gpu" (= pbig), "pbig", "lbvh", "auto"; anything else: nothing.
[[nodiscard]] std::optional<finder_backend> parse_backend(std::string_view name);

/// The canonical name of a backend ("brute", "cpu", "pbig", "lbvh", "auto").
[[nodiscard]] std::string_view backend_name(finder_backend backend);

/// Builds a finder. `pool` (may be null: the calling thread only) runs the CPU finders and the GPU
/// finders' host-side packing and copies; it must outlive the finder. Returns null with the reason
/// in `why` when the backend cannot run here (a GPU backend without a usable device or in a build
/// without CUDA). brute, cpu and auto never fail.
[[nodiscard]] std::unique_ptr<interest::pair_finder> make_finder(finder_backend backend, interest::thread_pool* pool,
                                                                 std::string* why = nullptr);

/// Builds a finder by name: parse_backend's names, and "cpu-1t" (the CPU grid finder on the calling
/// thread only). `grid` tunes the CPU grid finder of "cpu" and "cpu-1t". Returns null with the
/// reason in `why` for an unknown name ("unknown finder 'x' (brute, cpu, cpu-1t, gpu, pbig, lbvh,
/// auto)") and for a backend that cannot run here ("finder 'x' cannot run here: ..."). The one
/// place that maps a user's finder name to a finder (zone-server's --finder, bench-zone's).
[[nodiscard]] std::unique_ptr<interest::pair_finder> make_finder(std::string_view name, interest::thread_pool* pool,
                                                                 std::string* why = nullptr,
                                                                 const interest::grid_finder_options& grid = {});

/// Cheap statistics of a box set that the auto finder decides on: read from a fixed stratified
/// sample of at most `auto_sample_boxes` boxes (the same boxes every call for a given N), so the
/// cost does not grow with N (0.1-1.5 ms on the 2-core build machine; the auto finder amortises it, see
/// auto_redecide_calls).
struct box_set_summary {
  std::size_t n = 0;
  std::size_t sampled = 0;
  double scene_extent[3]{0, 0, 0};  ///< extent of the sample's boxes per axis
  double mean_size = 0;             ///< mean over the sample of a box's largest edge
  double size_spread = 0;           ///< largest sampled edge / median sampled edge (1 = all alike)
  double cell_edge = 0;             ///< the cubic cell edge a grid planned by Eq. 6 (W = 32) would get, estimated
  double largest_cells = 0;         ///< cells of that grid the largest sampled box would occupy
  double mean_cells = 0;            ///< cells the average sampled box would occupy (the paper's alpha)
  /// Fraction of sampled boxes that the grid finders would handle apart (more than
  /// max(64, 16 mean_cells) cells), and that fraction times N: PBIG tests each such box against
  /// all N boxes, so large_estimate * N estimates its large-box pass's tests.
  double large_fraction = 0;
  double large_estimate = 0;
  /// How crowded the planned grid's cells are compared with boxes spread evenly over the scene:
  /// M * sum over cells of p_c^2 (p_c: share of the boxes whose centre lies in cell c), estimated
  /// from pairs of sampled boxes that share a cell. About 1 for uniform sets, about 20 for the
  /// paper's Gaussian set (dense in its centre).
  double crowding = 0;
  /// Every array of the set lies in memory page-locked by a live pinned_boxes (boxes_pinned): PBIG
  /// then uploads it by DMA and validates it on the device, while LBVH still stages it on the host.
  bool pinned = false;
};
inline constexpr std::size_t auto_sample_boxes = 8192;

[[nodiscard]] box_set_summary summarize(const interest::box_set& boxes);

/// The auto rule: which finder a set with this summary goes to, given which GPU finders can run;
/// the reason in words in `reason`. See docs/gpu.md ("The auto finder and its rule") for the rule and the measurements behind it
/// (a pinned set goes to PBIG unless it is small or PBIG's large-box pass would be quadratic).
[[nodiscard]] finder_backend choose_backend(const box_set_summary& summary, bool pbig_usable, bool lbvh_usable,
                                            std::string* reason = nullptr);

/// The auto rule's constants (docs/gpu.md has the measurements behind them).
inline constexpr std::size_t auto_small_n = 20000;          ///< below, with size spread below auto_even_spread: LBVH
inline constexpr double auto_large_pass_tests = 4e9;        ///< above (large_estimate * N): LBVH
inline constexpr double auto_crowding = 4.0;                ///< above, with size spread below auto_even_spread: LBVH
inline constexpr double auto_even_spread = 4.0;
inline constexpr double auto_many_cells = 10.0;             ///< mean cells per box above: LBVH
/// The auto finder re-summarizes when N moved by more than this fraction since its last decision,
/// when the set's pinned state (boxes_pinned) changed, or after auto_redecide_calls calls; in
/// between it keeps its choice (the statistics of a zone
/// move slowly; a decision costs a sample of auto_sample_boxes boxes).
inline constexpr double auto_redecide_n_change = 0.10;
inline constexpr int auto_redecide_calls = 64;

/// The auto finder with explicit candidates (tests inject failing or counting finders here; null
/// GPU candidates mean "not available"). Per call: summarize and choose_backend (when due, see
/// above), run the choice; the choice and its reason are logged (spdlog info) when they change,
/// not every call. A GPU finder
/// that throws (a CUDA error) is logged as a warning and never used again by this finder; that
/// call and all later ones run on `cpu`. `cpu` must not be null.
[[nodiscard]] std::unique_ptr<interest::pair_finder> make_auto_finder(std::unique_ptr<interest::pair_finder> cpu,
                                                                      std::unique_ptr<interest::pair_finder> pbig,
                                                                      std::unique_ptr<interest::pair_finder> lbvh,
                                                                      interest::thread_pool* pool);

/// For a finder made by make_auto_finder / make_finder(auto_select): the backend of its last call
/// (nothing before the first call); null `finder` or another finder: nothing.
[[nodiscard]] std::optional<finder_backend> last_auto_choice(const interest::pair_finder& finder);

/// Zero-copy find for the GPU finders and the auto finder: validates, finds the same pairs as
/// `finder.find` into a buffer the finder owns and reuses, and points `view` at them (valid until
/// the finder's next call). When auto runs the CPU finder, the pairs are found into a list the auto
/// finder owns. Throws std::invalid_argument for any other finder (brute, cpu: those whose
/// pair_finder::views_own_buffer() is false). See gpu::find_pairs_view for the PBIG details.
[[nodiscard]] std::optional<interest::box_error> find_view(interest::pair_finder& finder,
                                                           const interest::box_set& boxes,
                                                           std::span<const interest::id_pair>& view);

}  // namespace zone::gpu
