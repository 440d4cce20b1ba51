// Shared by the finder test suites (CPU and GPU): fresh random seeds, a checked run of a finder,
// and the box-set families every fast finder is tested on against the brute-force reference.
#pragma once

#include <doctest/doctest.h>

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <initializer_list>
#include <memory>
#include <random>
#include <span>
#include <string>

#include "interest/interest.h"
#include "seeds.h"

namespace zone::test {

using namespace zone::interest;

/// Runs a finder on a valid set: asserts success, a < b in every pair and no duplicate; returns
/// the pairs in canonical order.
inline pair_list run(pair_finder& f, const box_set& s) {
  pair_list out;
  const auto err = f.find(s, out);
  REQUIRE_FALSE(err.has_value());
  // Each pair once, a < b.
  REQUIRE(std::all_of(out.begin(), out.end(), [](const id_pair& p) { return p.a < p.b; }));
  sort_canonical(out, s.size());
  REQUIRE(std::adjacent_find(out.begin(), out.end()) == out.end());
  return out;
}

/// The pairs of a view (find_view's) in canonical order, for comparing with run()'s.
inline pair_list canonical(std::span<const id_pair> view, std::size_t box_count) {
  pair_list pairs(view.begin(), view.end());
  sort_canonical(pairs, box_count);
  return pairs;
}

/// `made`, a finder a GPU factory returned (make_pbig_finder, make_lbvh_finder); a null one fails
/// the test case with the factory's `why`.
inline std::unique_ptr<pair_finder> made_or_fail(std::unique_ptr<pair_finder> made, const std::string& why) {
  if (!made) FAIL("the GPU finder did not start: " << why);
  return made;
}

/// True when `pairs` is every pair (a, b) with a < b < n, each once, in (a, b) order.
inline bool every_pair_in_order(const pair_list& pairs, box_id n) {
  if (pairs.size() != std::uint64_t{n} * (n > 0 ? n - 1 : 0) / 2) return false;
  std::size_t k = 0;
  for (box_id a = 0; a < n; ++a) {
    for (box_id b = a + 1; b < n; ++b, ++k) {
      if (pairs[k] != id_pair{a, b}) return false;
    }
  }
  return true;
}

struct rng_box_maker {
  std::mt19937_64 rng;
  explicit rng_box_maker(std::uint64_t seed) : rng(seed) {}
  float uni(float lo, float hi) { return std::uniform_real_distribution<float>(lo, hi)(rng); }
  std::uint32_t bits(std::uint32_t m) { return static_cast<std::uint32_t>(rng()) & m; }
  box make(float centre_range, float max_edge, float offset = 0) {
    box b;
    for (int d = 0; d < 3; ++d) {
      const float c = offset + uni(0, centre_range);
      const float e = uni(0, max_edge);
      b.lo[d] = c - e / 2;
      b.hi[d] = b.lo[d] + e;
    }
    return b;
  }
  /// A rod: make(centre_range, thickness) stretched along a random axis, from a start in
  /// [start_lo, start_hi) over a length in [min_len, max_len).
  box rod(float centre_range, float thickness, float start_lo, float start_hi, float min_len, float max_len) {
    box b = make(centre_range, thickness);
    const int axis = static_cast<int>(rng() % 3);
    b.lo[axis] = uni(start_lo, start_hi);
    b.hi[axis] = b.lo[axis] + uni(min_len, max_len);
    return b;
  }
};

/// Box-set families, each a stress for a different part of the grid finder.
enum class family {
  uniform,
  touching,
  zero_size,
  identical,
  huge_over_tiny,
  long_thin,
  negative_large,
  mask_mix,
  integer_grid,
  flat_world,
  few_classes
};
constexpr family all_families[] = {family::uniform,      family::touching,       family::zero_size, family::identical,
                                   family::huge_over_tiny, family::long_thin,     family::negative_large,
                                   family::mask_mix,     family::integer_grid,   family::flat_world,
                                   family::few_classes};

inline std::string family_name(family f) {
  switch (f) {
    case family::uniform: return "uniform";
    case family::touching: return "touching";
    case family::zero_size: return "zero_size";
    case family::identical: return "identical";
    case family::huge_over_tiny: return "huge_over_tiny";
    case family::long_thin: return "long_thin";
    case family::negative_large: return "negative_large";
    case family::mask_mix: return "mask_mix";
    case family::integer_grid: return "integer_grid";
    case family::flat_world: return "flat_world";
    case family::few_classes: return "few_classes";
  }
  return "?";
}

inline box_set make_family(family f, std::size_t n, std::uint64_t seed) {
  rng_box_maker r(seed);
  box_set s;
  for (std::size_t i = 0; i < n; ++i) {
    box b;
    switch (f) {
      case family::uniform: b = r.make(100, 12); break;
      case family::touching: {
        // Unit cubes on an integer lattice: neighbours share faces, edges and corners exactly.
        for (int d = 0; d < 3; ++d) {
          b.lo[d] = static_cast<float>(r.rng() % 6);
          b.hi[d] = b.lo[d] + 1.0f;
        }
        break;
      }
      case family::zero_size: {
        // Points and flat boxes on a coarse lattice, so many coincide or touch.
        for (int d = 0; d < 3; ++d) {
          b.lo[d] = static_cast<float>(r.rng() % 5);
          b.hi[d] = b.lo[d] + ((r.rng() % 3 == 0) ? 1.0f : 0.0f);
        }
        break;
      }
      case family::identical:
        for (int d = 0; d < 3; ++d) {
          b.lo[d] = 3.5f;
          b.hi[d] = 7.25f;
        }
        break;
      case family::huge_over_tiny:
        b = (i % 97 == 3) ? r.make(10, 400, -100) : r.make(200, 2);
        break;
      case family::long_thin:
        b = r.rod(100, 1, -50, 50, 50, 250);
        break;
      case family::negative_large:
        b = r.make(2e6f, 5e4f, -1e6f);
        break;
      case family::mask_mix:
        b = r.make(60, 15);
        b.category = r.bits(0xF);
        b.mask = r.bits(0xF);
        break;
      case family::integer_grid: {
        // Integer-aligned boxes of integer size: many bounds fall exactly on cell faces.
        for (int d = 0; d < 3; ++d) {
          b.lo[d] = static_cast<float>(r.rng() % 40);
          b.hi[d] = b.lo[d] + static_cast<float>(r.rng() % 8);
        }
        break;
      }
      case family::few_classes: {
        // A handful of (category, mask) signatures, some never compatible with each other:
        // exercises the per-cell grouping that skips incompatible signature pairs.
        static constexpr std::uint32_t cats[] = {1, 2, 4, 1, 8};
        static constexpr std::uint32_t masks[] = {2, 1, 4, 1, 0};
        b = r.make(80, 14);
        const auto k = r.rng() % 5;
        b.category = cats[k];
        b.mask = masks[k];
        break;
      }
      case family::flat_world: {
        b = r.make(500, 30);
        b.lo[2] = 0;
        b.hi[2] = (r.rng() % 2) ? 0.0f : 2.0f;
        b.category = (i % 2) ? category_bits::aoi : category_bits::normal;
        b.mask = (i % 2) ? category_bits::normal : category_bits::aoi;
        break;
      }
    }
    s.push_back(b);
  }
  return s;
}

/// generate_uniform(n, seed, edge_scale) with 3 boxes spanning its whole world after it (ids n to
/// n + 2): each pairs with every box.
inline box_set uniform_with_spanning(std::size_t n, std::uint64_t seed, double edge_scale = 1.0) {
  box_set s = generate_uniform(n, seed, edge_scale);
  for (int k = 0; k < 3; ++k) s.push_back(box{{-1, -1, -1}, {1e4f + 1, 1e4f + 1, 1e4f + 1}, 1, 1});
  return s;
}

/// The sizes every fast finder is compared with the reference at, on every family.
inline constexpr std::size_t finder_sizes[] = {0, 1, 2, 3, 7, 8, 33, 100, 513, 2000, 4001};
/// Families with many pairs a box: they overflow output buffers that start tiny.
inline constexpr family dense_families[] = {family::uniform, family::identical, family::huge_over_tiny,
                                            family::mask_mix, family::touching};
/// Families whose bounds meet cell faces in many ways: for fixed cell edges and cell-size rules.
inline constexpr family cell_edge_families[] = {family::uniform, family::integer_grid, family::huge_over_tiny,
                                                family::touching};

/// For every family of `families` and size of `sizes` (ranges, or braced lists): a set of that
/// family on a fresh random seed and its pairs by `reference` (run: checked, canonical order),
/// handed to check(set, expected). The family, size and seed are captured for check's assertions.
template <class Families = std::initializer_list<family>, class Sizes = std::initializer_list<std::size_t>,
          class Check>
void for_each_family_set(pair_finder& reference, const Families& families, const Sizes& sizes, Check&& check) {
  for (const family f : families) {
    for (const std::size_t n : sizes) {
      const auto seed = fresh_seed();
      CAPTURE(family_name(f));
      CAPTURE(n);
      CAPTURE(seed);
      const box_set s = make_family(f, n, seed);
      const pair_list expected = run(reference, s);
      check(s, expected);
    }
  }
}

/// For every generator of `kinds` (generate_named's names): a set of n boxes on a fresh random
/// seed, handed to check(set). The kind and seed are captured for check's assertions.
template <class Check>
void for_each_named_set(std::initializer_list<const char*> kinds, std::size_t n, Check&& check) {
  for (const char* kind : kinds) {
    const auto seed = fresh_seed();
    CAPTURE(kind);
    CAPTURE(seed);
    const box_set s = *generate_named(kind, n, seed);
    check(s);
  }
}

}  // namespace zone::test
