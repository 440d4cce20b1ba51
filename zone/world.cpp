// zone_world (NPC behaviours, movement, interest per tick).
#include <algorithm>
#include <functional>
#include <bit>
#include <chrono>
#include <limits>
#include <cmath>
#include <random>

#include "interest/measure.h"
#include "zone/zone_world.h"

namespace zone {

namespace cb = interest::category_bits;

namespace {

/// interest::run_tasks without a heap allocation per call: std::function keeps a
/// reference_wrapper in place, where a lambda capturing several references would be copied to
/// the heap (the tick allocates nothing in steady state).
template <class F>
void run_each(interest::thread_pool* pool, std::size_t n, F&& task) {
  interest::run_tasks(pool, n, std::ref(task));
}

using clock_type = std::chrono::steady_clock;

std::uint64_t splitmix(std::uint64_t z) {
  z += 0x9e3779b97f4a7c15ull;
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}

/// Uniform in [0, 1) from 53 random bits.
double unit_of(std::uint64_t bits) { return static_cast<double>(bits >> 11) * 0x1.0p-53; }

vec3 scaled(const vec3& v, float s) { return {v.x * s, v.y * s, v.z * s}; }
float length(const vec3& v) { return std::sqrt(v.x * v.x + v.y * v.y + v.z * v.z); }
vec3 toward(const vec3& from, const vec3& to, float speed) {
  const vec3 d{to.x - from.x, to.y - from.y, to.z - from.z};
  const float len = length(d);
  return len > 1e-6f ? scaled(d, speed / len) : vec3{};
}

constexpr std::uint64_t wander_period_ticks = 90;  // a wanderer picks a new heading this often
constexpr float patrol_side = 40;                  // patrol: a square of this side around home
constexpr float town_spread = 150;                 // town crowds: Gaussian of this sd around the centre
constexpr float town_radius = 250;                 // town NPCs walk back when farther than this

}  // namespace

// ---- zone_world --------------------------------------------------------------------------------

namespace {

interest::space_options on_finder(interest::pair_finder& finder, interest::thread_pool* pool) {
  interest::space_options o;
  o.where = interest::backend::cpu;
  o.finder = &finder;
  o.pool = pool;
  return o;
}

interest::space_options with_config(interest::space_options o, const zone_config& cfg) {
  o.hysteresis = cfg.hysteresis;
  o.max_visible = cfg.max_visible;
  return o;
}

}  // namespace

zone_world::zone_world(const zone_config& cfg, interest::pair_finder& finder, interest::thread_pool* pool)
    : zone_world(cfg, on_finder(finder, pool)) {}

zone_world::zone_world(const zone_config& cfg, interest::space_options interest)
    : cfg_(cfg), pool_(interest.pool), store_(max_entities, with_config(std::move(interest), cfg)) {
  std::mt19937_64 rng(cfg_.seed ^ 0x70776e73ull);
  const auto w = spawn_area();
  const std::size_t towns = cfg_.town_count != 0 ? cfg_.town_count : std::max<std::size_t>(1, cfg_.npc_count / 2000);
  for (std::size_t t = 0; t < towns; ++t) {
    const auto at = [&](float lo, float hi) {
      return lo + (hi - lo) * static_cast<float>(0.15 + 0.7 * unit_of(rng()));
    };
    towns_.push_back({at(w.lo.x, w.hi.x), at(w.lo.y, w.hi.y), w.lo.z});
  }
  // Only players (replication) and chasers (their behaviour) read visible sets right after the
  // interest step; a GPU engine copies back only theirs (interest_tracker::set_view_demand).
  store_.space().set_view_demand(&reads_view_);
}

void zone_world::set_reads_view(entity_id id, bool reads) {
  const std::uint32_t slot = slot_of(id);
  if (reads_view_.size() <= slot) reads_view_.resize(slot + 1, 0);
  reads_view_[slot] = reads ? 1 : 0;
}

void zone_world::set_watched(std::span<const entity_id> ids) {
  for (const entity_id id : watched_) {
    if (!store_.alive(id)) continue;
    const behaviour b = by_slot_[slot_of(id)].kind;  // back to what the world itself reads
    set_reads_view(id, b == behaviour::player || b == behaviour::chase);
  }
  watched_.assign(ids.begin(), ids.end());
  for (const entity_id id : watched_) {
    if (store_.alive(id)) set_reads_view(id, true);
  }
}

std::uint64_t zone_world::noise(entity_id id, std::uint64_t salt) const {
  return splitmix(cfg_.seed ^ splitmix(std::uint64_t{id} ^ splitmix(salt)));
}

vec3 zone_world::clamp_to_world(const vec3& p) const {
  const auto& w = cfg_.world;
  return {std::clamp(p.x, w.lo.x, w.hi.x), std::clamp(p.y, w.lo.y, w.hi.y), std::clamp(p.z, w.lo.z, w.hi.z)};
}

net::world_bounds zone_world::spawn_area() const {
  const auto& a = cfg_.spawn_area;
  if (!(a.lo.x < a.hi.x && a.lo.y < a.hi.y)) return cfg_.world;
  return {{a.lo.x, a.lo.y, cfg_.world.lo.z}, {a.hi.x, a.hi.y, cfg_.world.hi.z}};
}

behaviour zone_world::behaviour_of(entity_id id) const {
  if (!store_.alive(id)) return behaviour::player;
  return by_slot_[slot_of(id)].kind;
}

void zone_world::populate() {
  std::mt19937_64 rng(cfg_.seed);
  const auto u = [&] { return unit_of(rng()); };
  const auto w = spawn_area();
  const float shares[4] = {cfg_.share_wander, cfg_.share_patrol, cfg_.share_town, cfg_.share_chase};
  const float total = shares[0] + shares[1] + shares[2] + shares[3];
  const std::size_t n = cfg_.npc_count + cfg_.boss_count;
  store_.reserve(store_.size() + n);
  for (std::size_t k = 0; k < n; ++k) {
    entity_desc d;
    npc_state st;
    if (k < cfg_.boss_count) {
      st.kind = behaviour::boss;
    } else {
      const double r = u() * total;
      st.kind = r < shares[0]                           ? behaviour::wander
                : r < shares[0] + shares[1]             ? behaviour::patrol
                : r < shares[0] + shares[1] + shares[2] ? behaviour::town
                                                        : behaviour::chase;
    }
    const vec3 town = towns_[static_cast<std::size_t>(rng() % towns_.size())];
    if (st.kind == behaviour::town) {
      // A Gaussian crowd around the town.
      std::normal_distribution<float> spread(0, town_spread);
      const vec3 at{town.x + spread(rng), town.y + spread(rng), w.lo.z};
      d.position = clamp_to_world({std::clamp(at.x, w.lo.x, w.hi.x), std::clamp(at.y, w.lo.y, w.hi.y), at.z});
    } else {
      d.position = {static_cast<float>(w.lo.x + (w.hi.x - w.lo.x) * u()), static_cast<float>(w.lo.y + (w.hi.y - w.lo.y) * u()),
                    w.lo.z};
    }
    st.home = st.kind == behaviour::town ? town : d.position;
    // AOI tier by behaviour: small folk see tiny .. medium; chasers medium; bosses gigantic.
    const int tier = st.kind == behaviour::boss ? 4 : st.kind == behaviour::chase ? 2 : static_cast<int>(rng() % 3);
    const float aoi = cfg_.aoi_tier[tier];
    d.aoi_half_extent = {aoi, aoi, std::min(aoi, (w.hi.z - w.lo.z) / 2)};
    d.presence_half_extent = st.kind == behaviour::boss ? vec3{cfg_.boss_footprint, cfg_.boss_footprint, cfg_.boss_footprint}
                                                        : vec3{0.5f, 0.5f, 1.0f};
    d.kind = st.kind == behaviour::boss ? entity_kind::boss : entity_kind::npc;
    const double v = u();
    d.visibility_class = st.kind == behaviour::boss ? cb::normal
                         : v < 0.9                  ? cb::normal
                         : v < 0.95                 ? cb::stealth
                         : v < 0.975                ? cb::team_red
                                                    : cb::team_blue;
    d.sees = cb::normal | cb::team_red | cb::team_blue | (d.visibility_class == cb::stealth ? cb::stealth : 0u);
    const entity_id id = store_.create(d);
    if (id == null_entity) break;
    set_state(id, st);
    set_reads_view(id, st.kind == behaviour::chase);
  }
}

void zone_world::set_state(entity_id id, const npc_state& st) {
  const std::uint32_t slot = slot_of(id);
  if (by_slot_.size() <= slot) {
    by_slot_.resize(slot + 1);
    is_player_.resize(slot + 1, 0);
    headings_.resize(slot + 1);
  }
  by_slot_[slot] = st;
  is_player_[slot] = st.kind == behaviour::player ? 1 : 0;
}

vec3 zone_world::player_spawn_point(std::uint64_t key) const {
  const vec3 at = towns_[static_cast<std::size_t>(key % towns_.size())];
  const std::uint64_t h = splitmix(key);
  const double r = cfg_.spawn_radius * std::sqrt(static_cast<double>(h >> 40) / 16777216.0);
  const double a = static_cast<double>(h & 0xffffff) / 16777216.0 * 6.283185307179586;
  const auto w = spawn_area();
  return clamp_to_world({std::clamp(at.x + static_cast<float>(r * std::cos(a)), w.lo.x, w.hi.x),
                         std::clamp(at.y + static_cast<float>(r * std::sin(a)), w.lo.y, w.hi.y), at.z});
}

entity_id zone_world::spawn_player(const vec3& at, bool stealth, std::uint8_t team) {
  entity_desc d;
  const player_visibility v = visibility_for(stealth, team);
  d.visibility_class = v.visibility_class;
  d.sees = v.sees;
  d.position = clamp_to_world(at);
  d.aoi_half_extent = {cfg_.player_aoi, cfg_.player_aoi, cfg_.player_aoi};
  d.presence_half_extent = {0.5f, 0.5f, 1.0f};
  d.kind = entity_kind::player;
  const entity_id id = store_.create(d);
  if (id == null_entity) return id;
  set_state(id, npc_state{behaviour::player, d.position, 0, {}});
  set_reads_view(id, player_views_on_host_);
  return id;
}

void zone_world::set_player_views_on_host(bool on) {
  if (on == player_views_on_host_) return;
  player_views_on_host_ = on;
  for (const entity_id id : store_.ids()) {
    const std::uint32_t slot = slot_of(id);
    if (slot < by_slot_.size() && by_slot_[slot].kind == behaviour::player) set_reads_view(id, on);
  }
}

bool zone_world::despawn(entity_id id) {
  if (!store_.destroy(id)) return false;
  set_reads_view(id, false);
  return true;
}

entity_id zone_world::adopt(const entity_desc& d, const behaviour_state& b) {
  const entity_id id = store_.create(d);
  if (id == null_entity) return id;
  set_state(id, b);  // by_slot_ and is_player_ grow together
  // is_player_ tells the entity's kind (a world's ghost of a player is one too: chasers see it).
  is_player_[slot_of(id)] = d.kind == entity_kind::player ? 1 : 0;
  set_reads_view(id, b.kind == behaviour::player || b.kind == behaviour::chase);
  return id;
}

std::optional<behaviour_state> zone_world::behaviour_state_of(entity_id id) const {
  if (!store_.alive(id)) return std::nullopt;
  return by_slot_[slot_of(id)];
}

bool zone_world::set_behaviour_state(entity_id id, const behaviour_state& b) {
  if (!store_.alive(id)) return false;
  by_slot_[slot_of(id)] = b;
  set_reads_view(id, b.kind == behaviour::player || b.kind == behaviour::chase);
  return true;
}

bool zone_world::set_intent(entity_id player, const vec3& intent) {
  if (!store_.alive(player) || by_slot_[slot_of(player)].kind != behaviour::player) return false;
  if (!std::isfinite(intent.x) || !std::isfinite(intent.y) || !std::isfinite(intent.z)) return false;
  // The vertical rule: players walk unless they may fly.
  vec3 v{intent.x, intent.y, cfg_.player_fly ? intent.z : 0.0f};
  // Scale by the largest component first: the squares of a large finite intent (1e30) overflow
  // to infinity and the normalised intent became zero; of a tiny one they underflow.
  const float m = std::max({std::abs(v.x), std::abs(v.y), std::abs(v.z)});
  if (m > 1) v = scaled(v, 1 / m);
  const float len = length(v);
  by_slot_[slot_of(player)].intent = len > 1 ? scaled(v, 1 / len) : v;
  return true;
}

bool zone_world::teleport(entity_id player, const vec3& to, bool* clamped) {
  if (!store_.alive(player) || by_slot_[slot_of(player)].kind != behaviour::player) return false;
  if (!std::isfinite(to.x) || !std::isfinite(to.y) || !std::isfinite(to.z)) return false;
  const vec3 at = clamp_to_world(to);
  if (clamped) *clamped = !(at == to);
  return store_.space().teleport(player, at);  // the tick API's jump
}

void zone_world::decide(std::size_t first, std::size_t last) {
  const auto ids = store_.ids();
  const auto pos = store_.positions();
  auto vel = store_.velocities();
  for (std::size_t i = first; i < last; ++i) {
    const entity_id id = ids[i];
    const std::uint32_t slot = slot_of(id);
    npc_state& st = by_slot_[slot];
    const vec3 p = pos[i];
    const auto heading = [&](float speed) {
      // The period's heading, once a period (cos and sin in double were a tenth of the tick's
      // threads' time at 80,000 NPCs: docs/zone-benchmarks.md, "The tick's threads").
      const std::uint64_t period = tick_ / wander_period_ticks;
      heading_cache& h = headings_[slot];
      if (h.id != id || h.period != period) {
        const double a = unit_of(noise(id, period)) * 6.283185307179586;
        h = {id, period, static_cast<float>(std::cos(a)), static_cast<float>(std::sin(a))};
      }
      return vec3{speed * h.cos, speed * h.sin, 0};
    };
    switch (st.kind) {
      case behaviour::player:
        vel[i] = scaled(st.intent, cfg_.player_speed);
        break;
      case behaviour::wander:
        vel[i] = heading(cfg_.npc_speed);
        break;
      case behaviour::patrol: {
        const float h = patrol_side / 2;
        const vec3 corner[4] = {{st.home.x - h, st.home.y - h, p.z}, {st.home.x + h, st.home.y - h, p.z},
                                {st.home.x + h, st.home.y + h, p.z}, {st.home.x - h, st.home.y + h, p.z}};
        const vec3 target = clamp_to_world(corner[st.waypoint % 4]);
        const vec3 d{target.x - p.x, target.y - p.y, 0};
        if (length(d) <= cfg_.npc_speed / static_cast<float>(cfg_.tick_rate_hz) + 1e-3f) st.waypoint = (st.waypoint + 1) % 4;
        vel[i] = toward(p, clamp_to_world(corner[st.waypoint % 4]), cfg_.npc_speed);
        break;
      }
      case behaviour::town: {
        const vec3 d{st.home.x - p.x, st.home.y - p.y, 0};
        vel[i] = length(d) > town_radius ? toward(p, {st.home.x, st.home.y, p.z}, cfg_.npc_speed) : heading(cfg_.npc_speed / 2);
        break;
      }
      case behaviour::chase: {
        // The nearest player this NPC saw last tick (the same interest results as everyone).
        const std::size_t row = tracker().row_of(id);
        float best = std::numeric_limits<float>::infinity();
        entity_id prey = null_entity;
        if (row != entity_store::npos) {
          for (const entity_id seen : tracker().visible(row)) {
            // The kind first (one byte by slot): most of what a chaser sees is not a player,
            // and the store's lookup (two more random reads) is needed only for players. Same
            // result as the lookup first.
            const std::uint32_t slot = slot_of(seen);
            if (slot >= is_player_.size() || is_player_[slot] == 0) continue;
            const std::size_t k = store_.index_of(seen);
            if (k == entity_store::npos) continue;
            const vec3 d{pos[k].x - p.x, pos[k].y - p.y, pos[k].z - p.z};
            const float dist = length(d);
            if (dist < best || (dist == best && seen < prey)) {
              best = dist;
              prey = seen;
            }
          }
        }
        if (prey != null_entity) {
          // Run at 1.5 x speed, but stop at the prey instead of overshooting it.
          const float speed = std::min(cfg_.npc_speed * 1.5f, best * static_cast<float>(cfg_.tick_rate_hz));
          vel[i] = toward(p, pos[store_.index_of(prey)], speed);
        } else {
          vel[i] = heading(cfg_.npc_speed);
        }
        break;
      }
      case behaviour::boss: {
        const vec3 d{st.home.x - p.x, st.home.y - p.y, 0};
        vel[i] = length(d) > 100 ? toward(p, {st.home.x, st.home.y, p.z}, cfg_.npc_speed / 2) : heading(cfg_.npc_speed / 2);
        break;
      }
      case behaviour::ghost:
        vel[i] = {};  // placed by its owner zone's messages
        break;
    }
  }
}

std::optional<interest::box_error> zone_world::step() {
  const auto t_start = clock_type::now();
  ++tick_;
  const std::size_t n = store_.size();
  constexpr std::size_t chunk = 1024;
  const std::size_t tasks = (n + chunk - 1) / chunk;

  // 1. Behaviours: velocities from the previous tick's positions and visible sets.
  auto t0 = clock_type::now();
  run_each(pool_, tasks, [&](std::size_t t) { decide(t * chunk, std::min(n, (t + 1) * chunk)); });
  last_step_.behaviours = ms_since(t0);
  phases_.behaviours.record(last_step_.behaviours);

  // 2. Integrate inside the world bounds (bounce off the edges).
  t0 = clock_type::now();
  const float dt = static_cast<float>(1.0 / cfg_.tick_rate_hz);
  const auto& w = cfg_.world;
  run_each(pool_, tasks, [&](std::size_t t) {
    auto pos = store_.positions();
    auto vel = store_.velocities();
    for (std::size_t i = t * chunk; i < std::min(n, (t + 1) * chunk); ++i) {
      vec3 p{pos[i].x + vel[i].x * dt, pos[i].y + vel[i].y * dt, pos[i].z + vel[i].z * dt};
      if (p.x < w.lo.x || p.x > w.hi.x) vel[i].x = -vel[i].x;
      if (p.y < w.lo.y || p.y > w.hi.y) vel[i].y = -vel[i].y;
      if (p.z < w.lo.z || p.z > w.hi.z) vel[i].z = -vel[i].z;
      pos[i] = clamp_to_world(p);
    }
  });
  last_step_.integrate = ms_since(t0);
  phases_.integrate.record(last_step_.integrate);

  // 3. Interest.
  t0 = clock_type::now();
  auto err = store_.space().step();
  last_step_.interest = ms_since(t0);
  last_step_.total = ms_since(t_start);
  phases_.interest.record(last_step_.interest);
  phases_.total.record(last_step_.total);
  return err;
}

std::uint64_t zone_world::digest() const {
  std::uint64_t h = tracker().digest() ^ splitmix(tick_);
  for (std::size_t i = 0; i < store_.size(); ++i) {
    const vec3 p = store_.positions()[i];
    h = splitmix(h ^ store_.ids()[i]);
    h = splitmix(h ^ std::bit_cast<std::uint32_t>(p.x) ^ (std::uint64_t{std::bit_cast<std::uint32_t>(p.y)} << 32));
    h = splitmix(h ^ std::bit_cast<std::uint32_t>(p.z));
  }
  return h;
}

}  // namespace zone
