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
#include <atomic>
#include <bit>
#include <cerrno>
#include <sched.h>
#include <sys/resource.h>
#include <thread>
#include <unistd.h>
#include <nlohmann/json.hpp>

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
    s->xy.push_back(coord(rng));
    s->xy.push_back(coord(rng));
    s->classes.push_back(1u << (1 + rng() % 4));
    s->kind.push_back(static_cast<std::uint8_t>(rng() % 3));
  }
  return s;
}


/// A viewer served by a metrics server on a free loopback port, as zone-server serves it.
struct served_viewer {
  viewer_server viewer;
  metrics_server http{"127.0.0.1", 0};
  explicit served_viewer(const viewer_options& o = {}) : viewer(o) {
    http.attach_viewer(&viewer);
    REQUIRE_FALSE(http.start().has_value());
  }
};

/// A coordinate's quantization as the encoder's first version wrote it (std::round, then clamped).
std::uint16_t round_quantized(float v, float lo, float hi) {
  const float scale = 65535.0f / (hi - lo);
  return static_cast<std::uint16_t>(std::clamp(std::round((v - lo) * scale), 0.0f, 65535.0f));
}

bool inside(const viewer_snapshot& s, std::size_t i, const viewer_request& r) {
  return s.x(i) >= r.x0 && s.x(i) <= r.x1 && s.y(i) >= r.y0 && s.y(i) <= r.y1;
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
        CHECK(std::fabs(x - s->x(i)) <= stepx * 0.51f + 1e-3f);
        CHECK(std::fabs(y - s->y(i)) <= stepy * 0.51f + 1e-3f);
        CHECK(at<std::uint16_t>(out, o + 4) == round_quantized(s->x(i), r.x0, r.x1));
        CHECK(at<std::uint16_t>(out, o + 6) == round_quantized(s->y(i), r.y0, r.y1));
        CHECK(out[o + 8] == std::countr_zero(s->classes[i]));
        CHECK(out[o + 9] == s->kind[i]);
        expected.erase(it);  // each once
      }
      CHECK(expected.empty());
    }
  }

  TEST_CASE("quantization rounds as std::round: halves, just below them, the viewport's edges") {
    std::mt19937_64 rng(std::random_device{}());
    const viewer_request unit{0, 0, 65535, 65535, 0, 1u << 20};  // one metre a step
    std::vector<float> xs = {0.0f,
                             0.5f,
                             1.5f,
                             2.5f,
                             std::nextafter(0.5f, 0.0f),
                             std::nextafter(2.5f, 0.0f),
                             std::nextafter(2.5f, 3.0f),
                             32767.5f,
                             65534.5f,
                             std::nextafter(65534.5f, 0.0f),
                             std::nextafter(65535.0f, 0.0f),
                             65535.0f,
                             1e-30f};
    std::uniform_real_distribution<float> u(0, 65535);
    for (int k = 0; k < 2000; ++k) xs.push_back(k % 2 ? u(rng) : std::floor(u(rng)) + 0.5f);
    for (const viewer_request& r : {unit, viewer_request{-3.25f, 0, 1000.75f, 65535, 0, 1u << 20}}) {
      auto s = std::make_shared<viewer_snapshot>();
      for (std::size_t i = 0; i < xs.size(); ++i) {
        const float x = r.x0 + (xs[i] / 65535.0f) * (r.x1 - r.x0);
        s->ids.push_back(static_cast<std::uint32_t>(i + 1));
        s->xy.push_back(std::clamp(x, r.x0, r.x1));
        s->xy.push_back(std::clamp(xs[i], r.y0, r.y1));
        s->classes.push_back(2);
        s->kind.push_back(1);
      }
      std::vector<std::uint8_t> out;
      encode_viewer_view(*s, r, 64, out);
      REQUIRE(at<std::uint32_t>(out, 12) == xs.size());  // every one inside, in order
      std::size_t bad = 0;
      for (std::size_t i = 0; i < xs.size(); ++i) {
        const std::size_t o = viewer_frame_header_bytes + i * viewer_entity_record_bytes;
        bad += at<std::uint16_t>(out, o + 4) != round_quantized(s->x(i), r.x0, r.x1) ||
               at<std::uint16_t>(out, o + 6) != round_quantized(s->y(i), r.y0, r.y1);
      }
      CHECK(bad == 0);
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
      const auto cx = std::min<std::uint32_t>(g - 1, static_cast<std::uint32_t>((s->x(i) - r.x0) * (g / (r.x1 - r.x0))));
      const auto cy = std::min<std::uint32_t>(g - 1, static_cast<std::uint32_t>((s->y(i) - r.y0) * (g / (r.y1 - r.y0))));
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

    served_viewer web;
    const auto page = http_get(web.http.port(), "/viewer");
    CHECK(page.starts_with("HTTP/1.1 200"));
    CHECK(page.find("text/html") != std::string::npos);
    CHECK(page.ends_with(std::string(viewer_page())));
    CHECK(viewer_page().find("window.zoneViewer") != std::string_view::npos);
    CHECK(http_get(web.http.port(), "/viewer/").starts_with("HTTP/1.1 200"));
    CHECK(http_get(web.http.port(), "/viewer/nope").starts_with("HTTP/1.1 404"));
    CHECK(http_get(web.http.port(), "/viewer/ws").starts_with("HTTP/1.1 400"));  // not an upgrade
    CHECK(http_get(web.http.port(), "/viewer/entity.json?id=x").starts_with("HTTP/1.1 400"));
    CHECK(http_get(web.http.port(), "/viewer/entity.json?id=99999999999999").starts_with("HTTP/1.1 400"));
    CHECK(http_get(web.http.port(), "/viewer/entity.json?id=9").starts_with("HTTP/1.1 404"));
    CHECK(http_request(web.http.port(), "POST /viewer HTTP/1.1\r\nHost: x\r\nContent-Length: 0\r\n\r\n").starts_with("HTTP/1.1 405"));
    auto s = std::make_shared<viewer_snapshot>();
    s->tick = 5;
    s->selections.push_back({});
    s->selections[0].id = 9;
    s->selections[0].alive = true;
    s->selections[0].visible = {1, 2};
    s->selections[0].tier = {0, 2};
    web.viewer.next_snapshot() = *s;
    web.viewer.publish();
    const auto json = http_get(web.http.port(), "/viewer/entity.json?id=9");
    CHECK(json.starts_with("HTTP/1.1 200"));
    CHECK(json.ends_with(R"({"tick":5,"id":9,"alive":true,"visible":[1,2],"tier":[0,2]})"));
    web.http.stop();
  }

  TEST_CASE("a session gets the newest snapshot for its view and its selection, and stats; the cap holds") {
    viewer_options o;
    o.max_viewers = 2;
    served_viewer web(o);
    std::mt19937_64 rng(std::random_device{}());
    auto s = random_snapshot(rng, 2000, 500);
    viewer_snapshot::selection sel;
    sel.id = s->ids[0];
    sel.alive = true;
    sel.visible = {s->ids[1], s->ids[2]};
    sel.tier = {0, 1};
    s->selections.push_back(sel);
    web.viewer.next_snapshot() = *s;
    web.viewer.publish();
    web.viewer.next_stats().tick = 4242;
    web.viewer.next_stats().ticks.push_back({4242, 1, 2, 3, 4, 5, 6, 21});
    web.viewer.publish_stats();
    CHECK(web.viewer.next_stats().ticks.empty());  // the next buffer starts with no ticks

    ws_client a(web.http.port());
    REQUIRE_FALSE(a.error);
    CHECK(eventually([&] { return web.viewer.viewers() == 1; }));
    CHECK(web.viewer.selection_version() == 0);
    REQUIRE(a.send(request_bytes({0, 0, 500, 500, sel.id, 100000})));
    // The stats message, formatted on the viewer's thread from what the producer filled in.
    std::optional<std::pair<bool, std::vector<std::uint8_t>>> text;
    for (int k = 0; k < 10 && !(text && text->first); ++k) text = a.read();
    REQUIRE(text);
    REQUIRE(text->first);
    const std::string stats(text->second.begin(), text->second.end());
    CHECK(stats.starts_with(R"({"type":"stats","tick":4242,)"));
    CHECK(stats.find(R"("viewers":1,)") != std::string::npos);
    CHECK(stats.ends_with(R"("ticks":[[4242,1.0000,2.0000,3.0000,4.0000,5.0000,6.0000,21.0000]]})"));
    const auto frame = a.read_frame(viewer_frame_entities);
    REQUIRE(frame);
    CHECK(at<std::uint32_t>(*frame, 12) == 2000);
    const auto selection = a.read_frame(viewer_frame_selection);
    REQUIRE(selection);
    CHECK(at<std::uint32_t>(*selection, 8) == sel.id);
    CHECK(at<std::uint32_t>(*selection, 56) == 2);
    CHECK(web.viewer.selected() == std::vector<std::uint32_t>{sel.id});
    CHECK(web.viewer.selection_version() > 0);
    // A newer snapshot reaches the page.
    auto s2 = random_snapshot(rng, 10, 500);
    s2->tick = s->tick + 1;
    web.viewer.next_snapshot() = *s2;
    web.viewer.publish();
    bool newer = false;
    for (int k = 0; k < 10 && !newer; ++k) {
      const auto f = a.read_frame(viewer_frame_entities);
      REQUIRE(f);
      newer = at<std::uint32_t>(*f, 4) == s2->tick && at<std::uint32_t>(*f, 12) == 10;
    }
    CHECK(newer);
    ws_client b(web.http.port());
    CHECK_FALSE(b.error);
    CHECK(eventually([&] { return web.viewer.viewers() == 2; }));
    ws_client c(web.http.port());  // over the cap: refused with 503
    CHECK(c.error);
    CHECK(eventually([&] { return web.viewer.stats().sessions_refused == 1; }));
    web.http.stop();
  }

  TEST_CASE("hostile pages are closed: garbage, text, oversized messages, floods; the tick never waits") {
    viewer_options o;
    o.max_viewers = 8;
    o.max_requests_per_s = 20;
    served_viewer web(o);
    const auto good = request_bytes({0, 0, 100, 100, 0, 1000});
    {
      ws_client c(web.http.port());
      REQUIRE(c.send({1, 2, 3}));
      CHECK(c.closed_by_server());
    }
    {
      ws_client c(web.http.port());
      REQUIRE(c.send(good, false));  // the right bytes as text
      CHECK(c.closed_by_server());
    }
    {
      ws_client c(web.http.port());
      std::vector<std::uint8_t> big(4096, 1);
      (void)c.send(big);
      CHECK(c.closed_by_server());
    }
    {
      ws_client c(web.http.port());
      for (int k = 0; k < 200 && c.send(good); ++k) {
      }
      CHECK(c.closed_by_server());
    }
    CHECK(eventually([&] { return web.viewer.stats().sessions_closed_hostile >= 4; }));
    CHECK(eventually([&] { return web.viewer.viewers() == 0; }));
    // A well-behaved page still works afterwards.
    ws_client ok(web.http.port());
    REQUIRE(ok.send(good));
    web.viewer.publish();
    CHECK(ok.read_frame(viewer_frame_entities));
    web.http.stop();
  }

  TEST_CASE("a page that never reads is closed once a write stalls; publishing never blocks") {
    viewer_options o;
    o.stall_close_s = 0.5;
    served_viewer web(o);
    std::mt19937_64 rng(std::random_device{}());
    const auto big = random_snapshot(rng, 200000, 4000);  // 2 MB a frame
    ws_client c(web.http.port(), 4096);
    REQUIRE(c.send(request_bytes({0, 0, 4000, 4000, 0, viewer_max_points})));
    // Publish for up to 10 s while the page reads nothing: its socket fills, its write stalls,
    // and it is closed; every publish returns at once meanwhile (one atomic exchange).
    std::uint64_t published = 0;
    const bool closed = eventually(
        [&] {
          auto& s = web.viewer.next_snapshot();
          if (s.ids.size() != big->ids.size()) s = *big;  // three buffers rotate: each filled once
          s.tick = ++published;
          web.viewer.publish();
          return web.viewer.stats().sessions_closed_stalled == 1;
        },
        std::chrono::milliseconds(10000));
    CHECK(closed);
    CHECK(published > 5);
    CHECK(eventually([&] { return web.viewer.viewers() == 0; }));
    web.http.stop();
  }

  TEST_CASE("the stats message: every field the producer filled, as JSON, in order") {
    viewer_stats st;
    st.tick = 12;
    st.tick_rate = 30;
    st.budget_ms = 1000.0 / 30;
    st.entities = 20001;
    st.clients = 3;
    st.pairs = 1234567890;
    st.candidates = 5;
    st.visible = 6;
    st.enters = 7;
    st.leaves = 8;
    st.overruns = 9;
    st.byte_budget = 16384;
    st.update_near = 20;
    st.update_mid = 60;
    st.tick_p99_ms = 12.5;
    st.interest_p99_ms = 1.25;
    st.interest_on = "cpu \"grid\"";
    st.world[2] = st.world[3] = 4096;
    st.ticks = {{11, 0.1, 0.2, 0.3, 0.4, 0.5, 0.00049, 1.5}, {12, 1, 2, 3, 4, 5, 6, 7}};
    const auto j = viewer_stats_json(st, 2, 1000);
    CHECK(j == R"({"type":"stats","tick":12,"tick_rate":30,"budget_ms":33.33333333,"entities":20001,"clients":3,)"
               R"("pairs":1234567890,"candidates":5,"visible":6,"enters":7,"leaves":8,"viewers":2,"viewer_bytes":1000,)"
               R"("overruns":9,"byte_budget":16384,"update_near":20,"update_mid":60,"tick_p99_ms":12.5,"interest_p99_ms":1.25,)"
               R"("interest_on":"cpu \"grid\"","world":[0,0,4096,4096],)"
               R"("phases":["inputs","behaviours","integrate","interest","replicate","viewer"],)"
               R"("ticks":[[11,0.1000,0.2000,0.3000,0.4000,0.5000,0.0005,1.5000],[12,1.0000,2.0000,3.0000,4.0000,5.0000,6.0000,7.0000]]})");
    CHECK(nlohmann::json::parse(j)["ticks"].size() == 2);
  }

  TEST_CASE("a session's timer wakes just after the next snapshot is due, polls while it is late, else every 50 ms") {
    constexpr std::int64_t ms = 1'000'000;
    // Nothing published yet, or no period known: the stall check's pace.
    CHECK(viewer_poll_delay_ns(5 * ms, 0, 0) == 50 * ms);
    CHECK(viewer_poll_delay_ns(5 * ms, 4 * ms, 0) == 50 * ms);
    CHECK(viewer_poll_delay_ns(5 * ms, 4 * ms, 5000 * ms) == 50 * ms);  // a period over a second: not a stream
    std::mt19937_64 rng(17);
    for (int k = 0; k < 2000; ++k) {
      const std::int64_t last = 1 + static_cast<std::int64_t>(rng() % (1000 * ms));
      const std::int64_t period = 1 + static_cast<std::int64_t>(rng() % (200 * ms));
      const std::int64_t now = last + static_cast<std::int64_t>(rng() % (300 * ms));
      const std::int64_t d = viewer_poll_delay_ns(now, last, period), due = last + period;
      REQUIRE(d > 0);
      CHECK(d <= 50 * ms);
      if (now < due) {
        // Before the next is due: wakes 0.2 ms after it (or within 50 ms), never before it.
        CHECK(now + d >= std::min(due, now + 50 * ms));
        CHECK(now + d <= due + ms / 5);
      } else if (now - due <= 10 * ms) {
        CHECK(d == ms);  // due and not there: looks each millisecond
      } else {
        CHECK(d == 50 * ms);  // long overdue (no page, a paused zone): back to the slow pace
      }
    }
  }

  TEST_CASE("the viewer's thread runs below the tick: nice and SCHED_IDLE, or the nice value alone where refused") {
    // What the thread reports is what the OS holds for it (read from outside, by its thread id).
    const auto os_policy = [](long tid) { return ::sched_getscheduler(static_cast<pid_t>(tid)); };
    const auto os_nice = [](long tid) {
      errno = 0;
      return ::getpriority(PRIO_PROCESS, static_cast<id_t>(tid));
    };
    {
      viewer_server v;  // the defaults: nice 19 and SCHED_IDLE
      const auto p = v.thread_info();
      REQUIRE(p.tid > 0);
      CHECK(p.tid != static_cast<long>(::gettid()));
      CHECK(p.nice == 19);
      CHECK(os_nice(p.tid) == 19);
      CHECK(p.idle != p.idle_refused);  // applied, or refused and said so
      CHECK(os_policy(p.tid) == (p.idle ? SCHED_IDLE : SCHED_OTHER));
    }
    const int own = os_nice(::gettid());  // a thread starts at its creator's nice value; raising it needs no privilege
    const int lower = std::clamp(own + 5, 1, 19);
    {
      viewer_options o;
      o.idle = false;
      o.nice = lower;
      viewer_server v(o);
      const auto p = v.thread_info();
      CHECK_FALSE(p.idle);
      CHECK_FALSE(p.idle_refused);
      CHECK(p.nice == lower);
      CHECK(os_nice(p.tid) == lower);
      CHECK(os_policy(p.tid) == SCHED_OTHER);
    }
    // An OS that refuses SCHED_IDLE: the nice value alone, the policy unchanged, the refusal said.
    thread_priority refused, real;
    int policy_refused = -1, policy_real = -1;
    std::thread([&] {
      refused = lower_thread_priority(true, lower, [] {
        errno = EPERM;
        return -1;
      });
      policy_refused = ::sched_getscheduler(0);
    }).join();
    CHECK(refused.idle_refused);
    CHECK_FALSE(refused.idle);
    CHECK(refused.nice == lower);
    CHECK(policy_refused == SCHED_OTHER);
    // The real call on a fresh thread: what it reports is the thread's policy.
    std::thread([&] {
      real = lower_thread_priority(true, 0);
      policy_real = ::sched_getscheduler(0);
    }).join();
    CHECK(real.idle != real.idle_refused);
    CHECK(policy_real == (real.idle ? SCHED_IDLE : SCHED_OTHER));
    CHECK(real.nice == own);  // 0 leaves the nice value as it was
  }

  TEST_CASE("publishing hands over three rotating buffers: the newest reaches the page, none is torn") {
    // The producer fills a buffer while the viewer's thread encodes from another: every frame a
    // page gets must be one whole published snapshot (its tick and its entities agree), and the
    // last one published must arrive.
    viewer_server viewer;
    metrics_server m("127.0.0.1", 0);
    m.attach_viewer(&viewer);
    REQUIRE_FALSE(m.start().has_value());
    ws_client page(m.port());
    REQUIRE(page.send(request_bytes({0, 0, 1000, 1000, 0, viewer_max_points})));
    std::vector<viewer_snapshot*> buffers;
    std::atomic<bool> stop{false};
    std::uint64_t last = 0;
    std::thread producer([&] {
      // Snapshot t holds (t % 50) + 1 entities, each with id t * 1000 + k and x = t % 1000: until
      // the page has read its frames (at most 10 s).
      const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(10);
      for (std::uint64_t t = 1; !stop && std::chrono::steady_clock::now() < end; ++t) {
        auto& s = viewer.next_snapshot();
        if (std::find(buffers.begin(), buffers.end(), &s) == buffers.end()) buffers.push_back(&s);
        const std::size_t n = t % 50 + 1;
        s.tick = t;
        s.ids.resize(n);
        s.xy.assign(2 * n, static_cast<float>(t % 1000));
        s.classes.assign(n, 2);
        s.kind.assign(n, 1);
        for (std::size_t k = 0; k < n; ++k) s.ids[k] = static_cast<std::uint32_t>(t * 1000 + k);
        viewer.publish();
        last = t;
        std::this_thread::sleep_for(std::chrono::microseconds(200));
      }
    });
    std::size_t frames = 0;
    bool whole = true;
    for (int k = 0; k < 100; ++k) {
      const auto f = page.read_frame(viewer_frame_entities);
      if (!f) break;
      ++frames;
      const auto t = at<std::uint32_t>(*f, 4), count = at<std::uint32_t>(*f, 12);
      whole = whole && at<std::uint32_t>(*f, 8) == t % 50 + 1 && count == t % 50 + 1;
      for (std::uint32_t e = 0; e < count && whole; ++e) {
        const std::size_t o = viewer_frame_header_bytes + e * viewer_entity_record_bytes;
        whole = at<std::uint32_t>(*f, o) == t * 1000 + e && (*f)[o + 8] == 1 && (*f)[o + 9] == 1;
      }
    }
    stop = true;
    producer.join();
    CHECK(whole);
    CHECK(frames == 100);
    CHECK(buffers.size() == 3);  // the producer's buffer is one of three, never a new one
    // The newest: once publishing has stopped, the page gets the last snapshot.
    REQUIRE(page.send(request_bytes({0, 0, 1000, 1000, 0, viewer_max_points})));  // resend: a frame at once
    // The frames the session wrote before `stop` are still in the socket ahead of it: one for
    // each snapshot published after the page's last read (0.2 ms apart; many more than 10 when
    // this thread waited for a core), then the newest.
    bool newest = false;
    for (int k = 0; k < 100000 && !newest; ++k) {
      const auto f = page.read_frame(viewer_frame_entities);
      REQUIRE(f);
      newest = at<std::uint32_t>(*f, 4) == last;
    }
    CHECK(newest);
    CHECK(viewer.stats().snapshots_published == last);
    m.stop();
  }
}
