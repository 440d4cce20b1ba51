// zone-server: the MMO zone server (docs/zone.md). `zone-server --help` lists the options. With
// --world NAME --nats URL it serves one region of a world of zones (docs/world.md).
#include <algorithm>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <limits>
#include <memory>
#include <thread>

#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include "zone_server.h"
#ifdef ZONE_HAVE_NATS
#include "world/nats_node.h"
#endif

namespace {
zone::zone_server* running = nullptr;
volatile std::sig_atomic_t interrupted = 0;
extern "C" void on_signal(int) {
  interrupted = 1;
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
  // The log on stderr (docs/operating.md, "Logs"); stdout only carries --help. Same format as
  // spdlog's default logger (no logger name in the lines).
  spdlog::set_default_logger(
      std::make_shared<spdlog::logger>("", std::make_shared<spdlog::sinks::stderr_color_sink_mt>()));
  spdlog::set_level(spdlog::level::from_str(parsed.config->log_level));
  zone::zone_config cfg = *parsed.config;
  std::signal(SIGINT, on_signal);
  std::signal(SIGTERM, on_signal);
#ifdef ZONE_HAVE_NATS
  std::unique_ptr<zone::world::nats_node> node;
  if (!cfg.world_name.empty()) {
    zone::world::node_options o;
    o.world = cfg.world_name;
    o.url = cfg.nats_url;
    o.cols = cfg.world_cols;
    o.rows = cfg.world_rows;
    o.bounds = cfg.world;
    o.advertise_host = cfg.listen_address == "0.0.0.0" ? "127.0.0.1" : cfg.listen_address;
    o.lease_ttl_s = cfg.world_lease_ttl_s;
    o.nats_timeout_s = cfg.world_nats_timeout_s;
    o.capacity = cfg.world_capacity;
    o.checkpoint_s = cfg.world_checkpoint_s;
    o.resume_s = cfg.world_resume_s;
    o.linger_s = cfg.linger_s;
    // A restarted zone waits for its predecessor's lease to lapse (its TTL, a few seconds); a
    // standby for any region's, as long as it takes.
    o.claim_wait_s =
        cfg.world_standby ? std::numeric_limits<double>::infinity() : std::max(20.0, 2 * cfg.world_lease_ttl_s);
    o.keep_waiting = [] { return !interrupted; };
    std::string err;
    if (!(node = zone::world::nats_node::join(o, cfg, &err))) {
      if (interrupted) return 0;
      spdlog::critical("{}", err);
      return 1;
    }
    cfg = node->zone_for_region(cfg);
  }
#else
  if (!cfg.world_name.empty()) {
    std::fprintf(stderr, "zone-server: built without libnats: --world is not available (docs/world.md)\n");
    return 2;
  }
#endif
  zone::zone_server server(cfg);
#ifdef ZONE_HAVE_NATS
  if (node) server.set_extension(node.get());
#endif
  if (auto err = server.start()) {
    spdlog::critical("{}", *err);
    return 1;
  }
  running = &server;
  if (interrupted) server.stop();
  server.run();
  running = nullptr;
#ifdef ZONE_HAVE_NATS
  if (node) {
    node->leave();  // first: its sender settles (or abandons) the records still queued
    const auto& s = node->stats();
    const auto& l = node->link().stats();
    spdlog::info(
        "world: region {} owned {} entities at the end; handoffs out {} (CAS conflicts {}, confirmed by read-back {}, rounds retried {}, abandoned at the stop {}), in {} "
        "(duplicates {}, no room {}); held for a full neighbour {} entity-ticks; handoff latency p50 {:.2f} ms p99 {:.2f} ms max {:.2f} ms (p99 {:.2f} ticks); redirects {} claimed {}; "
        "players restored {} resumed {}, kept after a lost connection {} back {} (removed, their client never came: {}); "
        "ghost bytes out {} in {} over {} / {} messages; gaps {}, snapshots out {}; lease taken back {} times; "
        "checkpoints written {} (the last {} entities, {} bytes; the tick's copy {:.2f} ms on average, {:.2f} at most), skipped {}, failed {}; "
        "restored {} at the start ({} of them from handoff records; {} left out)",
        node->region(), node->link().owned_count(), l.handoffs_out, s.handoff_cas_conflicts.load(),
        s.handoff_cas_confirmed.load(), s.handoff_retries.load(), s.handoffs_abandoned.load(),
        s.handoffs_applied.load(), s.handoff_duplicates.load(), s.handoffs_no_room.load(), l.handoffs_held_for_room,
        node->handoff_ms().percentile(0.5), node->handoff_ms().percentile(0.99), node->handoff_ms().max(),
        node->handoff_ticks().percentile(0.99), s.redirects.load(), s.redirect_claims.load(), s.players_restored.load(),
        s.players_resumed.load(), s.players_lingered.load(), s.players_back_after_linger.load(),
        s.players_abandoned.load(), l.ghost_bytes_out, l.ghost_bytes_in, l.ghost_messages_out, l.ghost_messages_in,
        l.gaps, l.snapshots_out, s.lease_reclaims.load(), s.checkpoints_written.load(), s.checkpoint_entities.load(),
        s.checkpoint_bytes.load(),
        static_cast<double>(s.checkpoint_copy_total_us.load()) / 1000.0 /
            static_cast<double>(std::max<std::uint64_t>(1, s.checkpoint_copies.load())),
        static_cast<double>(s.checkpoint_copy_max_us.load()) / 1000.0, s.checkpoints_skipped.load(),
        s.checkpoint_failures.load(), l.restored, s.restored_from_records.load(), s.restore_skipped.load());
  }
#endif
  return 0;
}
