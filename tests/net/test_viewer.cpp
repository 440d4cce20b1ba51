// The live viewer (net/viewer.h): its wire format against a reference decoding on random
// snapshots, and its routes and WebSocket sessions over loopback (caps, hostile and stalled pages).
#include <utility>  // before Asio: GCC 12 in C++20 mode needs it first

#include <doctest/doctest.h>

#include <boost/asio.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/websocket.hpp>
#include <sys/socket.h>

#include <chrono>
#include <cmath>
#include <cstring>
#include <map>
#include <random>
#include <set>
#include <thread>

#include "loopback_client.h"
#include "ws_client.h"
#include "net/metrics.h"
#include "net/viewer.h"

using namespace zone::net;
using zone::net::testing::http_get;
using zone::net::testing::http_request;
using zone::net::testing::at;
using zone::net::testing::eventually;
using zone::net::testing::request_bytes;
using zone::net::testing::ws_client;

namespace {

std::shared_ptr<viewer_snapshot> random_snapshot(std::mt19937_64& rng, std::size_t n, float side) {
  auto s = std::make_shared<viewer_snapshot>();
  s->tick = rng() % 100000;
  s->world_hi[0] = s->world_hi[1] = side;
  std::uniform_real_distribution<float> coord(0, side);
  for (std::size_t i = 0; i < n; ++i) {
    s->ids.push_back(static_cast<std::uint32_t>(i + 1 + (rng() % 7) * (1u << 20)));
    s->x.push_back(coord(rng));
    s->y.push_back(coord(rng));
    s->visibility.push_back(static_cast<std::uint8_t>(1 + rng() % 4));
    s->kind.push_back(static_cast<std::uint8_t>(rng() % 3));
  }
  return s;
}


bool inside(const viewer_snapshot& s, std::size_t i, const viewer_request& r) {
  return s.x[i] >= r.x0 && s.x[i] <= r.x1 && s.y[i] >= r.y0 && s.y[i] <= r.y1;
}


}  // namespace

TEST_SUITE("net.viewer") {
  TEST_CASE("view requests: well-formed ones parse, malformed ones are refused, garbage never crashes") {
    const viewer_request good{10, 20, 30, 40, 12345, 5000};
    const auto ok = parse_viewer_request(request_bytes(good));
    REQUIRE(ok);
    CHECK(ok->x0 == 10);
    CHECK(ok->y1 == 40);
    CHECK(ok->selected == 12345);
    CHECK(ok->max_points == 5000);
    auto b = request_bytes(good);
    CHECK_FALSE(parse_viewer_request(std::span(b).first(27)));
    b.push_back(0);
    CHECK_FALSE(parse_viewer_request(b));
    CHECK_FALSE(parse_viewer_request(request_bytes(good, 2)));
    CHECK_FALSE(parse_viewer_request(request_bytes({30, 20, 10, 40, 0, 1})));  // x0 > x1
    CHECK_FALSE(parse_viewer_request(request_bytes({10, 20, 10, 40, 0, 1})));  // empty
    CHECK_FALSE(parse_viewer_request(request_bytes({NAN, 20, 30, 40, 0, 1})));
    CHECK_FALSE(parse_viewer_request(request_bytes({10, 20, INFINITY, 40, 0, 1})));
    CHECK_FALSE(parse_viewer_request(request_bytes({10, 20, 30, 40, 0, viewer_max_points + 1})));
    std::mt19937_64 rng(std::random_device{}());
    for (int k = 0; k < 20000; ++k) {
      std::vector<std::uint8_t> g(rng() % 40);
      for (auto& c : g) c = static_cast<std::uint8_t>(rng());
      if (!g.empty() && rng() % 2) g[0] = viewer_request_type;
      if (const auto r = parse_viewer_request(g)) {
        CHECK(g.size() == viewer_request_bytes);
        CHECK((std::isfinite(r->x0) && r->x0 < r->x1 && r->y0 < r->y1));
      }
    }
  }

  TEST_CASE("entities frames hold exactly the entities in the viewport, quantized within a step") {
    std::mt19937_64 rng(std::random_device{}());
    for (int round = 0; round < 30; ++round) {
      const std::size_t n = rng() % 3000;
      const auto s = random_snapshot(rng, n, 1000);
      std::uniform_real_distribution<float> c(-100, 1100);
      float a = c(rng), b = c(rng), d = c(rng), e = c(rng);
      if (a == b || d == e) continue;
      const viewer_request r{std::min(a, b), std::min(d, e), std::max(a, b), std::max(d, e), 0, 1u << 20};
      std::vector<std::uint8_t> out;
      encode_viewer_view(*s, r, 64, out);
      REQUIRE(out.size() >= viewer_frame_header_bytes);
      CHECK(out[0] == viewer_frame_entities);
      CHECK(at<std::uint32_t>(out, 4) == static_cast<std::uint32_t>(s->tick));
      CHECK(at<std::uint32_t>(out, 8) == n);
      const auto count = at<std::uint32_t>(out, 12);
      REQUIRE(out.size() == viewer_frame_header_bytes + count * viewer_entity_record_bytes);
      std::map<std::uint32_t, std::size_t> expected;
      for (std::size_t i = 0; i < n; ++i) {
        if (inside(*s, i, r)) expected[s->ids[i]] = i;
      }
      REQUIRE(count == expected.size());
      const float stepx = (r.x1 - r.x0) / 65535, stepy = (r.y1 - r.y0) / 65535;
      for (std::uint32_t k = 0; k < count; ++k) {
        const std::size_t o = viewer_frame_header_bytes + k * viewer_entity_record_bytes;
        const auto it = expected.find(at<std::uint32_t>(out, o));
        REQUIRE(it != expected.end());
        const std::size_t i = it->second;
        const float x = r.x0 + at<std::uint16_t>(out, o + 4) * stepx, y = r.y0 + at<std::uint16_t>(out, o + 6) * stepy;
        CHECK(std::fabs(x - s->x[i]) <= stepx * 0.51f + 1e-3f);
        CHECK(std::fabs(y - s->y[i]) <= stepy * 0.51f + 1e-3f);
        CHECK(out[o + 8] == s->visibility[i]);
        CHECK(out[o + 9] == s->kind[i]);
        expected.erase(it);  // each once
      }
      CHECK(expected.empty());
    }
  }

  TEST_CASE("beyond the point budget the frame is a density grid whose cells count the entities") {
    std::mt19937_64 rng(std::random_device{}());
    const auto s = random_snapshot(rng, 5000, 1000);
    const viewer_request r{100, 200, 900, 700, 0, 100};
    std::vector<std::uint8_t> out;
    const std::uint32_t g = 16;
    encode_viewer_view(*s, r, g, out);
    REQUIRE(out[0] == viewer_frame_density);
    CHECK(at<std::uint16_t>(out, 2) == g);
    REQUIRE(out.size() == viewer_frame_header_bytes + g * g * 2);
    std::vector<std::uint32_t> ref(g * g, 0);
    std::uint32_t in = 0;
    for (std::size_t i = 0; i < s->ids.size(); ++i) {
      if (!inside(*s, i, r)) continue;
      ++in;
      const auto cx = std::min<std::uint32_t>(g - 1, static_cast<std::uint32_t>((s->x[i] - r.x0) * (g / (r.x1 - r.x0))));
      const auto cy = std::min<std::uint32_t>(g - 1, static_cast<std::uint32_t>((s->y[i] - r.y0) * (g / (r.y1 - r.y0))));
      ++ref[cy * g + cx];
    }
    CHECK(at<std::uint32_t>(out, 12) == in);
    for (std::uint32_t k = 0; k < g * g; ++k) CHECK(at<std::uint16_t>(out, viewer_frame_header_bytes + 2 * k) == ref[k]);
  }

  TEST_CASE("the selection frame and its JSON carry the same visible set") {
    viewer_snapshot s;
    s.tick = 77;
    viewer_snapshot::selection sel;
    sel.id = 9;
    sel.alive = true;
    sel.visible = {3, 5, 8};
    sel.tier = {0, 1, 2};
    sel.events = {{70, 5, true}, {75, 4, false}};
    std::vector<std::uint8_t> out;
    encode_viewer_selection(s, sel, out);
    REQUIRE(out.size() == 64 + 3 * 5 + 2 * 9);
    CHECK(out[0] == viewer_frame_selection);
    CHECK(at<std::uint32_t>(out, 8) == 9);
    CHECK(at<std::uint32_t>(out, 56) == 3);
    CHECK(at<std::uint32_t>(out, 64 + 4) == 5);
    CHECK(out[64 + 12 + 2] == 2);
    CHECK(at<std::uint32_t>(out, 64 + 15 + 9 + 4) == 4);
    CHECK(viewer_selection_json(s, sel) == R"({"tick":77,"id":9,"alive":true,"visible":[3,5,8],"tier":[0,1,2]})");
  }

  TEST_CASE("routes: the page, JSON of a selected entity, errors; nothing under /viewer without a viewer") {
    metrics_server plain("127.0.0.1", 0);
    REQUIRE_FALSE(plain.start().has_value());
    CHECK(http_get(plain.port(), "/viewer").starts_with("HTTP/1.1 404"));
    plain.stop();

    viewer_server viewer;
    metrics_server m("127.0.0.1", 0);
    m.attach_viewer(&viewer);
    REQUIRE_FALSE(m.start().has_value());
    const auto page = http_get(m.port(), "/viewer");
    CHECK(page.starts_with("HTTP/1.1 200"));
    CHECK(page.find("text/html") != std::string::npos);
    CHECK(page.ends_with(std::string(viewer_page())));
    CHECK(viewer_page().find("window.zoneViewer") != std::string_view::npos);
    CHECK(http_get(m.port(), "/viewer/").starts_with("HTTP/1.1 200"));
    CHECK(http_get(m.port(), "/viewer/nope").starts_with("HTTP/1.1 404"));
    CHECK(http_get(m.port(), "/viewer/ws").starts_with("HTTP/1.1 400"));  // not an upgrade
    CHECK(http_get(m.port(), "/viewer/entity.json?id=x").starts_with("HTTP/1.1 400"));
    CHECK(http_get(m.port(), "/viewer/entity.json?id=99999999999999").starts_with("HTTP/1.1 400"));
    CHECK(http_get(m.port(), "/viewer/entity.json?id=9").starts_with("HTTP/1.1 404"));
    CHECK(http_request(m.port(), "POST /viewer HTTP/1.1\r\nHost: x\r\nContent-Length: 0\r\n\r\n").starts_with("HTTP/1.1 405"));
    auto s = std::make_shared<viewer_snapshot>();
    s->tick = 5;
    s->selections.push_back({});
    s->selections[0].id = 9;
    s->selections[0].alive = true;
    s->selections[0].visible = {1, 2};
    s->selections[0].tier = {0, 2};
    viewer.publish(s);
    const auto json = http_get(m.port(), "/viewer/entity.json?id=9");
    CHECK(json.starts_with("HTTP/1.1 200"));
    CHECK(json.ends_with(R"({"tick":5,"id":9,"alive":true,"visible":[1,2],"tier":[0,2]})"));
    m.stop();
  }

  TEST_CASE("a session gets the newest snapshot for its view and its selection, and stats; the cap holds") {
    viewer_options o;
    o.max_viewers = 2;
    viewer_server viewer(o);
    metrics_server m("127.0.0.1", 0);
    m.attach_viewer(&viewer);
    REQUIRE_FALSE(m.start().has_value());
    std::mt19937_64 rng(std::random_device{}());
    auto s = random_snapshot(rng, 2000, 500);
    viewer_snapshot::selection sel;
    sel.id = s->ids[0];
    sel.alive = true;
    sel.visible = {s->ids[1], s->ids[2]};
    sel.tier = {0, 1};
    s->selections.push_back(sel);
    viewer.publish(s);
    viewer.publish_stats(R"({"type":"stats","tick":1})");

    ws_client a(m.port());
    REQUIRE_FALSE(a.error);
    CHECK(eventually([&] { return viewer.viewers() == 1; }));
    REQUIRE(a.send(request_bytes({0, 0, 500, 500, sel.id, 100000})));
    const auto frame = a.read_frame(viewer_frame_entities);
    REQUIRE(frame);
    CHECK(at<std::uint32_t>(*frame, 12) == 2000);
    const auto selection = a.read_frame(viewer_frame_selection);
    REQUIRE(selection);
    CHECK(at<std::uint32_t>(*selection, 8) == sel.id);
    CHECK(at<std::uint32_t>(*selection, 56) == 2);
    CHECK(viewer.selected() == std::vector<std::uint32_t>{sel.id});
    // A newer snapshot reaches the page.
    auto s2 = random_snapshot(rng, 10, 500);
    s2->tick = s->tick + 1;
    viewer.publish(s2);
    bool newer = false;
    for (int k = 0; k < 10 && !newer; ++k) {
      const auto f = a.read_frame(viewer_frame_entities);
      REQUIRE(f);
      newer = at<std::uint32_t>(*f, 4) == s2->tick && at<std::uint32_t>(*f, 12) == 10;
    }
    CHECK(newer);
    ws_client b(m.port());
    CHECK_FALSE(b.error);
    CHECK(eventually([&] { return viewer.viewers() == 2; }));
    ws_client c(m.port());  // over the cap: refused with 503
    CHECK(c.error);
    CHECK(eventually([&] { return viewer.stats().sessions_refused == 1; }));
    m.stop();
  }

  TEST_CASE("hostile pages are closed: garbage, text, oversized messages, floods; the tick never waits") {
    viewer_options o;
    o.max_viewers = 8;
    o.max_requests_per_s = 20;
    viewer_server viewer(o);
    metrics_server m("127.0.0.1", 0);
    m.attach_viewer(&viewer);
    REQUIRE_FALSE(m.start().has_value());
    const auto good = request_bytes({0, 0, 100, 100, 0, 1000});
    {
      ws_client c(m.port());
      REQUIRE(c.send({1, 2, 3}));
      CHECK(c.closed_by_server());
    }
    {
      ws_client c(m.port());
      REQUIRE(c.send(good, false));  // the right bytes as text
      CHECK(c.closed_by_server());
    }
    {
      ws_client c(m.port());
      std::vector<std::uint8_t> big(4096, 1);
      (void)c.send(big);
      CHECK(c.closed_by_server());
    }
    {
      ws_client c(m.port());
      for (int k = 0; k < 200 && c.send(good); ++k) {
      }
      CHECK(c.closed_by_server());
    }
    CHECK(eventually([&] { return viewer.stats().sessions_closed_hostile >= 4; }));
    CHECK(eventually([&] { return viewer.viewers() == 0; }));
    // A well-behaved page still works afterwards.
    ws_client ok(m.port());
    REQUIRE(ok.send(good));
    viewer.publish(std::make_shared<viewer_snapshot>());
    CHECK(ok.read_frame(viewer_frame_entities));
    m.stop();
  }

  TEST_CASE("a page that never reads is closed once a write stalls; publishing never blocks") {
    viewer_options o;
    o.stall_close_s = 0.5;
    viewer_server viewer(o);
    metrics_server m("127.0.0.1", 0);
    m.attach_viewer(&viewer);
    REQUIRE_FALSE(m.start().has_value());
    std::mt19937_64 rng(std::random_device{}());
    const auto big = random_snapshot(rng, 200000, 4000);  // 2 MB a frame
    ws_client c(m.port(), 4096);
    REQUIRE(c.send(request_bytes({0, 0, 4000, 4000, 0, viewer_max_points})));
    // Publish for up to 10 s while the page reads nothing: its socket fills, its write stalls,
    // and it is closed; every publish returns at once meanwhile (it only swaps a pointer).
    std::uint64_t published = 0;
    const bool closed = eventually(
        [&] {
          auto s = std::make_shared<viewer_snapshot>(*big);
          s->tick = ++published;
          viewer.publish(std::move(s));
          return viewer.stats().sessions_closed_stalled == 1;
        },
        std::chrono::milliseconds(10000));
    CHECK(closed);
    CHECK(published > 5);
    CHECK(eventually([&] { return viewer.viewers() == 0; }));
    m.stop();
  }
}
