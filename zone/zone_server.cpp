// The tick loop (zone_server.h): drain client inputs, step the world, replicate, at a fixed rate.
#include "zone_server.h"

#include <spdlog/spdlog.h>

#include <chrono>
#include <thread>

namespace zone {

namespace {

using clock_type = std::chrono::steady_clock;
double ms_since(clock_type::time_point t0) {
  return std::chrono::duration<double, std::milli>(clock_type::now() - t0).count();
}

net::server_options net_options(const zone_config& c) {
  net::server_options o;
  o.address = c.listen_address;
  o.port = c.port;
  o.io_threads = c.io_threads;
  o.max_connections = c.max_clients;
  o.inbound.max_frame_bytes = c.max_frame_bytes;
  o.inputs_per_second = c.inputs_per_second;
  o.input_burst = std::max(1.0, c.inputs_per_second / 2);
  return o;
}

replication_options replica_options(const zone_config& c) {
  replication_options o;
  o.world = c.world;
  o.byte_budget = c.client_byte_budget;
  return o;
}

}  // namespace

zone_server::zone_server(const zone_config& cfg)
    : cfg_(cfg),
      pool_(std::make_unique<interest::thread_pool>(cfg.worker_threads)),
      finder_(std::make_unique<interest::grid_finder>(pool_.get())),
      world_(std::make_unique<zone_world>(cfg, *finder_, pool_.get())),
      replicator_(replica_options(cfg)),
      net_(net_options(cfg)) {}

zone_server::~zone_server() { net_.stop(); }

std::optional<std::string> zone_server::start() {
  if (auto err = validate(cfg_)) return err;
  world_->populate();
  spdlog::info("zone: {} NPCs, world {}x{}x{} m, {} Hz, {} worker threads", world_->store().size(), cfg_.world.hi.x,
               cfg_.world.hi.y, cfg_.world.hi.z, cfg_.tick_rate_hz, pool_->size());
  return net_.start();
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
          // Spawn at a town (deterministic in the session id).
          const vec3 town = world_->town(e.session % world_->town_count());
          const entity_id id = world_->spawn_player(town);
          if (id == null_entity) {
            net_.disconnect(e.session, net::error_code::server_full, "the zone is full");
            break;
          }
          client& c = clients_[e.session];
          c.entity = id;
          c.replica = replicator_.add_client(id);
          net::welcome_msg w{id, cfg_.world, static_cast<std::uint16_t>(cfg_.tick_rate_hz), world_->tick(),
                             net::protocol_version};
          net_.send(e.session, net::make_shared_frame(encoder_.encode(w)), net::delivery::control);
          spdlog::info("session {}: '{}' joined as entity {}", e.session, hello->name, id);
        } else if (const auto* in = std::get_if<net::input_msg>(&*e.msg)) {
          const auto it = clients_.find(e.session);
          if (it == clients_.end()) break;
          // A client steers only its own entity; the world clamps the speed.
          world_->set_intent(it->second.entity, {in->move.x, in->move.y, in->move.z});
          it->second.last_input = std::max(it->second.last_input, in->sequence);
        }
        break;
      }
      case net::inbound_event::kind::frames_dropped: {
        const auto it = clients_.find(e.session);
        if (it != clients_.end()) replicator_.resync(it->second.replica);
        break;
      }
      case net::inbound_event::kind::disconnected: {
        const auto it = clients_.find(e.session);
        if (it == clients_.end()) break;
        world_->despawn(it->second.entity);
        replicator_.remove_client(it->second.replica);
        clients_.erase(it);
        break;
      }
    }
  }
  stats_.clients = clients_.size();
}

void zone_server::replicate() {
  const std::uint64_t now = net_.now_us();
  for (const auto& [session, c] : clients_) {
    const auto frame = replicator_.build(c.replica, world_->store(), world_->tracker(), world_->tick(), now, c.last_input,
                                         writer_);
    net_.send(session, net::make_shared_frame(frame), net::delivery::state);
    ++stats_.frames_sent;
    stats_.bytes_sent += frame.size();
  }
}

void zone_server::tick_once() {
  const auto t0 = clock_type::now();
  drain_inputs();
  stats_.inputs_ms.record(ms_since(t0));
  if (auto err = world_->step()) spdlog::error("tick {}: {}", world_->tick(), err->message);
  const auto t1 = clock_type::now();
  replicate();
  stats_.replicate_ms.record(ms_since(t1));
  stats_.tick_ms.record(ms_since(t0));
  ++stats_.ticks;
}

void zone_server::run() {
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
      std::this_thread::sleep_until(next);
    }
  }
  net_.stop();
  spdlog::info("zone: stopped after {} ticks ({} overruns, {} ticks skipped)", stats_.ticks, stats_.overruns,
               stats_.skipped_ticks);
  const auto report = [](const char* name, const latency_histogram& h) {
    spdlog::info("  {:<10} p50 {:8.3f} ms  p99 {:8.3f} ms  max {:8.3f} ms", name, h.percentile(0.5), h.percentile(0.99),
                 h.max());
  };
  report("tick", stats_.tick_ms);
  report("inputs", stats_.inputs_ms);
  report("behaviours", world_->phases().behaviours);
  report("integrate", world_->phases().integrate);
  report("interest", world_->phases().interest);
  report("replicate", stats_.replicate_ms);
}

}  // namespace zone
