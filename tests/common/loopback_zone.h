// tests/common/loopback_zone.h: the small zone that the in-process server tests run on loopback
// (tests/bots/test_teleport.cpp, tests/zone/test_zone_server.cpp, tests/zone/test_zone_viewer.cpp);
// each test sets what it needs on top.
#pragma once

#include "zone/zone_config.h"

namespace zone::test {

/// A 600 x 600 x 40 m world at 30 Hz on 127.0.0.1, the game port and (when a test enables
/// /metrics) the metrics port ephemeral, logging only warnings.
inline zone_config loopback_zone_config() {
  zone_config c;
  c.world = {{0, 0, 0}, {600, 600, 40}};
  c.listen_address = "127.0.0.1";
  c.port = 0;
  c.metrics_port = 0;
  c.tick_rate_hz = 30;
  c.log_level = "warn";
  return c;
}

}  // namespace zone::test
