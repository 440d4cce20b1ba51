// A single zone's resume tokens (zone-server --linger; docs/protocol.md, "Coming back after a lost
// connection"): every player's client is told a token in its welcome; a player whose connection
// is lost (it said no leave) stands where it was for the linger time, and a hello with its token
// within it gets the same entity back. A hello with the token of a player whose old connection
// is still open (the server has not noticed its loss yet) takes the player over. A world of zones
// keeps its own tokens (world/nats_node.h), which also outlive a zone's loss.
#pragma once

#include <cstddef>
#include <cstdint>
#include <deque>
#include <optional>
#include <string>
#include <string_view>
#include <unordered_map>
#include <vector>

#include "entity_store.h"
#include "token.h"

namespace zone {

class resume_book {
 public:
  /// Players whose connection was lost wait `linger_ticks` ticks for their client; at most
  /// `max_kept` wait at once (more are removed at once).
  resume_book(std::uint64_t linger_ticks, std::size_t max_kept);

  /// The token entity `e`'s client is told (welcome.resume_token): a new one for a new player,
  /// the one it claimed with otherwise. From the OS's random source (os_random_u64: unguessable,
  /// a token is the right to play its entity), written as token.h writes tokens.
  std::string issue(entity_id e);
  /// `e`'s connection was lost (no leave) at `tick`: true when it is kept for its client (until
  /// tick + linger_ticks), false when the zone removes it (no token told, lingering off, full).
  bool keep(entity_id e, std::uint64_t tick);
  /// `e` leaves for good (its client said leave, or the zone removed it): its token is forgotten.
  void forget(entity_id e);

  /// What a hello's token names.
  struct claim {
    entity_id entity = null_entity;  ///< null_entity: unknown, expired or malformed
    bool live = false;               ///< its player's old connection is still open (a takeover)
  };
  /// A hello said `token`: the player it names; a kept player stops waiting (it is the new
  /// connection's now, with the same token).
  [[nodiscard]] claim take(std::string_view token);
  /// The kept players whose wait ran out by `tick`: appended to `out` (the zone removes them).
  void expire(std::uint64_t tick, std::vector<entity_id>& out);

  [[nodiscard]] std::size_t kept() const { return kept_; }
  [[nodiscard]] std::size_t known() const { return by_token_.size(); }

 private:
  struct entry {
    entity_id entity = null_entity;
    bool kept = false;
    std::uint64_t until = 0;  ///< kept: the tick its wait ends
  };
  std::uint64_t linger_ticks_;
  std::size_t max_kept_;
  std::size_t kept_ = 0;
  std::unordered_map<std::uint64_t, entry> by_token_;
  std::unordered_map<entity_id, std::uint64_t> by_entity_;
  /// (until, token) of every keep, oldest first (one linger for all: in order of their ends);
  /// an entry claimed or forgotten meanwhile is skipped when its turn comes.
  std::deque<std::pair<std::uint64_t, std::uint64_t>> waits_;
};

}  // namespace zone
