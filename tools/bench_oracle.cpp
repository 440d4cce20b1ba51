// bench-oracle: the oracle (bots/oracle.h) at a zone's scale, without sockets or a server: a
// synthetic world laid out as zone-server populates one (towns, AOI tiers, a boss, players
// spawning near towns and walking), its truth frames written by the server's encoder
// (net/truth.h) and fed to the oracle tick after tick; every sampled player's view (its true
// visible set, positions exact) is then checked against them. Prints, per tick, what feeding one
// truth frame costs (wall and CPU, by phase) and what checking one frame costs. docs/bots.md,
// "The oracle" ("What it costs").
//
//   bench-oracle --npcs 80000 --players 20000 --ticks 20 --threads 1
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include "bots/oracle.h"
#include "cli.h"
#include "interest/interest.h"
#include "interest/measure.h"
#include "net/client_view.h"
#include "net/truth.h"

namespace {

using clock_type = std::chrono::steady_clock;
using zone::ms_since;

/// The world: columns as the encoder reads them. NPCs first (ids 1..), players after.
struct world {
  std::vector<std::uint32_t> ids, classes, sees;
  std::vector<float> pos, aoi, presence, vel;  // 3 per entity
  std::vector<std::uint8_t> kinds;
  std::size_t size() const { return ids.size(); }
  void add(std::uint32_t id, float x, float y, float z, float a, float az, float h, float hz, std::uint32_t cls,
           std::uint32_t mask, zone::net::entity_kind kind) {
    ids.push_back(id);
    pos.insert(pos.end(), {x, y, z});
    aoi.insert(aoi.end(), {a, a, az});
    presence.insert(presence.end(), {h, h, hz});
    vel.insert(vel.end(), {0, 0, 0});
    classes.push_back(cls);
    sees.push_back(mask);
    kinds.push_back(static_cast<std::uint8_t>(kind));
  }
  zone::net::truth::layout_view layout() const { return {ids, aoi, presence, classes, sees, kinds}; }
};

}  // namespace

int main(int argc, char** argv) {
  namespace po = zone::tools::po;
  std::size_t npcs = 80000, players = 20000, ticks = 20, ramp_ticks = 0, check_every = 1, switches = 0;
  unsigned threads = 1, sample = 1;
  std::string scan = "default";
  float size = 4096, player_aoi = 60, boss_footprint = 40, cell = 0;
  std::uint64_t seed = 1;
  po::options_description cli("bench-oracle");
  cli.add_options()("npcs", po::value(&npcs)->default_value(npcs), "NPCs (one of them a boss)")  //
      ("players", po::value(&players)->default_value(players), "players (the observers)")        //
      ("ticks", po::value(&ticks)->default_value(ticks), "ticks after the players joined")       //
      ("ramp-ticks", po::value(&ramp_ticks)->default_value(ramp_ticks),
       "players join over this many ticks (a whole layout every tick), 0 = all at once")  //
      ("switches", po::value(&switches)->default_value(switches),
       "players switching stealth a tick once all joined (the truth sends changes to the layout)")  //
      ("threads", po::value(&threads)->default_value(threads), "the oracle's recomputing threads")  //
      ("sample", po::value(&sample)->default_value(sample),
       "--oracle-sample: 1 in K players recomputed and checked")  //
      ("scan", po::value(&scan)->default_value(scan),
       "grid, x or full (the oracle's recompute); default: the oracle's")  //
      ("check-every", po::value(&check_every)->default_value(check_every),
       "check the views every N-th tick (0: never)")                                                        //
      ("cell", po::value(&cell)->default_value(cell), "the grid's cell side (m), 0 = the oracle's choice")  //
      ("size", po::value(&size)->default_value(size), "world side (m)")                                     //
      ("player-aoi", po::value(&player_aoi)->default_value(player_aoi), "players' AOI half-extent (m)")     //
      ("boss-footprint", po::value(&boss_footprint)->default_value(boss_footprint),
       "the boss's presence half-extent (m)")  //
      ("seed", po::value(&seed)->default_value(seed), "the world's seed");
  std::ostringstream usage;
  usage << "bench-oracle [options]: the bot swarm's oracle at a zone's scale, in-process (docs/bots.md, \"What it "
           "costs\")\n"
        << cli;
  if (const auto rc = zone::tools::parse_command_line(argc, argv, "bench-oracle", usage.str(), cli, 2)) return *rc;

  namespace cb = zone::interest::category_bits;
  std::mt19937_64 rng(seed);
  const auto uni = [&](float lo, float hi) { return std::uniform_real_distribution<float>(lo, hi)(rng); };
  const zone::net::world_bounds bounds{{0, 0, 0}, {size, size, 256}};
  // zone_world::populate's layout: one town per 2,000 NPCs (sd 150 m), 45 % wanderers, 20 %
  // patrols, 30 % townsfolk, 5 % chasers; AOI tiers 10/30/60 (chasers 60, the boss 400); 90 %
  // normal, 5 % stealth, 2.5 % each team.
  const std::size_t towns = std::max<std::size_t>(1, npcs / 2000);
  std::vector<std::pair<float, float>> town;
  for (std::size_t t = 0; t < towns; ++t)
    town.emplace_back(uni(0.15f * size, 0.85f * size), uni(0.15f * size, 0.85f * size));
  world w;
  std::normal_distribution<float> spread(0, 150);
  for (std::size_t k = 0; k < npcs; ++k) {
    const float r = uni(0, 1);
    const bool boss = k == 0, in_town = !boss && r >= 0.65f && r < 0.95f;
    const auto& tc = town[rng() % towns];
    const float x = in_town ? std::clamp(tc.first + spread(rng), 0.0f, size) : uni(0, size);
    const float y = in_town ? std::clamp(tc.second + spread(rng), 0.0f, size) : uni(0, size);
    const float tiers[3] = {10, 30, 60};
    const float a = boss ? 400 : r >= 0.95f ? 60 : tiers[rng() % 3];
    const float v = uni(0, 1);
    const std::uint32_t cls = boss || v < 0.9f ? cb::normal
                              : v < 0.95f      ? cb::stealth
                              : v < 0.975f     ? cb::team_red
                                               : cb::team_blue;
    const float h = boss ? boss_footprint : 0.5f, hz = boss ? boss_footprint : 1.0f;
    w.add(static_cast<std::uint32_t>(k + 1), x, y, 0, a, std::min(a, 128.0f), h, hz, cls,
          cb::normal | cb::team_red | cb::team_blue | (cls == cb::stealth ? cb::stealth : 0u),
          boss ? zone::net::entity_kind::boss : zone::net::entity_kind::npc);
    const float heading = uni(0, 6.2831853f);
    w.vel[3 * k] = std::cos(heading) * 2 / 30, w.vel[3 * k + 1] = std::sin(heading) * 2 / 30;
  }

  zone::net::interest_rules rules;  // zone-server's defaults
  rules.hysteresis = 4;
  rules.update_near = 12, rules.update_mid = 30, rules.update_mid_period = 3, rules.update_far_period = 8;
  std::uint64_t mismatches_logged = 0;
  zone::bots::oracle o(
      bounds, rules, threads,
      [](void* ctx, std::string line) {
        if ((*static_cast<std::uint64_t*>(ctx))++ < 5) std::fprintf(stderr, "%s\n", line.c_str());
      },
      &mismatches_logged);
  if (scan == "full") o.scan = zone::bots::oracle::scan_mode::full;
  if (scan == "x") o.scan = zone::bots::oracle::scan_mode::x_window;
  if (scan == "grid") o.scan = zone::bots::oracle::scan_mode::grid;
  if (scan != "default" && scan != "full" && scan != "x" && scan != "grid") {
    std::fprintf(stderr, "bench-oracle: --scan must be grid, x or full, not '%s'\n", scan.c_str());
    return 2;
  }
  o.sample = sample;
  o.grid_cell = cell;

  zone::net::truth::encoder enc;
  std::vector<std::uint8_t> frame;
  std::uint64_t tick = 0;
  std::size_t joined = 0;
  struct tick_row {
    std::uint64_t tick;
    bool layout;  // whole or changes
    double feed_ms, feed_cpu_ms, check_us, compare_us;
    double index_ms, scan_ms, publish_ms;
    std::size_t checked = 0;
  };
  std::vector<tick_row> rows;
  std::vector<const char*> sents;
  std::uint64_t visible_sum = 0;
  const std::size_t total_ticks = 1 + std::max<std::size_t>(1, ramp_ticks) + ticks;
  for (; tick < total_ticks; ++tick) {
    // Joins: from tick 1, all at once or over the ramp.
    bool layout_changed = tick == 0;
    if (tick >= 1) {
      const std::size_t want = ramp_ticks == 0 ? players : std::min(players, players * tick / ramp_ticks);
      for (; joined < want; ++joined) {
        const auto& tc = town[joined % towns];
        const float r = 200 * std::sqrt(uni(0, 1)), a = uni(0, 6.2831853f);
        const float v = uni(0, 1);
        const std::uint32_t cls = v < 0.8f    ? cb::normal
                                  : v < 0.9f  ? cb::stealth
                                  : v < 0.95f ? cb::team_red
                                              : cb::team_blue;
        w.add(static_cast<std::uint32_t>(npcs + 1 + joined), std::clamp(tc.first + r * std::cos(a), 0.0f, size),
              std::clamp(tc.second + r * std::sin(a), 0.0f, size), 0, player_aoi, player_aoi, 0.5f, 1.0f, cls,
              cb::normal | (cls == cb::stealth ? cb::stealth : 0u) | (cls == cb::team_red ? cb::team_red : 0u) |
                  (cls == cb::team_blue ? cb::team_blue : 0u),
              zone::net::entity_kind::player);
        const float heading = uni(0, 6.2831853f);
        w.vel[w.vel.size() - 3] = std::cos(heading) * 6 / 30, w.vel[w.vel.size() - 2] = std::sin(heading) * 6 / 30;
        layout_changed = true;
      }
    }
    if (tick > 0) {
      for (std::size_t k = 0; k < w.size(); ++k) {
        for (int a = 0; a < 2; ++a) {
          float& p = w.pos[3 * k + a];
          p += w.vel[3 * k + a];
          if (p < 0 || p > size) w.vel[3 * k + a] = -w.vel[3 * k + a], p = std::clamp(p, 0.0f, size);
        }
      }
    }
    if (switches != 0 && joined == players && tick > 1 + std::max<std::size_t>(1, ramp_ticks)) {
      for (std::size_t k = 0; k < switches; ++k) {  // stealth toggled: the class and the mask
        const std::size_t at = npcs + rng() % players;
        w.classes[at] = w.classes[at] == cb::stealth ? cb::normal : cb::stealth;
        w.sees[at] ^= cb::stealth;
      }
      layout_changed = true;
    }
    const auto lv = w.layout();
    const auto sent = enc.encode(frame, tick, w.pos, layout_changed ? &lv : nullptr, false);
    const auto before = o.report();
    const auto t0 = clock_type::now();
    if (auto err = o.feed({frame.data() + 4, frame.size() - 4})) {
      std::fprintf(stderr, "bench-oracle: feed: %s\n", err->c_str());
      return 1;
    }
    const double feed_ms = ms_since(t0);
    const auto after = o.report();
    tick_row row{tick,
                 sent != zone::net::truth::encoder::sent::positions,
                 feed_ms,
                 (after.compute_cpu_ms + after.drain_cpu_ms) - (before.compute_cpu_ms + before.drain_cpu_ms),
                 0,
                 0,
                 after.index_ms - before.index_ms,
                 after.scan_ms - before.scan_ms,
                 after.publish_ms - before.publish_ms,
                 0};
    // Checks: every player's true view (as a server with nothing deferred would have sent it,
    // this tick), applied to a view outside the timing (hot in cache, as a bot's is right after
    // it applied its frame), then checked. An unsampled player's frame costs a hash of its id.
    if (check_every != 0 && tick >= 2 && tick % check_every == 0) {
      const double compare0 = after.check_ms;
      double check_ms = 0;
      zone::net::client_view view(bounds);
      for (std::size_t i = 0; i < joined; ++i) {
        const std::uint32_t id = static_cast<std::uint32_t>(npcs + 1 + i);
        const std::size_t self = npcs + i;
        const zone::net::vec3f own{w.pos[3 * self], w.pos[3 * self + 1], w.pos[3 * self + 2]};
        const auto vis = o.visible(id, tick);
        zone::net::tick_update_msg m;
        m.server_tick = tick;
        m.reset = true;
        for (const std::uint32_t t : vis.value_or(std::vector<std::uint32_t>{})) {
          const std::size_t k = t - 1;
          m.enters.push_back({t,
                              static_cast<zone::net::entity_kind>(w.kinds[k]),
                              w.classes[k],
                              {w.pos[3 * k], w.pos[3 * k + 1], w.pos[3 * k + 2]},
                              {},
                              {w.presence[3 * k], w.presence[3 * k + 1], w.presence[3 * k + 2]},
                              {}});
        }
        (void)view.apply(m);
        const auto c0 = clock_type::now();
        o.check(id, tick, view, {}, own, i);
        check_ms += ms_since(c0);
        if (vis) ++row.checked, visible_sum += vis->size();
      }
      row.check_us = row.checked == 0 ? 0 : check_ms * 1e3 / static_cast<double>(row.checked);
      row.compare_us = row.checked == 0 ? 0 : (o.report().check_ms - compare0) * 1e3 / static_cast<double>(row.checked);
    }
    rows.push_back(row);
    sents.push_back(sent == zone::net::truth::encoder::sent::layout    ? "layout"
                    : sent == zone::net::truth::encoder::sent::changes ? "changes"
                                                                       : "pos");
  }
  const auto r = o.report();
  std::printf("bench-oracle: %zu NPCs + %zu players (%zu towns) in %.0f m, %u threads, scan %s, sample 1 in %u\n", npcs,
              players, towns, size, threads, scan.c_str(), sample);
  std::printf("%6s %7s %9s %9s %9s %9s %9s %9s %11s %9s\n", "tick", "frame", "feed ms", "CPU ms", "index", "scan",
              "publish", "checked", "check us/fr", "compare");
  for (const auto& row : rows) {
    std::printf("%6llu %7s %9.2f %9.2f %9.2f %9.2f %9.2f %9zu %11.2f %9.2f\n",
                static_cast<unsigned long long>(row.tick), sents[row.tick], row.feed_ms, row.feed_cpu_ms, row.index_ms,
                row.scan_ms, row.publish_ms, row.checked, row.check_us, row.compare_us);
  }
  // Steady ticks: positions only, after the players joined, and once the oracle's ring of ticks
  // is reused (before, its first pass takes page faults), when the run is that long.
  const std::uint64_t warm = rows.size() > zone::bots::oracle::ring_ticks + 8 ? zone::bots::oracle::ring_ticks + 2 : 2;
  double feed = 0, cpu = 0, check = 0, compare = 0, ixs = 0, scans = 0, pubs = 0;
  std::size_t n = 0, nc = 0;
  for (const auto& row : rows) {
    if ((row.layout && switches == 0) || row.tick < warm) continue;
    ixs += row.index_ms, scans += row.scan_ms, pubs += row.publish_ms;
    feed += row.feed_ms, cpu += row.feed_cpu_ms, ++n;
    if (row.checked != 0) check += row.check_us, compare += row.compare_us, ++nc;
  }
  std::printf("steady (%zu ticks from tick %llu): index %.2f, scan %.2f, publish %.2f ms wall per tick\n", n,
              static_cast<unsigned long long>(warm), n ? ixs / n : 0.0, n ? scans / n : 0.0, n ? pubs / n : 0.0);
  std::printf(
      "steady (%zu ticks): feed %.2f ms wall, %.2f ms CPU per tick; check %.2f us per frame (compare %.2f us); "
      "observers up to %llu; frames checked %llu, unchecked %llu; mismatches %llu\n",
      n, n ? feed / n : 0.0, n ? cpu / n : 0.0, nc ? check / nc : 0.0, nc ? compare / nc : 0.0,
      static_cast<unsigned long long>(r.observers_max), static_cast<unsigned long long>(r.frames_checked),
      static_cast<unsigned long long>(r.frames_unchecked), static_cast<unsigned long long>(r.mismatches()));
  const double all = static_cast<double>(std::max<std::uint64_t>(1, r.truth_ticks));
  std::printf(
      "oracle's thread, wall per tick over all %llu ticks: decode %.2f, layout and index %.2f, scan %.2f, publish %.2f, "
      "waiting checks %.2f ms\n",
      static_cast<unsigned long long>(r.truth_ticks), r.decode_ms / all, r.index_ms / all, r.scan_ms / all,
      r.publish_ms / all, r.drain_ms / all);
  std::printf("visible entities per checked view: %.1f on average\n",
              r.frames_checked ? static_cast<double>(visible_sum) / static_cast<double>(r.frames_checked) : 0.0);
  return r.mismatches() == 0 ? 0 : 1;
}
