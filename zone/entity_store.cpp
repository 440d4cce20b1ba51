// The zone's entities (entity_store.h): an interest_space with the zone's columns beside it.
#include "zone/entity_store.h"

#include <cmath>

namespace zone {

namespace {

bool finite(const vec3& v) { return std::isfinite(v.x) && std::isfinite(v.y) && std::isfinite(v.z); }

interest::entity_spec spec_of(const entity_desc& d) {
  return {d.position, d.aoi_half_extent, d.presence_half_extent, d.visibility_class, d.sees};
}

interest::space_options with_capacity(interest::space_options o, std::size_t capacity) {
  o.capacity = capacity;
  return o;
}

}  // namespace

std::optional<std::string> validate(const entity_desc& d) {
  if (!finite(d.position)) return "position is not finite";
  if (!finite(d.velocity)) return "velocity is not finite";
  return interest::validate(spec_of(d));
}

entity_store::entity_store(std::size_t capacity, interest::space_options interest)
    : space_(with_capacity(std::move(interest), std::min(capacity, max_entities))) {}

void entity_store::reserve(std::size_t n) {
  space_.reserve(n);
  n = std::min(n, space_.capacity());
  velocity_.reserve(n);
  kind_.reserve(n);
}

void entity_store::clear() {
  space_.clear();
  journal_count_ = 0;
  velocity_.clear();
  kind_.clear();
}

entity_id entity_store::create(const entity_desc& d, std::string* error) {
  if (auto why = validate(d)) {
    if (error) *error = std::move(*why);
    return null_entity;
  }
  std::string reason;
  const entity_id id = space_.add(spec_of(d), &reason);
  if (id == null_entity) {
    if (error) *error = "entity store is full (" + std::to_string(space_.capacity()) + " entities)";
    return null_entity;
  }
  velocity_.push_back(d.velocity);
  kind_.push_back(d.kind);
  return id;
}

bool entity_store::destroy(entity_id id) {
  const std::size_t dense = index_of(id);
  if (dense == npos) return false;
  space_.remove(id);
  // The space moved its last entity into the hole: the same here.
  velocity_[dense] = velocity_.back();
  kind_[dense] = kind_.back();
  velocity_.pop_back();
  kind_.pop_back();
  return true;
}

std::optional<entity_desc> entity_store::get(entity_id id) const {
  const std::size_t i = index_of(id);
  if (i == npos) return std::nullopt;
  const auto s = *space_.get(id);
  return entity_desc{s.position, velocity_[i], s.visibility_class, s.sees, s.aoi_half, s.presence_half, kind_[i]};
}

bool entity_store::set_visibility(entity_id id, std::uint32_t visibility_class, std::uint32_t sees) {
  const std::uint64_t before = space_.layout_version();
  if (!space_.set_classes(id, visibility_class, sees)) return false;
  journal_[journal_count_ % journal_.size()] = {before, space_.layout_version(),
                                                static_cast<std::uint32_t>(index_of(id))};
  ++journal_count_;
  return true;
}

bool entity_store::set_velocity(entity_id id, const vec3& v) {
  const std::size_t i = index_of(id);
  if (i == npos || !finite(v)) return false;
  velocity_[i] = v;
  return true;
}

}  // namespace zone
