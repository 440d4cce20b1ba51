// The framing codec without sockets: round trips, split streams, malformed frames, random bytes,
// quantization bounds and the visible-set digest.
#include <doctest/doctest.h>

#include "../common/seeds.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <random>
#include <set>
#include <stdexcept>
#include <unordered_map>

#include "net/protocol.h"

using namespace zone::net;
using bytes = std::vector<std::uint8_t>;

namespace {

using zone::test::fresh_seed;

struct gen {
  std::mt19937_64 rng;
  explicit gen(std::uint64_t seed) : rng(seed) {}
  std::uint64_t u64() { return rng(); }
  std::uint32_t u32() { return static_cast<std::uint32_t>(rng()); }
  std::size_t below(std::size_t n) { return n == 0 ? 0 : static_cast<std::size_t>(rng() % n); }
  float f(float lo = -1e4f, float hi = 1e4f) { return std::uniform_real_distribution<float>(lo, hi)(rng); }
  vec3f v() { return {f(), f(), f()}; }
  std::string str(std::size_t max_len = 40) {
    std::string s(below(max_len + 1), ' ');
    for (auto& c : s) c = static_cast<char>(rng() % 256);  // any bytes, NULs included
    return s;
  }
  entity_state state() {
    return {u32(), static_cast<entity_kind>(below(3)), u32(), v(), v(), v(), str(12)};
  }
  entity_update update() {
    return {u32(),
            {static_cast<std::uint16_t>(rng()), static_cast<std::uint16_t>(rng()), static_cast<std::uint16_t>(rng())},
            {static_cast<std::int16_t>(rng()), static_cast<std::int16_t>(rng()), static_cast<std::int16_t>(rng())}};
  }
  /// A random message of kind `kind` (index of the variant).
  message make(std::size_t kind) {
    switch (kind) {
      case 0: {
        hello_msg h{str(), str(64), u32()};
        h.stealth = rng() % 2 == 0;
        h.team = static_cast<std::uint8_t>(rng());
        h.class_changes = rng() % 2 == 0;
        return h;
      }
      case 1: return input_msg{u32(), v()};
      case 2: return ping_msg{u64()};
      case 3: {
        // By field, in the order of the draws a braced list would make.
        welcome_msg w;
        w.entity_id = u32();
        w.world.lo = v();
        w.world.hi = v();
        w.tick_rate_hz = static_cast<std::uint16_t>(rng());
        w.server_tick = u64();
        w.protocol_version = u32();
        if (rng() % 2) w.spawn_position = v();
        w.host_clock = rng() % 2 == 0;
        if (rng() % 2) {
          interest_rules r;
          r.player_aoi = v();
          r.hysteresis = static_cast<float>(below(100)) / 4;
          r.max_visible = u32();
          r.player_class = u32();
          r.player_sees = u32();
          for (std::size_t i = below(6); i-- > 0;) r.npc_aoi_tiers.push_back(static_cast<float>(below(1000)));
          r.quantization_step = v();
          r.update_near = static_cast<float>(below(100));
          r.update_mid = static_cast<float>(below(300));
          r.update_mid_period = u32();
          r.update_far_period = u32();
          r.byte_budget = u32();
          r.send_every = u32();
          r.digest_every = u32();
          r.max_speed = static_cast<float>(below(50));
          r.allow_stealth = rng() % 2 == 0;
          r.teams = static_cast<std::uint8_t>(rng());
          r.visibility_cooldown = static_cast<float>(below(10));
          w.rules = r;
        }
        w.oracle_port = static_cast<std::uint16_t>(rng());
        w.instance = u64();
        if (rng() % 2) w.resume_token = str();
        return w;
      }
      case 4: {
        tick_update_msg t;
        t.server_tick = u64();
        t.server_time_us = u64();
        t.last_input_sequence = u32();
        for (std::size_t i = below(20); i-- > 0;) t.enters.push_back(state());
        for (std::size_t i = below(50); i-- > 0;) t.leaves.push_back(u32());
        for (std::size_t i = below(200); i-- > 0;) t.updates.push_back(update());
        if (rng() % 2) t.digest = verify_digest{u64(), u64(), u32()};
        t.reset = rng() % 4 == 0;
        if (rng() % 2) t.self_position = v();
        if (rng() % 2) t.deferred = deferred_counts{u32() | 1, u32(), u32()};  // present only when not all 0
        return t;
      }
      case 5: return pong_msg{u64(), u64()};
      case 6: return error_msg{static_cast<error_code>(below(static_cast<std::size_t>(error_code::MAX) + 1)), str()};
      case 7: return teleport_msg{u32(), v(), rng() % 2 ? 0u : u32()};
      case 8: return redirect_msg{str(), static_cast<std::uint16_t>(u32()), str()};
      case 9: return set_visibility_msg{u32(), rng() % 2 == 0, static_cast<std::uint8_t>(rng())};
      case 11: return leave_msg{};
      default: {  // 10
        class_changes_msg c;
        c.server_tick = u64();
        for (std::size_t i = below(40); i-- > 0;) c.notes.push_back({u32(), u32()});
        return c;
      }
    }
  }
  message any() { return make(below(std::variant_size_v<message>)); }
};

/// Feeds a stream in the given chunk sizes and collects messages and the final error, if any.
struct drain_result {
  std::vector<message> messages;
  std::optional<decode_error> error;
};
drain_result drain(frame_decoder& d, const bytes& stream, const std::vector<std::size_t>& chunks, bool close) {
  drain_result r;
  std::size_t at = 0;
  auto pump = [&] {
    while (!r.error) {
      const auto step = d.next();
      if (step.needs_more()) break;
      if (step.is_error()) {
        r.error = step.error;
        break;
      }
      REQUIRE(step.frame.envelope != nullptr);
      auto m = to_message(*step.frame.envelope);
      REQUIRE(m.has_value());
      CHECK(type_of(*m) == step.frame.type);
      r.messages.push_back(std::move(*m));
    }
  };
  for (const std::size_t c : chunks) {
    const std::size_t n = std::min(c, stream.size() - at);
    d.feed({stream.data() + at, n});
    at += n;
    pump();
  }
  if (at < stream.size()) {
    d.feed({stream.data() + at, stream.size() - at});
    pump();
  }
  if (close && !r.error) r.error = d.close();
  return r;
}

std::vector<std::size_t> random_chunks(gen& g, std::size_t total, std::size_t max_chunk) {
  std::vector<std::size_t> c;
  for (std::size_t at = 0; at < total;) {
    const std::size_t n = 1 + g.below(max_chunk);
    c.push_back(n);
    at += n;
  }
  return c;
}

bytes frame_of(const message& m) { return encode_frame(m); }

std::uint32_t read_le32(const std::uint8_t* p) {
  return std::uint32_t{p[0]} | std::uint32_t{p[1]} << 8 | std::uint32_t{p[2]} << 16 | std::uint32_t{p[3]} << 24;
}

void write_le32(std::uint8_t* p, std::uint32_t v) {
  for (int i = 0; i < 4; ++i) p[i] = static_cast<std::uint8_t>(v >> (8 * i));
}

/// A frame whose envelope carries union type `type` (possibly unknown) with a ping body.
bytes frame_with_type(std::uint8_t type, bool with_body = true) {
  flatbuffers::FlatBufferBuilder fbb;
  flatbuffers::Offset<void> body = with_body ? zone::net::wire::Createping(fbb, 42).Union() : flatbuffers::Offset<void>();
  const auto env = zone::net::wire::Createenvelope(fbb, static_cast<zone::net::wire::message>(type), body);
  zone::net::wire::FinishSizePrefixedenvelopeBuffer(fbb, env);
  return {fbb.GetBufferPointer(), fbb.GetBufferPointer() + fbb.GetSize()};
}

decoder_options big_frames() {
  decoder_options o;
  o.max_frame_bytes = 1 << 20;
  return o;
}

/// Everything of `t` into the writer, as the server's replication does field by field (finish() left to the caller).
void write_all(tick_update_writer& w, const tick_update_msg& t) {
  w.begin(t.server_tick, t.server_time_us, t.last_input_sequence);
  for (const auto& s : t.enters) w.add_enter(s);
  for (const auto id : t.leaves) w.add_leave(id);
  for (const auto& u : t.updates) w.add_update(u);
  if (t.digest) w.set_digest(*t.digest);
  w.set_reset(t.reset);
  if (t.self_position) w.set_self_position(*t.self_position);
  if (t.deferred) w.set_deferred(*t.deferred);
}

}  // namespace

TEST_SUITE("net.protocol") {
  TEST_CASE("every message type round-trips through encoder and decoder") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gen g(seed);
    encoder enc;
    for (int rep = 0; rep < 50; ++rep) {
      for (std::size_t kind = 0; kind < std::variant_size_v<message>; ++kind) {
        CAPTURE(kind);
        const message m = g.make(kind);
        const auto frame = enc.encode(m);
        REQUIRE(frame.size() >= frame_header_bytes);
        CHECK(read_le32(frame.data()) == frame.size() - frame_header_bytes);
        frame_decoder d(big_frames());
        d.feed(frame);
        const auto step = d.next();
        REQUIRE(step.is_frame());
        CHECK(step.frame.type == type_of(m));
        CHECK(type_name(step.frame.type) != "unknown");
        const auto back = to_message(*step.frame.envelope);
        REQUIRE(back.has_value());
        CHECK(*back == m);
        CHECK(d.next().needs_more());
        CHECK_FALSE(d.close().has_value());
        // The one-shot path agrees.
        const auto one = decode_frame(frame, big_frames());
        REQUIRE(one.value.has_value());
        CHECK(*one.value == m);
      }
    }
  }

  TEST_CASE("tick_update_writer frames equal encoded tick_update_msg values, size estimate is an upper bound") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gen g(seed);
    tick_update_writer w;
    for (int rep = 0; rep < 100; ++rep) {
      auto t = std::get<tick_update_msg>(g.make(4));
      write_all(w, t);
      CHECK(w.enter_count() == t.enters.size());
      CHECK(w.leave_count() == t.leaves.size());
      CHECK(w.update_count() == t.updates.size());
      const std::size_t estimate = w.size_estimate();
      const auto frame = w.finish();
      CHECK(frame.size() <= estimate);
      const auto back = decode_frame(frame, big_frames());
      REQUIRE(back.value.has_value());
      CHECK(std::get<tick_update_msg>(*back.value) == t);
    }
  }

  TEST_CASE("tick_update_writer::finish_into writes finish()'s bytes, every one of them, and nothing past the frame") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gen g(seed);
    std::mt19937_64 rng(seed);
    tick_update_writer w;
    std::vector<std::uint8_t> buffer;
    for (int rep = 0; rep < 200; ++rep) {
      CAPTURE(rep);
      auto t = std::get<tick_update_msg>(g.make(4));
      if (rep % 5 == 0) t.enters.clear();  // every part present or not, over the reps
      if (rep % 7 == 0) t.updates.clear();
      write_all(w, t);
      const std::size_t size = w.frame_size();
      const auto frame = w.finish();
      REQUIRE(frame.size() == size);
      const std::vector<std::uint8_t> want(frame.begin(), frame.end());
      // Into memory full of garbage, at an offset, with room to spare after the frame.
      write_all(w, t);
      const std::size_t offset = 8 * (rng() % 4), spare = rng() % 64;
      const auto fill = static_cast<std::uint8_t>(rng());
      buffer.assign(offset + size + spare, fill);
      const auto into = w.finish_into(std::span(buffer).subspan(offset));
      REQUIRE(into.size() == size);
      CHECK(into.data() == buffer.data() + offset);
      CHECK(std::equal(want.begin(), want.end(), into.begin()));
      CHECK(std::all_of(buffer.begin(), buffer.begin() + static_cast<std::ptrdiff_t>(offset), [&](std::uint8_t b) { return b == fill; }));
      CHECK(std::all_of(buffer.begin() + static_cast<std::ptrdiff_t>(offset + size), buffer.end(), [&](std::uint8_t b) { return b == fill; }));
      const auto back = decode_frame(into, big_frames());
      REQUIRE(back.value.has_value());
      CHECK(std::get<tick_update_msg>(*back.value) == t);
      // A buffer one byte short is refused, untouched.
      write_all(w, t);
      buffer.assign(size - 1, fill);
      CHECK_THROWS_AS((void)w.finish_into(buffer), std::length_error);
      CHECK(std::all_of(buffer.begin(), buffer.end(), [&](std::uint8_t b) { return b == fill; }));
    }
  }

  TEST_CASE("frame_cost: replication's frames (nameless enters) never exceed the closed form; spans equal add_*") {
    // The byte budget is decided with frame_cost alone (CPU and GPU replication alike), so it must
    // bound every frame: any counts, default or extreme field values (fields left out or not,
    // vtables shared or not), with or without self position, digest and reset.
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    std::mt19937_64 rng(seed);
    const auto val = [&](int mode) -> float {
      switch (mode) {
        case 0: return 0.0f;
        case 1: return std::numeric_limits<float>::max();
        default: return static_cast<float>(static_cast<double>(rng() % 100000) / 7.0);
      }
    };
    tick_update_writer w, by_span;
    std::size_t tightest = ~std::size_t{0};
    for (int rep = 0; rep < 400; ++rep) {
      const std::size_t enters = rep < 10 ? static_cast<std::size_t>(rep) : rng() % 200;
      const std::size_t leaves = rng() % 3 == 0 ? 0 : rng() % 300, updates = rng() % 3 == 0 ? 0 : rng() % 600;
      const bool self = rng() % 2 != 0, digest = rng() % 2 != 0, reset = rng() % 2 != 0;
      const std::uint64_t tick = rng() % 2 != 0 ? rng() : 0;
      std::vector<std::uint32_t> leave_ids;
      std::vector<wire::entity_update> ups;
      w.begin(tick, rng(), static_cast<std::uint32_t>(rng()));
      by_span.begin(tick, 0, 0);
      for (std::size_t k = 0; k < enters; ++k) {
        const int mode = static_cast<int>(rng() % 3);
        entity_state e{static_cast<std::uint32_t>(mode == 0 ? 0 : rng()),
                       static_cast<entity_kind>(rng() % 3),
                       mode == 0 ? 0u : static_cast<std::uint32_t>(rng()),
                       {val(mode), val(mode), val(mode)},
                       {val(mode), val(mode), val(mode)},
                       {val(mode), val(mode), val(mode)},
                       {}};
        w.add_enter(e);
      }
      for (std::size_t k = 0; k < leaves; ++k) leave_ids.push_back(static_cast<std::uint32_t>(rng()));
      for (std::size_t k = 0; k < updates; ++k) {
        ups.emplace_back(static_cast<std::uint32_t>(rng()), wire::qpos3(1, 2, 3), wire::qvel3(-1, 0, 1));
      }
      for (const auto id : leave_ids) w.add_leave(id);
      for (const auto& u : ups) w.add_wire_update(u);
      by_span.set_leaves(leave_ids);
      by_span.set_wire_updates(ups);
      for (auto* x : {&w, &by_span}) {
        if (self) x->set_self_position({val(2), val(1), val(0)});
        if (digest) x->set_digest({tick, rng(), static_cast<std::uint32_t>(rng())});
        x->set_reset(reset);
      }
      const std::size_t estimate = w.size_estimate();
      CHECK(estimate == frame_cost::of(enters, leaves, updates, self));
      const auto frame = w.finish();
      CAPTURE(enters);
      CAPTURE(leaves);
      CAPTURE(updates);
      REQUIRE(frame.size() <= estimate);
      tightest = std::min(tightest, estimate - frame.size());
      if (enters == 0) {
        // Without enters the span path writes the same frame as add_leave/add_wire_update (its
        // writer got the same values but for time and input: compare the decoded lists).
        const auto a = decode_frame(frame, big_frames());
        const auto b = decode_frame(by_span.finish(), big_frames());
        REQUIRE(a.value.has_value());
        REQUIRE(b.value.has_value());
        const auto& ta = std::get<tick_update_msg>(*a.value);
        const auto& tb = std::get<tick_update_msg>(*b.value);
        CHECK(ta.leaves == tb.leaves);
        CHECK(ta.updates == tb.updates);
      }
    }
    MESSAGE("least slack of the cost model over the frames: " << tightest << " bytes");
    CHECK(tightest < 128);  // a bound, but not a loose one
  }

  TEST_CASE("tick_update: an empty enters, leaves or updates vector is absent on the wire; writer and encoder agree byte for byte") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gen g(seed);
    tick_update_writer w;
    encoder enc;
    for (int rep = 0; rep < 40; ++rep) {
      for (int empty = 0; empty < 8; ++empty) {  // bit 0: no enters, bit 1: no leaves, bit 2: no updates
        CAPTURE(empty);
        auto t = std::get<tick_update_msg>(g.make(4));
        if (empty & 1) t.enters.clear(); else if (t.enters.empty()) t.enters.push_back(g.state());
        if (empty & 2) t.leaves.clear(); else if (t.leaves.empty()) t.leaves.push_back(g.u32());
        if (empty & 4) t.updates.clear(); else if (t.updates.empty()) t.updates.push_back(g.update());
        write_all(w, t);
        const auto written = w.finish();
        const bytes from_writer(written.begin(), written.end());
        const auto encoded = enc.encode(message{t});
        CHECK(from_writer == bytes(encoded.begin(), encoded.end()));
        const auto* body = zone::net::wire::GetSizePrefixedenvelope(from_writer.data())->message_as_tick_update();
        REQUIRE(body != nullptr);
        CHECK((body->enters() == nullptr) == ((empty & 1) != 0));
        CHECK((body->leaves() == nullptr) == ((empty & 2) != 0));
        CHECK((body->updates() == nullptr) == ((empty & 4) != 0));
        const auto back = decode_frame(from_writer, big_frames());
        REQUIRE(back.value.has_value());
        CHECK(std::get<tick_update_msg>(*back.value) == t);
      }
    }
  }

  TEST_CASE("tick_update frames are in the canonical layout: verified, decoded equal, every part where canonical_tick_update says") {
    // The CPU replicator and the GPU path both write frames with tick_update_writer, so equal
    // values give equal bytes; this pins the layout itself.
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gen g(seed);
    tick_update_writer w;
    using c = canonical_tick_update;
    {  // docs/protocol.md's example: a self position and N updates
      c::parts p;
      p.updates = p.self = true;
      for (std::size_t n = 1; n < 50; ++n) CHECK(c::size(p, 0, 0, n, 0) == 104 + 16 * n);
    }
    for (int rep = 0; rep < 200; ++rep) {
      auto t = std::get<tick_update_msg>(g.make(4));
      if (rep % 4 == 0) t.enters.clear();
      write_all(w, t);
      const auto span = w.finish();
      const bytes f(span.begin(), span.end());
      CAPTURE(rep);
      std::size_t names = 0;
      for (const auto& e : t.enters) names += c::name_bytes(e.name.size());
      c::parts parts;
      parts.enters = !t.enters.empty();
      parts.leaves = !t.leaves.empty();
      parts.updates = !t.updates.empty();
      parts.digest = t.digest.has_value();
      parts.self = t.self_position.has_value();
      parts.deferred = t.deferred.has_value() && t.deferred->any();
      parts.reset = t.reset;
      const auto l = c::layout(parts);
      REQUIRE(f.size() == c::size(parts, t.enters.size(), t.leaves.size(), t.updates.size(), names));
      CHECK(f.size() % 8 == 0);
      CHECK(reinterpret_cast<std::uintptr_t>(span.data()) % 8 == 0);
      flatbuffers::Verifier v(f.data(), f.size());
      REQUIRE(wire::VerifySizePrefixedenvelopeBuffer(v));
      const auto back = decode_frame(f, big_frames());
      REQUIRE(back.value.has_value());
      CHECK(std::get<tick_update_msg>(*back.value) == t);
      // Where the parts are.
      const auto* env = wire::GetSizePrefixedenvelope(f.data());
      const auto* body = env->message_as_tick_update();
      REQUIRE(body != nullptr);
      const auto at = [&](const void* p) { return static_cast<std::size_t>(static_cast<const std::uint8_t*>(p) - f.data()); };
      CHECK(at(env) == 20);
      CHECK(at(body) == l.table_at);
      CHECK(l.table_at % 8 == 4);
      // Every present field where the layout puts it; absent ones absent.
      const auto* vt = f.data() + c::vtable_at;
      for (int k = 0; k < 10; ++k) {
        const std::uint16_t place = k * 2 + 4 < static_cast<int>(l.vtable_size) ? static_cast<std::uint16_t>(vt[4 + 2 * k] | vt[5 + 2 * k] << 8) : 0;
        CHECK(place == l.field[k]);
      }
      CHECK((l.field[6] != 0) == t.digest.has_value());
      CHECK((l.field[8] != 0) == t.self_position.has_value());
      CHECK((l.field[7] != 0) == t.reset);
      if (t.self_position) CHECK(at(body->self_position()) == l.table_at + l.field[8]);
      if (t.digest) CHECK(at(body->digest()) == l.table_at + l.field[6]);
      std::size_t next = l.table_at + l.table_size;
      if (!t.enters.empty()) {
        REQUIRE(body->enters() != nullptr);
        CHECK(at(body->enters()) == next);
        next += 4 + 4 * t.enters.size();
      }
      if (!t.leaves.empty()) {
        CHECK(at(body->leaves()) == next);
        next += 4 + 4 * t.leaves.size();
      }
      if (!t.updates.empty()) {
        CHECK(at(body->updates()) == next);
        next += 4 + 16 * t.updates.size();
      }
      next += t.enters.empty() ? 0 : c::enter_vtable;
      for (std::size_t k = 0; k < t.enters.size(); ++k) {
        const auto* e = body->enters()->Get(static_cast<flatbuffers::uoffset_t>(k));
        CHECK(at(e) == next);
        CHECK(at(e->name()) == next + c::enter_table);
        next += c::enter_table + c::name_bytes(t.enters[k].name.size());
      }
      CHECK((next + 7) / 8 * 8 == f.size());
      // Deterministic: the same values again (after a different frame) give the same bytes.
      w.begin(1, 2, 3);
      w.add_leave(7);
      (void)w.finish();
      write_all(w, t);
      const auto again = w.finish();
      CHECK(bytes(again.begin(), again.end()) == f);
    }
  }

  TEST_CASE("a stream split byte by byte and in random chunks decodes to the same messages") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gen g(seed);
    std::vector<message> sent;
    bytes stream;
    for (int i = 0; i < 60; ++i) {
      sent.push_back(g.any());
      const auto f = frame_of(sent.back());
      stream.insert(stream.end(), f.begin(), f.end());
    }
    {
      frame_decoder d(big_frames());
      const auto r = drain(d, stream, std::vector<std::size_t>(stream.size(), 1), true);
      CHECK_FALSE(r.error.has_value());
      CHECK(r.messages == sent);
    }
    for (int rep = 0; rep < 30; ++rep) {
      const std::size_t max_chunk = 1 + g.below(rep % 2 ? 16 : 4096);
      CAPTURE(max_chunk);
      frame_decoder d(big_frames());
      const auto r = drain(d, stream, random_chunks(g, stream.size(), max_chunk), true);
      CHECK_FALSE(r.error.has_value());
      CHECK(r.messages == sent);
    }
    {  // Zero-copy receive path: prepare/commit with short reads.
      frame_decoder d(big_frames());
      std::vector<message> got;
      for (std::size_t at = 0; at < stream.size();) {
        const auto buf = d.prepare(1 + g.below(300));
        const std::size_t n = std::min({buf.size(), stream.size() - at, 1 + g.below(buf.size())});
        std::memcpy(buf.data(), stream.data() + at, n);
        d.commit(n);
        at += n;
        for (auto s = d.next(); s.is_frame(); s = d.next()) got.push_back(*to_message(*s.frame.envelope));
      }
      CHECK(got == sent);
      CHECK(d.pending_bytes() == 0);
    }
    {  // The bot swarm's read path: reads of up to 16 KiB, each decoding every frame it completes
       // before the next read (frames straddle reads; a frame is used before the next next()).
      frame_decoder d(big_frames());
      std::vector<message> got;
      std::size_t reads_with_several = 0;
      for (std::size_t at = 0; at < stream.size();) {
        const auto buf = d.prepare(16384);
        REQUIRE(buf.size() == 16384);
        const std::size_t n = std::min(stream.size() - at, 1 + g.below(buf.size()));
        std::memcpy(buf.data(), stream.data() + at, n);
        d.commit(n);
        at += n;
        std::size_t frames = 0;
        for (auto s = d.next(); s.is_frame(); s = d.next(), ++frames) got.push_back(*to_message(*s.frame.envelope));
        reads_with_several += frames > 1 ? 1 : 0;
      }
      CHECK(got == sent);
      CHECK(d.pending_bytes() == 0);
      CHECK(reads_with_several > 0);
    }
  }

  TEST_CASE("misaligned frames (sizes not a multiple of 8) still decode") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gen g(seed);
    // Rebuild frames with 4 trailing pad bytes inside the length (valid FlatBuffers: trailing
    // bytes are ignored), which shifts every later body off 8-byte alignment.
    bytes stream;
    std::vector<message> sent;
    for (int i = 0; i < 40; ++i) {
      sent.push_back(g.any());
      auto f = frame_of(sent.back());
      const std::uint32_t pad = static_cast<std::uint32_t>(g.below(8));
      write_le32(f.data(), read_le32(f.data()) + pad);
      f.insert(f.end(), pad, 0xAB);
      stream.insert(stream.end(), f.begin(), f.end());
    }
    frame_decoder d(big_frames());
    const auto r = drain(d, stream, random_chunks(g, stream.size(), 64), true);
    CHECK_FALSE(r.error.has_value());
    CHECK(r.messages == sent);
  }

  TEST_CASE("oversize frames are rejected from the prefix alone") {
    decoder_options o;
    o.max_frame_bytes = 256;
    frame_decoder d(o);
    const bytes ok = frame_of(ping_msg{7});
    d.feed(ok);
    REQUIRE(d.next().is_frame());
    bytes prefix(4);
    write_le32(prefix.data(), 257);
    d.feed(prefix);  // only the prefix: the body never has to arrive
    const auto s = d.next();
    REQUIRE(s.is_error());
    CHECK(s.error == decode_error::oversize);
    CHECK(d.failed());
    // The decoder stays failed, whatever comes next.
    d.feed(ok);
    CHECK(d.next().error == decode_error::oversize);
    CHECK(d.close() == decode_error::oversize);
    CHECK(to_error_code(decode_error::oversize) == error_code::oversize);

    // A real message larger than the limit, and the one-shot path.
    tick_update_msg big;
    big.leaves.assign(200, 1);
    const auto f = frame_of(big);
    frame_decoder d2(o);
    d2.feed(f);
    CHECK(d2.next().error == decode_error::oversize);
    CHECK(decode_frame(f, o).error == decode_error::oversize);
    // Exactly at the limit is accepted.
    decoder_options exact;
    exact.max_frame_bytes = f.size() - 4;
    frame_decoder d3(exact);
    d3.feed(f);
    CHECK(d3.next().is_frame());
  }

  TEST_CASE("truncated streams are reported at close") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gen g(seed);
    for (int rep = 0; rep < 200; ++rep) {
      const auto f = frame_of(g.any());
      const std::size_t cut = 1 + g.below(f.size() - 1);  // 1 .. size-1 bytes arrive
      CAPTURE(cut);
      frame_decoder d(big_frames());
      d.feed({f.data(), cut});
      CHECK(d.next().needs_more());
      CHECK(d.close() == decode_error::truncated_at_close);
      CHECK(d.next().error == decode_error::truncated_at_close);
    }
    frame_decoder clean;
    CHECK_FALSE(clean.close().has_value());
  }

  TEST_CASE("unknown and missing message types are rejected") {
    const auto first_unknown = static_cast<std::uint8_t>(static_cast<std::uint8_t>(zone::net::wire::message::MAX) + 1);
    for (const std::uint8_t type : {std::uint8_t{0}, first_unknown, std::uint8_t{77}, std::uint8_t{255}}) {
      CAPTURE(int(type));
      frame_decoder d;
      d.feed(frame_with_type(type));
      const auto s = d.next();
      REQUIRE(s.is_error());
      CHECK(s.error == decode_error::unknown_type);
      CHECK(to_error_code(s.error) == error_code::unknown_type);
    }
    // A known type without its body is not a message.
    frame_decoder d;
    d.feed(frame_with_type(static_cast<std::uint8_t>(zone::net::wire::message::ping), false));
    CHECK(d.next().error == decode_error::verification_failed);
    // Positive control: the helper builds valid frames when the type is right.
    frame_decoder ok;
    ok.feed(frame_with_type(static_cast<std::uint8_t>(zone::net::wire::message::ping)));
    CHECK(ok.next().is_frame());
  }

  TEST_CASE("schema evolution: teleport is appended; frames without the new fields decode as before") {
    namespace w = zone::net::wire;
    // Appended, never inserted: the wire numbers of the old messages are unchanged.
    CHECK(static_cast<int>(w::message::error) == 7);
    CHECK(static_cast<int>(w::message::teleport) == 8);
    CHECK(static_cast<int>(type_of(teleport_msg{})) == 8);
    CHECK(static_cast<int>(w::message::redirect) == 9);
    CHECK(static_cast<int>(type_of(set_visibility_msg{})) == 10);
    CHECK(static_cast<int>(w::message::class_changes) == 11);
    CHECK(static_cast<int>(type_of(class_changes_msg{})) == 11);
    CHECK(static_cast<int>(w::message::leave) == 12);
    CHECK(static_cast<int>(type_of(leave_msg{})) == 12);
    CHECK(static_cast<int>(w::error_code::bad_hello) == 12);  // error codes are appended too
    CHECK(static_cast<int>(w::error_code::taken_over) == 13);
    const auto body_frame = [](auto build) {
      flatbuffers::FlatBufferBuilder fbb;
      const auto body = build(fbb);
      w::FinishSizePrefixedenvelopeBuffer(fbb, w::Createenvelope(fbb, body.first, body.second));
      return bytes(fbb.GetBufferPointer(), fbb.GetBufferPointer() + fbb.GetSize());
    };
    // A welcome and a tick update as an older server builds them (no spawn, clock or self fields).
    const w::bounds3 world(w::vec3(0, 0, 0), w::vec3(100, 100, 10));
    const auto welcome = decode_frame(body_frame([&](flatbuffers::FlatBufferBuilder& fbb) {
      return std::pair{w::message::welcome, w::Createwelcome(fbb, 5, &world, 30, 9, 1).Union()};
    }));
    REQUIRE(welcome.value.has_value());
    const auto& wm = std::get<welcome_msg>(*welcome.value);
    CHECK(wm.entity_id == 5);
    CHECK_FALSE(wm.spawn_position.has_value());
    CHECK_FALSE(wm.host_clock);
    const auto tick = decode_frame(body_frame([&](flatbuffers::FlatBufferBuilder& fbb) {
      return std::pair{w::message::tick_update, w::Createtick_update(fbb, 3, 4, 5).Union()};
    }));
    REQUIRE(tick.value.has_value());
    CHECK_FALSE(std::get<tick_update_msg>(*tick.value).self_position.has_value());
    // A hello as an older client builds it (no visibility choice): not stealthed, no team.
    const auto old_hello = decode_frame(body_frame([&](flatbuffers::FlatBufferBuilder& fbb) {
      return std::pair{w::message::hello, w::Createhello(fbb, fbb.CreateString("old"), 0, 1).Union()};
    }));
    REQUIRE(old_hello.value.has_value());
    CHECK_FALSE(std::get<hello_msg>(*old_hello.value).stealth);
    CHECK(std::get<hello_msg>(*old_hello.value).team == 0);
    CHECK_FALSE(std::get<hello_msg>(*old_hello.value).class_changes);  // an older client gets resets
    // A class_changes without notes: nothing to apply.
    const auto no_notes = decode_frame(body_frame([&](flatbuffers::FlatBufferBuilder& fbb) {
      return std::pair{w::message::class_changes, w::Createclass_changes(fbb, 42).Union()};
    }));
    REQUIRE(no_notes.value.has_value());
    CHECK(std::get<class_changes_msg>(*no_notes.value) == class_changes_msg{42, {}});
    // An empty set_visibility asks for the plain class (not stealthed, no team).
    const auto plain = decode_frame(body_frame([&](flatbuffers::FlatBufferBuilder& fbb) {
      return std::pair{w::message::set_visibility, w::Createset_visibility(fbb).Union()};
    }));
    REQUIRE(plain.value.has_value());
    CHECK(std::get<set_visibility_msg>(*plain.value) == set_visibility_msg{});
    // A teleport without a position decodes to a non-finite target (the server refuses it),
    // never to the origin.
    const auto empty = decode_frame(body_frame([&](flatbuffers::FlatBufferBuilder& fbb) {
      return std::pair{w::message::teleport, w::Createteleport(fbb, 7).Union()};
    }));
    REQUIRE(empty.value.has_value());
    const auto& t = std::get<teleport_msg>(*empty.value);
    CHECK(t.sequence == 7);
    CHECK(t.entity_id == 0);
    CHECK(std::isnan(t.position.x));
    // Non-finite and huge coordinates travel as they are: refusing or clamping them is the game's job.
    const float inf = std::numeric_limits<float>::infinity();
    const auto hostile = decode_frame(encode_frame(teleport_msg{1, {inf, -1e30f, 0}, 12345}));
    REQUIRE(hostile.value.has_value());
    CHECK(std::get<teleport_msg>(*hostile.value).position.x == inf);
    CHECK(std::get<teleport_msg>(*hostile.value).entity_id == 12345);
    // The client view records the observer's own position with its tick.
    client_view view({{0, 0, 0}, {100, 100, 10}});
    tick_update_msg u;
    u.server_tick = 10;
    u.self_position = vec3f{1, 2, 3};
    CHECK(view.apply(u) == client_view::status::ok);
    REQUIRE(view.self_position().has_value());
    CHECK(*view.self_position() == vec3f{1, 2, 3});
    CHECK(view.self_position_tick() == 10);
  }

  TEST_CASE("frames that fail verification are rejected") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gen g(seed);
    const auto expect_verification_failure = [](const bytes& frame) {
      frame_decoder d(big_frames());
      d.feed(frame);
      const auto s = d.next();
      REQUIRE(s.is_error());
      CHECK(s.error == decode_error::verification_failed);
    };
    const bytes good = frame_of(hello_msg{"alice", "secret", protocol_version});
    {  // Wrong file identifier.
      bytes f = good;
      f[4 + 4] ^= 0x20;
      expect_verification_failure(f);
    }
    {  // Root offset pointing past the end.
      bytes f = good;
      write_le32(f.data() + 4, static_cast<std::uint32_t>(f.size() * 4));
      expect_verification_failure(f);
    }
    {  // Root offset misaligned / into the identifier.
      bytes f = good;
      write_le32(f.data() + 4, 5);
      expect_verification_failure(f);
    }
    {  // Too short to be a FlatBuffer at all, and an empty frame.
      expect_verification_failure(bytes{4, 0, 0, 0, 1, 2, 3, 4});
      expect_verification_failure(bytes{0, 0, 0, 0});
    }
    {  // String length pointing past the end of the buffer: found by scanning for the name's length word.
      bytes f = good;
      bool patched = false;
      for (std::size_t i = 4; i + 8 <= f.size(); i += 4) {
        if (read_le32(f.data() + i) == 5 && std::memcmp(f.data() + i + 4, "alice", 5) == 0) {
          write_le32(f.data() + i, 100000);
          patched = true;
        }
      }
      REQUIRE(patched);
      expect_verification_failure(f);
    }
    {  // Garbage bodies under a valid prefix.
      for (int rep = 0; rep < 500; ++rep) {
        bytes f(4 + 8 + g.below(200));
        for (std::size_t i = 4; i < f.size(); ++i) f[i] = static_cast<std::uint8_t>(g.u32());
        // A root offset past the buffer end guarantees rejection; the rest is arbitrary.
        write_le32(f.data() + 4, static_cast<std::uint32_t>(f.size() + g.below(1u << 30)));
        write_le32(f.data(), static_cast<std::uint32_t>(f.size() - 4));
        expect_verification_failure(f);
      }
    }
  }

  TEST_CASE("random bytes and mutated frames never crash or over-read") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gen g(seed);
    decoder_options o;
    o.max_frame_bytes = 4096;
    std::size_t frames = 0, errors = 0;
    for (int rep = 0; rep < 20000; ++rep) {
      bytes stream;
      if (rep % 2 == 0) {
        // Pure noise, with small length prefixes often enough that bodies reach the verifier.
        stream.resize(g.below(300));
        for (auto& b : stream) b = static_cast<std::uint8_t>(g.u32());
        if (stream.size() >= 4 && g.below(2)) write_le32(stream.data(), static_cast<std::uint32_t>(g.below(stream.size())));
      } else {
        // Valid frames with a few random byte flips.
        for (std::size_t i = 1 + g.below(3); i-- > 0;) {
          const auto f = frame_of(g.any());
          stream.insert(stream.end(), f.begin(), f.end());
        }
        for (std::size_t i = 1 + g.below(4); i-- > 0;) stream[g.below(stream.size())] ^= static_cast<std::uint8_t>(1 + g.below(255));
      }
      frame_decoder d(o);
      // Feed an exact-size heap copy per chunk so that ASan sees any read past the input.
      for (std::size_t at = 0; at < stream.size();) {
        const std::size_t n = std::min<std::size_t>(1 + g.below(64), stream.size() - at);
        const std::unique_ptr<std::uint8_t[]> chunk(new std::uint8_t[n]);
        std::memcpy(chunk.get(), stream.data() + at, n);
        d.feed({chunk.get(), n});
        at += n;
        for (auto s = d.next(); !s.needs_more(); s = d.next()) {
          if (s.is_error()) {
            ++errors;
            break;
          }
          ++frames;
          // A frame that passed verification must convert without trouble.
          const auto m = to_message(*s.frame.envelope);
          REQUIRE(m.has_value());
          CHECK(type_of(*m) == s.frame.type);
        }
        if (d.failed()) break;
      }
      (void)d.close();
      // The one-shot path on an exact-size copy of the stream.
      if (!stream.empty()) {
        const std::size_t n = stream.size();
        const std::unique_ptr<std::uint8_t[]> copy(new std::uint8_t[n]);
        std::memcpy(copy.get(), stream.data(), n);
        const auto r = decode_frame({copy.get(), n}, o);
        CHECK(r.value.has_value() != r.error.has_value());
      }
    }
    MESSAGE("fuzz: " << frames << " frames accepted, " << errors << " streams rejected");
    CHECK(errors > 0);
    CHECK(frames > 0);
  }

  TEST_CASE("position quantization round trip stays within max_error") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gen g(seed);
    for (int world_rep = 0; world_rep < 50; ++world_rep) {
      world_bounds w;
      w.lo = {g.f(-5e4f, 5e4f), g.f(-5e4f, 5e4f), g.f(-1e3f, 1e3f)};
      w.hi = {w.lo.x + g.f(1.f, 2e4f), w.lo.y + g.f(1.f, 2e4f), w.lo.z + g.f(0.5f, 500.f)};
      CAPTURE(w.lo.x);
      CAPTURE(w.hi.x);
      const position_quantizer q(w);
      const vec3f e = q.max_error();
      // The bound is half a step plus float rounding of the coordinate, not more.
      const double half_step = (double(w.hi.x) - double(w.lo.x)) / 65535.0 / 2;
      const double ulp = std::max(std::fabs(w.lo.x), std::fabs(w.hi.x)) * std::ldexp(1.0, -23);
      CHECK(e.x >= half_step);
      CHECK(e.x <= half_step + 2 * ulp);
      for (int rep = 0; rep < 2000; ++rep) {
        const vec3f p{g.f(w.lo.x, w.hi.x), g.f(w.lo.y, w.hi.y), g.f(w.lo.z, w.hi.z)};
        const vec3f back = q.dequantize(q.quantize(p));
        CHECK(std::fabs(back.x - p.x) <= e.x);
        CHECK(std::fabs(back.y - p.y) <= e.y);
        CHECK(std::fabs(back.z - p.z) <= e.z);
      }
      // The corners are exact; outside clamps to the bounds; NaN goes to lo.
      CHECK(q.dequantize(q.quantize(w.lo)) == w.lo);
      CHECK(q.quantize(w.hi) == std::array<std::uint16_t, 3>{65535, 65535, 65535});
      CHECK(q.quantize({w.lo.x - 100, w.hi.y + 100, w.lo.z}) == std::array<std::uint16_t, 3>{0, 65535, 0});
      CHECK(q.quantize({std::nanf(""), w.lo.y, w.lo.z})[0] == 0);
    }
    // A flat world: the zero-width axis decodes to lo.
    const position_quantizer flat({{0, 0, 5}, {100, 100, 5}});
    CHECK(flat.dequantize(flat.quantize({50, 50, 5})).z == 5.f);
  }

  TEST_CASE("velocity quantization round trip and clamping") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gen g(seed);
    for (int rep = 0; rep < 20000; ++rep) {
      const vec3f v{g.f(-velocity_limit, velocity_limit), g.f(-50, 50), g.f(-1, 1)};
      const vec3f back = dequantize_velocity(quantize_velocity(v));
      const float tol = velocity_max_error + 1e-4f;
      CHECK(std::fabs(back.x - v.x) <= tol);
      CHECK(std::fabs(back.y - v.y) <= tol);
      CHECK(std::fabs(back.z - v.z) <= tol);
    }
    CHECK(quantize_velocity({1e6f, -1e6f, std::nanf("")}) == std::array<std::int16_t, 3>{32767, -32767, 0});
  }

  TEST_CASE("quantization rounds exactly as std::lround: halves, neighbours of halves, clamps") {
    // The quantizers round without the library call (they run for every update sent); these
    // are the formulas they had before, with std::lround, as the reference.
    const world_bounds w{{-1000.5f, 0, -7}, {3095.25f, 4096, 249}};
    const position_quantizer q(w);
    const double step[3] = {(double(w.hi.x) - double(w.lo.x)) / 65535.0, (double(w.hi.y) - double(w.lo.y)) / 65535.0,
                            (double(w.hi.z) - double(w.lo.z)) / 65535.0};
    const float lo[3] = {w.lo.x, w.lo.y, w.lo.z};
    const auto ref_position = [&](const vec3f& p) {
      const float v[3] = {p.x, p.y, p.z};
      std::array<std::uint16_t, 3> r{};
      for (int d = 0; d < 3; ++d) {
        const double t = (static_cast<double>(v[d]) - static_cast<double>(lo[d])) / step[d];
        r[d] = !(t > 0) ? 0 : t >= 65535.0 ? 65535 : static_cast<std::uint16_t>(std::lround(t));
      }
      return r;
    };
    const auto ref_velocity = [](const vec3f& v) {
      const auto axis = [](float x) -> std::int16_t {
        const double t = static_cast<double>(x) * 100.0;
        if (!(t == t)) return 0;
        return static_cast<std::int16_t>(std::lround(std::clamp(t, -32767.0, 32767.0)));
      };
      return std::array<std::int16_t, 3>{axis(v.x), axis(v.y), axis(v.z)};
    };
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gen g(seed);
    std::vector<float> xs;
    // Floats at and next to the positions that quantize to k + 0.5 (the rounding boundary),
    // next to the cm-per-second halves, and at the clamps; then random ones.
    for (int rep = 0; rep < 3000; ++rep) {
      const double k = std::floor(g.f(0, 65535)) + 0.5;
      const float at = static_cast<float>(lo[0] + k * step[0]);
      xs.insert(xs.end(), {at, std::nextafter(at, -1e9f), std::nextafter(at, 1e9f)});
      const float half_cm = static_cast<float>((std::floor(g.f(-40000, 40000)) + 0.5) / 100.0);
      xs.insert(xs.end(), {half_cm, std::nextafter(half_cm, -1e9f), std::nextafter(half_cm, 1e9f)});
      xs.push_back(g.f(-2e4f, 2e4f));
      xs.push_back(g.f(-1, 1));
    }
    xs.insert(xs.end(), {0.f, -0.f, 0.005f, -0.005f, 0.004999f, -0.004999f, 327.665f, -327.665f, 327.67f, -327.67f,
                         1e9f, -1e9f, std::numeric_limits<float>::infinity(),
                         -std::numeric_limits<float>::infinity(), std::nanf(""), w.lo.x, w.hi.x, w.lo.z, w.hi.z});
    std::size_t checked = 0;
    for (std::size_t k = 0; k < xs.size(); ++k) {
      const vec3f p{xs[k], xs[(k * 7 + 1) % xs.size()], xs[(k * 13 + 2) % xs.size()]};
      CAPTURE(p.x);
      CHECK(q.quantize(p) == ref_position(p));
      CHECK(quantize_velocity(p) == ref_velocity(p));
      ++checked;
    }
    CHECK(checked > 10000);
  }

  TEST_CASE("visible digest: incremental equals direct, order independent") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gen g(seed);
    std::set<std::uint32_t> view;
    std::uint64_t hash = 0;
    for (int rep = 0; rep < 5000; ++rep) {
      const std::uint32_t id = 1 + static_cast<std::uint32_t>(g.below(300));
      if (view.insert(id).second) {
        hash = digest_add(hash, id);
      } else {
        view.erase(id);
        hash = digest_remove(hash, id);
      }
    }
    std::vector<std::uint32_t> ids(view.begin(), view.end());
    std::shuffle(ids.begin(), ids.end(), g.rng);
    const auto d = visible_digest(99, ids);
    CHECK(d.hash == hash);
    CHECK(d.count == view.size());
    CHECK(d.tick == 99);
    // Sensitive to membership.
    if (!ids.empty()) {
      ids.pop_back();
      CHECK(visible_digest(99, ids).hash != hash);
    }
  }
  TEST_CASE("id_map matches a std::unordered_map model under random inserts, erases and lookups") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gen g(seed);
    id_map<std::string> m;
    std::unordered_map<std::uint32_t, std::string> model;
    for (int op = 0; op < 20000; ++op) {
      // Small id ranges make probe runs collide and wrap; 0 and the largest id are keys too.
      const std::uint32_t range = op % 3 == 0 ? 64 : op % 3 == 1 ? 5000 : 0xffffffffu;
      std::uint32_t id = g.u32() % range;
      if (g.below(50) == 0) id = g.below(2) ? 0u : 0xffffffffu;
      switch (g.below(4)) {
        case 0:
        case 1: {
          const auto [it, fresh] = m.try_emplace(id);
          const auto [mit, mfresh] = model.try_emplace(id);
          REQUIRE(fresh == mfresh);
          CHECK(it->first == id);
          if (fresh) {
            it->second = std::to_string(id);
            mit->second = it->second;
          }
          break;
        }
        case 2: CHECK(m.erase(id) == model.erase(id)); break;
        default: {
          const auto it = m.find(id);
          const auto mit = model.find(id);
          REQUIRE((it == m.end()) == (mit == model.end()));
          if (mit != model.end()) CHECK(it->second == mit->second);
          CHECK(m.count(id) == model.count(id));
        }
      }
      REQUIRE(m.size() == model.size());
      if (op % 2000 == 0) {
        std::size_t seen = 0;
        for (const auto& [k, v] : m) {
          ++seen;
          CHECK(model.count(k) == 1);
          CHECK(model.at(k) == v);
        }
        CHECK(seen == model.size());
      }
      if (op == 15000) {
        m.clear();
        model.clear();
        CHECK(m.empty());
        CHECK(m.find(7) == m.end());
      }
    }
  }

  TEST_CASE("client_view applies updates, checks consistency and digests") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gen g(seed);
    const world_bounds world{{0, 0, 0}, {1000, 1000, 100}};
    const position_quantizer q(world);
    client_view view(world);
    // A server-side model: the set it believes the client holds.
    std::set<std::uint32_t> model;
    std::uint64_t tick = 0;
    for (int rep = 0; rep < 300; ++rep) {
      tick_update_msg m;
      m.server_tick = ++tick;
      m.reset = rep == 150;
      if (m.reset) model.clear();
      for (auto it = model.begin(); it != model.end();) {
        if (g.below(10) == 0) {
          m.leaves.push_back(*it);
          it = model.erase(it);
        } else {
          ++it;
        }
      }
      for (std::size_t k = g.below(5); k-- > 0;) {
        const std::uint32_t id = 1 + static_cast<std::uint32_t>(g.below(1000));
        if (model.insert(id).second) {
          entity_state s = g.state();
          s.id = id;
          s.position = {g.f(0, 1000), g.f(0, 1000), g.f(0, 100)};
          m.enters.push_back(s);
        }
      }
      for (const auto id : model) {
        if (g.below(2) && std::none_of(m.enters.begin(), m.enters.end(), [&](const entity_state& s) { return s.id == id; })) {
          const vec3f p{g.f(0, 1000), g.f(0, 1000), g.f(0, 100)};
          m.updates.push_back({id, q.quantize(p), quantize_velocity({1, 2, 3})});
        }
      }
      const std::vector<std::uint32_t> ids(model.begin(), model.end());
      m.digest = visible_digest(tick, ids);
      // Half the time through the wire form, with a visitor that sees every position told.
      struct told {
        std::vector<std::pair<std::uint32_t, vec3f>> positions;
        const client_view* view = nullptr;
        bool in_view = true;
      } seen;
      seen.view = &view;
      const auto status = g.below(2) ? view.apply(m) : [&] {
        const auto frame = encode_frame(m);
        frame_decoder d(big_frames());
        d.feed(frame);
        const auto s = d.next();
        REQUIRE(s.is_frame());
        const auto st = view.apply(
            *s.frame.envelope->message_as_tick_update(),
            [](void* ctx, std::uint32_t id, const vec3f& p, const vec3f&) {
              auto& t = *static_cast<told*>(ctx);
              t.positions.emplace_back(id, p);
              t.in_view = t.in_view && t.view->entities().count(id) == 1;  // called after the view holds it
            },
            &seen);
        REQUIRE(seen.positions.size() == m.enters.size() + m.updates.size());
        for (std::size_t k = 0; k < m.enters.size(); ++k) {
          CHECK(seen.positions[k].first == m.enters[k].id);
          CHECK(seen.positions[k].second == m.enters[k].position);
        }
        for (std::size_t k = 0; k < m.updates.size(); ++k) {
          CHECK(seen.positions[m.enters.size() + k].first == m.updates[k].id);
          CHECK(seen.positions[m.enters.size() + k].second == q.dequantize(m.updates[k].position));
        }
        CHECK(seen.in_view);
        return st;
      }();
      REQUIRE(status == client_view::status::ok);
      CHECK(view.last_bad_ids().empty());
      CHECK(view.size() == model.size());
    }
    CHECK(view.problems() == 0);
    CHECK(view.digests_checked() == 300);
    // Failures are detected: an unknown leave, a duplicate enter, a stale tick, a wrong digest.
    tick_update_msg bad;
    bad.server_tick = ++tick;
    bad.leaves.push_back(5000);
    bad.updates.push_back({5001, {}, {}});
    CHECK(view.apply(bad) == client_view::status::inconsistent);
    CHECK(view.last_bad_ids() == std::vector<std::uint32_t>{5000, 5001});
    tick_update_msg stale;
    stale.server_tick = 1;
    CHECK(view.apply(stale) == client_view::status::inconsistent);
    tick_update_msg wrong;
    wrong.server_tick = ++tick;
    wrong.digest = verify_digest{tick, view.hash() + 1, static_cast<std::uint32_t>(view.size())};
    CHECK(view.apply(wrong) == client_view::status::digest_mismatch);
    if (!model.empty()) {
      tick_update_msg dup;
      dup.server_tick = ++tick;
      entity_state s;
      s.id = *model.begin();
      dup.enters.push_back(s);
      CHECK(view.apply(dup) == client_view::status::inconsistent);
      CHECK(view.last_bad_ids() == std::vector<std::uint32_t>{s.id});
      // The same through the wire form.
      dup.server_tick = ++tick;
      const auto frame = encode_frame(dup);
      frame_decoder d(big_frames());
      d.feed(frame);
      const auto step = d.next();
      REQUIRE(step.is_frame());
      CHECK(view.apply(*step.frame.envelope->message_as_tick_update()) == client_view::status::inconsistent);
      CHECK(view.last_bad_ids() == std::vector<std::uint32_t>{s.id});
    }
    CHECK(view.problems() >= 3);
  }

  TEST_CASE("client_view: the batched wire path equals the value path (long update lists, unknown and repeated ids)") {
    // apply(wire) looks updates up in prefetched batches of 64; apply(msg) one by one. Twin views
    // fed the same frames must agree on status, bad ids, contents, digest and the positions told.
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    gen g(seed);
    const world_bounds world{{-500, -500, 0}, {500, 500, 50}};
    const position_quantizer q(world);
    client_view by_value(world), by_wire(world);
    std::vector<std::uint32_t> known;
    std::uint64_t tick = 0;
    for (int rep = 0; rep < 200; ++rep) {
      tick_update_msg m;
      m.server_tick = g.below(20) == 0 ? tick : ++tick;  // now and then a stale tick
      m.reset = g.below(50) == 0;
      if (m.reset) known.clear();
      for (std::size_t k = g.below(4); k-- > 0 && !known.empty();) {
        const std::size_t i = g.below(known.size());
        m.leaves.push_back(known[i]);
        known[i] = known.back();
        known.pop_back();
      }
      for (std::size_t k = g.below(rep < 20 ? 60 : 8); k-- > 0;) {
        entity_state s = g.state();
        s.id = 1 + static_cast<std::uint32_t>(g.below(5000));
        if (std::find(known.begin(), known.end(), s.id) == known.end()) known.push_back(s.id);
        m.enters.push_back(s);  // an id already known makes the update inconsistent, as it should
      }
      const std::size_t n_updates = g.below(4) == 0 ? g.below(3) : g.below(200);  // across batch edges
      for (std::size_t k = 0; k < n_updates; ++k) {
        std::uint32_t id = 0;
        if (!known.empty() && g.below(30) != 0) {
          id = known[g.below(known.size())];  // repeats happen
        } else {
          id = 100000 + static_cast<std::uint32_t>(g.below(100));  // unknown
        }
        const vec3f p{g.f(-500, 500), g.f(-500, 500), g.f(0, 50)};
        m.updates.push_back({id, q.quantize(p), quantize_velocity({g.f(-9, 9), g.f(-9, 9), 0})});
      }
      if (g.below(3) != 0) m.digest = verify_digest{m.server_tick, by_value.hash() + g.below(2), 0};
      const auto expected = by_value.apply(m);
      const auto frame = encode_frame(m);
      frame_decoder d(big_frames());
      d.feed(frame);
      const auto step = d.next();
      REQUIRE(step.is_frame());
      std::vector<std::pair<std::uint32_t, vec3f>> told;
      const auto got = by_wire.apply(
          *step.frame.envelope->message_as_tick_update(),
          [](void* ctx, std::uint32_t id, const vec3f& p, const vec3f&) {
            static_cast<std::vector<std::pair<std::uint32_t, vec3f>>*>(ctx)->emplace_back(id, p);
          },
          &told);
      CHECK(got == expected);
      CHECK(by_wire.last_bad_ids() == by_value.last_bad_ids());
      CHECK(by_wire.hash() == by_value.hash());
      REQUIRE(by_wire.size() == by_value.size());
      for (const auto& [id, e] : by_value.entities()) {
        const auto it = by_wire.entities().find(id);
        REQUIRE(it != by_wire.entities().end());
        CHECK(it->second.state == e.state);
        CHECK(it->second.last_tick == e.last_tick);
      }
      // Every known update was told, in frame order, at its dequantized position.
      std::vector<std::pair<std::uint32_t, vec3f>> told_updates(told.begin() + static_cast<std::ptrdiff_t>(
                                                                                    std::min(told.size(), m.enters.size())),
                                                                told.end());
      std::vector<std::pair<std::uint32_t, vec3f>> want;
      for (const auto& u : m.updates) {
        if (by_value.entities().count(u.id) == 1) want.emplace_back(u.id, q.dequantize(u.position));
      }
      CHECK(told_updates == want);
    }
  }

  TEST_CASE("player names: printable ASCII, 1 .. max bytes, no outer spaces; every byte value tried") {
    CHECK_FALSE(check_player_name("bot-17", 32).has_value());
    CHECK_FALSE(check_player_name("Ann Lee_2.0~", 32).has_value());
    CHECK_FALSE(check_player_name(std::string(32, 'x'), 32).has_value());
    CHECK(check_player_name(std::string(33, 'x'), 32).has_value());
    CHECK(check_player_name("", 32).has_value());
    CHECK(check_player_name(" a", 32).has_value());
    CHECK(check_player_name("a ", 32).has_value());
    for (int b = 0; b < 256; ++b) {
      CAPTURE(b);
      const std::string name = std::string("a") + static_cast<char>(b) + "z";
      CHECK(check_player_name(name, 32).has_value() == (b < 0x20 || b > 0x7e));
    }
  }

  TEST_CASE("escape_for_log: no control byte or non-ASCII byte survives, bounded, and it can be undone") {
    const std::uint64_t seed = fresh_seed();
    CAPTURE(seed);
    std::mt19937_64 rng(seed);
    const auto unescape = [](const std::string& e) {
      std::string out;
      for (std::size_t i = 0; i < e.size(); ++i) {
        if (e[i] != '\\') {
          out += e[i];
        } else if (e[i + 1] == '\\') {
          out += '\\';
          ++i;
        } else {
          REQUIRE(e[i + 1] == 'x');
          out += static_cast<char>(std::stoi(e.substr(i + 2, 2), nullptr, 16));
          i += 3;
        }
      }
      return out;
    };
    CHECK(escape_for_log("plain name") == "plain name");
    CHECK(escape_for_log("x\n[critical] INJECTED") == "x\\x0a[critical] INJECTED");
    CHECK(escape_for_log("a\\b") == "a\\\\b");
    CHECK(escape_for_log(std::string(100, 'q'), 10) == std::string(10, 'q') + "...(100 bytes)");
    for (int round = 0; round < 2000; ++round) {
      std::string s(rng() % 80, '\0');
      for (auto& c : s) c = static_cast<char>(rng() % 256);
      const std::size_t max = 1 + rng() % 64;
      const std::string e = escape_for_log(s, max);
      CHECK(e.size() <= 4 * max + 32);
      CHECK(std::all_of(e.begin(), e.end(), [](char c) { return c >= 0x20 && c <= 0x7e; }));
      if (s.size() <= max) {
        CHECK(unescape(e) == s);
      } else {
        CHECK(unescape(e.substr(0, e.rfind("...("))) == s.substr(0, max));
      }
    }
  }
}
