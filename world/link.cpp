// The world layout, the ghost and handoff wire formats and zone_link (world.h).
#include <algorithm>
#include <bit>
#include <cmath>
#include <cstring>
#include <sstream>

#include "world.h"

namespace zone::world {

// ---- rect and layout ---------------------------------------------------------------------------

float rect::distance(float x, float y) const {
  const float dx = std::max({0.0f, lo_x - x, x - hi_x});
  const float dy = std::max({0.0f, lo_y - y, y - hi_y});
  return std::max(dx, dy);
}

layout::layout(const net::world_bounds& bounds, std::uint32_t cols, std::uint32_t rows)
    : bounds_(bounds), cols_(std::max(1u, cols)), rows_(std::max(1u, rows)) {}

rect layout::region(std::uint32_t r) const {
  const std::uint32_t c = r % cols_, w = r / cols_;
  const float sx = (bounds_.hi.x - bounds_.lo.x) / static_cast<float>(cols_);
  const float sy = (bounds_.hi.y - bounds_.lo.y) / static_cast<float>(rows_);
  rect out{bounds_.lo.x + sx * static_cast<float>(c), bounds_.lo.y + sy * static_cast<float>(w),
           bounds_.lo.x + sx * static_cast<float>(c + 1), bounds_.lo.y + sy * static_cast<float>(w + 1)};
  if (c + 1 == cols_) out.hi_x = bounds_.hi.x;
  if (w + 1 == rows_) out.hi_y = bounds_.hi.y;
  return out;
}

std::uint32_t layout::region_at(float x, float y) const {
  const auto cell = [](float v, float lo, float hi, std::uint32_t n) {
    if (!(v > lo)) return 0u;  // NaN goes to 0 too
    const double t = (static_cast<double>(v) - lo) / (static_cast<double>(hi) - lo) * n;
    return static_cast<std::uint32_t>(std::min<double>(n - 1, std::floor(t)));
  };
  std::uint32_t c = cell(x, bounds_.lo.x, bounds_.hi.x, cols_), w = cell(y, bounds_.lo.y, bounds_.hi.y, rows_);
  // Float rounding at a boundary: trust the rectangles (a point on lo belongs to the region).
  while (c > 0 && x < region(w * cols_ + c).lo_x) --c;
  while (c + 1 < cols_ && x >= region(w * cols_ + c + 1).lo_x) ++c;
  while (w > 0 && y < region(w * cols_ + c).lo_y) --w;
  while (w + 1 < rows_ && y >= region((w + 1) * cols_ + c).lo_y) ++w;
  return w * cols_ + c;
}

std::vector<std::uint32_t> layout::neighbours(std::uint32_t r) const {
  std::vector<std::uint32_t> out;
  const int c = static_cast<int>(r % cols_), w = static_cast<int>(r / cols_);
  for (int dw = -1; dw <= 1; ++dw) {
    for (int dc = -1; dc <= 1; ++dc) {
      const int nc = c + dc, nw = w + dw;
      if ((dc == 0 && dw == 0) || nc < 0 || nw < 0 || nc >= static_cast<int>(cols_) || nw >= static_cast<int>(rows_)) continue;
      out.push_back(static_cast<std::uint32_t>(nw) * cols_ + static_cast<std::uint32_t>(nc));
    }
  }
  std::sort(out.begin(), out.end());
  return out;
}

std::string layout::encode() const {
  std::ostringstream o;
  o.precision(9);
  o << cols_ << ' ' << rows_ << ' ' << bounds_.lo.x << ' ' << bounds_.lo.y << ' ' << bounds_.lo.z << ' ' << bounds_.hi.x << ' '
    << bounds_.hi.y << ' ' << bounds_.hi.z;
  return o.str();
}

std::optional<layout> layout::decode(std::string_view text) {
  std::istringstream in{std::string(text)};
  std::uint32_t cols = 0, rows = 0;
  net::world_bounds b{};
  if (!(in >> cols >> rows >> b.lo.x >> b.lo.y >> b.lo.z >> b.hi.x >> b.hi.y >> b.hi.z)) return std::nullopt;
  std::string extra;
  if (in >> extra) return std::nullopt;
  if (cols == 0 || rows == 0 || cols > 64 || rows > 64) return std::nullopt;
  const float lo[3] = {b.lo.x, b.lo.y, b.lo.z}, hi[3] = {b.hi.x, b.hi.y, b.hi.z};
  for (int d = 0; d < 3; ++d) {
    if (!std::isfinite(lo[d]) || !std::isfinite(hi[d]) || !(hi[d] > lo[d])) return std::nullopt;
  }
  return layout(b, cols, rows);
}

// ---- wire helpers ------------------------------------------------------------------------------

namespace {

struct writer {
  std::vector<std::uint8_t>& out;
  template <class T>
  void put(T v) {
    static_assert(std::is_trivially_copyable_v<T>);
    const std::size_t at = out.size();
    out.resize(at + sizeof(T));
    std::memcpy(out.data() + at, &v, sizeof(T));  // the hosts we build for are little-endian
  }
  void put3(const vec3& v) { put(v.x), put(v.y), put(v.z); }
};

struct reader {
  std::span<const std::uint8_t> in;
  std::size_t at = 0;
  bool ok = true;
  template <class T>
  T get() {
    T v{};
    if (at + sizeof(T) > in.size()) {
      ok = false;
      return v;
    }
    std::memcpy(&v, in.data() + at, sizeof(T));
    at += sizeof(T);
    return v;
  }
  vec3 get3() {
    vec3 v;
    v.x = get<float>(), v.y = get<float>(), v.z = get<float>();
    return v;
  }
};

constexpr std::uint32_t ghost_magic = 0x32484753;       // "SGH2": "SGH1" and the sender's room
constexpr std::uint32_t handoff_magic_v1 = 0x31464f48;  // "HOF1": no visible set
constexpr std::uint32_t handoff_magic = 0x32464f48;     // "HOF2": a count and the visible set at the end
constexpr std::uint32_t chunk_magic = 0x31504b43;       // "CKP1"
constexpr std::uint32_t head_magic = 0x31484b43;        // "CKH1"

std::uint16_t half_q(float h) {
  return static_cast<std::uint16_t>(std::clamp(std::lround(static_cast<double>(h) * 16.0), 0l, 65535l));
}
float half_dq(std::uint16_t q) { return static_cast<float>(q) / 16.0f; }

}  // namespace

std::optional<std::uint32_t> token_region(std::string_view token) {
  const auto v = parse_token(token);
  if (!v || (*v >> 48) == 0) return std::nullopt;
  return static_cast<std::uint32_t>(*v >> 48) - 1;
}

std::vector<std::uint8_t> encode(const ghost_message& m) {
  std::vector<std::uint8_t> out;
  out.reserve(ghost_header_bytes + m.entries.size() * ghost_entry_bytes + m.removed.size() * 8);
  writer w{out};
  w.put(ghost_magic);
  w.put(static_cast<std::uint16_t>(m.from));
  w.put(static_cast<std::uint16_t>(m.to));
  w.put(m.seq);
  w.put(m.tick);
  w.put(static_cast<std::uint32_t>(m.snapshot ? 1 : 0));
  w.put(static_cast<std::uint32_t>(m.entries.size()));
  w.put(static_cast<std::uint32_t>(m.removed.size()));
  w.put(m.room);
  for (const auto& e : m.entries) {
    w.put(e.gid);
    for (auto v : e.position) w.put(v);
    for (auto v : e.aoi_half) w.put(v);
    for (auto v : e.presence_half) w.put(v);
    w.put(e.visibility_class);
    w.put(e.sees);
    w.put(e.kind);
    w.put(e.flags);
  }
  for (const auto g : m.removed) w.put(g);
  return out;
}

std::optional<ghost_message> decode_ghosts(std::span<const std::uint8_t> bytes) {
  reader r{bytes};
  if (r.get<std::uint32_t>() != ghost_magic) return std::nullopt;
  ghost_message m;
  m.from = r.get<std::uint16_t>();
  m.to = r.get<std::uint16_t>();
  m.seq = r.get<std::uint64_t>();
  m.tick = r.get<std::uint64_t>();
  const auto flags = r.get<std::uint32_t>();
  const auto n = r.get<std::uint32_t>();
  const auto k = r.get<std::uint32_t>();
  m.room = r.get<std::uint32_t>();
  if (!r.ok || flags > 1) return std::nullopt;
  m.snapshot = flags == 1;
  // Sizes checked before allocating: a hostile count cannot make us reserve gigabytes.
  if (bytes.size() != ghost_header_bytes + std::size_t{n} * ghost_entry_bytes + std::size_t{k} * 8) return std::nullopt;
  m.entries.resize(n);
  for (auto& e : m.entries) {
    e.gid = r.get<std::uint64_t>();
    for (auto& v : e.position) v = r.get<std::uint16_t>();
    for (auto& v : e.aoi_half) v = r.get<std::uint16_t>();
    for (auto& v : e.presence_half) v = r.get<std::uint16_t>();
    e.visibility_class = r.get<std::uint32_t>();
    e.sees = r.get<std::uint32_t>();
    e.kind = r.get<std::uint8_t>();
    e.flags = r.get<std::uint8_t>();
  }
  m.removed.resize(k);
  for (auto& g : m.removed) g = r.get<std::uint64_t>();
  if (!r.ok || r.at != bytes.size()) return std::nullopt;
  return m;
}

namespace {
/// A handoff record's bytes appended to `out` (encode, and each record of a checkpoint chunk).
void append(std::vector<std::uint8_t>& out, const handoff_record& h) {
  writer w{out};
  w.put(handoff_magic);
  w.put(h.gid);
  w.put(h.epoch);
  w.put(h.from);
  w.put(h.to);
  w.put3(h.desc.position);
  w.put3(h.desc.velocity);
  w.put(h.desc.visibility_class);
  w.put(h.desc.sees);
  w.put3(h.desc.aoi_half_extent);
  w.put3(h.desc.presence_half_extent);
  w.put(static_cast<std::uint8_t>(h.desc.kind));
  w.put(static_cast<std::uint8_t>(h.behaviour.kind));
  w.put3(h.behaviour.home);
  w.put(h.behaviour.waypoint);
  w.put3(h.behaviour.intent);
  w.put(h.token);
  w.put(h.owner_revision);
  w.put(h.last_input);
  w.put(h.sent_us);
  w.put(h.sent_tick);
  const std::size_t k = std::min(h.visible.size(), max_handoff_visible);
  w.put(static_cast<std::uint32_t>(k));
  for (std::size_t i = 0; i < k; ++i) w.put(h.visible[i]);
}
}  // namespace

std::vector<std::uint8_t> encode(const handoff_record& h) {
  std::vector<std::uint8_t> out;
  append(out, h);
  return out;
}

std::optional<handoff_record> decode_handoff(std::span<const std::uint8_t> bytes) {
  reader r{bytes};
  const auto magic = r.get<std::uint32_t>();
  if (magic != handoff_magic && magic != handoff_magic_v1) return std::nullopt;
  handoff_record h;
  h.gid = r.get<std::uint64_t>();
  h.epoch = r.get<std::uint64_t>();
  h.from = r.get<std::uint32_t>();
  h.to = r.get<std::uint32_t>();
  h.desc.position = r.get3();
  h.desc.velocity = r.get3();
  h.desc.visibility_class = r.get<std::uint32_t>();
  h.desc.sees = r.get<std::uint32_t>();
  h.desc.aoi_half_extent = r.get3();
  h.desc.presence_half_extent = r.get3();
  const auto kind = r.get<std::uint8_t>();
  const auto beh = r.get<std::uint8_t>();
  h.behaviour.home = r.get3();
  h.behaviour.waypoint = r.get<std::uint32_t>();
  h.behaviour.intent = r.get3();
  h.token = r.get<std::uint64_t>();
  h.owner_revision = r.get<std::uint64_t>();
  h.last_input = r.get<std::uint32_t>();
  h.sent_us = r.get<std::uint64_t>();
  h.sent_tick = r.get<std::uint64_t>();
  if (magic == handoff_magic) {
    // The count checked against the bytes before allocating: a hostile one reserves nothing.
    const auto k = r.get<std::uint32_t>();
    if (!r.ok || k > max_handoff_visible || bytes.size() - r.at != std::size_t{k} * sizeof(global_id)) return std::nullopt;
    h.visible.resize(k);
    for (auto& g : h.visible) g = r.get<global_id>();
  }
  if (!r.ok || r.at != bytes.size()) return std::nullopt;
  if (kind > static_cast<std::uint8_t>(entity_kind::boss) || beh > static_cast<std::uint8_t>(behaviour::ghost)) return std::nullopt;
  h.desc.kind = static_cast<entity_kind>(kind);
  h.behaviour.kind = static_cast<behaviour>(beh);
  if (h.behaviour.kind == behaviour::ghost || validate(h.desc)) return std::nullopt;
  return h;
}

std::vector<std::uint8_t> encode(const checkpoint_chunk& c) {
  std::vector<std::uint8_t> out;
  writer w{out};
  w.put(chunk_magic);
  w.put(c.region);
  w.put(c.incarnation);
  w.put(c.generation);
  w.put(c.tick);
  w.put(static_cast<std::uint32_t>(c.records.size()));
  out.reserve(out.size() + c.records.size() * 176);
  for (const auto& r : c.records) {
    const std::size_t at = out.size();
    w.put(std::uint32_t{0});  // its length, written once known
    append(out, r);
    const auto len = static_cast<std::uint32_t>(out.size() - at - 4);
    std::memcpy(out.data() + at, &len, 4);
  }
  return out;
}

std::optional<checkpoint_chunk> decode_checkpoint_chunk(std::span<const std::uint8_t> bytes) {
  reader r{bytes};
  if (r.get<std::uint32_t>() != chunk_magic) return std::nullopt;
  checkpoint_chunk c;
  c.region = r.get<std::uint32_t>();
  c.incarnation = r.get<std::uint32_t>();
  c.generation = r.get<std::uint64_t>();
  c.tick = r.get<std::uint64_t>();
  const auto n = r.get<std::uint32_t>();
  // Each record takes at least its length's 4 bytes: a hostile count reserves nothing.
  if (!r.ok || std::size_t{n} * 4 > bytes.size() - r.at) return std::nullopt;
  c.records.reserve(n);
  for (std::uint32_t k = 0; k < n; ++k) {
    const auto len = r.get<std::uint32_t>();
    if (!r.ok || len > bytes.size() - r.at) return std::nullopt;
    auto rec = decode_handoff(bytes.subspan(r.at, len));
    if (!rec) return std::nullopt;
    r.at += len;
    c.records.push_back(std::move(*rec));
  }
  if (r.at != bytes.size()) return std::nullopt;
  return c;
}

std::vector<std::uint8_t> encode(const checkpoint_head& h) {
  std::vector<std::uint8_t> out;
  writer w{out};
  w.put(head_magic);
  w.put(h.region);
  w.put(h.incarnation);
  w.put(h.generation);
  w.put(h.tick);
  w.put(h.entities);
  w.put(static_cast<std::uint32_t>(h.chunks.size()));
  for (const std::uint64_t seq : h.chunks) w.put(seq);
  return out;
}

std::optional<checkpoint_head> decode_checkpoint_head(std::span<const std::uint8_t> bytes) {
  reader r{bytes};
  if (r.get<std::uint32_t>() != head_magic) return std::nullopt;
  checkpoint_head h;
  h.region = r.get<std::uint32_t>();
  h.incarnation = r.get<std::uint32_t>();
  h.generation = r.get<std::uint64_t>();
  h.tick = r.get<std::uint64_t>();
  h.entities = r.get<std::uint64_t>();
  const auto n = r.get<std::uint32_t>();
  if (!r.ok || n > max_checkpoint_chunks || bytes.size() - r.at != std::size_t{n} * 8) return std::nullopt;
  h.chunks.resize(n);
  for (auto& seq : h.chunks) seq = r.get<std::uint64_t>();
  return h;
}

float ghost_band(const zone_config& c, float handoff_margin) {
  // The AOIs populate() and players use: NPC tiers 0-2 (chasers 2), bosses the gigantic tier 4.
  float aoi = std::max({c.player_aoi, c.aoi_tier[0], c.aoi_tier[1], c.aoi_tier[2]});
  if (c.boss_count > 0) aoi = std::max(aoi, c.aoi_tier[4]);
  const float presence = c.boss_count > 0 ? std::max(1.0f, c.boss_footprint) : 1.0f;
  const float speed = std::max(c.npc_speed * 1.5f, c.player_speed);
  return aoi + c.hysteresis + presence + handoff_margin + 2 * speed / static_cast<float>(c.tick_rate_hz) + 1;
}

// ---- zone_link ---------------------------------------------------------------------------------

zone_link::zone_link(link_options opt)
    : opt_(std::move(opt)), area_(opt_.map.region(opt_.region)), quantizer_(opt_.map.bounds()) {
  for (const auto n : opt_.map.neighbours(opt_.region)) out_.push_back(neighbour_out{n, 0, true, {}});
}

zone_link::slot_info* zone_link::info(entity_id local) {
  const auto s = slot_of(local);
  if (local == null_entity || s >= by_slot_.size() || by_slot_[s].local != local) return nullptr;
  return &by_slot_[s];
}

const zone_link::slot_info* zone_link::info(entity_id local) const {
  return const_cast<zone_link*>(this)->info(local);
}

zone_link::slot_info& zone_link::bind(entity_id local, global_id g, role what) {
  const auto s = slot_of(local);
  if (by_slot_.size() <= s) by_slot_.resize(s + 1);
  slot_info& i = by_slot_[s];
  // A slot reused by a new entity: the old one's gid no longer maps here.
  if (i.local != local && i.gid != 0) {
    const auto it = local_.find(i.gid);
    if (it != local_.end() && it->second == i.local) local_.erase(it);
  }
  i = slot_info{};
  i.local = local;
  i.gid = g;
  i.what = what;
  local_[g] = local;
  return i;
}

global_id zone_link::gid_of(entity_id local) const {
  const auto* i = info(local);
  return i ? i->gid : 0;
}

entity_id zone_link::local_of(global_id g) const {
  const auto it = local_.find(g);
  if (it == local_.end()) return null_entity;
  const auto* i = info(it->second);
  return i && i->gid == g ? it->second : null_entity;
}

bool zone_link::owns(entity_id local) const {
  const auto* i = info(local);
  return i && i->what == role::owned;
}

bool zone_link::in_transit(entity_id local) const {
  const auto* i = info(local);
  return i && i->what == role::transit;
}

std::size_t zone_link::owned_count() const {
  std::size_t n = 0;
  for (const auto& i : by_slot_) n += i.what == role::owned ? 1 : 0;
  return n;
}

std::vector<global_id> zone_link::owned_ids() const {
  std::vector<global_id> out;
  for (const auto& i : by_slot_) {
    if (i.what == role::owned) out.push_back(i.gid);
  }
  std::sort(out.begin(), out.end());
  return out;
}

std::vector<global_id> zone_link::transit_ids() const {
  std::vector<global_id> out;
  for (const auto& i : by_slot_) {
    if (i.what == role::transit) out.push_back(i.gid);
  }
  std::sort(out.begin(), out.end());
  return out;
}

std::vector<std::pair<global_id, std::uint64_t>> zone_link::owned_epochs() const {
  std::vector<std::pair<global_id, std::uint64_t>> out;
  for (const auto& i : by_slot_) {
    if (i.what == role::owned) out.emplace_back(i.gid, i.epoch);
  }
  std::sort(out.begin(), out.end());
  return out;
}

std::uint64_t zone_link::owner_revision(global_id g) const {
  const auto* i = info(local_of(g));
  return i ? i->revision : 0;
}

void zone_link::assign_ids(const zone_world& w) {
  // Entities removed by the zone itself (a player who left): forgotten.
  for (auto& i : by_slot_) {
    if (i.what != role::none && !w.store().alive(i.local)) {
      if (i.what == role::owned && i.epoch > 0) departed_.push_back(i.gid);
      const auto it = local_.find(i.gid);
      if (it != local_.end() && it->second == i.local) local_.erase(it);
      i = slot_info{};
    }
  }
  const auto ids = w.store().ids();
  for (const entity_id id : ids) {
    const auto s = slot_of(id);
    if (s < by_slot_.size() && by_slot_[s].local == id) continue;
    const global_id g = (std::uint64_t{opt_.region + 1} << 48) | (std::uint64_t{opt_.incarnation & 0xffff} << 32) | next_counter_++;
    bind(id, g, role::owned);
  }
}

ghost_entry zone_link::make_entry(const entity_store& s, std::size_t k, std::uint8_t flags) const {
  ghost_entry e;
  e.gid = gid_of(s.ids()[k]);
  const vec3 p = s.positions()[k];
  e.position = quantizer_.quantize({p.x, p.y, p.z});
  const vec3 a = s.aoi_half_extents()[k], h = s.presence_half_extents()[k];
  e.aoi_half = {half_q(a.x), half_q(a.y), half_q(a.z)};
  e.presence_half = {half_q(h.x), half_q(h.y), half_q(h.z)};
  e.visibility_class = s.visibility_classes()[k];
  e.sees = s.sees()[k];
  e.kind = static_cast<std::uint8_t>(s.kinds()[k]);
  e.flags = flags;
  return e;
}

void zone_link::build_ghosts(const zone_world& w, std::vector<ghost_message>& out) {
  out.clear();
  tick_ = w.tick();
  const auto& s = w.store();
  const auto ids = s.ids();
  const auto pos = s.positions();
  // Each neighbour's own entities that it keeps here, past its border and its handoff margin
  // (held for room: collect_handoffs): what they see of this zone is what it sends, so every owned
  // entity within the band of one of them goes too, not only those near the border. One pass for
  // every neighbour; (x, y), sorted by x.
  std::vector<std::vector<std::pair<float, float>>> anchors_of(out_.size());
  for (std::size_t k = 0; k < ids.size(); ++k) {
    const slot_info* i = info(ids[k]);
    if (i == nullptr || i->what != role::ghost || i->owner_claims == 0) continue;
    for (std::size_t nk = 0; nk < out_.size(); ++nk) {
      if ((i->owner_claims & (1u << nk)) != 0 &&
          opt_.map.region(out_[nk].region).distance(pos[k].x, pos[k].y) > opt_.handoff_margin) {
        anchors_of[nk].emplace_back(pos[k].x, pos[k].y);
      }
    }
  }
  for (std::size_t nk = 0; nk < out_.size(); ++nk) {
    auto& n = out_[nk];
    const rect r = opt_.map.region(n.region);
    auto& anchors = anchors_of[nk];
    std::sort(anchors.begin(), anchors.end());
    const float band = opt_.ghost_band;
    const auto near_anchor = [&](float x, float y) {
      for (auto it = std::lower_bound(anchors.begin(), anchors.end(), std::pair<float, float>(x - band, -INFINITY));
           it != anchors.end() && it->first <= x + band; ++it) {
        if (std::abs(it->second - y) <= band) return true;
      }
      return false;
    };
    ghost_message m;
    m.from = opt_.region;
    m.to = n.region;
    m.seq = ++n.seq;
    m.tick = w.tick();
    m.snapshot = n.snapshot_next;
    if (opt_.capacity != 0) {
      const std::size_t owned = owned_count();
      m.room = static_cast<std::uint32_t>(
          std::min<std::size_t>(opt_.capacity - std::min(owned, opt_.capacity), ghost_message::no_limit - 1));
    }
    std::unordered_map<global_id, ghost_entry> now;
    now.reserve(n.sent.size() + 16);
    for (std::size_t k = 0; k < ids.size(); ++k) {
      const slot_info* i = info(ids[k]);
      if (i == nullptr) continue;
      // Owned entities, and in-transit ones (so that neighbours keep seeing them until the new
      // owner's ghosts take over); never other zones' ghosts.
      const bool transit = i->what == role::transit;
      if (i->what != role::owned && !transit) continue;
      if (r.distance(pos[k].x, pos[k].y) > opt_.ghost_band && (anchors.empty() || !near_anchor(pos[k].x, pos[k].y)))
        continue;
      const ghost_entry e = make_entry(s, k, transit ? ghost_in_transit : 0);
      now.emplace(e.gid, e);
      if (m.snapshot) {
        m.entries.push_back(e);
      } else {
        const auto it = n.sent.find(e.gid);
        if (it == n.sent.end() || !(it->second == e)) m.entries.push_back(e);
      }
    }
    if (!m.snapshot) {
      for (const auto& [g, e] : n.sent) {
        if (!now.contains(g)) m.removed.push_back(g);
      }
    }
    // Deterministic order (the unordered maps' order is not).
    std::sort(m.entries.begin(), m.entries.end(), [](const ghost_entry& a, const ghost_entry& b) { return a.gid < b.gid; });
    std::sort(m.removed.begin(), m.removed.end());
    if (m.snapshot) ++stats_.snapshots_out;
    n.snapshot_next = false;
    n.sent = std::move(now);
    ++stats_.ghost_messages_out;
    stats_.ghost_bytes_out += ghost_header_bytes + m.entries.size() * ghost_entry_bytes + m.removed.size() * 8;
    out.push_back(std::move(m));
  }
}

void zone_link::snapshot_requested(std::uint32_t neighbour) {
  for (auto& n : out_) {
    if (n.region == neighbour) n.snapshot_next = true;
  }
}

std::vector<std::uint32_t> zone_link::snapshot_wanted() const {
  std::vector<std::uint32_t> out;
  for (const auto& n : out_) {
    const auto it = in_.find(n.region);
    if (it == in_.end() || it->second.expected == 0) out.push_back(n.region);
  }
  return out;
}

int zone_link::neighbour_index(std::uint32_t region) const {
  for (std::size_t k = 0; k < out_.size(); ++k) {
    if (out_[k].region == region) return static_cast<int>(k);
  }
  return -1;
}

void zone_link::set_classes(entity_store& st, std::size_t dense, entity_id id, std::uint32_t cls, std::uint32_t sees) {
  const std::uint32_t old_class = st.visibility_classes()[dense], old_sees = st.sees()[dense];
  if (old_class == cls && old_sees == sees) return;
  // Only a valid change is applied (and recorded): a bad one leaves the entity as it was.
  if (st.set_visibility(id, cls, sees)) class_changes_.push_back({id, old_class, old_sees});
}

void zone_link::place_ghost(zone_world& w, const ghost_entry& e, unsigned source) {
  const net::vec3f p = quantizer_.dequantize(e.position);
  const vec3 at{p.x, p.y, p.z};
  const vec3 aoi{half_dq(e.aoi_half[0]), half_dq(e.aoi_half[1]), half_dq(e.aoi_half[2])};
  const vec3 pres{half_dq(e.presence_half[0]), half_dq(e.presence_half[1]), half_dq(e.presence_half[2])};
  const auto bit = static_cast<std::uint8_t>(1u << source);
  const bool transit = (e.flags & ghost_in_transit) != 0;
  const entity_id have = local_of(e.gid);
  if (have != null_entity) {
    slot_info* i = info(have);
    if (i->what == role::owned) return;  // ours (an in-transit copy of what we adopted): ignore
    // Our own in-transit copy, claimed by a neighbour (its new owner's ghost): a ghost now.
    if (i->what == role::transit) i->what = role::ghost, i->claims = 0, i->owner_claims = 0;
    i->claims |= bit;
    i->owner_claims = static_cast<std::uint8_t>(transit ? i->owner_claims & ~bit : i->owner_claims | bit);
    // The owner's state wins over an in-transit copy's.
    if (transit && (i->owner_claims & ~bit) != 0) return;
    auto& st = w.store();
    const std::size_t k = st.index_of(have);
    st.set_position(have, at);
    if (!(st.aoi_half_extents()[k] == aoi)) st.set_aoi_half_extent(have, aoi);
    if (!(st.presence_half_extents()[k] == pres)) st.set_presence_half_extent(have, pres);
    set_classes(st, k, have, e.visibility_class, e.sees);
    return;
  }
  entity_desc d;
  d.position = at;
  d.aoi_half_extent = aoi;
  d.presence_half_extent = pres;
  d.visibility_class = e.visibility_class;
  d.sees = e.sees;
  d.kind = e.kind <= static_cast<std::uint8_t>(entity_kind::boss) ? static_cast<entity_kind>(e.kind) : entity_kind::npc;
  if (validate(d)) {
    ++stats_.bad;
    return;
  }
  const entity_id id = w.adopt(d, behaviour_state{behaviour::ghost, at, 0, {}});
  if (id == null_entity) return;
  slot_info& i = bind(id, e.gid, role::ghost);
  i.claims = bit;
  i.owner_claims = transit ? 0 : bit;
}

void zone_link::unclaim(zone_world& w, entity_id local, unsigned source) {
  slot_info* i = info(local);
  if (i == nullptr || i->what != role::ghost) return;
  const auto bit = static_cast<std::uint8_t>(1u << source);
  i->claims = static_cast<std::uint8_t>(i->claims & ~bit);
  i->owner_claims = static_cast<std::uint8_t>(i->owner_claims & ~bit);
  if (i->claims == 0) drop_ghost(w, local);
}

void zone_link::drop_ghost(zone_world& w, entity_id local) {
  slot_info* i = info(local);
  if (i == nullptr || i->what == role::owned) return;
  local_.erase(i->gid);
  *i = slot_info{};
  w.despawn(local);
}

ghost_status zone_link::apply_ghosts(zone_world& w, std::span<const std::uint8_t> bytes) {
  tick_ = w.tick();
  auto m = decode_ghosts(bytes);
  const int src = m ? neighbour_index(m->from) : -1;
  if (!m || m->to != opt_.region || src < 0) {
    ++stats_.bad;
    return ghost_status::bad;
  }
  const auto source = static_cast<unsigned>(src);
  ++stats_.ghost_messages_in;
  stats_.ghost_bytes_in += bytes.size();
  neighbour_in& n = in_[m->from];
  n.heard = true;
  n.last_tick = w.tick();
  n.room = m->room;  // whatever becomes of its ghosts (a gap), the room is its latest word
  if (!m->snapshot) {
    if (n.expected == 0 || m->seq > n.expected) {
      if (n.expected != 0) ++stats_.gaps;
      n.expected = 0;  // wait for a snapshot; the ghosts stay as they are meanwhile
      return ghost_status::gap;
    }
    if (m->seq < n.expected) {
      ++stats_.stale;
      return ghost_status::stale;
    }
  } else {
    if (n.expected != 0 && m->seq < n.expected) {
      ++stats_.stale;
      return ghost_status::stale;
    }
    ++stats_.snapshots_in;
    // The snapshot is the whole set: this neighbour's ghosts not in it go.
    std::vector<global_id> keep;
    for (const auto& e : m->entries) keep.push_back(e.gid);
    std::sort(keep.begin(), keep.end());
    std::vector<entity_id> gone;
    for (const auto& i : by_slot_) {
      if (i.what == role::ghost && (i.claims & (1u << source)) && !std::binary_search(keep.begin(), keep.end(), i.gid)) {
        gone.push_back(i.local);
      }
    }
    for (const entity_id id : gone) unclaim(w, id, source);
  }
  n.expected = m->seq + 1;
  for (const auto& e : m->entries) place_ghost(w, e, source);
  // A removal takes back only this sender's claim: an entity handed on may be another's now.
  for (const global_id g : m->removed) unclaim(w, local_of(g), source);
  return ghost_status::applied;
}

handoff_status zone_link::apply_handoff(zone_world& w, const handoff_record& r, entity_id* local) {
  tick_ = w.tick();
  if (r.to != opt_.region || r.gid == 0) {
    ++stats_.handoffs_refused;
    return handoff_status::refused;
  }
  const auto seen = last_epoch_.find(r.gid);
  const std::uint64_t last = seen == last_epoch_.end() ? 0 : seen->second;
  const entity_id have = local_of(r.gid);
  slot_info* i = info(have);
  if (r.epoch <= last || (i != nullptr && i->what == role::owned && i->epoch >= r.epoch)) {
      ++stats_.handoff_duplicates;
    if (local) *local = have;
    return handoff_status::duplicate;
  }
  // A full zone adopts nothing (the record is offered again later: never dropped).
  const bool full = opt_.capacity != 0 && owned_count() >= opt_.capacity;
  if (full || (i == nullptr && w.store().size() >= w.store().capacity())) {
    ++stats_.handoffs_no_room;
    return handoff_status::no_room;
  }
  entity_id id = have;
  const bool had_ghost = i != nullptr;
  if (had_ghost) {
    // Our ghost of it becomes the entity: same handle, so views here see no leave and enter.
    auto& st = w.store();
    st.set_position(id, r.desc.position);
    st.set_velocity(id, r.desc.velocity);
    st.set_aoi_half_extent(id, r.desc.aoi_half_extent);
    st.set_presence_half_extent(id, r.desc.presence_half_extent);
    set_classes(st, st.index_of(id), id, r.desc.visibility_class, r.desc.sees);
    w.set_behaviour_state(id, r.behaviour);
    i->what = role::owned;
    i->claims = i->owner_claims = 0;
  } else {
    id = w.adopt(r.desc, r.behaviour);
    if (id == null_entity) {  // the store is full after all: offered again later
      ++stats_.handoffs_no_room;
      return handoff_status::no_room;
    }
    i = &bind(id, r.gid, role::owned);
  }
  // Its view at the old owner, as this zone's handles (owned or ghosts; unknown ids skipped),
  // becomes its previous set here in place of what this zone saw of it as a ghost (one zone's
  // history: its owner's): the next step keeps each target within AOI + h. Only into a ghost: an
  // entity new here (no ghost of it: its owner fell silent for the ghost timeout, NATS down) is
  // new to every view here and starts from an empty set, as every new entity does.
  if (had_ghost) {
    std::vector<entity_id> carried;
    carried.reserve(std::min(r.visible.size(), max_handoff_visible));
    for (const global_id g : r.visible) {
      if (carried.size() >= max_handoff_visible) break;
      if (const entity_id v = local_of(g); v != null_entity && v != id) carried.push_back(v);
    }
    w.interest().carry_visible(id, carried);
  }
  last_epoch_[r.gid] = r.epoch;
  i->epoch = r.epoch;
  i->revision = r.owner_revision;
  i->source = opt_.region;
  ++stats_.handoffs_in;
  if (local) *local = id;
  return handoff_status::adopted;
}

void zone_link::checkpoint(const zone_world& w, std::vector<handoff_record>& out,
                           const std::unordered_map<entity_id, std::uint64_t>* resume) const {
  // Down the store's dense columns (the game thread pays this copy once a checkpoint).
  out.clear();
  const auto& s = w.store();
  const auto ids = s.ids();
  const auto pos = s.positions();
  const auto vel = s.velocities();
  const auto cls = s.visibility_classes();
  const auto sees = s.sees();
  const auto aoi = s.aoi_half_extents();
  const auto presence = s.presence_half_extents();
  const auto kinds = s.kinds();
  out.reserve(owned_count());
  for (std::size_t k = 0; k < ids.size(); ++k) {
    const slot_info* i = info(ids[k]);
    if (i == nullptr || i->what != role::owned) continue;
    const auto state = w.behaviour_state_of(ids[k]);
    if (!state) continue;
    std::uint64_t token = 0;
    if (state->kind == behaviour::player) {
      if (resume == nullptr) continue;
      const auto t = resume->find(ids[k]);
      if (t == resume->end()) continue;
      token = t->second;
    }
    handoff_record& r = out.emplace_back();
    r.gid = i->gid;
    r.epoch = i->epoch;
    r.from = r.to = opt_.region;
    r.desc = {pos[k], vel[k], cls[k], sees[k], aoi[k], presence[k], kinds[k]};
    r.behaviour = *state;
    r.owner_revision = i->revision;
    r.sent_tick = w.tick();
    r.token = token;
  }
}

handoff_status zone_link::restore(zone_world& w, const handoff_record& r) {
  tick_ = w.tick();
  if (r.to != opt_.region || r.gid == 0 || local_of(r.gid) != null_entity) {
    ++stats_.handoffs_refused;
    return handoff_status::refused;
  }
  if ((opt_.capacity != 0 && owned_count() >= opt_.capacity) || w.store().size() >= w.store().capacity()) {
    return handoff_status::no_room;
  }
  const entity_id id = w.adopt(r.desc, r.behaviour);
  if (id == null_entity) return handoff_status::no_room;
  slot_info& i = bind(id, r.gid, role::owned);
  i.epoch = r.epoch;
  i.revision = r.owner_revision;
  i.source = opt_.region;
  last_epoch_[r.gid] = r.epoch;
  ++stats_.restored;
  return handoff_status::adopted;
}

std::vector<handoff_record> zone_link::collect_handoffs(zone_world& w, std::uint64_t now_us) {
  tick_ = w.tick();
  std::vector<handoff_record> out;
  const auto& s = w.store();
  const auto ids = s.ids();
  const auto pos = s.positions();
  // The room each neighbour told in its last message, less the records sent to it in the last
  // room_lag_ticks ticks (what it told may not count them yet) and this call's (a neighbour
  // silent past the ghost timeout, or never heard, tells nothing: no limit here). A record that
  // overruns its room anyway (two neighbours at once, a slower stream) waits on the stream
  // (docs/world.md, "Faults").
  std::unordered_map<std::uint32_t, std::uint32_t> room;
  if (opt_.hold_for_room) {
    for (const auto& [region, n] : in_) {
      if (!n.heard || n.room == ghost_message::no_limit || tick_ > n.last_tick + opt_.ghost_timeout_ticks) continue;
      std::uint64_t recent = 0;
      for (std::size_t k = 0; k < room_lag_ticks; ++k) {
        if (n.sent[k] != 0 && n.sent_tick[k] < tick_ && tick_ - n.sent_tick[k] <= room_lag_ticks) recent += n.sent[k];
      }
      room[region] = n.room > recent ? static_cast<std::uint32_t>(n.room - recent) : 0;
    }
  }
  for (std::size_t k = 0; k < ids.size(); ++k) {
    slot_info* i = info(ids[k]);
    if (i == nullptr || i->what != role::owned) continue;
    if (area_.distance(pos[k].x, pos[k].y) <= opt_.handoff_margin) continue;
    const std::uint32_t to = opt_.map.region_at(pos[k].x, pos[k].y);
    if (to == opt_.region) continue;
    if (const auto left = room.find(to); left != room.end()) {
      if (left->second == 0) {  // the neighbour is full: the entity stays ours for now
        ++stats_.handoffs_held_for_room;
        continue;
      }
      --left->second;
    }
    handoff_record r;
    r.gid = i->gid;
    r.epoch = i->epoch + 1;
    r.from = opt_.region;
    r.to = to;
    r.desc = *s.get(ids[k]);
    r.behaviour = *w.behaviour_state_of(ids[k]);
    r.owner_revision = i->revision;
    r.sent_us = now_us;
    r.sent_tick = w.tick();
    // Its view here after this tick's step (world-wide ids; targets without one are skipped).
    const auto& t = w.tracker();
    if (const std::size_t row = t.row_of(ids[k]); row != interest_tracker::npos) {
      for (const entity_id v : t.visible(row)) {
        if (r.visible.size() >= max_handoff_visible) break;
        if (const global_id g = gid_of(v); g != 0) r.visible.push_back(g);
      }
    }
    out.push_back(r);
  }
  // Each becomes an in-transit ghost here (after the scan: changing behaviours does not move
  // dense indices, but keep the loop simple).
  for (const auto& r : out) {
    const entity_id id = local_of(r.gid);
    slot_info* i = info(id);
    i->what = role::transit;
    i->source = r.to;
    i->since_tick = w.tick();
    w.set_behaviour_state(id, behaviour_state{behaviour::ghost, r.desc.position, 0, {}});
    w.store().set_velocity(id, {});
    last_epoch_[r.gid] = std::max(last_epoch_[r.gid], r.epoch);
    ++stats_.handoffs_out;
    if (const auto it = in_.find(r.to); it != in_.end()) {
      const std::size_t slot = tick_ % room_lag_ticks;
      if (it->second.sent_tick[slot] != tick_) it->second.sent_tick[slot] = tick_, it->second.sent[slot] = 0;
      ++it->second.sent[slot];
    }
  }
  return out;
}

void zone_link::expire(zone_world& w) {
  tick_ = w.tick();
  // Neighbours silent too long: their claims go (and the ghosts only they claimed).
  std::uint8_t silent = 0;
  for (std::size_t k = 0; k < out_.size(); ++k) {
    const auto it = in_.find(out_[k].region);
    if (it != in_.end() && it->second.heard && tick_ > it->second.last_tick + opt_.ghost_timeout_ticks) {
      silent = static_cast<std::uint8_t>(silent | (1u << k));
      it->second.expected = 0;  // and a snapshot is needed when it speaks again
    }
  }
  std::vector<entity_id> gone;
  for (auto& i : by_slot_) {
    if (i.what == role::ghost && (i.claims & silent) != 0) {
      i.claims = static_cast<std::uint8_t>(i.claims & ~silent);
      i.owner_claims = static_cast<std::uint8_t>(i.owner_claims & ~silent);
      if (i.claims == 0) gone.push_back(i.local);
    } else if (i.what == role::transit && tick_ > i.since_tick + opt_.ghost_timeout_ticks) {
      gone.push_back(i.local);
    }
  }
  for (const entity_id id : gone) drop_ghost(w, id);
  stats_.ghosts_expired += gone.size();
}

}  // namespace zone::world
