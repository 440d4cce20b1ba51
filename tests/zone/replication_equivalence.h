// Replication on an engine (interest/replication_engine.h) against the CPU replicator, byte for
// byte: shared by test_zone (the engine's per-job code emulated on the CPU, every CI run) and
// test_zone_gpu (the GPU engine). Random worlds with movement, teleports, entities created and
// destroyed (observers too), stealth and team classes changing, observers that see nothing,
// clients' players switching stealth and team as zone_server applies it (the clients that may hold
// a switched entity resynced, or sent a class note when it takes them, on both sides by
// replicator::resync_viewers_of);
// clients joining, leaving and resynced mid-run, only some clients built each tick (the others'
// views carried over); budgets from below the header to huge, every distance tier, ticks across
// 2^32; the engine switched off and on mid-run.
#pragma once

#include <doctest/doctest.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <deque>
#include <functional>
#include <memory>
#include <random>
#include <utility>
#include <vector>

#include "gpu/replication/replication_shared.h"
#include "zone/zone.h"

namespace zone::test {

struct replication_equivalence_case {
  std::size_t entities = 400;
  std::size_t clients = 40;
  int ticks = 40;
  float side = 300;           ///< world side (m)
  float aoi_lo = 15, aoi_hi = 110;
  std::vector<std::size_t> budgets{150, 260, 420, 900, 3000, 8192, std::size_t{1} << 20};
  std::vector<std::uint64_t> first_ticks{1, (std::uint64_t{1} << 32) - 20};
  bool switch_engine = true;  ///< turn the engine off and on again mid-run
  bool churn = true;
  bool player_switches = true;  ///< clients' players switch stealth and team (each switch resyncs the clients near)
  /// When set, the interest tracker runs on this engine (the GPU's) with no row copied back, so a
  /// replication engine that can reads the visible sets in place (the CPU side fetches them).
  std::function<std::unique_ptr<interest::visibility_engine>(interest::thread_pool*)> make_visibility;
};

/// What the runs covered (summed over every frame compared).
struct replication_coverage {
  std::uint64_t frames = 0, differing = 0, stats_differing = 0, hash_differing = 0;
  std::uint64_t view_differing = 0;  ///< the host's copy of a view (follow_view on the engine) unlike the CPU's
  /// Engine frames the FlatBuffers verifier or the decoder rejected, or that decoded to another
  /// message than the CPU replicator's frame; one byte flipped per tick in a copy of a frame, and
  /// how many of those the comparison caught (all of them, or the check could not fail).
  std::uint64_t undecodable = 0, broken_probes = 0, broken_caught = 0;
  std::uint64_t enters = 0, leaves = 0, updates = 0;
  std::uint64_t deferred_enters = 0, deferred_leaves = 0, deferred_updates = 0;
  std::uint64_t ranked = 0;  ///< frames where the budget cut the due updates and some were sent
  /// Of them, those whose due updates were more than the engine ranks by counting (it sorts them:
  /// replication_shared.h, rank_by_sort_above); frames whose enters it sorted.
  std::uint64_t ranked_sorted = 0, entered_sorted = 0;
  std::uint64_t resets = 0, empty = 0, near = 0, mid = 0, far = 0;
  std::uint64_t resident_runs = 0;  ///< engine runs that read the visible sets in place
  std::uint64_t switches = 0;          ///< players' visibility switches (visibility_for) that changed their class
  std::uint64_t switch_resyncs = 0;    ///< clients resynced for them (resync_viewers_of; equal on both sides)
  std::uint64_t switch_notes = 0;      ///< class notes for them instead (odd clients take notes; equal on both sides)
  /// Engine-side frames written into the caller's room (build_many's frame_room), and those the
  /// sink did not get there.
  std::uint64_t room_frames = 0, room_misplaced = 0;
  /// Engine-side frames handed over without a copy (build_many's frame_share), and those of them
  /// that changed while held (two ticks after their own: the engine must not reuse their buffer).
  std::uint64_t shared_frames = 0, shared_changed = 0;
  std::uint64_t entities_ahead = 0;  ///< engine runs on entities staged ahead (replicator::prestage)
  /// Between ticks (every other one) the engine's buffers grown ahead (replicator::grow_ahead,
  /// as zone_server between ticks): the milliseconds it spent growing them (> 0: it grew some).
  double grown_ahead_ms = 0;
};

/// Runs `c` with engines from `make_engine` (one per budget and first tick) and compares every
/// frame with the CPU replicator's.
inline replication_coverage check_replication_equivalence(
    std::uint64_t seed, const replication_equivalence_case& c,
    const std::function<std::unique_ptr<interest::replication_engine>()>& make_engine) {
  namespace cb = interest::category_bits;
  replication_coverage cov;
  interest::thread_pool pool(3);
  for (const std::uint64_t first_tick : c.first_ticks) {
    for (const std::size_t budget : c.budgets) {
      CAPTURE(first_tick);
      CAPTURE(budget);
      std::mt19937_64 rng(seed ^ (budget * 0x9e3779b97f4a7c15ull) ^ first_tick);
      std::mt19937_64 probe_rng(~seed ^ budget);  // the broken-byte probe's own (the world's stream stays as it was)
      const auto uni = [&](float lo, float hi) { return std::uniform_real_distribution<float>(lo, hi)(rng); };
      const std::uint32_t classes[] = {cb::normal, cb::normal, cb::normal, cb::stealth, cb::team_red, cb::team_blue};
      const auto random_desc = [&] {
        entity_desc d;
        d.position = {uni(0, c.side), uni(0, c.side), uni(0, 10)};
        d.velocity = {uni(-3, 3), uni(-3, 3), uni(-0.5f, 0.5f)};
        const float aoi = uni(c.aoi_lo, c.aoi_hi);
        d.aoi_half_extent = {aoi, aoi, 40};
        d.presence_half_extent = {uni(0.3f, 2), uni(0.3f, 2), 1};
        d.visibility_class = classes[rng() % 6];
        const std::uint32_t r = static_cast<std::uint32_t>(rng() % 16);
        d.sees = r == 0 ? 0u : r < 3 ? cb::normal : cb::normal | cb::team_red | cb::team_blue | (r % 3 == 0 ? cb::stealth : 0u);
        d.kind = static_cast<entity_kind>(rng() % 3);
        return d;
      };
      entity_store store;
      for (std::size_t k = 0; k < c.entities; ++k) (void)store.create(random_desc());
      interest::grid_finder finder(&pool);
      interest_tracker tracker(finder, &pool, {3.0f, 0, 64});
      std::unique_ptr<interest::visibility_engine> vis_engine;
      const std::vector<std::uint8_t> no_rows;  // demand: no row copied back
      if (c.make_visibility) {
        vis_engine = c.make_visibility(&pool);
        REQUIRE(vis_engine != nullptr);
        tracker.set_engine(vis_engine.get());
        tracker.set_view_demand(&no_rows);
      }
      replication_options opt;
      opt.world = {{0, 0, 0}, {c.side, c.side, 20}};
      opt.byte_budget = budget;
      opt.near_distance = uni(10, 30);
      opt.mid_distance = opt.near_distance + uni(10, 50);
      opt.mid_period = 1 + static_cast<std::uint32_t>(rng() % 4);
      opt.far_period = opt.mid_period + static_cast<std::uint32_t>(rng() % 6);
      opt.digest_period = 1 + static_cast<std::uint32_t>(rng() % 3);
      opt.send_digest = rng() % 5 != 0;
      opt.clients_per_task = 1 + static_cast<std::uint32_t>(rng() % 8);
      opt.wrap_threads = static_cast<std::uint32_t>(rng() % 4);  // 0: every worker
      CAPTURE(opt.near_distance);
      CAPTURE(opt.mid_distance);
      replicator cpu(opt), dev(opt);
      auto engine = make_engine();
      REQUIRE(engine != nullptr);
      dev.set_engine(engine.get());
      struct client_rec {
        client_id id;
        bool active;
      };
      std::vector<client_rec> clients;
      const auto join = [&] {
        if (store.size() == 0) return;
        const entity_id o = store.ids()[rng() % store.size()];
        const client_id a = cpu.add_client(o), b = dev.add_client(o);
        REQUIRE(a == b);
        // Odd clients take class notes (their frames are never reset for a switch), even ones not.
        cpu.set_class_notes(a, a % 2 == 1);
        dev.set_class_notes(b, b % 2 == 1);
        auto it = std::find_if(clients.begin(), clients.end(), [&](const client_rec& r) { return r.id == a; });
        if (it == clients.end()) {
          clients.push_back({a, true});
        } else {
          it->active = true;
        }
      };
      for (std::size_t k = 0; k < c.clients; ++k) join();
      std::vector<replication_request> requests;
      std::vector<std::vector<std::uint8_t>> want, got;
      std::vector<replication_stats> want_st, got_st;
      std::vector<const std::uint8_t*> rooms;  // by request: the room given for its frame
      // The frames of the last sharing tick, with their bytes as handed over.
      std::deque<std::vector<std::pair<net::shared_frame, std::vector<std::uint8_t>>>> held;
      struct switch_rec {
        entity_id entity;
        std::uint32_t old_class, old_sees;
      };
      std::vector<switch_rec> switched;  // since the last step
      for (std::uint64_t tick = first_tick; tick < first_tick + static_cast<std::uint64_t>(c.ticks); ++tick) {
        CAPTURE(tick);
        // Every other tick the engine's buffers are grown ahead first (freed and allocated anew,
        // as zone_server does between ticks): the views, hashes and frames still held must stay.
        if (tick % 2 == 0)
          cov.grown_ahead_ms += dev.grow_ahead(std::chrono::steady_clock::now() + std::chrono::seconds(1));
        REQUIRE_FALSE(tracker.update(store.columns()).has_value());
        // After the step, as zone_server does: the clients that may hold a switched entity with
        // its old class start over, on both sides alike.
        if (!switched.empty()) {
          std::vector<class_change> changes;
          for (const auto& sw : switched) changes.push_back({sw.entity, sw.old_class, sw.old_sees});
          std::vector<replicator::class_note_target> notes_a, notes_b;
          const std::size_t a = cpu.resync_viewers_of(store, tracker, tick, changes, nullptr, &notes_a);
          const std::size_t b = dev.resync_viewers_of(store, tracker, tick, changes, nullptr, &notes_b);
          REQUIRE(a == b);
          REQUIRE(notes_a == notes_b);
          cov.switch_resyncs += a;
          cov.switch_notes += notes_a.size();
        }
        switched.clear();
        // Who is built this tick: usually everyone, sometimes a random part (the rest carry over).
        requests.clear();
        const bool some = rng() % 3 == 0;
        for (const auto& cl : clients) {
          if (!cl.active || (some && rng() % 2 == 0)) continue;
          requests.push_back({cl.id, static_cast<std::uint32_t>(rng())});
        }
        std::shuffle(requests.begin(), requests.end(), rng);
        want.assign(requests.size(), {});
        got.assign(requests.size(), {});
        want_st.assign(requests.size(), {});
        got_st.assign(requests.size(), {});
        cpu.build_many(requests, store, tracker, tick, tick * 3, &pool,
                       [&](std::size_t k, std::span<const std::uint8_t> f, const replication_stats& st) {
                         want[k].assign(f.begin(), f.end());
                         want_st[k] = st;
                       });
        // One tick in three the engine side writes each frame into room the caller gives
        // (build_many's frame_room, as zone_server's arena): each thread's own buffer, filled
        // with garbage first, so a byte the writer left unwritten would show. One in three it
        // takes the frames the engine keeps, without a copy (frame_share, as zone_server), and
        // holds them two more ticks.
        const bool in_room = tick % 3 == 1, sharing = tick % 3 == 2;
        std::vector<net::shared_frame> shared_now(sharing ? requests.size() : 0);
        std::atomic<std::uint64_t> room_frames{0}, room_misplaced{0};  // counted on the pool's threads
        rooms.assign(requests.size(), nullptr);
        // Replication's entities staged ahead (replicator::prestage) one tick in four; one in
        // four staged for another tick, which build_many must not use.
        if (tick % 4 == 1) dev.prestage(store, tick, &pool);
        if (tick % 4 == 3) dev.prestage(store, tick + 1, &pool);
        dev.build_many(
            requests, store, tracker, tick, tick * 3, &pool,
            [&](std::size_t k, std::span<const std::uint8_t> f, const replication_stats& st) {
              if (in_room && f.data() != rooms[k]) room_misplaced.fetch_add(1, std::memory_order_relaxed);
              got[k].assign(f.begin(), f.end());
              got_st[k] = st;
            },
            {},
            in_room ? replicator::frame_room([&](std::size_t k, std::size_t bytes) {
              thread_local std::vector<std::uint64_t> room;
              room.assign(bytes / 8 + 2, 0xa5a5a5a5a5a5a5a5ull);
              auto* const at = reinterpret_cast<std::uint8_t*>(room.data());
              rooms[k] = at;
              room_frames.fetch_add(1, std::memory_order_relaxed);
              return std::span<std::uint8_t>(at, bytes);
            })
                    : replicator::frame_room{},
            sharing ? replicator::frame_share([&](std::size_t k, net::shared_frame f, const replication_stats& st) {
              got[k].assign(f.bytes().begin(), f.bytes().end());
              got_st[k] = st;
              shared_now[k] = std::move(f);
            })
                    : replicator::frame_share{});
        // The frames held from earlier ticks are as they were handed over.
        for (const auto& tick_frames : held) {
          for (const auto& [frame, bytes] : tick_frames) {
            if (!std::ranges::equal(frame.bytes(), bytes)) ++cov.shared_changed;
          }
        }
        if (sharing) {
          auto& now_held = held.emplace_back();
          for (std::size_t k = 0; k < shared_now.size(); ++k) {
            if (!shared_now[k]) continue;
            ++cov.shared_frames;
            now_held.emplace_back(shared_now[k], got[k]);
          }
          while (held.size() > 1) held.pop_front();
        }
        if (dev.on_engine() && !requests.empty()) {
          if (dev.phase_times().entities_ahead) ++cov.entities_ahead;
          if (tick % 4 != 1) CHECK_FALSE(dev.phase_times().entities_ahead);
        }
        cov.room_frames += room_frames.load();
        cov.room_misplaced += room_misplaced.load();
        REQUIRE(dev.engine_error().empty());
        if (c.make_visibility) REQUIRE(tracker.last_update_on_engine());
        if (dev.on_engine() && !requests.empty() && engine->timing().resident) ++cov.resident_runs;
        if (c.switch_engine) REQUIRE(dev.on_engine() == (tick - first_tick < 4 || tick - first_tick >= 7));
        for (std::size_t k = 0; k < requests.size(); ++k) {
          const client_id id = requests[k].client;
          ++cov.frames;
          cov.differing += want[k] != got[k] ? 1 : 0;
          {
            net::decoder_options big;
            big.max_frame_bytes = std::size_t{4} << 20;
            const auto a_msg = net::decode_frame(got[k], big), b_msg = net::decode_frame(want[k], big);
            cov.undecodable += (!a_msg.value || !b_msg.value || *a_msg.value != *b_msg.value) ? 1 : 0;
          }
          if (k == 0) {  // a deliberately broken byte must fail the comparison
            auto broken = got[k];
            broken[probe_rng() % broken.size()] ^= static_cast<std::uint8_t>(1u << (probe_rng() % 8));
            ++cov.broken_probes;
            cov.broken_caught += broken != want[k] ? 1 : 0;
          }
          const auto& a = want_st[k];
          const auto& b = got_st[k];
          cov.stats_differing += (a.enters != b.enters || a.leaves != b.leaves || a.updates != b.updates ||
                                  a.deferred_enters != b.deferred_enters || a.deferred_leaves != b.deferred_leaves ||
                                  a.deferred_updates != b.deferred_updates || a.bytes != b.bytes || a.reset != b.reset)
                                     ? 1
                                     : 0;
          cov.hash_differing += (cpu.view_hash(id) != dev.view_hash(id) || cpu.view_size(id) != dev.view_size(id)) ? 1 : 0;
          // The host's copy of the engine's view, read every 4th tick (a read settles the frames'
          // changes held since: between reads they accumulate, cancel and settle on their own).
          if ((tick + id) % 4 == 0) cov.view_differing += !std::ranges::equal(cpu.view(id), dev.view(id)) ? 1 : 0;
          if (want[k] != got[k] && cov.differing <= 3) {
            MESSAGE("frame differs: client " << id << ", cpu " << want[k].size() << " bytes (" << a.enters << " enters, "
                                             << a.leaves << " leaves, " << a.updates << " updates), engine "
                                             << got[k].size() << " bytes (" << b.enters << " enters, " << b.leaves
                                             << " leaves, " << b.updates << " updates)");
          }
          cov.enters += a.enters;
          cov.leaves += a.leaves;
          cov.updates += a.updates;
          cov.deferred_enters += a.deferred_enters;
          cov.deferred_leaves += a.deferred_leaves;
          cov.deferred_updates += a.deferred_updates;
          cov.ranked += a.deferred_updates > 0 && a.updates > 0 ? 1 : 0;
          // (Frames the engine built: the CPU builds the ticks it is off for.)
          cov.ranked_sorted += dev.on_engine() && a.deferred_updates > 0 && a.updates > 0 &&
                                       a.updates + a.deferred_updates > gpu::detail::rep::rank_by_sort_above
                                   ? 1
                                   : 0;
          cov.entered_sorted +=
              dev.on_engine() && a.enters > 0 && a.enters + a.deferred_enters > gpu::detail::rep::rank_by_sort_above
                  ? 1
                  : 0;
          cov.resets += a.reset ? 1 : 0;
          cov.empty += cpu.view_size(id) == 0 ? 1 : 0;
          // The tiers the client's view spans (from the CPU side's record of it).
          const std::size_t self = store.index_of(cpu.observer(id));
          if (self != entity_store::npos) {
            for (const entity_id e : cpu.view(id)) {
              const std::size_t k2 = store.index_of(e);
              if (k2 == entity_store::npos) continue;
              const vec3 p = store.positions()[k2], q = store.positions()[self];
              const float d = std::sqrt((p.x - q.x) * (p.x - q.x) + (p.y - q.y) * (p.y - q.y) + (p.z - q.z) * (p.z - q.z));
              (d < opt.near_distance ? cov.near : d < opt.mid_distance ? cov.mid : cov.far) += 1;
            }
          }
        }
        // Early in the run: the engine off for three ticks, then on again (every client starts
        // over on the new side: resync them on the CPU side too).
        if (c.switch_engine && (tick - first_tick == 3 || tick - first_tick == 6)) {
          dev.set_engine(tick - first_tick == 3 ? nullptr : engine.get());
          for (const auto& cl : clients) {
            if (cl.active) cpu.resync(cl.id);
          }
        }
        // Clients join, leave and lose frames.
        if (rng() % 4 == 0) join();
        if (rng() % 5 == 0 && !clients.empty()) {
          auto& cl = clients[rng() % clients.size()];
          if (cl.active) {
            cpu.remove_client(cl.id);
            dev.remove_client(cl.id);
            cl.active = false;
          }
        }
        if (rng() % 3 == 0 && !clients.empty()) {
          const auto& cl = clients[rng() % clients.size()];
          if (cl.active) {
            cpu.resync(cl.id);
            dev.resync(cl.id);
          }
        }
        // Near the end every observer goes blind at once: whole views leave, more leaves than a
        // tight budget holds (the views grew since the engine came back on).
        if (static_cast<int>(tick - first_tick) == c.ticks - 6) {
          for (const auto& cl : clients) {
            const std::size_t b = store.index_of(cpu.observer(cl.id));
            if (b != entity_store::npos) (void)store.set_visibility(store.ids()[b], store.visibility_classes()[b], 0);
          }
        }
        // The world moves: integrate, teleports, classes change, entities come and go.
        auto pos = store.positions();
        auto vel = store.velocities();
        for (std::size_t i = 0; i < store.size(); ++i) {
          pos[i].x = std::clamp(pos[i].x + vel[i].x, 0.f, c.side);
          pos[i].y = std::clamp(pos[i].y + vel[i].y, 0.f, c.side);
          if (pos[i].x <= 0 || pos[i].x >= c.side) vel[i].x = -vel[i].x;
          if (pos[i].y <= 0 || pos[i].y >= c.side) vel[i].y = -vel[i].y;
        }
        for (int t = 0; t < 3 && store.size() > 0; ++t) {
          const std::size_t k = rng() % store.size();
          pos[k] = {uni(0, c.side), uni(0, c.side), pos[k].z};
        }
        // A client's observer teleports, and one goes blind (sees nothing: its whole view leaves
        // at once, more leaves than a tight budget holds) or sees again.
        if (!clients.empty()) {
          const std::size_t k = store.index_of(cpu.observer(clients[rng() % clients.size()].id));
          if (k != entity_store::npos) pos[k] = {uni(0, c.side), uni(0, c.side), pos[k].z};
          const entity_id o = cpu.observer(clients[rng() % clients.size()].id);
          const std::size_t b = store.index_of(o);
          if (b != entity_store::npos) {
            const bool blind = store.sees()[b] != 0;
            (void)store.set_visibility(o, store.visibility_classes()[b],
                                       blind ? 0u : cb::normal | cb::team_red | cb::team_blue | cb::stealth);
          }
        }
        if (store.size() > 0) {
          const entity_id e = store.ids()[rng() % store.size()];
          const auto d = random_desc();
          (void)store.set_visibility(e, d.visibility_class, d.sees);
        }
        // Players switch as clients ask (set_visibility): stealth and team by visibility_for.
        for (int t = 0; t < 3 && c.player_switches && !clients.empty(); ++t) {
          const entity_id o = cpu.observer(clients[rng() % clients.size()].id);
          const std::size_t k = store.index_of(o);
          if (k == entity_store::npos) continue;
          const std::uint32_t old = store.visibility_classes()[k], old_sees = store.sees()[k];
          const auto v = visibility_for(rng() % 2 == 0, static_cast<std::uint8_t>(rng() % 3));
          REQUIRE(store.set_visibility(o, v.visibility_class, v.sees));
          if (v.visibility_class != old || v.sees != old_sees) {
            switched.push_back({o, old, old_sees});
            ++cov.switches;
          }
        }
        if (c.churn) {
          for (int t = 0; t < 3 && store.size() > 1; ++t) store.destroy(store.ids()[rng() % store.size()]);
          for (int t = 0; t < 3; ++t) (void)store.create(random_desc());
        }
      }
    }
  }
  return cov;
}

/// A long run at tight budgets without resets: views grow past what a frame's leaves can hold
/// (a leave costs 4 bytes, an enter 96: only views built over more than 24 ticks can leave more
/// than a frame holds), then every observer goes blind.
inline replication_equivalence_case deferred_leaves_case() {
  replication_equivalence_case c;
  c.ticks = 70;
  c.budgets = {330, 420};
  c.first_ticks = {5};
  c.switch_engine = false;
  c.player_switches = false;  // each resyncs views, which then never grow long enough
  c.aoi_lo = 80;
  c.aoi_hi = 150;
  return c;
}

/// deferred_leaves_case on fresh worlds until one defers a leave (about 1 world in 40 defers none),
/// at most 4; every world's frames must be equal. Returns the last world's coverage.
template <class Run>
replication_coverage deferred_leaves_runs(Run run_one_world) {
  replication_coverage cov;
  for (int world = 0; world < 4 && cov.deferred_leaves == 0; ++world) cov = run_one_world();
  return cov;
}

/// A crowd: 400 entities in 70 m, so that every client sees most of them, and budgets that cut its
/// hundreds of due updates (the engine ranks them by sorting: ranked_sorted) or fit them all.
inline replication_equivalence_case crowd_case() {
  replication_equivalence_case c;
  c.side = 70;
  c.aoi_lo = 40;
  c.aoi_hi = 110;
  c.budgets = {3000, 8192};
  return c;
}

/// The checks every run must pass, and that the run covered what it claims (deferred leaves only
/// where `leaves_deferred`: see deferred_leaves_case).
inline void require_equivalent(const replication_coverage& cov, bool tiny_budgets = true, bool leaves_deferred = false,
                               bool switches = true) {
  MESSAGE("frames " << cov.frames << ": enters " << cov.enters << " leaves " << cov.leaves << " updates " << cov.updates
                    << "; deferred enters " << cov.deferred_enters << " leaves " << cov.deferred_leaves << " updates "
                    << cov.deferred_updates << "; ranked " << cov.ranked << " (sorted " << cov.ranked_sorted
                    << "), enters sorted " << cov.entered_sorted << ", resets " << cov.resets << ", empty " << cov.empty
                    << "; view entries near/mid/far " << cov.near << "/" << cov.mid << "/" << cov.far
                    << "; visibility switches " << cov.switches << " (clients resynced " << cov.switch_resyncs
                    << ", notes " << cov.switch_notes << ")");
  CHECK(cov.differing == 0);
  CHECK(cov.room_frames > 0);
  CHECK(cov.room_misplaced == 0);
  CHECK(cov.shared_frames > 0);
  CHECK(cov.shared_changed == 0);
  CHECK(cov.entities_ahead > 0);
  CHECK(cov.stats_differing == 0);
  CHECK(cov.hash_differing == 0);
  CHECK(cov.view_differing == 0);
  CHECK(cov.undecodable == 0);
  CHECK(cov.broken_probes > 0);
  CHECK(cov.broken_caught == cov.broken_probes);
  CHECK(cov.frames > 0);
  CHECK(cov.enters > 0);
  CHECK(cov.leaves > 0);
  CHECK(cov.updates > 0);
  CHECK(cov.resets > 0);
  CHECK(cov.entered_sorted > 0);
  CHECK(cov.empty > 0);
  CHECK(cov.near > 0);
  CHECK(cov.mid > 0);
  CHECK(cov.far > 0);
  if (switches) {
    CHECK(cov.switches > 0);
    CHECK(cov.switch_resyncs > 0);
    CHECK(cov.switch_notes > 0);
  }
  if (tiny_budgets) {
    CHECK(cov.deferred_enters > 0);
    if (leaves_deferred) CHECK(cov.deferred_leaves > 0);
    CHECK(cov.deferred_updates > 0);
    CHECK(cov.ranked > 0);
  }
}

}  // namespace zone::test
