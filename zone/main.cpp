// zone-server: the MMO zone server (docs/zone.md). `zone-server --help` lists the options.
#include <csignal>
#include <cstdio>

#include <spdlog/spdlog.h>

#include "zone_server.h"

namespace {
zone::zone_server* running = nullptr;
extern "C" void on_signal(int) {
  if (running) running->stop();
}
}  // namespace

int main(int argc, char** argv) {
  const auto parsed = zone::parse_config(argc, argv);
  if (parsed.help) {
    std::fputs(parsed.message.c_str(), stdout);
    return 0;
  }
  if (!parsed.config) {
    std::fprintf(stderr, "zone-server: %s (try --help)\n", parsed.message.c_str());
    return 2;
  }
  spdlog::set_level(spdlog::level::from_str(parsed.config->log_level));
  zone::zone_server server(*parsed.config);
  if (auto err = server.start()) {
    spdlog::critical("{}", *err);
    return 1;
  }
  running = &server;
  std::signal(SIGINT, on_signal);
  std::signal(SIGTERM, on_signal);
  server.run();
  running = nullptr;
  return 0;
}
