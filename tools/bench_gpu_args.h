// tools/bench_gpu_args.h: bench-gpu's command line (tools/cli.h), apart from the CUDA code so that
// a test checks it on a machine without a device (tests/tools/test_tool_args.cpp).
#pragma once

#include <algorithm>
#include <charconv>
#include <cstddef>
#include <cstdio>
#include <map>
#include <optional>
#include <string>
#include <type_traits>

#include "tools/cli.h"

namespace zone::tools {

struct bench_gpu_args {
  std::string only = "floors,public,overlap,targets,nsweep,cells,doc,gauss,ablation,lbvh";
  std::string csv_path = "bench-gpu.csv";
  std::string csv_lbvh = "bench_lbvh.csv";
  std::size_t max_n = 10000000;
  int reps = 5;
  std::size_t cgal_max_n = 1000000;
  std::string sets;  ///< comma-separated KIND:N; empty: every set
};

/// Whether `sets` (bench_gpu_args::sets) lets the set KIND:N run: an empty list lets every set.
[[nodiscard]] inline bool bench_gpu_set_wanted(const std::string& sets, const char* kind, std::size_t n) {
  if (sets.empty()) return true;
  const std::string item = std::string(kind) + ":" + std::to_string(n);
  return ("," + sets + ",").find("," + item + ",") != std::string::npos;
}

inline constexpr const char* bench_gpu_usage_line =
    "usage: bench-gpu [--csv FILE] [--csv-lbvh FILE] [--only LIST] [--sets LIST] [--max-n N] [--reps R] [--cgal-max-n N]\n"
    "                 [--help]\n";

inline constexpr const char* bench_gpu_usage =
    "bench-gpu: the PBIG paper's experiments on the GPU, PBIG beside LBVH, auto, the CPU grid finder and CGAL\n\n"
    "usage: bench-gpu [--csv FILE] [--csv-lbvh FILE] [--only LIST] [--sets LIST] [--max-n N] [--reps R] [--cgal-max-n N]\n"
    "  --only LIST       comma-separated of floors,public,overlap,targets,wsweep,esweep,eplan,nsweep,cells,doc,gauss,\n"
    "                    ablation,lbvh\n"
    "                    (default: all but wsweep, esweep, eplan)\n"
    "  --sets LIST       comma-separated KIND:N (N a whole number, e.g. uniform:10000000,doc:10:1000000): only these\n"
    "                    of the public, overlap, targets, wsweep, esweep and eplan experiments' sets (default: all)\n"
    "  --csv FILE        PBIG rows as CSV (default bench-gpu.csv)\n"
    "  --csv-lbvh FILE   the lbvh experiment's rows as CSV (default bench_lbvh.csv)\n"
    "  --max-n N         skip sets larger than N boxes (default 10000000)\n"
    "  --reps R          timed repetitions per row (default 5; the targets use 21 below 10^7)\n"
    "  --cgal-max-n N    run CGAL up to N boxes (default 1000000)\n"
    "Exits 77 without a CUDA device. docs/gpu-benchmarks.md says what each table means.\n";

/// Reads bench-gpu's command line into `a`. Returns nothing when bench-gpu goes on, else its exit
/// code: 0 after --help, 2 after a message on stderr (an unknown option, a missing or bad value).
[[nodiscard]] inline std::optional<int> parse_bench_gpu_args(int argc, char** argv, bench_gpu_args& a) {
  po::options_description cli;
  std::map<std::string, std::string> given;
  add_text_options(cli, given, {"csv", "csv-lbvh", "only", "sets", "max-n", "reps", "cgal-max-n"});
  if (const auto rc = parse_command_line(argc, argv, "bench-gpu", bench_gpu_usage, cli, 2, nullptr, bench_gpu_usage_line)) {
    return rc;
  }
  const auto count = [&](const char* name, auto& out, long long least) -> bool {
    const auto it = given.find(name);
    if (it == given.end()) return true;
    const std::string& s = it->second;
    using T = std::remove_reference_t<decltype(out)>;
    const auto v = parse_value<T>(s);
    if (!v || *v < static_cast<T>(least)) {
      std::fprintf(stderr, "bench-gpu: --%s: expected a whole number >= %lld, not '%s'\n%s", name, least, s.c_str(),
                   bench_gpu_usage_line);
      return false;
    }
    out = *v;
    return true;
  };
  if (!count("max-n", a.max_n, 0) || !count("reps", a.reps, 1) || !count("cgal-max-n", a.cgal_max_n, 0)) return 2;
  take_text(given, "csv", a.csv_path);
  take_text(given, "csv-lbvh", a.csv_lbvh);
  take_text(given, "only", a.only);
  take_text(given, "sets", a.sets);
  // Each of --sets' items KIND:N with a whole N (a typo would silently skip every set).
  for (std::size_t b = 0; b <= a.sets.size() && !a.sets.empty();) {
    const std::size_t e = std::min(a.sets.find(',', b), a.sets.size());
    const std::string item = a.sets.substr(b, e - b);
    const std::size_t colon = item.rfind(':');
    if (colon == std::string::npos || colon == 0 || !parse_value<std::size_t>(item.substr(colon + 1))) {
      std::fprintf(stderr, "bench-gpu: --sets: expected KIND:N items, not '%s'\n%s", item.c_str(),
                   bench_gpu_usage_line);
      return 2;
    }
    b = e + 1;
  }
  return std::nullopt;
}

}  // namespace zone::tools
