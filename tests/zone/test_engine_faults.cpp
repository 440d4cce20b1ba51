// A GPU interest engine that fails mid-run (zone/engine_faults.h, zone-server --test-fault
// gpu-interest / gpu-lost), without a GPU: the engine is emulated on the CPU by brute force (the
// contract of interest/visibility_engine.h), wrapped in the fault, and the interest tracker must
// run every tick before the fault on the engine and the fault's tick and every later one on its
// host path, with every visible set, enter and leave equal to the brute-force oracle of
// tracker_harness.h throughout. With a view demand (only some rows' sets copied back, as
// zone-server asks for its players) the device's copy of the other rows is lost with it: the rows
// read on the host stay exact, the others start over from what their AOI holds. The GPU engine
// itself behind the same wrapper runs on the H100 (docs/zone.md, "A GPU that fails mid-run").
#include <doctest/doctest.h>

#include <algorithm>
#include <map>

#include "tracker_harness.h"
#include "zone/engine_faults.h"

using namespace zone;
using namespace zone::test;

namespace {

/// interest::visibility_engine's contract, literally, O(n^2): the previous sets are kept by handle.
class emulated_visibility_engine final : public interest::visibility_engine {
 public:
  std::optional<std::size_t> update(const interest::visibility_input& in, interest::visibility_output& out) override {
    const std::size_t n = in.n;
    const auto box = [&](std::size_t i, const float* half, float grow) {
      fbox b;
      for (int d = 0; d < 3; ++d) {
        b.lo[d] = in.position[3 * i + d] - (half[3 * i + d] + grow);
        b.hi[d] = in.position[3 * i + d] + (half[3 * i + d] + grow);
      }
      return b;
    };
    for (std::size_t i = 0; i < n; ++i) {
      for (int d = 0; d < 3; ++d) {
        if (!std::isfinite(in.position[3 * i + d]) || !(in.aoi_half[3 * i + d] >= 0)) return 2 * i;
        if (!(in.body_half[3 * i + d] >= 0)) return 2 * i + 1;
      }
    }
    std::map<std::uint32_t, id_list> next;
    vis_.clear(), enters_.clear(), leaves_.clear();
    vis_off_.assign(1, 0), enter_off_.assign(1, 0), leave_off_.assign(1, 0);
    all_.clear(), all_off_.assign(1, 0);
    std::uint64_t pairs = 0, candidates = 0, total = 0;
    for (std::size_t i = 0; i < n; ++i) {
      const fbox aoi = box(i, in.aoi_half, 0), grown = box(i, in.aoi_half, in.hysteresis);
      const auto it = prev_.find(in.ids[i]);
      const id_list none;
      const id_list& old = it == prev_.end() ? none : it->second;
      id_list row;
      for (std::size_t j = 0; j < n; ++j) {
        const fbox body = box(j, in.body_half, 0);
        if (!meets(grown, body)) continue;
        ++pairs;
        if (j == i || (in.visibility[j] & in.sees[i]) == 0) continue;
        ++candidates;
        if (std::binary_search(old.begin(), old.end(), in.ids[j]) || meets(aoi, body)) row.push_back(in.ids[j]);
      }
      std::sort(row.begin(), row.end());
      std::set_difference(row.begin(), row.end(), old.begin(), old.end(), std::back_inserter(enters_));
      std::set_difference(old.begin(), old.end(), row.begin(), row.end(), std::back_inserter(leaves_));
      enter_off_.push_back(static_cast<std::uint32_t>(enters_.size()));
      leave_off_.push_back(static_cast<std::uint32_t>(leaves_.size()));
      if (in.wanted == nullptr || in.wanted[i] != 0) vis_.insert(vis_.end(), row.begin(), row.end());
      vis_off_.push_back(static_cast<std::uint32_t>(vis_.size()));
      all_.insert(all_.end(), row.begin(), row.end());
      all_off_.push_back(static_cast<std::uint32_t>(all_.size()));
      total += row.size();
      next[in.ids[i]] = std::move(row);
    }
    prev_ = std::move(next);
    out = {};
    out.visible = vis_.data(), out.visible_off = vis_off_.data();
    out.enters = enters_.data(), out.enter_off = enter_off_.data();
    out.leaves = leaves_.data(), out.leave_off = leave_off_.data();
    out.visible_complete = in.wanted == nullptr;
    out.visible_total = total;
    out.pairs = pairs;
    out.candidates = candidates;
    ++updates;
    return std::nullopt;
  }
  void load_previous(std::span<const std::uint32_t> ids, std::uint32_t, std::span<const std::uint32_t> offsets,
                     std::span<const std::uint32_t> visible) override {
    prev_.clear();
    for (std::size_t r = 0; r < ids.size(); ++r) {
      prev_[ids[r]] = id_list(visible.begin() + offsets[r], visible.begin() + offsets[r + 1]);
    }
    ++loads;
  }
  interest::visibility_lists fetch_all_visible() override { return {all_.data(), all_off_.data()}; }
  [[nodiscard]] const char* name() const override { return "emulated"; }
  int updates = 0, loads = 0;

 private:
  std::map<std::uint32_t, id_list> prev_;
  id_list vis_, enters_, leaves_, all_;
  std::vector<std::uint32_t> vis_off_, enter_off_, leave_off_, all_off_;
};

/// The rules every visible set obeys, whatever the previous sets were: inside the grown box, of a
/// class the observer sees, never itself; and everything inside the AOI box that it sees is in it.
void check_rules(const interest_tracker& t, const entity_store& s, std::size_t row, float h) {
  const auto pos = s.positions();
  const entity_id a = s.ids()[row];
  const auto vis = t.visible(row);
  const fbox aoi = around(pos[row], s.aoi_half_extents()[row]);
  const fbox grown = around_grown(pos[row], s.aoi_half_extents()[row], h);
  for (std::size_t j = 0; j < s.size(); ++j) {
    const bool in = std::binary_search(vis.begin(), vis.end(), s.ids()[j]);
    const fbox body = around(pos[j], s.presence_half_extents()[j]);
    const bool seen = j != row && (s.visibility_classes()[j] & s.sees()[row]) != 0;
    if (in) CHECK((seen && meets(body, grown)));
    if (seen && meets(body, aoi)) CHECK(in);
  }
  (void)a;
}

/// The harness's oracle (no cap) with its previous sets open, so that it can go on from the
/// tracker's sets after rows were lost with the device.
struct open_oracle {
  std::map<entity_id, id_list> prev;
  std::map<entity_id, row_result> step(const entity_store& s, float h) {
    std::map<entity_id, row_result> out;
    std::map<entity_id, id_list> next;
    const auto pos = s.positions();
    for (std::size_t i = 0; i < s.size(); ++i) {
      const entity_id a = s.ids()[i];
      const fbox aoi = around(pos[i], s.aoi_half_extents()[i]);
      const fbox grown = around_grown(pos[i], s.aoi_half_extents()[i], h);
      const id_list& old = prev[a];
      row_result r;
      for (std::size_t j = 0; j < s.size(); ++j) {
        if (j == i || (s.visibility_classes()[j] & s.sees()[i]) == 0) continue;
        const fbox body = around(pos[j], s.presence_half_extents()[j]);
        const bool was = std::binary_search(old.begin(), old.end(), s.ids()[j]);
        if (meets(body, aoi) || (was && meets(body, grown))) r.visible.push_back(s.ids()[j]);
      }
      std::sort(r.visible.begin(), r.visible.end());
      std::set_difference(r.visible.begin(), r.visible.end(), old.begin(), old.end(), std::back_inserter(r.enters));
      std::set_difference(old.begin(), old.end(), r.visible.begin(), r.visible.end(), std::back_inserter(r.leaves));
      next[a] = r.visible;
      out[a] = std::move(r);
    }
    prev = std::move(next);
    return out;
  }
};

struct fault_run {
  int engine_ticks = 0, host_ticks = 0;
  std::uint64_t exact_rows = 0, rule_rows = 0;
};

fault_run run_with_fault(std::uint64_t seed, int fault_tick, bool demand, bool real_style_raise, int ticks = 40) {
  CAPTURE(seed);
  CAPTURE(fault_tick);
  CAPTURE(demand);
  const float h = 4.0f;
  world w(seed, 260, false);
  interest::thread_pool pool(2);
  interest::grid_finder finder(&pool);
  interest_tracker tracker(finder, &pool, interest_options{h, 0, 7});
  emulated_visibility_engine inner;
  std::uint64_t tick = 0;
  engine_fault fault;
  fault.tick = [&] { return tick; };
  fault.at_tick = static_cast<std::uint64_t>(fault_tick);
  if (real_style_raise) fault.raise = [] { throw std::runtime_error("a device error from raise"); };
  faulty_visibility_engine engine(inner, fault);
  tracker.set_engine(&engine);
  // Rows read on the host: every third slot (zone-server's players), the others left on the "device".
  std::vector<std::uint8_t> by_slot;
  if (demand) tracker.set_view_demand(&by_slot);
  open_oracle o;
  fault_run r;
  bool lost = false;  // the device held rows that were never copied back when it failed
  for (; tick < static_cast<std::uint64_t>(ticks); ++tick) {
    CAPTURE(tick);
    by_slot.assign(w.store.slot_count(), 0);
    for (std::size_t k = 0; k < by_slot.size(); k += 3) by_slot[k] = 1;
    REQUIRE_FALSE(tracker.update(w.store.columns()).has_value());
    const bool before = tick < static_cast<std::uint64_t>(fault_tick);
    REQUIRE(tracker.last_update_on_engine() == before);
    REQUIRE(engine.fault().fired() == !before);
    REQUIRE(tracker.engine_error().empty() == before);
    if (!before) {
      CHECK(tracker.engine_error().find(real_style_raise ? "a device error from raise" : "CUDA error") != std::string::npos);
      if (tick == static_cast<std::uint64_t>(fault_tick)) lost = demand && fault_tick > 0;
    }
    (before ? r.engine_ticks : r.host_ticks)++;
    auto expected = o.step(w.store, h);
    for (std::size_t row = 0; row < w.store.size(); ++row) {
      const entity_id a = w.store.ids()[row];
      const bool read = !demand || by_slot[slot_of(a)] != 0;
      if (lost && !read) {
        // Its set was on the failed device: it starts over (rules only), and so does the oracle's.
        check_rules(tracker, w.store, row, h);
        ++r.rule_rows;
        continue;
      }
      REQUIRE(tracker.observer(row) == a);
      const auto vis = tracker.visible(row), en = tracker.enters(row), lv = tracker.leaves(row);
      CHECK(id_list(vis.begin(), vis.end()) == expected[a].visible);
      CHECK(id_list(en.begin(), en.end()) == expected[a].enters);
      CHECK(id_list(lv.begin(), lv.end()) == expected[a].leaves);
      ++r.exact_rows;
    }
    if (lost) {
      // From the next tick on both go on from the tracker's sets (the lost rows' new start).
      for (std::size_t row = 0; row < w.store.size(); ++row) {
        const auto vis = tracker.visible(row);
        o.prev[w.store.ids()[row]] = id_list(vis.begin(), vis.end());
      }
      lost = false;
    }
    w.step();
  }
  CHECK(inner.updates == std::min(fault_tick, ticks));  // the engine ran exactly the ticks before the fault
  return r;
}

}  // namespace

TEST_SUITE("zone.engine_faults") {
  TEST_CASE("the GPU interest engine failing mid-run: the same tick runs on the host, every set exact") {
    for (const int at : {0, 1, 9, 23}) {
      const auto r = run_with_fault(fresh_seed(), at, false, false);
      CHECK(r.engine_ticks == at);
      CHECK(r.host_ticks == 40 - at);
      CHECK(r.rule_rows == 0);
    }
  }

  TEST_CASE("a raise that throws its own error (zone-server's real device fault): the same fallback") {
    const auto r = run_with_fault(fresh_seed(), 5, false, true);
    CHECK(r.host_ticks == 35);
  }

  TEST_CASE("with only some rows read on the host: those stay exact, the rows lost with the device start over") {
    for (const int at : {1, 12}) {
      const auto r = run_with_fault(fresh_seed(), at, true, false);
      CHECK(r.rule_rows > 0);   // some rows were lost with the device
      CHECK(r.exact_rows > r.rule_rows);
    }
  }

  TEST_CASE("engine_fault: due at its tick, then for good; the wrapper forwards until then") {
    std::uint64_t tick = 0;
    engine_fault f;
    f.tick = [&] { return tick; };
    f.at_tick = 3;
    for (; tick < 3; ++tick) CHECK_NOTHROW(f.check("step"));
    CHECK_FALSE(f.fired());
    CHECK_THROWS_AS(f.check("step"), std::runtime_error);
    CHECK(f.fired());
    tick = 0;  // a fired fault stays fired
    CHECK_THROWS_AS(f.check("step"), std::runtime_error);
    engine_fault g;
    g.at_tick = 1;
    g.tick = [] { return std::uint64_t{1}; };
    g.raise = [] {};  // a raise that does not throw is a bug in the test hook, reported as such
    CHECK_THROWS_AS(g.check("step"), std::logic_error);
  }
}
