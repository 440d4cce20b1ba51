// The GPU replication engine's per-job code (gpu/replication/replication_shared.h: the client table's plan, the
// carry of views without a job, decide_job) run on the CPU through an emulated engine, against the
// CPU replicator byte for byte (replication_equivalence.h). This runs in every CI run, device or
// not; test_zone_gpu runs the same comparison on the device. The jobs run in a shuffled order, as
// the device's threads may (their records land anywhere in the buffer).
#include <doctest/doctest.h>

#include <algorithm>
#include <atomic>
#include <barrier>
#include <cstring>
#include <functional>
#include <limits>
#include <memory>
#include <numeric>
#include <random>
#include <set>
#include <span>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "../common/seeds.h"
#include "gpu/replication/replication_shared.h"
#include "replication_equivalence.h"
#include "zone/zone.h"
#include "zone/engine_faults.h"

using namespace zone;
namespace rep = zone::gpu::detail::rep;

namespace {

/// decide_job's group of lanes as W host threads in step (replication_shared.h, serial_lanes):
/// the device runs 32 lanes a job; widths 4 and 32 here check the lane-parallel walk on the CPU.
template <std::uint32_t W>
struct thread_lanes {
  struct shared {
    std::barrier<> step{W};
    std::uint32_t word[W] = {};
    std::uint64_t wide[W] = {};
  };
  static constexpr std::uint32_t width = W;
  shared* s;
  std::uint32_t l;
  [[nodiscard]] std::uint32_t lane() const { return l; }
  std::uint32_t ballot(bool p) {
    s->word[l] = p ? 1u : 0u;
    s->step.arrive_and_wait();
    std::uint32_t m = 0;
    for (std::uint32_t k = 0; k < W; ++k) m |= s->word[k] << k;
    s->step.arrive_and_wait();
    return m;
  }
  std::uint32_t first(std::uint32_t v) {
    if (l == 0) s->word[0] = v;
    s->step.arrive_and_wait();
    const std::uint32_t r = s->word[0];
    s->step.arrive_and_wait();
    return r;
  }
  std::uint64_t sum(std::uint64_t v) {
    s->wide[l] = v;
    s->step.arrive_and_wait();
    std::uint64_t t = 0;
    for (std::uint32_t k = 0; k < W; ++k) t += s->wide[k];
    s->step.arrive_and_wait();
    return t;
  }
  void sync() { s->step.arrive_and_wait(); }
};

/// Every job of `order`, in that order, by W threads as one group each.
template <std::uint32_t W>
void decide_in_lanes(const rep::run_args& a, const std::vector<std::uint32_t>& order) {
  typename thread_lanes<W>::shared s;
  std::vector<std::thread> lanes;
  for (std::uint32_t l = 0; l < W; ++l) {
    lanes.emplace_back([&, l] {
      thread_lanes<W> g{&s, l};
      for (const std::uint32_t t : order) rep::decide_job(a, t, g);
    });
  }
  for (auto& t : lanes) t.join();
}

class emulated_engine final : public interest::replication_engine {
 public:
  /// keep: the output's records stay the caller's while it holds records_keep (as the GPU
  /// engine's: up to four buffers, then copied again), else reused every run.
  /// lanes: how many lanes decide each job (1, 4 or 32: decide_job's group; the device's is 32).
  explicit emulated_engine(std::uint64_t seed, bool keep = true, std::uint32_t lanes = 1)
      : rng_(seed), keep_(keep), lanes_(lanes) {}
  [[nodiscard]] const char* name() const override { return "emulated"; }
  [[nodiscard]] const interest::replication_timing& timing() const override { return timing_; }
  void set_frame_format(const interest::replication_frame_format& format) override { format_ = format; }

  staging stage(std::size_t entities, std::size_t slots, std::size_t jobs, std::size_t visible) override {
    // Entities handed over ahead (stage_entities, upload_entities) stay when the counts match;
    // else the staging starts as garbage the caller must overwrite.
    if (!(uploaded_ && entities == entities_.size() && slots == slot_dense_.size())) {
      uploaded_ = false;
      entities_.assign(entities, garbage_entity());
      slot_dense_.assign(slots, 0xfefefefe);
    }
    jobs_.assign(jobs, {});
    visible_.assign(visible, 0);
    return {entities_.data(), slot_dense_.data(), jobs_.data(), visible_.data()};
  }

  staging stage_entities(std::size_t entities, std::size_t slots) override {
    uploaded_ = false;
    entities_.assign(entities, garbage_entity());
    slot_dense_.assign(slots, 0xfefefefe);
    return {entities_.data(), slot_dense_.data(), nullptr, nullptr};
  }
  void upload_entities() override {
    uploaded_ = true;
    ++uploads_;
  }
  void discard_entities() override { uploaded_ = false; }
  /// Runs that used entities handed over ahead.
  [[nodiscard]] std::uint64_t runs_uploaded_ahead() const { return runs_ahead_; }

  output run(const interest::replication_rules& rules, std::size_t client_count,
             const interest::visibility_engine::resident_lists* rows,
             const std::function<void()>* while_waiting) override {
    if (uploaded_) ++runs_ahead_;
    uploaded_ = false;
    REQUIRE(rows == nullptr);  // reads_resident() is false: the replicator stages the sets
    ++runs;
    if (len_.size() < client_count) {
      len_.resize(client_count, 0);
      off_.resize(client_count, 0);
      hash_.resize(client_count, 0);
    }
    clients_.resize(client_count);
    new_off_.resize(client_count + 1);
    rep::table_clients(jobs_.data(), jobs_.size(), visible_.size(), 0, len_.data(), off_.data(), client_count,
                       clients_.data());
    std::uint64_t record_cap = 0;
    const std::uint64_t total =
        rep::plan_staged(jobs_.data(), clients_.data(), client_count, rules, format_, new_off_.data(), record_cap);
    // The device's planning (client_room, used with resident rows) must agree with the host's.
    std::uint64_t rooms = 0, records = 0;
    new_id_.assign(total, 0xdeadbeef);
    new_sent_.assign(total, 0xdeadbeef);
    scratch_.assign(total, {});
    records_.assign(record_cap, 0xcd);
    results_.assign(jobs_.size(), {});
    std::uint32_t cursor[2] = {0, 0};
    rep::run_args a{};
    a.rules = rules;
    a.entities = entities_.data();
    a.entity_count = static_cast<std::uint32_t>(entities_.size());
    updates_.assign(4 * entities_.size(), 0xdeadbeef);
    a.updates = updates_.data();
    a.format = &format_;
    a.slot_dense = slot_dense_.data();
    a.slot_count = static_cast<std::uint32_t>(slot_dense_.size());
    a.jobs = jobs_.data();
    a.job_count = static_cast<std::uint32_t>(jobs_.size());
    a.visible = visible_.data();
    a.clients = clients_.data();
    a.client_count = static_cast<std::uint32_t>(client_count);
    a.new_off = new_off_.data();
    for (std::uint32_t c = 0; c < client_count; ++c) {
      std::uint32_t room = 0;
      std::uint64_t record = 0;
      rep::client_room(a, c, room, record);
      CHECK(new_off_[c] == rooms);
      rooms += room;
      records += record;
    }
    CHECK(rooms == total);
    CHECK(records == record_cap);
    a.old_id = id_.data();
    a.old_sent = sent_.data();
    a.new_id = new_id_.data();
    a.new_sent = new_sent_.data();
    a.scratch = scratch_.data();
    a.hash = hash_.data();
    a.records = records_.data();
    a.record_capacity = record_cap;
    a.cursor = cursor;
    a.results = results_.data();
    for (std::uint32_t k = 0; k < a.entity_count; ++k) rep::quantize_entity(a, k);
    for (std::uint32_t c = 0; c < client_count; ++c) rep::carry_client(a, c, 0, 1);
    // Where the GPU engine's kernels are queued: the caller's side work, before the decisions.
    if (while_waiting != nullptr && *while_waiting) {
      ++side_calls;
      (*while_waiting)();
    }
    std::vector<std::uint32_t> order(jobs_.size());
    std::iota(order.begin(), order.end(), 0u);
    std::shuffle(order.begin(), order.end(), rng_);
    if (lanes_ == 4) {
      decide_in_lanes<4>(a, order);
    } else if (lanes_ == 32) {
      decide_in_lanes<32>(a, order);
    } else {
      for (const std::uint32_t t : order) rep::decide_job(a, t);
    }
    REQUIRE(cursor[1] == 0);
    REQUIRE(cursor[0] <= record_cap);
    id_.swap(new_id_);
    sent_.swap(new_sent_);
    for (std::size_t c = 0; c < client_count; ++c) off_[c] = new_off_[c];
    for (std::size_t k = 0; k < jobs_.size(); ++k) len_[jobs_[k].client] = results_[k].view_size;
    if (keep_) {
      std::shared_ptr<std::vector<std::uint8_t>>* pick = nullptr;
      for (auto& b : kept_) {
        if (b.use_count() == 1) {
          pick = &b;
          break;
        }
      }
      if (pick == nullptr && kept_.size() < 4) pick = &kept_.emplace_back(std::make_shared<std::vector<std::uint8_t>>());
      if (pick != nullptr) {
        std::vector<std::uint8_t>& buf = **pick;
        buf.assign(records_.size(), 0xab);  // a reused buffer's old frames never show through
        std::memcpy(buf.data(), records_.data(), cursor[0]);
        output o{results_.data(), buf.data(), *pick};
        return o;
      }
    }
    return {results_.data(), records_.data(), nullptr};
  }

  void forget_all() override {
    std::fill(len_.begin(), len_.end(), 0u);
    std::fill(off_.begin(), off_.end(), 0u);
  }

  std::size_t runs = 0;        ///< run() calls
  std::size_t side_calls = 0;  ///< of which called while_waiting

 private:
  static interest::replication_entity garbage_entity() {
    interest::replication_entity e{};
    e.x = e.y = e.z = -1e30f;
    e.id = 0xfefefefe;
    return e;
  }
  std::mt19937_64 rng_;
  bool keep_ = true;
  std::uint32_t lanes_ = 1;
  bool uploaded_ = false;
  std::uint64_t uploads_ = 0, runs_ahead_ = 0;
  std::vector<std::shared_ptr<std::vector<std::uint8_t>>> kept_;
  std::vector<interest::replication_entity> entities_;
  std::vector<std::uint32_t> slot_dense_, visible_;
  std::vector<interest::replication_job> jobs_;
  std::vector<rep::client_slot> clients_;
  std::vector<std::uint32_t> len_, off_, id_, sent_, new_id_, new_sent_, new_off_, updates_;
  std::vector<std::uint64_t> hash_;
  std::vector<rep::scratch_entry> scratch_;
  std::vector<std::uint8_t> records_;
  std::vector<interest::replication_result> results_;
  interest::replication_timing timing_;
  interest::replication_frame_format format_;
};

/// `n` entities at random in a side x side x 10 m world (AOI half extents 15-80 m, every
/// `stealth_every`-th one stealth), for the tests below.
void add_random_entities(entity_store& store, std::mt19937_64& rng, int n, float side, int stealth_every) {
  namespace cb = interest::category_bits;
  const auto uni = [&](float lo, float hi) { return std::uniform_real_distribution<float>(lo, hi)(rng); };
  for (int k = 0; k < n; ++k) {
    entity_desc d;
    d.position = {uni(0, side), uni(0, side), uni(0, 10)};
    d.velocity = {uni(-3, 3), uni(-3, 3), 0};
    const float aoi = uni(15, 80);
    d.aoi_half_extent = {aoi, aoi, 40};
    d.presence_half_extent = {1, 1, 1};
    d.visibility_class = k % stealth_every == 0 ? cb::stealth : cb::normal;
    d.sees = cb::normal;
    (void)store.create(d);
  }
}

/// One tick's move of every entity by its velocity, clamped to the side x side world.
void move_all(entity_store& store, float side) {
  auto pos = store.positions();
  const auto vel = store.velocities();
  for (std::size_t i = 0; i < store.size(); ++i) {
    pos[i] = {std::clamp(pos[i].x + vel[i].x, 0.f, side), std::clamp(pos[i].y + vel[i].y, 0.f, side), pos[i].z};
  }
}

/// The setting of the build_many tests below: `n` random entities (add_random_entities) in a
/// side x side world, the interest tracker over them (grid finder, 2 threads), and replication
/// options for that world.
struct random_zone {
  std::mt19937_64 rng;
  entity_store store;
  interest::thread_pool pool{2};
  interest::grid_finder finder{&pool};
  interest_tracker tracker{finder, &pool, {3.0f, 0, 64}};
  replication_options opt;
  random_zone(std::uint64_t seed, int n, float side, int stealth_every) : rng(seed) {
    add_random_entities(store, rng, n, side, stealth_every);
    opt.world = {{0, 0, 0}, {side, side, 20}};
  }
};

/// The same `count` clients (the entities at every `stride`-th id) in each replicator of `reps`;
/// the requests for them.
std::vector<replication_request> add_same_clients(std::span<replicator* const> reps, const entity_store& store,
                                                  std::size_t count, std::size_t stride) {
  std::vector<replication_request> requests;
  for (std::size_t k = 0; k < count; ++k) {
    const client_id c = reps[0]->add_client(store.ids()[k * stride]);
    for (std::size_t r = 1; r < reps.size(); ++r) REQUIRE(reps[r]->add_client(store.ids()[k * stride]) == c);
    requests.push_back({c, 0});
  }
  return requests;
}

}  // namespace

TEST_SUITE("zone.replication") {
  TEST_CASE("the GPU engine's per-job code, emulated on the CPU, gives the CPU replicator's frames byte for byte") {
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    zone::test::replication_equivalence_case c;
    const auto cov = zone::test::check_replication_equivalence(
        seed, c, [&] { return std::make_unique<emulated_engine>(seed); });
    zone::test::require_equivalent(cov);
  }

  TEST_CASE(
      "sort_entries (the ranks of long lists): std::sort's order by before() for every length, 1, 4 and 32 lanes") {
    // Keys with many ties (the id breaks them), +0 and -0, both key fields; 16 guard entries past
    // n must stay as they were (the network is padded to a power of two).
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    std::mt19937_64 rng(seed);
    std::vector<std::uint32_t> lengths;
    for (std::uint32_t n = 0; n <= 70; ++n) lengths.push_back(n);
    for (const std::uint32_t n : {127u, 128u, 129u, 511u, 512u, 513u, 1000u, 2049u}) lengths.push_back(n);
    std::uint64_t sorted_lists = 0;
    for (const bool by_z : {false, true}) {
      for (const std::uint32_t n : lengths) {
        CAPTURE(by_z);
        CAPTURE(n);
        std::vector<rep::scratch_entry> in(n + 16);
        std::vector<std::uint32_t> ids(n);
        std::iota(ids.begin(), ids.end(), 1u);
        std::shuffle(ids.begin(), ids.end(), rng);
        const float keys[] = {0.0f, -0.0f, 1.5f, -3.25f, 7.0f, 1e-30f};
        for (std::uint32_t k = 0; k < n + 16; ++k) {
          const float key = rng() % 3 == 0 ? keys[rng() % 6] : std::uniform_real_distribution<float>(-50, 50)(rng);
          const std::uint32_t id = k < n ? ids[k] : 0xdead0000u + k, other = static_cast<std::uint32_t>(rng());
          in[k] = by_z ? rep::entry(other, other, rep::float_bits(key), id)
                       : rep::entry(rep::float_bits(key), id, other, other);
        }
        const auto key_of = [&](const rep::scratch_entry& e) {
          return by_z ? std::pair{rep::bits_float(e.z), e.w} : std::pair{rep::bits_float(e.x), e.y};
        };
        std::vector<rep::scratch_entry> want(in.begin(), in.begin() + n);
        std::sort(want.begin(), want.end(), [&](const rep::scratch_entry& a, const rep::scratch_entry& b) {
          const auto [ka, ia] = key_of(a);
          const auto [kb, ib] = key_of(b);
          return rep::before(ka, ia, kb, ib);
        });
        const auto same = [](const rep::scratch_entry& a, const rep::scratch_entry& b) {
          return a.x == b.x && a.y == b.y && a.z == b.z && a.w == b.w;
        };
        const auto check = [&](const std::vector<rep::scratch_entry>& got) {
          bool ok = true;
          for (std::uint32_t k = 0; k < n; ++k) ok = ok && same(got[k], want[k]);
          for (std::uint32_t k = n; k < n + 16; ++k) ok = ok && same(got[k], in[k]);
          return ok;
        };
        std::vector<rep::scratch_entry> one = in;
        rep::serial_lanes g1;
        rep::sort_entries(one.data(), n, by_z, g1);
        CHECK(check(one));
        ++sorted_lists;
        if (n > 300) continue;  // the threaded widths: a barrier a step
        for (const std::uint32_t lanes : {4u, 32u}) {
          std::vector<rep::scratch_entry> got = in;
          const auto run = [&]<std::uint32_t W>() {
            typename thread_lanes<W>::shared sh;
            std::vector<std::thread> ts;
            for (std::uint32_t l = 0; l < W; ++l) {
              ts.emplace_back([&, l] {
                thread_lanes<W> g{&sh, l};
                rep::sort_entries(got.data(), n, by_z, g);
              });
            }
            for (auto& t : ts) t.join();
          };
          if (lanes == 4) {
            run.template operator()<4>();
          } else {
            run.template operator()<32>();
          }
          CAPTURE(lanes);
          CHECK(check(got));
        }
      }
    }
    CHECK(sorted_lists == 2 * 79);
  }

  TEST_CASE(
      "the per-job code in a crowd (hundreds of due updates a frame, ranked by sorting), 1 and 32 lanes: the same frames") {
    for (const std::uint32_t lanes : {1u, 32u}) {
      const std::uint64_t seed = zone::test::fresh_seed();
      CAPTURE(seed);
      CAPTURE(lanes);
      zone::test::replication_equivalence_case c = zone::test::crowd_case();
      if (lanes == 32) c.ticks = 15;
      const auto cov = zone::test::check_replication_equivalence(
          seed, c, [&] { return std::make_unique<emulated_engine>(seed, true, lanes); });
      zone::test::require_equivalent(cov);
      CHECK(cov.ranked_sorted > 0);
    }
  }

  TEST_CASE("the per-job code with 4 and 32 lanes a job (the device's warp), emulated by threads: the same frames") {
    for (const std::uint32_t lanes : {4u, 32u}) {
      const std::uint64_t seed = zone::test::fresh_seed();
      CAPTURE(seed);
      CAPTURE(lanes);
      zone::test::replication_equivalence_case c;
      if (lanes == 32) c.ticks = 12;  // 32 threads in step on a 2-core machine are slow
      const auto cov = zone::test::check_replication_equivalence(
          seed, c, [&] { return std::make_unique<emulated_engine>(seed, true, lanes); });
      zone::test::require_equivalent(cov);
    }
    const auto cov = zone::test::deferred_leaves_runs([&] {
      const std::uint64_t seed = zone::test::fresh_seed();
      CAPTURE(seed);
      const auto world = zone::test::check_replication_equivalence(
          seed, zone::test::deferred_leaves_case(), [&] { return std::make_unique<emulated_engine>(seed, true, 4); });
      zone::test::require_equivalent(world, true, false, false);
      return world;
    });
    CHECK(cov.deferred_leaves > 0);
  }

  TEST_CASE("the engine's quantization (quantize_entity) equals net::position_quantizer and quantize_velocity bit for bit") {
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    std::mt19937_64 rng(seed);
    // Worlds: the default, an offset one, one with a zero-width axis.
    const net::world_bounds worlds[] = {{{0, 0, 0}, {4096, 4096, 256}},
                                        {{-1000.5f, 37.25f, -3}, {2500.75f, 9000, 60}},
                                        {{-10, -10, 5}, {10, 10, 5}}};
    for (const auto& wb : worlds) {
      const net::position_quantizer q(wb);
      interest::replication_rules rules;
      rules.quant_lo[0] = wb.lo.x;
      rules.quant_lo[1] = wb.lo.y;
      rules.quant_lo[2] = wb.lo.z;
      for (int d = 0; d < 3; ++d) rules.quant_step[d] = q.step(d);
      std::vector<interest::replication_entity> ents;
      const auto add = [&](float x, float y, float z, float vx, float vy, float vz) {
        ents.push_back({x, y, z, static_cast<std::uint32_t>(ents.size() * 7 + 1), vx, vy, vz, 0});
      };
      // Edges: the corners, just outside, exact half steps, velocities at and past the clamp, NaN.
      const float nan = std::numeric_limits<float>::quiet_NaN(), inf = std::numeric_limits<float>::infinity();
      add(wb.lo.x, wb.lo.y, wb.lo.z, 0, -0.0f, 327.67f);
      add(wb.hi.x, wb.hi.y, wb.hi.z, 327.675f, -327.675f, 1e9f);
      add(wb.lo.x - 1, wb.hi.y + 1, nan, nan, -inf, inf);
      for (int k = 0; k < 64; ++k) {
        const double t = k + 0.5;  // half steps: round half up
        add(static_cast<float>(wb.lo.x + t * q.step(0)), static_cast<float>(wb.lo.y + t * q.step(1)),
            static_cast<float>(wb.lo.z + t * q.step(2)), static_cast<float>(k) * 0.005f, -static_cast<float>(k) * 0.005f,
            static_cast<float>(k) * 0.015f);
      }
      std::uniform_real_distribution<float> ux(wb.lo.x - 50, wb.hi.x + 50), uy(wb.lo.y - 50, wb.hi.y + 50),
          uz(wb.lo.z - 5, wb.hi.z + 5), uv(-400, 400);
      for (int k = 0; k < 20000; ++k) add(ux(rng), uy(rng), uz(rng), uv(rng), uv(rng), uv(rng) * 1e-3f);
      std::vector<std::uint32_t> words(4 * ents.size());
      rep::run_args a{};
      a.rules = rules;
      a.entities = ents.data();
      a.entity_count = static_cast<std::uint32_t>(ents.size());
      a.updates = words.data();
      for (std::uint32_t k = 0; k < a.entity_count; ++k) rep::quantize_entity(a, k);
      for (std::size_t k = 0; k < ents.size(); ++k) {
        const auto& e = ents[k];
        const auto qp = q.quantize({e.x, e.y, e.z});
        const auto qv = net::quantize_velocity({e.vx, e.vy, e.vz});
        const net::wire::entity_update want(e.id, net::wire::qpos3(qp[0], qp[1], qp[2]),
                                            net::wire::qvel3(qv[0], qv[1], qv[2]));
        CAPTURE(k);
        REQUIRE(std::memcmp(&want, words.data() + 4 * k, 16) == 0);
      }
    }
  }

  TEST_CASE("emulated GPU engine: views grown past a frame's leaves, then every observer blind: leaves deferred, frames equal") {
    const auto cov = zone::test::deferred_leaves_runs([&] {
      const std::uint64_t seed = zone::test::fresh_seed();
      CAPTURE(seed);
      const auto world = zone::test::check_replication_equivalence(seed, zone::test::deferred_leaves_case(), [&] { return std::make_unique<emulated_engine>(seed); });
      zone::test::require_equivalent(world, true, false, false);
      return world;
    });
    CHECK(cov.deferred_leaves > 0);
  }
}

namespace {

/// The emulated engine that calls the side work and then fails (as a device error in the wait
/// after the kernels would): from tick `at` on, every run throws after calling it.
class fails_after_side final : public interest::replication_engine {
 public:
  fails_after_side(interest::replication_engine& inner, const std::uint64_t& tick, std::uint64_t at)
      : inner_(inner), tick_(tick), at_(at) {}
  staging stage(std::size_t entities, std::size_t slots, std::size_t jobs, std::size_t visible) override {
    return inner_.stage(entities, slots, jobs, visible);
  }
  output run(const interest::replication_rules& rules, std::size_t client_count,
             const interest::visibility_engine::resident_lists* rows,
             const std::function<void()>* while_waiting) override {
    const auto out = inner_.run(rules, client_count, rows, while_waiting);
    if (tick_ >= at_) throw std::runtime_error("CUDA error: an illegal memory access was encountered (test)");
    return out;
  }
  void set_frame_format(const interest::replication_frame_format& format) override { inner_.set_frame_format(format); }
  void forget_all() override { inner_.forget_all(); }
  [[nodiscard]] const interest::replication_timing& timing() const override { return inner_.timing(); }
  [[nodiscard]] const char* name() const override { return "fails after side work"; }

 private:
  interest::replication_engine& inner_;
  const std::uint64_t& tick_;
  std::uint64_t at_;
};

}  // namespace

// build_many's side work (zone-server fills the viewer's snapshot there): exactly once per call on
// every path; on an engine inside run() before any frame, on the CPU after the last frame; an
// engine that fails before calling it leaves it to the CPU path, one that fails after does not
// run it twice; what it throws leaves build_many after the frames and does not give the engine
// up. What it reads (the store, the tracker) is what it would read after build_many.
TEST_SUITE("zone.replication") {
  TEST_CASE("build_many's side work: once per call, in the engine's wait or after the CPU's frames; frames unchanged") {
    namespace cb = interest::category_bits;
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    random_zone z(seed, 400, 250, 5);
    z.opt.byte_budget = 900;
    z.opt.clients_per_task = 3;  // several chunks
    std::uint64_t tick = 0;
    // The paths: the CPU; the emulated engine; the engine failing before the side work (the fault
    // wrapper) at tick 4; the engine failing after it at tick 6; the emulated engine whose side
    // work throws at ticks 3 and 8.
    constexpr std::uint64_t fault_at = 4, fail_after_at = 6;
    emulated_engine e_ok(seed), e_fault(seed + 1), e_after(seed + 2), e_throw(seed + 3);
    engine_fault fault;
    fault.tick = [&] { return tick; };
    fault.at_tick = fault_at;
    faulty_replication_engine faulty(e_fault, fault);
    fails_after_side after(e_after, tick, fail_after_at);
    // 0: the CPU; 5 and 6: CPU references resynced where 2 and 3 fall back (their frames' model).
    std::vector<std::unique_ptr<replicator>> reps;
    for (int k = 0; k < 7; ++k) reps.push_back(std::make_unique<replicator>(z.opt));
    reps[1]->set_engine(&e_ok);
    reps[2]->set_engine(&faulty);
    reps[3]->set_engine(&after);
    reps[4]->set_engine(&e_throw);
    emulated_engine* const inner[7] = {nullptr, &e_ok, &e_fault, &e_after, &e_throw, nullptr, nullptr};
    const std::size_t ref_of[7] = {0, 0, 5, 6, 0, 5, 6};
    std::vector<replicator*> all;
    for (const auto& r : reps) all.push_back(r.get());
    const std::vector<replication_request> requests = add_same_clients(all, z.store, 30, 11);
    const std::size_t chunks = (requests.size() + z.opt.clients_per_task - 1) / z.opt.clients_per_task;
    const entity_id watched = z.store.ids()[0];
    std::size_t in_wait = 0, after_frames = 0, thrown = 0;
    for (; tick < 12; ++tick) {
      CAPTURE(tick);
      move_all(z.store, 250);
      REQUIRE_FALSE(z.tracker.update(z.store.columns()).has_value());
      if (tick == fault_at) {
        for (const auto& r : requests) reps[5]->resync(r.client);
      }
      if (tick == fail_after_at) {
        for (const auto& r : requests) reps[6]->resync(r.client);
      }
      std::vector<std::vector<std::vector<std::uint8_t>>> frames(reps.size(), std::vector<std::vector<std::uint8_t>>(requests.size()));
      // What the side work of replicator 0 read: every other one must read the same.
      std::vector<vec3> read_pos;
      std::vector<entity_id> read_visible;
      for (std::size_t r = 0; r < reps.size(); ++r) {
        CAPTURE(r);
        const bool engine_before = reps[r]->on_engine();
        std::atomic<std::size_t> sunk{0}, chunks_done{0};
        std::size_t calls = 0, sunk_at_call = 0, chunks_at_call = 0, side_calls_at_call = 0;
        const std::size_t side_before = inner[r] ? inner[r]->side_calls : 0;
        const bool throws = r == 4 && (tick == 3 || tick == 8);
        const auto work = [&] {
          ++calls;
          sunk_at_call = sunk.load();
          chunks_at_call = chunks_done.load();
          side_calls_at_call = inner[r] ? inner[r]->side_calls : 0;
          const auto p = z.store.positions();
          const std::size_t row = z.tracker.row_of(watched);
          REQUIRE(row != entity_store::npos);
          const auto v = z.tracker.visible(row);
          if (r == 0) {
            read_pos.assign(p.begin(), p.end());
            read_visible.assign(v.begin(), v.end());
          } else {
            CHECK(std::equal(p.begin(), p.end(), read_pos.begin(), read_pos.end(),
                             [](const vec3& a, const vec3& b) { return a.x == b.x && a.y == b.y && a.z == b.z; }));
            CHECK(std::equal(v.begin(), v.end(), read_visible.begin(), read_visible.end()));
          }
          if (throws) throw std::runtime_error("the side work failed");
        };
        const std::function<void()> side = std::ref(work);
        bool threw = false;
        try {
          reps[r]->build_many(
              requests, z.store, z.tracker, tick, tick * 3, &z.pool,
              [&](std::size_t k, std::span<const std::uint8_t> f, const replication_stats&) {
                frames[r][k].assign(f.begin(), f.end());
                ++sunk;
              },
              [&](std::size_t, std::size_t) { ++chunks_done; }, {}, {}, &side);
        } catch (const std::runtime_error& e) {
          threw = true;
          CHECK(std::string(e.what()) == "the side work failed");
        }
        CHECK(threw == throws);
        thrown += threw ? 1 : 0;
        CHECK(calls == 1);
        CHECK(sunk.load() == requests.size());  // every frame, also when the side work threw
        // Did the engine call it inside run(), before any frame?
        const bool by_engine = inner[r] != nullptr && inner[r]->side_calls == side_before + 1;
        const bool want_engine = engine_before && !(r == 2 && tick == fault_at);
        CHECK(by_engine == want_engine);
        if (by_engine) {
          ++in_wait;
          CHECK(side_calls_at_call == side_before + 1);
          CHECK(sunk_at_call == 0);
          CHECK(chunks_at_call == 0);
        } else {
          ++after_frames;
          if (inner[r] != nullptr) CHECK(inner[r]->side_calls == side_before);
          CHECK(sunk_at_call == requests.size());
          CHECK(chunks_at_call == chunks);
        }
        // Who is on the engine afterwards: the side work's failure never gives it up.
        const bool want_on = r == 1 || r == 4 || (r == 2 && tick < fault_at) || (r == 3 && tick < fail_after_at);
        CHECK(reps[r]->on_engine() == want_on);
        // No requests: still once, after (nothing to wait for), with no frame.
        std::size_t empty_calls = 0;
        const auto count = [&] { ++empty_calls; };
        const std::function<void()> count_side = std::ref(count);
        reps[r]->build_many({}, z.store, z.tracker, tick, tick * 3, &z.pool,
                            [&](std::size_t, std::span<const std::uint8_t>, const replication_stats&) { FAIL("a frame"); },
                            {}, {}, {}, &count_side);
        CHECK(empty_calls == 1);
      }
      for (std::size_t r = 1; r < reps.size(); ++r) {
        CAPTURE(r);
        for (std::size_t k = 0; k < requests.size(); ++k) CHECK(frames[r][k] == frames[ref_of[r]][k]);
      }
    }
    CHECK(thrown == 2);
    CHECK(in_wait > 0);
    CHECK(after_frames > 0);
    CHECK(e_fault.side_calls == fault_at);       // ticks 0..3 on the engine
    CHECK(e_after.side_calls == fail_after_at + 1);  // ticks 0..6: the last one called it, then failed
  }
}

TEST_SUITE("zone.engine_faults") {
  TEST_CASE("frames handed on without a copy: held frames stay intact, and with every kept buffer held they are copied") {
    // build_many's frame_share: the engine keeps up to four buffers while the caller holds their
    // frames; this caller holds every frame it is given, so ticks 0-3 share and later ticks fall
    // back to the sink (a copy), all frames equal to the CPU replicator's.
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    random_zone z(seed, 200, 200, 1000000);
    z.opt.clients_per_task = 4;
    replicator cpu(z.opt), dev(z.opt);
    emulated_engine engine(seed);
    dev.set_engine(&engine);
    replicator* const both[] = {&cpu, &dev};
    const std::vector<replication_request> requests = add_same_clients(both, z.store, 20, 9);
    std::vector<std::pair<net::shared_frame, std::vector<std::uint8_t>>> held;  // every shared frame, and its bytes
    for (std::uint64_t tick = 0; tick < 7; ++tick) {
      CAPTURE(tick);
      move_all(z.store, 200);
      REQUIRE_FALSE(z.tracker.update(z.store.columns()).has_value());
      std::vector<std::vector<std::uint8_t>> want(requests.size()), got(requests.size());
      std::atomic<int> shared{0}, sunk{0};
      cpu.build_many(requests, z.store, z.tracker, tick, tick * 3, &z.pool,
                     [&](std::size_t k, std::span<const std::uint8_t> f, const replication_stats&) { want[k].assign(f.begin(), f.end()); });
      std::vector<net::shared_frame> frames(requests.size());
      dev.build_many(
          requests, z.store, z.tracker, tick, tick * 3, &z.pool,
          [&](std::size_t k, std::span<const std::uint8_t> f, const replication_stats&) {
            got[k].assign(f.begin(), f.end());
            ++sunk;
          },
          {}, {},
          [&](std::size_t k, net::shared_frame f, const replication_stats&) {
            got[k].assign(f.bytes().begin(), f.bytes().end());
            frames[k] = std::move(f);
            ++shared;
          });
      REQUIRE(dev.on_engine());
      CHECK(got == want);
      CHECK(shared.load() == (tick < 4 ? 20 : 0));
      CHECK(sunk.load() == (tick < 4 ? 0 : 20));
      for (std::size_t k = 0; k < frames.size(); ++k) {
        if (frames[k]) held.emplace_back(frames[k], got[k]);
      }
      for (const auto& [frame, bytes] : held) CHECK(std::ranges::equal(frame.bytes(), bytes));
    }
    // Released: the engine shares again.
    held.clear();
    REQUIRE_FALSE(z.tracker.update(z.store.columns()).has_value());
    std::atomic<int> shared{0};
    dev.build_many(requests, z.store, z.tracker, 7, 21, &z.pool, [](std::size_t, std::span<const std::uint8_t>, const replication_stats&) {}, {}, {},
                   [&](std::size_t, net::shared_frame, const replication_stats&) { ++shared; });
    CHECK(shared.load() == 20);
  }

  TEST_CASE("the GPU replication engine failing mid-run: the same tick on the CPU, every client reset, frames exact") {
    namespace cb = interest::category_bits;
    for (const std::uint64_t at : {0u, 1u, 6u, 17u}) {
      const std::uint64_t seed = zone::test::fresh_seed();
      CAPTURE(seed);
      CAPTURE(at);
      random_zone z(seed, 300, 250, 7);
      z.opt.byte_budget = 700;  // small enough that enters and updates are deferred
      replicator cpu(z.opt), dev(z.opt);
      emulated_engine inner(seed);
      std::uint64_t tick = 0;
      engine_fault fault;
      fault.tick = [&] { return tick; };
      fault.at_tick = at;
      faulty_replication_engine engine(inner, fault);
      dev.set_engine(&engine);
      replicator* const both[] = {&cpu, &dev};
      const std::vector<replication_request> requests = add_same_clients(both, z.store, 40, 7);
      std::vector<std::set<std::uint32_t>> held(requests.size());  // each client's view, from its frames
      std::vector<std::vector<std::uint8_t>> want(requests.size()), got(requests.size());
      std::uint64_t deferred = 0, compared = 0;
      for (; tick < 30; ++tick) {
        CAPTURE(tick);
        move_all(z.store, 250);
        REQUIRE_FALSE(z.tracker.update(z.store.columns()).has_value());
        if (tick == at) {
          for (const auto& r : requests) cpu.resync(r.client);
        }
        const auto sink = [](std::vector<std::vector<std::uint8_t>>& into) {
          return [&into](std::size_t k, std::span<const std::uint8_t> f, const replication_stats&) {
            into[k].assign(f.begin(), f.end());
          };
        };
        cpu.build_many(requests, z.store, z.tracker, tick, tick * 3, &z.pool, sink(want));
        dev.build_many(requests, z.store, z.tracker, tick, tick * 3, &z.pool, sink(got));
        REQUIRE(dev.on_engine() == (tick < at));
        REQUIRE(engine.fault().fired() == (tick >= at));
        if (tick >= at) CHECK(dev.engine_error().find("CUDA error") != std::string::npos);
        for (std::size_t k = 0; k < requests.size(); ++k) {
          CHECK(got[k] == want[k]);
          ++compared;
          net::decoder_options big;
          big.max_frame_bytes = std::size_t{4} << 20;
          const auto msg = net::decode_frame(got[k], big);
          REQUIRE(msg.value);
          const auto* m = std::get_if<net::tick_update_msg>(&*msg.value);
          REQUIRE(m != nullptr);
          CHECK(m->reset == (tick == at || tick == 0));  // a new client's first frame, and the fallback's tick
          if (m->reset) held[k].clear();
          for (const std::uint32_t id : m->leaves) CHECK(held[k].erase(id) == 1);
          for (const auto& e : m->enters) CHECK(held[k].insert(e.id).second);
          for (const auto& u : m->updates) CHECK(held[k].count(u.id) == 1);
          if (m->deferred) deferred += m->deferred->enters + m->deferred->updates;
          // What the client holds is the server's view of it, exactly.
          CHECK(held[k].size() == dev.view_size(requests[k].client));
          CHECK(dev.view_hash(requests[k].client) == cpu.view_hash(requests[k].client));
          if (m->digest) {
            CHECK(m->digest->count == held[k].size());
            std::uint64_t h = 0;
            for (const std::uint32_t id : held[k]) h += net::digest_mix(id);
            CHECK(m->digest->hash == h);
          }
        }
      }
      CHECK(compared == 30 * requests.size());
      CHECK(deferred > 0);  // the budget cut frames, before and after the fault
    }
  }
}
