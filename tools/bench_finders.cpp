// bench-finders: the pair finders side by side on the PBIG paper's data sets and an MMO-like zone.
//
// Finders: brute (the O(N^2) reference, small N only), cpu (grid_finder on a thread_pool of
// --threads), cpu-1t (grid_finder on the calling thread only) and cgal (CGAL's
// box_self_intersection_d, sequential, CLOSED topology, the contract's category/mask rule in its
// callback; compiled only when ZONE_HAVE_CGAL).
//
// What is timed: each finder end to end, from a box_set to a pair list in memory (for CGAL that
// includes building its box vector from the box_set, as a user would have to; that part is also
// reported on its own). Validation inside pair_finder::find is part of the grid and brute timings;
// CGAL validates nothing. Not timed: sort_canonical and the comparison. Protocol: one warm-up run
// (its output is the one checked), then --reps timed runs, each into a fresh pair list; median and
// min reported (without --reps: 3, fewer for runs of many seconds, see measure()). After timing,
// every finder's list is sorted canonically and compared for EXACT equality with the reference
// (brute where it ran, else the first finder); any mismatch makes the program exit non-zero.
//
// Modes: the default comparison; --sweep-w (W = min_boxes_per_cell for the cpu finder);
// --sweep-edge (fixed cell edges for the cpu finder). See --help.
#include <algorithm>
#include <charconv>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <optional>
#include <sstream>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include "interest/interest.h"
#include "interest/measure.h"
#include "interest/thread_pool.h"
#include "tools/cli.h"

#if ZONE_HAVE_CGAL
#include <CGAL/box_intersection_d.h>
#endif

namespace {

using namespace zone::interest;
using clock_type = std::chrono::steady_clock;

using zone::ms_since;

using zone::median;

// ---- Options --------------------------------------------------------------------------------

struct set_spec {
  std::string kind;  // uniform, gaussian, mmo, doc:<value>
  std::size_t n = 0;
  [[nodiscard]] std::string family() const { return kind; }
};

enum class mode { compare, sweep_w, sweep_edge };

struct options {
  mode run_mode = mode::compare;
  std::vector<set_spec> sets;
  std::vector<std::string> finders{"brute", "cpu", "cpu-1t", "cgal"};
  std::optional<int> reps;  // nullopt: automatic
  unsigned threads = 0;     // 0: all cores
  std::string csv_path;     // empty: mode's default
  double max_seconds = 30.0;
  std::size_t brute_max = 20000;
  std::uint64_t seed = 1;
  std::vector<double> w_values{1, 2, 3, 4, 6, 8, 12, 16, 32};
  std::vector<double> edges{25, 35, 50, 70, 100, 140, 200, 280, 400};
};

const char* const help_text = R"(bench-finders: pair finders side by side (brute, cpu, cpu-1t, CGAL).

Usage: bench-finders [options]
  --sets LIST        comma-separated KIND:N, KIND = uniform | gaussian | mmo | doc:<DoC>,
                     N like 1e5 or 100000. Default (compare mode): uniform:1e4,uniform:1e5,
                     uniform:1e6,gaussian:1e5,gaussian:1e6,doc:0.01:1e6,doc:0.1:1e6,doc:1:1e6,
                     doc:10:1e6,mmo:1e5,mmo:1e6
  --finders LIST     subset of brute,cpu,cpu-1t,cgal (default: all)
  --reps N           timed runs per finder after one warm-up; median and min reported
                     (default: 3; 1 where the warm-up took over 10 s; none where it took
                     over 30 s: that one run is then the measurement, marked 1*)
  --threads N        threads of the cpu finder (and brute); default 0 = all cores
  --csv FILE         CSV output (default, in the current directory: bench-finders.csv,
                     bench-finders-sweep-w.csv or bench-finders-sweep-edge.csv by mode);
                     directories are created
  --max-seconds S    skip a finder at larger N of a family once its median exceeded S seconds
                     at a smaller N of that family (default 30)
  --brute-max N      run brute only where N <= this (default 2e4; it is O(N^2))
  --seed S           generator seed (default 1)
  --sweep-w          cpu finder, W = min_boxes_per_cell over --w-values, on --sets
                     (default uniform:1e6,gaussian:1e6,mmo:1e6)
  --w-values LIST    default 1,2,3,4,6,8,12,16,32
  --sweep-edge       cpu finder with fixed cell edges over --edges, on --sets
                     (default uniform:1e6), plus the Eq. 6 plan for comparison
  --edges LIST       default 25,35,50,70,100,140,200,280,400
  --help             this text

Every finder's output is sorted canonically after timing and compared for exact equality;
the program exits with status 1 on any MISMATCH, 2 on bad arguments.
)";

std::optional<double> parse_number(std::string_view s) { return zone::tools::parse_value<double>(s); }

std::optional<std::size_t> parse_count(std::string_view s) {
  const auto v = parse_number(s);
  if (!v || *v < 0 || *v > 4e9 || std::floor(*v) != *v) return std::nullopt;
  return static_cast<std::size_t>(*v);
}

std::vector<std::string> split(std::string_view s, char sep) {
  std::vector<std::string> out;
  std::size_t start = 0;
  for (;;) {
    const std::size_t p = s.find(sep, start);
    const std::string_view item = s.substr(start, p == std::string_view::npos ? std::string_view::npos : p - start);
    if (!item.empty()) out.emplace_back(item);
    if (p == std::string_view::npos) break;
    start = p + 1;
  }
  return out;
}

std::optional<std::string> parse_sets(std::string_view list, std::vector<set_spec>& out) {
  out.clear();
  for (const auto& item : split(list, ',')) {
    const std::size_t colon = item.rfind(':');
    if (colon == std::string::npos) return "set '" + item + "' is not KIND:N";
    set_spec s;
    s.kind = item.substr(0, colon);
    const auto n = parse_count(std::string_view(item).substr(colon + 1));
    if (!n || *n < 2) return "set '" + item + "': bad size";
    s.n = *n;
    std::string error;
    if (!generate_named(s.kind, 2, 1, &error)) return "set '" + item + "': " + error;
    out.push_back(s);
  }
  if (out.empty()) return std::string("--sets is empty");
  return std::nullopt;
}

std::optional<std::string> parse_doubles(std::string_view list, std::vector<double>& out, const char* what) {
  out.clear();
  for (const auto& item : split(list, ',')) {
    const auto v = parse_number(item);
    if (!v || *v <= 0) return std::string(what) + ": bad value '" + item + "'";
    out.push_back(*v);
  }
  if (out.empty()) return std::string(what) + " is empty";
  return std::nullopt;
}

/// Checks the values of the command line (read by tools/cli.h); returns an error message, or nothing.
std::optional<std::string> parse_args(const std::map<std::string, std::string>& given, bool sweep_w, bool sweep_edge,
                                      options& opt) {
  if (sweep_w) opt.run_mode = mode::sweep_w;
  if (sweep_edge) opt.run_mode = mode::sweep_edge;
  const auto get = [&](const char* name) -> std::optional<std::string_view> {
    const auto it = given.find(name);
    if (it == given.end()) return std::nullopt;
    return std::string_view(it->second);
  };
  bool sets_given = false;
  if (const auto v = get("sets")) {
    if (auto e = parse_sets(*v, opt.sets)) return e;
    sets_given = true;
  }
  if (const auto v = get("finders")) {
    opt.finders = split(*v, ',');
    for (const auto& f : opt.finders) {
      if (f != "brute" && f != "cpu" && f != "cpu-1t" && f != "cgal") return "unknown finder '" + f + "'";
    }
    if (opt.finders.empty()) return std::string("--finders is empty");
  }
  if (const auto v = get("reps")) {
    const auto n = parse_count(*v);
    if (!n || *n < 1 || *n > 1000) return std::string("--reps: expected 1..1000");
    opt.reps = static_cast<int>(*n);
  }
  if (const auto v = get("threads")) {
    const auto n = parse_count(*v);
    if (!n || *n > 4096) return std::string("--threads: expected 0..4096");
    opt.threads = static_cast<unsigned>(*n);
  }
  if (const auto v = get("csv")) opt.csv_path = std::string(*v);
  if (const auto v = get("max-seconds")) {
    const auto sec = parse_number(*v);
    if (!sec || *sec <= 0) return std::string("--max-seconds: expected a positive number");
    opt.max_seconds = *sec;
  }
  if (const auto v = get("brute-max")) {
    const auto n = parse_count(*v);
    if (!n) return std::string("--brute-max: expected a count");
    opt.brute_max = *n;
  }
  if (const auto v = get("seed")) {
    const auto n = parse_count(*v);
    if (!n) return std::string("--seed: expected a non-negative integer");
    opt.seed = *n;
  }
  if (const auto v = get("w-values")) {
    if (auto e = parse_doubles(*v, opt.w_values, "--w-values")) return e;
  }
  if (const auto v = get("edges")) {
    if (auto e = parse_doubles(*v, opt.edges, "--edges")) return e;
  }
  if (!sets_given) {
    const char* defaults = opt.run_mode == mode::compare
                               ? "uniform:1e4,uniform:1e5,uniform:1e6,gaussian:1e5,gaussian:1e6,doc:0.01:1e6,"
                                 "doc:0.1:1e6,doc:1:1e6,doc:10:1e6,mmo:1e5,mmo:1e6"
                           : opt.run_mode == mode::sweep_w ? "uniform:1e6,gaussian:1e6,mmo:1e6"
                                                           : "uniform:1e6";
    if (auto e = parse_sets(defaults, opt.sets)) return e;
  }
  if (opt.csv_path.empty()) {
    opt.csv_path = opt.run_mode == mode::compare   ? "bench-finders.csv"
                   : opt.run_mode == mode::sweep_w ? "bench-finders-sweep-w.csv"
                                                   : "bench-finders-sweep-edge.csv";
  }
  if (opt.threads == 0) opt.threads = std::max(1u, std::thread::hardware_concurrency());
  return std::nullopt;
}

// ---- Host and formatting --------------------------------------------------------------------

std::string cpu_model() {
  std::ifstream in("/proc/cpuinfo");
  std::string line;
  while (std::getline(in, line)) {
    if (line.rfind("model name", 0) == 0) {
      const std::size_t colon = line.find(':');
      if (colon != std::string::npos) {
        std::string m = line.substr(colon + 1);
        m.erase(0, m.find_first_not_of(" \t"));
        return m;
      }
    }
  }
  return "unknown";
}

std::string utc_now() {
  const std::time_t t = std::time(nullptr);
  std::tm tm{};
  gmtime_r(&t, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%SZ", &tm);
  return buf;
}

std::string fmt(double v, int decimals) {
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.*f", decimals, v);
  return buf;
}

std::string fmt_n(std::size_t n) {
  // 1e4, 1e6, 2.5e5 where exact; else the plain number.
  if (n >= 1000) {
    int e = 0;
    double m = static_cast<double>(n);
    while (m >= 10 && std::fmod(m, 10) == 0) {
      m /= 10;
      ++e;
    }
    if (e >= 3 && m < 10)
      return (m == std::floor(m) ? std::to_string(static_cast<int>(m)) : fmt(m, 1)) + "e" + std::to_string(e);
  }
  return std::to_string(n);
}

std::string csv_quote(const std::string& s) {
  if (s.find_first_of(",\"\n") == std::string::npos) return s;
  std::string q = "\"";
  for (const char c : s) {
    if (c == '"') q += '"';
    q += c;
  }
  return q + "\"";
}

/// A simple fixed-width table: columns right-aligned except the ones named left.
struct table {
  std::vector<std::string> header;
  std::vector<bool> left;
  std::vector<std::vector<std::string>> rows;
  void print(std::ostream& os) const {
    std::vector<std::size_t> w(header.size());
    for (std::size_t c = 0; c < header.size(); ++c) w[c] = header[c].size();
    for (const auto& r : rows)
      for (std::size_t c = 0; c < r.size() && c < w.size(); ++c) w[c] = std::max(w[c], r[c].size());
    auto line = [&](const std::vector<std::string>& r) {
      std::string s;
      for (std::size_t c = 0; c < header.size(); ++c) {
        const std::string& cell = c < r.size() ? r[c] : std::string();
        const std::string pad(w[c] - std::min(w[c], cell.size()), ' ');
        s += (c ? "  " : "") + (left[c] ? cell + pad : pad + cell);
      }
      while (!s.empty() && s.back() == ' ') s.pop_back();
      os << s << '\n';
    };
    line(header);
    std::size_t total = 0;
    for (const auto x : w) total += x;
    os << std::string(total + 2 * (w.size() - 1), '-') << '\n';
    for (const auto& r : rows) line(r);
  }
};

bool open_csv(const std::string& path, std::ofstream& out) {
  const std::filesystem::path p(path);
  std::error_code ec;
  if (p.has_parent_path()) std::filesystem::create_directories(p.parent_path(), ec);
  out.open(path, std::ios::trunc);
  if (!out) {
    std::cerr << "bench-finders: cannot write " << path << "\n";
    return false;
  }
  return true;
}

// ---- Checking -------------------------------------------------------------------------------

/// Sorts `pairs` canonically after checking each is (a < b < n); false when one is not.
bool canonicalize(pair_list& pairs, std::size_t n, thread_pool& pool, std::string& why) {
  for (const auto& p : pairs) {
    if (!(p.a < p.b && p.b < n)) {
      why = "malformed pair (" + std::to_string(p.a) + ", " + std::to_string(p.b) + ")";
      return false;
    }
  }
  sort_canonical(pairs, n, &pool);
  return true;
}

/// Exact comparison of two canonical lists; on a difference, a short description in `why`.
bool same_pairs(const pair_list& ref, const pair_list& got, std::string& why) {
  if (ref == got) {
    for (std::size_t i = 1; i < got.size(); ++i) {
      if (!(got[i - 1] < got[i])) {
        why = "duplicate pair (" + std::to_string(got[i].a) + ", " + std::to_string(got[i].b) + ") in both lists";
        return false;
      }
    }
    return true;
  }
  std::size_t missing = 0, extra = 0;
  std::optional<id_pair> first_missing, first_extra;
  std::size_t i = 0, j = 0;
  while (i < ref.size() || j < got.size()) {
    if (j >= got.size() || (i < ref.size() && ref[i] < got[j])) {
      if (!first_missing) first_missing = ref[i];
      ++missing, ++i;
    } else if (i >= ref.size() || got[j] < ref[i]) {
      if (!first_extra) first_extra = got[j];
      ++extra, ++j;
    } else {
      ++i, ++j;
    }
  }
  std::ostringstream os;
  os << ref.size() << " reference pairs vs " << got.size() << ": " << missing << " missing, " << extra << " extra";
  if (first_missing) os << "; first missing (" << first_missing->a << ", " << first_missing->b << ")";
  if (first_extra) os << "; first extra (" << first_extra->a << ", " << first_extra->b << ")";
  if (missing == 0 && extra == 0) os << " (same multiset, duplicates or order differ)";
  why = os.str();
  return false;
}

// ---- Finders under test ---------------------------------------------------------------------

/// One run of a finder: the pairs, plus what the finder reports about itself.
struct run_result {
  double total_ms = 0;
  double build_ms = 0;  // CGAL: building its box vector (part of total_ms)
  std::uint64_t checks = 0;
  double cell_edge = 0;
  bool has_stats = false;
};

/// A finder as the benchmark drives it: one call from a box_set to a pair list, timed inside.
class bench_finder {
 public:
  virtual ~bench_finder() = default;
  virtual run_result run(const box_set& boxes, pair_list& out) = 0;
};

class zone_finder final : public bench_finder {
 public:
  explicit zone_finder(std::unique_ptr<pair_finder> f) : finder_(std::move(f)) {}
  run_result run(const box_set& boxes, pair_list& out) override {
    run_result r;
    const auto t0 = clock_type::now();
    const auto err = finder_->find(boxes, out);
    r.total_ms = ms_since(t0);
    if (err) {
      std::cerr << "bench-finders: " << finder_->name() << " rejected the set: " << err->message << "\n";
      std::exit(1);
    }
    r.checks = finder_->stats().checks;
    r.cell_edge = finder_->stats().cell_edge;
    r.has_stats = true;
    return r;
  }

 private:
  std::unique_ptr<pair_finder> finder_;
};

#if ZONE_HAVE_CGAL
/// CGAL's streaming segment-tree algorithm (Zomorodian & Edelsbrunner), sequential, closed boxes.
class cgal_finder final : public bench_finder {
 public:
  using cgal_box =
      CGAL::Box_intersection_d::Box_with_info_d<float, 3, std::uint32_t, CGAL::Box_intersection_d::ID_EXPLICIT>;
  run_result run(const box_set& boxes, pair_list& out) override {
    run_result r;
    const auto t0 = clock_type::now();
    // What a user of CGAL has to do: one CGAL box per entry of the box_set.
    std::vector<cgal_box> cgal_boxes;
    const std::size_t n = boxes.size();
    cgal_boxes.reserve(n);
    for (std::size_t i = 0; i < n; ++i) {
      float lo[3] = {boxes.lo_x[i], boxes.lo_y[i], boxes.lo_z[i]};
      float hi[3] = {boxes.hi_x[i], boxes.hi_y[i], boxes.hi_z[i]};
      cgal_boxes.emplace_back(lo, hi, static_cast<std::uint32_t>(i));
    }
    r.build_ms = ms_since(t0);
    out.clear();
    const std::uint32_t* category = boxes.category.data();
    const std::uint32_t* mask = boxes.mask.data();
    auto report = [&](const cgal_box& p, const cgal_box& q) {
      const std::uint32_t a = p.info(), b = q.info();
      if (((category[a] & mask[b]) | (category[b] & mask[a])) != 0) {
        out.push_back(a < b ? id_pair{a, b} : id_pair{b, a});
      }
    };
    CGAL::box_self_intersection_d<CGAL::Sequential_tag>(cgal_boxes.begin(), cgal_boxes.end(), report,
                                                        std::ptrdiff_t{10}, CGAL::Box_intersection_d::CLOSED);
    r.total_ms = ms_since(t0);
    return r;
  }
};
#endif

std::unique_ptr<bench_finder> make_finder(const std::string& name, thread_pool& pool) {
  if (name == "brute") return std::make_unique<zone_finder>(std::make_unique<brute_force_finder>(&pool));
  if (name == "cpu") return std::make_unique<zone_finder>(std::make_unique<grid_finder>(&pool));
  if (name == "cpu-1t") return std::make_unique<zone_finder>(std::make_unique<grid_finder>(nullptr));
#if ZONE_HAVE_CGAL
  if (name == "cgal") return std::make_unique<cgal_finder>();
#endif
  return nullptr;
}

constexpr bool have_cgal =
#if ZONE_HAVE_CGAL
    true;
#else
    false;
#endif

/// Timings of one finder on one set: warm-up (whose output is kept in `pairs`), then timed reps.
struct measurement {
  run_result first;
  std::vector<double> times_ms;
  std::vector<double> build_ms;
  pair_list pairs;
  bool warmup_only = false;  // times_ms holds the warm-up run only
};

/// Automatic repetitions (no --reps): 3 timed runs after the warm-up; 1 where the warm-up took
/// more than 10 s; none where it took more than 30 s: then the warm-up is the one measurement
/// (`warmup_only`), since a warm-up brings nothing to a run that long and the full run must fit
/// in minutes.
measurement measure(bench_finder& f, const box_set& boxes, std::optional<int> reps_opt) {
  measurement m;
  m.first = f.run(boxes, m.pairs);
  const int reps = reps_opt ? *reps_opt : m.first.total_ms > 30000 ? 0 : m.first.total_ms > 10000 ? 1 : 3;
  if (reps == 0) {
    m.warmup_only = true;
    m.times_ms.push_back(m.first.total_ms);
    m.build_ms.push_back(m.first.build_ms);
  }
  for (int r = 0; r < reps; ++r) {
    pair_list out;  // fresh every run, for every finder: the output's allocation is part of the cost
    const run_result res = f.run(boxes, out);
    m.times_ms.push_back(res.total_ms);
    m.build_ms.push_back(res.build_ms);
  }
  return m;
}

box_set make_set(const set_spec& s, std::uint64_t seed) {
  std::string error;
  auto boxes = generate_named(s.kind, s.n, seed, &error);
  if (!boxes) {
    std::cerr << "bench-finders: " << error << "\n";
    std::exit(2);
  }
  return std::move(*boxes);
}

// ---- Compare mode ---------------------------------------------------------------------------

struct row {
  std::string set;
  std::size_t n = 0;
  std::string finder;
  bool ran = false;
  std::string skip_reason;
  std::size_t pairs = 0;
  double median_ms = 0, min_ms = 0, first_ms = 0;
  int reps = 0;
  bool warmup_only = false;
  double build_median_ms = 0;
  run_result stats;
  std::string check;  // identical / MISMATCH / unchecked
  std::string speedup = "-";
};

int run_compare(const options& opt) {
  thread_pool pool(opt.threads);
  const std::string date = utc_now();
  const std::string cpu = cpu_model();
  const unsigned nproc = std::max(1u, std::thread::hardware_concurrency());
  std::cerr << "bench-finders: " << opt.sets.size() << " sets, threads " << pool.size() << ", seed " << opt.seed
            << ", host " << nproc << " x " << cpu << "\n";
  if (!have_cgal) std::cerr << "bench-finders: CGAL peer absent (built without CGAL): no cgal rows, no speedups\n";

  std::vector<row> rows;
  // (family, finder) -> (N, median ms) of the largest size run so far, for --max-seconds.
  std::map<std::pair<std::string, std::string>, std::pair<std::size_t, double>> slow;
  bool mismatch = false;

  for (const auto& spec : opt.sets) {
    const std::string label = spec.kind + ":" + fmt_n(spec.n);
    std::cerr << "[" << label << "] generating " << spec.n << " boxes (seed " << opt.seed << ")\n";
    const box_set boxes = make_set(spec, opt.seed);
    {
      const auto t0 = clock_type::now();
      const bool valid = !validate(boxes);
      std::cerr << "[" << label << "] validate(): " << fmt(ms_since(t0), 1) << " ms" << (valid ? "" : " INVALID")
                << "\n";
    }

    std::vector<row> set_rows;
    std::optional<pair_list> reference;
    std::string reference_name;
    for (const auto& name : opt.finders) {
      row r;
      r.set = spec.kind;
      r.n = spec.n;
      r.finder = name;
      if (name == "brute" && spec.n > opt.brute_max) continue;  // O(N^2): not a row at all
      if (name == "cgal" && !have_cgal) {
        r.skip_reason = "absent (built without CGAL)";
        set_rows.push_back(r);
        continue;
      }
      const auto it = slow.find({spec.family(), name});
      if (it != slow.end() && it->second.first < spec.n && it->second.second > opt.max_seconds * 1000) {
        r.skip_reason = "skipped: " + fmt(it->second.second / 1000, 1) + " s at N=" + fmt_n(it->second.first);
        std::cerr << "[" << label << "] " << name << ": " << r.skip_reason << "\n";
        set_rows.push_back(r);
        continue;
      }
      std::cerr << "[" << label << "] " << name << ": running" << std::flush;
      auto finder = make_finder(name, pool);
      measurement m = measure(*finder, boxes, opt.reps);
      r.ran = true;
      r.pairs = m.pairs.size();
      r.median_ms = median(m.times_ms);
      r.min_ms = *std::min_element(m.times_ms.begin(), m.times_ms.end());
      r.first_ms = m.first.total_ms;
      r.reps = static_cast<int>(m.times_ms.size());
      r.warmup_only = m.warmup_only;
      r.build_median_ms = median(m.build_ms);
      r.stats = m.first;
      std::cerr << " -> " << r.pairs << " pairs, first " << fmt(r.first_ms, 1) << " ms, median " << fmt(r.median_ms, 1)
                << " ms of " << r.reps << (r.warmup_only ? " (the warm-up only)" : "") << "\n";
      auto& s = slow[{spec.family(), name}];
      if (spec.n >= s.first) s = {spec.n, r.median_ms};

      std::string why;
      if (!canonicalize(m.pairs, boxes.size(), pool, why)) {
        r.check = "MISMATCH";
        std::cerr << "[" << label << "] " << name << ": MISMATCH: " << why << "\n";
      } else if (!reference) {
        reference = std::move(m.pairs);
        reference_name = name;
        r.check = "reference";
        for (std::size_t i = 1; i < reference->size(); ++i) {
          if (!((*reference)[i - 1] < (*reference)[i])) {
            r.check = "MISMATCH";
            std::cerr << "[" << label << "] " << name << ": MISMATCH: duplicate pair in its own output\n";
            break;
          }
        }
      } else if (same_pairs(*reference, m.pairs, why)) {
        r.check = "identical";
      } else {
        r.check = "MISMATCH";
        std::cerr << "[" << label << "] " << name << ": MISMATCH against " << reference_name << " (set " << spec.kind
                  << ", N " << spec.n << ", seed " << opt.seed << "): " << why << "\n";
      }
      set_rows.push_back(r);
    }

    // The reference row is identical iff every other list equalled it; a lone finder is unchecked.
    std::size_t compared = 0;
    bool any_bad = false;
    for (const auto& r : set_rows) {
      if (!r.ran) continue;
      if (r.check == "identical") ++compared;
      if (r.check == "MISMATCH") any_bad = true;
    }
    double cgal_ms = 0;
    for (const auto& r : set_rows) {
      if (r.ran && r.finder == "cgal") cgal_ms = r.median_ms;
    }
    for (auto& r : set_rows) {
      if (r.ran && r.check == "reference") r.check = any_bad ? "MISMATCH" : compared ? "identical" : "unchecked";
      if (r.ran && cgal_ms > 0 && r.median_ms > 0) r.speedup = fmt(cgal_ms / r.median_ms, 2) + "x";
      if (r.check == "MISMATCH") mismatch = true;
      rows.push_back(r);
    }
  }

  table t;
  t.header = {"set",    "N",         "pairs", "finder", "runs", "median ms", "min ms", "speedup vs CGAL",
              "checks", "cell edge", "result"};
  t.left = {true, false, false, true, false, false, false, false, false, false, true};
  for (const auto& r : rows) {
    if (!r.ran) {
      t.rows.push_back({r.set, fmt_n(r.n), "-", r.finder, "-", "-", "-", "-", "-", "-", r.skip_reason});
      continue;
    }
    t.rows.push_back({r.set, fmt_n(r.n), std::to_string(r.pairs), r.finder,
                      r.warmup_only ? "1*" : std::to_string(r.reps), fmt(r.median_ms, 1), fmt(r.min_ms, 1), r.speedup,
                      r.stats.has_stats ? std::to_string(r.stats.checks) : "-",
                      r.stats.cell_edge > 0 ? fmt(r.stats.cell_edge, 1) : "-", r.check});
  }
  std::cout << "bench-finders " << date << "  host: " << nproc << " x " << cpu << "  threads " << pool.size()
            << "  seed " << opt.seed << "\n";
  t.print(std::cout);
  std::cout << "median/min of the timed runs after one warm-up (runs = timed runs; 1* = a run over 30 s, timed once "
               "with no warm-up); cpu = grid_finder on "
            << pool.size() << " threads, cpu-1t = grid_finder single-threaded (both with default options: W = "
            << fmt(grid_finder_options{}.min_boxes_per_cell, 1) << "), cgal = CGAL box_self_intersection_d (sequential)"
            << (have_cgal ? "" : " [absent: built without CGAL]") << "\n";
  for (const auto& r : rows) {
    if (r.ran && r.finder == "cgal") {
      std::cout << "  cgal " << r.set << ":" << fmt_n(r.n) << ": building the CGAL box vector "
                << fmt(r.build_median_ms, 1) << " ms of " << fmt(r.median_ms, 1) << " ms\n";
    }
  }

  std::ofstream csv;
  if (open_csv(opt.csv_path, csv)) {
    csv << "date,host_nproc,cpu_model,set,n,seed,threads,reps,pairs,finder,median_ms,min_ms,first_ms,"
           "speedup_vs_cgal,checks,cell_edge,result,cgal_build_ms,warmup_only\n";
    for (const auto& r : rows) {
      csv << date << ',' << nproc << ',' << csv_quote(cpu) << ',' << r.set << ',' << r.n << ',' << opt.seed << ','
          << (r.finder == "cpu" || r.finder == "brute" ? pool.size() : 1u) << ',';
      if (!r.ran) {
        csv << ",," << r.finder << ",,,,,,," << csv_quote(r.skip_reason) << ",,\n";
        continue;
      }
      csv << r.reps << ',' << r.pairs << ',' << r.finder << ',' << fmt(r.median_ms, 3) << ',' << fmt(r.min_ms, 3) << ','
          << fmt(r.first_ms, 3) << ',' << (r.speedup == "-" ? "" : r.speedup.substr(0, r.speedup.size() - 1)) << ','
          << (r.stats.has_stats ? std::to_string(r.stats.checks) : "") << ','
          << (r.stats.cell_edge > 0 ? fmt(r.stats.cell_edge, 3) : "") << ',' << r.check << ','
          << (r.finder == "cgal" ? fmt(r.build_median_ms, 3) : "") << ',' << (r.warmup_only ? 1 : 0) << '\n';
    }
    std::cerr << "bench-finders: wrote " << opt.csv_path << "\n";
  }
  if (mismatch) {
    std::cerr << "bench-finders: MISMATCH between finders (see above)\n";
    return 1;
  }
  return 0;
}

// ---- Sweep modes ----------------------------------------------------------------------------

struct sweep_point {
  std::string set;
  std::size_t n = 0;
  double w = 0;           // W (sweep-w), 0 in sweep-edge
  double asked_edge = 0;  // requested fixed edge (sweep-edge), 0 = planned by Eq. 6
  double cell_edge = 0;   // the edge used
  std::uint64_t cells = 0, entries = 0, checks = 0, large = 0;
  std::size_t pairs = 0;
  double median_ms = 0, min_ms = 0;
  int reps = 0;
  std::string check;
};

int run_sweep(const options& opt) {
  const bool by_w = opt.run_mode == mode::sweep_w;
  thread_pool pool(opt.threads);
  const std::string date = utc_now();
  const std::string cpu = cpu_model();
  const unsigned nproc = std::max(1u, std::thread::hardware_concurrency());
  std::vector<sweep_point> points;
  bool mismatch = false;

  for (const auto& spec : opt.sets) {
    const std::string label = spec.kind + ":" + fmt_n(spec.n);
    std::cerr << "[" << label << "] generating " << spec.n << " boxes (seed " << opt.seed << ")\n";
    const box_set boxes = make_set(spec, opt.seed);
    std::optional<pair_list> reference;
    // Sweep-edge also runs the planned grid (W = default) first, as the point of comparison.
    std::vector<grid_finder_options> configs;
    if (by_w) {
      for (const double w : opt.w_values) {
        grid_finder_options o;
        o.min_boxes_per_cell = w;
        configs.push_back(o);
      }
    } else {
      configs.push_back(grid_finder_options{});
      for (const double e : opt.edges) {
        grid_finder_options o;
        o.fixed_cell_edge = e;
        configs.push_back(o);
      }
    }
    // Warm-up pass: one run per configuration, whose output is checked. Then the timed runs go
    // round-robin over the configurations (alternating direction), so that load from other
    // processes drifting over the minutes of a sweep falls on every configuration alike.
    std::vector<std::unique_ptr<grid_finder>> finders;
    std::vector<sweep_point> set_points;
    for (const auto& cfg : configs) {
      sweep_point p;
      p.set = spec.kind;
      p.n = spec.n;
      p.w = by_w || cfg.fixed_cell_edge == 0 ? cfg.min_boxes_per_cell : 0;
      p.asked_edge = cfg.fixed_cell_edge;
      std::cerr << "[" << label << "] cpu, "
                << (by_w                      ? "W " + fmt(cfg.min_boxes_per_cell, 0)
                    : cfg.fixed_cell_edge > 0 ? "edge " + fmt(cfg.fixed_cell_edge, 1)
                                              : std::string("planned (Eq. 6)"))
                << ": warm-up" << std::flush;
      auto finder = std::make_unique<grid_finder>(&pool, cfg);
      pair_list first;
      const auto t0 = clock_type::now();
      if (auto err = finder->find(boxes, first)) {
        std::cerr << "\nbench-finders: rejected: " << err->message << "\n";
        return 1;
      }
      const double first_ms = ms_since(t0);
      const finder_stats& st = finder->stats();
      p.cell_edge = st.cell_edge;
      p.cells = st.cells;
      p.entries = st.cell_entries;
      p.checks = st.checks;
      p.large = st.large_boxes;
      p.pairs = first.size();
      std::cerr << " -> edge " << fmt(p.cell_edge, 1) << ", " << fmt(first_ms, 1) << " ms\n";
      std::string why;
      if (!canonicalize(first, boxes.size(), pool, why)) {
        p.check = "MISMATCH";
        std::cerr << "[" << label << "] MISMATCH: " << why << "\n";
      } else if (!reference) {
        reference = std::move(first);
        p.check = "reference";
      } else if (same_pairs(*reference, first, why)) {
        p.check = "identical";
      } else {
        p.check = "MISMATCH";
        std::cerr << "[" << label << "] MISMATCH against the first configuration (seed " << opt.seed << "): " << why
                  << "\n";
      }
      if (p.check == "MISMATCH") mismatch = true;
      finders.push_back(std::move(finder));
      set_points.push_back(p);
    }
    const int reps = opt.reps ? *opt.reps : 3;
    std::vector<std::vector<double>> times(configs.size());
    for (int r = 0; r < reps; ++r) {
      std::cerr << "[" << label << "] timed round " << r + 1 << " of " << reps << "\n";
      for (std::size_t k = 0; k < configs.size(); ++k) {
        const std::size_t c = r % 2 == 0 ? k : configs.size() - 1 - k;
        pair_list out;
        const auto t0 = clock_type::now();
        (void)finders[c]->find(boxes, out);
        times[c].push_back(ms_since(t0));
      }
    }
    for (std::size_t c = 0; c < configs.size(); ++c) {
      sweep_point& p = set_points[c];
      p.median_ms = median(times[c]);
      p.min_ms = *std::min_element(times[c].begin(), times[c].end());
      p.reps = reps;
      points.push_back(p);
    }
  }

  table t;
  t.header = {"set",       "N",      by_w ? "W" : "asked edge",
              "cell edge", "cells",  "entries",
              "large",     "checks", "pairs",
              "median ms", "min ms", "result"};
  t.left = {true, false, false, false, false, false, false, false, false, false, false, true};
  for (const auto& p : points) {
    t.rows.push_back({p.set, fmt_n(p.n),
                      by_w ? fmt(p.w, p.w == std::floor(p.w) ? 0 : 2)
                           : (p.asked_edge > 0 ? fmt(p.asked_edge, 1) : "Eq.6 W=" + fmt(p.w, 0)),
                      fmt(p.cell_edge, 1), std::to_string(p.cells), std::to_string(p.entries), std::to_string(p.large),
                      std::to_string(p.checks), std::to_string(p.pairs), fmt(p.median_ms, 1), fmt(p.min_ms, 1),
                      p.check});
  }
  std::cout << "bench-finders " << (by_w ? "--sweep-w" : "--sweep-edge") << " " << date << "  host: " << nproc << " x "
            << cpu << "  cpu finder on " << pool.size() << " threads  seed " << opt.seed << "\n";
  t.print(std::cout);

  // Best per set, and (sweep-w) overall by the geometric mean over sets of time / the set's best;
  // by the median and, as a check that is less sensitive to other load on the machine, by the min.
  auto summarize = [&](const char* metric, double sweep_point::*ms) {
    std::map<std::string, double> best_ms;
    for (const auto& p : points) {
      const std::string key = p.set + ":" + fmt_n(p.n);
      if (!best_ms.count(key) || p.*ms < best_ms[key]) best_ms[key] = p.*ms;
    }
    for (const auto& p : points) {
      const std::string key = p.set + ":" + fmt_n(p.n);
      if (p.*ms == best_ms[key]) {
        std::cout << "best on " << key << " by " << metric << ": "
                  << (by_w ? "W " + fmt(p.w, 0) : "cell edge " + fmt(p.cell_edge, 1)) << " (" << fmt(p.*ms, 1)
                  << " ms)\n";
      }
    }
    if (!by_w || best_ms.size() < 2) return;
    std::map<double, std::pair<double, int>> rel;  // W -> (sum of log(time / best), sets)
    for (const auto& p : points) {
      auto& x = rel[p.w];
      x.first += std::log(p.*ms / best_ms[p.set + ":" + fmt_n(p.n)]);
      ++x.second;
    }
    double best_w = 0, best_score = 1e300;
    std::cout << "  by " << metric << ", time / the per-set best (geometric mean over sets):";
    for (const auto& [w, x] : rel) {
      const double score = std::exp(x.first / x.second);
      std::cout << "  W " << fmt(w, 0) << ": " << fmt(score, 2);
      if (score < best_score) best_score = score, best_w = w;
    }
    std::cout << "\nbest W over all sets by " << metric << ": " << fmt(best_w, 0) << " (" << fmt(best_score, 3)
              << "x the per-set best)\n";
  };
  summarize("median", &sweep_point::median_ms);
  summarize("min", &sweep_point::min_ms);

  std::ofstream csv;
  if (open_csv(opt.csv_path, csv)) {
    csv << "date,host_nproc,cpu_model,mode,set,n,seed,threads,reps,w,asked_edge,cell_edge,cells,entries,large_boxes,"
           "checks,pairs,median_ms,min_ms,result\n";
    for (const auto& p : points) {
      csv << date << ',' << nproc << ',' << csv_quote(cpu) << ',' << (by_w ? "sweep-w" : "sweep-edge") << ',' << p.set
          << ',' << p.n << ',' << opt.seed << ',' << pool.size() << ',' << p.reps << ',' << fmt(p.w, 3) << ','
          << fmt(p.asked_edge, 3) << ',' << fmt(p.cell_edge, 3) << ',' << p.cells << ',' << p.entries << ',' << p.large
          << ',' << p.checks << ',' << p.pairs << ',' << fmt(p.median_ms, 3) << ',' << fmt(p.min_ms, 3) << ','
          << p.check << '\n';
    }
    std::cerr << "bench-finders: wrote " << opt.csv_path << "\n";
  }
  if (mismatch) {
    std::cerr << "bench-finders: MISMATCH between configurations (see above)\n";
    return 1;
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  options opt;
  namespace po = zone::tools::po;
  po::options_description cli;
  std::map<std::string, std::string> given;  // the valued options, checked by parse_args
  bool sweep_w = false, sweep_edge = false;
  cli.add_options()("sweep-w", po::bool_switch(&sweep_w))("sweep-edge", po::bool_switch(&sweep_edge));
  zone::tools::add_text_options(cli, given, {"sets", "finders", "reps", "threads", "csv", "max-seconds", "brute-max", "seed",
                                             "w-values", "edges"});
  if (const auto rc = zone::tools::parse_command_line(argc, argv, "bench-finders", help_text, cli, 2)) return *rc;
  if (auto err = parse_args(given, sweep_w, sweep_edge, opt)) {
    std::cerr << "bench-finders: " << *err << "\n";
    return 2;
  }
  return opt.run_mode == mode::compare ? run_compare(opt) : run_sweep(opt);
}
