// zone/zone.h: the zone layer's headers in one include (docs/zone.md). Each part has a header of
// its own; include the one you need:
//  - zone/entity_store.h: entities, a dense store with generation-checked handles;
//  - interest/interest_tracker.h (the interest layer's): per-observer visible sets with enter/leave
//    events and hysteresis;
//  - zone/replicator.h: what each client is sent per tick;
//  - zone/zone_config.h: configuration (command line, config file) and NPC behaviours;
//  - zone/zone_world.h: the per-tick world step and its timings (net/latency_histogram.h).
#pragma once

#include "zone/entity_store.h"
#include "interest/interest_tracker.h"
#include "zone/replicator.h"
#include "zone/zone_config.h"
#include "zone/zone_world.h"
