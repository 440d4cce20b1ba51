// The interest step's host reference engine (interest/host_visibility_engine.h) against the
// contract of interest/visibility_engine.h written out by brute force: random worlds of moving,
// teleporting, resizing, class-switching, removed and added entities (slots reused under new
// handles), with and without a hysteresis margin and a max_visible cap, on the grid finder (a
// pool, the finder's view) and the brute-force finder (one thread, a list of its own); an engine
// started mid-run from another's sets (load_previous, fetch_all_visible); refused input that
// changes nothing; apply_pairs' refusals. The presence-grid path (host_engine_options::presence_grid)
// against the same model: planned, fine (bodies over many cells, some kept out of the grid) and
// coarse (one cell) grids, coincident entities, observers beyond the presence bounds, its refusals
// and the sets it declines.
#include <doctest/doctest.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <map>
#include <random>
#include <span>
#include <vector>

#include "../common/seeds.h"
#include "interest/host_visibility_engine.h"
#include "interest/thread_pool.h"

using namespace zone::interest;
using zone::test::fresh_seed;
using ids = std::vector<std::uint32_t>;

namespace {

constexpr std::uint32_t slot_bits = 10;

/// A world of rows (the engine's input columns) and the contract's model of the step.
struct world {
  std::mt19937_64 rng;
  float h;
  std::uint32_t cap;
  std::vector<std::uint32_t> id, cls, sees;
  std::vector<float> pos, aoi, body;  // 3 per row
  std::vector<std::uint32_t> generation;  // by slot
  std::vector<std::uint32_t> free_slots;
  std::map<std::uint32_t, ids> prev;  // the model's previous sets, by handle

  world(std::uint64_t seed, float margin, std::uint32_t max_visible, std::size_t n) : rng(seed), h(margin), cap(max_visible) {
    for (std::size_t k = 0; k < n; ++k) add();
  }
  float uni(float lo, float hi) { return std::uniform_real_distribution<float>(lo, hi)(rng); }
  std::uint32_t random_class() {
    constexpr std::uint32_t classes[] = {category_bits::normal, category_bits::stealth, category_bits::team_red,
                                         category_bits::team_blue};
    return classes[rng() % 4];
  }
  std::uint32_t random_sees() { return static_cast<std::uint32_t>(rng() % 32) & ~category_bits::aoi; }
  void set_aoi(std::size_t r) {
    const float t = uni(0, 18);
    aoi[3 * r] = t, aoi[3 * r + 1] = uni(0, 18), aoi[3 * r + 2] = uni(0, 6);
  }
  void add() {
    std::uint32_t slot;
    if (!free_slots.empty() && rng() % 2 == 0) {
      slot = free_slots.back();
      free_slots.pop_back();
      ++generation[slot];
    } else {
      slot = static_cast<std::uint32_t>(generation.size());
      generation.push_back(1);
    }
    id.push_back((generation[slot] << slot_bits) | slot);
    cls.push_back(random_class());
    sees.push_back(random_sees());
    for (int d = 0; d < 3; ++d) pos.push_back(d == 2 ? uni(0, 10) : uni(0, 100));
    aoi.insert(aoi.end(), 3, 0.0f);
    set_aoi(id.size() - 1);
    const float b = rng() % 30 == 0 ? uni(5, 12) : uni(0, 1.5f);  // a few large footprints
    body.insert(body.end(), {b, b, 2 * b});
  }
  void remove(std::size_t r) {
    const std::size_t last = id.size() - 1;
    free_slots.push_back(id[r] & ((1u << slot_bits) - 1));
    id[r] = id[last], cls[r] = cls[last], sees[r] = sees[last];
    for (int d = 0; d < 3; ++d) pos[3 * r + d] = pos[3 * last + d], aoi[3 * r + d] = aoi[3 * last + d], body[3 * r + d] = body[3 * last + d];
    id.pop_back(), cls.pop_back(), sees.pop_back();
    pos.resize(3 * last), aoi.resize(3 * last), body.resize(3 * last);
  }
  void step() {
    for (std::size_t r = 0; r < id.size(); ++r) {
      switch (rng() % 30) {
        case 0: pos[3 * r] = uni(0, 100), pos[3 * r + 1] = uni(0, 100); break;  // teleport
        case 1: set_aoi(r); break;
        case 2: cls[r] = random_class(), sees[r] = random_sees(); break;
        default:  // a step that crosses AOI edges and the hysteresis band both ways
          pos[3 * r] += uni(-2.5f, 2.5f), pos[3 * r + 1] += uni(-2.5f, 2.5f);
      }
    }
    for (int k = static_cast<int>(rng() % 4); k > 0 && !id.empty(); --k) remove(rng() % id.size());
    for (int k = static_cast<int>(rng() % 4); k > 0; --k) add();
  }
  [[nodiscard]] visibility_input input() const {
    visibility_input in;
    in.n = id.size();
    in.ids = id.data();
    in.slot_bits = slot_bits;
    in.position = pos.data();
    in.aoi_half = aoi.data();
    in.body_half = body.data();
    in.visibility = cls.data();
    in.sees = sees.data();
    in.hysteresis = h;
    in.max_visible = cap;
    return in;
  }

  struct expected {
    std::vector<ids> visible, enters, leaves;
    std::uint64_t pairs = 0, candidates = 0, capped = 0;
  };
  /// The contract, literally: O(n^2) over (observer, target), the same float expressions.
  [[nodiscard]] expected model() const {
    const std::size_t n = id.size();
    const auto meets = [&](std::size_t i, float grow, std::size_t j) {
      for (int d = 0; d < 3; ++d) {
        const float a = grow == 0.0f ? aoi[3 * i + d] : aoi[3 * i + d] + grow;
        const float lo = pos[3 * i + d] - a, hi = pos[3 * i + d] + a;
        const float blo = pos[3 * j + d] - body[3 * j + d], bhi = pos[3 * j + d] + body[3 * j + d];
        if (!(lo <= bhi && blo <= hi)) return false;
      }
      return true;
    };
    expected e;
    e.visible.resize(n), e.enters.resize(n), e.leaves.resize(n);
    for (std::size_t i = 0; i < n; ++i) {
      const auto it = prev.find(id[i]);
      const ids none;
      const ids& old = it == prev.end() ? none : it->second;
      std::vector<std::pair<std::uint64_t, std::size_t>> kept;  // (distance key << 32 | handle, row)
      for (std::size_t j = 0; j < n; ++j) {
        if ((cls[j] & sees[i]) == 0 || !meets(i, h, j)) continue;
        ++e.pairs;
        if (j == i) continue;
        ++e.candidates;
        const bool was = std::binary_search(old.begin(), old.end(), id[j]);
        if (!was && !meets(i, 0.0f, j)) continue;
        const float dx = pos[3 * i] - pos[3 * j], dy = pos[3 * i + 1] - pos[3 * j + 1], dz = pos[3 * i + 2] - pos[3 * j + 2];
        kept.emplace_back((std::uint64_t{std::bit_cast<std::uint32_t>(dx * dx + dy * dy + dz * dz)} << 32) | id[j], j);
      }
      if (cap != 0 && kept.size() > cap) {
        std::sort(kept.begin(), kept.end());
        e.capped += kept.size() - cap;
        kept.resize(cap);
      }
      for (const auto& k : kept) e.visible[i].push_back(id[k.second]);
      std::sort(e.visible[i].begin(), e.visible[i].end());
      std::set_difference(e.visible[i].begin(), e.visible[i].end(), old.begin(), old.end(), std::back_inserter(e.enters[i]));
      std::set_difference(old.begin(), old.end(), e.visible[i].begin(), e.visible[i].end(), std::back_inserter(e.leaves[i]));
    }
    return e;
  }
  void commit(const expected& e) {
    prev.clear();
    for (std::size_t i = 0; i < id.size(); ++i) prev[id[i]] = e.visible[i];
  }
};

ids row(const std::uint32_t* data, const std::uint32_t* off, const std::uint32_t* len, std::size_t r) {
  const std::uint32_t b = off[r], n = len != nullptr ? len[r] : off[r + 1] - off[r];
  return ids(data + b, data + b + n);
}

/// Every row of an engine's output against the model; the events seen.
std::uint64_t check(const visibility_output& out, const world::expected& e) {
  std::uint64_t events = 0, total = 0;
  for (std::size_t r = 0; r < e.visible.size(); ++r) {
    CAPTURE(r);
    CHECK(row(out.visible, out.visible_off, out.visible_len, r) == e.visible[r]);
    CHECK(row(out.enters, out.enter_off, out.enter_len, r) == e.enters[r]);
    CHECK(row(out.leaves, out.leave_off, out.leave_len, r) == e.leaves[r]);
    events += e.enters[r].size() + e.leaves[r].size();
    total += e.visible[r].size();
  }
  CHECK(out.visible_complete);
  CHECK(out.visible_total == total);
  CHECK(out.pairs == e.pairs);
  CHECK(out.candidates == e.candidates);
  CHECK(out.capped == e.capped);
  return events;
}

}  // namespace

TEST_SUITE("interest.host_engine") {
  TEST_CASE("random worlds: every update is the contract's, on any finder, with margins and caps") {
    for (const auto& [h, cap] : {std::pair{3.0f, 0u}, std::pair{0.0f, 0u}, std::pair{2.0f, 4u}}) {
      const std::uint64_t seed = fresh_seed();
      CAPTURE(seed);
      CAPTURE(h);
      CAPTURE(cap);
      world w(seed, h, cap, 220);
      thread_pool pool(3);
      grid_finder grid(&pool);
      brute_force_finder brute;
      host_visibility_engine on_grid(grid, &pool, {.rows_per_task = 5, .finder_view = true});
      host_visibility_engine on_brute(brute, nullptr, {.rows_per_task = 256, .finder_view = false});
      host_visibility_engine late(grid, &pool);  // starts at tick 20 from on_grid's sets
      // The presence grid: planned on the pool; fine cells (the edge raised only by the cell
      // cap: bodies span several cells, the largest more than 64 and are kept apart); one cell.
      host_visibility_engine presence(brute, &pool, {.rows_per_task = 5, .finder_view = true, .presence_grid = true});
      host_visibility_engine fine(brute, nullptr,
                                  {.rows_per_task = 64, .finder_view = true, .presence_grid = true, .grid_cell_edge = 0.3f});
      host_visibility_engine coarse(brute, &pool,
                                    {.rows_per_task = 17, .finder_view = true, .presence_grid = true, .grid_cell_edge = 1e6f});
      visibility_output a, b, c, d;
      std::uint64_t fine_large = 0, fine_multi = 0;
      std::uint64_t events = 0, capped = 0;
      ids prev_rows;  // the rows of the last update
      for (int tick = 0; tick < 40; ++tick) {
        CAPTURE(tick);
        if (tick == 20) {
          // on_grid's sets of the last update (rows prev_rows), compact: the model's, and the
          // start of a fresh engine.
          const visibility_lists all = on_grid.fetch_all_visible();
          const std::size_t rows = prev_rows.size();
          for (std::size_t r = 0; r < rows; ++r) CHECK(row(all.data, all.off, nullptr, r) == w.prev.at(prev_rows[r]));
          late.load_previous(prev_rows, slot_bits, std::span(all.off, rows + 1), std::span(all.data, all.off[rows]));
        }
        // One footprint of the largest size every tick (the world's own large ones, 1 in 30, may
        // all be too small for the fine grid to keep apart: the check below would fail on them).
        if (!w.id.empty()) w.body[0] = w.body[1] = 12.0f, w.body[2] = 24.0f;
        const auto want = w.model();
        const visibility_input in = w.input();
        REQUIRE_FALSE(on_grid.update(in, a).has_value());
        REQUIRE_FALSE(on_brute.update(in, b).has_value());
        events += check(a, want);
        check(b, want);
        for (host_visibility_engine* e : {&presence, &fine, &coarse}) {
          REQUIRE_FALSE(e->update(in, d).has_value());
          check(d, want);
          CHECK(e->last_on_grid());
        }
        CHECK(coarse.grid_stats().cells == 1);
        fine_large += fine.grid_stats().large_boxes;
        // Entries beyond one per box in the grid: boxes listed in several cells.
        if (fine.grid_stats().cell_entries + fine.grid_stats().large_boxes > in.n) ++fine_multi;
        if (tick >= 20) {
          REQUIRE_FALSE(late.update(in, c).has_value());
          check(c, want);
        }
        capped += want.capped;
        w.commit(want);
        prev_rows = w.id;
        w.step();
      }
      CHECK(events > 100);  // the run was not vacuous
      if (cap != 0) CHECK(capped > 0);
      // The fine grid had boxes kept apart and boxes listed in several cells.
      CHECK(fine_large > 0);
      CHECK(fine_multi > 0);
    }
  }

  TEST_CASE("refused input: the first invalid box in build_step_boxes' numbering, and nothing changes") {
   for (const bool presence_grid : {false, true}) {
    CAPTURE(presence_grid);
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    world w(seed, 2.0f, 0, 120);
    grid_finder grid;
    host_visibility_engine engine(grid, nullptr, {.rows_per_task = 256, .finder_view = true, .presence_grid = presence_grid});
    visibility_output out;
    for (int tick = 0; tick < 12; ++tick) {
      CAPTURE(tick);
      if (tick % 3 == 2) {
        // Row 7's position NaN (its AOI box 14 and presence box 15), row 3's presence inverted
        // (box 7) on some ticks: the lowest invalid box is named; the previous sets stay.
        world bad = w;
        bad.pos[3 * 7] = std::nanf("");
        std::size_t want = 14;
        if (tick % 2 == 0) {
          bad.body[3 * 3 + 1] = -0.5f;
          want = 7;
        }
        const visibility_output before = out;
        const auto refused = engine.update(bad.input(), out);
        REQUIRE(refused.has_value());
        CHECK(*refused == want);
        CHECK(out.visible == before.visible);  // `out` is written only on success
        CHECK(validate_box(step_box(bad.input(), want), want).has_value());  // what a caller names
      }
      const auto expect = w.model();
      REQUIRE_FALSE(engine.update(w.input(), out).has_value());
      check(out, expect);
      CHECK(engine.last_on_grid() == presence_grid);
      w.commit(expect);
      w.step();
    }
   }
  }

  TEST_CASE("presence grid: coincident entities, observers far beyond the presence bounds, empty and one-row worlds") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    thread_pool pool(2);
    brute_force_finder brute;
    host_visibility_engine reference(brute);
    host_visibility_engine presence(brute, &pool, {.rows_per_task = 8, .finder_view = true, .presence_grid = true});
    visibility_output a, b;
    world w(seed, 1.5f, 0, 0);
    std::uint64_t events = 0;
    for (int tick = 0; tick < 30; ++tick) {
      CAPTURE(tick);
      if (tick == 2) w.add();  // one row (after empty ones)
      if (tick == 4) {
        for (int k = 0; k < 80; ++k) w.add();
        // A crowd on one point, on a cell corner of any planned grid's origin: every pair meets.
        for (std::size_t r = 0; r < 20; ++r) {
          w.pos[3 * r] = w.pos[3 * r + 1] = w.pos[3 * r + 2] = 50.0f;
          w.body[3 * r] = w.body[3 * r + 1] = w.body[3 * r + 2] = 0.0f;
          w.sees[r] = w.cls[r];
        }
        // Observers whose AOI reaches far beyond every presence box, and one entity far away
        // (the grid's extent, and so its cell edge, grows with it).
        for (std::size_t r = 20; r < 24; ++r) w.aoi[3 * r] = w.aoi[3 * r + 1] = 400.0f;
        w.pos[3 * 24] = 1.0e6f;
      }
      const auto want = w.model();
      const visibility_input in = w.input();
      REQUIRE_FALSE(reference.update(in, a).has_value());
      REQUIRE_FALSE(presence.update(in, b).has_value());
      check(a, want);
      events += check(b, want);
      CHECK(presence.last_on_grid());
      w.commit(want);
      if (tick >= 4) w.step();
    }
    CHECK(events > 50);
  }

  TEST_CASE("presence grid: a set with many presence boxes over 64 cells is declined to the pair finder") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    world w(seed, 2.0f, 0, 400);
    // Every body 60 m wide over the 100 m world: far more than 64 cells of any grid the cell cap
    // allows (and 400 of them: more than the 256 and the 1/16 of the rows the grid takes apart).
    for (std::size_t r = 0; r < w.id.size(); ++r) w.body[3 * r] = w.body[3 * r + 1] = 30.0f;
    grid_finder grid;
    host_visibility_engine presence(grid, nullptr, {.rows_per_task = 256, .finder_view = true, .presence_grid = true,
                                                    .grid_cell_edge = 0.5f});
    visibility_output out;
    for (int tick = 0; tick < 3; ++tick) {
      const auto want = w.model();
      REQUIRE_FALSE(presence.update(w.input(), out).has_value());
      check(out, want);
      CHECK_FALSE(presence.last_on_grid());
      w.commit(want);
      for (std::size_t r = 0; r < w.id.size(); ++r) w.pos[3 * r] += w.uni(-1, 1);
    }
  }

  TEST_CASE("apply_pairs: any order of the qualifying pairs gives update's output; mismatches are refused") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    world w(seed, 3.0f, 3, 150);
    brute_force_finder brute;
    host_visibility_engine a(brute), b(brute);
    visibility_output oa, ob;
    box_set boxes;
    pair_list pairs;
    for (int tick = 0; tick < 15; ++tick) {
      CAPTURE(tick);
      const visibility_input in = w.input();
      const auto expect = w.model();
      REQUIRE_FALSE(a.update(in, oa).has_value());
      build_step_boxes(in, boxes);
      REQUIRE_FALSE(brute.find(boxes, pairs).has_value());
      std::shuffle(pairs.begin(), pairs.end(), std::mt19937_64(seed + static_cast<std::uint64_t>(tick)));
      REQUIRE_FALSE(b.apply_pairs(in, boxes, pairs, ob).has_value());
      check(oa, expect);
      check(ob, expect);
      w.commit(expect);
      w.step();
    }
    // Refusals leave the last sets: the next update still diffs against them.
    const visibility_input in = w.input();
    build_step_boxes(in, boxes);
    REQUIRE_FALSE(brute.find(boxes, pairs).has_value());
    box_set short_set = boxes;
    short_set.resize(boxes.size() - 2);
    CHECK(b.apply_pairs(in, short_set, pairs, ob).has_value());
    pair_list beyond = pairs;
    beyond.push_back({0, static_cast<box_id>(boxes.size())});
    const auto err = b.apply_pairs(in, boxes, beyond, ob);
    REQUIRE(err.has_value());
    CHECK(err->message.find("beyond the set") != std::string::npos);
    REQUIRE_FALSE(b.update(in, ob).has_value());
    check(ob, w.model());
  }

  TEST_CASE("load_previous refuses inconsistent sets") {
    grid_finder grid;
    host_visibility_engine e(grid);
    const std::uint32_t ids2[] = {1, 2}, off_short[] = {0, 1}, off_beyond[] = {0, 1, 3}, vis[] = {2, 1};
    CHECK_THROWS_AS(e.load_previous(ids2, slot_bits, off_short, vis), std::invalid_argument);
    CHECK_THROWS_AS(e.load_previous(ids2, slot_bits, off_beyond, vis), std::invalid_argument);
    const std::uint32_t off_ok[] = {0, 1, 2};
    e.load_previous(ids2, slot_bits, off_ok, vis);
    const auto all = e.fetch_all_visible();
    CHECK(row(all.data, all.off, nullptr, 0) == ids{2});
    CHECK(row(all.data, all.off, nullptr, 1) == ids{1});
  }
}
