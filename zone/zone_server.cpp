// The tick loop (zone_server.h): drain client inputs, step the world, replicate, at a fixed rate.
#include "zone_server.h"

#include "engine_faults.h"
#include "gpu/device_fault.h"
#include "gpu/finders.h"
#include "gpu/replication.h"
#include "gpu/visibility.h"
#include "interest/measure.h"
#include "net/os_limits.h"

#include <spdlog/spdlog.h>

#include <bit>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <functional>
#include <random>
#include <thread>
#include <utility>

namespace zone {

namespace {

using clock_type = std::chrono::steady_clock;

/// A CPU list of the config as CPUs to pin to: empty when the list is bad or names a CPU this
/// process may not use (validate() refuses those with the reason; nothing is pinned meanwhile).
std::vector<int> pin_cpus(const std::string& list) {
  auto cpus = net::parse_cpu_list(list);
  if (!cpus || net::check_cpus_allowed(*cpus)) return {};
  return *cpus;
}

net::server_options net_options(const zone_config& c) {
  net::server_options o;
  o.address = c.listen_address;
  o.port = c.port;
  o.io_threads = c.io_threads;
  o.max_connections = c.max_clients;
  o.inbound.max_frame_bytes = c.max_frame_bytes;
  o.socket_send_buffer = c.socket_send_buffer;
  o.direct_writes = c.direct_writes;
  o.io_thread_nice = c.io_nice;
  o.io_thread_cpus = pin_cpus(c.io_cpus);
  o.batching = net::parse_write_batching(c.write_batching).value_or(net::write_batching::automatic);
  o.write_slice = c.write_slice;
  o.inputs_per_second = c.inputs_per_second;
  o.input_burst = std::max(1.0, c.inputs_per_second / 2);
  o.pings_per_second = c.pings_per_second;
  o.ping_burst = std::max(1.0, c.pings_per_second);
  o.hello_timeout = std::chrono::milliseconds(static_cast<std::int64_t>(std::ceil(c.hello_timeout_s * 1000)));
  o.idle_timeout = std::chrono::milliseconds(static_cast<std::int64_t>(std::ceil(c.idle_timeout_s * 1000)));
  o.max_pending = c.max_pending;
  o.max_pending_per_address = c.max_pending_per_address;
  o.connect_rate = c.connect_rate;
  o.connect_burst = c.connect_burst;
  o.connect_min_session = std::chrono::milliseconds(static_cast<std::int64_t>(std::ceil(c.connect_min_session_s * 1000)));
  o.connect_refusal_hold = std::chrono::milliseconds(static_cast<std::int64_t>(std::ceil(c.connect_refusal_hold_s * 1000)));
  o.max_name_bytes = c.max_name_bytes;
  return o;
}

}  // namespace

engine_fault zone_server::gpu_fault(const zone_config& cfg) const {
  engine_fault f;
  f.tick = [w = world_.get()] { return w->tick(); };
  f.at_tick = cfg.test_fault_tick;
  if (cfg.test_fault == "gpu-lost") f.raise = [] { gpu::raise_device_fault(); };
  return f;
}

zone_server::zone_server(const zone_config& cfg)
    : cfg_(cfg),
      pool_(std::make_unique<interest::thread_pool>(cfg.worker_threads, worker_spin(cfg),
                                                    [cpus = pin_cpus(cfg.worker_cpus)](unsigned worker) {
                                                      if (auto err = net::pin_current_thread(cpus))
                                                        spdlog::warn("worker {}: not pinned: {}", worker, *err);
                                                    })),
      parts_(make_interest_parts(cfg, pool_.get())),
      world_(std::make_unique<zone_world>(cfg, *parts_.finder, pool_.get())),
      replicator_(replication_options_of(cfg)),
      net_(net_options(cfg)) {
  world_->set_presence_grid(parts_.presence_grid);
  created_unix_s_ = std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
  std::random_device entropy;
  while (instance_ == 0) instance_ = (std::uint64_t{entropy()} << 32) | entropy();
  // The interest step on the GPU (the whole of it: candidates, classification, events), when
  // make_interest_parts made its engine.
  if (parts_.engine) {
    if (cfg.test_fault == "gpu-interest" || cfg.test_fault == "gpu-lost") {
      faulty_engine_ = std::make_unique<faulty_visibility_engine>(*parts_.engine, gpu_fault(cfg));
    }
    world_->set_visibility_engine(faulty_engine_ ? faulty_engine_.get() : parts_.engine.get());
  }
  // Replication's decisions on the GPU (the frames are the CPU replicator's, byte for byte).
  if (cfg.replicate == "gpu" || cfg.replicate == "auto") {
    std::string why;
    replication_engine_ = gpu::make_replication_engine(&why);
    if (replication_engine_) {
      if (cfg.test_fault == "gpu-replication" || (cfg.test_fault == "gpu-lost" && !faulty_engine_)) {
        faulty_replication_ = std::make_unique<faulty_replication_engine>(*replication_engine_, gpu_fault(cfg));
      }
      replicator_.set_engine(faulty_replication_ ? faulty_replication_.get() : replication_engine_.get());
      // With the interest step on the GPU too, replication reads the visible sets there in place;
      // unless --host-views (the default), the players' rows then stay on the device only.
      world_->set_player_views_on_host(cfg.host_views);
    } else if (cfg.replicate == "gpu") {
      replicate_error_ = "replicate 'gpu' cannot run here: " + why + " (use --replicate auto or cpu)";
    } else {
      replicate_note_ = why;
    }
  }
  // While the interest engine's device works, in a single zone (nothing moves the entities
  // between the step and replication there; a world's link may, after the step): the entities for
  // replication staged and copied up, then a due viewer snapshot's columns copied.
  if (parts_.engine) {
    interest_wait_work_ = [this] {
      if (ext_ != nullptr) return;
      if (replication_engine_) replicator_.prestage(world_->store(), world_->tick(), pool_.get());
      viewer_copy_columns();
    };
    world_->interest().set_while_device_works(&interest_wait_work_);
  }
}

std::string zone_server::replication_name() const {
  if (replicator_.on_engine()) return std::string(replication_engine_->name()) + " engine";
  return "cpu";
}

std::string zone_server::interest_name() const {
  if (parts_.engine && world_->tracker().engine_error().empty()) return std::string(parts_.engine->name()) + " engine";
  if (parts_.presence_grid) return "host (presence grid)";
  return "host (finder " + std::string(parts_.finder->name()) + ")";
}

zone_server::~zone_server() {
  viewer_copier_.reset();  // a copy in flight reads the store
  net_.stop();
  if (metrics_) metrics_->stop();
  if (tick_csv_) std::fclose(tick_csv_);
}

std::array<double, 3> zone_server::cpu_by_thread_group(const net::process_usage& u) const {
  std::array<double, 3> cpu{0, 0, 0};  // tick, io, other
  const int tick_tid = tick_thread_id_.load(std::memory_order_relaxed);
  for (const auto& th : u.threads) {
    const bool tick = th.tid == tick_tid || th.name.starts_with("zone-worker-");
    cpu[tick ? 0 : th.name.starts_with("zone-io-") ? 1 : 2] += th.cpu_seconds;
  }
  return cpu;
}

std::string zone_server::metrics_text() const {
  net::prometheus_text t;
  const auto ns = net_.stats();
  const auto& ts = world_->tracker().stats();
  // The process, as Prometheus' client libraries name it, and its CPU by thread group: the
  // tick's (the thread that runs the ticks and the pool's workers), the I/O threads' and the rest
  // (viewer, metrics, the GPU driver's, NATS'); rate(process_cpu_seconds_total) over
  // rate(zone_net_frames_out_total) is the server's CPU per frame (docs/zone-benchmarks.md).
  const net::process_usage pu = net::read_process_usage(true);
  t.counter("process_cpu_seconds_total", "User and system CPU time of every thread of the process, in seconds.",
            pu.cpu_seconds);
  t.gauge("process_resident_memory_bytes", "Resident memory in bytes.", static_cast<double>(pu.resident_bytes));
  t.gauge("process_open_fds", "Open file descriptors (every socket is one).", static_cast<double>(pu.open_fds));
  t.gauge("process_max_fds", "The open-file limit (soft).", static_cast<double>(pu.max_fds));
  t.gauge("process_start_time_seconds", "When the zone server was made, in seconds since the Unix epoch.",
          created_unix_s_);
  const auto group_cpu = cpu_by_thread_group(pu);
  const char* groups[3] = {"tick", "io", "other"};
  for (int g = 0; g < 3; ++g) {
    t.counter("zone_thread_cpu_seconds_total",
              "CPU time of the live threads by group: tick (the thread running the ticks and the pool's workers), "
              "io (the network's I/O threads), other.",
              group_cpu[g], std::string("threads=\"") + groups[g] + "\"");
  }
  t.counter("zone_ticks_total", "Ticks run.", static_cast<double>(stats_.ticks));
  t.counter("zone_tick_overruns_total", "Ticks that ended after the next was due.", static_cast<double>(stats_.overruns));
  t.counter("zone_ticks_skipped_total", "Ticks skipped to catch up after overruns.", static_cast<double>(stats_.skipped_ticks));
  t.gauge("zone_entities", "Live entities.", static_cast<double>(world_->store().size()));
  t.gauge("zone_clients", "Clients with an entity.", static_cast<double>(stats_.clients));
  t.gauge("zone_interest_pairs", "Pairs found by the last interest step.", static_cast<double>(ts.pairs));
  t.gauge("zone_visible_total", "Sum of visible-set sizes after the last tick.", static_cast<double>(ts.visible));
  t.gauge("zone_interest_on_gpu", "1 while the interest step runs on the GPU engine (--interest), else 0.",
          parts_.engine && world_->tracker().engine_error().empty() ? 1.0 : 0.0);
  t.counter("zone_interest_gpu_fallbacks_total",
            "Times the GPU interest engine failed and the interest step fell back to the host (for good).",
            engine_failure_logged_ ? 1.0 : 0.0);
  t.counter("zone_replication_gpu_fallbacks_total",
            "Times the GPU replication engine failed and replication fell back to the CPU (for good).",
            replication_failure_logged_ ? 1.0 : 0.0);
  t.gauge("zone_replication_on_gpu", "1 while replication's decisions run on the GPU engine (--replicate), else 0.",
          replicator_.on_engine() ? 1.0 : 0.0);
  t.counter("zone_replication_frames_total", "Tick updates handed to the network.", static_cast<double>(stats_.frames_sent));
  t.counter("zone_replication_bytes_total", "Bytes of tick updates handed to the network.", static_cast<double>(stats_.bytes_sent));
  t.counter("zone_joins_total", "Players welcomed (new, resumed or taken over).", static_cast<double>(stats_.joins));
  t.counter("zone_leaves_total", "Players whose session ended.", static_cast<double>(stats_.leaves));
  t.counter("zone_logouts_total", "Of the leaves: the client said leave (its entity removed at once).",
            static_cast<double>(stats_.logouts));
  t.counter("zone_players_lingered_total",
            "Players kept after a lost connection for their client's resume token (--linger).",
            static_cast<double>(stats_.players_lingered));
  t.counter("zone_players_resumed_total", "Kept players whose client came back with its token.",
            static_cast<double>(stats_.players_resumed));
  t.counter("zone_linger_expired_total", "Kept players removed: their client did not come back in time.",
            static_cast<double>(stats_.linger_expired));
  t.counter("zone_takeovers_total",
            "Players taken over by a hello with their token while their old connection was open.",
            static_cast<double>(stats_.takeovers));
  t.counter("zone_resumes_refused_total", "Hellos whose token this single zone did not know (auth_failed).",
            static_cast<double>(stats_.resumes_refused));
  t.gauge("zone_players_lingering", "Players kept now, waiting for their client's resume token.",
          resume_ ? static_cast<double>(resume_->kept()) : 0.0);
  t.counter("zone_teleports_total", "Teleport requests applied.", static_cast<double>(stats_.teleports));
  t.counter("zone_teleports_clamped_total", "Applied teleports clamped into the world.", static_cast<double>(stats_.teleports_clamped));
  t.counter("zone_teleports_refused_total", "Teleport requests refused (off, cooldown, another's entity, not finite).",
            static_cast<double>(stats_.teleports_refused));
  t.counter("zone_visibility_switches_total", "Visibility switches (set_visibility) applied.", static_cast<double>(stats_.visibility_switches));
  t.counter("zone_visibility_refused_total", "Visibility switches refused (a value the zone does not allow, cooldown).",
            static_cast<double>(stats_.visibility_refused));
  t.counter("zone_visibility_resyncs_total", "Clients resynced because an entity they may hold changed class.",
            static_cast<double>(stats_.visibility_resyncs));
  t.counter("zone_visibility_notes_total",
            "Class notes sent (instead of resyncs) because an entity the client may hold changed class.",
            static_cast<double>(stats_.class_notes));
  t.counter("zone_viewer_column_copies_total",
            "Viewer snapshots whose ids, classes and kinds were copied whole (entities created or destroyed).",
            static_cast<double>(stats_.viewer_columns_copied_all));
  t.counter("zone_viewer_class_patches_total", "Viewer snapshots that patched only the classes set_visibility changed.",
            static_cast<double>(stats_.viewer_columns_classes_patched));
  t.counter("zone_viewer_copies_after_tick_total",
            "Viewer snapshots whose columns were copied after their tick (--viewer-fill after).",
            static_cast<double>(stats_.viewer_columns_after_tick));
  t.counter("zone_viewer_copy_seconds_total",
            "Time the copier's thread spent copying those columns (--viewer-fill after).",
            stats_.viewer_copy_ms / 1000.0);
  t.counter("zone_viewer_copy_wait_seconds_total",
            "Time ticks spent waiting for the copier at their start (--viewer-fill after; part of those ticks).",
            stats_.viewer_copy_wait_ms / 1000.0);
  t.counter("zone_net_connections_accepted_total", "Connections accepted.", static_cast<double>(ns.connections_accepted));
  t.counter("zone_net_connections_refused_total", "Connections refused (limit).", static_cast<double>(ns.connections_refused));
  t.gauge("zone_net_sessions_open", "Open sessions.", static_cast<double>(ns.sessions_open));
  t.counter("zone_net_frames_in_total", "Frames received.", static_cast<double>(ns.frames_in));
  t.counter("zone_net_frames_out_total", "Frames written.", static_cast<double>(ns.frames_out));
  t.counter("zone_net_writes_total", "Socket writes (gathered: one may carry several frames).", static_cast<double>(ns.writes));
  t.counter("zone_net_write_batches_total", "io_uring submissions of the I/O threads (each carries several sessions' writes).",
            static_cast<double>(ns.write_batches));
  t.counter("zone_net_registered_sends_total",
            "io_uring sends naming the socket's registered file (no descriptor lookup in the kernel).",
            static_cast<double>(ns.registered_sends));
  t.gauge("zone_net_io_uring", "1 when the I/O threads write through io_uring (--write-batching), else 0.",
          net_.uses_io_uring() ? 1.0 : 0.0);
  t.counter("zone_net_bytes_in_total", "Bytes received.", static_cast<double>(ns.bytes_in));
  t.counter("zone_net_bytes_out_total", "Bytes written.", static_cast<double>(ns.bytes_out));
  t.counter("zone_frames_held_total", "Client-ticks without a frame because the client had not read its backlog yet.",
            static_cast<double>(stats_.frames_held));
  t.counter("zone_client_stalls_total", "Stalled clients (backlog full for client-stall seconds): queued state dropped, a reset once drained.",
            static_cast<double>(stats_.client_stalls));
  t.counter("zone_net_frames_dropped_total", "State frames not delivered to slow clients (dropped or superseded by a reset).",
            static_cast<double>(ns.frames_dropped));
  t.counter("zone_net_resyncs_requested_total", "Drop episodes: a slow client's view resynchronised with a reset.",
            static_cast<double>(ns.resyncs_requested));
  t.counter("zone_net_frames_rejected_total", "Inbound frames rejected (client disconnected).", static_cast<double>(ns.frames_rejected));
  t.counter("zone_net_inputs_dropped_total", "Inputs over the rate limit.", static_cast<double>(ns.inputs_dropped));
  t.counter("zone_net_pings_answered_total", "Pings answered with a pong.", static_cast<double>(ns.pings_answered));
  t.counter("zone_net_pings_dropped_total", "Pings over the rate limit, or from a client that does not read its pongs (no pong).", static_cast<double>(ns.pings_dropped));
  t.counter("zone_net_rate_limited_total", "Sessions closed for flooding (error rate_limited).", static_cast<double>(ns.rate_limited));
  t.gauge("zone_net_pending_open", "Connections open that have not said hello yet.", static_cast<double>(ns.pending_open));
  t.counter("zone_net_pending_evicted_total", "Connections without a hello closed to admit a newer one (cap: max-pending-per-address or max-pending).",
            static_cast<double>(ns.pending_evicted_address), "cap=\"address\"");
  t.counter("zone_net_pending_evicted_total", "Connections without a hello closed to admit a newer one (cap: max-pending-per-address or max-pending).",
            static_cast<double>(ns.pending_evicted), "cap=\"total\"");
  t.counter("zone_net_hello_timeouts_total", "Connections closed at the hello deadline.", static_cast<double>(ns.hello_timeouts));
  t.counter("zone_net_connections_rate_limited_total",
            "Connections refused at accept (error rate_limited, no session): their address's reconnect churn was over connect-rate.",
            static_cast<double>(ns.connections_rate_limited));
  t.counter("zone_net_connections_short_total",
            "Connections that ended within connect-min-session of their accept (each took a token of its address's connect-rate).",
            static_cast<double>(ns.connections_charged));
  t.counter("zone_net_pending_spared_total",
            "At a pending cap, connections not evicted because their first bytes (a hello) waited unread in the socket.",
            static_cast<double>(ns.pending_spared));
  t.counter("zone_net_hellos_rejected_total", "Hellos refused (bad name).", static_cast<double>(ns.hellos_rejected));
  t.counter("zone_net_idle_timeouts_total", "Sessions closed at the idle timeout.", static_cast<double>(ns.idle_timeouts));
  // The configured limits, so a dashboard reads them beside what they bound.
  const auto limit = [&](const char* name, double v) {
    t.gauge("zone_limit", "Configured limits (docs/operating.md, Limits and hardening).", v, std::string("limit=\"") + name + "\"");
  };
  limit("max_clients", static_cast<double>(cfg_.max_clients));
  limit("linger_seconds", cfg_.linger_s);
  limit("max_pending", static_cast<double>(cfg_.max_pending));
  limit("max_pending_per_address", static_cast<double>(cfg_.max_pending_per_address));
  limit("hello_timeout_seconds", cfg_.hello_timeout_s);
  limit("connect_rate", cfg_.connect_rate);
  limit("connect_burst", cfg_.connect_burst);
  limit("connect_min_session_seconds", cfg_.connect_min_session_s);
  limit("connect_refusal_hold_seconds", cfg_.connect_refusal_hold_s);
  limit("idle_timeout_seconds", cfg_.idle_timeout_s);
  limit("inputs_per_second", cfg_.inputs_per_second);
  limit("pings_per_second", cfg_.pings_per_second);
  limit("max_name_bytes", static_cast<double>(cfg_.max_name_bytes));
  limit("max_frame_bytes", static_cast<double>(cfg_.max_frame_bytes));
  limit("metrics_max_connections", static_cast<double>(cfg_.metrics_max_connections));
  if (metrics_) {
    t.counter("zone_metrics_connections_refused_total", "/metrics connections closed at accept (over metrics-max-connections).",
              static_cast<double>(metrics_->connections_refused()));
    t.counter("zone_metrics_accept_errors_total", "/metrics accepts that failed (each followed by a 50 ms pause).",
              static_cast<double>(metrics_->accept_errors()));
  }
  // Histograms in seconds, one bucket per octave up to ~100 s (the rest in +Inf), from one
  // snapshot of the buckets whose total is the count: one that other threads record into while
  // this reads (the frames' write ages) stays consistent. `per_s`: the units recorded per second.
  const auto histogram = [&]<class H>(const char* metric, const char* help, const std::string& labels, const H& h,
                                      double per_s) {
    const typename H::counts c = h.snapshot();
    std::vector<double> bounds;
    std::vector<std::uint64_t> cumulative;
    std::uint64_t seen = 0;
    for (int b = 0; b < H::buckets && (bounds.empty() || bounds.back() < 100.0); ++b) {
      seen += c[static_cast<std::size_t>(b)];
      if (b % H::per_octave == H::per_octave - 1) {
        bounds.push_back(H::bucket_upper(b) / per_s);
        cumulative.push_back(seen);
      }
    }
    t.histogram(metric, help, bounds, cumulative, h.sum() / per_s, H::total(c), labels);
  };
  const auto phase = [&](const char* name, const latency_histogram& h) {
    histogram("zone_tick_phase_seconds", "Wall time of the tick and its phases.", std::string("phase=\"") + name + "\"",
              h, 1000.0);
  };
  const auto join = [&](const char* part, const latency_histogram& h) {
    histogram("zone_join_seconds",
              "A player's join: its connection accepted to its hello read, and that to its welcome queued.",
              std::string("part=\"") + part + "\"", h, 1000.0);
  };
  histogram("zone_frame_write_seconds",
            "A tick update's age when the kernel took its last byte: from its tick's server_time (replication's start) "
            "to its write, the server's share of a client's update latency.",
            "", net_.frame_write_age(), 1e6);  // microseconds
  join("accept_to_hello", stats_.join_hello_ms);
  join("hello_to_welcome", stats_.join_welcome_ms);
  phase("tick", stats_.tick_ms);
  phase("inputs", stats_.inputs_ms);
  phase("behaviours", world_->phases().behaviours);
  phase("integrate", world_->phases().integrate);
  phase("interest", world_->phases().interest);
  phase("replicate", stats_.replicate_ms);
  return t.str();
}

net::interest_rules zone_server::rules() const {
  net::interest_rules r;
  r.player_aoi = {cfg_.player_aoi, cfg_.player_aoi, cfg_.player_aoi};
  r.hysteresis = cfg_.hysteresis;
  r.max_visible = cfg_.max_visible;
  const player_visibility player = visibility_for(false, 0);  // a player that chose nothing (the welcome says the client's own)
  r.player_class = player.visibility_class;
  r.player_sees = player.sees;
  r.npc_aoi_tiers.assign(std::begin(cfg_.aoi_tier), std::end(cfg_.aoi_tier));
  const auto& w = cfg_.world;
  r.quantization_step = {(w.hi.x - w.lo.x) / 65535.0f, (w.hi.y - w.lo.y) / 65535.0f, (w.hi.z - w.lo.z) / 65535.0f};
  r.update_near = cfg_.update_near;
  r.update_mid = cfg_.update_mid;
  r.update_mid_period = std::max<std::uint32_t>(1, cfg_.update_mid_period);
  r.update_far_period = std::max<std::uint32_t>(1, cfg_.update_far_period);
  r.byte_budget = static_cast<std::uint32_t>(cfg_.client_byte_budget);
  r.send_every = cfg_.client_send_every;
  r.digest_every = cfg_.digest_every;
  r.max_speed = std::max(cfg_.player_speed, 1.5f * cfg_.npc_speed);  // chasers run at 1.5 x npc-speed
  r.allow_stealth = cfg_.allow_stealth;
  r.teams = static_cast<std::uint8_t>(cfg_.player_teams);
  r.visibility_cooldown = static_cast<float>(cfg_.visibility_cooldown_s);
  return r;
}

std::optional<std::string> zone_server::start() {
  if (auto err = validate(cfg_)) return err;
  if (!parts_.finder_error.empty()) return parts_.finder_error;
  if (!parts_.engine_error.empty()) return parts_.engine_error;
  if (!replicate_error_.empty()) return replicate_error_;
  if (!cfg_.tick_csv.empty()) {
    tick_csv_ = std::fopen(cfg_.tick_csv.c_str(), "w");
    if (!tick_csv_) return "cannot write tick-csv file '" + cfg_.tick_csv + "': " + std::strerror(errno);
    std::fputs(
        "tick,t_s,clients,frames,bytes,inputs_ms,behaviours_ms,integrate_ms,interest_ms,replicate_ms,tick_ms,"
        "viewer_ms,viewer_fill_ms,interest_wait_ms,select_ms,replicate_engine_ms,replicate_alloc_ms,replicate_kept\n",
        tick_csv_);
  }
  if (cfg_.test_fault.rfind("gpu-", 0) == 0) {
    if (!faulty_engine_ && !faulty_replication_) {
      return "test-fault " + cfg_.test_fault + " needs the GPU " +
             (cfg_.test_fault == "gpu-replication" ? std::string("replication engine (--replicate auto or gpu)")
                                                   : std::string("interest engine (--interest auto or gpu)")) +
             ", which does not run here";
    }
    spdlog::warn("zone: TESTING: the GPU {} fails at tick {} ({})",
                 faulty_engine_ ? "interest engine" : "replication engine", cfg_.test_fault_tick,
                 cfg_.test_fault == "gpu-lost" ? "a real device fault: a kernel traps" : "an injected CUDA error");
  }
  if (cfg_.oracle) {
    truth_ = std::make_unique<truth_publisher>();
    if (auto err = truth_->start(cfg_.oracle_port, cfg_.oracle_subscribers)) return err;
    spdlog::info("zone: oracle stream on 127.0.0.1:{} (ground truth of every tick, for bot-swarm --oracle)", truth_->port());
    if (const auto k = fault_injector::parse(cfg_.test_fault)) {
      fault_ = std::make_unique<fault_injector>(*k, cfg_.test_fault_tick, cfg_.world, cfg_.player_aoi + cfg_.hysteresis);
      spdlog::warn("zone: TESTING: fault '{}' injected into one client's frames from tick {}", cfg_.test_fault,
                   cfg_.test_fault_tick);
    }
  }
  if (cfg_.populate) world_->populate();
  spdlog::info("zone: {} NPCs, world {}x{}x{} m, {} Hz, {} worker threads{}, interest on {}, replication on {}",
               world_->store().size(), cfg_.world.hi.x, cfg_.world.hi.y, cfg_.world.hi.z, cfg_.tick_rate_hz,
               pool_->size(), cfg_.worker_cpus.empty() ? std::string() : " on CPUs " + cfg_.worker_cpus,
               interest_name(), replication_name());
  if (!parts_.engine_note.empty()) spdlog::info("zone: interest runs on the host: {}", parts_.engine_note);
  if (!replicate_note_.empty()) spdlog::info("zone: replication runs on the CPU: {}", replicate_note_);
  if (ext_ == nullptr && cfg_.linger_s > 0) {
    resume_ = std::make_unique<resume_book>(static_cast<std::uint64_t>(std::ceil(cfg_.linger_s * cfg_.tick_rate_hz)),
                                            cfg_.max_clients);
    spdlog::info("zone: a player whose connection is lost waits {} s for its client's resume token (--linger)",
                 cfg_.linger_s);
  }
  if (auto err = net_.start()) return err;
  if (ext_ != nullptr) ext_->started(net_.port());
  if (cfg_.metrics_enabled) {
    net::metrics_limits limits;
    limits.max_connections = cfg_.metrics_max_connections;
    metrics_ = std::make_unique<net::metrics_server>(cfg_.metrics_address, cfg_.metrics_port, limits);
    if (cfg_.viewer_enabled) {
      net::viewer_options vo;
      vo.max_viewers = cfg_.max_viewers;
      vo.allow_remote = cfg_.viewer_remote;
      vo.nice = cfg_.viewer_nice;
      vo.idle = cfg_.viewer_idle;
      viewer_ = std::make_unique<net::viewer_server>(vo);
      metrics_->attach_viewer(viewer_.get());
      if (cfg_.viewer_fill == "after") viewer_copier_ = std::make_unique<viewer_copier>();
    }
    if (auto err = metrics_->start()) return err;
    metrics_->publish(metrics_text());
    if (viewer_) {
      const auto pr = viewer_->thread_info();
      spdlog::info("viewer on http://{}:{}/viewer ({}; its thread at nice {}{})", cfg_.metrics_address, metrics_->port(),
                   cfg_.viewer_remote ? "any peer" : "loopback peers only", pr.nice,
                   pr.idle ? ", SCHED_IDLE" : pr.idle_refused ? ", SCHED_IDLE refused" : "");
    }
  }
  return std::nullopt;
}

void zone_server::drain_inputs() {
  events_.clear();
  net_.poll(events_);
  for (auto& e : events_) {
    switch (e.type) {
      case net::inbound_event::kind::connected:
        break;  // nothing until hello
      case net::inbound_event::kind::message: {
        if (!e.msg) break;
        if (const auto* hello = std::get_if<net::hello_msg>(&*e.msg)) {
          if (hello->protocol_version != net::protocol_version) {
            net_.disconnect(e.session, net::error_code::protocol_version,
                            "server speaks protocol " + std::to_string(net::protocol_version));
            break;
          }
          if (ext_ != nullptr && !hello->token.empty()) {
            // A client redirected here by another zone of the world.
            pending_hellos_.push_back({e.session, hello->token,
                                       world_->tick() + static_cast<std::uint64_t>(5 * cfg_.tick_rate_hz),
                                       {hello->name, hello->class_changes, e.accepted_us, e.hello_us}});
            break;
          }
          if (resume_ && !hello->token.empty()) {
            resume(e, *hello);
            break;
          }
          if (auto why = check_visibility_choice(hello->stealth, hello->team)) {
            net_.disconnect(e.session, net::error_code::bad_hello, *why);
            break;
          }
          const entity_id id = world_->spawn_player(world_->player_spawn_point(e.session), hello->stealth, hello->team);
          if (id == null_entity) {
            net_.disconnect(e.session, net::error_code::server_full, "the zone is full");
            break;
          }
          welcome(e.session, id, {hello->name, hello->class_changes, e.accepted_us, e.hello_us});
        } else if (const auto* in = std::get_if<net::input_msg>(&*e.msg)) {
          const auto it = clients_.find(e.session);
          if (it == clients_.end()) break;
          // A client steers only its own entity; the world clamps the speed.
          const vec3 intent{in->move.x, in->move.y, in->move.z};
          if (ext_ != nullptr && !ext_->owns(it->second.entity)) {
            // Handed off (its redirect may still be on the way): the input goes after the entity.
            ext_->forward_input(it->second.entity, intent, in->sequence);
          } else {
            world_->set_intent(it->second.entity, intent);
          }
          note_sequence(it->second, in->sequence);
        } else if (const auto* tp = std::get_if<net::teleport_msg>(&*e.msg)) {
          const auto it = clients_.find(e.session);
          if (it != clients_.end()) teleport(e.session, it->second, *tp);
        } else if (const auto* sv = std::get_if<net::set_visibility_msg>(&*e.msg)) {
          const auto it = clients_.find(e.session);
          if (it != clients_.end()) set_visibility(e.session, it->second, *sv);
        }
        break;
      }
      case net::inbound_event::kind::frames_dropped: {
        // The session delivers no state frame until a reset: make this client's next frame one.
        const auto it = clients_.find(e.session);
        if (it != clients_.end()) replicator_.resync(it->second.replica);
        break;
      }
      case net::inbound_event::kind::disconnected: {
        std::erase_if(pending_hellos_, [&](const pending_hello& p) { return p.session == e.session; });
        const auto it = clients_.find(e.session);
        if (it == clients_.end()) break;
        spdlog::debug("session {}: left ({})", e.session, net::escape_for_log(e.reason, 200));
        const entity_id entity = it->second.entity;
        drop_client(it);
        ++stats_.leaves;
        if (e.left) ++stats_.logouts;
        // Kept for a resume only when the connection was lost: not after a leave, nor when the
        // server cut the client off for breaking the rules.
        const bool lost = !e.left && !e.cut_off;
        if (ext_ != nullptr) {
          // An entity handed off to another zone lives on there (here it is a ghost).
          if (ext_->owns(entity) && (!lost || !ext_->keep_for_resume(entity, *world_))) world_->despawn(entity);
        } else if (resume_ && lost && resume_->keep(entity, world_->tick())) {
          world_->set_intent(entity, {0, 0, 0});  // it stands where it was until its client is back
          ++stats_.players_lingered;
        } else {
          if (resume_) resume_->forget(entity);
          world_->despawn(entity);
        }
        break;
      }
    }
  }
  stats_.clients = clients_.size();
}

void zone_server::welcome(net::session_id session, entity_id id, const hello_info& hello, const std::string& token) {
  const auto [at, added] = clients_.try_emplace(session);
  client& c = at->second;
  if (added) {
    c.row = rows_.size();
    rows_.push_back({session, &c, nullptr});
  }
  c.entity = id;
  c.backlog = net_.state_backlog(session);
  rows_[c.row].backlog = c.backlog.get();
  c.written = net_.bytes_written(session);
  c.replica = replicator_.add_client(id);
  replicator_.set_class_notes(c.replica, hello.class_changes);
  if (hello.hello_us != 0) {
    const std::uint64_t now = net_.now_us();
    stats_.join_hello_ms.record(static_cast<double>(hello.hello_us - std::min(hello.hello_us, hello.accepted_us)) / 1000.0);
    stats_.join_welcome_ms.record(static_cast<double>(now - std::min(now, hello.hello_us)) / 1000.0);
  }
  session_of_entity_[id] = session;
  net::welcome_msg w;
  w.entity_id = id;
  w.world = cfg_.world;
  w.tick_rate_hz = static_cast<std::uint16_t>(cfg_.tick_rate_hz);
  w.server_tick = world_->tick();
  if (const auto at = world_->store().get(id)) w.spawn_position = net::vec3f{at->position.x, at->position.y, at->position.z};
  w.host_clock = true;  // net::server::now_us() is CLOCK_MONOTONIC
  w.rules = rules();
  if (const auto d = world_->store().get(id)) w.rules->player_class = d->visibility_class, w.rules->player_sees = d->sees;
  w.oracle_port = oracle_port();
  w.instance = instance_;
  if (ext_ != nullptr) {
    w.resume_token = ext_->resume_token(id, token);
  } else if (resume_) {
    w.resume_token = resume_->issue(id);
  }
  net_.send(session, net::make_shared_frame(encoder_.encode(w)), net::delivery::control);
  // The name is client data: escaped (the server also checked it at hello), at debug.
  spdlog::debug("session {}: '{}' joined as entity {}", session, net::escape_for_log(hello.name), id);
  ++stats_.joins;
}

void zone_server::drop_client(std::unordered_map<net::session_id, client>::iterator it) {
  const auto se = session_of_entity_.find(it->second.entity);
  if (se != session_of_entity_.end() && se->second == it->first) session_of_entity_.erase(se);
  replicator_.remove_client(it->second.replica);
  // Its row takes the last one's.
  const std::size_t row = it->second.row;
  rows_[row] = rows_.back();
  rows_[row].c->row = row;
  rows_.pop_back();
  clients_.erase(it);
}

void zone_server::resume(const net::inbound_event& e, const net::hello_msg& hello) {
  const auto c = resume_->take(hello.token);
  if (c.entity == null_entity || !world_->store().get(c.entity)) {
    if (c.entity != null_entity) resume_->forget(c.entity);
    ++stats_.resumes_refused;
    net_.disconnect(e.session, net::error_code::auth_failed, "unknown or expired token");
    return;
  }
  if (c.live) {
    // Its old connection is still open here (its loss not seen yet, or a second client with the
    // token): the new one takes the player over, the old one is closed.
    const auto se = session_of_entity_.find(c.entity);
    if (se != session_of_entity_.end() && se->second != e.session) {
      const net::session_id old = se->second;
      const auto it = clients_.find(old);
      if (it != clients_.end()) {
        drop_client(it);
        ++stats_.leaves;
      }
      net_.disconnect(old, net::error_code::taken_over, "the player was taken over by a new connection with its token");
    }
    ++stats_.takeovers;
  } else {
    ++stats_.players_resumed;
  }
  // The hello's visibility choices are not applied: the player comes back as it was.
  welcome(e.session, c.entity, {hello.name, hello.class_changes, e.accepted_us, e.hello_us}, hello.token);
}

void zone_server::retry_pending_hellos() {
  if (ext_ == nullptr) return;
  for (std::size_t k = 0; k < pending_hellos_.size();) {
    const pending_hello p = pending_hellos_[k];
    entity_id id = null_entity;
    const auto verdict = ext_->claim_token(p.token, *world_, id);
    if (verdict == zone_extension::claim::wait && world_->tick() < p.deadline_tick) {
      ++k;
      continue;
    }
    pending_hellos_.erase(pending_hellos_.begin() + static_cast<std::ptrdiff_t>(k));
    if (verdict == zone_extension::claim::ready) {
      welcome(p.session, id, p.hello, p.token);
    } else {
      net_.disconnect(p.session, net::error_code::auth_failed, "unknown or expired token");
    }
  }
}

void zone_server::teleport(net::session_id session, client& c, const net::teleport_msg& t) {
  note_sequence(c, t.sequence);
  const auto refuse = [&](const char* why) {
    ++stats_.teleports_refused;
    spdlog::debug("session {}: teleport refused: {}", session, why);
  };
  if (!cfg_.teleport_enabled) return refuse("teleports are off");
  // A client moves only its own entity: 0 names it, any other id (another player, an NPC) is refused.
  if (t.entity_id != 0 && t.entity_id != c.entity) return refuse("not the client's entity");
  // The cooldown in ticks (world time, not wall time: the same on a loaded server).
  const auto cooldown = static_cast<std::uint64_t>(std::ceil(cfg_.teleport_cooldown_s * cfg_.tick_rate_hz));
  if (c.teleported && world_->tick() < c.last_teleport_tick + cooldown) return refuse("cooldown");
  bool clamped = false;
  if (!world_->teleport(c.entity, {t.position.x, t.position.y, t.position.z}, &clamped)) return refuse("not a finite position");
  c.teleported = true;
  c.last_teleport_tick = world_->tick();
  ++stats_.teleports;
  if (clamped) ++stats_.teleports_clamped;
}

std::optional<std::string> zone_server::check_visibility_choice(bool stealth, std::uint8_t team) const {
  if (stealth && !cfg_.allow_stealth) return std::string("stealth is not allowed in this zone");
  if (team > cfg_.player_teams) {
    return "team " + std::to_string(team) + " is not allowed in this zone (teams 1 .. " + std::to_string(cfg_.player_teams) +
           ", 0 = none)";
  }
  return std::nullopt;
}

void zone_server::set_visibility(net::session_id session, client& c, const net::set_visibility_msg& v) {
  note_sequence(c, v.sequence);
  const auto refuse = [&](const std::string& why) {
    ++stats_.visibility_refused;
    spdlog::debug("session {}: set_visibility refused: {}", session, why);
  };
  if (auto why = check_visibility_choice(v.stealth, v.team)) return refuse(*why);
  if (ext_ != nullptr && !ext_->owns(c.entity)) return refuse("the entity was handed off");
  const auto cooldown = static_cast<std::uint64_t>(std::ceil(cfg_.visibility_cooldown_s * cfg_.tick_rate_hz));
  if (c.switched && world_->tick() < c.last_visibility_tick + cooldown) return refuse("cooldown");
  const std::size_t d = world_->store().index_of(c.entity);
  if (d == entity_store::npos) return refuse("no entity");
  const std::uint32_t old_class = world_->store().visibility_classes()[d], old_sees = world_->store().sees()[d];
  const player_visibility pv = visibility_for(v.stealth, v.team);
  if (!world_->store().set_visibility(c.entity, pv.visibility_class, pv.sees)) return refuse("invalid");
  if (pv.visibility_class != old_class || pv.sees != old_sees) class_changes_.push_back({c.entity, old_class, old_sees});
  c.switched = true;
  c.last_visibility_tick = world_->tick();
  ++stats_.visibility_switches;
}

void zone_server::replicate_class_changes() {
  if (class_changes_.empty() && !replicator_.class_changes_pending()) return;
  stats_.visibility_resyncs += replicator_.resync_viewers_of(world_->store(), world_->tracker(), world_->tick(),
                                                             class_changes_, pool_.get(), &class_notes_);
  class_changes_.clear();
  // One message per noted client (the notes come by client), queued before this tick's frame: as
  // state, so that a client whose state frames are dropped gets a reset (current classes) instead.
  net::class_changes_msg msg;
  msg.server_tick = world_->tick();
  for (std::size_t k = 0; k < class_notes_.size();) {
    const client_id who = class_notes_[k].client;
    msg.notes.clear();
    for (; k < class_notes_.size() && class_notes_[k].client == who; ++k) {
      msg.notes.push_back({class_notes_[k].entity, class_notes_[k].visibility_class});
    }
    // The client's session through its entity (the replicator's observer is the client's entity).
    const auto se = session_of_entity_.find(replicator_.observer(who));
    if (se == session_of_entity_.end()) continue;
    const auto it = clients_.find(se->second);
    if (it == clients_.end() || it->second.replica != who || it->second.redirected) continue;
    net_.send(se->second, net::make_shared_frame(encoder_.encode(msg)), net::delivery::state);
    stats_.class_notes += msg.notes.size();
  }
}

void zone_server::note_sequence(client& c, std::uint32_t sequence) {
  if (!c.any_input || static_cast<std::int32_t>(sequence - c.last_input) > 0) c.last_input = sequence;
  c.any_input = true;
}

void zone_server::choose_fault_victim() {
  if (fault_has_victim_ && clients_.count(fault_session_) != 0) return;
  fault_has_victim_ = false;
  for (const auto& [session, c] : clients_) {
    if (!fault_has_victim_ || session < fault_session_) fault_session_ = session, fault_has_victim_ = true;
  }
  if (fault_has_victim_) {
    fault_->set_victim(clients_[fault_session_].entity);
    spdlog::warn("zone: TESTING: fault acts on session {} (entity {})", fault_session_, fault_->victim());
  }
}

namespace {
/// Each replication worker's frames: carved out of its own blocks (net::frame_arena).
net::frame_arena& replication_arena() {
  thread_local net::frame_arena arena;
  return arena;
}
}  // namespace

void zone_server::replicate() {
  const std::uint64_t now = net_.now_us();
  if (fault_ && world_->tick() >= fault_->from_tick()) choose_fault_victim();
  // Every client's frame is built on the worker pool (replicator::build_many: fixed chunks of
  // clients, one writer each; the frames are those of building them one by one) and handed to
  // the network by the worker that built it (net::server::send: into the session's mailbox, one
  // wake-up per I/O thread for a burst). Each session gets one frame per tick, so its frames stay
  // in tick order.
  const auto select_start = clock_type::now();
  requests_.clear();
  request_sessions_.clear();
  const std::uint64_t every = cfg_.client_send_every, phase = world_->tick() % every;
  const std::uint64_t tick = world_->tick();
  const auto stall_ticks = static_cast<std::uint64_t>(std::ceil(cfg_.client_stall_s * cfg_.tick_rate_hz));
  // On the tick's own thread, one client after another (timed: --tick-csv's select_ms), down the
  // dense rows: the clients and their backlog counters (written by the I/O threads) fetched some
  // rows ahead, not one map node after another.
  const std::size_t n_rows = rows_.size();
  constexpr std::size_t ahead = 16;
  for (std::size_t r = 0; r < n_rows; ++r) {
    if (r + ahead < n_rows) {
      __builtin_prefetch(rows_[r + ahead].c);
      if (rows_[r + ahead].backlog != nullptr) __builtin_prefetch(rows_[r + ahead].backlog);
    }
    const net::session_id session = rows_[r].session;
    client& c = *rows_[r].c;
    if (c.redirected) continue;  // its entity is served by another zone now
    // Not this client's tick (client_send_every > 1): its next frame carries this tick's changes.
    if (every > 1 && session % every != phase) continue;
    if (cfg_.client_max_backlog != 0 && rows_[r].backlog != nullptr) {
      const std::uint32_t backlog = rows_[r].backlog->load(std::memory_order_relaxed);
      if (c.stalled) {
        // Stalled: nothing until its socket has taken every frame, then the current state.
        if (backlog != 0) {
          ++stats_.frames_held;
          continue;
        }
        c.stalled = c.holding = false;
      } else if (backlog >= cfg_.client_max_backlog) {
        // Paced to what the client absorbs: no new frame while its backlog is full (the next one
        // carries everything since: the replicator moves the view from what was last built).
        ++stats_.frames_held;
        // Stalled: held this long with not one byte taken by its socket (a slow reader moves it on).
        const std::uint64_t written = c.written ? c.written->load(std::memory_order_relaxed) : 0;
        if (!c.holding || written != c.held_written) c.holding = true, c.held_since = tick, c.held_written = written;
        if (stall_ticks > 0 && tick - c.held_since >= stall_ticks) {
          // Full for client_stall_s and nothing written: the client is not reading. The frames queued for it would be
          // stale when it reads again: dropped, and its next frame (once it drained) a reset.
          (void)net_.drop_stale_state(session);
          replicator_.resync(c.replica);
          c.stalled = true;
          ++stats_.client_stalls;
        }
        continue;
      } else {
        c.holding = false;
      }
    }
    requests_.push_back({c.replica, c.last_input});
    request_sessions_.push_back(session);
  }
  select_ms_ = ms_since(select_start);
  frame_bytes_.resize(requests_.size());
  outgoing_.resize(requests_.size());
  // TESTING ONLY (--test-fault): frame k is the victim's, broken on purpose before it is sent.
  const auto victim = [&](std::size_t k) { return fault_ && fault_has_victim_ && request_sessions_[k] == fault_session_; };
  const auto deliver = [&](std::size_t k, net::shared_frame frame, const replication_stats& st) {
    frame_bytes_[k] = frame.size();
    // A reset frame ends a session's wait after dropped frames (net/server.h).
    // Its age (net::server::frame_write_age) counts from the time the frame carries: the client's
    // update latency less the network's and the client's share.
    outgoing_[k] = {request_sessions_[k], std::move(frame),
                    st.reset ? net::delivery::state_reset : net::delivery::state, now};
  };
  // A viewer snapshot due this tick is filled while the replication engine waits for the device
  // (build_many's side work: the store and the tracker are final after the step and stay so until
  // publish_viewer, which then only publishes). Only on the engine with frames to build: elsewhere
  // there is no wait to fill, and publish_viewer fills it (in the tick's viewer phase, as before).
  // The lambda is held by reference: no allocation.
  const auto viewer_work = [&] {
    // An engine that failed before calling it leaves it to build_many's CPU path (after the frames).
    if (replicator_.on_engine()) ++stats_.viewer_snapshots_in_wait;
    viewer_step_taken_ = true;
    // The pool is idle while the engine waits (build_many parked it): the columns, when the
    // interest engine's wait did not copy them, go over it.
    viewer_take_step(pool_.get());
  };
  const std::function<void()> viewer_side = std::ref(viewer_work);
  const bool viewer_due = viewer_ && !requests_.empty() && replicator_.on_engine() && viewer_->viewers() > 0 &&
                          viewer_snapshot_due();
  replicator_.build_many(
      requests_, world_->store(), world_->tracker(), world_->tick(), now, pool_.get(),
      [&](std::size_t k, std::span<const std::uint8_t> frame, const replication_stats& st) {
        if (victim(k)) frame = fault_->rewrite(frame, world_->tick(), world_->store());
        net::frame_arena& arena = replication_arena();
        // The frame was written into the room reserved for it below: it becomes the session's
        // frame as it is (the rewritten one of the fault test is copied in).
        deliver(k, arena.in_reservation(frame) ? arena.commit(frame.size()) : arena.make(frame), st);
      },
      [&](std::size_t begin, std::size_t end) {
        // A chunk's frames to the network together: one lookup lock, one ready-list append per
        // I/O thread (net::server::send_many_moved: the frames are taken, the slots left empty).
        net_.send_many_moved(std::span(outgoing_).subspan(begin, end - begin));
      },
      // Each frame is written straight into its worker's net::frame_arena (blocks taken again
      // once their frames are written: no allocation a frame, no copy out of the writer).
      [](std::size_t, std::size_t bytes) { return replication_arena().reserve(bytes); },
      // On the GPU replication engine: each frame sent from the engine's own buffer, no copy
      // (the engine reuses it once every frame of it is released).
      [&](std::size_t k, net::shared_frame frame, const replication_stats& st) {
        if (victim(k)) frame = net::make_shared_frame(fault_->rewrite(frame.bytes(), world_->tick(), world_->store()));
        deliver(k, std::move(frame), st);
      },
      viewer_due ? &viewer_side : nullptr);
  replicated_on_engine_ = replicator_.on_engine() && !requests_.empty();
  for (const std::size_t bytes : frame_bytes_) stats_.bytes_sent += bytes;
  stats_.frames_sent += frame_bytes_.size();
}

void zone_server::log_summary() {
  if (!(cfg_.log_summary_s > 0)) return;
  const auto now = clock_type::now();
  if (last_summary_ == clock_type::time_point{}) last_summary_ = now;
  if (now - last_summary_ < std::chrono::duration<double>(cfg_.log_summary_s)) return;
  last_summary_ = now;
  const auto ns = net_.stats();
  const auto& a = summary_net_;
  const std::uint64_t joined = stats_.joins - summary_loop_.joins, left = stats_.leaves - summary_loop_.leaves;
  const std::uint64_t refused = (ns.connections_refused - a.connections_refused) + (ns.pending_evicted_address - a.pending_evicted_address) +
                                (ns.pending_evicted - a.pending_evicted) + (ns.hellos_rejected - a.hellos_rejected);
  const std::uint64_t timeouts = (ns.hello_timeouts - a.hello_timeouts) + (ns.idle_timeouts - a.idle_timeouts);
  const std::uint64_t limited = ns.rate_limited - a.rate_limited, rejected = ns.frames_rejected - a.frames_rejected;
  const std::uint64_t churn = ns.connections_rate_limited - a.connections_rate_limited;
  // Quiet when nothing happened.
  if (joined + left + refused + timeouts + limited + rejected + churn != 0) {
    spdlog::info(
        "clients: {} ({} joined, {} left in {:.0f} s); refused {} (slots {}, evicted per address {}, evicted in all {}, bad hello {}); "
        "timeouts {} (hello {}, idle {}); rate-limited {}; refused at accept (connect-rate) {}; bad frames {}; {} without hello now; "
        "joins so far: accept to hello p50 {:.1f} / p99 {:.1f} ms, hello to welcome p50 {:.1f} / p99 {:.1f} ms",
        clients_.size(), joined, left, cfg_.log_summary_s, refused, ns.connections_refused - a.connections_refused,
        ns.pending_evicted_address - a.pending_evicted_address, ns.pending_evicted - a.pending_evicted,
        ns.hellos_rejected - a.hellos_rejected, timeouts, ns.hello_timeouts - a.hello_timeouts,
        ns.idle_timeouts - a.idle_timeouts, limited, churn, rejected, ns.pending_open,
        stats_.join_hello_ms.percentile(0.5), stats_.join_hello_ms.percentile(0.99),
        stats_.join_welcome_ms.percentile(0.5), stats_.join_welcome_ms.percentile(0.99));
  }
  summary_net_ = ns;
  summary_loop_.joins = stats_.joins;
  summary_loop_.leaves = stats_.leaves;
}

void zone_server::write_tick_line(double inputs_ms, double replicate_ms, double tick_ms, std::uint64_t frames,
                                  std::uint64_t bytes) {
  const step_times& ph = world_->last_step();
  const double t = std::chrono::duration<double>(clock_type::now() - started_).count();
  // The viewer's columns: its phase, its snapshot's fill wherever it ran (in the interest
  // engine's wait, the replication engine's or the viewer phase), and what was left of the interest
  // engine's device wait after the host work overlapped with it (0 off the GPU engine).
  const double interest_wait_ms = world_->tracker().stats().on_engine ? world_->tracker().stats().engine_timing.wait_ms : 0.0;
  // The GPU replication engine's share of the replicate phase (its run: uploads, kernels, copies
  // back, waits), of that its buffers' growth, and whether the frames went on in its pinned
  // buffer (1) or were copied on the host (0: every such buffer still held by slow clients).
  interest::replication_timing engine{};
  if (replicated_on_engine_ && replication_engine_) engine = replication_engine_->timing();
  std::fprintf(tick_csv_, "%llu,%.4f,%llu,%llu,%llu,%.3f,%.3f,%.3f,%.3f,%.3f,%.3f,%.4f,%.4f,%.4f,%.4f,%.3f,%.3f,%d\n",
               static_cast<unsigned long long>(world_->tick()), t, static_cast<unsigned long long>(stats_.clients),
               static_cast<unsigned long long>(frames), static_cast<unsigned long long>(bytes), inputs_ms,
               ph.behaviours, ph.integrate, ph.interest, replicate_ms, tick_ms, viewer_ms_, viewer_fill_ms_,
               interest_wait_ms, select_ms_, engine.total_ms, engine.alloc_ms, engine.kept ? 1 : 0);
}

void zone_server::tick_once() {
  const auto t0 = clock_type::now();
  thread_local const int self = net::current_thread_id();
  if (tick_thread_id_.load(std::memory_order_relaxed) != self) tick_thread_id_.store(self, std::memory_order_relaxed);
  if (stats_.ticks == 0) started_ = t0;
  const std::uint64_t frames0 = stats_.frames_sent, bytes0 = stats_.bytes_sent;
  viewer_fill_ms_ = 0;
  // The last tick's snapshot copied before anything changes the store; the wait is this tick's
  // viewer cost (its viewer phase and viewer_fill_ms), not its inputs'.
  const double copy_wait_ms = viewer_copy_wait();
  stats_.viewer_copy_wait_ms += copy_wait_ms;
  viewer_fill_ms_ += copy_wait_ms;
  const auto t_inputs = clock_type::now();
  drain_inputs();
  if (resume_) {
    expired_.clear();
    resume_->expire(world_->tick(), expired_);
    for (const entity_id id : expired_) world_->despawn(id);
    stats_.linger_expired += expired_.size();
  }
  if (ext_ != nullptr) {
    ext_->before_step(*world_);
    ext_->take_class_changes(class_changes_);
    retry_pending_hellos();
  }
  const double inputs_ms = ms_since(t_inputs);
  stats_.inputs_ms.record(inputs_ms);
  if (auto err = world_->step()) spdlog::error("tick {}: {}", world_->tick(), err->message);
  if (ext_ != nullptr) {
    redirects_.clear();
    ext_->after_step(*world_, redirects_);
    for (const auto& r : redirects_) {
      const auto se = session_of_entity_.find(r.entity);
      if (se == session_of_entity_.end()) continue;
      const auto it = clients_.find(se->second);
      if (it == clients_.end() || it->second.redirected) continue;
      it->second.redirected = true;
      net_.send(se->second, net::make_shared_frame(encoder_.encode(net::redirect_msg{r.host, r.port, r.token})),
                net::delivery::control);
    }
    ext_->clients(clients_.size(), cfg_.max_clients);
    if (ext_->must_stop()) stop();
  }
  if (!engine_failure_logged_ && !world_->tracker().engine_error().empty()) {
    engine_failure_logged_ = true;
    spdlog::warn("zone: tick {}: the GPU interest engine failed ({}); interest runs on the host from this tick on, finder {}",
                 world_->tick(), world_->tracker().engine_error(), parts_.finder->name());
  }
  replicate_class_changes();
  // The ground truth of this tick (--oracle), before any frame of it is sent.
  if (truth_)
    truth_->publish(world_->store(), world_->tick(), world_->tracker().carried_by_last_update(), world_->tick() == 1);
  const auto t1 = clock_type::now();
  replicate();
  if (!replication_failure_logged_ && !replicator_.engine_error().empty()) {
    replication_failure_logged_ = true;
    spdlog::warn("zone: tick {}: the GPU replication engine failed ({}); replication runs on the CPU from this tick on, every client resynced",
                 world_->tick(), replicator_.engine_error());
    world_->set_player_views_on_host(true);
  }
  const double replicate_ms = ms_since(t1);
  const auto t2 = clock_type::now();
  publish_viewer();
  viewer_ms_ = ms_since(t2) + copy_wait_ms;
  const double tick_ms = ms_since(t0);
  if (viewer_ && viewer_->viewers() > 0) {
    auto& rows = viewer_->next_stats().ticks;  // reserved: no allocation
    const step_times& ph = world_->last_step();
    if (rows.size() < net::viewer_stats::max_ticks) {
      rows.push_back({world_->tick(), inputs_ms, ph.behaviours, ph.integrate, ph.interest, replicate_ms, viewer_ms_, tick_ms});
    }
  }
  stats_.replicate_ms.record(replicate_ms);
  stats_.tick_ms.record(tick_ms);
  ++stats_.ticks;
  if (tick_csv_) {
    write_tick_line(inputs_ms, replicate_ms, tick_ms, stats_.frames_sent - frames0, stats_.bytes_sent - bytes0);
  }
  // Refresh the metrics snapshot about once a second (the scrape never touches game state).
  const auto every = static_cast<std::uint64_t>(std::max(1.0, cfg_.tick_rate_hz));
  if (metrics_ && stats_.ticks % every == 1) metrics_->publish(metrics_text());
  log_summary();
}

double zone_server::viewer_copy_wait() {
  if (!viewer_copier_) return 0;
  const auto t0 = clock_type::now();
  const auto done = viewer_copier_->wait();
  if (!done) return 0;
  const double waited = ms_since(t0);
  if (done->failed && !viewer_copy_failure_logged_) {
    viewer_copy_failure_logged_ = true;
    spdlog::warn(
        "viewer: a snapshot's copy failed (out of memory?): that snapshot was not sent; the next one is tried");
  }
  if (!done->failed) {
    count_viewer_columns(done->what);
    ++stats_.viewer_columns_after_tick;  // published
  }
  stats_.viewer_copy_ms += done->copy_ms;
  return waited;
}

void zone_server::viewer_copy_columns() {
  if (!viewer_ || viewer_copier_ || viewer_->viewers() == 0 || !viewer_snapshot_due()) return;
  const auto t0 = clock_type::now();
  // The pool is idle while the device works (replication's prestage, if any, has returned).
  count_viewer_columns(
      fill_viewer_columns(world_->store(), viewer_->next_snapshot(), pool_.get(), cfg_.viewer_copy_chunk));
  viewer_columns_tick_ = world_->tick();
  ++stats_.viewer_columns_in_interest_wait;
  viewer_fill_ms_ += ms_since(t0);
}

void zone_server::count_viewer_columns(viewer_columns_fill what) {
  if (what == viewer_columns_fill::all) ++stats_.viewer_columns_copied_all;
  if (what == viewer_columns_fill::classes_patched) ++stats_.viewer_columns_classes_patched;
}

void zone_server::fill_viewer_snapshot(net::viewer_snapshot& s, interest::thread_pool* pool) {
  const entity_store& store = world_->store();
  const interest::interest_tracker& tr = world_->tracker();
  s.tick = world_->tick();
  s.world_lo[0] = cfg_.world.lo.x, s.world_lo[1] = cfg_.world.lo.y, s.world_lo[2] = cfg_.world.lo.z;
  s.world_hi[0] = cfg_.world.hi.x, s.world_hi[1] = cfg_.world.hi.y, s.world_hi[2] = cfg_.world.hi.z;
  // The columns, unless this tick's were copied while the interest engine's device worked (a
  // single zone: nothing moves an entity after the step; a class changed since, by a player's
  // visibility switch, changes the layout version and the columns are copied again).
  // With --viewer-fill after, the copier's thread copies them once the tick is over.
  if (!viewer_copier_ && (viewer_columns_tick_ != s.tick || s.layout != store.layout_version())) {
    count_viewer_columns(fill_viewer_columns(store, s, pool, cfg_.viewer_copy_chunk));
  }
  const auto pos = store.positions();
  const auto cls = store.visibility_classes();
  const auto kinds = store.kinds();
  // The selected entities: boxes, visible set with each entity's replication tier, events.
  s.selections.resize(viewer_watch_.size());
  const float near_sq = cfg_.update_near * cfg_.update_near, mid_sq = cfg_.update_mid * cfg_.update_mid;
  for (std::size_t k = 0; k < viewer_watch_.size(); ++k) {
    auto& sel = s.selections[k];
    const auto& w = viewer_watch_[k];
    sel.id = w.id;
    sel.events.resize(w.count);
    for (std::size_t e = 0; e < w.count; ++e) sel.events[e] = w.events[(w.first + e) % viewer_watch::max_events];
    sel.visible.clear();
    sel.tier.clear();
    const std::size_t d = store.index_of(sel.id), row = tr.row_of(sel.id);
    sel.alive = d != entity_store::npos && row != entity_store::npos;
    if (!sel.alive) continue;
    const vec3 p = pos[d], a = store.aoi_half_extents()[d], h = store.presence_half_extents()[d];
    sel.position[0] = p.x, sel.position[1] = p.y, sel.position[2] = p.z;
    sel.aoi_half[0] = a.x, sel.aoi_half[1] = a.y, sel.aoi_half[2] = a.z;
    sel.presence_half[0] = h.x, sel.presence_half[1] = h.y, sel.presence_half[2] = h.z;
    sel.hysteresis = tr.options().hysteresis;
    sel.sees = store.sees()[d];
    sel.visibility = static_cast<std::uint8_t>(std::countr_zero(cls[d]));
    sel.kind = static_cast<std::uint8_t>(kinds[d]);
    const auto visible = tr.visible(row);
    sel.visible.assign(visible.begin(), visible.end());
    sel.tier.resize(visible.size());
    for (std::size_t v = 0; v < visible.size(); ++v) {
      const std::size_t j = store.index_of(visible[v]);
      if (j == entity_store::npos) {
        sel.tier[v] = 2;
        continue;
      }
      // The replicator's distance tiers (docs/zone.md): every tick near, every few ticks mid, far.
      const float dx = pos[j].x - p.x, dy = pos[j].y - p.y, dz = pos[j].z - p.z, d2 = dx * dx + dy * dy + dz * dz;
      sel.tier[v] = d2 < near_sq ? 0 : d2 < mid_sq ? 1 : 2;
    }
  }
}

void zone_server::fill_viewer_stats(net::viewer_stats& s) const {
  const auto& ts = world_->tracker().stats();
  s.tick = world_->tick();
  s.tick_rate = cfg_.tick_rate_hz;
  s.budget_ms = 1000.0 / cfg_.tick_rate_hz;
  s.entities = static_cast<double>(world_->store().size());
  s.clients = static_cast<double>(stats_.clients);
  s.pairs = static_cast<double>(ts.pairs);
  s.candidates = static_cast<double>(ts.candidates);
  s.visible = static_cast<double>(ts.visible);
  s.enters = static_cast<double>(ts.enters);
  s.leaves = static_cast<double>(ts.leaves);
  s.overruns = static_cast<double>(stats_.overruns);
  s.byte_budget = static_cast<double>(cfg_.client_byte_budget);
  s.update_near = cfg_.update_near;
  s.update_mid = cfg_.update_mid;
  s.tick_p99_ms = stats_.tick_ms.percentile(0.99);
  s.interest_p99_ms = world_->phases().interest.percentile(0.99);
  s.interest_on = interest_name();
  s.world[0] = cfg_.world.lo.x, s.world[1] = cfg_.world.lo.y, s.world[2] = cfg_.world.hi.x, s.world[3] = cfg_.world.hi.y;
}

bool zone_server::viewer_snapshot_due() const {
  const auto every = static_cast<std::uint64_t>(std::max(1.0, std::round(cfg_.tick_rate_hz / cfg_.viewer_hz)));
  return world_->tick() % every == 0;
}

void zone_server::viewer_take_step(interest::thread_pool* pool) {
  const interest::interest_tracker& tr = world_->tracker();
  const std::uint64_t tick = world_->tick();
  // The watched entities' enters and leaves of this step (a window of the latest 64 each).
  for (auto& w : viewer_watch_) {
    const std::size_t row = tr.row_of(w.id);
    if (row == entity_store::npos) continue;
    for (const entity_id id : tr.enters(row)) w.add({tick, id, true});
    for (const entity_id id : tr.leaves(row)) w.add({tick, id, false});
  }
  // A snapshot every tick_rate / viewer_hz ticks, filled into the viewer's free buffer.
  viewer_snapshot_filled_ = viewer_snapshot_due();
  if (viewer_snapshot_filled_) {
    const auto t0 = clock_type::now();
    fill_viewer_snapshot(viewer_->next_snapshot(), pool);
    viewer_fill_ms_ += ms_since(t0);
  }
}

void zone_server::publish_viewer() {
  if (!viewer_) return;
  // Taken in replicate() (while the engine waited): the page was open then; publish what it filled.
  const bool taken = std::exchange(viewer_step_taken_, false);
  if (!taken && viewer_->viewers() == 0) {
    if (!viewer_watch_ids_.empty()) {
      viewer_watch_.clear();
      viewer_watch_ids_.clear();
      world_->set_watched({});
    }
    viewer_->next_stats().ticks.clear();
    return;
  }
  if (!taken) viewer_take_step(nullptr);
  // The snapshot handed over with one atomic exchange (no lock, no allocation once the buffers
  // have grown).
  if (std::exchange(viewer_snapshot_filled_, false)) {
    if (viewer_copier_) {
      // Its columns copied and published by the copier's thread (the next tick waits for it).
      viewer_copier_->start(world_->store(), viewer_->next_snapshot(), *viewer_, cfg_.viewer_copy_chunk);
    } else {
      viewer_->publish();
    }
  }
  // The stats twice a second: numbers only; the viewer's thread formats the JSON.
  const auto now = clock_type::now();
  if (now >= next_viewer_stats_) {
    next_viewer_stats_ = now + std::chrono::milliseconds(500);
    fill_viewer_stats(viewer_->next_stats());
    viewer_->publish_stats();
  }
  // The pages' selections, watched from the next step on (a GPU engine copies their rows back):
  // read only when a page changed its selection (one relaxed atomic read a tick otherwise).
  if (const auto version = viewer_->selection_version(); version != viewer_selection_version_) {
    viewer_selection_version_ = version;
    const auto wanted = viewer_->selected();
    if (wanted != viewer_watch_ids_) {
      std::vector<viewer_watch> next;
      for (const entity_id id : wanted) {
        auto& w = next.emplace_back();
        w.id = id;
        for (const auto& old : viewer_watch_) {
          if (old.id == id) w = old;
        }
      }
      viewer_watch_ = std::move(next);
      viewer_watch_ids_ = wanted;
      world_->set_watched(viewer_watch_ids_);
    }
  }
}

double zone_server::between_ticks(std::chrono::steady_clock::time_point deadline) {
  const double ms = replicator_.grow_ahead(deadline);
  stats_.grow_ahead_ms += ms;
  return ms;
}

void zone_server::run() {
  // The tick's own thread runs a share of every phase: on the workers' CPUs, until run() returns
  // (then as before: the caller's thread may go on to other work, or start another server).
  struct restore_cpus {
    std::vector<int> cpus = net::allowed_cpus();
    ~restore_cpus() { (void)net::pin_current_thread(cpus); }
  } const restore;
  if (auto err = net::pin_current_thread(pin_cpus(cfg_.worker_cpus))) {
    spdlog::warn("zone: the tick's thread not pinned: {}", *err);
  }
  const auto period = std::chrono::duration_cast<clock_type::duration>(std::chrono::duration<double>(1.0 / cfg_.tick_rate_hz));
  auto next = clock_type::now();
  while (!stop_requested_) {
    tick_once();
    next += period;
    const auto now = clock_type::now();
    if (now > next) {
      // Overrun: skip the ticks already missed instead of running them back to back (no spiral).
      ++stats_.overruns;
      const auto late = now - next;
      const auto behind = late / period;
      stats_.skipped_ticks += static_cast<std::uint64_t>(behind);
      next += behind * period;
      if (stats_.overruns % 100 == 1) {
        spdlog::warn("tick {} overran by {:.2f} ms ({} overruns so far)", world_->tick(),
                     std::chrono::duration<double, std::milli>(late).count(), stats_.overruns);
      }
    } else {
      const auto spin = std::chrono::microseconds(pool_->spin_us());
      // In the time left: the GPU replication engine's buffers grown ahead of the next ticks'
      // needs (their growth in a tick cost it 7-13 ms at 20,000 clients on the H200 host).
      (void)between_ticks(next - spin);
      // Wake the workers a little before the tick (they spin until it starts): a sleeping
      // thread's wake-up would otherwise land in the tick's first parallel phase.
      if (spin.count() > 0 && next - clock_type::now() > spin) {
        std::this_thread::sleep_until(next - spin);
        pool_->run(pool_->size(), [](std::size_t) {});
        (void)viewer_copy_wait();  // the copier reads the store: done before anything else touches it (between ticks: no tick's wait)
        world_->prepare();  // and the GPU, if the interest step runs there
      }
      std::this_thread::sleep_until(next);
    }
  }
  // The process's CPU by thread group, read while the I/O threads still run (docs/operating.md).
  const net::process_usage used = net::read_process_usage(true);
  const std::uint64_t frames_written = net_.stats().frames_out;
  net_.stop();
  // The growth ahead only where the GPU replication engine ran (a CPU-only server has none).
  const std::string ahead =
      replication_engine_ ? fmt::format("; {:.1f} ms between ticks growing the GPU replication engine's buffers ahead",
                                        stats_.grow_ahead_ms)
                          : std::string();
  spdlog::info("zone: stopped after {} ticks ({} overruns, {} ticks skipped{})", stats_.ticks, stats_.overruns,
               stats_.skipped_ticks, ahead);
  if (resume_) {
    spdlog::info(
        "  players: {} joined, {} left ({} with a leave), {} connected at the stop; kept after a lost connection {}: "
        "back {}, removed unclaimed {}, waiting {}; taken over {}; tokens refused {}",
        stats_.joins, stats_.leaves, stats_.logouts, clients_.size(), stats_.players_lingered, stats_.players_resumed,
        stats_.linger_expired, resume_->kept(), stats_.takeovers, stats_.resumes_refused);
  }
  // `per_ms`: the units recorded per millisecond.
  const auto report = [](const char* name, const auto& h, double per_ms = 1.0) {
    spdlog::info("  {:<10} p50 {:8.3f} ms  p99 {:8.3f} ms  max {:8.3f} ms", name, h.percentile(0.5) / per_ms,
                 h.percentile(0.99) / per_ms, h.max() / per_ms);
  };
  report("tick", stats_.tick_ms);
  report("inputs", stats_.inputs_ms);
  report("behaviours", world_->phases().behaviours);
  report("integrate", world_->phases().integrate);
  report("interest", world_->phases().interest);
  report("replicate", stats_.replicate_ms);
  report("written", net_.frame_write_age(), 1000.0);  // each tick update's age when written (microseconds)
  const auto groups = cpu_by_thread_group(used);
  spdlog::info("  cpu        {:.1f} s (tick {:.1f}, io {:.1f}, other {:.1f}): {:.2f} us a frame written ({} frames)",
               used.cpu_seconds, groups[0], groups[1], groups[2],
               frames_written > 0 ? used.cpu_seconds / static_cast<double>(frames_written) * 1e6 : 0.0, frames_written);
  if (truth_) {
    truth_->stop();
    const auto& t = truth_->stats();
    const double n = static_cast<double>(std::max<std::uint64_t>(1, t.ticks));
    spdlog::info(
        "  oracle stream: {} ticks published, {:.1f} KB per tick ({} with the whole layout, {} with changes to it: "
        "{} entities), publish {:.3f} ms per tick, {} subscribers dropped, {} refused",
        t.ticks, static_cast<double>(t.bytes) / 1024.0 / n, t.layouts, t.changes, t.changed_entities, t.publish_ms / n,
        t.dropped_subscribers, t.refused_subscribers);
  }
}

}  // namespace zone
