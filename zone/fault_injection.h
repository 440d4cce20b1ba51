// TESTING ONLY (zone-server --test-fault): deliberate replication faults in one client's frames,
// to prove that the oracle (docs/bots.md) catches what the server's own digests cannot. Each
// fault rewrites the client's frames after the replicator built them and fixes up the frame's
// digest to match what the client then holds, so only an independent check can see it:
//   drop     an entity that enters the client's view is never sent (nor its updates)
//   extra    an entity far outside the client's AOI is sent as entered and kept
//   stealth  the nearest stealth entity (a class players do not see) is sent as entered and kept
//   freeze   a moving entity's updates keep the position it had when the fault began
//   class    an entering entity is sent with another visibility class
#pragma once

#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "net/protocol.h"
#include "zone.h"

namespace zone {

class fault_injector {
 public:
  enum class kind : std::uint8_t { drop, extra, stealth, freeze, klass };
  /// `name` as zone_config::test_fault ("drop", ...); nothing for "" or an unknown name.
  [[nodiscard]] static std::optional<kind> parse(const std::string& name);

  fault_injector(kind k, std::uint64_t from_tick, const net::world_bounds& world, float aoi_reach)
      : kind_(k), from_tick_(from_tick), quantizer_(world), reach_(aoi_reach) {}

  /// The client whose frames are rewritten (its observer entity); chosen by the tick loop.
  /// A new victim (the last one left, e.g. redirected to another zone) starts the fault afresh:
  /// what the old one was believed to hold says nothing of the new one's view.
  void set_victim(entity_id observer) {
    if (observer != victim_) target_ = 0, target_held_ = false, class_done_ = false;
    victim_ = observer;
  }
  [[nodiscard]] entity_id victim() const { return victim_; }
  [[nodiscard]] std::uint64_t from_tick() const { return from_tick_; }
  /// Entities the fault touched so far (the oracle's log names them).
  [[nodiscard]] const std::vector<std::uint32_t>& touched() const { return touched_; }

  /// The victim's frame of `tick`, rewritten (valid until the next call), or `frame` unchanged.
  /// One thread at a time (the victim's frame is built by one worker per tick).
  [[nodiscard]] std::span<const std::uint8_t> rewrite(std::span<const std::uint8_t> frame, std::uint64_t tick,
                                                      const entity_store& store);

 private:
  void pick_injected(const entity_store& store, const net::tick_update_msg& m);
  kind kind_;
  std::uint64_t from_tick_;
  net::position_quantizer quantizer_;
  float reach_;  ///< a player's AOI + hysteresis (what "far outside" is measured from)
  entity_id victim_ = null_entity;
  std::uint32_t target_ = 0;       ///< the entity the fault is acting on (0 = none yet)
  bool target_held_ = false;       ///< drop: the client lacks it; extra/stealth: the client holds it
  std::array<std::uint16_t, 3> frozen_{};
  bool class_done_ = false;
  std::vector<std::uint32_t> touched_;
  net::encoder encoder_{4096};
};

}  // namespace zone
