// Public API of the interest core: boxes, pairs, the pair_finder interface and its CPU backends,
// data-set generators and box-file formats. Other layers include this header, and thread_pool.h
// where they construct or drive the worker threads.
//
// Semantics (docs/architecture.md, "Semantics"): boxes are closed; the pair {a, b}, a != b,
// qualifies iff the boxes intersect on every axis (lo_a <= hi_b and lo_b <= hi_a) and
// ((category_a & mask_b) != 0 or (category_b & mask_a) != 0).
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <type_traits>
#include <utility>
#include <optional>
#include <random>
#include <span>
#include <string>
#include <string_view>
#include <vector>

namespace zone::interest {

/// The worker threads the finders run on (thread_pool.h: construct one there). May be null
/// wherever a pool is taken: the calling thread runs everything then.
class thread_pool;

/// Box id: the 0-based index of a box in its box_set.
using box_id = std::uint32_t;

/// One box, as a value. Storage uses box_set (structure of arrays).
struct box {
  float lo[3]{0, 0, 0};
  float hi[3]{0, 0, 0};
  std::uint32_t category = 1;
  std::uint32_t mask = 1;
};

/// A set of axis-aligned boxes in structure-of-arrays layout: one float array per bound and axis,
/// one 32-bit array each for category and mask. Indices are box ids.
class box_set {
 public:
  std::vector<float> lo_x, lo_y, lo_z, hi_x, hi_y, hi_z;
  std::vector<std::uint32_t> category, mask;

  [[nodiscard]] std::size_t size() const { return lo_x.size(); }
  [[nodiscard]] bool empty() const { return lo_x.empty(); }
  void clear();
  void reserve(std::size_t n);
  /// Resizes every array; new boxes are zero-size at the origin with category = mask = 1.
  void resize(std::size_t n);
  void push_back(const box& b);
  void set(std::size_t i, const box& b);
  [[nodiscard]] box get(std::size_t i) const;
  /// Bytes of box data held (what a transfer of the set would move).
  [[nodiscard]] std::size_t byte_size() const { return size() * (6 * sizeof(float) + 2 * sizeof(std::uint32_t)); }
};

/// Why a box set was rejected: the first offending box and a readable reason.
struct box_error {
  std::size_t index = 0;
  std::string message;  ///< e.g. "box 17: lo.x = 5 > hi.x = 4"
};

/// Checks every box: no NaN or infinite coordinate, lo <= hi on every axis.
/// Returns the first invalid box (lowest index), or nothing when the set is valid. With a pool,
/// the scan is split over its threads (the answer is the same).
[[nodiscard]] std::optional<box_error> validate(const box_set& boxes, thread_pool* pool = nullptr);

/// validate()'s rule for one box, as a branch-free test for hot scans: lo <= hi on every axis (false
/// for NaN) and every bound finite. validate_box says why a box fails it.
[[nodiscard]] inline bool valid_bounds(float lo_x, float lo_y, float lo_z, float hi_x, float hi_y, float hi_z) {
  return lo_x <= hi_x && lo_y <= hi_y && lo_z <= hi_z && std::isfinite(lo_x) && std::isfinite(hi_x) &&
         std::isfinite(lo_y) && std::isfinite(hi_y) && std::isfinite(lo_z) && std::isfinite(hi_z);
}

/// Validates one box; `index` is only used in the message.
[[nodiscard]] std::optional<box_error> validate_box(const box& b, std::size_t index);

/// The exact test of the contract: closed intersection plus the category/mask rule.
[[nodiscard]] inline bool qualifies(const box_set& s, std::size_t a, std::size_t b) {
  return s.lo_x[a] <= s.hi_x[b] && s.lo_x[b] <= s.hi_x[a] &&  //
         s.lo_y[a] <= s.hi_y[b] && s.lo_y[b] <= s.hi_y[a] &&  //
         s.lo_z[a] <= s.hi_z[b] && s.lo_z[b] <= s.hi_z[a] &&  //
         ((s.category[a] & s.mask[b]) | (s.category[b] & s.mask[a])) != 0;
}

/// An unordered pair of box ids, stored with a < b. (No default member values: a pair_list that
/// grows to hold a finder's output is not zero-filled first; id_pair{} is still {0, 0}.)
struct id_pair {
  box_id a;
  box_id b;
  friend bool operator==(const id_pair&, const id_pair&) = default;
  friend auto operator<=>(const id_pair&, const id_pair&) = default;
};

/// An allocator whose resize() leaves new trivially-constructible elements uninitialised, so
/// finders that size their output and then fill it do not pay for a zero-fill pass.
template <class T>
struct default_init_allocator : std::allocator<T> {
  template <class U>
  struct rebind {
    using other = default_init_allocator<U>;
  };
  using std::allocator<T>::allocator;
  template <class U>
  void construct(U* p) noexcept(std::is_nothrow_default_constructible_v<U>) {
    ::new (static_cast<void*>(p)) U;
  }
  template <class U, class... Args>
  void construct(U* p, Args&&... args) {
    ::new (static_cast<void*>(p)) U(std::forward<Args>(args)...);
  }
};

using pair_list = std::vector<id_pair, default_init_allocator<id_pair>>;

/// Canonical order for comparison and output: every pair as (min id, max id), sorted ascending
/// by (a, b). Linear-time bucket pass by first id, then a small sort per bucket (spread over
/// `pool`'s threads when given); deterministic.
void sort_canonical(pair_list& pairs, std::size_t box_count, thread_pool* pool = nullptr);

/// Per-box adjacency in compressed sparse rows: the neighbours of box i are
/// neighbors[offsets[i] .. offsets[i+1]), ascending. Each pair appears in both rows.
struct adjacency {
  std::vector<std::uint64_t> offsets;  ///< size box_count + 1
  std::vector<box_id> neighbors;       ///< size 2 * pair count
  [[nodiscard]] std::size_t box_count() const { return offsets.empty() ? 0 : offsets.size() - 1; }
};

/// Builds the CSR adjacency of a pair list (any order, a < b per pair).
[[nodiscard]] adjacency to_adjacency(const pair_list& pairs, std::size_t box_count);

/// Counters a finder fills for reports and benchmarks (zero where a finder has no such notion).
struct finder_stats {
  std::uint64_t checks = 0;        ///< box-pair intersection tests performed
  std::uint64_t cells = 0;         ///< grid cells (grid finders)
  std::uint64_t cell_entries = 0;  ///< (cell, box) entries after mapping
  double cell_edge = 0;            ///< planned cell edge (grid finders)
  std::uint64_t large_boxes = 0;   ///< boxes handled apart from the grid
  // Wall time of the phases of the last call, in milliseconds (grid finders).
  double plan_ms = 0;    ///< bounds, planning, packing, classification
  double map_ms = 0;     ///< count, scan, map
  double check_ms = 0;   ///< per-cell checking, large boxes included
  double output_ms = 0;  ///< gathering the output list
};

/// Finds every qualifying pair of a box set exactly once (see the semantics above).
///
/// `find` validates the input first and returns the first invalid box instead of pairs; on
/// success `out` holds every qualifying pair once, each with a < b, in an order that depends only
/// on the input (not on thread timing), but is not necessarily sorted: call sort_canonical for
/// the canonical order. An instance is not safe to call from several threads at once.
class pair_finder {
 public:
  virtual ~pair_finder() = default;
  [[nodiscard]] virtual std::string_view name() const = 0;

  /// Sets larger than 2^32 - 1 boxes (32-bit ids) are rejected too.
  [[nodiscard]] std::optional<box_error> find(const box_set& boxes, pair_list& out);

  /// The same pairs as find, as a view: a finder with a result buffer of its own (the GPU finders:
  /// their pinned buffer, gpu/finders.h) points `view` at it and leaves `scratch` alone, saving a
  /// copy of every pair; the others (the default) find into `scratch` and view that. `view` is
  /// valid until the next call of this finder or a change of `scratch`; empty on error.
  [[nodiscard]] virtual std::optional<box_error> find_view(const box_set& boxes, pair_list& scratch,
                                                           std::span<const id_pair>& view);
  /// True when find_view points `view` at a result buffer of the finder's own and never touches
  /// `scratch` (the GPU finders and the auto finder, gpu/finders.h); false (the default) when it
  /// finds into `scratch`. gpu::find_view takes only finders that say true.
  [[nodiscard]] virtual bool views_own_buffer() const { return false; }

  /// Statistics of the last successful call.
  [[nodiscard]] const finder_stats& stats() const { return stats_; }

 protected:
  /// Threads `find` may use to validate the input (null: the calling thread).
  [[nodiscard]] virtual thread_pool* worker_pool() const { return nullptr; }
  /// Called with a validated set; must clear `out` and fill it.
  virtual void find_valid(const box_set& boxes, pair_list& out) = 0;
  finder_stats stats_;
};

/// The reference: every pair tested once by the balanced circular loop of Saldanha & Souza
/// (Algorithm 4; for even N, steps 1..N/2-1 for every box and step N/2 for the first half),
/// split over the pool's threads. O(N^2): the oracle for tests, not for large sets.
class brute_force_finder final : public pair_finder {
 public:
  /// `pool` may be null: then the finder runs on the calling thread only.
  explicit brute_force_finder(thread_pool* pool = nullptr) : pool_(pool) {}
  [[nodiscard]] std::string_view name() const override { return "brute"; }

 protected:
  void find_valid(const box_set& boxes, pair_list& out) override;
  [[nodiscard]] thread_pool* worker_pool() const override { return pool_; }

 private:
  thread_pool* pool_;
};

/// Tuning of the uniform-grid CPU finder.
struct grid_finder_options {
  /// Eq. 6's lower bound W on f = N*alpha/M (average boxes per cell). On the GPU W is the warp
  /// width (32). On a CPU core the best W depends on the data (1e6 boxes on the 2-core machine:
  /// cpu-finders/sweep_w.txt in docs/data.tar.xz): uniform is flat from 3 to 32, the MMO-like set wants 12-16 (smaller cells
  /// cut its large view boxes into many pieces), the Gaussian set, dense in its centre, wants 2-6.
  /// W = 12 has the best geometric mean over the three (1.15x the per-set best).
  double min_boxes_per_cell = 12.0;
  /// Boxes sampled to estimate alpha (the paper uses 1000).
  std::size_t alpha_samples = 1000;
  /// A box that would occupy more than max(large_box_min_cells, large_box_alpha_factor * alpha)
  /// cells is handled apart from the grid (see grid_finder.cpp), keeping memory linear.
  std::uint64_t large_box_min_cells = 64;
  double large_box_alpha_factor = 16.0;
  /// Fixed edge instead of planning (0 = plan by Eq. 6); for the cell-size sweep.
  double fixed_cell_edge = 0.0;
  /// Seed of the planning sample (fixed, so results and timings repeat).
  std::uint64_t sample_seed = 0x5eed;
};

/// The plan of a uniform grid: origin, one cubic cell edge, cells per axis.
struct grid_plan {
  float origin[3]{0, 0, 0};
  double cell_edge = 1.0;
  std::uint32_t dims[3]{1, 1, 1};
  double alpha = 1.0;  ///< estimated average number of cells a box occupies
  [[nodiscard]] std::uint64_t cell_count() const { return std::uint64_t{dims[0]} * dims[1] * dims[2]; }
};

/// Plans a grid by the PBIG paper's Eq. 6: the cubic cell edge l minimising f = N*alpha(l)/M(l)
/// subject to f >= W, found by binary search on l (f grows with l), alpha estimated from a fixed
/// random sample. Also caps the cell count so the grid's memory stays linear in N.
[[nodiscard]] grid_plan plan_grid(const box_set& boxes, const grid_finder_options& opt);

/// The fast CPU finder: PBIG's ideas on the CPU. A uniform grid planned by Eq. 6; count, scan and
/// map of (cell, box) entries; per cell, every pair tested once and reported only in the cell that
/// holds the max corner of the pair's intersection (no de-duplication pass); boxes far larger than
/// the cells handled apart. Multi-threaded over cells in fixed chunks: the output does not depend
/// on the number of threads.
class grid_finder final : public pair_finder {
 public:
  explicit grid_finder(thread_pool* pool = nullptr, grid_finder_options opt = {});
  ~grid_finder() override;
  [[nodiscard]] std::string_view name() const override { return "cpu"; }
  [[nodiscard]] const grid_finder_options& options() const { return opt_; }
  [[nodiscard]] const grid_plan& last_plan() const { return plan_; }

 protected:
  void find_valid(const box_set& boxes, pair_list& out) override;
  [[nodiscard]] thread_pool* worker_pool() const override { return pool_; }

 private:
  struct scratch;
  thread_pool* pool_;
  grid_finder_options opt_;
  grid_plan plan_;
  std::unique_ptr<scratch> scratch_;  // reused across calls: no allocation in steady state
};

// ---------------------------------------------------------------------------------------------
// Data-set generators. Deterministic for a given seed.

/// The paper's uniform set: centres uniform in [0, 1e4]^3, edge lengths U[1, 100] * edge_scale
/// per axis; category = mask = 1.
[[nodiscard]] box_set generate_uniform(std::size_t n, std::uint64_t seed, double edge_scale = 1.0);

/// Edge scale for which the uniform set of n boxes has the given degree of coverage
/// (sum of box volumes / domain volume, the paper's Eq. 11).
[[nodiscard]] double edge_scale_for_doc(std::size_t n, double doc);

/// The paper's Gaussian set: centres normal with mean 5000 and sd 1000 per axis, edges U[1, 100].
[[nodiscard]] box_set generate_gaussian(std::size_t n, std::uint64_t seed);

/// Visibility classes and the AOI bit used by the MMO-like generator and the zone.
namespace category_bits {
inline constexpr std::uint32_t aoi = 1u << 0;
inline constexpr std::uint32_t normal = 1u << 1;
inline constexpr std::uint32_t stealth = 1u << 2;
inline constexpr std::uint32_t team_red = 1u << 3;
inline constexpr std::uint32_t team_blue = 1u << 4;
}  // namespace category_bits

/// An MMO-like zone: n boxes = n/2 entities (n rounded down to even) on a flat world whose side
/// grows as 40 * sqrt(entities) m (a busy zone's density at any size), about 60% of entities
/// clustered in towns (Gaussian crowds, one town per ~4,000 entities), the rest spread uniformly.
/// Entity k owns box 2k (its AOI box: half-extent from tiers tiny..gigantic, category AOI,
/// mask = the classes it sees) and box 2k+1 (its presence box: a small body, or a boss-sized one,
/// category = its visibility class, mask 0). Only AOI-vs-presence pairs qualify, and only where
/// the AOI's mask holds the presence's class (a presence mask of AOI would, by the symmetric
/// rule, make every AOI see it: stealth would not hide).
[[nodiscard]] box_set generate_mmo(std::size_t n, std::uint64_t seed);

/// Names accepted by generate_named: "uniform", "gaussian", "mmo", "doc:<value>".
[[nodiscard]] std::optional<box_set> generate_named(std::string_view kind, std::size_t n, std::uint64_t seed,
                                                    std::string* error = nullptr);

// ---------------------------------------------------------------------------------------------
// Box files. CSV: one box a line, `minx,miny,minz,maxx,maxy,maxz[,category,mask]`; blank lines and
// lines starting with '#' skipped. Binary: see docs/embedding.md, "Box files".

/// A parse or I/O failure: the 1-based line number (0 when not about a line) and a message.
struct file_error {
  std::size_t line = 0;
  std::string message;
};

/// Parses CSV text. Every error names its line; boxes are validated (NaN/Inf, lo > hi).
[[nodiscard]] std::optional<file_error> parse_csv(std::string_view text, box_set& out);
[[nodiscard]] std::optional<file_error> read_csv_file(const std::string& path, box_set& out);
/// Writes CSV (category and mask always written).
[[nodiscard]] std::optional<file_error> write_csv_file(const std::string& path, const box_set& boxes);

/// Binary box file (".boxes"): little-endian header then the structure-of-arrays columns.
[[nodiscard]] std::optional<file_error> read_binary_file(const std::string& path, box_set& out);
[[nodiscard]] std::optional<file_error> write_binary_file(const std::string& path, const box_set& boxes);

/// Reads either format: binary when the file starts with the binary magic, else CSV.
[[nodiscard]] std::optional<file_error> read_box_file(const std::string& path, box_set& out);

}  // namespace zone::interest
