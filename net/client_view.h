// The client side of replication (docs/protocol.md): a client's picture of the zone, built and
// checked from the tick updates it receives.
#pragma once

#include <cstdint>
#include <optional>
#include <vector>

#include "net/id_map.h"
#include "net/messages.h"
#include "net/quantizer.h"

namespace zone::net {

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
  /// Applies a class change (sent before the tick_update of its server_tick): every note whose id
  /// the view holds sets that entity's class; other ids are ignored (the server sends notes to
  /// every client that may hold the entity). Inconsistent when it is not newer than the last
  /// tick applied (the server sends it before that tick's update). Counts as no update.
  status apply(const class_changes_msg& m);
  /// The same on a verified frame, read in place.
  status apply(const wire::class_changes& c);
  /// Notes that found their entity held (the others were ignored).
  [[nodiscard]] std::uint64_t class_notes_applied() const { return class_notes_applied_; }
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
  void note_class(std::uint32_t id, std::uint32_t visibility_class);
  status finish_notes(std::uint64_t tick);
  position_quantizer quantizer_;
  id_map<entity> entities_;
  std::uint64_t hash_ = 0;
  std::uint64_t last_tick_ = 0;
  std::optional<vec3f> self_position_;
  std::uint64_t self_tick_ = 0;
  std::vector<std::uint32_t> bad_ids_;
  bool any_ = false;
  std::uint64_t applied_ = 0, digests_checked_ = 0, problems_ = 0, class_notes_applied_ = 0;
};

}  // namespace zone::net
