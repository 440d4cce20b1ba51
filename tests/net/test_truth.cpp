// The ground-truth stream's codec (net/truth.h): round trips with and without the layout; the
// encoder's frames (whole layout, changes, positions) applied by a reader give the writer's
// columns exactly, tick after tick, on random worlds; every malformed body rejected with a
// reason, never a crash or an over-read, the reader's layout untouched.
#include <doctest/doctest.h>

#include "../common/seeds.h"

#include <algorithm>
#include <cstring>
#include <random>

#include "net/truth.h"

using namespace zone::net;
using zone::test::fresh_seed;

namespace {

/// A writer's columns (what a server's entity store holds), mutated at random.
struct columns {
  std::vector<float> pos, aoi, presence;
  std::vector<std::uint32_t> ids, cls, sees;
  std::vector<std::uint8_t> kinds;
  [[nodiscard]] std::size_t size() const { return ids.size(); }
  [[nodiscard]] truth::layout_view view() const { return {ids, aoi, presence, cls, sees, kinds}; }
  void push(std::mt19937_64& rng, std::uint32_t id) {
    std::uniform_real_distribution<float> u(-500, 500);
    for (int a = 0; a < 3; ++a) pos.push_back(u(rng)), aoi.push_back(u(rng)), presence.push_back(u(rng));
    ids.push_back(id);
    cls.push_back(1u << (rng() % 4));
    sees.push_back(static_cast<std::uint32_t>(rng() % 16));
    kinds.push_back(static_cast<std::uint8_t>(rng() % 3));
  }
  void erase(std::size_t k) {  // the store's swap-remove
    const std::size_t last = size() - 1;
    for (int a = 0; a < 3; ++a)
      pos[3 * k + a] = pos[3 * last + a], aoi[3 * k + a] = aoi[3 * last + a],
                  presence[3 * k + a] = presence[3 * last + a];
    ids[k] = ids[last], cls[k] = cls[last], sees[k] = sees[last], kinds[k] = kinds[last];
    pos.resize(3 * last), aoi.resize(3 * last), presence.resize(3 * last);
    ids.pop_back(), cls.pop_back(), sees.pop_back(), kinds.pop_back();
  }
  /// Changes one field of row k (or writes the value it has: no change).
  void touch(std::mt19937_64& rng, std::size_t k) {
    switch (rng() % 6) {
      case 0: cls[k] = rng() % 3 ? 1u << (rng() % 4) : cls[k]; break;
      case 1: sees[k] = static_cast<std::uint32_t>(rng() % 16); break;
      case 2: aoi[3 * k + rng() % 3] = static_cast<float>(rng() % 50); break;
      case 3: presence[3 * k + rng() % 3] = static_cast<float>(rng() % 5) * 0.5f; break;
      case 4: kinds[k] = static_cast<std::uint8_t>(rng() % 3); break;
      default: aoi[3 * k] = -0.0f; break;  // bit for bit: -0 differs from 0
    }
  }
};

bool same_bits(const std::vector<float>& a, const std::vector<float>& b) {
  return a.size() == b.size() && (a.empty() || std::memcmp(a.data(), b.data(), 4 * a.size()) == 0);
}

/// Rows whose non-position fields differ bit for bit (the same ids assumed).
std::size_t rows_differing(const columns& a, const columns& b) {
  std::size_t d = 0;
  for (std::size_t k = 0; k < a.size(); ++k) {
    d += a.cls[k] != b.cls[k] || a.sees[k] != b.sees[k] || a.kinds[k] != b.kinds[k] ||
         std::memcmp(&a.aoi[3 * k], &b.aoi[3 * k], 12) != 0 ||
         std::memcmp(&a.presence[3 * k], &b.presence[3 * k], 12) != 0;
  }
  return d;
}

/// The reader holds exactly the writer's columns.
void check_reader(const truth::tick_frame& f, const columns& c) {
  REQUIRE(f.count == c.size());
  CHECK(same_bits(f.positions, c.pos));
  CHECK(f.ids == c.ids);
  CHECK(same_bits(f.aoi_half, c.aoi));
  CHECK(same_bits(f.presence_half, c.presence));
  CHECK(f.classes == c.cls);
  CHECK(f.sees == c.sees);
  CHECK(f.kinds == c.kinds);
}

}  // namespace

TEST_SUITE("net.truth") {
  TEST_CASE("truth frames round-trip; a frame without the layout keeps the last one") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    std::mt19937_64 rng(seed);
    for (const std::size_t n : {std::size_t{0}, std::size_t{1}, std::size_t{3}, std::size_t{1000}}) {
      CAPTURE(n);
      std::vector<float> pos(3 * n), aoi(3 * n), body(3 * n);
      std::vector<std::uint32_t> ids(n), cls(n), sees(n);
      std::vector<std::uint8_t> kinds(n);
      std::uniform_real_distribution<float> u(-1000, 1000);
      for (auto& x : pos) x = u(rng);
      for (auto& x : aoi) x = u(rng);
      for (auto& x : body) x = u(rng);
      for (std::size_t k = 0; k < n; ++k) {
        ids[k] = static_cast<std::uint32_t>(rng()), cls[k] = static_cast<std::uint32_t>(rng());
        sees[k] = static_cast<std::uint32_t>(rng()), kinds[k] = static_cast<std::uint8_t>(rng() % 3);
      }
      const truth::layout_view lv{ids, aoi, body, cls, sees, kinds};
      std::vector<std::uint8_t> bytes;
      truth::encode_tick(bytes, 77, pos, &lv);
      std::uint32_t len = 0;
      std::memcpy(&len, bytes.data(), 4);
      REQUIRE(len == bytes.size() - 4);
      CHECK(bytes.size() % 4 == 0);
      truth::tick_frame f;
      REQUIRE_FALSE(truth::decode_tick(std::span(bytes).subspan(4), f).has_value());
      CHECK(f.tick == 77);
      CHECK(f.count == n);
      CHECK(f.has_layout);
      CHECK_FALSE(f.first_step);
      CHECK(f.positions == pos);
      CHECK(f.ids == ids);
      CHECK(f.aoi_half == aoi);
      CHECK(f.presence_half == body);
      CHECK(f.classes == cls);
      CHECK(f.sees == sees);
      CHECK(f.kinds == kinds);
      // Positions only: 12 bytes an entity plus the header; the layout stays.
      for (auto& x : pos) x = u(rng);
      truth::encode_tick(bytes, 78, pos, nullptr);
      CHECK(bytes.size() == truth::header_bytes + 12 * n);
      REQUIRE_FALSE(truth::decode_tick(std::span(bytes).subspan(4), f).has_value());
      CHECK(f.tick == 78);
      CHECK_FALSE(f.has_layout);
      CHECK(f.positions == pos);
      CHECK(f.ids == ids);
      CHECK(f.kinds == kinds);
      // The server's first step: a flag on the frame, nothing else changed; the next frame has none.
      truth::encode_tick(bytes, 1, pos, &lv);
      truth::mark_first_step(bytes);
      REQUIRE_FALSE(truth::decode_tick(std::span(bytes).subspan(4), f).has_value());
      CHECK(f.first_step);
      CHECK(f.has_layout);
      CHECK(f.tick == 1);
      CHECK(f.ids == ids);
      truth::encode_tick(bytes, 2, pos, nullptr);
      REQUIRE_FALSE(truth::decode_tick(std::span(bytes).subspan(4), f).has_value());
      CHECK_FALSE(f.first_step);
    }
  }

  TEST_CASE(
      "the encoder sends changes when few rows changed; a reader applying its frames holds the writer's columns at every tick") {
    // Random worlds, 400 ticks each: moves every tick; some ticks nothing else, some a few rows
    // changed (under the cap: changes), some many (over it: the whole layout), some a spawn or a
    // despawn (the ids change: the whole layout), some a subscriber joining (forced layout). A
    // reader from the start and one joining mid-stream (from a forced layout) both hold the
    // writer's columns after every frame; the kind and size of every frame is the one expected.
    for (const std::size_t n0 : {std::size_t{0}, std::size_t{5}, std::size_t{64}, std::size_t{3000}}) {
      const std::uint64_t seed = fresh_seed();
      CAPTURE(seed);
      CAPTURE(n0);
      std::mt19937_64 rng(seed);
      columns c;
      std::uint32_t next_id = 1;
      for (std::size_t k = 0; k < n0; ++k) c.push(rng, next_id++);
      truth::encoder enc;
      truth::tick_frame early, late;
      bool late_joined = false;
      std::size_t counts[3] = {0, 0, 0}, changed_rows = 0;
      std::vector<std::uint8_t> bytes;
      for (std::uint64_t tick = 0; tick < 400; ++tick) {
        CAPTURE(tick);
        std::uniform_real_distribution<float> step(-2, 2);
        for (auto& x : c.pos) x += step(rng);
        const columns before = c;
        bool ids_changed = false, force = false;
        const auto r = rng() % 10;
        if (tick > 0 && r < 4 && c.size() > 0) {  // a few rows touched (maybe to the same values)
          const std::size_t touches = 1 + rng() % std::max<std::size_t>(1, c.size() / 6);
          for (std::size_t t = 0; t < touches; ++t) c.touch(rng, rng() % c.size());
        } else if (tick > 0 && r == 4 && c.size() > 0) {  // many rows: over the cap
          for (std::size_t k = 0; k < c.size(); ++k) c.sees[k] ^= (rng() % 2 ? 1u : 0u);
        } else if (tick > 0 && r == 5) {  // a spawn
          c.push(rng, next_id++);
          ids_changed = true;
        } else if (tick > 0 && r == 6 && c.size() > 0) {  // a despawn
          c.erase(rng() % c.size());
          ids_changed = true;
        } else if (tick > 0 && r == 7) {  // a subscriber joins
          force = true;
        }
        // The writer tells the encoder whenever its columns may have changed (as the store's
        // layout_version does), and now and then when they did not.
        const bool maybe_changed = tick == 0 || ids_changed || r < 5 || rng() % 8 == 0;
        const auto lv = c.view();
        const auto sent = enc.encode(bytes, tick, c.pos, maybe_changed ? &lv : nullptr, force);
        const std::size_t n = c.size();
        const std::size_t differing = ids_changed || tick == 0 ? 0 : rows_differing(before, c);
        using kind = truth::encoder::sent;
        const kind expect = tick == 0 || ids_changed || force || differing > n / truth::max_changes_divisor
                                ? kind::layout
                            : differing > 0 ? kind::changes
                                            : kind::positions;
        REQUIRE(sent == expect);
        ++counts[static_cast<int>(sent)];
        std::size_t expect_bytes = truth::header_bytes + 12 * n;
        if (sent == kind::layout) expect_bytes += 36 * n + ((n + 3) & ~std::size_t{3});
        if (sent == kind::changes) {
          CHECK(enc.last_changes() == differing);
          changed_rows += differing;
          expect_bytes += 4 + 36 * differing + ((differing + 3) & ~std::size_t{3});
        }
        CHECK(bytes.size() == expect_bytes);
        const auto body = std::span(bytes).subspan(4);
        REQUIRE_FALSE(truth::decode_tick(body, early).has_value());
        CHECK(early.tick == tick);
        CHECK(early.has_layout == (sent == kind::layout));
        CHECK(early.has_changes == (sent == kind::changes));
        check_reader(early, c);
        // The late reader joins at the first forced layout after tick 100; before, it reads nothing.
        if (!late_joined && tick > 100 && sent == kind::layout) late_joined = true;
        if (late_joined) {
          REQUIRE_FALSE(truth::decode_tick(body, late).has_value());
          check_reader(late, c);
        }
      }
      MESSAGE(n0 << " entities at first: " << counts[2] << " frames with the layout, " << counts[1] << " with changes ("
                 << changed_rows << " rows), " << counts[0] << " positions only");
      CHECK(counts[2] > 20);
      CHECK(counts[0] > 20);
      if (n0 >= 64) CHECK(counts[1] > 50);  // (with 5 entities, the cap is 1 row)
      CHECK(late_joined);
    }
  }

  TEST_CASE("a reader that missed a frame which changed the layout stops at the next frame") {
    std::mt19937_64 rng(fresh_seed());
    columns c;
    for (std::uint32_t k = 0; k < 40; ++k) c.push(rng, k + 1);
    truth::encoder enc;
    std::vector<std::uint8_t> f0, f1, f2, f3;
    auto lv = c.view();
    REQUIRE(enc.encode(f0, 1, c.pos, &lv, false) == truth::encoder::sent::layout);
    c.cls[7] ^= 3;
    lv = c.view();
    REQUIRE(enc.encode(f1, 2, c.pos, &lv, false) == truth::encoder::sent::changes);
    REQUIRE(enc.encode(f2, 3, c.pos, nullptr, false) == truth::encoder::sent::positions);
    c.sees[9] ^= 1;
    lv = c.view();
    REQUIRE(enc.encode(f3, 4, c.pos, &lv, false) == truth::encoder::sent::changes);
    const auto body = [](const std::vector<std::uint8_t>& b) { return std::span(b).subspan(4); };
    // In order: fine.
    truth::tick_frame ok;
    for (const auto* f : {&f0, &f1, &f2, &f3}) REQUIRE_FALSE(truth::decode_tick(body(*f), ok).has_value());
    CHECK(ok.classes == c.cls);
    CHECK(ok.sees == c.sees);
    // f1 (changes) missed: the positions-only frame after it and the next changes are refused,
    // and the reader's columns stay those of f0.
    truth::tick_frame r;
    REQUIRE_FALSE(truth::decode_tick(body(f0), r).has_value());
    const truth::tick_frame kept = r;
    const auto e2 = truth::decode_tick(body(f2), r);
    REQUIRE(e2.has_value());
    CHECK(e2->find("missed") != std::string::npos);
    const auto e3 = truth::decode_tick(body(f3), r);
    REQUIRE(e3.has_value());
    CHECK(e3->find("missed") != std::string::npos);
    CHECK(r.tick == kept.tick);
    CHECK(r.classes == kept.classes);
    CHECK(r.sees == kept.sees);
    // Changes or positions before any layout.
    truth::tick_frame fresh;
    CHECK(truth::decode_tick(body(f1), fresh).value_or("").find("no layout") != std::string::npos);
    CHECK(truth::decode_tick(body(f2), fresh).value_or("").find("no layout") != std::string::npos);
    // A refusal reads as its text.
    std::vector<std::uint8_t> refusal;
    truth::encode_refusal(refusal, "at most 4 subscribers (--oracle-subscribers)");
    CHECK(truth::decode_tick(body(refusal), fresh).value_or("") ==
          "the server refused this subscriber: at most 4 subscribers (--oracle-subscribers)");
  }

  TEST_CASE("malformed changes are rejected with a reason; the reader's layout is left as it was") {
    std::mt19937_64 rng(fresh_seed());
    columns c;
    for (std::uint32_t k = 0; k < 12; ++k) c.push(rng, k + 1);
    truth::encoder enc;
    std::vector<std::uint8_t> full, ch;
    auto lv = c.view();
    REQUIRE(enc.encode(full, 1, c.pos, &lv, false) == truth::encoder::sent::layout);
    c.cls[2] ^= 1, c.aoi[3 * 5] += 1, c.kinds[9] = c.kinds[9] == 2 ? 1 : 2;
    lv = c.view();
    REQUIRE(enc.encode(ch, 2, c.pos, &lv, false) == truth::encoder::sent::changes);
    REQUIRE(enc.last_changes() == 3);
    truth::tick_frame base;
    REQUIRE_FALSE(truth::decode_tick(std::span(full).subspan(4), base).has_value());
    const std::vector<std::uint8_t> body(ch.begin() + 4, ch.end());
    const std::size_t m_at = truth::header_bytes - 4 + 12 * 12, idx_at = m_at + 4;
    const auto rejected = [&](const std::vector<std::uint8_t>& b) {
      truth::tick_frame f = base;
      const auto err = truth::decode_tick(b, f);
      CHECK(f.tick == base.tick);
      CHECK(f.positions == base.positions);
      CHECK(f.classes == base.classes);
      CHECK(same_bits(f.aoi_half, base.aoi_half));
      CHECK(f.kinds == base.kinds);
      return err.has_value();
    };
    {  // the frame itself applies
      truth::tick_frame f = base;
      REQUIRE_FALSE(truth::decode_tick(body, f).has_value());
      check_reader(f, c);
      CHECK(f.changed == std::vector<std::uint32_t>{2, 5, 9});
    }
    for (std::size_t cut = 0; cut < body.size(); ++cut)
      CHECK(rejected({body.begin(), body.begin() + static_cast<std::ptrdiff_t>(cut)}));
    auto bad = body;
    bad.push_back(0);  // a byte too many
    CHECK(rejected(bad));
    const auto put32 = [](std::vector<std::uint8_t>& b, std::size_t at, std::uint32_t v) {
      std::memcpy(b.data() + at, &v, 4);
    };
    bad = body;
    put32(bad, idx_at + 4, 2);  // indices 2, 2, 9: not ascending
    CHECK(rejected(bad));
    bad = body;
    put32(bad, idx_at + 4, 1);  // 2, 1, 9
    CHECK(rejected(bad));
    bad = body;
    put32(bad, idx_at + 8, 12);  // index == count
    CHECK(rejected(bad));
    bad = body;
    put32(bad, idx_at + 8, 0xffffffffu);
    CHECK(rejected(bad));
    bad = body;
    put32(bad, m_at, 13);  // more changes than entities
    CHECK(rejected(bad));
    bad = body;
    put32(bad, m_at, 0xffffffffu);
    CHECK(rejected(bad));
    bad = body;
    put32(bad, m_at, 2);  // a count that disagrees with the size
    CHECK(rejected(bad));
    bad = body;
    put32(bad, 4, truth::flag_layout | truth::flag_changes);  // both
    CHECK(rejected(bad));
    bad = body;
    put32(bad, 20, base.layout_seq);  // not the next layout
    CHECK(rejected(bad));
    bad = body;
    put32(bad, 16, 11);  // another count
    CHECK(rejected(bad));
    // Random bytes after a valid header never crash.
    std::mt19937_64 r2(fresh_seed());
    for (int i = 0; i < 3000; ++i) {
      auto junk = body;
      for (int k = 0; k < 3; ++k) junk[r2() % junk.size()] = static_cast<std::uint8_t>(r2());
      if (r2() % 3 == 0) junk.resize(r2() % (junk.size() + 8), 0);
      truth::tick_frame f = base;
      (void)truth::decode_tick(junk, f);
    }
  }

  TEST_CASE("carried sets ride along any frame, one frame only; malformed carried sections are rejected") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    std::mt19937_64 rng(seed);
    columns c;
    for (std::uint32_t id = 1; id <= 50; ++id) c.push(rng, id);
    // Random carried sets: observers ascending, each one's targets ascending (some with none).
    std::vector<std::uint32_t> obs, off{0}, targets;
    for (std::uint32_t id = 1; id <= 50; ++id) {
      if (rng() % 5 != 0) continue;
      obs.push_back(id);
      for (std::uint32_t t = 1; t <= 60; ++t) {
        if (rng() % 4 == 0) targets.push_back(t);  // ids the layout lacks (51..60) too: the reader ignores them
      }
      off.push_back(static_cast<std::uint32_t>(targets.size()));
    }
    obs.push_back(51), off.push_back(off.back());  // an observer carried with no targets
    const truth::carried_view cv{obs, off, targets};
    const auto check_carried = [&](const truth::tick_frame& f) {
      CHECK(f.carried_observers == obs);
      CHECK(f.carried_off == off);
      CHECK(f.carried_targets == targets);
    };
    truth::encoder enc;
    truth::tick_frame f;
    std::vector<std::uint8_t> bytes;
    const auto lv = c.view();
    // The whole layout, positions only, changes: each with the carried sets, then without.
    CHECK(enc.encode(bytes, 1, c.pos, &lv, false, &cv) == truth::encoder::sent::layout);
    REQUIRE_FALSE(truth::decode_tick(std::span(bytes).subspan(4), f).has_value());
    check_reader(f, c);
    check_carried(f);
    CHECK(enc.encode(bytes, 2, c.pos, nullptr, false, &cv) == truth::encoder::sent::positions);
    REQUIRE_FALSE(truth::decode_tick(std::span(bytes).subspan(4), f).has_value());
    check_carried(f);
    c.cls[7] ^= 8;
    const auto lv2 = c.view();
    CHECK(enc.encode(bytes, 3, c.pos, &lv2, false, &cv) == truth::encoder::sent::changes);
    REQUIRE_FALSE(truth::decode_tick(std::span(bytes).subspan(4), f).has_value());
    check_reader(f, c);
    check_carried(f);
    const std::vector<std::uint8_t> with = bytes;
    CHECK(enc.encode(bytes, 4, c.pos, nullptr, false) == truth::encoder::sent::positions);
    REQUIRE_FALSE(truth::decode_tick(std::span(bytes).subspan(4), f).has_value());
    CHECK(f.carried_observers.empty());  // a frame's own: gone with the next frame
    CHECK(f.carried_targets.empty());
    // Malformed: every cut, observers or targets out of order, counts that do not sum.
    const std::vector<std::uint8_t> body(with.begin() + 4, with.end());
    const auto decodes = [&](const std::vector<std::uint8_t>& b) {
      truth::tick_frame g;
      truth::encode_tick(bytes, 2, c.pos, &lv);  // a reader that holds the layout before it
      REQUIRE_FALSE(truth::decode_tick(std::span(bytes).subspan(4), g).has_value());
      g.layout_seq = f.layout_seq - 1;  // the changes apply to the layout just before them
      return !truth::decode_tick(b, g).has_value();
    };
    REQUIRE(decodes(body));
    for (std::size_t cut = body.size() - (8 + 8 * obs.size() + 4 * targets.size()); cut < body.size(); ++cut) {
      CHECK_FALSE(decodes(std::vector<std::uint8_t>(body.begin(), body.begin() + static_cast<std::ptrdiff_t>(cut))));
    }
    const std::size_t at = body.size() - (8 * obs.size() + 4 * targets.size());  // the observers' ids
    const auto with_word = [&](std::size_t pos, std::uint32_t v) {
      auto b = body;
      std::memcpy(b.data() + pos, &v, 4);
      return b;
    };
    REQUIRE(obs.size() >= 2);
    CHECK_FALSE(decodes(with_word(at + 4, obs[0])));                   // the second observer not above the first
    CHECK_FALSE(decodes(with_word(at + 4 * obs.size(), off[1] + 1)));  // the first count one too many
    CHECK_FALSE(decodes(with_word(at - 8, 0)));  // no observers, but the flag says carried sets follow
    const auto first_with_two =
        std::adjacent_find(off.begin(), off.end(), [](std::uint32_t a, std::uint32_t b) { return b >= a + 2; });
    REQUIRE(first_with_two != off.end());
    const std::size_t t0 = at + 8 * obs.size() + 4 * *first_with_two;
    CHECK_FALSE(decodes(with_word(t0 + 4, targets[*first_with_two])));  // a target repeated
  }

  TEST_CASE("malformed truth frames are rejected with a reason") {
    std::vector<float> pos{1, 2, 3, 4, 5, 6};
    std::vector<std::uint32_t> ids{1, 2}, cls{1, 1}, sees{2, 2};
    std::vector<float> ext(6, 1);
    std::vector<std::uint8_t> kinds{0, 1};
    const truth::layout_view lv{ids, ext, ext, cls, sees, kinds};
    std::vector<std::uint8_t> bytes;
    truth::encode_tick(bytes, 5, pos, &lv);
    const std::vector<std::uint8_t> body(bytes.begin() + 4, bytes.end());
    truth::tick_frame f;
    // Every truncation.
    for (std::size_t cut = 0; cut < body.size(); ++cut) {
      CHECK(truth::decode_tick(std::span(body).first(cut), f).has_value());
    }
    // Bad magic, unknown flags, a count that disagrees with the size.
    auto bad = body;
    bad[0] ^= 1;
    CHECK(truth::decode_tick(bad, f).value_or("") == "not a truth frame (bad magic)");
    bad = body;
    bad[4] |= 2;
    CHECK(truth::decode_tick(bad, f).has_value());
    bad = body;
    bad[4] |= 16;  // a flag no reader knows
    CHECK(truth::decode_tick(bad, f).value_or("").find("unknown flags") != std::string::npos);
    bad = body;
    bad[16] = 200;
    CHECK(truth::decode_tick(bad, f).has_value());
    // A frame without a layout whose count differs from the last layout's.
    truth::tick_frame fresh;
    truth::encode_tick(bytes, 6, pos, nullptr);
    CHECK(truth::decode_tick(std::span(bytes).subspan(4), fresh).has_value());
    // Random bytes never crash.
    std::mt19937_64 rng(fresh_seed());
    for (int i = 0; i < 2000; ++i) {
      std::vector<std::uint8_t> junk(rng() % 80);
      for (auto& b : junk) b = static_cast<std::uint8_t>(rng());
      if (rng() % 2 && junk.size() >= 4) std::memcpy(junk.data(), &truth::magic, 4);
      (void)truth::decode_tick(junk, f);
    }
    CHECK(truth::decode_tick(body, f) == std::nullopt);
  }
}
