// The framing codec, message conversion and quantization of net/protocol.h.
#include "protocol.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <bit>
#include <limits>
#include <stdexcept>
#include <type_traits>

namespace zone::net {

namespace w = wire;

namespace {

// Smallest FlatBuffer with a file identifier: root offset + identifier.
constexpr std::size_t min_body_bytes = 2 * sizeof(flatbuffers::uoffset_t);

w::vec3 to_wire(const vec3f& v) { return w::vec3(v.x, v.y, v.z); }
vec3f from_wire(const w::vec3* v) { return v ? vec3f{v->x(), v->y(), v->z()} : vec3f{}; }

std::string from_wire(const flatbuffers::String* s) { return s ? s->str() : std::string(); }

w::entity_update to_wire(const entity_update& u) {
  return w::entity_update(u.id, w::qpos3(u.position[0], u.position[1], u.position[2]),
                          w::qvel3(u.velocity[0], u.velocity[1], u.velocity[2]));
}

flatbuffers::Offset<w::entity_state> build_entity_state(flatbuffers::FlatBufferBuilder& fbb, const entity_state& s) {
  const auto name = fbb.CreateString(s.name);
  const w::vec3 pos = to_wire(s.position), vel = to_wire(s.velocity), half = to_wire(s.presence_half_extent);
  return w::Createentity_state(fbb, s.id, s.kind, s.visibility_class, &pos, &vel, &half, name);
}

flatbuffers::Offset<void> build_body(flatbuffers::FlatBufferBuilder& fbb, const message& m) {
  return std::visit(
      [&](const auto& msg) -> flatbuffers::Offset<void> {
        using T = std::decay_t<decltype(msg)>;
        if constexpr (std::is_same_v<T, hello_msg>) {
          const auto name = fbb.CreateString(msg.name);
          const auto token = fbb.CreateString(msg.token);
          return w::Createhello(fbb, name, token, msg.protocol_version, msg.stealth, msg.team, msg.class_changes)
              .Union();
        } else if constexpr (std::is_same_v<T, input_msg>) {
          const w::vec3 move = to_wire(msg.move);
          return w::Createinput(fbb, msg.sequence, &move).Union();
        } else if constexpr (std::is_same_v<T, ping_msg>) {
          return w::Createping(fbb, msg.client_time_us).Union();
        } else if constexpr (std::is_same_v<T, welcome_msg>) {
          const w::bounds3 world(to_wire(msg.world.lo), to_wire(msg.world.hi));
          std::optional<w::vec3> spawn;
          if (msg.spawn_position) spawn = to_wire(*msg.spawn_position);
          flatbuffers::Offset<w::interest_rules> rules = 0;
          if (msg.rules) {
            const auto& r = *msg.rules;
            const auto tiers = fbb.CreateVector(r.npc_aoi_tiers);
            const w::vec3 aoi = to_wire(r.player_aoi), step = to_wire(r.quantization_step);
            rules = w::Createinterest_rules(fbb, &aoi, r.hysteresis, r.max_visible, r.player_class, r.player_sees, tiers,
                                            &step, r.update_near, r.update_mid, r.update_mid_period, r.update_far_period,
                                            r.byte_budget, r.send_every, r.digest_every, r.max_speed, r.allow_stealth,
                                            r.teams, r.visibility_cooldown);
          }
          const auto resume = msg.resume_token.empty() ? flatbuffers::Offset<flatbuffers::String>()
                                                       : fbb.CreateString(msg.resume_token);
          return w::Createwelcome(fbb, msg.entity_id, &world, msg.tick_rate_hz, msg.server_tick, msg.protocol_version,
                                  spawn ? &*spawn : nullptr, msg.host_clock, rules, msg.oracle_port, msg.instance,
                                  resume)
              .Union();
        } else if constexpr (std::is_same_v<T, tick_update_msg>) {
          std::vector<flatbuffers::Offset<w::entity_state>> enters;
          enters.reserve(msg.enters.size());
          for (const auto& s : msg.enters) enters.push_back(build_entity_state(fbb, s));
          std::vector<w::entity_update> updates;
          updates.reserve(msg.updates.size());
          for (const auto& u : msg.updates) updates.push_back(to_wire(u));
          const auto enters_v = enters.empty() ? 0 : fbb.CreateVector(enters);  // empty: absent, as tick_update_writer
          const auto leaves_v = msg.leaves.empty() ? 0 : fbb.CreateVector(msg.leaves);
          const auto updates_v = updates.empty() ? 0 : fbb.CreateVectorOfStructs(updates);
          std::optional<w::verify_digest> digest;
          if (msg.digest) digest.emplace(msg.digest->tick, msg.digest->hash, msg.digest->count);
          std::optional<w::vec3> self;
          if (msg.self_position) self = to_wire(*msg.self_position);
          std::optional<w::deferred_counts> deferred;
          if (msg.deferred) deferred.emplace(msg.deferred->enters, msg.deferred->leaves, msg.deferred->updates);
          return w::Createtick_update(fbb, msg.server_tick, msg.server_time_us, msg.last_input_sequence, enters_v,
                                      leaves_v, updates_v, digest ? &*digest : nullptr, msg.reset, self ? &*self : nullptr,
                                      deferred ? &*deferred : nullptr)
              .Union();
        } else if constexpr (std::is_same_v<T, pong_msg>) {
          return w::Createpong(fbb, msg.client_time_us, msg.server_time_us).Union();
        } else if constexpr (std::is_same_v<T, error_msg>) {
          const auto reason = fbb.CreateString(msg.reason);
          return w::Createerror(fbb, msg.code, reason).Union();
        } else if constexpr (std::is_same_v<T, teleport_msg>) {
          const w::vec3 position = to_wire(msg.position);
          return w::Createteleport(fbb, msg.sequence, &position, msg.entity_id).Union();
        } else if constexpr (std::is_same_v<T, set_visibility_msg>) {
          return w::Createset_visibility(fbb, msg.sequence, msg.stealth, msg.team).Union();
        } else if constexpr (std::is_same_v<T, class_changes_msg>) {
          std::vector<w::class_note> notes;
          notes.reserve(msg.notes.size());
          for (const auto& n : msg.notes) notes.emplace_back(n.id, n.visibility_class);
          const auto notes_v = fbb.CreateVectorOfStructs(notes);
          return w::Createclass_changes(fbb, msg.server_tick, notes_v).Union();
        } else if constexpr (std::is_same_v<T, leave_msg>) {
          return w::Createleave(fbb).Union();
        } else {
          static_assert(std::is_same_v<T, redirect_msg>);
          const auto host = fbb.CreateString(msg.host);
          const auto token = fbb.CreateString(msg.token);
          return w::Createredirect(fbb, host, msg.port, token).Union();
        }
      },
      m);
}

std::span<const std::uint8_t> finish_frame(flatbuffers::FlatBufferBuilder& fbb, w::message type,
                                           flatbuffers::Offset<void> body) {
  const auto env = w::Createenvelope(fbb, type, body);
  w::FinishSizePrefixedenvelopeBuffer(fbb, env);
  return {fbb.GetBufferPointer(), fbb.GetSize()};
}

bool known_type(w::message t) {
  return t != w::message::NONE && static_cast<std::uint8_t>(t) <= static_cast<std::uint8_t>(w::message::MAX);
}

/// Verifies one whole frame (prefix included) that starts 8-byte aligned and whose prefix says
/// `frame_len - 4`. Returns the envelope or the error.
std::variant<const w::envelope*, decode_error> verify_frame(const std::uint8_t* frame, std::size_t frame_len,
                                                            const decoder_options& opt) {
  if (frame_len < frame_header_bytes + min_body_bytes) return decode_error::verification_failed;
  flatbuffers::Verifier::Options vopt;
  vopt.max_depth = opt.max_depth;
  vopt.max_tables = opt.max_tables;
  vopt.check_alignment = true;
  flatbuffers::Verifier verifier(frame, frame_len, vopt);
  if (!w::VerifySizePrefixedenvelopeBuffer(verifier)) return decode_error::verification_failed;
  const w::envelope* env = w::GetSizePrefixedenvelope(frame);
  if (!known_type(env->message_type())) return decode_error::unknown_type;
  // A known type whose body is absent verifies (a null table is valid FlatBuffers) but is not a message.
  if (env->message() == nullptr) return decode_error::verification_failed;
  return env;
}

std::size_t read_prefix(const std::uint8_t* p) {
  return std::size_t{p[0]} | std::size_t{p[1]} << 8 | std::size_t{p[2]} << 16 | std::size_t{p[3]} << 24;
}

bool aligned8(const void* p) { return reinterpret_cast<std::uintptr_t>(p) % alignof(std::uint64_t) == 0; }

}  // namespace

// ---------------------------------------------------------------------------------------------

w::message type_of(const message& m) { return static_cast<w::message>(m.index() + 1); }

std::string_view type_name(w::message t) {
  if (!known_type(t)) return "unknown";
  return w::EnumNamemessage(t);
}

std::string_view to_string(decode_error e) {
  switch (e) {
    case decode_error::oversize: return "oversize frame";
    case decode_error::verification_failed: return "frame failed verification";
    case decode_error::unknown_type: return "unknown message type";
    case decode_error::truncated_at_close: return "stream closed inside a frame";
  }
  return "unknown decode error";
}

error_code to_error_code(decode_error e) {
  switch (e) {
    case decode_error::oversize: return error_code::oversize;
    case decode_error::verification_failed: return error_code::verification_failed;
    case decode_error::unknown_type: return error_code::unknown_type;
    case decode_error::truncated_at_close: return error_code::bad_frame;
  }
  return error_code::unspecified;
}

// ---- encoder --------------------------------------------------------------------------------

encoder::encoder(std::size_t initial_bytes) : fbb_(initial_bytes) {}
encoder::~encoder() = default;
encoder::encoder(encoder&&) noexcept = default;
encoder& encoder::operator=(encoder&&) noexcept = default;

std::span<const std::uint8_t> encoder::encode(const message& m) {
  if (const auto* t = std::get_if<tick_update_msg>(&m)) {
    // The canonical layout (canonical_tick_update), the same bytes as tick_update_writer's.
    if (!tick_) tick_ = std::make_unique<tick_update_writer>();
    tick_->begin(t->server_tick, t->server_time_us, t->last_input_sequence);
    for (const auto& s : t->enters) tick_->add_enter(s);
    for (const auto id : t->leaves) tick_->add_leave(id);
    for (const auto& u : t->updates) tick_->add_update(u);
    if (t->digest) tick_->set_digest(*t->digest);
    tick_->set_reset(t->reset);
    if (t->self_position) tick_->set_self_position(*t->self_position);
    if (t->deferred) tick_->set_deferred(*t->deferred);
    return tick_->finish();
  }
  fbb_.Clear();
  const auto body = build_body(fbb_, m);
  return finish_frame(fbb_, type_of(m), body);
}

std::span<const std::uint8_t> encoder::finish(w::message type, flatbuffers::Offset<void> body) {
  return finish_frame(fbb_, type, body);
}

std::vector<std::uint8_t> encode_frame(const message& m) {
  encoder e(256);
  const auto frame = e.encode(m);
  return {frame.begin(), frame.end()};
}

tick_update_writer::tick_update_writer(std::size_t initial_bytes) { out_.reserve((initial_bytes + 7) / 8); }

void tick_update_writer::begin(std::uint64_t server_tick, std::uint64_t server_time_us,
                               std::uint32_t last_input_sequence) {
  enters_.clear();
  names_.clear();
  leaves_.clear();
  updates_.clear();
  leaves_span_ = {};
  updates_span_ = {};
  enter_name_bytes_ = 0;
  digest_.reset();
  self_position_.reset();
  deferred_ = {};
  reset_ = false;
  tick_ = server_tick;
  time_us_ = server_time_us;
  last_input_ = last_input_sequence;
}

void tick_update_writer::add_enter(const entity_state& s) {
  enter_record r;
  r.id = s.id;
  r.visibility_class = s.visibility_class;
  r.position = to_wire(s.position);
  r.velocity = to_wire(s.velocity);
  r.half = to_wire(s.presence_half_extent);
  r.name_at = static_cast<std::uint32_t>(names_.size());
  r.name_length = static_cast<std::uint32_t>(s.name.size());
  r.kind = s.kind;
  names_ += s.name;
  enters_.push_back(r);
  enter_name_bytes_ += frame_cost::entity_name_cost(s.name.size());
}
void tick_update_writer::add_leave(std::uint32_t id) { leaves_.push_back(id); }

std::size_t tick_update_writer::size_estimate() const {
  return frame_cost::of(enters_.size(), leave_count(), update_count(), self_position_.has_value(), enter_name_bytes_);
}

namespace {
// Little-endian stores at byte offsets (the wire is little-endian; so are the hosts we build for).
static_assert(std::endian::native == std::endian::little, "the canonical writer stores host words as they are");
template <class T>
inline void put(std::uint8_t* base, std::size_t at, T v) {
  std::memcpy(base + at, &v, sizeof(T));
}
inline void put_vec3(std::uint8_t* base, std::size_t at, const w::vec3& v) {
  put(base, at, v.x());
  put(base, at + 4, v.y());
  put(base, at + 8, v.z());
}
}  // namespace

canonical_tick_update::parts tick_update_writer::frame_parts() const {
  canonical_tick_update::parts parts;
  parts.enters = !enters_.empty();
  parts.leaves = leave_count() != 0;
  parts.updates = update_count() != 0;
  parts.digest = digest_.has_value();
  parts.self = self_position_.has_value();
  parts.deferred = deferred_.any();
  parts.reset = reset_;
  return parts;
}

std::size_t tick_update_writer::frame_size() const {
  using c = canonical_tick_update;
  std::size_t names = 0;
  for (const auto& e : enters_) names += c::name_bytes(e.name_length);
  return c::size(frame_parts(), enters_.size(), leave_count(), update_count(), names);
}

std::span<const std::uint8_t> tick_update_writer::finish() {
  const std::size_t size = frame_size();
  out_.resize(size / 8);
  return finish_into({reinterpret_cast<std::uint8_t*>(out_.data()), size});
}

std::span<const std::uint8_t> tick_update_writer::finish_into(std::span<std::uint8_t> out) {
  using c = canonical_tick_update;
  const std::span<const std::uint32_t> leaves = leaves_span_.empty() ? std::span<const std::uint32_t>(leaves_) : leaves_span_;
  const std::span<const w::entity_update> updates =
      updates_span_.empty() ? std::span<const w::entity_update>(updates_) : updates_span_;
  std::size_t names = 0;
  for (const auto& e : enters_) names += c::name_bytes(e.name_length);
  const std::size_t n = enters_.size();
  const c::parts parts = frame_parts();
  const c::table_layout l = c::layout(parts);
  const std::size_t size = c::size(parts, n, leaves.size(), updates.size(), names);
  if (out.size() < size) throw std::length_error("tick_update_writer::finish_into: the buffer is smaller than the frame");
  std::uint8_t* const f = out.data();
  const std::size_t t = l.table_at;
  std::memset(f, 0, t + l.table_size);
  std::memset(f + size - 8, 0, 8);  // the tail padding (the content after it overwrites the rest)

  // Prefix, root offset, identifier.
  put<std::uint32_t>(f, 0, static_cast<std::uint32_t>(size - frame_header_bytes));
  put<std::uint32_t>(f, 4, 20 - 4);
  std::memcpy(f + 8, w::envelopeIdentifier(), 4);
  // Envelope vtable and table.
  put<std::uint16_t>(f, 12, 8);
  put<std::uint16_t>(f, 14, 12);
  put<std::uint16_t>(f, 16, 8);  // message_type
  put<std::uint16_t>(f, 18, 4);  // message
  put<std::int32_t>(f, 20, 20 - 12);
  put<std::uint32_t>(f, 24, static_cast<std::uint32_t>(t - 24));
  f[28] = static_cast<std::uint8_t>(w::message::tick_update);
  // tick_update vtable and table.
  constexpr std::size_t vt = c::vtable_at;
  put<std::uint16_t>(f, vt, static_cast<std::uint16_t>(l.vtable_size));
  put<std::uint16_t>(f, vt + 2, static_cast<std::uint16_t>(l.table_size));
  std::memcpy(f + vt + 4, l.field, l.vtable_size - 4);
  put<std::int32_t>(f, t, static_cast<std::int32_t>(t - vt));
  put<std::uint64_t>(f, t + l.field[0], tick_);
  put<std::uint64_t>(f, t + l.field[1], time_us_);
  put<std::uint32_t>(f, t + l.field[2], last_input_);
  if (parts.digest) {
    put<std::uint64_t>(f, t + l.field[6], digest_->tick);
    put<std::uint64_t>(f, t + l.field[6] + 8, digest_->hash);
    put<std::uint32_t>(f, t + l.field[6] + 16, digest_->count);
  }
  if (parts.self) put_vec3(f, t + l.field[8], to_wire(*self_position_));
  if (parts.deferred) {
    put<std::uint32_t>(f, t + l.field[9], deferred_.enters);
    put<std::uint32_t>(f, t + l.field[9] + 4, deferred_.leaves);
    put<std::uint32_t>(f, t + l.field[9] + 8, deferred_.updates);
  }
  if (parts.reset) f[t + l.field[7]] = 1;
  const bool has_enters = parts.enters, has_leaves = parts.leaves, has_updates = parts.updates;
  // The vectors.
  std::size_t at = t + l.table_size;
  const std::size_t enters_at = at;
  if (has_enters) {
    put<std::uint32_t>(f, t + l.field[3], static_cast<std::uint32_t>(at - (t + l.field[3])));
    at += 4 + 4 * n;
  }
  if (has_leaves) {
    put<std::uint32_t>(f, t + l.field[4], static_cast<std::uint32_t>(at - (t + l.field[4])));
    put<std::uint32_t>(f, at, static_cast<std::uint32_t>(leaves.size()));
    std::memcpy(f + at + 4, leaves.data(), leaves.size() * 4);
    at += 4 + 4 * leaves.size();
  }
  if (has_updates) {
    put<std::uint32_t>(f, t + l.field[5], static_cast<std::uint32_t>(at - (t + l.field[5])));
    put<std::uint32_t>(f, at, static_cast<std::uint32_t>(updates.size()));
    static_assert(sizeof(w::entity_update) == 16);
    std::memcpy(f + at + 4, updates.data(), updates.size() * 16);
    at += 4 + 16 * updates.size();
  }
  if (has_enters) {
    // One shared vtable, then each enter's table and name.
    const std::size_t evt = at;
    static_assert(sizeof c::enter_vtable_fields == c::enter_vtable);
    for (std::size_t k = 0; k < 10; ++k) put<std::uint16_t>(f, evt + 2 * k, c::enter_vtable_fields[k]);
    at += c::enter_vtable;
    put<std::uint32_t>(f, enters_at, static_cast<std::uint32_t>(n));
    for (std::size_t k = 0; k < n; ++k) {
      const auto& e = enters_[k];
      const std::size_t slot = enters_at + 4 + 4 * k;
      put<std::uint32_t>(f, slot, static_cast<std::uint32_t>(at - slot));
      put<std::int32_t>(f, at, static_cast<std::int32_t>(at - evt));
      put<std::uint32_t>(f, at + 4, e.id);
      put<std::uint32_t>(f, at + 8, e.visibility_class);
      put_vec3(f, at + 12, e.position);
      put_vec3(f, at + 24, e.velocity);
      put_vec3(f, at + 36, e.half);
      put<std::uint32_t>(f, at + 48, c::enter_table - 48);
      put<std::uint32_t>(f, at + 52, static_cast<std::uint32_t>(static_cast<std::uint8_t>(e.kind)));
      at += c::enter_table;
      const std::size_t nb = c::name_bytes(e.name_length);
      put<std::uint32_t>(f, at + nb - 4, 0);  // terminator and padding
      put<std::uint32_t>(f, at, e.name_length);
      std::memcpy(f + at + 4, names_.data() + e.name_at, e.name_length);
      at += nb;
    }
  }
  return {f, size};
}

// ---- conversion -----------------------------------------------------------------------------

std::optional<message> to_message(const w::envelope& env) {
  switch (env.message_type()) {
    case w::message::hello: {
      const auto* m = env.message_as_hello();
      if (!m) return std::nullopt;
      return hello_msg{from_wire(m->name()), from_wire(m->token()), m->protocol_version(), m->stealth(), m->team(),
                       m->class_changes()};
    }
    case w::message::input: {
      const auto* m = env.message_as_input();
      if (!m) return std::nullopt;
      return input_msg{m->sequence(), from_wire(m->move())};
    }
    case w::message::ping: {
      const auto* m = env.message_as_ping();
      if (!m) return std::nullopt;
      return ping_msg{m->client_time_us()};
    }
    case w::message::welcome: {
      const auto* m = env.message_as_welcome();
      if (!m) return std::nullopt;
      welcome_msg out;
      out.entity_id = m->entity_id();
      if (const auto* b = m->world()) out.world = {from_wire(&b->lo()), from_wire(&b->hi())};
      out.tick_rate_hz = m->tick_rate_hz();
      out.server_tick = m->server_tick();
      out.protocol_version = m->protocol_version();
      if (const auto* p = m->spawn_position()) out.spawn_position = from_wire(p);
      out.host_clock = m->host_clock();
      if (const auto* r = m->rules()) {
        interest_rules rules;
        if (const auto* a = r->player_aoi()) rules.player_aoi = from_wire(a);
        rules.hysteresis = r->hysteresis();
        rules.max_visible = r->max_visible();
        rules.player_class = r->player_class();
        rules.player_sees = r->player_sees();
        if (const auto* t = r->npc_aoi_tiers()) rules.npc_aoi_tiers.assign(t->begin(), t->end());
        if (const auto* q = r->quantization_step()) rules.quantization_step = from_wire(q);
        rules.update_near = r->update_near();
        rules.update_mid = r->update_mid();
        rules.update_mid_period = r->update_mid_period();
        rules.update_far_period = r->update_far_period();
        rules.byte_budget = r->byte_budget();
        rules.send_every = r->send_every();
        rules.digest_every = r->digest_every();
        rules.max_speed = r->max_speed();
        rules.allow_stealth = r->allow_stealth();
        rules.teams = r->teams();
        rules.visibility_cooldown = r->visibility_cooldown();
        out.rules = std::move(rules);
      }
      out.oracle_port = m->oracle_port();
      out.instance = m->instance();
      if (const auto* t = m->resume_token()) out.resume_token = t->str();
      return out;
    }
    case w::message::tick_update: {
      const auto* m = env.message_as_tick_update();
      if (!m) return std::nullopt;
      tick_update_msg out;
      out.server_tick = m->server_tick();
      out.server_time_us = m->server_time_us();
      out.last_input_sequence = m->last_input_sequence();
      if (const auto* v = m->enters()) {
        out.enters.reserve(v->size());
        for (const auto* s : *v) {
          if (!s) continue;
          out.enters.push_back({s->id(), s->kind(), s->visibility_class(), from_wire(s->position()),
                                from_wire(s->velocity()), from_wire(s->presence_half_extent()), from_wire(s->name())});
        }
      }
      if (const auto* v = m->leaves()) out.leaves.assign(v->begin(), v->end());
      if (const auto* v = m->updates()) {
        out.updates.reserve(v->size());
        for (const auto* u : *v) {
          out.updates.push_back({u->id(),
                                 {u->position().x(), u->position().y(), u->position().z()},
                                 {u->velocity().x(), u->velocity().y(), u->velocity().z()}});
        }
      }
      if (const auto* d = m->digest()) out.digest = verify_digest{d->tick(), d->hash(), d->count()};
      out.reset = m->reset();
      if (const auto* p = m->self_position()) out.self_position = from_wire(p);
      if (const auto* d = m->deferred()) out.deferred = deferred_counts{d->enters(), d->leaves(), d->updates()};
      return out;
    }
    case w::message::pong: {
      const auto* m = env.message_as_pong();
      if (!m) return std::nullopt;
      return pong_msg{m->client_time_us(), m->server_time_us()};
    }
    case w::message::error: {
      const auto* m = env.message_as_error();
      if (!m) return std::nullopt;
      return error_msg{m->code(), from_wire(m->reason())};
    }
    case w::message::teleport: {
      const auto* m = env.message_as_teleport();
      if (!m) return std::nullopt;
      // An absent position converts to NaN, so the server refuses it rather than jumping to 0,0,0.
      const float nan = std::numeric_limits<float>::quiet_NaN();
      return teleport_msg{m->sequence(), m->position() ? from_wire(m->position()) : vec3f{nan, nan, nan}, m->entity_id()};
    }
    case w::message::redirect: {
      const auto* m = env.message_as_redirect();
      if (!m) return std::nullopt;
      return redirect_msg{from_wire(m->host()), m->port(), from_wire(m->token())};
    }
    case w::message::set_visibility: {
      const auto* m = env.message_as_set_visibility();
      if (!m) return std::nullopt;
      return set_visibility_msg{m->sequence(), m->stealth(), m->team()};
    }
    case w::message::class_changes: {
      const auto* m = env.message_as_class_changes();
      if (!m) return std::nullopt;
      class_changes_msg out;
      out.server_tick = m->server_tick();
      if (const auto* v = m->notes()) {
        out.notes.reserve(v->size());
        for (const auto* n : *v) out.notes.push_back({n->id(), n->visibility_class()});
      }
      return out;
    }
    case w::message::leave: {
      if (!env.message_as_leave()) return std::nullopt;
      return leave_msg{};
    }
    default: return std::nullopt;
  }
}

decoded_message decode_frame(std::span<const std::uint8_t> frame, const decoder_options& opt) {
  if (frame.size() < frame_header_bytes) return {std::nullopt, decode_error::truncated_at_close};
  const std::size_t len = read_prefix(frame.data());
  if (len > opt.max_frame_bytes) return {std::nullopt, decode_error::oversize};
  if (frame.size() - frame_header_bytes < len) return {std::nullopt, decode_error::truncated_at_close};
  if (frame.size() - frame_header_bytes > len) return {std::nullopt, decode_error::verification_failed};
  std::vector<std::uint64_t> aligned;
  const std::uint8_t* p = frame.data();
  if (!aligned8(p)) {
    aligned.resize((frame.size() + 7) / 8);
    std::memcpy(aligned.data(), frame.data(), frame.size());
    p = reinterpret_cast<const std::uint8_t*>(aligned.data());
  }
  const auto verified = verify_frame(p, frame.size(), opt);
  if (const auto* e = std::get_if<decode_error>(&verified)) return {std::nullopt, *e};
  auto m = to_message(*std::get<const w::envelope*>(verified));
  if (!m) return {std::nullopt, decode_error::unknown_type};
  return {std::move(m), std::nullopt};
}

// ---- decoder --------------------------------------------------------------------------------

namespace {
// Pending bytes are kept from this offset of the inbox (whose memory is 16-byte aligned), so that
// a frame, prefix included, starts 8-byte aligned as FlatBuffers expects of a size-prefixed
// buffer; frames whose size is a multiple of 8 (all that FlatBufferBuilder makes with 8-byte
// fields) keep the next frame aligned too. Others are copied to aligned memory before verifying.
constexpr std::size_t inbox_headroom = 0;
}  // namespace

frame_decoder::frame_decoder(decoder_options opt) : opt_(opt), begin_(inbox_headroom), end_(inbox_headroom) {}

void frame_decoder::compact() {
  if (begin_ == inbox_headroom) return;
  const std::size_t pending = end_ - begin_;
  if (pending > 0) std::memmove(inbox_.data() + inbox_headroom, inbox_.data() + begin_, pending);
  begin_ = inbox_headroom;
  end_ = inbox_headroom + pending;
}

void frame_decoder::feed(std::span<const std::uint8_t> bytes) {
  if (bytes.empty()) return;
  const auto dst = prepare(bytes.size());
  std::memcpy(dst.data(), bytes.data(), bytes.size());
  commit(bytes.size());
}

std::span<std::uint8_t> frame_decoder::prepare(std::size_t max_bytes) {
  compact();
  if (inbox_.size() < end_ + max_bytes) inbox_.resize(end_ + max_bytes);
  return {inbox_.data() + end_, max_bytes};
}

void frame_decoder::commit(std::size_t received) { end_ = std::min(end_ + received, inbox_.size()); }

decode_step frame_decoder::fail(decode_error e) {
  failed_ = e;
  decode_step s;
  s.state = decode_step::status::error;
  s.error = e;
  return s;
}

decode_step frame_decoder::next() {
  if (failed_) return fail(*failed_);
  const std::size_t avail = end_ - begin_;
  if (avail < frame_header_bytes) return {};
  const std::uint8_t* frame = inbox_.data() + begin_;
  const std::size_t len = read_prefix(frame);
  // Rejected from the prefix alone: an oversize frame is never buffered.
  if (len > opt_.max_frame_bytes) return fail(decode_error::oversize);
  if (avail - frame_header_bytes < len) return {};

  const std::size_t frame_len = frame_header_bytes + len;
  begin_ += frame_len;
  if (!aligned8(frame)) {
    if (aligned_.size() * 8 < frame_len) aligned_.resize((frame_len + 7) / 8);
    std::memcpy(aligned_.data(), frame, frame_len);
    frame = reinterpret_cast<const std::uint8_t*>(aligned_.data());
  }
  const auto verified = verify_frame(frame, frame_len, opt_);
  if (const auto* e = std::get_if<decode_error>(&verified)) return fail(*e);
  decode_step s;
  s.state = decode_step::status::frame;
  s.frame.envelope = std::get<const w::envelope*>(verified);
  s.frame.type = s.frame.envelope->message_type();
  s.frame.bytes = {frame, frame_len};
  return s;
}

std::optional<decode_error> frame_decoder::close() {
  if (failed_) return failed_;
  if (end_ != begin_) {
    failed_ = decode_error::truncated_at_close;
    return failed_;
  }
  return std::nullopt;
}

// ---- quantization ---------------------------------------------------------------------------

position_quantizer::position_quantizer(const world_bounds& world) : world_(world) {
  const float lo[3] = {world.lo.x, world.lo.y, world.lo.z};
  const float hi[3] = {world.hi.x, world.hi.y, world.hi.z};
  for (int d = 0; d < 3; ++d) {
    const double extent = static_cast<double>(hi[d]) - static_cast<double>(lo[d]);
    step_[d] = std::isfinite(extent) && extent > 0 ? extent / 65535.0 : 0.0;
  }
}

vec3f position_quantizer::dequantize(const std::array<std::uint16_t, 3>& q) const {
  return {static_cast<float>(world_.lo.x + q[0] * step_[0]), static_cast<float>(world_.lo.y + q[1] * step_[1]),
          static_cast<float>(world_.lo.z + q[2] * step_[2])};
}

vec3f position_quantizer::max_error() const {
  // Half a step, plus one float ulp of the largest coordinate for the final rounding to float.
  const auto axis = [&](int d, float lo, float hi) {
    const float mag = std::max(std::fabs(lo), std::fabs(hi));
    return static_cast<float>(step_[d] / 2 + std::nextafter(mag, std::numeric_limits<float>::infinity()) - mag);
  };
  return {axis(0, world_.lo.x, world_.hi.x), axis(1, world_.lo.y, world_.hi.y), axis(2, world_.lo.z, world_.hi.z)};
}

vec3f dequantize_velocity(const std::array<std::int16_t, 3>& q) {
  return {static_cast<float>(q[0] / 100.0), static_cast<float>(q[1] / 100.0), static_cast<float>(q[2] / 100.0)};
}

verify_digest visible_digest(std::uint64_t tick, std::span<const std::uint32_t> ids) {
  std::uint64_t hash = 0;
  for (const std::uint32_t id : ids) hash = digest_add(hash, id);
  return {tick, hash, static_cast<std::uint32_t>(ids.size())};
}

// ---- client_view ----------------------------------------------------------------------------

client_view::status client_view::finish(std::uint64_t tick, const std::optional<verify_digest>& digest, bool consistent) {
  consistent = consistent && (!any_ || tick > last_tick_);
  any_ = true;
  last_tick_ = tick;
  ++applied_;
  status s = consistent ? status::ok : status::inconsistent;
  if (digest) {
    ++digests_checked_;
    if (s == status::ok && (digest->hash != hash_ || digest->count != entities_.size() || digest->tick != tick)) {
      s = status::digest_mismatch;
    }
  }
  if (s != status::ok) ++problems_;
  return s;
}

namespace {
constexpr std::size_t max_bad_ids = 16;
}

client_view::status client_view::apply(const tick_update_msg& m) {
  bad_ids_.clear();
  bool consistent = true;
  const auto bad = [&](std::uint32_t id) {
    consistent = false;
    if (bad_ids_.size() < max_bad_ids) bad_ids_.push_back(id);
  };
  if (m.reset) {
    entities_.clear();
    hash_ = 0;
  }
  if (m.self_position) {
    self_position_ = m.self_position;
    self_tick_ = m.server_tick;
  }
  for (const auto id : m.leaves) {
    if (entities_.erase(id) == 1) {
      hash_ = digest_remove(hash_, id);
    } else {
      bad(id);
    }
  }
  for (const auto& e : m.enters) {
    const auto [it, fresh] = entities_.try_emplace(e.id);
    if (fresh) {
      hash_ = digest_add(hash_, e.id);
    } else {
      bad(e.id);
    }
    it->second = {e, m.server_tick};
  }
  for (const auto& u : m.updates) {
    const auto it = entities_.find(u.id);
    if (it == entities_.end()) {
      bad(u.id);
      continue;
    }
    it->second.state.position = quantizer_.dequantize(u.position);
    it->second.state.velocity = dequantize_velocity(u.velocity);
    it->second.last_tick = m.server_tick;
  }
  return finish(m.server_tick, m.digest, consistent);
}

void client_view::note_class(std::uint32_t id, std::uint32_t visibility_class) {
  const auto it = entities_.find(id);
  if (it == entities_.end()) return;  // not held: the note was for a client that might hold it
  it->second.state.visibility_class = visibility_class;
  ++class_notes_applied_;
}

client_view::status client_view::finish_notes(std::uint64_t tick) {
  bad_ids_.clear();
  if (!any_ || tick > last_tick_) return status::ok;
  ++problems_;
  return status::inconsistent;
}

client_view::status client_view::apply(const class_changes_msg& m) {
  for (const class_note& n : m.notes) note_class(n.id, n.visibility_class);
  return finish_notes(m.server_tick);
}

client_view::status client_view::apply(const w::class_changes& c) {
  if (const auto* v = c.notes()) {
    for (const auto* n : *v) note_class(n->id(), n->visibility_class());
  }
  return finish_notes(c.server_tick());
}

client_view::status client_view::apply(const w::tick_update& u, position_visitor visit, void* ctx) {
  // The same steps as apply(const tick_update_msg&), reading the frame in place.
  bad_ids_.clear();
  bool consistent = true;
  const auto bad = [&](std::uint32_t id) {
    consistent = false;
    if (bad_ids_.size() < max_bad_ids) bad_ids_.push_back(id);
  };
  const std::uint64_t tick = u.server_tick();
  if (u.reset()) {
    entities_.clear();
    hash_ = 0;
  }
  if (const auto* p = u.self_position()) {
    self_position_ = from_wire(p);
    self_tick_ = tick;
  }
  if (const auto* v = u.leaves()) {
    for (const auto id : *v) {
      if (entities_.erase(id) == 1) {
        hash_ = digest_remove(hash_, id);
      } else {
        bad(id);
      }
    }
  }
  if (const auto* v = u.enters()) {
    for (const auto* e : *v) {
      if (!e) continue;
      const auto [it, fresh] = entities_.try_emplace(e->id());
      if (fresh) {
        hash_ = digest_add(hash_, e->id());
      } else {
        bad(e->id());
      }
      it->second = {{e->id(), e->kind(), e->visibility_class(), from_wire(e->position()), from_wire(e->velocity()),
                     from_wire(e->presence_half_extent()), from_wire(e->name())},
                    tick};
      if (visit && e->position()) visit(ctx, e->id(), it->second.state.position, it->second.state.presence_half_extent);
    }
  }
  if (const auto* v = u.updates()) {
    // Updates in batches of 64 (a typical frame in one): first the index slots of a batch are
    // prefetched, then its entries are looked up and prefetched, then applied in order. A bot's
    // view is cold when its frame comes (thousands of views share the cache), so taking a batch's
    // misses together rather than one after another is most of the cost saved. Updates neither
    // add nor remove entries, so the iterators of a batch stay valid; the order of effects (and
    // of bad ids) is unchanged.
    constexpr std::uint32_t batch = 64;
    id_map<entity>::iterator found[batch];
    const std::uint32_t n = v->size();
    for (std::uint32_t base = 0; base < n; base += batch) {
      const std::uint32_t m = std::min(batch, n - base);
      for (std::uint32_t j = 0; j < m; ++j) entities_.prefetch(v->Get(base + j)->id());
      for (std::uint32_t j = 0; j < m; ++j) {
        found[j] = entities_.find(v->Get(base + j)->id());
        if (found[j] != entities_.end()) {
          __builtin_prefetch(&found[j]->second.state.position, 1);
          __builtin_prefetch(&found[j]->second.last_tick, 1);
        }
      }
      for (std::uint32_t j = 0; j < m; ++j) {
        const auto* x = v->Get(base + j);
        const auto it = found[j];
        if (it == entities_.end()) {
          bad(x->id());
          continue;
        }
        const auto& q = x->position();
        const auto& qv = x->velocity();
        it->second.state.position = quantizer_.dequantize({q.x(), q.y(), q.z()});
        it->second.state.velocity = dequantize_velocity({qv.x(), qv.y(), qv.z()});
        it->second.last_tick = tick;
        if (visit) visit(ctx, x->id(), it->second.state.position, it->second.state.presence_half_extent);
      }
    }
  }
  std::optional<verify_digest> digest;
  if (const auto* d = u.digest()) digest = verify_digest{d->tick(), d->hash(), d->count()};
  return finish(tick, digest, consistent);
}

std::optional<std::string> check_player_name(std::string_view name, std::size_t max_bytes) {
  if (name.empty()) return std::string("empty name");
  if (name.size() > max_bytes) {
    return "name of " + std::to_string(name.size()) + " bytes (at most " + std::to_string(max_bytes) + ")";
  }
  for (std::size_t i = 0; i < name.size(); ++i) {
    const auto c = static_cast<unsigned char>(name[i]);
    if (c < 0x20 || c > 0x7e) {
      char buf[64];
      std::snprintf(buf, sizeof buf, "name byte %zu is 0x%02x (printable ASCII only)", i, c);
      return std::string(buf);
    }
  }
  if (name.front() == ' ' || name.back() == ' ') return std::string("name starts or ends with a space");
  return std::nullopt;
}

std::string escape_for_log(std::string_view s, std::size_t max_bytes) {
  static constexpr char hex[] = "0123456789abcdef";
  const std::size_t shown = std::min(s.size(), max_bytes);
  std::string out;
  out.reserve(shown + 16);
  for (std::size_t i = 0; i < shown; ++i) {
    const auto c = static_cast<unsigned char>(s[i]);
    if (c == '\\') {
      out += "\\\\";
    } else if (c >= 0x20 && c <= 0x7e) {
      out += static_cast<char>(c);
    } else {
      out += "\\x";
      out += hex[c >> 4];
      out += hex[c & 15];
    }
  }
  if (shown < s.size()) out += "...(" + std::to_string(s.size()) + " bytes)";
  return out;
}

}  // namespace zone::net
