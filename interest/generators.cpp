// Data-set generators: the PBIG paper's experimental sets and an MMO-like zone.
// All use std::mt19937_64 with explicit seeds and hand-written distributions (the standard
// library's distributions are not specified bit-for-bit), so a seed gives the same set everywhere.
#include <cmath>
#include <charconv>
#include <algorithm>
#include <numbers>

#include "interest.h"

namespace zone::interest {
namespace {

constexpr double world_edge = 1e4;  // the paper's domain: [0, 1e4]^3

/// Uniform double in [0, 1) from 53 random bits.
double unit(std::mt19937_64& rng) { return static_cast<double>(rng() >> 11) * 0x1.0p-53; }
double uniform(std::mt19937_64& rng, double lo, double hi) { return lo + (hi - lo) * unit(rng); }
/// Standard normal by Box-Muller (one value per call; simple and portable).
double normal(std::mt19937_64& rng) {
  double u1 = unit(rng);
  while (u1 <= 0.0) u1 = unit(rng);
  const double u2 = unit(rng);
  return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * std::numbers::pi * u2);
}

box centred_box(const double centre[3], const double edge[3], std::uint32_t category, std::uint32_t mask) {
  box b;
  for (int d = 0; d < 3; ++d) {
    b.lo[d] = static_cast<float>(centre[d] - edge[d] / 2);
    b.hi[d] = static_cast<float>(centre[d] + edge[d] / 2);
  }
  b.category = category;
  b.mask = mask;
  return b;
}

}  // namespace

box_set generate_uniform(std::size_t n, std::uint64_t seed, double edge_scale) {
  std::mt19937_64 rng(seed);
  box_set s;
  s.reserve(n);
  for (std::size_t i = 0; i < n; ++i) {
    double c[3], e[3];
    for (int d = 0; d < 3; ++d) c[d] = uniform(rng, 0.0, world_edge);
    for (int d = 0; d < 3; ++d) e[d] = uniform(rng, 1.0, 100.0) * edge_scale;
    s.push_back(centred_box(c, e, 1, 1));
  }
  return s;
}

double edge_scale_for_doc(std::size_t n, double doc) {
  // DoC = N * E[volume] / world volume; with independent U[1,100]*k edges, E[volume] = (50.5 k)^3.
  if (n == 0) return 1.0;
  const double mean_edge = 50.5;
  return std::cbrt(doc * world_edge * world_edge * world_edge / static_cast<double>(n)) / mean_edge;
}

box_set generate_gaussian(std::size_t n, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  box_set s;
  s.reserve(n);
  for (std::size_t i = 0; i < n; ++i) {
    double c[3], e[3];
    for (int d = 0; d < 3; ++d) c[d] = 5000.0 + 1000.0 * normal(rng);
    for (int d = 0; d < 3; ++d) e[d] = uniform(rng, 1.0, 100.0);
    s.push_back(centred_box(c, e, 1, 1));
  }
  return s;
}

box_set generate_mmo(std::size_t n, std::uint64_t seed) {
  namespace cb = category_bits;
  std::mt19937_64 rng(seed);
  const std::size_t entities = n / 2;
  box_set s;
  s.reserve(entities * 2);

  // A flat world whose area grows with the population (about 1,600 m^2 per entity, so density
  // stays that of a busy zone at any size): side 40 * sqrt(entities) m, 0..200 m in height.
  const double ground = std::max(1000.0, 40.0 * std::sqrt(static_cast<double>(entities)));
  constexpr double height = 200.0;
  // Towns: one per ~4,000 entities, each a Gaussian crowd of sd 80..250 m.
  const int town_count = static_cast<int>(std::clamp<std::size_t>(entities / 4000, 1, 4096));
  std::vector<double> town_x(town_count), town_y(town_count), town_sd(town_count);
  for (int t = 0; t < town_count; ++t) {
    town_x[t] = uniform(rng, 0.1 * ground, 0.9 * ground);
    town_y[t] = uniform(rng, 0.1 * ground, 0.9 * ground);
    town_sd[t] = uniform(rng, 80.0, 250.0);
  }
  // AOI half-extent tiers (tiny .. gigantic) and how common each is.
  constexpr double tier_half[5] = {10.0, 30.0, 60.0, 150.0, 400.0};
  constexpr double tier_cdf[5] = {0.30, 0.70, 0.92, 0.995, 1.0};

  for (std::size_t k = 0; k < entities; ++k) {
    double x, y;
    if (unit(rng) < 0.6) {
      const int t = static_cast<int>(rng() % static_cast<std::uint64_t>(town_count));
      x = town_x[t] + town_sd[t] * normal(rng);
      y = town_y[t] + town_sd[t] * normal(rng);
    } else {
      x = uniform(rng, 0.0, ground);
      y = uniform(rng, 0.0, ground);
    }
    const double z = uniform(rng, 0.0, height) * (unit(rng) < 0.9 ? 0.05 : 1.0);  // most on the ground

    // Visibility class: mostly normal; some stealthy; the rest on a team.
    const double r = unit(rng);
    const std::uint32_t vis = r < 0.80 ? cb::normal : r < 0.85 ? cb::stealth : r < 0.925 ? cb::team_red : cb::team_blue;
    // What it sees: normal always; its own team; stealth only for a few (detectors).
    std::uint32_t sees = cb::normal | cb::team_red | cb::team_blue;
    if (unit(rng) < 0.05) sees |= cb::stealth;
    if (vis == cb::stealth) sees |= cb::stealth;

    const double u = unit(rng);
    int tier = 0;
    while (u >= tier_cdf[tier]) ++tier;
    const double half = tier_half[tier] * uniform(rng, 0.8, 1.2);
    const double centre[3] = {x, y, z};
    const double aoi_edge[3] = {2 * half, 2 * half, std::min(2 * half, 2 * height)};
    s.push_back(centred_box(centre, aoi_edge, cb::aoi, sees));

    const double body = vis == cb::normal && unit(rng) < 0.002 ? uniform(rng, 20.0, 60.0)  // a boss-sized body
                                                               : uniform(rng, 0.5, 2.0);
    const double body_edge[3] = {body, body, body * 2};
    // Mask 0: the pair rule is symmetric ((cat_a & mask_b) | (cat_b & mask_a)), so a presence box
    // with mask AOI would be seen by every AOI box whatever it may see; with 0, only the AOI
    // box's mask (the classes it sees) decides.
    s.push_back(centred_box(centre, body_edge, vis, 0));
  }
  return s;
}

std::optional<box_set> generate_named(std::string_view kind, std::size_t n, std::uint64_t seed, std::string* error) {
  if (kind == "uniform") return generate_uniform(n, seed);
  if (kind == "gaussian") return generate_gaussian(n, seed);
  if (kind == "mmo") return generate_mmo(n, seed);
  if (kind.starts_with("doc:")) {
    const std::string_view value = kind.substr(4);
    double doc = 0;
    const auto [ptr, ec] = std::from_chars(value.data(), value.data() + value.size(), doc);
    if (ec == std::errc{} && ptr == value.data() + value.size() && doc > 0 && std::isfinite(doc)) {
      return generate_uniform(n, seed, edge_scale_for_doc(n, doc));
    }
  }
  if (error) *error = "unknown data set '" + std::string(kind) + "' (expected uniform, gaussian, mmo or doc:<value>)";
  return std::nullopt;
}

}  // namespace zone::interest
