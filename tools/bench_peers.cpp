// bench-peers: the public finder API (the documented call of docs/embedding.md and
// examples/find_pairs) beside NVIDIA's cuBQL (tools/peers/cubql_peer.h: its default GPU BVH
// builder, a count query, a scan, a fill query; pinned in, pinned pairs out) on the six target
// sets. Prints a table and writes CSV.
//
//   bench-peers [--csv FILE] [--sets LIST] [--max-n N] [--reps R] [--cubql-leaf L]
//               [--cubql-builder B] [--seed S]
//
// Per set: the boxes generated once (seed 42 unless --seed), the set pinned (pinned_boxes) for
// the documented call, and a page-locked AoS copy (6 floats a box; category/mask only when some
// box is not category = mask = 1) made for cuBQL, both outside the timing. One warm-up of each,
// then their pair sets compared (count + order-independent hash: "verified"; a mismatch fails
// the run, exit 1), then R rounds (default 21; 5 at 10^7 boxes and more) that time each once,
// alternating which goes first; medians and minima. Then one call of a PBIG finder with the
// default options on the same pinned set (the path auto takes there) for its phase report:
// where the documented call's time goes.
//
// Before anything, a self-check: cuBQL's pairs against the brute-force reference, element by
// element, on small sets with touching faces, duplicate and zero-size boxes and mixed classes
// (exit 1 if they differ). Exits 77 without a CUDA device.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <limits>
#include <memory>
#include <random>
#include <span>
#include <string>
#include <vector>

#include "gpu/finders.h"
#include "gpu/pbig.h"
#include "interest/interest.h"
#include "interest/measure.h"
#include "interest/thread_pool.h"
#include "tools/bench_peers_args.h"
#include "tools/pair_digest.h"
#include "tools/peers/cubql_peer.h"

namespace zi = zone::interest;
namespace zg = zone::gpu;
namespace zp = zone::peers;

namespace {

using clock_type = std::chrono::steady_clock;
using zone::median;
using zone::ms_since;

static_assert(sizeof(zi::id_pair) == 8, "an id_pair is two 32-bit ids, as the peer writes them");

using zone::bench::digest;
using zone::bench::pair_digest;

/// A box set's copy in the peer's input layout, in page-locked memory.
struct peer_input {
  float* boxes = nullptr;
  std::uint32_t* category = nullptr;  // null: every box category = mask = 1 (the plain self-join)
  std::uint32_t* mask = nullptr;
  std::size_t n = 0;
  explicit peer_input(const zi::box_set& s) : n(s.size()) {
    boxes = static_cast<float*>(zp::alloc_pinned(6 * n * sizeof(float)));
    for (std::size_t i = 0; i < n; ++i) {
      float* b = boxes + 6 * i;
      b[0] = s.lo_x[i], b[1] = s.lo_y[i], b[2] = s.lo_z[i], b[3] = s.hi_x[i], b[4] = s.hi_y[i], b[5] = s.hi_z[i];
    }
    bool plain = true;
    for (std::size_t i = 0; i < n && plain; ++i) plain = s.category[i] == 1 && s.mask[i] == 1;
    if (!plain) {
      category = static_cast<std::uint32_t*>(zp::alloc_pinned(n * 4));
      mask = static_cast<std::uint32_t*>(zp::alloc_pinned(n * 4));
      std::memcpy(category, s.category.data(), n * 4);
      std::memcpy(mask, s.mask.data(), n * 4);
    }
  }
  ~peer_input() {
    zp::free_pinned(boxes);
    zp::free_pinned(category);
    zp::free_pinned(mask);
  }
  peer_input(const peer_input&) = delete;
  peer_input& operator=(const peer_input&) = delete;
};

std::span<const zi::id_pair> peer_pairs(const zp::cubql_join& peer, std::uint64_t count) {
  return {reinterpret_cast<const zi::id_pair*>(peer.pairs()), static_cast<std::size_t>(count)};
}

/// Small sets with the contract's edge cases: coordinates on a coarse lattice (touching faces and
/// edges), zero-size boxes, exact duplicates, and (when `classes`) random category/mask bits.
zi::box_set edge_case_set(std::size_t n, bool classes, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<int> cell(0, 15), size(0, 3), bits(0, 7);
  zi::box_set s;
  for (std::size_t i = 0; i < n; ++i) {
    zi::box b;
    if (i > 0 && i % 17 == 0) {
      b = s.get(i - 1);  // a duplicate of the previous box
    } else {
      for (int d = 0; d < 3; ++d) {
        b.lo[d] = static_cast<float>(cell(rng));
        b.hi[d] = b.lo[d] + static_cast<float>(i % 11 == 0 ? 0 : size(rng));  // some zero-size boxes
      }
      if (classes) {
        b.category = static_cast<std::uint32_t>(bits(rng));
        b.mask = static_cast<std::uint32_t>(bits(rng));
      }
    }
    s.push_back(b);
  }
  return s;
}

/// cuBQL against the brute-force reference on edge-case and random sets; false on any difference.
bool self_check(zi::thread_pool& pool, int leaf, zp::cubql_builder builder) {
  zp::cubql_join peer(leaf, builder);
  zi::brute_force_finder brute(&pool);
  bool ok = true;
  struct c {
    const char* name;
    zi::box_set s;
  };
  std::vector<c> cases;
  cases.push_back({"lattice, plain", edge_case_set(3000, false, 7)});
  cases.push_back({"lattice, classes", edge_case_set(3000, true, 8)});
  cases.push_back({"uniform 20000", *zi::generate_named("uniform", 20000, 9)});
  cases.push_back({"gaussian 20000", *zi::generate_named("gaussian", 20000, 10)});
  cases.push_back({"one box", edge_case_set(1, false, 11)});
  for (const c& k : cases) {
    const peer_input in(k.s);
    const std::uint64_t count = peer.run(in.boxes, in.category, in.mask, in.n);
    std::vector<zi::id_pair> got(peer_pairs(peer, count).begin(), peer_pairs(peer, count).end());
    std::sort(got.begin(), got.end());
    zi::pair_list want;
    (void)brute.find(k.s, want);
    std::vector<zi::id_pair> ref(want.begin(), want.end());
    for (auto& p : ref) {
      if (p.a > p.b) std::swap(p.a, p.b);
    }
    std::sort(ref.begin(), ref.end());
    const bool same = got == ref;
    std::printf("  self-check %-17s %6zu boxes: cuBQL %8zu pairs, brute force %8zu: %s\n", k.name, k.s.size(),
                got.size(), ref.size(), same ? "same" : "DIFFERENT");
    ok = ok && same;
  }
  return ok;
}

/// The PBIG variants timed beside the documented call: the defaults first, then each of this
/// session's changes off, then both off (the code before them).
struct variant {
  const char* name;
  zg::pbig_options options;
};
const variant variants[] = {
    {"defaults", zg::pbig_options{}},
    {"no-class-fill", zg::pbig_options{.fill_uniform_classes = false}},
    {"gathered", zg::pbig_options{.indirect_check_min_boxes = std::numeric_limits<std::size_t>::max()}},
    {"neither", zg::pbig_options{.indirect_check_min_boxes = std::numeric_limits<std::size_t>::max(),
                                 .fill_uniform_classes = false}},
};
struct variant_result {
  const char* name;
  std::unique_ptr<zi::pair_finder> finder;
  std::vector<double> ms;
  std::vector<zg::pbig_report> reports;
  double median = 0;
};

struct set_spec {
  std::string kind;
  std::size_t n;
};

}  // namespace

int main(int argc, char** argv) {
  zone::tools::bench_peers_args args;
  if (const auto rc = zone::tools::parse_bench_peers_args(argc, argv, args)) return *rc;
  const std::string& csv_path = args.csv_path;
  const std::string& sets = args.sets;
  const std::size_t max_n = args.max_n;
  const int reps = args.reps;
  const int leaf = args.leaf;
  const zp::cubql_builder builder = args.builder;
  const std::string& builder_name = args.builder_name;
  const std::uint64_t seed = args.seed;
  std::vector<set_spec> specs;
  {
    std::size_t b = 0;
    while (b <= sets.size()) {
      std::size_t e = sets.find(',', b);
      if (e == std::string::npos) e = sets.size();
      const std::string item = sets.substr(b, e - b);
      const std::size_t colon = item.rfind(':');
      std::size_t n = 0;
      bool ok = colon != std::string::npos && colon > 0;
      if (ok) {
        try {
          std::size_t used = 0;
          n = std::stoull(item.substr(colon + 1), &used);
          ok = used == item.size() - colon - 1 && n > 0;
        } catch (const std::exception&) {
          ok = false;
        }
      }
      std::string why;
      if (ok && !zi::generate_named(item.substr(0, colon), 1, 1, &why)) ok = false;
      if (!ok) {
        std::fprintf(stderr, "bench-peers: bad set '%s' (KIND:N, e.g. uniform:100000; %s)\n", item.c_str(),
                     why.empty() ? "see --help" : why.c_str());
        return 2;
      }
      specs.push_back({item.substr(0, colon), n});
      b = e + 1;
    }
  }
  std::string why;
  zg::device_info dev;
  if (!zg::device_available(&dev, &why) || !zp::cubql_join::device_usable()) {
    std::fprintf(stderr, "bench-peers: %s\n", why.empty() ? "no CUDA device" : why.c_str());
    return 77;
  }
  zi::thread_pool pool(0);
  std::printf("bench-peers on %s (%d SMs), %u host threads\n", dev.name.c_str(), dev.multiprocessors, pool.size());
  std::printf("cuBQL builder: %s, leaf threshold %d\n", builder_name.c_str(), leaf);
  if (!self_check(pool, leaf, builder)) {
    std::fprintf(stderr, "bench-peers: cuBQL's pairs differ from the brute-force reference\n");
    return 1;
  }

  std::ofstream csv(csv_path);
  csv << "set,n,pairs,public_ms,public_min_ms,public_choice,cubql_ms,cubql_min_ms,cubql_over_public,cubql_in_ms,"
         "cubql_build_ms,cubql_count_ms,cubql_scan_ms,cubql_fill_ms,cubql_out_ms,pbig_ms,pbig_in_ms,pbig_plan_ms,"
         "pbig_map_ms,pbig_map_count_ms,pbig_map_scatter_ms,pbig_map_sort_ms,pbig_map_gather_ms,pbig_check_ms,"
         "pbig_out_ms,pbig_pipeline_ms,pbig_batches,bytes_in,bytes_out,floor_serial_ms,cubql_leaf,pbig_no_fill_ms,"
         "pbig_no_indirect_ms,pbig_neither_ms,classes_filled,indirect_check,cubql_builder,verified\n";
  std::printf("\n== The documented call (make_finder(auto), pinned_boxes, find_view) beside cuBQL (gpuBuilder, count, "
              "scan, fill; pinned in and out); ms, medians\n");
  std::printf("%-9s %9s %13s %10s %-5s %10s %7s | %7s %7s %7s %7s %7s %7s | %7s %7s %7s %7s %7s %7s %s\n", "set", "N",
              "pairs", "public", "auto", "cuBQL", "x", "c.in", "c.build", "c.count", "c.scan", "c.fill", "c.out", "p.in",
              "p.plan", "p.map", "p.check", "p.out", "p.pipe", "verified");
  bool all_same = true;
  for (const set_spec& sp : specs) {
    if (sp.n > max_n) continue;
    const zi::box_set s = *zi::generate_named(sp.kind, sp.n, seed);
    const zg::pinned_boxes pin(s);
    const peer_input in(s);
    auto pub = zg::make_finder(zg::finder_backend::auto_select, &pool, &why);
    zp::cubql_join peer(leaf, builder);
    std::span<const zi::id_pair> view;
    // Warm-ups, then the pair sets compared before anything is timed.
    if (zg::find_view(*pub, s, view)) {
      std::fprintf(stderr, "bench-peers: invalid input\n");
      return 2;
    }
    std::uint64_t peer_count = peer.run(in.boxes, in.category, in.mask, in.n);
    const pair_digest dp = digest(view, pool);
    const pair_digest dc = digest(peer_pairs(peer, peer_count), pool);
    const bool same = dp == dc;
    all_same = all_same && same;
    const int r = reps > 0 ? reps : (sp.n >= 10000000 ? 5 : 21);
    std::vector<double> tp, tc;
    std::vector<zp::cubql_timing> phases;
    for (int k = 0; k < r; ++k) {
      for (int j = 0; j < 2; ++j) {
        const bool public_now = (j == 0) == (k % 2 == 0);
        if (public_now) {
          const auto t0 = clock_type::now();
          (void)zg::find_view(*pub, s, view);
          tp.push_back(ms_since(t0));
        } else {
          const auto t0 = clock_type::now();
          peer_count = peer.run(in.boxes, in.category, in.mask, in.n);
          tc.push_back(ms_since(t0));
          phases.push_back(peer.timing());
        }
      }
    }
    const bool same_after = digest(view, pool) == dp && digest(peer_pairs(peer, peer_count), pool) == dc;
    all_same = all_same && same_after;
    const double pm = median(tp), cm = median(tc);
    // The peer's phases of its median call.
    std::size_t mid = 0;
    for (std::size_t k = 0; k < tc.size(); ++k) {
      if (std::abs(tc[k] - cm) < std::abs(tc[mid] - cm)) mid = k;
    }
    const zp::cubql_timing& ct = phases[mid];
    const auto choice = zg::last_auto_choice(*pub);
    const std::string choice_name = choice ? std::string(zg::backend_name(*choice)) : "?";
    // Where the documented call's time goes, and what this session's two upload/map changes give:
    // PBIG (the path auto takes on a pinned set) with its defaults and with each change off, on
    // the same pinned set, interleaved rounds after a warm-up each; the defaults' phase report of
    // its median call.
    // (Sets of more than 10^8 pairs time the defaults only: each variant holds its own pinned
    // result buffer of 8 bytes a pair.)
    std::vector<variant_result> var;
    for (const variant& v : variants) {
      if (dp.count > 100000000 && !var.empty()) break;
      zg::pbig_options o = v.options;
      o.decode_pool = &pool;
      var.push_back({v.name, zg::make_pbig_finder(o, &why), {}, {}, 0});
    }
    const int vr = sp.n >= 10000000 ? 5 : 11;
    for (auto& v : var) {
      std::span<const zi::id_pair> v2;
      if (!v.finder || zg::find_pairs_view(*v.finder, s, v2)) {
        std::fprintf(stderr, "bench-peers: PBIG finder failed: %s\n", why.c_str());
        return 2;
      }
      if (digest(v2, pool) != dp) all_same = false;
    }
    for (int k = 0; k < vr; ++k) {
      for (std::size_t j = 0; j < var.size(); ++j) {
        variant_result& v = var[(j + static_cast<std::size_t>(k)) % var.size()];
        std::span<const zi::id_pair> v2;
        const auto t0 = clock_type::now();
        (void)zg::find_pairs_view(*v.finder, s, v2);
        v.ms.push_back(ms_since(t0));
        v.reports.push_back(*zg::last_pbig_report(*v.finder));
      }
    }
    for (auto& v : var) v.median = median(v.ms);
    const zg::pbig_report rep = [&] {
      const variant_result& d = var[0];
      std::size_t at = 0;
      for (std::size_t k = 0; k < d.ms.size(); ++k) {
        if (std::abs(d.ms[k] - d.median) < std::abs(d.ms[at] - d.median)) at = k;
      }
      return d.reports[at];
    }();
    const double pbig_ms = var[0].median;
    auto variant_ms = [&](std::size_t k) { return k < var.size() ? var[k].median : -1.0; };
    const double bytes_out = static_cast<double>(dp.count) * 8;
    const double floor_ms = (32.0 * static_cast<double>(sp.n) + bytes_out) / 55e9 * 1e3;  // 55 GB/s each way, serial
    const std::string verified = same && same_after ? "yes" : "MISMATCH";
    std::printf("%-9s %9zu %13llu %10.3f %-5s %10.3f %6.2fx | %7.3f %7.3f %7.3f %7.3f %7.3f %7.3f | %7.3f %7.3f %7.3f "
                "%7.3f %7.3f %7.3f %s%s\n",
                sp.kind.c_str(), sp.n, static_cast<unsigned long long>(dp.count), pm, choice_name.c_str(), cm, cm / pm,
                ct.in_ms, ct.build_ms, ct.count_ms, ct.scan_ms, ct.fill_ms, ct.out_ms, rep.data_in_ms, rep.plan_ms,
                rep.map_ms, rep.check_ms, rep.data_out_ms, rep.pipeline_ms, verified.c_str(),
                pin.active() ? "" : " (input NOT pinned)");
    std::printf("   PBIG defaults %.3f ms: in %.3f, plan %.3f, map %.3f (count %.3f, scatter %.3f, sort %.3f, gather "
                "%.3f), sched %.3f, check+out wall %.3f (check %.3f, out %.3f, %u batches); %.1f MB in, %.1f MB out\n",
                pbig_ms, rep.data_in_ms, rep.plan_ms, rep.map_ms, rep.map_count_ms, rep.map_scatter_ms, rep.map_sort_ms,
                rep.map_gather_ms, rep.sched_ms, rep.pipeline_ms, rep.check_ms, rep.data_out_ms, rep.batches,
                static_cast<double>(rep.bytes_in) / 1e6, static_cast<double>(rep.bytes_out) / 1e6);
    std::printf("   PBIG variants (medians of %d, interleaved%s):", vr, var.size() < 4 ? "; defaults only above 10^8 pairs" : "");
    for (const auto& v : var) std::printf(" %s %.3f ms;", v.name, v.median);
    std::printf(" classes filled %s, indirect checks %s\n", rep.classes_filled ? "yes" : "no",
                rep.indirect_check ? "yes" : "no");
    std::fflush(stdout);
    csv << sp.kind << ',' << sp.n << ',' << dp.count << ',' << pm << ',' << *std::min_element(tp.begin(), tp.end())
        << ',' << choice_name << ',' << cm << ',' << *std::min_element(tc.begin(), tc.end()) << ',' << cm / pm << ','
        << ct.in_ms << ',' << ct.build_ms << ',' << ct.count_ms << ',' << ct.scan_ms << ',' << ct.fill_ms << ','
        << ct.out_ms << ',' << pbig_ms << ',' << rep.data_in_ms << ',' << rep.plan_ms << ',' << rep.map_ms << ','
        << rep.map_count_ms << ',' << rep.map_scatter_ms << ',' << rep.map_sort_ms << ',' << rep.map_gather_ms << ','
        << rep.check_ms << ',' << rep.data_out_ms << ',' << rep.pipeline_ms << ',' << rep.batches << ',' << rep.bytes_in
        << ',' << rep.bytes_out << ',' << floor_ms << ',' << leaf << ',' << variant_ms(1) << ',' << variant_ms(2) << ','
        << variant_ms(3) << ',' << rep.classes_filled << ',' << rep.indirect_check << ',' << builder_name << ',' << verified << '\n';
    csv.flush();
  }
  std::printf("CSV: %s\n", csv_path.c_str());
  if (!all_same) {
    std::fprintf(stderr, "bench-peers: a pair set differs between the documented call and cuBQL\n");
    return 1;
  }
  return 0;
}
