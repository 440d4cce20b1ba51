// The tick-level API (interest_space.h): a generation-checked dense registry of entities in front
// of the interest tracker, and the choice of its backend.
#include "interest_space.h"

#include <algorithm>
#include <atomic>
#include <bit>
#include <cmath>
#include <stdexcept>

namespace zone::interest {

namespace {

constexpr std::uint32_t invalid_dense = 0xffffffffu;

bool finite(const vec3& v) { return std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z); }
bool extent_ok(const vec3& v) { return finite(v) && v.x >= 0 && v.y >= 0 && v.z >= 0; }

std::optional<std::string> check_classes(std::uint32_t cls, std::uint32_t sees) {
  if (std::popcount(cls) != 1 || (cls & category_bits::aoi) != 0) {
    return "visibility class must be exactly one category bit other than aoi (got " + std::to_string(cls) + ")";
  }
  if ((sees & category_bits::aoi) != 0) return "sees must not contain the aoi bit";
  return std::nullopt;
}

std::uint32_t next_generation(std::uint32_t gen) { return gen == space_max_generation ? 1 : gen + 1; }

}  // namespace

std::optional<backend> parse_backend(std::string_view name) {
  if (name == "cpu") return backend::cpu;
  if (name == "gpu") return backend::gpu;
  if (name == "auto") return backend::automatic;
  return std::nullopt;
}

std::optional<std::string> validate(const entity_spec& s) {
  if (!finite(s.position)) return "position is not finite";
  if (!extent_ok(s.aoi_half)) return "AOI half-extent must be finite and >= 0";
  if (!extent_ok(s.presence_half)) return "presence half-extent must be finite and >= 0";
  return check_classes(s.visibility_class, s.sees);
}

namespace {

/// Without a finder of the caller's, the CPU backend finds candidates on the presence grid (the
/// same output as the space's own grid finder would give, faster on a zone's boxes).
interest_options tracker_options(const space_options& o) {
  interest_options t;
  t.hysteresis = o.hysteresis;
  t.max_visible = o.max_visible;
  t.rows_per_task = 256;
  t.presence_grid = o.finder == nullptr;
  return t;
}

}  // namespace

interest_space::interest_space(space_options options)
    : opt_(std::move(options)),
      capacity_(std::min(opt_.capacity, space_max_entities)),
      own_finder_(opt_.finder != nullptr ? nullptr : std::make_unique<grid_finder>(opt_.pool)),
      tracker_(opt_.finder != nullptr ? *opt_.finder : *own_finder_, opt_.pool, tracker_options(opt_)) {
  if (!std::isfinite(opt_.hysteresis) || opt_.hysteresis < 0) {
    throw std::invalid_argument("interest_space: the hysteresis must be finite and >= 0");
  }
  bump_layout();
  if (opt_.where == backend::cpu) return;
  if (opt_.max_visible != 0) {
    if (opt_.where == backend::gpu) throw std::invalid_argument("interest_space: max_visible runs on the CPU only");
    note_ = "max_visible is set (the cap runs on the CPU)";
    return;
  }
  std::string why;
  if (!set_backend(backend::gpu, &why)) {
    if (opt_.where == backend::gpu) throw std::invalid_argument("interest_space: backend gpu cannot run here: " + why);
    note_ = why;
  }
}

interest_space::~interest_space() = default;

void interest_space::bump_layout() {
  // One counter for every space of the process: no two spaces (or states) share a version.
  static std::atomic<std::uint64_t> next{1};
  layout_version_ = next.fetch_add(1, std::memory_order_relaxed);
}

bool interest_space::set_backend(backend b, std::string* why) {
  if (b == backend::cpu) {
    use_engine(nullptr);
    return true;
  }
  if (opt_.max_visible != 0) {
    if (why) *why = "max_visible is set (the cap runs on the CPU)";
    return false;
  }
  if (!own_engine_) {
    std::string reason = "no GPU engine maker was given (space_options::gpu)";
    if (opt_.gpu) own_engine_ = opt_.gpu(opt_.pool, &reason);
    if (!own_engine_) {
      if (why) *why = reason;
      return false;
    }
  }
  use_engine(own_engine_.get());
  return true;
}

void interest_space::use_engine(visibility_engine* engine) {
  engine_ = engine;
  tracker_.set_engine(engine);
  if (engine != nullptr) note_.clear();
}

backend interest_space::current_backend() const {
  return engine_ != nullptr && tracker_.engine_error().empty() ? backend::gpu : backend::cpu;
}

std::string interest_space::backend_note() const {
  if (engine_ != nullptr && !tracker_.engine_error().empty()) return "the engine failed: " + tracker_.engine_error();
  return note_;
}

void interest_space::reserve(std::size_t n) {
  n = std::min(n, capacity_);
  ids_.reserve(n);
  position_.reserve(n);
  aoi_half_.reserve(n);
  presence_half_.reserve(n);
  visibility_.reserve(n);
  sees_.reserve(n);
  slot_dense_.reserve(n);
  slot_generation_.reserve(n);
}

void interest_space::clear() {
  bump_layout();
  // Every live slot gets a new generation, so no old handle is accepted again.
  for (const entity_id id : ids_) {
    const std::uint32_t slot = id & slot_mask;
    slot_dense_[slot] = invalid_dense;
    slot_generation_[slot] = static_cast<std::uint16_t>(next_generation(id >> space_slot_bits));
    free_slots_.push_back(slot);
  }
  ids_.clear();
  position_.clear();
  aoi_half_.clear();
  presence_half_.clear();
  visibility_.clear();
  sees_.clear();
}

entity_id interest_space::add(const entity_spec& s, std::string* error) {
  if (auto why = validate(s)) {
    if (error) *error = std::move(*why);
    return null_entity;
  }
  if (ids_.size() >= capacity_) {
    if (error) *error = "the space is full (" + std::to_string(capacity_) + " entities)";
    return null_entity;
  }
  std::uint32_t slot;
  const std::size_t free = free_slots_.size() - free_head_;
  if (free > 0 && opt_.slot_reuse_after == 0) {
    slot = free_slots_.back();  // the most recently freed (free_head_ stays 0 here)
    free_slots_.pop_back();
  } else if (free > opt_.slot_reuse_after || (free > 0 && slot_dense_.size() >= space_max_entities)) {
    slot = free_slots_[free_head_++];  // the first freed
    if (free_head_ == free_slots_.size()) {
      free_slots_.clear();
      free_head_ = 0;
    } else if (free_head_ >= 4096 && free_head_ * 2 >= free_slots_.size()) {
      free_slots_.erase(free_slots_.begin(), free_slots_.begin() + static_cast<std::ptrdiff_t>(free_head_));
      free_head_ = 0;
    }
  } else {
    slot = static_cast<std::uint32_t>(slot_dense_.size());
    slot_dense_.push_back(invalid_dense);
    slot_generation_.push_back(1);
  }
  const entity_id id = (std::uint32_t{slot_generation_[slot]} << space_slot_bits) | slot;
  bump_layout();
  slot_dense_[slot] = static_cast<std::uint32_t>(ids_.size());
  ids_.push_back(id);
  position_.push_back(s.position);
  aoi_half_.push_back(s.aoi_half);
  presence_half_.push_back(s.presence_half);
  visibility_.push_back(s.visibility_class);
  sees_.push_back(s.sees);
  return id;
}

bool interest_space::remove(entity_id id) {
  const std::size_t dense = index_of(id);
  if (dense == npos) return false;
  bump_layout();
  const std::size_t last = ids_.size() - 1;
  // Swap-remove: the last entity moves into the hole.
  if (dense != last) {
    ids_[dense] = ids_[last];
    position_[dense] = position_[last];
    aoi_half_[dense] = aoi_half_[last];
    presence_half_[dense] = presence_half_[last];
    visibility_[dense] = visibility_[last];
    sees_[dense] = sees_[last];
    slot_dense_[ids_[dense] & slot_mask] = static_cast<std::uint32_t>(dense);
  }
  ids_.pop_back();
  position_.pop_back();
  aoi_half_.pop_back();
  presence_half_.pop_back();
  visibility_.pop_back();
  sees_.pop_back();
  const std::uint32_t slot = id & slot_mask;
  slot_dense_[slot] = invalid_dense;
  slot_generation_[slot] = static_cast<std::uint16_t>(next_generation(id >> space_slot_bits));
  free_slots_.push_back(slot);
  return true;
}

std::optional<entity_spec> interest_space::get(entity_id id) const {
  const std::size_t i = index_of(id);
  if (i == npos) return std::nullopt;
  return entity_spec{position_[i], aoi_half_[i], presence_half_[i], visibility_[i], sees_[i]};
}

bool interest_space::move(entity_id id, const vec3& p) {
  const std::size_t i = index_of(id);
  if (i == npos || !finite(p)) return false;
  position_[i] = p;
  return true;
}

bool interest_space::resize_aoi(entity_id id, const vec3& half) {
  const std::size_t i = index_of(id);
  if (i == npos || !extent_ok(half)) return false;
  aoi_half_[i] = half;
  bump_layout();
  return true;
}

bool interest_space::resize_presence(entity_id id, const vec3& half) {
  const std::size_t i = index_of(id);
  if (i == npos || !extent_ok(half)) return false;
  presence_half_[i] = half;
  bump_layout();
  return true;
}

bool interest_space::set_classes(entity_id id, std::uint32_t visibility_class, std::uint32_t sees) {
  const std::size_t i = index_of(id);
  if (i == npos || check_classes(visibility_class, sees)) return false;
  visibility_[i] = visibility_class;
  sees_[i] = sees;
  bump_layout();
  return true;
}

entity_columns interest_space::columns() const {
  entity_columns c;
  c.n = ids_.size();
  c.ids = ids_.data();
  c.slot_bits = space_slot_bits;
  c.slot_count = slot_dense_.size();
  c.position = position_.data();
  c.aoi_half = aoi_half_.data();
  c.presence_half = presence_half_.data();
  c.visibility = visibility_.data();
  c.sees = sees_.data();
  c.layout_version = layout_version_;
  return c;
}

std::optional<box_error> interest_space::step() { return tracker_.update(columns()); }

std::size_t interest_space::row_of(entity_id observer) const { return tracker_.row_of(observer); }

std::span<const entity_id> interest_space::visible(entity_id observer) const {
  const std::size_t r = row_of(observer);
  return r == npos ? std::span<const entity_id>{} : tracker_.visible(r);
}

std::span<const entity_id> interest_space::entered(entity_id observer) const {
  const std::size_t r = row_of(observer);
  return r == npos ? std::span<const entity_id>{} : tracker_.enters(r);
}

std::span<const entity_id> interest_space::left(entity_id observer) const {
  const std::size_t r = row_of(observer);
  return r == npos ? std::span<const entity_id>{} : tracker_.leaves(r);
}

}  // namespace zone::interest
