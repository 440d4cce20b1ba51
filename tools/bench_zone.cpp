// bench-zone: the zone server's tick without sockets (docs/zone-benchmarks.md).
//
// Builds a zone_world with the default NPC mix (zone_config defaults; --entities NPCs), optionally
// K player entities with scripted movement and one replication client each (--clients), warms up,
// then runs --ticks ticks and prints per-phase p50/p99/max/mean (behaviours, integrate, interest
// and its parts: boxes, find, diff; the finder's own phases; replication; the total), the pair and
// visible counts, and the machine's load average before and after (/proc/loadavg: the machine is
// shared, so every figure is recorded with it).
//
// Ticks run back to back (as fast as possible; dt = 1 / --rate all the same) unless --paced, which
// sleeps until each tick is due at --rate like the server's loop (an overrun starts the next tick
// at once). Percentiles here are exact (sorted per-tick samples), not histogram bucket edges.
//
// The finder is a parameter (--finder; zone/interest_setup.h builds it and the GPU engine as
// zone-server does), so other backends slot in without touching the rest of the tool.
//
// Modes: the default tick table; --clients K adds replication (build() for K clients per tick,
// serial with one writer or build_many on the pool: --replicate serial|parallel|both, the frames'
// bytes hashed so the two can be compared); --sweep-w LIST reruns the finder on the world's own
// boxes for each W (grid_finder_options::min_boxes_per_cell).
#include <algorithm>
#include <atomic>
#include <cstdlib>
#include <new>
#include <charconv>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <functional>
#include <iostream>
#include <map>
#include <memory>
#include <optional>
#include <random>
#include <sstream>
#include <string>
#include <string_view>
#include <thread>
#include <time.h>
#include <dirent.h>
#include <unistd.h>
#include <cctype>
#include <vector>

#include "gpu/finders.h"
#include "gpu/replication.h"
#include "gpu/visibility.h"
#include "interest/interest.h"
#include "interest/measure.h"
#include "net/protocol.h"
#include "net/server.h"
#include "zone/zone.h"
#include "tools/cli.h"
#include "zone/interest_setup.h"

// Every heap allocation of the process is counted (operator new below), so the table can say
// how many a steady-state tick makes (the tick loop should make none).
std::atomic<std::uint64_t> g_allocations{0};

// GCC pairs this malloc with the free below across the replaced operators and warns; they match.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmismatched-new-delete"
void* operator new(std::size_t n) {
  g_allocations.fetch_add(1, std::memory_order_relaxed);
  if (void* p = std::malloc(n == 0 ? 1 : n)) return p;
  throw std::bad_alloc();
}
void* operator new[](std::size_t n) { return operator new(n); }
void operator delete(void* p) noexcept { std::free(p); }
void operator delete[](void* p) noexcept { operator delete(p); }
void operator delete(void* p, std::size_t) noexcept { operator delete(p); }
void operator delete[](void* p, std::size_t) noexcept { operator delete(p); }
#pragma GCC diagnostic pop

namespace {

using namespace zone;
using clock_type = std::chrono::steady_clock;

/// The calling thread's frame arena (--sink arena, arena-copy): one per worker, as zone-server's.
net::frame_arena& sink_arena() {
  thread_local net::frame_arena arena;
  return arena;
}

/// CPU time consumed so far (ms) by the process (all threads) or by the calling thread. Unlike
/// wall time it does not count time spent descheduled, so it is the steadier figure on a shared
/// machine.
double cpu_ms(clockid_t clock) {
  timespec ts{};
  clock_gettime(clock, &ts);
  return static_cast<double>(ts.tv_sec) * 1e3 + static_cast<double>(ts.tv_nsec) * 1e-6;
}

/// CPU time of a group of threads (those whose name is the same once a trailing "-N" or number is
/// dropped: zone-worker-1..15 -> zone-worker), from /proc/self/task/*/stat (clock ticks).
struct thread_group_cpu {
  double seconds = 0;
  int threads = 0;
};
std::map<std::string, thread_group_cpu> thread_cpu_by_name() {
  std::map<std::string, thread_group_cpu> out;
  const long hz = sysconf(_SC_CLK_TCK);
  if (hz <= 0) return out;
  DIR* d = opendir("/proc/self/task");
  if (d == nullptr) return out;
  while (const dirent* e = readdir(d)) {
    if (e->d_name[0] == '.') continue;
    const std::string base = std::string("/proc/self/task/") + e->d_name;
    std::ifstream stat(base + "/stat");
    std::string line;
    if (!std::getline(stat, line)) continue;
    // Fields after the ")" that closes the name: state is field 3, utime 14, stime 15.
    const auto close = line.rfind(')');
    if (close == std::string::npos) continue;
    std::istringstream rest(line.substr(close + 2));
    std::string field;
    double utime = 0, stime = 0;
    for (int f = 3; f <= 15 && (rest >> field); ++f) {
      if (f == 14) utime = std::atof(field.c_str());
      if (f == 15) stime = std::atof(field.c_str());
    }
    std::ifstream comm(base + "/comm");
    std::string name;
    std::getline(comm, name);
    while (!name.empty() && (std::isdigit(static_cast<unsigned char>(name.back())) != 0)) name.pop_back();
    while (!name.empty() && name.back() == '-') name.pop_back();
    if (name.empty()) name.push_back('?');
    auto& g = out[name];
    g.seconds += (utime + stime) / static_cast<double>(hz);
    ++g.threads;
  }
  closedir(d);
  return out;
}

/// Exact CPU time (ms) of every thread of the process: the sum of each thread's own CPU clock
/// (clock_gettime on its per-thread clock, by TID). CLOCK_PROCESS_CPUTIME_ID is not exact with
/// several threads running: Linux adds the pending time of the calling thread only, and other
/// running threads' time since their last scheduler tick or switch shows up later (up to a tick
/// each), which put the pool's workers' time from the world step into replication's window.
class thread_clocks {
 public:
  /// Lists the process's threads now (call again after threads are created).
  void refresh() {
    clocks_.clear();
    DIR* d = opendir("/proc/self/task");
    if (d == nullptr) return;
    while (const dirent* e = readdir(d)) {
      if (e->d_name[0] == '.') continue;
      const long tid = std::atol(e->d_name);
      if (tid <= 0) continue;
      // glibc's MAKE_THREAD_CPUCLOCK(tid, CPUCLOCK_SCHED): what pthread_getcpuclockid returns.
      clocks_.push_back(static_cast<clockid_t>((~static_cast<unsigned>(tid)) << 3) | 6);
    }
    closedir(d);
  }
  [[nodiscard]] double ms() const {
    double total = 0;
    for (const clockid_t c : clocks_) {
      timespec ts{};
      if (clock_gettime(c, &ts) == 0) total += static_cast<double>(ts.tv_sec) * 1e3 + static_cast<double>(ts.tv_nsec) * 1e-6;
    }
    return total;
  }
  [[nodiscard]] std::size_t threads() const { return clocks_.size(); }

 private:
  std::vector<clockid_t> clocks_;
};

std::string load_average() {
  std::ifstream f("/proc/loadavg");
  std::string a, b, c;
  if (!(f >> a >> b >> c)) return "unknown";
  return a + " " + b + " " + c;
}

// ---- Options --------------------------------------------------------------------------------

/// serial: build() one by one; parallel (= cpu): build_many on the pool; both: the two, compared;
/// gpu: build_many on the GPU replication engine; gpu_vs_cpu: the engine (timed as the tick's)
/// and the CPU build_many each tick, frames compared byte for byte.
enum class replicate_mode { serial, parallel, both, gpu, gpu_vs_cpu };

struct options {
  std::size_t entities = 20000;
  std::size_t clients = 0;
  std::size_t switches = 0;  // --switches: players' visibility switches a tick
  std::size_t ticks = 300;
  std::size_t warmup = 30;
  double rate = 30;
  bool paced = false;
  unsigned threads = 0;
  int spin_us = 0;  // zone_config::worker_spin_us
  std::uint64_t seed = 1;
  std::string finder = "cpu";
  double w = 0;  // 0 = the finder's default
  std::string csv;
  bool view = true;  // GPU finders / auto: the tracker reads the finder's buffer (pair_finder::find_view)
  std::string interest = "auto";  // auto | gpu | host (zone_config::interest)
  std::string host_grid = "auto";  // auto | on | off (zone_config::host_grid)
  replicate_mode replicate = replicate_mode::parallel;
  bool replicate_auto = true;  // --replicate auto: gpu when a device is usable
  bool host_views = false;     // --host-views: the GPU replication engine gets the sets from the host
  interest::replication_engine::device_wait device_wait = interest::replication_engine::device_wait::doze;  // --device-wait
  bool rep_park = true;           // --rep-park: replication_options::park_between_phases
  bool prestage = true;           // --prestage: replicator::prestage while the interest device works
  // --sink: build_many's frames written into net::frame_arena in place (as zone-server), copied
  // into it (arena-copy), copied into per-client vectors, or left where the GPU engine put them (view).
  enum class sink_mode { arena, arena_copy, copy, view } sink = sink_mode::arena;
  bool sink_arena = true;  // arena or arena_copy
  std::size_t budget = 8 * 1024;
  std::uint32_t clients_per_task = replication_options{}.clients_per_task;
  std::uint32_t wrap_threads = 0;  // --wrap-threads
  std::uint32_t snapshot = 16;  // replication_options::snapshot_entities_per_client
  float hysteresis = 4;
  std::uint32_t max_visible = 0;
  std::vector<double> sweep_w;
  double density = 0;      // entities per km^2 (the world grows with N); 0 = the config's fixed world
  std::string summary_csv;  // one line per run appended (the growth curve)
};

/// --density's reference: with the default NPC mix, about 100 visible entities per entity
/// (measured: docs/zone-benchmarks.md, "Growth past 100,000").
constexpr double reference_density = 15000;

constexpr const char* usage = R"(bench-zone: the zone server's tick (world step + replication) without sockets

Usage: bench-zone [options]
  --entities N       NPCs (default 20000; plus the config's one boss), default behaviour mix
  --clients K        player entities with scripted movement, one replication client each
                     (default 0: no replication); spawned at the towns like the server does
  --switches N       visibility switches a tick among the players (stealth on or off, team 0-2,
                     as zone-server allows them; every client takes class notes, as bot-swarm's
                     bots): after the step the replicator names the clients to tell
                     (resync_viewers_of, the "class changes" phase, part of the tick) (default 0)
  --ticks N          measured ticks (default 300)
  --warmup N         ticks before measuring (default 30)
  --rate HZ          tick rate: dt of the simulation and, with --paced, the loop rate (default 30)
  --paced            sleep until each tick is due (like zone-server); default: back to back
  --threads N        worker threads, the calling thread included (default 0 = all cores)
  --spin-us N        microseconds an idle worker spins before it sleeps, and (--paced) how early
                     the workers are woken before a tick, as zone-server's --worker-spin-us
                     (default 0, as zone-server's: no spin)
  --seed S           world seed (default 1)
  --finder NAME      pair finder: cpu (grid finder on the pool) | cpu-1t | brute | gpu (= pbig) |
                     pbig | lbvh | auto (gpu/finders.h) (default cpu)
  --w W              grid finder's W (min_boxes_per_cell; default: the finder's default)
  --host-grid MODE   the host path's candidates: on (a grid of the presence boxes, observer by
                     observer) | off (the pair finder of --finder) | auto (on when --finder is cpu,
                     or auto without a device), as zone-server's --host-grid (default auto)
  --replicate MODE   cpu (= parallel: build_many on the pool) | gpu (build_many's decisions on the
                     GPU replication engine, as zone-server --replicate gpu; exit 64 without a
                     device) | auto (gpu when a device is usable, else cpu) | serial (build()
                     one by one on this thread) | both (serial and parallel each tick, frames
                     compared) | gpu-vs-cpu (the engine, timed as the tick's, and the CPU
                     build_many each tick, frames compared byte for byte) (default auto)
  --device-wait HOW  spin | block | doze: how the GPU replication engine waits for the device
                     (replication_engine::set_device_wait; default doze, as zone-server)
  --prestage on|off  on the GPU engines, replication's entities staged and copied up while the
                     interest engine's device works (replicator::prestage; default on, as zone-server)
  --rep-park on|off  idle workers sleep after each host phase of replication on an engine
                     (replication_options::park_between_phases; default on, as zone-server)
  --sink MODE        where build_many's frames go: arena (as zone-server: written in place into
                     net::frame_arena blocks, reserved through build_many's frame room; on the GPU
                     engine, handed on from its kept output buffer without a copy),
                     arena-copy (built in the replicator's buffer, then copied into the arena),
                     copy (one vector per client, no arena) or view (on the GPU engine only: each
                     frame left where the engine put it, no copy: what a hand-off without a copy
                     would cost) (default arena)
  --budget BYTES     per-client byte budget (default 8192)
  --clients-per-task N  replication chunk size (default 64)
  --wrap-threads N   on a replication engine, the most threads handing frames to the sink (default
                     0: every worker; replication_options::wrap_threads)
  --snapshot N       build_many snapshots the entities when clients * N >= entities; 0 = never
                     (replication_options::snapshot_entities_per_client, default 16)
  --hysteresis M     (default 4)   --max-visible N (default 0 = no cap)
  --density D        constant density: the world's x and y edges grow with the entity count
                     (NPCs + bosses + clients) to hold D entities per km^2 (height unchanged),
                     so each entity sees about as many others whatever N; 15000 gives ~100
                     visible per entity with the default mix (default 0: the fixed 4,096 m world,
                     where density grows with N). "ref" = 15000
  --summary-csv FILE append one line for this run (entities, world, visible per entity, tick and
                     interest percentiles, setup time, load): the growth curve, one run per N
  --interest WHERE   auto (the GPU visibility engine when a device is usable and --max-visible is
                     0, else host) | gpu (the engine, or exit 64) | host (the finder and the host
                     diff), as zone-server's --interest (default auto)
  --host-views       with --replicate gpu: copy the players' visible sets to the host and stage
                     them for the engine, instead of its reading them in place on the device
  --find-into-list   GPU finders / auto: find() into the tracker's own pair list instead of
                     reading the finder's result buffer (pair_finder::find_view, zone-server's way)
  --csv FILE         per-tick samples (ms and counts) as CSV
  --sweep-w LIST     after the run, time the finder on the last tick's boxes for each W
                     (comma-separated; 5 calls each, median)
  --help             this text
)";

using zone::tools::parse_value;

std::optional<double> real(std::string_view s) {
  try {
    std::size_t used = 0;
    const double v = std::stod(std::string(s), &used);
    if (used != s.size() || !std::isfinite(v)) return std::nullopt;
    return v;
  } catch (...) {
    return std::nullopt;
  }
}

/// The switches of the command line (read by tools/cli.h).
struct switches {
  bool paced = false, host_views = false, find_into_list = false;
};

/// Checks the values of the command line (read by tools/cli.h: `given` holds each valued option's
/// text under its name) into `o`; returns an error message, or nothing.
std::optional<std::string> parse_args(const std::map<std::string, std::string>& given, const switches& sw, options& o) {
  o.paced = sw.paced;
  o.host_views = sw.host_views;
  o.view = !sw.find_into_list;
  std::string_view v;
  const auto value = [&](const char* name) -> bool {
    const auto it = given.find(name);
    if (it == given.end()) return false;
    v = it->second;
    return true;
  };
  const auto need = [](const char* name, const char* what) { return std::string("--") + name + ": expected " + what; };
  for (const char* name : {"entities", "clients", "switches", "ticks", "warmup", "budget"}) {
    if (!value(name)) continue;
    const auto n = parse_value<std::size_t>(v);
    if (!n) return need(name, "a count");
    (name == std::string_view("entities")   ? o.entities
     : name == std::string_view("clients")  ? o.clients
     : name == std::string_view("switches") ? o.switches
     : name == std::string_view("ticks")    ? o.ticks
     : name == std::string_view("warmup")   ? o.warmup
                                            : o.budget) = *n;
  }
  if (value("threads")) {
    const auto n = parse_value<unsigned>(v);
    if (!n || *n > 1024) return need("threads", "0..1024");
    o.threads = *n;
  }
  if (value("spin-us")) {
    const auto n = parse_value<long long>(v);
    if (!n || *n < -1 || *n > 1000000) return need("spin-us", "-1 .. 1000000");
    o.spin_us = static_cast<int>(*n);
  }
  if (value("seed")) {
    const auto n = parse_value<std::uint64_t>(v);
    if (!n) return need("seed", "an unsigned integer");
    o.seed = *n;
  }
  if (value("rate")) {
    const auto r = real(v);
    if (!r || *r <= 0 || *r > 1000) return need("rate", "a rate in (0, 1000]");
    o.rate = *r;
  }
  if (value("w")) {
    const auto r = real(v);
    if (!r || *r < 1) return need("w", "W >= 1");
    o.w = *r;
  }
  if (value("finder")) o.finder = std::string(v);
  if (value("host-grid")) {
    if (v != "auto" && v != "on" && v != "off") return need("host-grid", "auto|on|off");
    o.host_grid = std::string(v);
  }
  if (value("replicate")) {
    o.replicate_auto = false;
    if (v == "serial") o.replicate = replicate_mode::serial;
    else if (v == "parallel" || v == "cpu") o.replicate = replicate_mode::parallel;
    else if (v == "both") o.replicate = replicate_mode::both;
    else if (v == "gpu") o.replicate = replicate_mode::gpu;
    else if (v == "gpu-vs-cpu") o.replicate = replicate_mode::gpu_vs_cpu;
    else if (v == "auto") o.replicate_auto = true;
    else return need("replicate", "cpu|gpu|auto|serial|parallel|both|gpu-vs-cpu");
  }
  if (value("device-wait")) {
    using dw = interest::replication_engine::device_wait;
    if (v != "block" && v != "spin" && v != "doze") return need("device-wait", "spin|block|doze");
    o.device_wait = v == "block" ? dw::block : v == "doze" ? dw::doze : dw::spin;
  }
  if (value("sink")) {
    if (v != "arena" && v != "arena-copy" && v != "copy" && v != "view") return need("sink", "arena|arena-copy|copy|view");
    o.sink = v == "arena"        ? options::sink_mode::arena
             : v == "arena-copy" ? options::sink_mode::arena_copy
             : v == "copy"       ? options::sink_mode::copy
                                 : options::sink_mode::view;
    o.sink_arena = o.sink == options::sink_mode::arena || o.sink == options::sink_mode::arena_copy;
  }
  if (value("rep-park")) {
    if (v != "on" && v != "off") return need("rep-park", "on|off");
    o.rep_park = v == "on";
  }
  if (value("prestage")) {
    if (v != "on" && v != "off") return need("prestage", "on|off");
    o.prestage = v == "on";
  }
  if (value("clients-per-task")) {
    const auto n = parse_value<std::uint32_t>(v);
    if (!n || *n == 0) return need("clients-per-task", "a positive count");
    o.clients_per_task = *n;
  }
  if (value("wrap-threads")) {
    const auto n = parse_value<std::uint32_t>(v);
    if (!n) return need("wrap-threads", "a count (0: every worker)");
    o.wrap_threads = *n;
  }
  if (value("snapshot")) {
    const auto n = parse_value<std::uint32_t>(v);
    if (!n) return need("snapshot", "a count");
    o.snapshot = *n;
  }
  if (value("hysteresis")) {
    const auto r = real(v);
    if (!r || *r < 0) return need("hysteresis", "metres >= 0");
    o.hysteresis = static_cast<float>(*r);
  }
  if (value("max-visible")) {
    const auto n = parse_value<std::uint32_t>(v);
    if (!n) return need("max-visible", "a count");
    o.max_visible = *n;
  }
  if (value("interest")) {
    o.interest = std::string(v);
    if (o.interest != "auto" && o.interest != "gpu" && o.interest != "host") return need("interest", "auto, gpu or host");
  }
  if (value("density")) {
    if (v == "ref") {
      o.density = reference_density;
    } else {
      const auto r = real(v);
      if (!r || *r < 0 || *r > 1e9) return need("density", "entities per km^2 in [0, 1e9] or ref");
      o.density = *r;
    }
  }
  if (value("summary-csv")) o.summary_csv = std::string(v);
  if (value("csv")) o.csv = std::string(v);
  if (value("sweep-w")) {
    std::stringstream ss{std::string(v)};
    std::string item;
    while (std::getline(ss, item, ',')) {
      const auto r = real(item);
      if (!r || *r < 1) return need("sweep-w", "W values >= 1");
      o.sweep_w.push_back(*r);
    }
  }
  if (o.ticks == 0) return std::string("--ticks must be >= 1");
  // The limit the zone checks too (validate), said here with the option's name.
  if (o.entities > zone::max_entities || o.clients > zone::max_entities - std::min(o.entities, zone::max_entities) - 1) {
    return "--entities + --clients + 1 boss must be at most " + std::to_string(zone::max_entities) +
           " (the most entities one zone holds)";
  }
  return std::nullopt;
}

// ---- Samples and the table ------------------------------------------------------------------

struct series {
  explicit series(std::string n) : name(std::move(n)) {}
  std::string name;
  std::vector<double> v;
};

double mean_of(const std::vector<double>& v) {
  double s = 0;
  for (const double x : v) s += x;
  return v.empty() ? 0 : s / static_cast<double>(v.size());
}

std::uint64_t fnv(std::uint64_t h, std::span<const std::uint8_t> bytes) {
  for (const auto b : bytes) h = (h ^ b) * 0x100000001b3ull;
  return h;
}

}  // namespace

int main(int argc, char** argv) {
  options opt;
  {
    namespace po = zone::tools::po;
    po::options_description cli;
    std::map<std::string, std::string> given;  // the valued options, checked by parse_args
    switches sw;
    cli.add_options()("paced", po::bool_switch(&sw.paced))("host-views", po::bool_switch(&sw.host_views))(
        "find-into-list", po::bool_switch(&sw.find_into_list));
    zone::tools::add_text_options(
        cli, given,
        {"entities",    "clients",     "switches", "ticks",    "warmup",           "budget",       "threads",
         "spin-us",     "seed",        "rate",     "w",        "finder",           "host-grid",    "replicate",
         "device-wait", "sink",        "rep-park", "prestage", "clients-per-task", "wrap-threads", "snapshot",
         "hysteresis",  "max-visible", "interest", "density",  "summary-csv",      "csv",          "sweep-w"});
    if (const auto rc = zone::tools::parse_command_line(argc, argv, "bench-zone", usage, cli, 64)) return *rc;
    if (auto err = parse_args(given, sw, opt)) {
      std::cerr << "bench-zone: " << *err << "\n";
      return 64;
    }
  }

  zone_config spin_cfg;
  spin_cfg.worker_spin_us = opt.spin_us;
  interest::thread_pool pool(opt.threads, worker_spin(spin_cfg));
  zone_config cfg;
  cfg.npc_count = opt.entities;
  cfg.tick_rate_hz = opt.rate;
  cfg.seed = opt.seed;
  cfg.worker_threads = pool.size();
  cfg.hysteresis = opt.hysteresis;
  cfg.max_visible = opt.max_visible;
  cfg.client_byte_budget = opt.budget;
  if (opt.density > 0) {
    // Square world of (NPCs + bosses + clients) / density km^2; at least 1 m.
    const double n = static_cast<double>(opt.entities + cfg.boss_count + opt.clients);
    const auto edge = static_cast<float>(std::max(1.0, std::sqrt(n / opt.density) * 1000.0));
    cfg.world.hi.x = cfg.world.lo.x + edge;
    cfg.world.hi.y = cfg.world.lo.y + edge;
  }
  if (auto err = validate(cfg)) {
    std::cerr << "bench-zone: " << *err << "\n";
    return 64;
  }
  // The interest step as zone-server builds it (zone/interest_setup.h): the finder of --finder
  // and, per --interest, the whole step on the GPU engine when asked and possible.
  cfg.finder = opt.finder;
  cfg.interest = opt.interest;
  cfg.host_grid = opt.host_grid;
  interest::grid_finder_options grid_tuning;
  if (opt.w > 0) grid_tuning.min_boxes_per_cell = opt.w;
  interest_parts parts = make_interest_parts(cfg, &pool, grid_tuning);
  for (const std::string* why : {&parts.finder_error, &parts.engine_error}) {
    if (!why->empty()) {
      std::cerr << "bench-zone: " << *why << "\n";
      return 64;
    }
  }
  const auto& finder = parts.finder;
  const auto& engine = parts.engine;
  zone_world world(cfg, *finder, &pool);
  // As zone-server does: the GPU finders and auto hand their result buffer to the tracker
  // (pair_finder::find_view), unless --find-into-list.
  world.set_finder_view(opt.view);
  world.set_presence_grid(parts.presence_grid);
  if (engine) world.set_visibility_engine(engine.get());
  const auto setup0 = clock_type::now();
  // Progress on stdout during set-up, flushed: a million entities take seconds to place, and the
  // first ticks (the engine sizes its buffers) longer than the rest.
  std::printf("bench-zone: placing %zu NPCs + %zu bosses + %zu clients in a %.0f x %.0f x %.0f m world%s\n", opt.entities,
              cfg.boss_count, opt.clients, static_cast<double>(cfg.world.hi.x - cfg.world.lo.x),
              static_cast<double>(cfg.world.hi.y - cfg.world.lo.y), static_cast<double>(cfg.world.hi.z - cfg.world.lo.z),
              opt.density > 0 ? (" (constant density " + std::to_string(static_cast<long long>(opt.density)) + " per km^2)").c_str()
                              : "");
  std::fflush(stdout);
  world.populate();

  // Players and their replication clients, as zone-server makes them: spawned uniformly within
  // spawn_radius of town(i % towns); replication options from the config (replication_options_of).
  replication_options ro = replication_options_of(cfg);
  ro.clients_per_task = opt.clients_per_task;
  ro.wrap_threads = opt.wrap_threads;
  ro.snapshot_entities_per_client = opt.snapshot;
  ro.park_between_phases = opt.rep_park;
  replicator repl(ro), repl_serial(ro);  // repl_serial: the reference in --replicate both and gpu-vs-cpu
  // As zone-server --replicate: the decisions on the GPU replication engine when asked and possible.
  std::unique_ptr<interest::replication_engine> rep_engine;
  // As zone-server: the entities for replication staged and copied up while the interest
  // engine's device works (--prestage).
  const std::function<void()> prestage_work = [&] { repl.prestage(world.store(), world.tick(), &pool); };
  thread_clocks clocks;  // replication's CPU time, every thread read exactly (refreshed below)
  if (opt.replicate_auto || opt.replicate == replicate_mode::gpu || opt.replicate == replicate_mode::gpu_vs_cpu) {
    std::string why;
    rep_engine = gpu::make_replication_engine(&why);
    if (rep_engine) {
      if (opt.replicate_auto) opt.replicate = replicate_mode::gpu;
      rep_engine->set_device_wait(opt.device_wait);
      repl.set_engine(rep_engine.get());
      repl.set_phase_cpu_clock([&clocks] { return clocks.ms(); });
      if (opt.prestage) world.interest().set_while_device_works(&prestage_work);
      // As zone-server: the players' sets stay on the device (the CPU reference of gpu-vs-cpu
      // reads them on the host).
      if (opt.replicate != replicate_mode::gpu_vs_cpu && !opt.host_views) world.set_player_views_on_host(false);
    } else if (!opt.replicate_auto) {
      std::cerr << "bench-zone: replicate on the GPU cannot run here: " << why << "\n";
      return 64;
    }
  }
  const bool on_gpu = opt.replicate == replicate_mode::gpu || opt.replicate == replicate_mode::gpu_vs_cpu;
  if (opt.sink == options::sink_mode::view && !on_gpu) {
    // The CPU replicator's frames live in its writers, reused for the next frame.
    std::cerr << "bench-zone: --sink view needs the GPU replication engine (--replicate gpu or gpu-vs-cpu)\n";
    return 64;
  }
  const bool reference = opt.replicate == replicate_mode::both || opt.replicate == replicate_mode::gpu_vs_cpu;
  std::vector<entity_id> players;
  std::vector<replication_request> requests;
  std::mt19937_64 spawn_rng(opt.seed ^ 0x7370776eull);
  for (std::size_t k = 0; k < opt.clients; ++k) {
    const vec3 town = world.town(k % world.town_count());
    const double r = cfg.spawn_radius * std::sqrt(std::uniform_real_distribution<double>(0, 1)(spawn_rng));
    const double a = std::uniform_real_distribution<double>(0, 6.283185307179586)(spawn_rng);
    const entity_id id = world.spawn_player(
        {town.x + static_cast<float>(r * std::cos(a)), town.y + static_cast<float>(r * std::sin(a)), town.z});
    if (id == null_entity) break;
    players.push_back(id);
    requests.push_back({repl.add_client(id), 0});
    (void)repl_serial.add_client(id);
    repl.set_class_notes(requests.back().client, true);
    repl_serial.set_class_notes(requests.back().client, true);
  }
  std::mt19937_64 script(opt.seed * 7 + 1);
  std::vector<std::size_t> frame_bytes(requests.size());
  std::vector<std::uint64_t> frame_hash(requests.size());
  std::vector<replication_stats> frame_stats(requests.size());
  std::vector<std::vector<std::uint8_t>> frame_copy(requests.size()), serial_copy(requests.size());
  // --sink view: the frames where build_many's sink saw them (valid until its next call).
  std::vector<std::span<const std::uint8_t>> frame_view(opt.sink == options::sink_mode::view ? requests.size() : 0);
  if (opt.sink == options::sink_mode::copy) {
    for (auto& f : frame_copy) f.reserve(opt.budget + 4096);  // frames stay within the budget
  }
  std::vector<net::shared_frame> frame_shared(opt.sink_arena ? requests.size() : 0);
  const auto frame_of = [&](std::size_t k) -> std::span<const std::uint8_t> {
    if (opt.sink == options::sink_mode::view) return frame_view[k];
    return opt.sink_arena ? frame_shared[k].bytes() : std::span<const std::uint8_t>(frame_copy[k]);
  };
  for (auto& f : serial_copy) f.reserve(opt.budget + 4096);
  replication_writer serial_writer;

  const double setup_ms = ms_since(setup0);
  std::printf("bench-zone: placed in %.0f ms; %zu warm-up ticks next\n", setup_ms, opt.warmup);
  std::fflush(stdout);
  const std::string load_before = load_average();
  std::cout << "bench-zone: " << world.store().size() << " entities (" << opt.entities << " NPCs + bosses, "
            << players.size() << " players/clients), " << world.town_count() << " towns, interest on "
            << (engine                ? std::string(engine->name()) + " engine"
                : parts.presence_grid ? std::string("host, presence grid")
                                      : "host, finder " + std::string(finder->name()))
            << ", replication on " << (on_gpu ? "gpu engine" : opt.replicate == replicate_mode::serial ? "cpu, serial" : "cpu")
            << (opt.replicate == replicate_mode::gpu_vs_cpu ? " (and the cpu, compared)" : "")
            << ", " << pool.size() << " threads (spin " << pool.spin_us() << " us), " << opt.rate << " Hz " << (opt.paced ? "paced" : "back to back")
            << ", " << opt.warmup << " warm-up + " << opt.ticks << " ticks, seed " << opt.seed << "\n";
  std::cout << "load average before: " << load_before << "  (setup " << ms_since(setup0) << " ms)\n";

  series s_beh{"behaviours"}, s_int{"integrate"}, s_boxes{"  boxes"}, s_find{"  find"}, s_diff{"  diff"},
      s_interest{"interest"}, s_f_plan{"    plan"}, s_f_map{"    map"}, s_f_check{"    check"}, s_f_out{"    output"},
      s_d_count{"    count"}, s_d_offsets{"    offsets"}, s_d_fill{"    fill"}, s_d_rows{"    rows"},
      s_e_pack{"  engine pack"}, s_e_up{"  engine upload"}, s_e_dev{"  engine device"}, s_e_down{"  engine download"},
      s_e_grid{"    grid"}, s_e_query{"    candidates, classified"}, s_e_class{"    scans, enters placed"},
      s_e_write{"    write"}, s_e_host{"  host work (overlapped)"}, s_class{"class changes"}, s_rep{"replicate"},
      s_rep_serial{"replicate 1t"}, s_total{"tick"}, s_rep_cpu{"replicate, CPU time (all threads)"},
      s_rep_cpu_process{"replicate, CPU time (process clock, lags)"}, s_rep_serial_cpu{"replicate 1t, CPU time"},
      s_rg_total{"  engine run"}, s_rg_up{"    upload"}, s_rg_dev{"    device"}, s_rg_down{"    download"},
      s_rg_wait{"    host waiting for the device"}, s_rp_stage{"  host staging (entities, slot map, jobs)"},
      s_rp_wrap{"  wrap (frames to the sink)"}, s_rp_stage_cpu{"  host staging, CPU time (all threads)"},
      s_rp_engine_cpu{"  engine run, CPU time (all threads)"}, s_rp_wrap_cpu{"  wrap, CPU time (all threads)"};
  std::map<std::string, thread_group_cpu> threads_before;
  if (opt.replicate == replicate_mode::gpu_vs_cpu) {
    s_rep_serial.name = "replicate cpu (reference)";
    s_rep_serial_cpu.name = "replicate cpu, CPU time";
  }
  std::vector<double> step_allocs, rep_allocs;  // heap allocations per tick (world step; replication)
  std::size_t on_engine_ticks = 0;  // measured ticks whose interest step ran on the engine
  std::size_t resident_ticks = 0;   // measured ticks whose replication read the sets on the device
  std::size_t ahead_ticks = 0;      // measured ticks whose entities were on the device ahead (--prestage)
  std::vector<double> pairs, candidates, visible, enters, leaves, bytes_per_frame, checks;
  std::uint64_t frames_digest = 0xcbf29ce484222325ull, frames_mismatch = 0;
  std::vector<class_change> class_changes;  // --switches: this tick's
  std::vector<replicator::class_note_target> class_notes, ref_notes;
  std::uint64_t switch_count = 0, note_count = 0, resync_count = 0, notes_mismatch = 0;
  std::uint64_t sent_enters = 0, sent_updates = 0, sent_leaves = 0, deferred = 0, view_entries = 0;

  const auto period =
      std::chrono::duration_cast<clock_type::duration>(std::chrono::duration<double>(1.0 / opt.rate));
  auto next = clock_type::now();
  const std::size_t total_ticks = opt.warmup + opt.ticks;
  auto last_progress = clock_type::now();
  double first_tick_ms = 0;
  for (std::size_t t = 0; t < total_ticks; ++t) {
    if (opt.paced) {
      const auto now = clock_type::now();
      // As zone-server's loop: the workers are woken spin_us before the tick.
      const auto spin = std::chrono::microseconds(pool.spin_us());
      if (spin.count() > 0 && next - now > spin) {
        std::this_thread::sleep_until(next - spin);
        pool.run(pool.size(), [](std::size_t) {});
        world.prepare();
      }
      if (clock_type::now() < next) std::this_thread::sleep_until(next);
      next = std::max(next + period, clock_type::now() - period);
    }
    const bool measured = t >= opt.warmup;
    if (t == 0 || t == opt.warmup) clocks.refresh();  // the pool's and the device runtime's threads
    if (t == opt.warmup) threads_before = thread_cpu_by_name();
    // Player inputs (a seeded random walk, changed every 30 ticks).
    for (std::size_t p = 0; p < players.size(); ++p) {
      if ((t + p) % 30 == 0) {
        std::uniform_real_distribution<float> u(-1, 1);
        (void)world.set_intent(players[p], {u(script), u(script), 0});
      }
    }
    // Visibility switches (--switches), as zone-server applies a tick's set_visibility inputs.
    class_changes.clear();
    for (std::size_t k = 0; k < opt.switches && !players.empty(); ++k) {
      const entity_id id = players[script() % players.size()];
      const std::size_t x = world.store().index_of(id);
      if (x == entity_store::npos) continue;
      const std::uint32_t old_class = world.store().visibility_classes()[x], old_sees = world.store().sees()[x];
      const auto v = visibility_for(script() % 2 == 0, static_cast<std::uint8_t>(script() % 3));
      if (!world.store().set_visibility(id, v.visibility_class, v.sees)) continue;
      if (v.visibility_class != old_class || v.sees != old_sees) class_changes.push_back({id, old_class, old_sees});
    }
    const std::uint64_t alloc0 = g_allocations.load();
    const auto t0 = clock_type::now();
    if (auto err = world.step()) {
      std::cerr << "bench-zone: tick " << world.tick() << ": " << err->message << "\n";
      return 1;
    }
    const double step_ms = ms_since(t0);
    // Progress: the first tick, and a line every 10 s of a long run.
    if (t == 0) {
      first_tick_ms = step_ms;
      std::printf("bench-zone: first tick %.1f ms\n", step_ms);
      std::fflush(stdout);
      last_progress = clock_type::now();
    } else if (clock_type::now() - last_progress > std::chrono::seconds(10)) {
      std::printf("bench-zone: tick %zu of %zu (last world step %.1f ms)\n", t + 1, total_ticks, step_ms);
      std::fflush(stdout);
      last_progress = clock_type::now();
    }
    // The clients to tell of this tick's switches (after the step, before the frames, as zone-server).
    double class_ms = 0;
    if (!class_changes.empty() && !requests.empty()) {
      const auto n0 = clock_type::now();
      const std::size_t resynced =
          repl.resync_viewers_of(world.store(), world.tracker(), world.tick(), class_changes, &pool, &class_notes);
      class_ms = ms_since(n0);
      if (reference) {
        const std::size_t ref_resynced = repl_serial.resync_viewers_of(world.store(), world.tracker(), world.tick(),
                                                                       class_changes, &pool, &ref_notes);
        if (ref_resynced != resynced || ref_notes != class_notes) ++notes_mismatch;
      }
      if (t >= opt.warmup)
        switch_count += class_changes.size(), note_count += class_notes.size(), resync_count += resynced;
    }
    const std::uint64_t alloc1 = g_allocations.load();
    double rep_ms = 0, rep_serial_ms = 0, rep_cpu = 0, rep_serial_cpu = 0, rep_cpu_process = 0;
    if (!requests.empty()) {
      const std::uint64_t tick = world.tick();
      const std::uint64_t now_us = tick * 1000;  // deterministic, so frames compare across runs
      if (opt.replicate != replicate_mode::serial) {
        // parallel, both, gpu, gpu-vs-cpu: build_many (on the engine when set).
        const auto r0 = clock_type::now();
        const double c0 = clocks.ms(), p0 = cpu_ms(CLOCK_PROCESS_CPUTIME_ID);
        repl.build_many(requests, world.store(), world.tracker(), tick, now_us, &pool,
                        [&](std::size_t k, std::span<const std::uint8_t> frame, const replication_stats& st) {
                          if (opt.sink_arena) {
                            // As zone-server's sink: each worker's frames in its own blocks,
                            // written there in place (arena) or copied in (arena-copy).
                            net::frame_arena& arena = sink_arena();
                            frame_shared[k] = arena.in_reservation(frame) ? arena.commit(frame.size()) : arena.make(frame);
                          } else if (opt.sink == options::sink_mode::view) {
                            frame_view[k] = frame;  // the engine's output, valid until its next run
                          } else {
                            frame_copy[k].assign(frame.begin(), frame.end());
                          }
                          frame_stats[k] = st;
                        },
                        {},
                        opt.sink == options::sink_mode::arena
                            ? replicator::frame_room([](std::size_t, std::size_t bytes) { return sink_arena().reserve(bytes); })
                            : replicator::frame_room{},
                        // As zone-server: on the GPU engine, the frames of its kept buffer as they are.
                        opt.sink == options::sink_mode::arena
                            ? replicator::frame_share([&](std::size_t k, net::shared_frame frame, const replication_stats& st) {
                                frame_shared[k] = std::move(frame);
                                frame_stats[k] = st;
                              })
                            : replicator::frame_share{});
        rep_ms = ms_since(r0);
        rep_cpu = clocks.ms() - c0;
        rep_cpu_process = cpu_ms(CLOCK_PROCESS_CPUTIME_ID) - p0;
        // Each frame's hash on the pool (outside the timed phases; byte by byte, the digest's
        // definition, which a crowd's 16 MB a tick made half the bench's time on one thread).
        constexpr std::size_t hash_chunk = 256;
        interest::run_tasks(&pool, (requests.size() + hash_chunk - 1) / hash_chunk, [&](std::size_t t) {
          for (std::size_t k = t * hash_chunk, end = std::min(requests.size(), k + hash_chunk); k < end; ++k) {
            frame_bytes[k] = frame_of(k).size();
            frame_hash[k] = fnv(0xcbf29ce484222325ull, frame_of(k));
          }
        });
      }
      if (opt.replicate == replicate_mode::gpu_vs_cpu) {
        // The CPU replicator's build_many: the reference the engine's frames must equal.
        const auto r0 = clock_type::now();
        const double c0 = clocks.ms();
        repl_serial.build_many(requests, world.store(), world.tracker(), tick, now_us, &pool,
                               [&](std::size_t k, std::span<const std::uint8_t> frame, const replication_stats&) {
                                 serial_copy[k].assign(frame.begin(), frame.end());
                               });
        rep_serial_ms = ms_since(r0);
        rep_serial_cpu = clocks.ms() - c0;
        for (std::size_t k = 0; k < requests.size(); ++k) frames_mismatch += std::ranges::equal(serial_copy[k], frame_of(k)) ? 0 : 1;
      }
      if (opt.replicate == replicate_mode::serial || opt.replicate == replicate_mode::both) {
        replicator& r = opt.replicate == replicate_mode::both ? repl_serial : repl;
        const auto r0 = clock_type::now();
        const double c0 = cpu_ms(CLOCK_THREAD_CPUTIME_ID);
        for (std::size_t k = 0; k < requests.size(); ++k) {
          replication_stats st;
          const auto frame = r.build(requests[k].client, world.store(), world.tracker(), tick, now_us, 0, serial_writer, &st);
          serial_copy[k].assign(frame.begin(), frame.end());
          if (opt.replicate != replicate_mode::both) frame_stats[k] = st;
        }
        (opt.replicate == replicate_mode::both ? rep_serial_ms : rep_ms) = ms_since(r0);
        (opt.replicate == replicate_mode::both ? rep_serial_cpu : rep_cpu) = cpu_ms(CLOCK_THREAD_CPUTIME_ID) - c0;
        for (std::size_t k = 0; k < requests.size(); ++k) {
          const std::uint64_t h = fnv(0xcbf29ce484222325ull, serial_copy[k]);
          if (opt.replicate == replicate_mode::both) {
            if (h != frame_hash[k] || serial_copy[k].size() != frame_bytes[k]) ++frames_mismatch;
          } else {
            frame_bytes[k] = serial_copy[k].size();
            frame_hash[k] = h;
          }
        }
      }
      for (std::size_t k = 0; k < requests.size(); ++k) {
        frames_digest = (frames_digest ^ frame_hash[k]) * 0x100000001b3ull;
        if (measured) {
          bytes_per_frame.push_back(static_cast<double>(frame_bytes[k]));
          sent_enters += frame_stats[k].enters;
          sent_updates += frame_stats[k].updates;
          sent_leaves += frame_stats[k].leaves;
          deferred += frame_stats[k].deferred_enters + frame_stats[k].deferred_leaves + frame_stats[k].deferred_updates;
          view_entries += repl.view_size(requests[k].client);
        }
      }
    }
    // The tick: the world step and the (parallel, or the only) replication; the bench's own
    // frame hashing and counting above are not part of it.
    const double total_ms = step_ms + class_ms + rep_ms;
    const std::uint64_t alloc2 = g_allocations.load();
    if (!measured) continue;
    step_allocs.push_back(static_cast<double>(alloc1 - alloc0));
    rep_allocs.push_back(static_cast<double>(alloc2 - alloc1));
    const auto& ts = world.tracker().stats();
    // The host path's candidate search: the presence grid's figures, or the pair finder's.
    const auto& fs = world.tracker().reference().last_on_grid() ? world.tracker().reference().grid_stats() : finder->stats();
    const step_times& ph = world.last_step();
    s_beh.v.push_back(ph.behaviours);
    s_int.v.push_back(ph.integrate);
    s_interest.v.push_back(ph.interest);
    s_boxes.v.push_back(ts.boxes_ms);
    s_find.v.push_back(ts.find_ms);
    s_diff.v.push_back(ts.diff_ms);
    s_d_count.v.push_back(ts.count_ms);
    s_d_offsets.v.push_back(ts.offsets_ms);
    s_d_fill.v.push_back(ts.fill_ms);
    s_d_rows.v.push_back(ts.rows_ms);
    s_e_pack.v.push_back(ts.engine_timing.pack_ms);
    s_e_up.v.push_back(ts.engine_timing.upload_ms);
    s_e_dev.v.push_back(ts.engine_timing.device_ms);
    s_e_down.v.push_back(ts.engine_timing.download_ms);
    s_e_grid.v.push_back(ts.engine_timing.grid_ms);
    s_e_query.v.push_back(ts.engine_timing.query_ms);
    s_e_class.v.push_back(ts.engine_timing.place_ms);
    s_e_write.v.push_back(ts.engine_timing.write_ms);
    s_e_host.v.push_back(ts.on_engine ? ts.diff_ms : 0.0);
    on_engine_ticks += ts.on_engine ? 1 : 0;
    s_f_plan.v.push_back(fs.plan_ms);
    s_f_map.v.push_back(fs.map_ms);
    s_f_check.v.push_back(fs.check_ms);
    s_f_out.v.push_back(fs.output_ms);
    s_rep.v.push_back(rep_ms);
    s_class.v.push_back(class_ms);
    s_rep_serial.v.push_back(rep_serial_ms);
    s_rep_cpu.v.push_back(rep_cpu);
    s_rep_cpu_process.v.push_back(rep_cpu_process);
    s_rep_serial_cpu.v.push_back(rep_serial_cpu);
    if (rep_engine) {
      const auto& rt = rep_engine->timing();
      resident_ticks += rt.resident ? 1 : 0;
      s_rg_total.v.push_back(rt.total_ms);
      s_rg_up.v.push_back(rt.upload_ms);
      s_rg_dev.v.push_back(rt.device_ms);
      s_rg_down.v.push_back(rt.download_ms);
      s_rg_wait.v.push_back(rt.wait_ms);
      const auto& ph = repl.phase_times();
      ahead_ticks += ph.entities_ahead ? 1 : 0;
      s_rp_stage.v.push_back(ph.stage_ms);
      s_rp_wrap.v.push_back(ph.wrap_ms);
      s_rp_stage_cpu.v.push_back(ph.stage_cpu_ms);
      s_rp_engine_cpu.v.push_back(ph.engine_cpu_ms);
      s_rp_wrap_cpu.v.push_back(ph.wrap_cpu_ms);
    }
    s_total.v.push_back(total_ms);
    pairs.push_back(static_cast<double>(ts.pairs));
    candidates.push_back(static_cast<double>(ts.candidates));
    visible.push_back(static_cast<double>(ts.visible));
    enters.push_back(static_cast<double>(ts.enters));
    leaves.push_back(static_cast<double>(ts.leaves));
    checks.push_back(static_cast<double>(fs.checks));
  }
  const std::string load_after = load_average();
  const auto threads_after = thread_cpu_by_name();

  // ---- Report ----
  std::vector<const series*> rows = {&s_beh, &s_int, &s_interest};
  // The host path on the presence grid (interest_options::presence_grid): its build and query
  // stand in the boxes and find rows; the finder is not called.
  const bool on_grid = on_engine_ticks == 0 && world.tracker().reference().last_on_grid();
  const bool grid = ((opt.finder == "cpu" || opt.finder == "cpu-1t") && on_engine_ticks == 0) || on_grid;
  if (on_engine_ticks > 0) {
    // The engine's call (find_ms) and its parts, then the host's bookkeeping around it.
    s_find.name = "  engine call";
    for (const series* s : {&s_find, &s_e_pack, &s_e_up, &s_e_dev, &s_e_grid, &s_e_query, &s_e_class, &s_e_write, &s_e_down,
                            &s_e_host}) {
      rows.push_back(s);
    }
  } else {
    if (on_grid) {
      s_boxes.name = "  presence grid (boxes, grid)";
      s_find.name = "  candidates (grid query)";
    }
    rows.push_back(&s_boxes);
    rows.push_back(&s_find);
    if (grid && !on_grid) {
      for (const series* s : {&s_f_plan, &s_f_map, &s_f_check, &s_f_out}) rows.push_back(s);
    }
    rows.push_back(&s_diff);
    for (const series* s : {&s_d_count, &s_d_offsets, &s_d_fill, &s_d_rows}) rows.push_back(s);
  }
  if (!requests.empty()) {
    if (opt.switches > 0) rows.push_back(&s_class);
    rows.push_back(&s_rep);
    if (on_gpu && !s_rg_total.v.empty()) {
      for (const series* s : {&s_rp_stage, &s_rg_total, &s_rg_up, &s_rg_dev, &s_rg_down, &s_rg_wait, &s_rp_wrap,
                              &s_rp_stage_cpu, &s_rp_engine_cpu, &s_rp_wrap_cpu}) {
        rows.push_back(s);
      }
    }
    rows.push_back(&s_rep_cpu);
    if (opt.replicate != replicate_mode::serial) rows.push_back(&s_rep_cpu_process);
    if (reference) {
      rows.push_back(&s_rep_serial);
      rows.push_back(&s_rep_serial_cpu);
    }
  }
  rows.push_back(&s_total);
  if (opt.switches > 0) {
    const double ticks = static_cast<double>(std::max<std::size_t>(1, opt.ticks));
    std::printf("visibility switches: %.1f a tick; class notes %.1f a tick, clients resynced %.1f a tick%s\n",
                static_cast<double>(switch_count) / ticks, static_cast<double>(note_count) / ticks,
                static_cast<double>(resync_count) / ticks,
                reference ? (notes_mismatch == 0 ? " (the reference's: the same)" : " (THE REFERENCE'S DIFFER)") : "");
  }
  std::printf("\n| phase | p50 ms | p99 ms | max ms | mean ms |\n|---|---|---|---|---|\n");
  for (const series* s : rows) {
    std::printf("| %s | %.2f | %.2f | %.2f | %.2f |\n", s->name.c_str(), quantile(s->v, 0.5), quantile(s->v, 0.99),
                *std::max_element(s->v.begin(), s->v.end()), mean_of(s->v));
  }
  const double budget_ms = 1000.0 / opt.rate;
  const auto over = std::count_if(s_total.v.begin(), s_total.v.end(), [&](double x) { return x > budget_ms; });
  std::printf("\nticks over the %.1f ms budget: %lld of %zu\n", budget_ms, static_cast<long long>(over), s_total.v.size());
  std::printf("per tick (mean): pairs %.0f, candidates %.0f, visible %.0f, enters %.0f, leaves %.0f", mean_of(pairs),
              mean_of(candidates), mean_of(visible), mean_of(enters), mean_of(leaves));
  if (grid) {
    const auto& fs = on_grid ? world.tracker().reference().grid_stats() : finder->stats();
    std::printf(", %s checks %.0f, cell edge %.1f m, cells %llu, entries %llu, large boxes %llu",
                on_grid ? "presence grid" : "finder", mean_of(checks), fs.cell_edge,
                static_cast<unsigned long long>(fs.cells), static_cast<unsigned long long>(fs.cell_entries),
                static_cast<unsigned long long>(fs.large_boxes));
  }
  const double visible_per_entity = mean_of(visible) / static_cast<double>(std::max<std::size_t>(1, world.store().size()));
  std::printf("\nvisible per entity (mean): %.1f; world %.0f x %.0f m, %.0f entities per km^2\n", visible_per_entity,
              static_cast<double>(cfg.world.hi.x - cfg.world.lo.x), static_cast<double>(cfg.world.hi.y - cfg.world.lo.y),
              static_cast<double>(world.store().size()) * 1e6 /
                  (static_cast<double>(cfg.world.hi.x - cfg.world.lo.x) * static_cast<double>(cfg.world.hi.y - cfg.world.lo.y)));
  if (!requests.empty()) {
    const double frames = static_cast<double>(bytes_per_frame.size());
    std::printf("replication: %zu clients, %.2f us per client (p50 tick), CPU time %.2f us per client (mean; process clock %.2f), "
                "frame bytes p50 %.0f p99 %.0f, per frame: enters %.2f, "
                "updates %.1f, leaves %.2f, deferred %.2f; view entries per client %.1f; frames digest %016llx",
                requests.size(), quantile(s_rep.v, 0.5) * 1000.0 / static_cast<double>(requests.size()),
                mean_of(s_rep_cpu.v) * 1000.0 / static_cast<double>(requests.size()),
                mean_of(s_rep_cpu_process.v) * 1000.0 / static_cast<double>(requests.size()),
                quantile(bytes_per_frame, 0.5), quantile(bytes_per_frame, 0.99), static_cast<double>(sent_enters) / frames,
                static_cast<double>(sent_updates) / frames, static_cast<double>(sent_leaves) / frames,
                static_cast<double>(deferred) / frames, static_cast<double>(view_entries) / frames,
                static_cast<unsigned long long>(frames_digest));
    if (opt.replicate == replicate_mode::both) {
      std::printf("; serial vs parallel frames differing: %llu", static_cast<unsigned long long>(frames_mismatch));
    }
    if (opt.replicate == replicate_mode::gpu_vs_cpu) {
      std::printf("; gpu vs cpu frames differing: %llu of %llu", static_cast<unsigned long long>(frames_mismatch),
                  static_cast<unsigned long long>(static_cast<std::uint64_t>(total_ticks) * requests.size()));
    }
    if (on_gpu) {
      std::printf("; visible sets read on the device in %zu of %zu ticks; entities staged ahead in %zu", resident_ticks,
                  s_total.v.size(), ahead_ticks);
    }
    if (on_gpu && !repl.engine_error().empty()) std::printf("; GPU ENGINE FAILED: %s", repl.engine_error().c_str());
    std::printf("\n");
  }
  std::printf("heap allocations per measured tick: world step mean %.1f max %.0f", mean_of(step_allocs),
              *std::max_element(step_allocs.begin(), step_allocs.end()));
  if (!requests.empty()) {
    std::printf(", replication (%s) mean %.1f max %.0f",
                opt.replicate == replicate_mode::both ? "both modes" : "the frames' copies included", mean_of(rep_allocs),
                *std::max_element(rep_allocs.begin(), rep_allocs.end()));
  }
  std::printf("\n");
  // Where the process's CPU went over the measured ticks, by thread name (the main thread has the
  // program's name; CUDA's own threads show as theirs).
  std::printf("CPU over the measured ticks by thread (ms per tick):");
  for (const auto& [name, g] : threads_after) {
    const auto before = threads_before.find(name);
    const double sec = g.seconds - (before != threads_before.end() ? before->second.seconds : 0.0);
    std::printf(" %s (%d) %.2f;", name.c_str(), g.threads, sec * 1000.0 / static_cast<double>(std::max<std::size_t>(1, opt.ticks)));
  }
  std::printf("\n");
  std::printf("world digest after the run: %016llx\n", static_cast<unsigned long long>(world.digest()));
  std::printf("load average before: %s, after: %s\n", load_before.c_str(), load_after.c_str());

  if (!opt.summary_csv.empty()) {
    // One line per run, appended; the header when the file is new or empty.
    bool fresh = true;
    {
      std::ifstream in(opt.summary_csv);
      fresh = !in || in.peek() == std::ifstream::traits_type::eof();
    }
    std::ofstream f(opt.summary_csv, std::ios::app);
    if (!f) {
      std::cerr << "bench-zone: cannot write " << opt.summary_csv << "\n";
      return 1;
    }
    if (fresh) {
      f << "entities,clients,world_x_m,world_y_m,density_per_km2,interest,threads,visible_per_entity,pairs,setup_ms,"
           "first_tick_ms,tick_p50_ms,tick_p99_ms,tick_max_ms,interest_p50_ms,interest_p99_ms,engine_device_p50_ms,"
           "behaviours_p50_ms,integrate_p50_ms,ticks,load_before,load_after\n";
    }
    f << world.store().size() << ',' << players.size() << ',' << (cfg.world.hi.x - cfg.world.lo.x) << ','
      << (cfg.world.hi.y - cfg.world.lo.y) << ',' << opt.density << ','
      << (engine ? std::string(engine->name()) : "host " + std::string(finder->name())) << ',' << pool.size() << ','
      << visible_per_entity << ',' << mean_of(pairs) << ',' << setup_ms << ',' << first_tick_ms << ','
      << quantile(s_total.v, 0.5) << ',' << quantile(s_total.v, 0.99) << ','
      << *std::max_element(s_total.v.begin(), s_total.v.end()) << ',' << quantile(s_interest.v, 0.5) << ','
      << quantile(s_interest.v, 0.99) << ',' << quantile(s_e_dev.v, 0.5) << ',' << quantile(s_beh.v, 0.5) << ','
      << quantile(s_int.v, 0.5) << ',' << s_total.v.size() << ",\"" << load_before << "\",\"" << load_after << "\"\n";
  }

  if (!opt.csv.empty()) {
    std::ofstream f(opt.csv);
    if (!f) {
      std::cerr << "bench-zone: cannot write " << opt.csv << "\n";
      return 1;
    }
    f << "tick,behaviours_ms,integrate_ms,interest_ms,boxes_ms,find_ms,diff_ms,find_plan_ms,find_map_ms,find_check_ms,"
         "find_output_ms,replicate_ms,tick_ms,pairs,candidates,visible,enters,leaves\n";
    for (std::size_t i = 0; i < s_total.v.size(); ++i) {
      f << (opt.warmup + i + 1) << ',' << s_beh.v[i] << ',' << s_int.v[i] << ',' << s_interest.v[i] << ','
        << s_boxes.v[i] << ',' << s_find.v[i] << ',' << s_diff.v[i] << ',' << s_f_plan.v[i] << ',' << s_f_map.v[i]
        << ',' << s_f_check.v[i] << ',' << s_f_out.v[i] << ',' << s_rep.v[i] << ',' << s_total.v[i] << ','
        << pairs[i] << ',' << candidates[i] << ',' << visible[i] << ',' << enters[i] << ',' << leaves[i] << '\n';
    }
  }

  if (!opt.sweep_w.empty()) {
    // The finder alone on the last tick's boxes (the zone's real distribution), per W.
    interest::box_set boxes;
    world.tracker().build_boxes(world.store().columns(), boxes);  // also when the engine ran the ticks
    std::printf("\nW sweep on the last tick's %zu boxes (grid finder, %u threads, median of 5 calls)\n", boxes.size(),
                pool.size());
    std::printf("| W | median ms | min ms | pairs | checks | cell edge m | cells | entries | large |\n"
                "|---|---|---|---|---|---|---|---|---|\n");
    interest::pair_list out;
    for (const double w : opt.sweep_w) {
      interest::grid_finder_options g;
      g.min_boxes_per_cell = w;
      interest::grid_finder f(&pool, g);
      std::vector<double> ms;
      for (int r = 0; r < 6; ++r) {
        const auto t0 = clock_type::now();
        if (f.find(boxes, out)) return 1;
        if (r > 0) ms.push_back(ms_since(t0));  // the first call sizes the scratch memory
      }
      const auto& fs = f.stats();
      std::printf("| %.0f | %.2f | %.2f | %zu | %llu | %.1f | %llu | %llu | %llu |\n", w, quantile(ms, 0.5),
                  *std::min_element(ms.begin(), ms.end()), out.size(), static_cast<unsigned long long>(fs.checks),
                  fs.cell_edge, static_cast<unsigned long long>(fs.cells),
                  static_cast<unsigned long long>(fs.cell_entries), static_cast<unsigned long long>(fs.large_boxes));
    }
    std::printf("load average after the sweep: %s\n", load_average().c_str());
  }
  return 0;
}
