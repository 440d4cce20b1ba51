// The ground-truth stream's codec (net/truth.h): round trips with and without the layout, and
// every malformed body rejected with a reason, never a crash or an over-read.
#include <doctest/doctest.h>

#include "../common/seeds.h"

#include <cstring>
#include <random>

#include "net/truth.h"

using namespace zone::net;
using zone::test::fresh_seed;

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
    }
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
