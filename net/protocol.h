// Public API of the net layer's wire protocol: message types, the framing codec (pure: bytes in,
// messages or a typed error out; no sockets), position/velocity quantization and the visible-set
// digest that clients use to verify their view. See docs/protocol.md.
//
// The schema is net/protocol.fbs; flatc generates protocol_generated.h into the build tree at build
// time. Code that wants zero-copy access to a received frame uses the generated accessors
// (namespace zone::net::wire) on frame_view::envelope; everything else can use the plain value
// types below (`message`), which the encoder and `to_message` convert from and to.
#pragma once

#include <algorithm>
#include <array>
#include <bit>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <unordered_map>
#include <utility>
#include <variant>
#include <vector>

#include "protocol_generated.h"

namespace zone::net {

/// Protocol version carried in hello and welcome; bumped on incompatible schema changes.
inline constexpr std::uint32_t protocol_version = 1;

/// Size of the little-endian length prefix of every frame (FlatBuffers' size-prefixed convention).
inline constexpr std::size_t frame_header_bytes = 4;

// ---------------------------------------------------------------------------------------------
// Plain value types, one per message of the schema.

struct vec3f {
  float x = 0, y = 0, z = 0;
  friend bool operator==(const vec3f&, const vec3f&) = default;
};

struct world_bounds {
  vec3f lo{};
  vec3f hi{};
  friend bool operator==(const world_bounds&, const world_bounds&) = default;
};

using error_code = wire::error_code;
using entity_kind = wire::entity_kind;

// client -> server
struct hello_msg {
  std::string name;
  std::string token;
  std::uint32_t protocol_version = net::protocol_version;
  bool stealth = false;    ///< join stealthed (the zone may refuse: interest_rules::allow_stealth)
  std::uint8_t team = 0;   ///< 0 = none, 1 = red, 2 = blue (at most interest_rules::teams)
  friend bool operator==(const hello_msg&, const hello_msg&) = default;
};
struct input_msg {
  std::uint32_t sequence = 0;
  vec3f move{};  ///< movement intent; the server clamps its length to 1
  friend bool operator==(const input_msg&, const input_msg&) = default;
};
struct ping_msg {
  std::uint64_t client_time_us = 0;
  friend bool operator==(const ping_msg&, const ping_msg&) = default;
};
/// A teleport jump of the sender's own entity (entity_id 0 = own; any other id is refused).
struct teleport_msg {
  std::uint32_t sequence = 0;  ///< shares the input counter
  vec3f position{};            ///< target; the server clamps it into the world
  std::uint32_t entity_id = 0;
  friend bool operator==(const teleport_msg&, const teleport_msg&) = default;
};

/// Switch the sender's own visibility (hello's choices) during play; validated by the zone.
struct set_visibility_msg {
  std::uint32_t sequence = 0;  ///< shares the input counter
  bool stealth = false;
  std::uint8_t team = 0;
  friend bool operator==(const set_visibility_msg&, const set_visibility_msg&) = default;
};

// server -> client
/// The zone's interest rules, as the welcome tells them (see the schema's interest_rules).
struct interest_rules {
  vec3f player_aoi{60, 60, 60};
  float hysteresis = 4;
  std::uint32_t max_visible = 0;
  std::uint32_t player_class = 1;
  std::uint32_t player_sees = 0;
  std::vector<float> npc_aoi_tiers;
  vec3f quantization_step{};
  float update_near = 0, update_mid = 0;
  std::uint32_t update_mid_period = 1, update_far_period = 1;
  std::uint32_t byte_budget = 0;
  std::uint32_t send_every = 1;
  std::uint32_t digest_every = 1;
  float max_speed = 0;
  bool allow_stealth = false;       ///< a player may choose stealth
  std::uint8_t teams = 0;           ///< teams a player may join (0 none, 1 red, 2 red and blue)
  float visibility_cooldown = 0;    ///< seconds between two applied set_visibility of one client
  friend bool operator==(const interest_rules&, const interest_rules&) = default;
};
struct welcome_msg {
  std::uint32_t entity_id = 0;
  world_bounds world{};
  std::uint16_t tick_rate_hz = 30;
  std::uint64_t server_tick = 0;
  std::uint32_t protocol_version = net::protocol_version;
  std::optional<vec3f> spawn_position;  ///< where the client's entity starts
  bool host_clock = false;              ///< server_time_us is the host's CLOCK_MONOTONIC in microseconds
  std::optional<interest_rules> rules;  ///< the zone's interest rules
  std::uint16_t oracle_port = 0;        ///< loopback port of the ground-truth stream (0 = none)
  friend bool operator==(const welcome_msg&, const welcome_msg&) = default;
};
/// Full state of an entity entering a view.
struct entity_state {
  std::uint32_t id = 0;
  entity_kind kind = entity_kind::player;
  std::uint32_t visibility_class = 0;
  vec3f position{};
  vec3f velocity{};
  vec3f presence_half_extent{};
  std::string name;
  friend bool operator==(const entity_state&, const entity_state&) = default;
};
/// Quantized update of a visible entity (see position_quantizer, quantize_velocity).
struct entity_update {
  std::uint32_t id = 0;
  std::array<std::uint16_t, 3> position{};
  std::array<std::int16_t, 3> velocity{};
  friend bool operator==(const entity_update&, const entity_update&) = default;
};
/// Digest of an observer's visible set after `tick` (see visible_digest).
struct verify_digest {
  std::uint64_t tick = 0;
  std::uint64_t hash = 0;
  std::uint32_t count = 0;
  friend bool operator==(const verify_digest&, const verify_digest&) = default;
};
/// What a frame left for later because of the byte budget (see the schema).
struct deferred_counts {
  std::uint32_t enters = 0, leaves = 0, updates = 0;
  [[nodiscard]] bool any() const { return (enters | leaves | updates) != 0; }
  friend bool operator==(const deferred_counts&, const deferred_counts&) = default;
};
struct tick_update_msg {
  std::uint64_t server_tick = 0;
  std::uint64_t server_time_us = 0;
  std::uint32_t last_input_sequence = 0;
  std::vector<entity_state> enters;
  std::vector<std::uint32_t> leaves;
  std::vector<entity_update> updates;
  std::optional<verify_digest> digest;
  bool reset = false;  ///< drop the whole view before applying (a resync after lost frames)
  std::optional<vec3f> self_position;  ///< the observer's own position at server_tick (exact)
  std::optional<deferred_counts> deferred;  ///< what the byte budget left for later (absent: nothing)
  friend bool operator==(const tick_update_msg&, const tick_update_msg&) = default;
};
struct pong_msg {
  std::uint64_t client_time_us = 0;
  std::uint64_t server_time_us = 0;
  friend bool operator==(const pong_msg&, const pong_msg&) = default;
};
struct error_msg {
  error_code code = error_code::unspecified;
  std::string reason;
  friend bool operator==(const error_msg&, const error_msg&) = default;
};

/// A world's handoff moved the client's entity: reconnect to host:port with hello{token}.
struct redirect_msg {
  std::string host;
  std::uint16_t port = 0;
  std::string token;
  friend bool operator==(const redirect_msg&, const redirect_msg&) = default;
};

/// Any message; the alternatives are in the order of the schema's union (index + 1 = wire type).
using message =
    std::variant<hello_msg, input_msg, ping_msg, welcome_msg, tick_update_msg, pong_msg, error_msg, teleport_msg,
                 redirect_msg, set_visibility_msg>;

/// The wire type of a message value.
[[nodiscard]] wire::message type_of(const message& m);

/// Readable name of a wire type ("hello", "tick_update", ...; "unknown" otherwise).
[[nodiscard]] std::string_view type_name(wire::message t);

// ---------------------------------------------------------------------------------------------
// Encoding.

/// Builds frames: each a 4-byte little-endian length then one FlatBuffer (root `envelope`,
/// identifier "ZSV1"). The builder's memory is reused between frames; a returned span stays valid
/// until the next call on the same encoder. Not thread-safe: one encoder per thread.
class tick_update_writer;

class encoder {
 public:
  explicit encoder(std::size_t initial_bytes = 1024);
  ~encoder();
  encoder(encoder&&) noexcept;
  encoder& operator=(encoder&&) noexcept;

  /// Encodes one message as a complete frame (length prefix included).
  [[nodiscard]] std::span<const std::uint8_t> encode(const message& m);

  /// Low level, for callers that build a message body with the generated Create* functions:
  /// clear() resets the builder, then build the body on builder(), then finish(type, body).
  void clear() { fbb_.Clear(); }
  [[nodiscard]] flatbuffers::FlatBufferBuilder& builder() { return fbb_; }
  [[nodiscard]] std::span<const std::uint8_t> finish(wire::message type, flatbuffers::Offset<void> body);

 private:
  flatbuffers::FlatBufferBuilder fbb_;
  std::unique_ptr<tick_update_writer> tick_;  // tick_update messages: the canonical layout
};

/// Streams one tick_update into a frame without building a tick_update_msg first: the replication
/// step adds enters, leaves and updates as it decides them and can ask for the frame size so far
/// (for a per-client byte budget). Memory is reused between frames. Usage per frame:
/// begin(); add_*()...; finish(). A returned span is valid until the next begin().
/// The frame is written straight in the canonical tick_update layout (canonical_tick_update,
/// docs/protocol.md), not through a FlatBuffers builder: the same values give the same bytes
/// whoever writes them (the CPU replicator, the GPU replication engine from the same tables,
/// encoder::encode).
/// The closed-form cost model of a tick_update frame (prefix included): an upper bound on the
/// encoded size of a frame with these counts, whatever the values, field order of the builder
/// or vtable sharing. Replication decides its byte budget with it alone (on the CPU and on the
/// GPU alike: the same integers give the same decisions); tested against real frames in
/// tests/net/test_protocol.cpp. `name_bytes` is the sum of entity_name_cost over the enters'
/// names (0 when they have none, as replication sends them).
struct frame_cost {
  /// The header: envelope and tick_update tables with their vtables, the three vectors' length
  /// words and offsets with alignment, the digest, the deferred counts (16: the struct and its
  /// vtable slot), identifier and prefix.
  static constexpr std::size_t header = 212;
  static constexpr std::size_t self_position = 16;  ///< the optional self_position struct and its vtable slot
  /// One enter: its offset in the enters vector, the entity_state table with a vtable of its own
  /// (the builder may share it; the bound does not count on it) and an empty name string, with
  /// alignment padding.
  static constexpr std::size_t enter = 96;
  static constexpr std::size_t leave = sizeof(std::uint32_t);
  static constexpr std::size_t update = 16;  ///< sizeof(wire::entity_update)
  /// The extra bytes of a non-empty name: its characters and terminator, padded to 4.
  static constexpr std::size_t entity_name_cost(std::size_t length) { return length == 0 ? 0 : (length + 4) & ~std::size_t{3}; }
  static constexpr std::size_t of(std::size_t enters, std::size_t leaves, std::size_t updates, bool has_self,
                                  std::size_t name_bytes = 0) {
    return header + (has_self ? self_position : 0) + enters * enter + name_bytes + leaves * leave + updates * update;
  }
};

/// The canonical layout of a tick_update frame: one deterministic FlatBuffers serialization
/// (valid for any FlatBuffers reader and the verifier), written by tick_update_writer. Offsets in
/// bytes from the frame's first byte (the length prefix), which is 8-byte aligned:
///   0 length prefix, 4 root offset (16), 8 identifier "ZSV1";
///   12 envelope vtable (8 bytes), 20 envelope table (12: message offset, message type);
///   32 tick_update vtable: up to the last present field (at least the first three), zero for
///      absent ones, padded so that the table starts at 4 mod 8;
///   the tick_update table: its vtable offset, then the present fields in this order:
///      server_tick, server_time_us (always), digest, last_input_sequence (always), enters,
///      leaves, updates (offsets; present when not empty), self_position, deferred (when any
///      count is non-zero), reset (only when true; then padded to 4);
///   the enters' offsets vector, the leaves vector, the updates vector (each when not empty);
///   then, with enters, one entity_state vtable (20 bytes) shared by all enters, and per enter
///      its table (56 bytes: +4 id, +8 visibility_class, +12 position, +24 velocity,
///      +36 presence_half_extent, +48 name, +52 kind) followed by its name (always present,
///      padded to 4);
///   zero padding to a multiple of 8.
struct canonical_tick_update {
  static constexpr std::size_t vtable_at = 32;
  static constexpr std::size_t enter_vtable = 20;
  static constexpr std::size_t enter_table = 56;
  /// The enters' shared vtable, as written: its size, the table's size, then the entity_state
  /// fields' offsets in schema order (id, kind, visibility_class, position, velocity,
  /// presence_half_extent, name), and a zero pad to 20 bytes.
  static constexpr std::uint16_t enter_vtable_fields[10] = {4 + 2 * 7, enter_table, 4, 52, 8, 12, 24, 36, 48, 0};
  /// Which optional parts a frame has.
  struct parts {
    bool enters = false, leaves = false, updates = false, digest = false, self = false, deferred = false,
         reset = false;
  };
  /// The tick_update table's place and its fields' (0 = absent), in schema order, and its size.
  struct table_layout {
    std::size_t table_at = 0, table_size = 0, vtable_size = 0;
    std::uint16_t field[10] = {};
  };
  static constexpr table_layout layout(const parts& p) {
    table_layout l;
    const bool present[10] = {true, true, true, p.enters, p.leaves, p.updates, p.digest, p.reset, p.self, p.deferred};
    std::size_t fields = 3;
    for (std::size_t i = 3; i < 10; ++i) {
      if (present[i]) fields = i + 1;
    }
    l.vtable_size = 4 + 2 * fields;
    l.table_at = vtable_at + l.vtable_size;
    l.table_at += (12 - l.table_at % 8) % 8;  // 4 mod 8: the 8-byte fields after the vtable offset align
    std::size_t at = 4;
    const auto take = [&](std::size_t field, std::size_t bytes) {
      l.field[field] = static_cast<std::uint16_t>(at);
      at += bytes;
    };
    take(0, 8);
    take(1, 8);
    if (p.digest) take(6, 24);
    take(2, 4);
    if (p.enters) take(3, 4);
    if (p.leaves) take(4, 4);
    if (p.updates) take(5, 4);
    if (p.self) take(8, 12);
    if (p.deferred) take(9, 12);
    if (p.reset) take(7, 4);  // the byte and its padding
    l.table_size = at;
    return l;
  }
  /// Bytes of one enter's name string (length word, characters, terminator, padding to 4).
  static constexpr std::size_t name_bytes(std::size_t length) { return 4 + ((length + 4) & ~std::size_t{3}); }
  /// The exact size of a frame (prefix included) with these parts and counts; `names` is the sum
  /// of name_bytes over the enters.
  static constexpr std::size_t size(const parts& p, std::size_t enters, std::size_t leaves, std::size_t updates,
                                    std::size_t names) {
    const table_layout l = layout(p);
    const std::size_t n = l.table_at + l.table_size +
                          (enters != 0 ? 4 + 4 * enters + enter_vtable + enter_table * enters + names : 0) +
                          (leaves != 0 ? 4 + 4 * leaves : 0) + (updates != 0 ? 4 + 16 * updates : 0);
    return (n + 7) & ~std::size_t{7};
  }
};

class tick_update_writer {
 public:
  explicit tick_update_writer(std::size_t initial_bytes = 4096);

  void begin(std::uint64_t server_tick, std::uint64_t server_time_us, std::uint32_t last_input_sequence = 0);
  void add_enter(const entity_state& s);
  void add_leave(std::uint32_t id);
  void add_update(const entity_update& u) {
    updates_.emplace_back(u.id, wire::qpos3(u.position[0], u.position[1], u.position[2]),
                          wire::qvel3(u.velocity[0], u.velocity[1], u.velocity[2]));
  }
  /// The same with the update already in its wire form (16 bytes, copied as is).
  void add_wire_update(const wire::entity_update& u) { updates_.push_back(u); }
  void set_digest(const verify_digest& d) { digest_ = d; }
  void set_reset(bool reset) { reset_ = reset; }
  /// The observer's own position at this tick (12 bytes; lets a client check its view exactly).
  void set_self_position(const vec3f& p) { self_position_ = p; }
  /// What the budget left for later (written only when any count is non-zero; frame_cost's header
  /// has room for it).
  void set_deferred(const deferred_counts& d) { deferred_ = d; }
  /// Leaves and updates taken from the caller's arrays instead of add_leave/add_wire_update
  /// (which must not be called in the same frame): the spans must stay valid until finish(), which
  /// copies them into the frame as they are (the GPU replication path hands over its slices).
  void set_leaves(std::span<const std::uint32_t> ids) { leaves_span_ = ids; }
  void set_wire_updates(std::span<const wire::entity_update> updates) { updates_span_ = updates; }
  /// Upper bound on the bytes of the frame if finish() were called now (prefix included). A closed
  /// form of the counts (frame_cost): it never reads the builder, so a device can compute it too.
  [[nodiscard]] std::size_t size_estimate() const;
  [[nodiscard]] std::size_t enter_count() const { return enters_.size(); }
  [[nodiscard]] std::size_t leave_count() const { return leaves_.size() + leaves_span_.size(); }
  [[nodiscard]] std::size_t update_count() const { return updates_.size() + updates_span_.size(); }
  [[nodiscard]] std::span<const std::uint8_t> finish();

 private:
  struct enter_record {
    std::uint32_t id = 0, visibility_class = 0;
    wire::vec3 position, velocity, half;
    std::uint32_t name_at = 0, name_length = 0;  // in names_
    entity_kind kind = entity_kind::player;
  };
  std::vector<std::uint64_t> out_;  // the frame (8-byte aligned)
  std::uint64_t tick_ = 0, time_us_ = 0;
  std::uint32_t last_input_ = 0;
  std::vector<enter_record> enters_;
  std::string names_;
  std::vector<std::uint32_t> leaves_;
  std::vector<wire::entity_update> updates_;
  std::span<const std::uint32_t> leaves_span_;
  std::span<const wire::entity_update> updates_span_;
  std::size_t enter_name_bytes_ = 0;  // frame_cost's name term, summed over the enters
  std::optional<verify_digest> digest_;
  std::optional<vec3f> self_position_;
  deferred_counts deferred_{};
  bool reset_ = false;
};

/// Convenience: one message as a new frame (allocates; use encoder in hot paths).
[[nodiscard]] std::vector<std::uint8_t> encode_frame(const message& m);

// ---------------------------------------------------------------------------------------------
// Decoding.

/// Why a stream was rejected. After an error the stream cannot be resynchronised: the decoder
/// stays failed (every later next() returns the same error) and the connection should be closed.
enum class decode_error : std::uint8_t {
  oversize,             ///< the length prefix exceeds max_frame_bytes (detected from the prefix alone)
  verification_failed,  ///< the FlatBuffers verifier rejected the frame (or its identifier/length)
  unknown_type,         ///< verified, but the envelope's message type is NONE or unknown to us
  truncated_at_close,   ///< the stream closed in the middle of a frame
};

[[nodiscard]] std::string_view to_string(decode_error e);

/// The wire error code a server sends for a decode error.
[[nodiscard]] error_code to_error_code(decode_error e);

struct decoder_options {
  /// Largest accepted frame body (excluding the 4-byte prefix). Inbound client messages are tiny;
  /// a client-side decoder for tick updates wants a larger limit.
  std::size_t max_frame_bytes = 16 * 1024;
  /// FlatBuffers verifier limits.
  std::uint32_t max_depth = 16;
  std::uint32_t max_tables = 100000;
};

/// One verified frame. The pointers and spans point into the decoder's memory and stay valid
/// until the next call of feed(), prepare(), commit() or next() on that decoder.
struct frame_view {
  wire::message type = wire::message::NONE;
  /// The whole frame, length prefix included, 8-byte aligned (FlatBuffers aligns a size-prefixed
  /// buffer from its prefix, so the prefix is verified with the body). Can be forwarded as is.
  std::span<const std::uint8_t> bytes;
  const wire::envelope* envelope = nullptr;  ///< verified root
};

/// Result of decoder::next().
struct decode_step {
  enum class status : std::uint8_t { frame, need_more, error };
  status state = status::need_more;
  frame_view frame{};        ///< when state == frame
  decode_error error{};      ///< when state == error
  [[nodiscard]] bool is_frame() const { return state == status::frame; }
  [[nodiscard]] bool is_error() const { return state == status::error; }
  [[nodiscard]] bool needs_more() const { return state == status::need_more; }
};

/// Streaming frame decoder: bytes arrive in arbitrary chunks (a frame may be split anywhere, a
/// chunk may hold many frames); next() returns complete, verified frames in order. Never reads
/// past the bytes it was given; the memory it holds is bounded by max_frame_bytes plus the bytes
/// fed but not yet consumed by next(). Not thread-safe: one decoder per connection.
class frame_decoder {
 public:
  explicit frame_decoder(decoder_options opt = {});

  /// Appends received bytes (copied).
  void feed(std::span<const std::uint8_t> bytes);
  /// Zero-copy receive: a writable span of `max_bytes` to read into, then commit(received).
  [[nodiscard]] std::span<std::uint8_t> prepare(std::size_t max_bytes);
  void commit(std::size_t received);

  /// The next complete frame, or need_more, or the stream's error. Call until need_more after each feed.
  [[nodiscard]] decode_step next();

  /// The stream closed: returns truncated_at_close when part of a frame is pending (or the
  /// earlier error when the decoder already failed), nothing on a clean close.
  [[nodiscard]] std::optional<decode_error> close();

  [[nodiscard]] bool failed() const { return failed_.has_value(); }
  /// Bytes received but not yet returned as frames.
  [[nodiscard]] std::size_t pending_bytes() const { return end_ - begin_; }
  [[nodiscard]] const decoder_options& options() const { return opt_; }

 private:
  decode_step fail(decode_error e);
  void compact();
  decoder_options opt_;
  std::vector<std::uint8_t> inbox_;   // received bytes; [begin_, end_) not yet consumed
  std::size_t begin_ = 0, end_ = 0;
  std::vector<std::uint64_t> aligned_;  // 8-byte aligned copy of a frame that sits misaligned in the inbox
  std::optional<decode_error> failed_;
};

/// Converts a verified envelope to its value type (copies strings and vectors).
/// Returns nothing when the envelope's type is NONE or unknown.
[[nodiscard]] std::optional<message> to_message(const wire::envelope& env);

/// Verifies and converts exactly one complete frame (length prefix included): the one-shot path.
/// A prefix that disagrees with the span's size is verification_failed (truncated_at_close when
/// the span is shorter than the prefix says).
struct decoded_message {
  std::optional<message> value;
  std::optional<decode_error> error;
};
[[nodiscard]] decoded_message decode_frame(std::span<const std::uint8_t> frame, const decoder_options& opt = {});

// ---------------------------------------------------------------------------------------------
// Quantization.

/// Positions as 16 bits per axis relative to the world bounds: q = round((p - lo) / step) with
/// step = (hi - lo) / 65535, clamped to [0, 65535] (positions outside the bounds clamp to them).
/// Round-trip error per axis for a position inside the bounds: at most max_error() = step / 2
/// plus float rounding (a few ulps of the coordinate). A zero-width axis always decodes to lo.
class position_quantizer {
 public:
  explicit position_quantizer(const world_bounds& world);
  /// Inline (replication quantizes every update it sends); exactly the rounding of std::lround.
  [[nodiscard]] std::array<std::uint16_t, 3> quantize(const vec3f& p) const;
  [[nodiscard]] vec3f dequantize(const std::array<std::uint16_t, 3>& q) const;
  /// Guaranteed bound on |dequantize(quantize(p)) - p| per axis for p inside the bounds.
  [[nodiscard]] vec3f max_error() const;
  [[nodiscard]] const world_bounds& world() const { return world_; }
  /// The step of axis 0, 1 or 2 (0 for a zero-width or non-finite axis): what a device quantizing
  /// the same way needs (gpu/replication_shared.h).
  [[nodiscard]] double step(int axis) const { return step_[axis]; }

 private:
  world_bounds world_;
  double step_[3];
};

/// Velocity in centimetres per second per axis, clamped to [-32767, 32767] (+-327.67 m/s).
/// Round-trip error within the range: at most velocity_max_error = 0.005 m/s (plus float rounding).
inline constexpr float velocity_max_error = 0.005f;
inline constexpr float velocity_limit = 327.67f;
[[nodiscard]] std::array<std::int16_t, 3> quantize_velocity(const vec3f& v);
[[nodiscard]] vec3f dequantize_velocity(const std::array<std::int16_t, 3>& q);

namespace detail {
/// std::lround(t) for 0 <= t < 2^31 without the library call: round half away from zero.
/// t - trunc(t) is exact in double, so the comparison with 0.5 decides exactly as lround does.
inline std::uint32_t round_half_up(double t) {
  const auto i = static_cast<std::uint32_t>(t);
  return i + (t - static_cast<double>(i) >= 0.5 ? 1u : 0u);
}
}  // namespace detail

inline std::array<std::uint16_t, 3> position_quantizer::quantize(const vec3f& p) const {
  const float v[3] = {p.x, p.y, p.z};
  const float lo[3] = {world_.lo.x, world_.lo.y, world_.lo.z};
  std::array<std::uint16_t, 3> q{};
  for (int d = 0; d < 3; ++d) {
    if (step_[d] <= 0) continue;
    const double t = (static_cast<double>(v[d]) - static_cast<double>(lo[d])) / step_[d];
    // NaN and below-range clamp to 0, above-range to 65535.
    q[d] = !(t > 0) ? 0 : t >= 65535.0 ? 65535 : static_cast<std::uint16_t>(detail::round_half_up(t));
  }
  return q;
}

inline std::array<std::int16_t, 3> quantize_velocity(const vec3f& v) {
  const auto axis = [](float x) -> std::int16_t {
    const double t = static_cast<double>(x) * 100.0;
    if (!(t == t)) return 0;  // NaN
    const double c = std::clamp(t, -32767.0, 32767.0);
    const auto r = static_cast<std::int32_t>(detail::round_half_up(c < 0 ? -c : c));
    return static_cast<std::int16_t>(c < 0 ? -r : r);
  };
  return {axis(v.x), axis(v.y), axis(v.z)};
}

// ---------------------------------------------------------------------------------------------
// Visible-set digest.

/// Order-independent hash of a set of entity ids: the sum (mod 2^64) of a 64-bit mix of each id.
/// A client keeps it incrementally (add on enter, remove on leave) and compares it with the
/// server's verify_digest; the server computes it from the sorted visible set.
[[nodiscard]] constexpr std::uint64_t digest_mix(std::uint32_t id) {
  std::uint64_t z = std::uint64_t{id} + 0x9e3779b97f4a7c15ull;  // splitmix64 finaliser
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}
[[nodiscard]] constexpr std::uint64_t digest_add(std::uint64_t hash, std::uint32_t id) { return hash + digest_mix(id); }
[[nodiscard]] constexpr std::uint64_t digest_remove(std::uint64_t hash, std::uint32_t id) { return hash - digest_mix(id); }
/// The digest of a whole set (any order; ids assumed distinct).
[[nodiscard]] verify_digest visible_digest(std::uint64_t tick, std::span<const std::uint32_t> ids);

// ---------------------------------------------------------------------------------------------
// The client side of replication.

/// A hash map from 32-bit ids to values: the values in one dense array (iteration runs over it;
/// erase moves the last value into the hole) and an open-addressing index of (id, position)
/// pairs with linear probing and backward-shift deletion (load at most 1/2), so a lookup touches
/// a cache line or two rather than a bucket and a node. The client view's entity table: a bot
/// swarm looks entities up hundreds of thousands of times a second. Any id, 0 included.
/// try_emplace and erase invalidate iterators and references; iteration order is unspecified.
template <class V>
class id_map {
 public:
  using value_type = std::pair<std::uint32_t, V>;
  using iterator = typename std::vector<value_type>::iterator;
  using const_iterator = typename std::vector<value_type>::const_iterator;

  [[nodiscard]] std::size_t size() const { return values_.size(); }
  [[nodiscard]] bool empty() const { return values_.empty(); }
  iterator begin() { return values_.begin(); }
  iterator end() { return values_.end(); }
  const_iterator begin() const { return values_.begin(); }
  const_iterator end() const { return values_.end(); }

  iterator find(std::uint32_t id) {
    const std::size_t i = slot_of(id);
    return i == npos ? values_.end() : values_.begin() + static_cast<std::ptrdiff_t>(slots_[i].at - 1);
  }
  const_iterator find(std::uint32_t id) const {
    const std::size_t i = slot_of(id);
    return i == npos ? values_.end() : values_.begin() + static_cast<std::ptrdiff_t>(slots_[i].at - 1);
  }
  [[nodiscard]] std::size_t count(std::uint32_t id) const { return slot_of(id) == npos ? 0 : 1; }

  /// A cache hint only (contents unchanged): starts fetching the index slot where a lookup of
  /// `id` begins, so that a batch of lookups overlaps its cache misses instead of taking them in turn.
  void prefetch(std::uint32_t id) const {
    if (!slots_.empty()) __builtin_prefetch(&slots_[home(id)]);
  }

  /// The entry of `id`, appended with a value-initialised V when absent (second: inserted).
  std::pair<iterator, bool> try_emplace(std::uint32_t id) {
    if ((values_.size() + 1) * 2 > slots_.size()) rehash(std::max<std::size_t>(64, slots_.size() * 2));
    const std::size_t mask = slots_.size() - 1;
    for (std::size_t i = home(id);; i = (i + 1) & mask) {
      if (slots_[i].at == 0) {
        values_.emplace_back(id, V{});
        slots_[i] = {id, static_cast<std::uint32_t>(values_.size())};
        return {values_.end() - 1, true};
      }
      if (slots_[i].id == id) return {values_.begin() + static_cast<std::ptrdiff_t>(slots_[i].at - 1), false};
    }
  }

  /// Removes `id`; returns how many entries were removed (0 or 1).
  std::size_t erase(std::uint32_t id) {
    std::size_t i = slot_of(id);
    if (i == npos) return 0;
    const std::uint32_t at = slots_[i].at;
    // Backward shift: move later entries of the probe run into the hole when their home allows.
    const std::size_t mask = slots_.size() - 1;
    for (std::size_t j = (i + 1) & mask; slots_[j].at != 0; j = (j + 1) & mask) {
      const std::size_t k = home(slots_[j].id);
      if (i <= j ? (k <= i || k > j) : (k <= i && k > j)) {
        slots_[i] = slots_[j];
        i = j;
      }
    }
    slots_[i] = {};
    // The last value fills the erased one's place.
    if (at != values_.size()) {
      values_[at - 1] = std::move(values_.back());
      slots_[slot_of(values_[at - 1].first)].at = at;
    }
    values_.pop_back();
    return 1;
  }

  void clear() {
    values_.clear();
    std::fill(slots_.begin(), slots_.end(), slot{});
  }

 private:
  struct slot {
    std::uint32_t id = 0;
    std::uint32_t at = 0;  ///< 1 + position in values_; 0 = empty
  };
  static constexpr std::size_t npos = static_cast<std::size_t>(-1);
  [[nodiscard]] std::size_t home(std::uint32_t id) const {
    // Fibonacci hashing: the top bits of id * 2^64/phi.
    return static_cast<std::size_t>((std::uint64_t{id} * 0x9e3779b97f4a7c15ull) >> shift_);
  }
  [[nodiscard]] std::size_t slot_of(std::uint32_t id) const {
    if (values_.empty()) return npos;
    const std::size_t mask = slots_.size() - 1;
    for (std::size_t i = home(id); slots_[i].at != 0; i = (i + 1) & mask) {
      if (slots_[i].id == id) return i;
    }
    return npos;
  }
  void rehash(std::size_t capacity) {
    slots_.assign(capacity, slot{});
    shift_ = 64 - static_cast<unsigned>(std::countr_zero(capacity));
    const std::size_t mask = capacity - 1;
    for (std::size_t k = 0; k < values_.size(); ++k) {
      std::size_t i = home(values_[k].first);
      while (slots_[i].at != 0) i = (i + 1) & mask;
      slots_[i] = {values_[k].first, static_cast<std::uint32_t>(k + 1)};
    }
  }

  std::vector<value_type> values_;
  std::vector<slot> slots_;
  unsigned shift_ = 64;
};

/// A client's picture of the zone, built only from the tick updates it receives: reset clears it,
/// leaves remove, enters add (full state), updates refresh quantized position and velocity. Each
/// update is checked: leaves and updates must name known entities, enters new ones, ticks must
/// increase, and the verify digest (when present) must equal the view's own. Used by bots and
/// tests to prove that what the server sent adds up. Not thread-safe.
class client_view {
 public:
  explicit client_view(const world_bounds& world) : quantizer_(world) {}

  enum class status : std::uint8_t {
    ok,
    inconsistent,     ///< leave/update of an unknown id, enter of a known id, or a tick not after the last
    digest_mismatch,  ///< the view does not hash to the server's digest
  };
  struct entity {
    entity_state state;          ///< as entered; position and velocity refreshed by updates
    std::uint64_t last_tick = 0;  ///< tick of the last enter or update
  };

  /// Called for each position an update tells, after the view holds it: enters with their exact
  /// position, updates dequantized; with the entity's presence half-extent. `ctx` is the caller's.
  /// The visitor must not change the view.
  using position_visitor = void (*)(void* ctx, std::uint32_t id, const vec3f& position, const vec3f& presence_half_extent);

  /// Applies one update (the whole update is applied even when a check fails).
  status apply(const tick_update_msg& m);
  /// The same on a verified frame's tick_update, read in place (no copy of the frame), calling
  /// `visit` (when given) for every position told: one lookup per entity for view and caller.
  status apply(const wire::tick_update& u, position_visitor visit = nullptr, void* ctx = nullptr);
  /// The ids that made the last apply() inconsistent (unknown leaves and updates, known or
  /// repeated enters; at most 16), empty after a consistent one.
  [[nodiscard]] const std::vector<std::uint32_t>& last_bad_ids() const { return bad_ids_; }

  [[nodiscard]] const id_map<entity>& entities() const { return entities_; }
  [[nodiscard]] std::size_t size() const { return entities_.size(); }
  [[nodiscard]] std::uint64_t hash() const { return hash_; }
  [[nodiscard]] std::uint64_t last_tick() const { return last_tick_; }
  /// The observer's own position from the last update that carried one, and that update's tick.
  [[nodiscard]] const std::optional<vec3f>& self_position() const { return self_position_; }
  [[nodiscard]] std::uint64_t self_position_tick() const { return self_tick_; }
  [[nodiscard]] std::uint64_t updates_applied() const { return applied_; }
  [[nodiscard]] std::uint64_t digests_checked() const { return digests_checked_; }
  [[nodiscard]] std::uint64_t problems() const { return problems_; }
  [[nodiscard]] const position_quantizer& quantizer() const { return quantizer_; }

 private:
  status finish(std::uint64_t tick, const std::optional<verify_digest>& digest, bool consistent);
  position_quantizer quantizer_;
  id_map<entity> entities_;
  std::uint64_t hash_ = 0;
  std::uint64_t last_tick_ = 0;
  std::optional<vec3f> self_position_;
  std::uint64_t self_tick_ = 0;
  std::vector<std::uint32_t> bad_ids_;
  bool any_ = false;
  std::uint64_t applied_ = 0, digests_checked_ = 0, problems_ = 0;
};

// ---------------------------------------------------------------------------------------------
// Client strings: what the server accepts, and how it logs them.

/// Why `name` is not an acceptable player name, or nothing when it is: 1 .. max_bytes bytes of
/// printable ASCII (0x20-0x7E), no leading or trailing space. Pure; any bytes are safe input.
[[nodiscard]] std::optional<std::string> check_player_name(std::string_view name, std::size_t max_bytes);

/// A client-supplied string made safe for one log line: printable ASCII except the backslash is
/// kept, every other byte (newlines, escape sequences, UTF-8, NUL) is written as \xNN and the
/// backslash as \\; at most `max_bytes` input bytes are shown, then "...(N bytes)". The result
/// holds no byte below 0x20 or above 0x7E and is at most 4 * max_bytes + 32 bytes long.
[[nodiscard]] std::string escape_for_log(std::string_view s, std::size_t max_bytes = 64);

}  // namespace zone::net
