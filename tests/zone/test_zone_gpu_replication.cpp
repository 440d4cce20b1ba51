// Replication on the GPU engine (gpu/replication.h) against the CPU replicator, byte for byte
// (replication_equivalence.h): small random worlds at every budget, and a large one. Part of
// test_zone_gpu (skipped without a CUDA device: test_zone_gpu.cpp exits 77 before any test).
#include <doctest/doctest.h>

#include <string>

#include "../common/seeds.h"
#include "gpu/replication.h"
#include "gpu/visibility.h"
#include "replication_equivalence.h"
#include "zone/zone.h"

using namespace zone;

namespace {

std::unique_ptr<interest::replication_engine> make_gpu_replication() {
  std::string why;
  auto e = gpu::make_replication_engine(&why);
  if (!e) FAIL("make_replication_engine failed: " << why);
  return e;
}

/// The GPU interest engine, whose visible sets the replication engine reads in place.
auto make_gpu_visibility(interest::thread_pool* pool) {
  std::string why;
  auto e = gpu::make_visibility_engine(pool, &why);
  if (!e) FAIL("make_visibility_engine failed: " << why);
  return e;
}

/// 20,000 entities, 3,000 clients, 20 ticks at two budgets.
zone::test::replication_equivalence_case large_world_case() {
  zone::test::replication_equivalence_case c;
  c.entities = 20000;
  c.clients = 3000;
  c.ticks = 20;
  c.side = 2000;
  c.aoi_lo = 20;
  c.aoi_hi = 80;
  c.budgets = {700, 8192};
  c.first_ticks = {7};
  return c;
}

}  // namespace

TEST_SUITE("zone.gpu") {
  TEST_CASE("GPU replication: frames equal the CPU replicator's byte for byte (random worlds, every budget)") {
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    zone::test::replication_equivalence_case c;
    const auto cov = zone::test::check_replication_equivalence(seed, c, make_gpu_replication);
    zone::test::require_equivalent(cov);
    CHECK(cov.grown_ahead_ms > 0);  // buffers were grown ahead between ticks, and the frames stayed equal
  }

  TEST_CASE(
      "GPU replication in a crowd: hundreds of due updates a frame ranked by sorting, the CPU replicator's frames") {
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    const auto cov = zone::test::check_replication_equivalence(seed, zone::test::crowd_case(), make_gpu_replication);
    zone::test::require_equivalent(cov);
    CHECK(cov.ranked_sorted > 0);
  }

  TEST_CASE("GPU replication: a large world (20,000 entities, 3,000 clients) equals the CPU replicator") {
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    zone::test::replication_equivalence_case c = large_world_case();
    const auto cov = zone::test::check_replication_equivalence(seed, c, make_gpu_replication);
    zone::test::require_equivalent(cov);
    CHECK(cov.grown_ahead_ms > 0);
  }

  TEST_CASE("GPU replication: views grown past a frame's leaves, then every observer blind: leaves deferred, frames equal") {
    const auto cov = zone::test::deferred_leaves_runs([&] {
      const std::uint64_t seed = zone::test::fresh_seed();
      CAPTURE(seed);
      const auto world = zone::test::check_replication_equivalence(seed, zone::test::deferred_leaves_case(), make_gpu_replication);
      zone::test::require_equivalent(world, true, false, false);
      return world;
    });
    CHECK(cov.deferred_leaves > 0);
  }

  TEST_CASE("GPU replication reading the GPU interest engine's visible sets in place equals the CPU replicator") {
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    zone::test::replication_equivalence_case c;
    c.budgets = {260, 900, 8192, std::size_t{1} << 20};
    c.make_visibility = make_gpu_visibility;
    const auto cov = zone::test::check_replication_equivalence(seed, c, make_gpu_replication);
    zone::test::require_equivalent(cov);
    CHECK(cov.resident_runs > 0);
    MESSAGE("engine runs that read the sets in place: " << cov.resident_runs);
  }

  TEST_CASE("GPU replication waiting by blocking or spinning (the default dozes): the same frames as the CPU replicator") {
    // The wait changes only how the host waits: every mode must give the same frames. A doze
    // engages once a wait's last eight durations are known and at least 0.4 ms (the large world's
    // in-place runs on an H100 or H200 are shorter: then this checks the path around it).
    for (const auto how : {interest::replication_engine::device_wait::block, interest::replication_engine::device_wait::spin}) {
      const std::uint64_t seed = zone::test::fresh_seed();
      CAPTURE(seed);
      CAPTURE(static_cast<int>(how));
      zone::test::replication_equivalence_case c = large_world_case();
      c.ticks = 30;
      c.make_visibility = make_gpu_visibility;
      const auto cov = zone::test::check_replication_equivalence(seed, c, [how] {
        auto e = make_gpu_replication();
        e->set_device_wait(how);
        return e;
      });
      zone::test::require_equivalent(cov);
      CHECK(cov.resident_runs > 0);
    }
  }

  TEST_CASE("GPU replication in place: a large world (20,000 entities, 3,000 clients) equals the CPU replicator") {
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    zone::test::replication_equivalence_case c = large_world_case();
    c.make_visibility = make_gpu_visibility;
    const auto cov = zone::test::check_replication_equivalence(seed, c, make_gpu_replication);
    zone::test::require_equivalent(cov);
    CHECK(cov.resident_runs > 0);
    CHECK(cov.grown_ahead_ms > 0);
  }
}
