// TESTING ONLY: deliberate replication faults (fault_injection.h).
#include "fault_injection.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace zone {

std::optional<fault_injector::kind> fault_injector::parse(const std::string& name) {
  if (name == "drop") return kind::drop;
  if (name == "extra") return kind::extra;
  if (name == "stealth") return kind::stealth;
  if (name == "freeze") return kind::freeze;
  if (name == "class") return kind::klass;
  return std::nullopt;
}

void fault_injector::pick_injected(const entity_store& store, const net::tick_update_msg& m) {
  // extra: the nearest entity beyond reach + 20 m on some axis (certainly not visible);
  // stealth: the nearest stealth entity. Both must be seen-able classes for "extra" to be wrong
  // only by position, and an unseen class for "stealth".
  const std::size_t self = store.index_of(victim_);
  if (self == entity_store::npos) return;
  const vec3 eye = store.positions()[self];
  const auto pos = store.positions();
  const auto cls = store.visibility_classes();
  const std::uint32_t sees = store.sees()[self];
  float best = std::numeric_limits<float>::max();
  std::size_t pick = entity_store::npos;
  for (std::size_t k = 0; k < store.size(); ++k) {
    if (k == self) continue;
    const float dx = pos[k].x - eye.x, dy = pos[k].y - eye.y, dz = pos[k].z - eye.z;
    const float d2 = dx * dx + dy * dy + dz * dz;
    bool ok;
    if (kind_ == kind::stealth) {
      ok = cls[k] == interest::category_bits::stealth && (cls[k] & sees) == 0;
    } else {
      const float far = reach_ + 20;
      ok = (cls[k] & sees) != 0 && (std::fabs(dx) > far || std::fabs(dy) > far || std::fabs(dz) > far);
    }
    if (ok && d2 < best) best = d2, pick = k;
  }
  (void)m;
  if (pick == entity_store::npos) return;
  target_ = store.ids()[pick];
  touched_.push_back(target_);
}

std::span<const std::uint8_t> fault_injector::rewrite(std::span<const std::uint8_t> frame, std::uint64_t tick,
                                                      const entity_store& store) {
  if (tick < from_tick_ || victim_ == null_entity) return frame;
  auto decoded = net::decode_frame(frame, [] {
    net::decoder_options o;
    o.max_frame_bytes = 1 << 24;
    o.max_tables = 1u << 22;
    return o;
  }());
  if (!decoded.value) return frame;
  auto* mp = std::get_if<net::tick_update_msg>(&*decoded.value);
  if (!mp) return frame;
  net::tick_update_msg& m = *mp;
  if (m.reset) target_held_ = false, target_ = kind_ == kind::freeze || kind_ == kind::drop ? 0 : target_;
  const auto erase_id = [](auto& v, std::uint32_t id, auto get) {
    v.erase(std::remove_if(v.begin(), v.end(), [&](const auto& x) { return get(x) == id; }), v.end());
  };
  const auto enter_id = [](const net::entity_state& s) { return s.id; };
  const auto update_id = [](const net::entity_update& u) { return u.id; };
  const auto leave_id = [](std::uint32_t id) { return id; };
  std::int64_t count_delta = 0;
  std::uint64_t hash_delta = 0;  // added to the digest's hash (mod 2^64)

  switch (kind_) {
    case kind::drop: {
      if (target_ == 0 && !m.enters.empty()) {
        target_ = m.enters.front().id;  // the closest entering entity
        touched_.push_back(target_);
      }
      if (target_ == 0) break;
      const bool entered = std::any_of(m.enters.begin(), m.enters.end(), [&](const auto& s) { return s.id == target_; });
      const bool left = std::find(m.leaves.begin(), m.leaves.end(), target_) != m.leaves.end();
      erase_id(m.enters, target_, enter_id);
      erase_id(m.updates, target_, update_id);
      erase_id(m.leaves, target_, leave_id);
      if (entered) target_held_ = true;  // the server now believes the client holds it
      if (left) target_held_ = false, target_ = 0;  // and now that it left: pick another
      if (target_held_) count_delta = -1, hash_delta = 0 - net::digest_mix(target_);
      break;
    }
    case kind::extra:
    case kind::stealth: {
      if (target_ == 0) pick_injected(store, m);
      if (target_ == 0) break;
      // The client keeps it whatever the server sends about it.
      const bool server_has = std::any_of(m.enters.begin(), m.enters.end(), [&](const auto& s) { return s.id == target_; });
      erase_id(m.enters, target_, enter_id);
      erase_id(m.leaves, target_, leave_id);
      if (!target_held_) {
        const std::size_t k = store.index_of(target_);
        if (k == entity_store::npos) break;
        const vec3 p = store.positions()[k], v = store.velocities()[k], h = store.presence_half_extents()[k];
        m.enters.push_back({target_, static_cast<net::entity_kind>(store.kinds()[k]), store.visibility_classes()[k],
                            {p.x, p.y, p.z}, {v.x, v.y, v.z}, {h.x, h.y, h.z}, {}});
        target_held_ = true;
      }
      (void)server_has;
      // The digest: the client holds the target; the server's view may not.
      if (m.digest) {
        // The server's digest counts it only while the server believes the client holds it, which
        // never happens for a stealth target and is rare for a far one: count it as the client's.
        count_delta = 1, hash_delta = net::digest_mix(target_);
      }
      break;
    }
    case kind::freeze: {
      if (target_ == 0) {
        for (const auto& u : m.updates) {
          if (u.velocity[0] != 0 || u.velocity[1] != 0) {
            target_ = u.id;
            frozen_ = u.position;
            touched_.push_back(target_);
            break;
          }
        }
      }
      if (target_ == 0) break;
      for (auto& u : m.updates) {
        if (u.id == target_) u.position = frozen_;
      }
      if (std::find(m.leaves.begin(), m.leaves.end(), target_) != m.leaves.end()) target_ = 0;
      break;
    }
    case kind::klass: {
      if (class_done_) break;
      for (auto& s : m.enters) {
        s.visibility_class = s.visibility_class == interest::category_bits::normal ? interest::category_bits::team_red
                                                                                   : interest::category_bits::normal;
        touched_.push_back(s.id);
        class_done_ = true;
        break;
      }
      break;
    }
  }
  if (m.digest && (count_delta != 0 || hash_delta != 0)) {
    m.digest->count = static_cast<std::uint32_t>(static_cast<std::int64_t>(m.digest->count) + count_delta);
    m.digest->hash += hash_delta;
  }
  return encoder_.encode(m);
}

}  // namespace zone
