// A game server's tick loop on the tick API of the installed `zone` package (docs/embedding.md):
// register entities, move them, step once a tick, send each observer its enters and leaves.
// Usage: tick-loop [cpu|gpu|auto] (default auto: the GPU when the package and a device allow).
#include <zone/interest_space.h>
#ifdef EXAMPLE_WITH_GPU
#include <zone/visibility.h>
#endif

#include <cstdio>
#include <map>
#include <stdexcept>
#include <string>

namespace zi = zone::interest;
namespace bits = zone::interest::category_bits;

int main(int argc, char** argv) {
  zi::space_options options;
  const auto where = zi::parse_backend(argc > 1 ? argv[1] : "auto");
  if (!where) {
    std::fprintf(stderr, "usage: tick-loop [cpu|gpu|auto]\n");
    return 64;
  }
  options.where = *where;
  options.hysteresis = 2;  // metres: an entity at the edge of a view does not flicker in and out
#ifdef EXAMPLE_WITH_GPU
  options.gpu = zone::gpu::make_visibility_engine;
#endif
  try {
    zi::interest_space space(options);
    std::fprintf(stderr, "tick-loop: interest on the %s\n", space.current_backend() == zi::backend::gpu ? "GPU" : "CPU");

    std::map<zi::entity_id, std::string> name;
    const auto add = [&](const char* who, const zi::entity_spec& spec) {
      const zi::entity_id id = space.add(spec);
      name[id] = who;
      return id;
    };
    const auto guard = add("guard", {.position = {0, 0, 0}, .aoi_half = {20, 20, 5}});
    const auto thief = add("thief", {.position = {40, 0, 0}, .aoi_half = {20, 20, 5}, .visibility_class = bits::stealth});
    const auto merchant = add("merchant", {.position = {-30, 0, 0}, .aoi_half = {10, 10, 5}});

    for (int tick = 1; tick <= 6; ++tick) {
      space.move(thief, {40.0f - 8.0f * static_cast<float>(tick), 0, 0});  // sneaks towards the guard
      if (tick == 3) space.set_classes(guard, bits::normal, bits::normal | bits::stealth);  // a potion
      if (tick == 4) space.teleport(merchant, {5, 5, 0});
      if (tick == 5) space.resize_aoi(guard, {5, 5, 5});  // night falls
      if (tick == 6) space.remove(merchant);
      if (auto error = space.step()) {
        std::fprintf(stderr, "tick %d: %s\n", tick, error->message.c_str());
        return 2;
      }
      for (const auto& [id, who] : name) {  // what a server sends each observer's client
        if (!space.alive(id)) continue;
        for (const zi::entity_id e : space.entered(id)) std::printf("tick %d: %s + %s\n", tick, who.c_str(), name[e].c_str());
        for (const zi::entity_id e : space.left(id)) std::printf("tick %d: %s - %s\n", tick, who.c_str(), name[e].c_str());
      }
    }
    std::printf("guard sees %zu at the end\n", space.visible(guard).size());
  } catch (const std::invalid_argument& e) {  // backend gpu where none can run
    std::fprintf(stderr, "tick-loop: %s\n", e.what());
    return 1;
  }
  return 0;
}
