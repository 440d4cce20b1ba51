// The framing codec of the wire protocol (docs/protocol.md): pure, bytes in, messages or a typed
// error out; no sockets. Encoding (encoder, the canonical tick_update layout and its writer, the
// frame cost model) and decoding (the streaming frame decoder, the one-shot decode_frame).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string_view>
#include <vector>

#include "net/messages.h"

namespace zone::net {

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
  /// The frame in the writer's own buffer (valid until the next begin() or finish()).
  [[nodiscard]] std::span<const std::uint8_t> finish();
  /// The exact size of the frame finish() would write now (prefix included; a multiple of 8).
  [[nodiscard]] std::size_t frame_size() const;
  /// finish() straight into the caller's memory (at least frame_size() bytes; every byte of the
  /// frame is written, none after it): the same bytes, without the copy out of the writer's
  /// buffer (the zone server writes each frame into the block its session then holds,
  /// net::frame_arena::reserve). Returns the frame, a prefix of `out`. Throws
  /// std::length_error when `out` is too small.
  std::span<const std::uint8_t> finish_into(std::span<std::uint8_t> out);

 private:
  struct enter_record {
    std::uint32_t id = 0, visibility_class = 0;
    wire::vec3 position, velocity, half;
    std::uint32_t name_at = 0, name_length = 0;  // in names_
    entity_kind kind = entity_kind::player;
  };
  [[nodiscard]] canonical_tick_update::parts frame_parts() const;
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

}  // namespace zone::net
