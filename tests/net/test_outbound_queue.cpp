// The session's outbound queue policy (net/outbound_queue.h) without sockets: control frames are
// never dropped and keep their order; after a drop no state frame is delivered until a reset; the
// game is asked for a reset once per episode, and again if a reset is lost; memory is bounded.
#include <doctest/doctest.h>

#include "../common/seeds.h"

#include <cstring>
#include <optional>
#include <random>
#include <unordered_map>
#include <vector>

#include "net/outbound_queue.h"

using namespace zone::net;

namespace {

/// A frame whose bytes are its number (8 bytes), to follow it through the queue.
shared_frame numbered(std::uint64_t n) {
  std::vector<std::uint8_t> b(8);
  std::memcpy(b.data(), &n, 8);
  return make_shared_frame(b);
}
std::uint64_t number_of(const shared_frame& f) {
  std::uint64_t n = 0;
  std::memcpy(&n, f.data(), 8);
  return n;
}

/// What the client receives: (number, kind) in write order.
struct delivered {
  std::uint64_t n;
  delivery kind;
};

/// Writes (and finishes) everything queued, in order.
std::vector<delivered> drain(outbound_queue& q) {
  std::vector<delivered> out;
  while (const auto* e = q.start_write()) {
    out.push_back({number_of(e->frame), e->kind});
    q.finish_write();
  }
  return out;
}

std::vector<std::uint64_t> numbers(const std::vector<delivered>& d) {
  std::vector<std::uint64_t> n;
  for (const auto& x : d) n.push_back(x.n);
  return n;
}

}  // namespace

TEST_SUITE("net.outbound_queue") {
  TEST_CASE("below the bound everything is queued in order") {
    outbound_queue q(4);
    CHECK(q.push(numbered(1), delivery::control).queued);
    CHECK(q.push(numbered(2), delivery::state_reset).queued);
    CHECK(q.push(numbered(3), delivery::state).queued);
    CHECK(q.push(numbered(4), delivery::control).queued);
    CHECK(numbers(drain(q)) == std::vector<std::uint64_t>{1, 2, 3, 4});
    CHECK(q.empty());
  }

  TEST_CASE("a drop episode: queued deltas dropped, nothing but control frames until a reset, reported once") {
    outbound_queue q(4);
    REQUIRE(q.push(numbered(1), delivery::state_reset).queued);
    REQUIRE(q.start_write() != nullptr);  // frame 1 is being written: it is never dropped
    REQUIRE(q.push(numbered(2), delivery::state).queued);
    REQUIRE(q.push(numbered(100), delivery::control).queued);
    REQUIRE(q.push(numbered(3), delivery::state).queued);
    REQUIRE(q.size() == 4);

    // Full: frame 4 starts an episode. 2 and 3 go (queued deltas), and 4 itself.
    auto r = q.push(numbered(4), delivery::state);
    CHECK_FALSE(r.queued);
    CHECK(r.resync);
    CHECK(r.dropped == 3);
    CHECK(q.awaiting_reset());
    CHECK(q.size() == 2);  // 1 (being written) and the control frame

    // Deltas built before the game saw the report: dropped, not reported again.
    r = q.push(numbered(5), delivery::state);
    CHECK_FALSE(r.queued);
    CHECK_FALSE(r.resync);
    CHECK(r.dropped == 1);
    // Control frames still go through, in order.
    CHECK(q.push(numbered(101), delivery::control).queued);
    r = q.push(numbered(6), delivery::state);
    CHECK(r.dropped == 1);
    CHECK_FALSE(r.resync);

    // The reset ends the wait; deltas after it are queued again.
    r = q.push(numbered(7), delivery::state_reset);
    CHECK(r.queued);
    CHECK_FALSE(r.resync);
    CHECK(r.dropped == 0);
    CHECK_FALSE(q.awaiting_reset());
    q.finish_write();  // frame 1 written
    CHECK(q.push(numbered(8), delivery::state).queued);
    const auto got = drain(q);
    REQUIRE(numbers(got) == std::vector<std::uint64_t>{100, 101, 7, 8});
    CHECK(got[2].kind == delivery::state_reset);
  }

  TEST_CASE("a reset replaces the state frames queued before it, not the one being written") {
    outbound_queue q(8);
    REQUIRE(q.push(numbered(1), delivery::state).queued);
    REQUIRE(q.start_write() != nullptr);
    REQUIRE(q.push(numbered(2), delivery::state).queued);
    REQUIRE(q.push(numbered(50), delivery::control).queued);
    auto r = q.push(numbered(3), delivery::state_reset);
    CHECK(r.queued);
    CHECK_FALSE(r.resync);  // nothing the client needs was lost
    CHECK(r.dropped == 1);  // 2: superseded
    REQUIRE(q.push(numbered(4), delivery::state).queued);
    r = q.push(numbered(5), delivery::state_reset);
    CHECK(r.queued);
    CHECK_FALSE(r.resync);
    CHECK(r.dropped == 2);  // 3 and 4
    q.finish_write();
    CHECK(numbers(drain(q)) == std::vector<std::uint64_t>{50, 5});
  }

  TEST_CASE("a queued reset dropped in a later episode is reported again") {
    outbound_queue q(3);
    REQUIRE(q.push(numbered(1), delivery::state).queued);
    REQUIRE(q.start_write() != nullptr);
    REQUIRE(q.push(numbered(2), delivery::state_reset).queued);
    REQUIRE(q.push(numbered(3), delivery::state).queued);
    auto r = q.push(numbered(4), delivery::state);  // full: the reset 2 goes with 3 and 4
    CHECK(r.resync);
    CHECK(r.dropped == 3);
    // The answer to this report is a new reset; until then nothing.
    CHECK(q.push(numbered(5), delivery::state).dropped == 1);
    r = q.push(numbered(6), delivery::state_reset);
    CHECK(r.queued);
    q.finish_write();
    CHECK(numbers(drain(q)) == std::vector<std::uint64_t>{6});
  }

  TEST_CASE("a reset that finds the queue full of control frames is dropped and reported") {
    outbound_queue q(2);
    REQUIRE(q.push(numbered(1), delivery::control).queued);
    REQUIRE(q.push(numbered(2), delivery::control).queued);
    auto r = q.push(numbered(3), delivery::state_reset);
    CHECK_FALSE(r.queued);
    CHECK(r.resync);
    CHECK(r.dropped == 1);
    CHECK(q.awaiting_reset());
    r = q.push(numbered(4), delivery::state);
    CHECK_FALSE(r.resync);
    CHECK(r.dropped == 1);
    // Control frames up to twice the bound; beyond: a stuck client.
    CHECK(q.push(numbered(5), delivery::control).queued);
    CHECK(q.push(numbered(6), delivery::control).queued);
    CHECK(q.push(numbered(7), delivery::control).overflow);
    CHECK(numbers(drain(q)) == std::vector<std::uint64_t>{1, 2, 5, 6});
    CHECK(q.push(numbered(8), delivery::state_reset).queued);
  }

  TEST_CASE("random traffic: every delivered state frame applies, nothing is lost unaccounted, memory bounded") {
    // A game builds one state frame per tick (a reset when a resync is pending, which it learns a
    // random number of ticks after the report), sends pongs now and then; a writer takes frames
    // at a random pace (sometimes stalled for long). The client checks that each state frame it
    // gets is a reset or the next tick after the state frame before it.
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    std::mt19937_64 rng(seed);
    std::uint64_t episodes = 0, superseded_or_dropped = 0;
    for (int round = 0; round < 20; ++round) {
      const std::size_t bound = 1 + rng() % 10;
      CAPTURE(bound);
      outbound_queue q(bound);
      std::uint64_t sent_state = 0, dropped = 0, delivered_state = 0, reports = 0, resets_sent = 0;
      std::optional<std::uint64_t> last_state;   // tick of the last state frame the client got
      bool reset_pending = true;                 // the first frame of a client is a reset
      std::vector<int> report_delays;            // ticks until the game sees each report
      bool stalled = false;
      std::uint64_t next_control = 1ull << 40;
      std::size_t control_in_queue = 0;
      const auto take = [&](const outbound_queue::entry& e) {
        if (e.kind == delivery::control) {
          CHECK(number_of(e.frame) >= (1ull << 40));
          --control_in_queue;
          return;
        }
        const std::uint64_t t = number_of(e.frame);
        ++delivered_state;
        if (e.kind == delivery::state_reset) {
          if (last_state) CHECK(t > *last_state);
        } else {
          REQUIRE(last_state.has_value());  // a client's first state frame is a reset
          CHECK(t == *last_state + 1);      // a delta applies only on the frame before it
        }
        last_state = t;
      };
      // The game's tick: the tick's state frame, a reset when a report has reached the game; a
      // report (a resync) reaches it delay() ticks later (the next tick's input phase, or later).
      const auto send_state = [&](std::uint64_t tick, const auto& delay) {
        for (auto& d : report_delays) {
          if (--d <= 0) reset_pending = true;
        }
        std::erase_if(report_delays, [](int d) { return d <= 0; });
        const bool reset = reset_pending;
        reset_pending = false;
        resets_sent += reset ? 1 : 0;
        ++sent_state;
        const auto r = q.push(numbered(tick), reset ? delivery::state_reset : delivery::state);
        dropped += r.dropped;
        if (r.resync) {
          ++reports;
          report_delays.push_back(delay());
        }
        return r;
      };
      for (std::uint64_t tick = 0; tick < 3000; ++tick) {
        CHECK_FALSE(send_state(tick, [&] { return 1 + static_cast<int>(rng() % 4); }).overflow);
        if (rng() % 8 == 0 && control_in_queue < bound) {  // a pong (clients ping far slower than the tick)
          REQUIRE(q.push(numbered(next_control++), delivery::control).queued);
          ++control_in_queue;
        }
        CHECK(q.size() <= 2 * bound);
        // The writer: stalls now and then for a while, else takes 0..3 frames this tick.
        if (rng() % 50 == 0) stalled = !stalled;
        if (!stalled) {
          const int n = static_cast<int>(rng() % 4);
          for (int k = 0; k < n; ++k) {
            if (!q.writing()) {
              if (q.start_write() == nullptr) break;
            }
            take(q.entries().front());
            q.finish_write();
          }
        } else if (!q.writing()) {
          (void)q.start_write();  // one frame stuck in the socket
        }
      }
      // Unstall: the game keeps ticking until the client is served again.
      for (std::uint64_t tick = 3000; tick < 3100; ++tick) {
        (void)send_state(tick, [] { return 1; });
        if (q.writing()) {
          take(q.entries().front());
          q.finish_write();
        }
        while (const auto* e = q.start_write()) {
          take(*e);
          q.finish_write();
        }
      }
      CHECK(last_state.value_or(0) == 3099);            // served again, up to the newest tick
      CHECK(delivered_state + dropped == sent_state);   // every state frame delivered or counted
      CHECK(reports <= resets_sent);                    // each report answered by a reset
      CHECK_FALSE(q.awaiting_reset());
      episodes += reports;
      superseded_or_dropped += dropped;
    }
    MESSAGE("drop episodes " << episodes << ", state frames not delivered " << superseded_or_dropped);
    CHECK(episodes > 20);  // the stalls did overflow the queues
  }

  TEST_CASE("a partial write: the frames written whole retire, the rest stay in flight and are never dropped") {
    outbound_queue q(4);
    for (int i = 0; i < 3; ++i) REQUIRE(q.push(make_shared_frame(std::vector<std::uint8_t>(100, std::uint8_t(i))), delivery::state).queued);
    REQUIRE(q.start_write_many(64) == 3);  // bound - 1
    q.finish_frames(1);                     // the socket took frame 0 and part of frame 1
    CHECK(q.in_flight() == 2);
    CHECK(q.writing());
    CHECK(q.start_write_many(64) == 0);     // still one write in flight: its rest
    // A state frame at a full queue drops what is not being written: here only itself.
    REQUIRE(q.push(make_shared_frame(std::vector<std::uint8_t>(100, 3)), delivery::state).queued);
    REQUIRE(q.push(make_shared_frame(std::vector<std::uint8_t>(100, 4)), delivery::state).queued);
    const auto r = q.push(make_shared_frame(std::vector<std::uint8_t>(100, 5)), delivery::state);
    CHECK(r.resync);
    CHECK(r.dropped == 3);  // frames 3 and 4 (queued) and 5 (new); frames 1 and 2 are in flight
    REQUIRE(q.size() == 2);
    CHECK(q.entries()[0].frame.data()[0] == 1);
    CHECK(q.entries()[1].frame.data()[0] == 2);
    q.finish_frames(5);  // more than in flight: only those
    CHECK(q.empty());
    CHECK_FALSE(q.writing());
  }

  TEST_CASE("gathered writes: at most bound - 1 frames and about 64 KiB a write, retired together, in order") {
    outbound_queue q(8);
    for (std::uint64_t n = 0; n < 8; ++n) REQUIRE(q.push(numbered(n), n % 3 == 0 ? delivery::control : delivery::state).queued);
    CHECK(q.start_write_many(64) == 7);  // bound - 1: a reset always fits behind a write
    CHECK(q.writing());
    CHECK(q.in_flight() == 7);
    CHECK(q.start_write_many(64) == 0);  // one write in flight
    CHECK(q.start_write() == nullptr);
    REQUIRE(q.push(numbered(8), delivery::control).queued);
    REQUIRE(q.push(numbered(9), delivery::control).queued);
    q.finish_write();
    CHECK_FALSE(q.writing());
    CHECK(q.size() == 3);
    CHECK(number_of(q.entries()[0].frame) == 7);
    CHECK(q.start_write_many(2) == 2);  // the caller's cap
    q.finish_write();
    CHECK(number_of(q.entries()[0].frame) == 9);

    // Bytes: 40 KiB frames go one a write (a second would pass 64 KiB); a frame larger than that
    // still goes, alone.
    outbound_queue big(8);
    std::vector<std::uint8_t> b40(40 * 1024), b100(100 * 1024);
    REQUIRE(big.push(make_shared_frame(b40), delivery::state).queued);
    REQUIRE(big.push(make_shared_frame(b40), delivery::state).queued);
    CHECK(big.start_write_many(64) == 1);
    big.finish_write();
    CHECK(big.start_write_many(64) == 1);
    big.finish_write();
    REQUIRE(big.push(make_shared_frame(b100), delivery::state).queued);
    REQUIRE(big.push(numbered(1), delivery::state).queued);
    CHECK(big.start_write_many(64) == 1);
    big.finish_write();
    std::vector<std::uint8_t> small(1000);
    for (int i = 0; i < 6; ++i) REQUIRE(big.push(make_shared_frame(small), delivery::state).queued);
    CHECK(big.start_write_many(64) == 7);  // the numbered frame and six of 1,000 bytes
  }

  TEST_CASE("a drop episode while several frames are being written keeps them all; the reset fits behind them") {
    outbound_queue q(8);
    for (std::uint64_t n = 1; n <= 7; ++n) REQUIRE(q.push(numbered(n), delivery::state).queued);
    REQUIRE(q.start_write_many(64) == 7);
    REQUIRE(q.push(numbered(8), delivery::state).queued);  // 8 held: the bound
    auto r = q.push(numbered(9), delivery::state);
    CHECK_FALSE(r.queued);
    CHECK(r.resync);
    CHECK(r.dropped == 2);  // 8 (queued, not being written) and 9
    CHECK(q.size() == 7);   // 1..7 are on their way: kept
    r = q.push(numbered(10), delivery::state);
    CHECK_FALSE(r.queued);  // awaiting a reset
    CHECK_FALSE(r.resync);
    r = q.push(numbered(11), delivery::state_reset);
    CHECK(r.queued);  // 7 in flight + the reset < 8
    CHECK_FALSE(r.resync);
    q.finish_write();
    CHECK(numbers(drain(q)) == std::vector<std::uint64_t>{11});
  }

  TEST_CASE("random traffic with gathered writes: every delivered state frame applies, memory bounded") {
    const auto seed = zone::test::fresh_seed();
    INFO("seed " << seed);
    std::mt19937_64 rng(seed);
    outbound_queue q(6);
    std::uint64_t next = 1, last_state = 0, sent_state = 0, delivered_state = 0, dropped = 0, episodes = 0;
    bool reset_due = true, awaiting = false;
    std::vector<delivered> in_flight;
    std::unordered_map<std::uint64_t, std::uint64_t> previous_sent;  // state frame -> the state frame sent before it
    std::uint64_t last_sent_state = 0;
    for (int step = 0; step < 200000; ++step) {
      const auto roll = rng() % 100;
      if (roll < 55) {  // the game sends
        const bool control = rng() % 8 == 0 && q.size() < 11;
        const delivery d = control ? delivery::control : reset_due ? delivery::state_reset : delivery::state;
        if (!control) {
          ++sent_state;
          previous_sent[next] = last_sent_state;
          last_sent_state = next;
        }
        const auto r = q.push(numbered(next), d);
        dropped += r.dropped;
        if (r.resync) {
          ++episodes;
          reset_due = true;  // the game's next state frame is a reset
        } else if (d == delivery::state_reset && r.queued) {
          reset_due = false;
        }
        awaiting = q.awaiting_reset();
        ++next;
      } else if (roll < 80) {  // the socket takes a gathered write
        if (q.start_write_many(1 + rng() % 8) != 0) {
          for (std::size_t i = 0; i < q.in_flight(); ++i) in_flight.push_back({number_of(q.entries()[i].frame), q.entries()[i].kind});
        }
      } else if (q.writing()) {  // the write completes
        q.finish_write();
        for (const auto& d : in_flight) {
          if (d.kind == delivery::control) continue;
          ++delivered_state;
          // A delta applies only on the state frame sent right before it (numbers are per send).
          if (d.kind == delivery::state) {
            REQUIRE_MESSAGE(previous_sent[d.n] == last_state, "delta " << d.n << " after " << last_state);
          }
          last_state = d.n;
        }
        in_flight.clear();
      }
      REQUIRE(q.size() <= 12);
      (void)awaiting;
    }
    for (const auto& e : q.entries()) delivered_state += e.kind != delivery::control ? 1 : 0;
    CHECK(delivered_state + dropped == sent_state);  // every state frame delivered or counted
    CHECK(episodes > 20);
  }

  TEST_CASE("drop_stale (a stalled client): queued state dropped, the write in flight and control frames kept, then only a reset") {
    outbound_queue q(8);
    REQUIRE(q.push(numbered(1), delivery::state).queued);
    REQUIRE(q.start_write() != nullptr);  // frame 1 is being written
    REQUIRE(q.push(numbered(2), delivery::state).queued);
    REQUIRE(q.push(numbered(3), delivery::control).queued);
    REQUIRE(q.push(numbered(4), delivery::state).queued);
    CHECK(q.drop_stale() == 2);  // 2 and 4
    CHECK(q.awaiting_reset());
    const auto late = q.push(numbered(5), delivery::state);  // a delta built before the game knew
    CHECK_FALSE(late.queued);
    CHECK(late.dropped == 1);
    CHECK_FALSE(late.resync);  // the caller resyncs itself: not reported again
    REQUIRE(q.push(numbered(6), delivery::state_reset).queued);
    CHECK_FALSE(q.awaiting_reset());
    REQUIRE(q.push(numbered(7), delivery::state).queued);
    q.finish_write();
    CHECK(numbers(drain(q)) == std::vector<std::uint64_t>{3, 6, 7});
    CHECK(q.drop_stale() == 0);  // nothing queued: still awaits a reset
    CHECK(q.awaiting_reset());
  }
}
