// tools/bench_peers_args.h: bench-peers' command line (tools/cli.h), apart from the CUDA code so
// that a test checks it on a machine without a device (tests/tools/test_tool_args.cpp).
#pragma once

#include <charconv>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <map>
#include <optional>
#include <string>
#include <type_traits>

#include "tools/cli.h"
#include "tools/peers/cubql_peer.h"

namespace zone::tools {

struct bench_peers_args {
  std::string csv_path = "bench-peers.csv";
  std::string sets = "uniform:100000,uniform:1000000,uniform:10000000,gaussian:1000000,doc:10:1000000,gaussian:10000000";
  std::size_t max_n = 10000000;
  int reps = 0;  ///< 0: 21 rounds, 5 at 10^7 boxes and more
  int leaf = 0;  ///< 0: the builder's default
  peers::cubql_builder builder = peers::cubql_builder::spatial_median;
  std::string builder_name = "median";
  std::uint64_t seed = 42;
};

inline constexpr const char* bench_peers_usage =
    "bench-peers: the documented finder call (make_finder(auto), pinned_boxes, find_view) beside NVIDIA cuBQL\n\n"
    "usage: bench-peers [--csv FILE] [--sets LIST] [--max-n N] [--reps R] [--cubql-leaf L] [--cubql-builder B]\n"
    "                   [--seed S]\n"
    "  --csv FILE       rows as CSV (default bench-peers.csv)\n"
    "  --sets LIST      comma-separated KIND:N, KIND one of uniform, gaussian, mmo, doc:<value>\n"
    "                   (default: the six target sets, uniform 1e5/1e6/1e7, gaussian 1e6, doc:10 1e6, gaussian 1e7)\n"
    "  --max-n N        skip sets larger than N boxes (default 10000000)\n"
    "  --reps R         timed rounds per set (default 21; 5 at 10^7 boxes and more)\n"
    "  --cubql-leaf L   cuBQL BuildConfig::makeLeafThreshold (default 0: the builder's default)\n"
    "  --cubql-builder B  median (cuBQL::gpuBuilder, default BuildConfig; the default), radix\n"
    "                   (cuBQL::cuda::radixBuilder) or rebin (cuBQL::cuda::rebinRadixBuilder)\n"
    "  --seed S         generator seed (default 42)\n"
    "A self-check (cuBQL against brute force on edge-case sets) runs first. Exits 1 when a pair set\n"
    "differs, 77 without a CUDA device. docs/gpu-benchmarks.md says what the table means.\n";

/// Reads bench-peers' command line into `a` (the set list is checked by bench-peers, against the
/// generators). Returns nothing when bench-peers goes on, else its exit code: 0 after --help, 2
/// after a message on stderr (an unknown option, a missing or bad value).
[[nodiscard]] inline std::optional<int> parse_bench_peers_args(int argc, char** argv, bench_peers_args& a) {
  po::options_description cli;
  std::map<std::string, std::string> given;
  add_text_options(cli, given, {"csv", "sets", "max-n", "reps", "cubql-leaf", "cubql-builder", "seed"});
  if (const auto rc = parse_command_line(argc, argv, "bench-peers", bench_peers_usage, cli, 2)) return rc;
  const auto number = [&](const char* name, auto& out) -> bool {
    const auto it = given.find(name);
    if (it == given.end()) return true;
    const std::string& s = it->second;
    const auto v = parse_value<std::remove_reference_t<decltype(out)>>(s);
    if (!v) {
      std::fprintf(stderr, "bench-peers: bad value for --%s (see --help)\n", name);
      return false;
    }
    out = *v;
    return true;
  };
  if (!number("max-n", a.max_n) || !number("reps", a.reps) || !number("cubql-leaf", a.leaf) || !number("seed", a.seed)) {
    return 2;
  }
  if (a.reps < 0 || a.leaf < 0) {
    std::fprintf(stderr, "bench-peers: --reps and --cubql-leaf take values >= 0\n");
    return 2;
  }
  take_text(given, "csv", a.csv_path);
  take_text(given, "sets", a.sets);
  if (const auto it = given.find("cubql-builder"); it != given.end()) {
    a.builder_name = it->second;
    if (a.builder_name == "median") a.builder = peers::cubql_builder::spatial_median;
    else if (a.builder_name == "radix") a.builder = peers::cubql_builder::radix;
    else if (a.builder_name == "rebin") a.builder = peers::cubql_builder::rebin_radix;
    else {
      std::fprintf(stderr, "bench-peers: unknown --cubql-builder '%s' (median, radix, rebin)\n", a.builder_name.c_str());
      return 2;
    }
  }
  return std::nullopt;
}

}  // namespace zone::tools
