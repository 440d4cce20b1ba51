// The client connector against the Asio server over loopback: hello and welcome, verified tick
// updates (and a detected bad digest), inputs with sequence numbers, ping round trips, and the
// server's error before a disconnect.
#include <doctest/doctest.h>

#include <set>
#include <thread>

#include "net/client.h"
#include "net/server.h"

using namespace zone::net;
using namespace std::chrono_literals;

namespace {

template <class Pred>
bool eventually(Pred pred, std::chrono::milliseconds timeout = 5000ms) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (!pred()) {
    if (std::chrono::steady_clock::now() > deadline) return false;
    std::this_thread::sleep_for(2ms);
  }
  return true;
}

}  // namespace

TEST_SUITE("net.client") {
  TEST_CASE("connector: welcome, verified updates, inputs, pings, error and close") {
    server_options so;
    so.max_queued_frames = 64;  // the test sends its updates in one burst
    server srv(so);
    REQUIRE_FALSE(srv.start().has_value());
    client_pool pool(2);
    client_options opt;
    opt.port = srv.port();
    opt.name = "bot-1";
    client_connection bot(pool, opt);
    bot.connect();

    // The game side: wait for the hello, welcome the client.
    std::vector<inbound_event> events;
    session_id s = 0;
    REQUIRE(eventually([&] {
      srv.poll(events);
      for (const auto& e : events) {
        if (e.msg && std::holds_alternative<hello_msg>(*e.msg) && std::get<hello_msg>(*e.msg).name == "bot-1") s = e.session;
      }
      return s != 0;
    }));
    const world_bounds world{{0, 0, 0}, {1000, 1000, 100}};
    welcome_msg w;
    w.entity_id = 42;
    w.world = world;
    w.tick_rate_hz = 30;
    REQUIRE(srv.send(s, make_shared_frame(encode_frame(w)), delivery::control));
    REQUIRE(eventually([&] { return bot.snapshot().phase == client_snapshot::state::welcomed; }));
    CHECK(bot.snapshot().entity_id == 42);
    CHECK(bot.snapshot().world == world);

    // Tick updates with correct digests.
    std::set<std::uint32_t> view;
    const position_quantizer q(world);
    for (std::uint64_t tick = 1; tick <= 30; ++tick) {
      tick_update_msg m;
      m.server_tick = tick;
      m.reset = tick == 1;
      if (tick % 3 == 0 && !view.empty()) {
        m.leaves.push_back(*view.begin());
        view.erase(view.begin());
      }
      const std::uint32_t fresh = static_cast<std::uint32_t>(100 + tick);
      entity_state e;
      e.id = fresh;
      e.position = {1, 2, 3};
      m.enters.push_back(e);
      for (const auto id : view) m.updates.push_back({id, q.quantize({5, 5, 5}), quantize_velocity({0, 0, 0})});
      view.insert(fresh);
      m.digest = visible_digest(tick, std::vector<std::uint32_t>(view.begin(), view.end()));
      m.last_input_sequence = static_cast<std::uint32_t>(tick);
      REQUIRE(srv.send(s, make_shared_frame(encode_frame(m))));
    }
    REQUIRE(eventually([&] { return bot.snapshot().updates == 30; }));
    auto snap = bot.snapshot();
    CHECK(snap.problems == 0);
    CHECK(snap.digests_checked == 30);
    CHECK(snap.visible == view.size());
    CHECK(snap.resets == 1);
    CHECK(snap.last_tick == 30);
    CHECK(snap.last_input_echo == 30);

    // A wrong digest is detected.
    tick_update_msg wrong;
    wrong.server_tick = 31;
    wrong.digest = verify_digest{31, 12345, 1};
    REQUIRE(srv.send(s, make_shared_frame(encode_frame(wrong))));
    REQUIRE(eventually([&] { return bot.snapshot().updates == 31; }));
    CHECK(bot.snapshot().problems == 1);

    // Inputs arrive in order with sequence numbers; pings come back.
    for (int i = 0; i < 5; ++i) bot.send_input({1, 0, 0});
    bot.send_ping();
    std::vector<std::uint32_t> sequences;
    REQUIRE(eventually([&] {
      srv.poll(events);
      sequences.clear();
      for (const auto& e : events) {
        if (e.session == s && e.msg && std::holds_alternative<input_msg>(*e.msg)) sequences.push_back(std::get<input_msg>(*e.msg).sequence);
      }
      return sequences.size() == 5;
    }));
    CHECK(sequences == std::vector<std::uint32_t>{1, 2, 3, 4, 5});
    REQUIRE(eventually([&] { return bot.snapshot().pongs == 1; }));
    CHECK(bot.snapshot().last_rtt_ms >= 0);
    CHECK(bot.snapshot().inputs_sent == 5);

    // The server's error, then the close.
    srv.disconnect(s, error_code::shutting_down, "maintenance");
    REQUIRE(eventually([&] { return bot.snapshot().phase == client_snapshot::state::closed; }));
    snap = bot.snapshot();
    REQUIRE(snap.error.has_value());
    CHECK(snap.error->code == error_code::shutting_down);
    CHECK(snap.error->reason == "maintenance");
  }

  TEST_CASE("connector: refused connection and bad address end closed with a reason") {
    client_pool pool;
    client_options opt;
    opt.port = 1;  // nothing listens there
    client_connection refused(pool, opt);
    refused.connect();
    REQUIRE(eventually([&] { return refused.snapshot().phase == client_snapshot::state::closed; }));
    CHECK(refused.snapshot().close_reason.find("connect failed") != std::string::npos);
    opt.address = "not an address";
    client_connection bad(pool, opt);
    bad.connect();
    REQUIRE(eventually([&] { return bad.snapshot().phase == client_snapshot::state::closed; }));
    CHECK(bad.snapshot().close_reason.find("bad address") != std::string::npos);
  }
}
