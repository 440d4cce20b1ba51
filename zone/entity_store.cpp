// Dense structure-of-arrays entity storage with generation-checked handles (zone.h).
#include <algorithm>
#include <bit>
#include <cmath>

#include <atomic>

#include "zone/entity_store.h"

namespace zone {

namespace {

constexpr std::uint32_t invalid_dense = 0xffffffffu;

bool finite(const vec3& v) { return std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z); }
bool extent_ok(const vec3& v) { return finite(v) && v.x >= 0 && v.y >= 0 && v.z >= 0; }

std::optional<std::string> check_visibility(std::uint32_t cls, std::uint32_t sees) {
  if (std::popcount(cls) != 1 || (cls & interest::category_bits::aoi) != 0) {
    return "visibility class must be exactly one category bit other than aoi (got " + std::to_string(cls) + ")";
  }
  if ((sees & interest::category_bits::aoi) != 0) return "sees must not contain the aoi bit";
  return std::nullopt;
}

}  // namespace

std::optional<std::string> validate(const entity_desc& d) {
  if (!finite(d.position)) return "position is not finite";
  if (!finite(d.velocity)) return "velocity is not finite";
  if (!extent_ok(d.aoi_half_extent)) return "AOI half-extent must be finite and >= 0";
  if (!extent_ok(d.presence_half_extent)) return "presence half-extent must be finite and >= 0";
  return check_visibility(d.visibility_class, d.sees);
}

entity_store::entity_store(std::size_t capacity) : capacity_(std::min(capacity, max_entities)) { bump_layout(); }

void entity_store::bump_layout() {
  // One counter for every store of the process: no two stores (or states) share a version.
  static std::atomic<std::uint64_t> next{1};
  layout_version_ = next.fetch_add(1, std::memory_order_relaxed);
}

void entity_store::reserve(std::size_t n) {
  n = std::min(n, capacity_);
  ids_.reserve(n);
  position_.reserve(n);
  velocity_.reserve(n);
  aoi_half_.reserve(n);
  presence_half_.reserve(n);
  visibility_class_.reserve(n);
  sees_.reserve(n);
  kind_.reserve(n);
  slot_dense_.reserve(n);
  slot_generation_.reserve(n);
}

void entity_store::clear() {
  bump_layout();
  // Every live slot gets a new generation, so no old handle is accepted again.
  for (const entity_id id : ids_) {
    const std::uint32_t slot = slot_of(id);
    slot_dense_[slot] = invalid_dense;
    slot_generation_[slot] = static_cast<std::uint16_t>(generation_of(id) == max_generation ? 1 : generation_of(id) + 1);
    free_slots_.push_back(slot);
  }
  ids_.clear();
  position_.clear();
  velocity_.clear();
  aoi_half_.clear();
  presence_half_.clear();
  visibility_class_.clear();
  sees_.clear();
  kind_.clear();
}

entity_id entity_store::create(const entity_desc& d, std::string* error) {
  if (auto why = validate(d)) {
    if (error) *error = std::move(*why);
    return null_entity;
  }
  if (ids_.size() >= capacity_) {
    if (error) *error = "entity store is full (" + std::to_string(capacity_) + " entities)";
    return null_entity;
  }
  std::uint32_t slot;
  if (!free_slots_.empty()) {
    slot = free_slots_.back();
    free_slots_.pop_back();
  } else {
    slot = static_cast<std::uint32_t>(slot_dense_.size());
    slot_dense_.push_back(invalid_dense);
    slot_generation_.push_back(1);
  }
  const entity_id id = (std::uint32_t{slot_generation_[slot]} << entity_index_bits) | slot;
  bump_layout();
  slot_dense_[slot] = static_cast<std::uint32_t>(ids_.size());
  ids_.push_back(id);
  position_.push_back(d.position);
  velocity_.push_back(d.velocity);
  aoi_half_.push_back(d.aoi_half_extent);
  presence_half_.push_back(d.presence_half_extent);
  visibility_class_.push_back(d.visibility_class);
  sees_.push_back(d.sees);
  kind_.push_back(d.kind);
  return id;
}

bool entity_store::destroy(entity_id id) {
  const std::size_t dense = index_of(id);
  if (dense == npos) return false;
  bump_layout();
  const std::size_t last = ids_.size() - 1;
  // Swap-remove: the last entity moves into the hole.
  if (dense != last) {
    ids_[dense] = ids_[last];
    position_[dense] = position_[last];
    velocity_[dense] = velocity_[last];
    aoi_half_[dense] = aoi_half_[last];
    presence_half_[dense] = presence_half_[last];
    visibility_class_[dense] = visibility_class_[last];
    sees_[dense] = sees_[last];
    kind_[dense] = kind_[last];
    slot_dense_[slot_of(ids_[dense])] = static_cast<std::uint32_t>(dense);
  }
  ids_.pop_back();
  position_.pop_back();
  velocity_.pop_back();
  aoi_half_.pop_back();
  presence_half_.pop_back();
  visibility_class_.pop_back();
  sees_.pop_back();
  kind_.pop_back();

  const std::uint32_t slot = slot_of(id);
  slot_dense_[slot] = invalid_dense;
  const std::uint32_t gen = generation_of(id);
  slot_generation_[slot] = static_cast<std::uint16_t>(gen == max_generation ? 1 : gen + 1);
  free_slots_.push_back(slot);
  return true;
}

std::optional<entity_desc> entity_store::get(entity_id id) const {
  const std::size_t i = index_of(id);
  if (i == npos) return std::nullopt;
  return entity_desc{position_[i], velocity_[i], visibility_class_[i], sees_[i], aoi_half_[i], presence_half_[i], kind_[i]};
}

bool entity_store::set_position(entity_id id, const vec3& p) {
  const std::size_t i = index_of(id);
  if (i == npos || !finite(p)) return false;
  position_[i] = p;
  return true;
}

bool entity_store::set_velocity(entity_id id, const vec3& v) {
  const std::size_t i = index_of(id);
  if (i == npos || !finite(v)) return false;
  velocity_[i] = v;
  return true;
}

bool entity_store::set_aoi_half_extent(entity_id id, const vec3& h) {
  const std::size_t i = index_of(id);
  if (i == npos || !extent_ok(h)) return false;
  aoi_half_[i] = h;
  bump_layout();
  return true;
}

bool entity_store::set_presence_half_extent(entity_id id, const vec3& h) {
  const std::size_t i = index_of(id);
  if (i == npos || !extent_ok(h)) return false;
  presence_half_[i] = h;
  bump_layout();
  return true;
}

bool entity_store::set_visibility(entity_id id, std::uint32_t visibility_class, std::uint32_t sees) {
  const std::size_t i = index_of(id);
  if (i == npos || check_visibility(visibility_class, sees)) return false;
  visibility_class_[i] = visibility_class;
  sees_[i] = sees;
  bump_layout();
  return true;
}

interest::entity_columns entity_store::columns() const {
  interest::entity_columns c;
  c.n = ids_.size();
  c.ids = ids_.data();
  c.slot_bits = entity_index_bits;
  c.slot_count = slot_count();
  c.position = position_.data();
  c.aoi_half = aoi_half_.data();
  c.presence_half = presence_half_.data();
  c.visibility = visibility_class_.data();
  c.sees = sees_.data();
  c.layout_version = layout_version_;
  return c;
}

}  // namespace zone
