// interest-pairs: the offline CLI. Reads a box file (CSV or binary .boxes), finds every qualifying
// pair with the chosen backend and writes them as `i j` lines in canonical order; `gen` writes a
// generated data set. Usage and exit codes: docs/embedding.md and `interest-pairs --help`.
//
// Exit status: 0 success; 1 failure of the environment (no GPU for --backend gpu, a write error);
// 2 bad input or usage (unparsable or invalid box file, unknown option, missing argument).
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <charconv>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "gpu/finders.h"
#include "interest/interest.h"
#include "interest/measure.h"
#include "interest/thread_pool.h"
#include "tools/cli.h"

namespace {

namespace zi = zone::interest;

constexpr int exit_ok = 0;
constexpr int exit_failure = 1;
constexpr int exit_bad_input = 2;

constexpr const char* usage_line =
    "usage: interest-pairs [--backend brute|cpu|gpu|pbig|lbvh|auto] [--count-only] [--output FILE] [--threads N] [--quiet] INPUT\n"
    "       interest-pairs gen --set uniform|gaussian|mmo|doc:<value> --count N [--seed S] [--format csv|binary] "
    "--output FILE\n";

constexpr const char* help_text =
    "\n"
    "Finds every pair of boxes in INPUT (CSV or binary .boxes, see docs/embedding.md) that intersect and\n"
    "pass the category/mask filter; writes one line `i j` per pair (i < j, sorted by i then j).\n"
    "\n"
    "  --backend B     brute (O(N^2) reference), cpu (grid finder), gpu or pbig (PBIG on CUDA),\n"
    "                  lbvh (Karras's LBVH on CUDA), auto (per call: a GPU finder chosen from the\n"
    "                  set's statistics when a device is usable, else cpu; the default)\n"
    "  --count-only    print only the number of pairs\n"
    "  --output FILE   write to FILE instead of stdout (created only once the pairs are found)\n"
    "  --threads N     threads for the brute and cpu finders and the GPU decode (0 = all cores; default 0)\n"
    "  --quiet         log only warnings and errors (logs go to stderr)\n"
    "  --help          this text\n"
    "\n"
    "gen: writes a generated data set (boxes ids 0..N-1).\n"
    "  --set S         uniform, gaussian, mmo or doc:<degree of coverage>, e.g. doc:2.5\n"
    "  --count N       number of boxes\n"
    "  --seed S        generator seed (default 1)\n"
    "  --format F      csv or binary (default: binary when FILE ends in .boxes, else csv)\n"
    "  --output FILE   the file to write\n"
    "\n"
    "Exit status: 0 success, 1 failure (no GPU for --backend gpu/pbig/lbvh, write error),\n"
    "2 bad input or usage (the message names the offending line or box).\n";

const std::string usage_text = std::string(usage_line) + help_text;

int usage_error(const std::string& message) {
  std::fprintf(stderr, "interest-pairs: %s\n%s", message.c_str(), usage_line);
  return exit_bad_input;
}

template <class T>
bool parse_uint(std::string_view s, T& value) {
  const auto v = zone::tools::parse_value<T>(s);
  if (v) value = *v;
  return v.has_value();
}

using zone::ms_since;

/// Writes `text` pieces through a large buffer to a FILE*; remembers the first error.
class fast_writer {
 public:
  explicit fast_writer(std::FILE* f) : file_(f), buffer_(std::size_t{1} << 22) {}
  void pair_line(zi::box_id a, zi::box_id b) {
    if (buffer_.size() - used_ < 32) flush();
    char* p = buffer_.data() + used_;
    char* const end = buffer_.data() + buffer_.size();
    p = std::to_chars(p, end, a).ptr;
    *p++ = ' ';
    p = std::to_chars(p, end, b).ptr;
    *p++ = '\n';
    used_ = static_cast<std::size_t>(p - buffer_.data());
  }
  void number_line(std::uint64_t n) {
    if (buffer_.size() - used_ < 32) flush();
    char* p = buffer_.data() + used_;
    p = std::to_chars(p, buffer_.data() + buffer_.size(), n).ptr;
    *p++ = '\n';
    used_ = static_cast<std::size_t>(p - buffer_.data());
  }
  void flush() {
    if (used_ > 0 && !failed_ && std::fwrite(buffer_.data(), 1, used_, file_) != used_) {
      failed_ = true;
      errno_ = errno;
    }
    used_ = 0;
  }
  /// Flushes everything down to the OS; false (with errno in error()) on failure.
  bool finish() {
    flush();
    if (!failed_ && std::fflush(file_) != 0) {
      failed_ = true;
      errno_ = errno;
    }
    return !failed_;
  }
  [[nodiscard]] int error() const { return errno_; }

 private:
  std::FILE* file_;
  std::vector<char> buffer_;
  std::size_t used_ = 0;
  bool failed_ = false;
  int errno_ = 0;
};

/// Writes the result to `output` (empty = stdout). Returns an exit status.
int write_result(const std::string& output, const zi::pair_list& pairs, bool count_only) {
  std::FILE* f = stdout;
  if (!output.empty()) {
    f = std::fopen(output.c_str(), "wb");
    if (!f) {
      spdlog::error("cannot create '{}': {}", output, std::strerror(errno));
      return exit_failure;
    }
  }
  fast_writer w(f);
  if (count_only) {
    w.number_line(pairs.size());
  } else {
    for (const auto& p : pairs) w.pair_line(p.a, p.b);
  }
  bool ok = w.finish();
  int err = w.error();
  if (!output.empty()) {
    if (std::fclose(f) != 0 && ok) {
      ok = false;
      err = errno;
    }
    if (!ok) std::remove(output.c_str());  // never leave a partial result behind
  }
  if (!ok) {
    spdlog::error("cannot write '{}': {}", output.empty() ? std::string("<stdout>") : output, std::strerror(err));
    return exit_failure;
  }
  return exit_ok;
}

int run_gen(int argc, char** argv) {
  std::string set, count_text, seed_text = "1", format, output;
  {
    namespace po = zone::tools::po;
    po::options_description cli;
    std::map<std::string, std::string> given;
    zone::tools::add_text_options(cli, given, {"set", "count", "seed", "format", "output,o"});
    // argv[1] is "gen": the parser reads from there, as a program name.
    if (const auto rc = zone::tools::parse_command_line(argc - 1, argv + 1, "interest-pairs: gen", usage_text, cli,
                                                        exit_bad_input, nullptr, usage_line)) {
      return *rc;
    }
    zone::tools::take_text(given, "set", set);
    zone::tools::take_text(given, "count", count_text);
    zone::tools::take_text(given, "seed", seed_text);
    zone::tools::take_text(given, "format", format);
    zone::tools::take_text(given, "output", output);
  }
  if (set.empty()) return usage_error("gen: --set is required");
  if (count_text.empty()) return usage_error("gen: --count is required");
  if (output.empty()) return usage_error("gen: --output is required");
  std::size_t count = 0;
  std::uint64_t seed = 0;
  if (!parse_uint(count_text, count)) return usage_error("gen: --count '" + count_text + "' is not a non-negative integer");
  if (count > (std::size_t{1} << 32)) return usage_error("gen: --count is at most 2^32 (box ids are 32-bit)");
  if (!parse_uint(seed_text, seed)) return usage_error("gen: --seed '" + seed_text + "' is not a non-negative integer");
  if (format.empty()) format = output.ends_with(".boxes") ? "binary" : "csv";
  if (format != "csv" && format != "binary") return usage_error("gen: --format must be csv or binary, not '" + format + "'");

  std::string why;
  const auto t0 = std::chrono::steady_clock::now();
  const auto boxes = zi::generate_named(set, count, seed, &why);
  if (!boxes) return usage_error("gen: " + why);
  const auto err = format == "csv" ? zi::write_csv_file(output, *boxes) : zi::write_binary_file(output, *boxes);
  if (err) {
    spdlog::error("gen: {}", err->message);
    return exit_failure;
  }
  spdlog::info("gen: wrote {} boxes of set '{}' (seed {}) to '{}' as {} in {:.1f} ms", boxes->size(), set, seed, output,
               format, ms_since(t0));
  return exit_ok;
}

int run_pairs(int argc, char** argv) {
  std::string backend = "auto", output, threads_text = "0", input;
  bool count_only = false, quiet = false;
  {
    namespace po = zone::tools::po;
    po::options_description cli;
    std::map<std::string, std::string> given;
    zone::tools::add_text_options(cli, given, {"backend", "output,o", "threads", "input"});
    cli.add_options()("count-only", po::bool_switch(&count_only))("quiet,q", po::bool_switch(&quiet));
    po::positional_options_description positional;
    positional.add("input", 1);
    if (const auto rc = zone::tools::parse_command_line(argc, argv, "interest-pairs", usage_text, cli, exit_bad_input,
                                                        &positional, usage_line)) {
      return *rc;
    }
    zone::tools::take_text(given, "backend", backend);
    zone::tools::take_text(given, "output", output);
    zone::tools::take_text(given, "threads", threads_text);
    zone::tools::take_text(given, "input", input);
  }
  if (quiet) spdlog::set_level(spdlog::level::warn);
  const bool have_input = !input.empty();
  if (!have_input) return usage_error("missing INPUT");
  const auto chosen = zone::gpu::parse_backend(backend);
  if (!chosen) return usage_error("unknown backend '" + backend + "' (expected brute, cpu, gpu, pbig, lbvh or auto)");
  unsigned threads = 0;
  if (!parse_uint(threads_text, threads)) return usage_error("--threads '" + threads_text + "' is not a non-negative integer");
  if (output == "-") output.clear();

  zi::thread_pool pool(threads);

  // The finder first: a missing GPU is reported before a long read.
  // `auto` decides per call (and falls back to the CPU finder if a GPU finder fails mid-call).
  std::string why;
  std::unique_ptr<zi::pair_finder> finder = zone::gpu::make_finder(*chosen, &pool, &why);
  if (!finder) {
    spdlog::error("--backend {}: no usable GPU: {}", backend, why);
    return exit_failure;
  }

  auto t0 = std::chrono::steady_clock::now();
  zi::box_set boxes;
  if (const auto err = zi::read_box_file(input, boxes)) {
    spdlog::error("{}: {}", input, err->message);
    return exit_bad_input;
  }
  const double read_ms = ms_since(t0);

  t0 = std::chrono::steady_clock::now();
  zi::pair_list pairs;
  const std::optional<zi::box_error> err = finder->find(boxes, pairs);
  if (err) {
    spdlog::error("{}: {}", input, err->message);
    return exit_bad_input;
  }
  const double find_ms = ms_since(t0);
  // Every finder reports each pair once, so the count needs no canonical order.
  t0 = std::chrono::steady_clock::now();
  if (!count_only) zi::sort_canonical(pairs, boxes.size(), &pool);
  const double sort_ms = ms_since(t0);

  t0 = std::chrono::steady_clock::now();
  const int status = write_result(output, pairs, count_only);
  const auto ran = zone::gpu::last_auto_choice(*finder);
  spdlog::info("{} boxes, {} pairs, backend {} ({} threads): read {:.1f} ms, find {:.1f} ms, sort {:.1f} ms, write {:.1f} ms",
               boxes.size(), pairs.size(),
               ran ? "auto: " + std::string(zone::gpu::backend_name(*ran)) : std::string(finder->name()), pool.size(), read_ms, find_ms, sort_ms, ms_since(t0));
  return status;
}

}  // namespace

int main(int argc, char** argv) {
  // Logs go to stderr only: stdout carries the pairs.
  auto logger = spdlog::stderr_color_mt("interest-pairs");
  logger->set_pattern("%n: [%l] %v");
  spdlog::set_default_logger(logger);
  spdlog::set_level(spdlog::level::info);
  try {
    if (argc > 1 && std::string_view(argv[1]) == "gen") return run_gen(argc, argv);
    return run_pairs(argc, argv);
  } catch (const std::exception& e) {  // e.g. std::bad_alloc on a huge input
    spdlog::error("{}", e.what());
    return exit_failure;
  }
}
