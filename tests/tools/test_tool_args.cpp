// The command lines of bench-gpu and bench-peers (tools/bench_gpu_args.h, tools/bench_peers_args.h
// on tools/cli.h), checked without a device: each flag fills its field as the hand-written loops
// these replaced did, the defaults are the documented ones, --help exits 0 and a bad argument 2.
#include <doctest/doctest.h>

#include <optional>
#include <string>
#include <vector>

#include "tools/bench_gpu_args.h"
#include "tools/bench_peers_args.h"

namespace {

/// argv for `tool args...` (argv[0] the tool).
struct argv_of {
  argv_of(const char* tool, const std::vector<const char*>& args) {
    text.emplace_back(tool);
    for (const char* a : args) text.emplace_back(a);
    for (auto& t : text) ptrs.push_back(t.data());
    ptrs.push_back(nullptr);
  }
  [[nodiscard]] int argc() const { return static_cast<int>(text.size()); }
  char** argv() { return ptrs.data(); }
  std::vector<std::string> text;
  std::vector<char*> ptrs;
};

std::optional<int> gpu(const std::vector<const char*>& args, zone::tools::bench_gpu_args& out) {
  argv_of a("bench-gpu", args);
  return zone::tools::parse_bench_gpu_args(a.argc(), a.argv(), out);
}

std::optional<int> peers(const std::vector<const char*>& args, zone::tools::bench_peers_args& out) {
  argv_of a("bench-peers", args);
  return zone::tools::parse_bench_peers_args(a.argc(), a.argv(), out);
}

}  // namespace

TEST_CASE("bench-gpu: defaults, every flag, --help and bad arguments") {
  using zone::tools::bench_gpu_args;
  {
    bench_gpu_args a;
    REQUIRE_FALSE(gpu({}, a).has_value());
    CHECK(a.only == "floors,public,overlap,targets,nsweep,cells,doc,gauss,ablation,lbvh");
    CHECK(a.csv_path == "bench-gpu.csv");
    CHECK(a.csv_lbvh == "bench_lbvh.csv");
    CHECK(a.max_n == 10000000);
    CHECK(a.reps == 5);
    CHECK(a.cgal_max_n == 1000000);
    CHECK(a.sets.empty());
    CHECK(zone::tools::bench_gpu_set_wanted(a.sets, "gaussian", 10000000));
  }
  {
    bench_gpu_args a;
    REQUIRE_FALSE(gpu({"--sets", "uniform:10000000,doc:10:1000000"}, a).has_value());
    CHECK(a.sets == "uniform:10000000,doc:10:1000000");
    CHECK(zone::tools::bench_gpu_set_wanted(a.sets, "uniform", 10000000));
    CHECK(zone::tools::bench_gpu_set_wanted(a.sets, "doc:10", 1000000));
    CHECK_FALSE(zone::tools::bench_gpu_set_wanted(a.sets, "gaussian", 10000000));
    CHECK_FALSE(zone::tools::bench_gpu_set_wanted(a.sets, "uniform", 1000000));
    CHECK_FALSE(zone::tools::bench_gpu_set_wanted(a.sets, "doc:10", 100000));
  }
  {
    bench_gpu_args a;
    REQUIRE_FALSE(gpu({"--csv", "p.csv", "--csv-lbvh", "l.csv", "--only", "public,lbvh", "--max-n", "123456", "--reps",
                       "7", "--cgal-max-n", "0"},
                      a)
                      .has_value());
    CHECK(a.csv_path == "p.csv");
    CHECK(a.csv_lbvh == "l.csv");
    CHECK(a.only == "public,lbvh");
    CHECK(a.max_n == 123456);
    CHECK(a.reps == 7);
    CHECK(a.cgal_max_n == 0);
  }
  {
    bench_gpu_args a;
    REQUIRE_FALSE(gpu({"--only=targets", "--reps=21"}, a).has_value());
    CHECK(a.only == "targets");
    CHECK(a.reps == 21);
  }
  bench_gpu_args a;
  CHECK(gpu({"--help"}, a) == 0);
  CHECK(gpu({"-h"}, a) == 0);
  for (const auto& bad : std::vector<std::vector<const char*>>{{"--frobnicate"},
                                                               {"--reps"},
                                                               {"--reps", "x"},
                                                               {"--reps", "0"},
                                                               {"--reps", "-3"},
                                                               {"--max-n", "-5"},
                                                               {"--max-n", "12x"},
                                                               {"--cgal-max-n", ""},
                                                               {"--sets", "uniform"},
                                                               {"--sets", "uniform:1e7"},
                                                               {"--sets", "uniform:100,:5"},
                                                               {"--sets", "uniform:100,"},
                                                               {"--rep", "3"},
                                                               {"stray"},
                                                               {"--csv", "a", "--csv", "b"}}) {
    CAPTURE(bad[0]);
    bench_gpu_args b;
    CHECK(gpu(bad, b) == 2);
  }
}

TEST_CASE("bench-peers: defaults, every flag, --help and bad arguments") {
  using zone::tools::bench_peers_args;
  using zone::peers::cubql_builder;
  {
    bench_peers_args a;
    REQUIRE_FALSE(peers({}, a).has_value());
    CHECK(a.csv_path == "bench-peers.csv");
    CHECK(a.sets == "uniform:100000,uniform:1000000,uniform:10000000,gaussian:1000000,doc:10:1000000,gaussian:10000000");
    CHECK(a.max_n == 10000000);
    CHECK(a.reps == 0);
    CHECK(a.leaf == 0);
    CHECK(a.builder == cubql_builder::spatial_median);
    CHECK(a.builder_name == "median");
    CHECK(a.seed == 42);
  }
  {
    bench_peers_args a;
    REQUIRE_FALSE(peers({"--csv", "x.csv", "--sets", "mmo:1000", "--max-n", "5000", "--reps", "3", "--cubql-leaf", "8",
                         "--cubql-builder", "radix", "--seed", "18446744073709551615"},
                        a)
                      .has_value());
    CHECK(a.csv_path == "x.csv");
    CHECK(a.sets == "mmo:1000");
    CHECK(a.max_n == 5000);
    CHECK(a.reps == 3);
    CHECK(a.leaf == 8);
    CHECK(a.builder == cubql_builder::radix);
    CHECK(a.builder_name == "radix");
    CHECK(a.seed == 18446744073709551615ull);
  }
  {
    bench_peers_args a;
    REQUIRE_FALSE(peers({"--cubql-builder", "rebin"}, a).has_value());
    CHECK(a.builder == cubql_builder::rebin_radix);
    CHECK(a.builder_name == "rebin");
  }
  bench_peers_args a;
  CHECK(peers({"--help"}, a) == 0);
  CHECK(peers({"--frobnicate"}, a) == 2);
  CHECK(peers({"--cubql-builder", "fastest"}, a) == 2);
  CHECK(peers({"--reps", "-1"}, a) == 2);
  CHECK(peers({"--cubql-leaf", "-2"}, a) == 2);
  CHECK(peers({"--seed", "-1"}, a) == 2);
  CHECK(peers({"--max-n", "1e6"}, a) == 2);
  CHECK(peers({"--sets"}, a) == 2);
  CHECK(peers({"uniform:100"}, a) == 2);
}
