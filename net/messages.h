// The wire protocol's messages (docs/protocol.md): the protocol version, the frame prefix, and
// one plain value type per message of the schema (net/protocol.fbs; flatc generates
// protocol_generated.h, the zero-copy accessors in namespace zone::net::wire, into the build
// tree). The codec (net/codec.h) converts these values from and to frames.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <variant>
#include <vector>

#include "protocol_generated.h"

namespace zone::net {

/// Protocol version carried in hello and welcome; bumped on incompatible schema changes.
inline constexpr std::uint32_t protocol_version = 1;

/// Size of the little-endian length prefix of every frame (FlatBuffers' size-prefixed convention).
inline constexpr std::size_t frame_header_bytes = 4;

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
  /// The client applies class_changes_msg: a class change of an entity it holds comes as a note,
  /// not as a reset of its whole view (an older client never says so and gets the reset).
  bool class_changes = false;
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

/// The client leaves on purpose (a logout): its entity is removed at once, not kept for a resume.
struct leave_msg {
  friend bool operator==(const leave_msg&, const leave_msg&) = default;
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
  /// This server process: a random number drawn at its start, never 0 (0: an older server). A
  /// client tells a restarted server on the same address from the one it knew by it.
  std::uint64_t instance = 0;
  /// A world of zones: the token to say in a hello (at the world's gate, or the zone now serving
  /// the region) to get this entity back after its zone was lost; empty: none (a single zone).
  std::string resume_token;
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

/// Entities the client may hold changed visibility class at server_tick (docs/protocol.md).
struct class_note {
  std::uint32_t id = 0;
  std::uint32_t visibility_class = 0;
  friend bool operator==(const class_note&, const class_note&) = default;
};
struct class_changes_msg {
  std::uint64_t server_tick = 0;
  std::vector<class_note> notes;
  friend bool operator==(const class_changes_msg&, const class_changes_msg&) = default;
};

/// Any message; the alternatives are in the order of the schema's union (index + 1 = wire type).
using message = std::variant<hello_msg, input_msg, ping_msg, welcome_msg, tick_update_msg, pong_msg, error_msg,
                             teleport_msg, redirect_msg, set_visibility_msg, class_changes_msg, leave_msg>;

/// The wire type of a message value.
[[nodiscard]] wire::message type_of(const message& m);

/// Readable name of a wire type ("hello", "tick_update", ...; "unknown" otherwise).
[[nodiscard]] std::string_view type_name(wire::message t);

}  // namespace zone::net
