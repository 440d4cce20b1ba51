// Finder factory and the `auto` finder (finders.h). Plain C++, built with and without CUDA: the
// GPU factories (make_pbig_finder, make_lbvh_finder) return null where no device can be used.
#include "finders.h"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <exception>
#include <stdexcept>
#include <vector>

#include "interest/thread_pool.h"
#include "lbvh.h"
#include "pbig.h"

namespace zone::gpu {

std::optional<finder_backend> parse_backend(std::string_view name) {
  if (name == "brute") return finder_backend::brute;
  if (name == "cpu") return finder_backend::cpu;
  if (name == "gpu" || name == "pbig") return finder_backend::pbig;
  if (name == "lbvh") return finder_backend::lbvh;
  if (name == "auto") return finder_backend::auto_select;
  return std::nullopt;
}

std::string_view backend_name(finder_backend backend) {
  switch (backend) {
    case finder_backend::brute: return "brute";
    case finder_backend::cpu: return "cpu";
    case finder_backend::pbig: return "pbig";
    case finder_backend::lbvh: return "lbvh";
    case finder_backend::auto_select: return "auto";
  }
  return "?";
}

// ---- statistics and the rule ------------------------------------------------------------------

box_set_summary summarize(const interest::box_set& boxes) {
  box_set_summary s;
  s.n = boxes.size();
  if (s.n == 0) return s;
  s.pinned = boxes_pinned(boxes);
  const std::size_t k = std::min(s.n, auto_sample_boxes);
  s.sampled = k;
  // A fixed stratified sample: stratum i = [i n / k, (i + 1) n / k), one box of it picked by a
  // hash of i (no aliasing with periodic layouts such as the MMO set's AOI/presence pairs).
  double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
  thread_local std::vector<float> edge, largest, sorted;
  thread_local std::vector<double> lo_of[3];
  edge.resize(3 * k);
  largest.resize(k);
  for (auto& v : lo_of) v.resize(k);
  const float* blo[3] = {boxes.lo_x.data(), boxes.lo_y.data(), boxes.lo_z.data()};
  const float* bhi[3] = {boxes.hi_x.data(), boxes.hi_y.data(), boxes.hi_z.data()};
  double sum_largest = 0;
  for (std::size_t i = 0; i < k; ++i) {
    const std::uint64_t first = std::uint64_t{i} * s.n / k, next = std::uint64_t{i + 1} * s.n / k;  // < 2^13 * 2^32
    std::uint64_t h = (i + 1) * 0x9e3779b97f4a7c15ull;
    h = (h ^ (h >> 31)) * 0xbf58476d1ce4e5b9ull;
    const std::size_t b = static_cast<std::size_t>(first + (h >> 32) % std::max<std::uint64_t>(1, next - first));
    float big = 0;
    for (int d = 0; d < 3; ++d) {
      const double l = blo[d][b], h = bhi[d][b];
      lo[d] = std::min(lo[d], l);
      hi[d] = std::max(hi[d], h);
      const float e = static_cast<float>(std::max(0.0, h - l));
      edge[3 * i + d] = e;
      lo_of[d][i] = l;
      big = std::max(big, e);
    }
    largest[i] = big;
    sum_largest += big;
  }
  for (int d = 0; d < 3; ++d) s.scene_extent[d] = std::isfinite(hi[d] - lo[d]) ? std::max(0.0, hi[d] - lo[d]) : 0.0;
  s.mean_size = sum_largest / static_cast<double>(k);
  sorted = largest;
  std::nth_element(sorted.begin(), sorted.begin() + k / 2, sorted.begin() + k);
  const double median = sorted[k / 2];
  const double maxv = *std::max_element(largest.begin(), largest.begin() + k);
  s.size_spread = median > 0 ? maxv / median : (maxv > 0 ? INFINITY : 1.0);

  // Eq. 6 estimated on the sample: the smallest cubic edge l with f(l) = N * alpha(l) / M(l) >= 32,
  // alpha(l) = mean of prod_d (e_d / l + 1) (expected cells of a randomly placed box), M(l) =
  // prod_d (extent_d / l + 1) capped at 2N + 64 like the planners. f grows with l: bisection in log l.
  const double n = static_cast<double>(s.n);
  const double max_extent = std::max({s.scene_extent[0], s.scene_extent[1], s.scene_extent[2]});
  auto cells_of = [](const float* e, double l) {
    return (e[0] / l + 1.0) * (e[1] / l + 1.0) * (e[2] / l + 1.0);
  };
  auto m_of = [&](double l) {
    double m = 1;
    for (int d = 0; d < 3; ++d) m *= s.scene_extent[d] / l + 1.0;
    return m;
  };
  // alpha(l) = mean prod_d (e_d / l + 1) = s3 / l^3 + s2 / l^2 + s1 / l + 1 with the sample means
  // of the elementary symmetric polynomials of the edges: O(1) per candidate edge.
  double s1 = 0, s2 = 0, s3 = 0;
  for (std::size_t i = 0; i < k; ++i) {
    const double e0 = edge[3 * i], e1 = edge[3 * i + 1], e2 = edge[3 * i + 2];
    s1 += e0 + e1 + e2;
    s2 += e0 * e1 + e0 * e2 + e1 * e2;
    s3 += e0 * e1 * e2;
  }
  s1 /= static_cast<double>(k);
  s2 /= static_cast<double>(k);
  s3 /= static_cast<double>(k);
  auto f_of = [&](double l, double* alpha_out) {
    const double alpha = ((s3 / l + s2) / l + s1) / l + 1.0;
    if (alpha_out) *alpha_out = alpha;
    return n * alpha / m_of(l);
  };
  if (max_extent <= 0) {
    s.cell_edge = 1;
    s.mean_cells = 1;
    s.largest_cells = 1;
    return s;
  }
  // Uncapped, f grows with l; the cap then grows l until M(l) <= 2N + 64 (M falls with l).
  auto bisect = [&](auto&& good) {
    double a = max_extent * 1e-7, b = max_extent * 2;
    if (good(a)) return a;
    for (int it = 0; it < 40 && b / a > 1.01; ++it) {
      const double mid = std::sqrt(a * b);
      if (good(mid)) b = mid; else a = mid;
    }
    return b;
  };
  const double eq6 = bisect([&](double l) { return f_of(l, nullptr) >= 32; });
  const double cap = bisect([&](double l) { return m_of(l) <= 2.0 * n + 64.0; });
  const double b = std::max(eq6, cap);
  s.cell_edge = b;
  (void)f_of(b, &s.mean_cells);
  // The grid finders' large-box rule at that edge: more than max(64, 16 alpha) cells.
  const double large_cells = std::max(64.0, 16.0 * s.mean_cells);
  double most = 0;
  std::size_t large = 0;
  for (std::size_t i = 0; i < k; ++i) {
    const double c = cells_of(&edge[3 * i], b);
    most = std::max(most, c);
    large += c > large_cells ? 1 : 0;
  }
  s.largest_cells = most;
  s.large_fraction = static_cast<double>(large) / static_cast<double>(k);
  s.large_estimate = s.large_fraction * n;

  // Crowding: sampled boxes whose centres share a cell of that grid, against the 1 / M an even
  // spread would give. Cells keyed by their coordinates (21 bits per axis), sorted, runs counted.
  thread_local std::vector<std::uint64_t> cell;
  cell.resize(k);
  double cells_total = 1;
  std::uint64_t dims[3];
  for (int d = 0; d < 3; ++d) {
    dims[d] = static_cast<std::uint64_t>(std::min(2097151.0, std::floor(s.scene_extent[d] / b) + 1));
    cells_total *= static_cast<double>(dims[d]);
  }
  for (std::size_t i = 0; i < k; ++i) {
    std::uint64_t key = 0;
    for (int d = 0; d < 3; ++d) {
      const double centre = lo_of[d][i] + 0.5 * edge[3 * i + d];
      const double c = std::clamp(std::floor((centre - lo[d]) / b), 0.0, static_cast<double>(dims[d] - 1));
      key = (key << 21) | static_cast<std::uint64_t>(c);
    }
    cell[i] = key;
  }
  std::sort(cell.begin(), cell.end());
  double same = 0;
  for (std::size_t i = 0; i < k;) {
    std::size_t j = i;
    while (j < k && cell[j] == cell[i]) ++j;
    const double g = static_cast<double>(j - i);
    same += g * (g - 1) / 2;
    i = j;
  }
  const double sample_pairs = static_cast<double>(k) * static_cast<double>(k - 1) / 2;
  s.crowding = k > 1 ? same / sample_pairs * cells_total : 1.0;
  return s;
}

finder_backend choose_backend(const box_set_summary& summary, bool pbig_usable, bool lbvh_usable,
                              std::string* reason) {
  auto say = [&](const std::string& text) {
    if (reason) *reason = text;
  };
  if (!pbig_usable && !lbvh_usable) {
    say("no GPU finder can run");
    return finder_backend::cpu;
  }
  if (!pbig_usable) {
    say("PBIG cannot run, LBVH can");
    return finder_backend::lbvh;
  }
  if (!lbvh_usable) {
    say("LBVH cannot run, PBIG can");
    return finder_backend::pbig;
  }
  const double n = static_cast<double>(summary.n);
  if (summary.n < auto_small_n && summary.size_spread < auto_even_spread) {
    say(fmt::format("N = {} < {} and box sizes alike (spread {:.3g}x): LBVH, less fixed cost per call", summary.n,
                    auto_small_n, summary.size_spread));
    return finder_backend::lbvh;
  }
  const double large_tests = summary.large_estimate * n;
  if (large_tests > auto_large_pass_tests) {
    say(fmt::format("N = {}, about {:.0f} boxes ({:.2f}% of the sample) would occupy more than max(64, 16 alpha) "
                    "cells of the planned grid (edge {:.3g}; largest sampled box {:.0f} cells): PBIG's large-box pass "
                    "would test about {:.2g} pairs; LBVH",
                    summary.n, summary.large_estimate, 100 * summary.large_fraction, summary.cell_edge,
                    summary.largest_cells, large_tests));
    return finder_backend::lbvh;
  }
  if (summary.pinned) {
    // Measured on the H100 (docs/gpu.md, "The auto finder and its rule"): with the input pinned, PBIG beats LBVH
    // 1.4-1.8x on the sets rules 4 and 5 send to LBVH (Gaussian 10^6 and 10^7, DoC 10).
    say(fmt::format("N = {}, the input pinned (PBIG uploads it by DMA and validates it on the device; LBVH stages "
                    "it): PBIG",
                    summary.n));
    return finder_backend::pbig;
  }
  if (summary.crowding > auto_crowding && summary.size_spread < auto_even_spread) {
    say(fmt::format("N = {}, boxes of like size (spread {:.3g}x) crowded {:.3g}x into the planned grid's cells "
                    "(edge {:.3g}): LBVH",
                    summary.n, summary.size_spread, summary.crowding, summary.cell_edge));
    return finder_backend::lbvh;
  }
  if (summary.mean_cells > auto_many_cells) {
    say(fmt::format("N = {}, a box covers {:.3g} cells of the planned grid (edge {:.3g}) on average: LBVH", summary.n,
                    summary.mean_cells, summary.cell_edge));
    return finder_backend::lbvh;
  }
  say(fmt::format("N = {}, box sizes spread {:.3g}x, crowding {:.3g}x, {:.3g} cells per box, largest sampled box "
                  "{:.0f} cells of the planned grid (edge {:.3g}), about {:.0f} boxes apart from it: PBIG",
                  summary.n, summary.size_spread, summary.crowding, summary.mean_cells, summary.largest_cells,
                  summary.cell_edge, summary.large_estimate));
  return finder_backend::pbig;
}

// ---- the auto finder --------------------------------------------------------------------------

namespace {

/// Copies `src` into `out` (resized to fit), split over the pool for large lists.
void copy_pairs(std::span<const interest::id_pair> src, interest::pair_list& out, interest::thread_pool* pool) {
  out.resize(src.size());
  const std::size_t parts = src.size() < 65536 || pool == nullptr ? 1 : pool->size() * 4;
  interest::run_tasks(parts > 1 ? pool : nullptr, parts, [&](std::size_t p) {
    const std::size_t b = src.size() * p / parts, e = src.size() * (p + 1) / parts;
    if (e > b) std::memcpy(static_cast<void*>(out.data() + b), src.data() + b, (e - b) * sizeof(interest::id_pair));
  });
}

class auto_finder final : public interest::pair_finder {
 public:
  auto_finder(std::unique_ptr<interest::pair_finder> cpu, std::unique_ptr<interest::pair_finder> pbig,
              std::unique_ptr<interest::pair_finder> lbvh, interest::thread_pool* pool, std::string no_gpu_why)
      : cpu_(std::move(cpu)), pbig_(std::move(pbig)), lbvh_(std::move(lbvh)), pool_(pool),
        no_gpu_why_(std::move(no_gpu_why)) {
    if (!cpu_) throw std::invalid_argument("make_auto_finder: the CPU finder must not be null");
  }
  [[nodiscard]] std::string_view name() const override { return "auto"; }
  [[nodiscard]] bool views_own_buffer() const override { return true; }
  [[nodiscard]] std::optional<finder_backend> last_choice() const { return last_; }

  /// pair_finder::find_view: the chosen finder's view (its own buffer for the GPU finders, with
  /// the validation in their packing pass), or a list of this finder's own (`scratch` unused).
  std::optional<interest::box_error> find_view(const interest::box_set& boxes, interest::pair_list& /*scratch*/,
                                               std::span<const interest::id_pair>& out) override {
    out = {};
    const finder_backend b = decide(boxes);
    if (b != finder_backend::cpu) {
      try {
        interest::pair_finder& f = *(b == finder_backend::pbig ? pbig_ : lbvh_);
        // The GPU finders view their own buffer; an injected finder (tests) finds into buffer_.
        const auto err = f.find_view(boxes, buffer_, out);
        if (!err) stats_ = f.stats();
        return err;
      } catch (const std::exception& e) {
        fail(b, e);
      }
    }
    const auto err = cpu_->find(boxes, buffer_);
    if (!err) {
      stats_ = cpu_->stats();
      out = buffer_;
    }
    return err;
  }

 protected:
  [[nodiscard]] interest::thread_pool* worker_pool() const override { return pool_; }
  void find_valid(const interest::box_set& boxes, interest::pair_list& out) override {
    const finder_backend b = decide(boxes);
    if (b != finder_backend::cpu) {
      std::optional<interest::box_error> err;
      bool ran = false;
      try {
        interest::pair_finder& f = *(b == finder_backend::pbig ? pbig_ : lbvh_);
        if (f.views_own_buffer()) {
          // The GPU finders validate while packing the upload: cheaper than a second full pass.
          std::span<const interest::id_pair> v;
          err = f.find_view(boxes, buffer_, v);
          if (!err) copy_pairs(v, out, pool_);
        } else {
          err = f.find(boxes, out);
        }
        stats_ = f.stats();
        ran = true;
      } catch (const std::exception& e) {
        fail(b, e);
      }
      if (ran) {
        if (err) throw std::logic_error("auto: a validated set was rejected: " + err->message);
        return;
      }
    }
    if (const auto err = cpu_->find(boxes, out)) throw std::logic_error("auto: a validated set was rejected: " + err->message);
    stats_ = cpu_->stats();
  }

 private:
  finder_backend decide(const interest::box_set& boxes) {
    std::string reason;
    const bool pbig_ok = pbig_ != nullptr && !gpu_failed_;
    const bool lbvh_ok = lbvh_ != nullptr && !gpu_failed_;
    finder_backend b = finder_backend::cpu;
    if (pbig_ok || lbvh_ok) {
      // Re-decide when due: first call, N moved by more than 10%, or every auto_redecide_calls calls.
      const double n = static_cast<double>(boxes.size());
      const bool pinned = boxes_pinned(boxes);
      const bool due = !last_ || *last_ == finder_backend::cpu || calls_since_decision_ >= auto_redecide_calls ||
                       std::abs(n - decided_n_) > auto_redecide_n_change * std::max(decided_n_, 1.0) ||
                       pinned != decided_pinned_;
      if (!due) {
        ++calls_since_decision_;
        return *last_;
      }
      b = choose_backend(summarize(boxes), pbig_ok, lbvh_ok, &reason);
      decided_n_ = n;
      decided_pinned_ = pinned;
      calls_since_decision_ = 1;
    } else {
      reason = gpu_failed_ ? "a GPU finder failed earlier" : "no GPU: " + no_gpu_why_;
    }
    if (!last_ || *last_ != b || reason_ != reason) {
      // Logged when the choice or its reason changes, not every call.
      if (b == finder_backend::cpu) {
        spdlog::info("auto: using the CPU grid finder ({})", reason);
      } else {
        spdlog::info("auto: using the GPU {} finder ({})", backend_name(b), reason);
      }
      reason_ = reason;
    }
    last_ = b;
    return b;
  }

  void fail(finder_backend b, const std::exception& e) {
    spdlog::warn("auto: the GPU {} finder failed ({}); falling back to the CPU grid finder for this call and after",
                 backend_name(b), e.what());
    gpu_failed_ = true;
    last_ = finder_backend::cpu;
    reason_ = "a GPU finder failed earlier";
  }

  std::unique_ptr<interest::pair_finder> cpu_, pbig_, lbvh_;
  interest::thread_pool* pool_;
  std::string no_gpu_why_;
  std::optional<finder_backend> last_;
  std::string reason_;
  bool gpu_failed_ = false;
  double decided_n_ = 0;
  bool decided_pinned_ = false;
  int calls_since_decision_ = 0;
  interest::pair_list buffer_;  // view's list when the CPU finder (or an injected finder) runs
};

}  // namespace

std::unique_ptr<interest::pair_finder> make_auto_finder(std::unique_ptr<interest::pair_finder> cpu,
                                                        std::unique_ptr<interest::pair_finder> pbig,
                                                        std::unique_ptr<interest::pair_finder> lbvh,
                                                        interest::thread_pool* pool) {
  return std::make_unique<auto_finder>(std::move(cpu), std::move(pbig), std::move(lbvh), pool,
                                       "none was given");
}

std::unique_ptr<interest::pair_finder> make_finder(finder_backend backend, interest::thread_pool* pool,
                                                   std::string* why) {
  switch (backend) {
    case finder_backend::brute: return std::make_unique<interest::brute_force_finder>(pool);
    case finder_backend::cpu: return std::make_unique<interest::grid_finder>(pool);
    case finder_backend::pbig: {
      pbig_options o;
      o.decode_pool = pool;
      return make_pbig_finder(o, why);
    }
    case finder_backend::lbvh: {
      lbvh_options o;
      o.pool = pool;
      return make_lbvh_finder(o, why);
    }
    case finder_backend::auto_select: {
      std::string no_gpu;
      pbig_options po;
      po.decode_pool = pool;
      auto pbig = make_pbig_finder(po, &no_gpu);
      std::unique_ptr<interest::pair_finder> lbvh;
      if (pbig) {
        lbvh_options lo;
        lo.pool = pool;
        std::string lbvh_why;
        lbvh = make_lbvh_finder(lo, &lbvh_why);
        if (!lbvh) spdlog::debug("auto: no LBVH finder: {}", lbvh_why);
      }
      return std::make_unique<auto_finder>(std::make_unique<interest::grid_finder>(pool), std::move(pbig),
                                           std::move(lbvh), pool, no_gpu);
    }
  }
  if (why) *why = "unknown backend";
  return nullptr;
}

std::unique_ptr<interest::pair_finder> make_finder(std::string_view name, interest::thread_pool* pool, std::string* why,
                                                   const interest::grid_finder_options& grid) {
  if (name == "cpu") return std::make_unique<interest::grid_finder>(pool, grid);
  if (name == "cpu-1t") return std::make_unique<interest::grid_finder>(nullptr, grid);
  const auto backend = parse_backend(name);
  if (!backend) {
    if (why) *why = "unknown finder '" + std::string(name) + "' (brute, cpu, cpu-1t, gpu, pbig, lbvh, auto)";
    return nullptr;
  }
  std::string reason;
  auto f = make_finder(*backend, pool, &reason);
  if (!f && why) *why = "finder '" + std::string(name) + "' cannot run here: " + reason;
  return f;
}

std::optional<finder_backend> last_auto_choice(const interest::pair_finder& finder) {
  const auto* f = dynamic_cast<const auto_finder*>(&finder);
  return f != nullptr ? f->last_choice() : std::nullopt;
}

std::optional<interest::box_error> find_view(interest::pair_finder& finder, const interest::box_set& boxes,
                                             std::span<const interest::id_pair>& view) {
  // The finder says whether it views a buffer of its own (pair_finder::views_own_buffer): such a
  // finder never touches the scratch list, so an empty one is passed.
  if (!finder.views_own_buffer()) throw std::invalid_argument("find_view: not a GPU finder or an auto finder");
  interest::pair_list unused;
  return finder.find_view(boxes, unused, view);
}

}  // namespace zone::gpu
