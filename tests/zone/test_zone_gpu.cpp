// Tick determinism with the GPU finder: the same seed and inputs give the same per-tick world
// digest (positions and the interest tracker's visible sets, enters and leaves) with the CPU grid
// finder and with the GPU finders (PBIG in both its output modes, LBVH, auto), with 1 and several
// threads, with the tracker reading the finder's own buffer (gpu::find_view, zone-server's way),
// and with an output buffer forced tiny (the overflow path runs inside the tick loop). Without a CUDA
// device the executable prints why and exits with 77 before any test case (CTest: Skipped).
#include <doctest/doctest.h>

#include <cstdio>
#include <cstdlib>
#include <string>

#include "../common/seeds.h"
#include "finders.h"
#include "pbig.h"
#include "world_script.h"
#include "zone.h"

using namespace zone;
using zone::test::fresh_seed;
using zone::test::run_digests;
using zone::test::small_config;

namespace {

const bool device_present = [] {
  std::string why;
  if (!gpu::device_available(nullptr, &why)) {
    std::printf("test_zone_gpu: skipped, no CUDA device: %s\n", why.c_str());
    std::fflush(stdout);
    std::_Exit(77);
  }
  return true;
}();

std::unique_ptr<interest::pair_finder> make_gpu(const gpu::pbig_options& opt) {
  std::string why;
  auto f = gpu::make_pbig_finder(opt, &why);
  if (!f) FAIL("make_pbig_finder failed: " << why);
  return f;
}

/// The tracker's pair source as zone-server sets it for GPU finders and auto.
interest_tracker::pair_view_source view_of(interest::pair_finder& f) {
  return [&f](const interest::box_set& boxes, std::span<const interest::id_pair>& view) {
    return gpu::find_view(f, boxes, view);
  };
}

}  // namespace

TEST_SUITE("zone.gpu") {
  TEST_CASE("small fast zone: CPU and GPU finders give the same per-tick digests") {
    REQUIRE(device_present);
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    const zone_config cfg = small_config(seed);
    interest::thread_pool one(1), four(4);
    interest::grid_finder cpu(&one);
    const auto reference = run_digests(cfg, cpu, &one, 60);

    gpu::pbig_options direct;
    direct.decode_pool = &four;
    auto gpu_direct = make_gpu(direct);
    CHECK(run_digests(cfg, *gpu_direct, &four, 60) == reference);
    CHECK(run_digests(cfg, *gpu_direct, nullptr, 60) == reference);  // the same finder again: plan reuse
    // zone-server's way: the tracker reads the finder's own result buffer (gpu::find_view).
    CHECK(run_digests(cfg, *gpu_direct, &four, 60, 8, view_of(*gpu_direct)) == reference);

    gpu::pbig_options paper = direct;
    paper.direct_output = false;
    paper.initial_output_pairs = 64;  // overflow and re-run inside the tick loop
    auto gpu_paper = make_gpu(paper);
    CHECK(run_digests(cfg, *gpu_paper, &four, 60) == reference);
  }

  TEST_CASE("default-sized zone with 20,000 NPCs: CPU and GPU finders agree tick by tick") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    zone_config cfg;  // the default world and NPC mix
    cfg.seed = seed;
    cfg.npc_count = 20000;
    cfg.npc_speed = 20;
    interest::thread_pool pool(4);
    interest::grid_finder cpu(&pool);
    gpu::pbig_options opt;
    opt.decode_pool = &pool;
    auto gpu_finder = make_gpu(opt);
    const auto reference = run_digests(cfg, cpu, &pool, 20, 32);
    CHECK(run_digests(cfg, *gpu_finder, &pool, 20, 32) == reference);
    CHECK(run_digests(cfg, *gpu_finder, &pool, 20, 32, view_of(*gpu_finder)) == reference);
    for (const char* name : {"lbvh", "auto"}) {
      CAPTURE(name);
      std::string why;
      auto f = gpu::make_finder(*gpu::parse_backend(name), &pool, &why);
      REQUIRE_MESSAGE(f != nullptr, why);
      CHECK(run_digests(cfg, *f, &pool, 20, 32, view_of(*f)) == reference);
    }
  }
}
