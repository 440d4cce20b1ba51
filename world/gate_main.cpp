// world-gate: the login service of a world of zones (docs/world.md, "Logging in through a gate").
// A client connects and says hello as it would to a zone; the gate answers with a redirect to the
// least loaded zone that serves the world now (gate_pick: the regions whose lease names an
// address, a standby that took a region over among them, by the load each zone tells beside its
// lease) with an empty token, and closes: the client says hello at that zone and joins it as a
// new player. No zone serving, or every one full: error(server_full).
// A hello with a token (welcome.resume_token: a client whose zone was lost) goes to the zone that
// serves the region the token names, with the token: as soon as one does (a standby, a restarted
// zone), waiting for it up to --resume-wait seconds (then error(timeout)).
// The leases are read from NATS KV every 250 ms by a thread of its own (a lease its zone has not
// renewed for half the TTL is left out: lease_watch); a client gets
// --hello-timeout seconds to say hello, a hello of at most 4 KiB, and at most --max-connections
// are held at once, --max-per-address from one address (more are closed at accept).
#include <utility>  // first: Boost 1.74's asio under GCC 12 in C++20

#include <nats/nats.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include <array>
#include <boost/asio.hpp>
#include <boost/program_options.hpp>
#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <sstream>
#include <string>
#include <thread>

#include "gate.h"
#include "net/codec.h"

namespace asio = boost::asio;
namespace po = boost::program_options;
using tcp = asio::ip::tcp;
using namespace zone;

namespace {

struct gate_options {
  std::string nats_url, world, listen = "127.0.0.1";
  std::uint16_t port = 0;
  std::size_t max_connections = 1024;
  std::size_t max_per_address = 64;
  double hello_timeout_s = 5;
  double resume_wait_s = 30;
};

struct gate_counters {
  std::uint64_t redirected = 0, no_zone = 0, refused_full = 0, refused_address = 0, bad = 0, timeouts = 0;
  std::uint64_t resumed = 0, resume_timeouts = 0;
};

/// The leases as last read, and the NATS connection that reads them (its own thread).
class lease_table {
 public:
  explicit lease_table(const gate_options& o) : o_(o) {}
  ~lease_table() { stop(); }
  /// Connects (an error when NATS cannot be reached) and starts reading every 250 ms.
  std::optional<std::string> start() {
    natsOptions* no = nullptr;
    natsOptions_Create(&no);
    natsOptions_SetURL(no, o_.nats_url.c_str());
    natsOptions_SetMaxReconnect(no, -1);  // a NATS restart must not end the gate
    natsOptions_SetReconnectWait(no, 200);
    const natsStatus s = natsConnection_Connect(&nc_, no);
    natsOptions_Destroy(no);
    if (s != NATS_OK) return "cannot connect to NATS at " + o_.nats_url + ": " + natsStatus_GetText(s);
    if (natsConnection_JetStream(&js_, nc_, nullptr) != NATS_OK) return std::string("no JetStream at ") + o_.nats_url;
    thread_ = std::thread([this] { loop(); });
    return std::nullopt;
  }
  void stop() {
    {
      std::lock_guard lock(m_);
      stopping_ = true;
    }
    cv_.notify_all();
    if (thread_.joinable()) thread_.join();
    if (kv_) kvStore_Destroy(kv_), kv_ = nullptr;
    if (js_) jsCtx_Destroy(js_), js_ = nullptr;
    if (nc_) natsConnection_Destroy(nc_), nc_ = nullptr;
  }
  [[nodiscard]] std::map<std::uint32_t, world::lease_info> leases() const {
    std::lock_guard lock(m_);
    return leases_;
  }

 private:
  void loop() {
    std::string said;  // the last error logged (each new one once)
    std::unique_lock lock(m_);
    while (!stopping_) {
      lock.unlock();
      std::string err;
      std::optional<std::map<std::uint32_t, world::lease_info>> now;
      if (!kv_ && js_KeyValue(&kv_, js_, ("world-" + o_.world + "-lease").c_str()) != NATS_OK) {
        kv_ = nullptr;
        err = "no world '" + o_.world + "' in NATS yet (no lease bucket): waiting for its first zone";
      } else if (kv_) {
        if (stale_after_ == world::lease_watch::clock::duration{}) stale_after_ = half_ttl();
        now = world::read_leases(kv_, &err);
      }
      if (!err.empty() && err != said) spdlog::warn("world gate: {}", err);
      said = err;
      if (now) {
        const auto read = std::move(*now);
        now = watch_.fresh(read, world::lease_watch::clock::now(), stale_after_);
        for (const auto& [region, l] : read) {  // said once each time a zone stops or starts renewing
          const bool stale = !now->contains(region);
          if (stale != stale_.contains(region)) {
            if (stale) {
              stale_.insert(region);
              spdlog::warn(
                  "world gate: region {}'s lease ({}) not renewed for {:.1f} s: no client goes there until it is",
                  region, l.raw, std::chrono::duration<double>(stale_after_).count());
            } else {
              stale_.erase(region);
              spdlog::info("world gate: region {}'s lease renewed again", region);
            }
          }
        }
        std::erase_if(stale_, [&](std::uint32_t r) { return !read.contains(r); });
      }
      lock.lock();
      if (now) leases_ = std::move(*now);
      cv_.wait_for(lock, std::chrono::milliseconds(250), [&] { return stopping_; });
    }
  }
  /// Half the lease bucket's TTL (its zones renew every quarter of it; 1.5 s when it cannot be read).
  [[nodiscard]] world::lease_watch::clock::duration half_ttl() const {
    const double ttl_s = world::lease_ttl_s(kv_).value_or(3);
    return std::chrono::duration_cast<world::lease_watch::clock::duration>(std::chrono::duration<double>(ttl_s / 2));
  }
  gate_options o_;
  world::lease_watch watch_;  ///< the loop's thread
  world::lease_watch::clock::duration stale_after_{};
  std::set<std::uint32_t> stale_;
  natsConnection* nc_ = nullptr;
  jsCtx* js_ = nullptr;
  kvStore* kv_ = nullptr;
  mutable std::mutex m_;
  std::condition_variable cv_;
  bool stopping_ = false;
  std::map<std::uint32_t, world::lease_info> leases_;
  std::thread thread_;
};

/// What the gate's sessions share; the event loop's thread only (one thread runs it).
struct gate_state {
  gate_state(const gate_options& opt, const lease_table& leases) : o(opt), table(leases) {}
  const gate_options& o;
  const lease_table& table;
  gate_counters c;
  std::uint64_t logins = 0;  ///< hellos answered with a pick (gate_pick's round robin)
  std::size_t open = 0;      ///< sessions held
  std::map<asio::ip::address, std::size_t> per_address;  ///< sessions held per client address
  /// Per region: the load its zone told last (as stored), and the logins sent there since.
  std::map<std::uint32_t, std::string> told;
  std::map<std::uint32_t, std::uint64_t> sent;
};

/// One client: its hello, then a redirect (or an error), then closed.
class gate_session : public std::enable_shared_from_this<gate_session> {
 public:
  gate_session(tcp::socket s, gate_state& g, asio::ip::address from)
      : sock_(std::move(s)), timer_(sock_.get_executor()), g_(g), from_(std::move(from)),
        dec_(net::decoder_options{.max_frame_bytes = 4096}) {
    ++g_.open;
    ++g_.per_address[from_];
  }
  ~gate_session() {
    --g_.open;
    if (const auto it = g_.per_address.find(from_); it != g_.per_address.end() && --it->second == 0) {
      g_.per_address.erase(it);
    }
  }
  void start() {
    timer_.expires_after(std::chrono::duration_cast<std::chrono::steady_clock::duration>(
        std::chrono::duration<double>(g_.o.hello_timeout_s)));
    timer_.async_wait([self = shared_from_this()](const boost::system::error_code& ec) {
      if (ec || self->done_) return;
      ++self->g_.c.timeouts;
      self->reply(net::error_msg{net::error_code::timeout, "no hello within the gate's hello timeout"});
    });
    read();
  }

 private:
  void read() {
    auto buf = dec_.prepare(4096);
    reading_ = true;
    sock_.async_read_some(asio::buffer(buf.data(), buf.size()),
                          [self = shared_from_this()](const boost::system::error_code& ec, std::size_t n) {
                            self->reading_ = false;
                            if (self->done_) {  // replied meanwhile (a timeout): drained from here on
                              if (ec) return self->finish();
                              return self->drain();
                            }
                            if (ec) {
                              self->finish();
                              return;
                            }
                            self->dec_.commit(n);
                            self->on_bytes();
                          });
  }
  void on_bytes() {
    const auto step = dec_.next();
    if (step.needs_more()) return read();
    if (step.is_error() || step.frame.type != net::wire::message::hello) {
      ++g_.c.bad;
      reply(net::error_msg{step.is_error() ? net::error_code::bad_frame : net::error_code::unexpected_message,
                           "the gate takes one hello, then redirects to a zone"});
      return;
    }
    const auto* h = step.frame.envelope->message_as_hello();
    if (h && h->protocol_version() != net::protocol_version) {
      ++g_.c.bad;
      reply(net::error_msg{net::error_code::protocol_version, "this world speaks protocol version " +
                                                                   std::to_string(net::protocol_version)});
      return;
    }
    if (h && h->token() && h->token()->size() != 0) {
      const auto region = world::token_region(h->token()->string_view());
      if (!region) {
        ++g_.c.bad;
        reply(net::error_msg{net::error_code::auth_failed, "not a token of this world's zones"});
        return;
      }
      token_ = h->token()->str();
      region_ = *region;
      resume_until_ =
          std::chrono::steady_clock::now() + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                                 std::chrono::duration<double>(g_.o.resume_wait_s));
      resume();
      return;
    }
    const auto leases = g_.table.leases();
    // The logins sent to a region since its zone last told its load (that report counts them).
    for (const auto& [region, l] : leases) {
      if (auto& told = g_.told[region]; told != l.load_raw) told = l.load_raw, g_.sent[region] = 0;
    }
    const auto zone = world::gate_pick(leases, g_.logins++, g_.sent);
    if (!zone) {
      ++g_.c.no_zone;
      reply(net::error_msg{net::error_code::server_full, "no zone of world '" + g_.o.world + "' serves or has room now"});
      return;
    }
    ++g_.sent[zone->first];
    ++g_.c.redirected;
    reply(net::redirect_msg{zone->second.host, zone->second.port, ""});
  }
  /// A client back with its resume token: to the zone that serves its region now, with the token
  /// (it restored the region and waits for the client under it); none yet: asked again every 250 ms.
  void resume() {
    const auto leases = g_.table.leases();
    if (const auto it = leases.find(region_);
        it != leases.end() && it->second.incarnation != 0 && it->second.port != 0) {
      ++g_.c.resumed;
      reply(net::redirect_msg{it->second.host, it->second.port, token_});
      return;
    }
    if (std::chrono::steady_clock::now() >= resume_until_) {
      ++g_.c.resume_timeouts;
      reply(net::error_msg{net::error_code::timeout, "no zone serves region " + std::to_string(region_) +
                                                         " of world '" + g_.o.world + "' (the gate's --resume-wait)"});
      return;
    }
    timer_.expires_after(std::chrono::milliseconds(250));  // the hello timeout's wait ends here (aborted)
    timer_.async_wait([self = shared_from_this()](const boost::system::error_code& ec) {
      if (ec || self->done_) return;
      self->resume();
    });
  }
  void reply(const net::message& m) {
    done_ = true;
    timer_.cancel();
    out_ = net::encode_frame(m);
    asio::async_write(sock_, asio::buffer(out_), [self = shared_from_this()](const boost::system::error_code& ec,
                                                                             std::size_t) {
      if (ec) return self->finish();
      self->linger();
    });
  }
  /// The reply written: our side of the connection shut, what the client still sends read and
  /// dropped until it closes (at most 1 s), so that closing with its bytes unread (a reset) never
  /// takes the reply with it.
  void linger() {
    boost::system::error_code ignored;
    sock_.shutdown(tcp::socket::shutdown_send, ignored);
    timer_.expires_after(std::chrono::seconds(1));
    timer_.async_wait([self = shared_from_this()](const boost::system::error_code& ec) {
      if (!ec) self->finish();
    });
    if (!reading_) drain();  // else the read in flight goes on to drain (one read at a time)
  }
  void drain() {
    sock_.async_read_some(asio::buffer(scratch_), [self = shared_from_this()](const boost::system::error_code& ec,
                                                                                  std::size_t) {
      if (ec) return self->finish();
      self->drain();
    });
  }
  void finish() {
    done_ = true;
    timer_.cancel();
    boost::system::error_code ignored;
    sock_.shutdown(tcp::socket::shutdown_both, ignored);
    sock_.close(ignored);
  }
  tcp::socket sock_;
  asio::steady_timer timer_;
  gate_state& g_;
  asio::ip::address from_;
  net::frame_decoder dec_;
  std::vector<std::uint8_t> out_;
  std::array<std::uint8_t, 512> scratch_{};
  bool done_ = false, reading_ = false;
  std::string token_;  ///< a resuming client's
  std::uint32_t region_ = 0;
  std::chrono::steady_clock::time_point resume_until_{};
};

void accept(tcp::acceptor& a, asio::steady_timer& pause, gate_state& g) {
  a.async_accept([&](const boost::system::error_code& ec, tcp::socket s) {
    if (ec == asio::error::operation_aborted) return;
    if (ec) {  // out of descriptors, say: accept again in a moment, not in a busy loop
      pause.expires_after(std::chrono::milliseconds(100));
      pause.async_wait([&](const boost::system::error_code& e) {
        if (!e) accept(a, pause, g);
      });
      return;
    }
    boost::system::error_code ignored;
    const auto from = s.remote_endpoint(ignored).address();
    if (g.open >= g.o.max_connections) {
      ++g.c.refused_full;
      s.close(ignored);
    } else if (const auto it = g.per_address.find(from); it != g.per_address.end() && it->second >= g.o.max_per_address) {
      ++g.c.refused_address;
      s.close(ignored);
    } else {
      s.set_option(tcp::no_delay(true), ignored);
      std::make_shared<gate_session>(std::move(s), g, from)->start();
    }
    accept(a, pause, g);
  });
}

}  // namespace

int main(int argc, char** argv) {
  gate_options o;
  std::string log_level = "info";
  po::options_description desc(
      "world-gate: the login service of a world of zones (docs/world.md). A client says hello here and is\n"
      "redirected to the least loaded zone that serves the world now (the regions' leases and loads in NATS\n"
      "KV), where it joins as a new player; a client that says its resume token (its zone was lost) goes to\n"
      "the zone that serves its region now, to get its entity back.\n\nOptions");
  desc.add_options()                                                                                           //
      ("help", "this text")                                                                                    //
      ("nats", po::value(&o.nats_url), "NATS server URL of the world (e.g. nats://127.0.0.1:4222); required")  //
      ("world", po::value(&o.world), "the world's name; required")                                             //
      ("listen", po::value(&o.listen)->default_value(o.listen), "address to listen on")                        //
      ("port", po::value(&o.port)->default_value(o.port), "port to listen on (0 = an ephemeral one, logged)")  //
      ("max-connections", po::value(&o.max_connections)->default_value(o.max_connections),
       "clients held at once (a client stays until its redirect is written); more are closed at accept")  //
      ("max-per-address", po::value(&o.max_per_address)->default_value(o.max_per_address),
       "clients held at once from one address; more are closed at accept")  //
      ("hello-timeout", po::value(&o.hello_timeout_s)->default_value(o.hello_timeout_s),
       "seconds a client has to say hello")  //
      ("resume-wait", po::value(&o.resume_wait_s)->default_value(o.resume_wait_s),
       "seconds a client with a resume token waits here for a zone to serve its region (its zone was lost)")  //
      ("log-level", po::value(&log_level)->default_value(log_level), "trace, debug, info, warn, error or critical");
  po::variables_map vm;
  try {
    po::store(po::parse_command_line(argc, argv, desc), vm);
    po::notify(vm);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "world-gate: %s (try --help)\n", e.what());
    return 2;
  }
  if (vm.count("help")) {
    std::ostringstream text;
    text << desc;
    std::fputs(text.str().c_str(), stdout);
    return 0;
  }
  if (o.nats_url.empty() || o.world.empty()) {
    std::fprintf(stderr, "world-gate: --nats and --world are required (try --help)\n");
    return 2;
  }
  if (!(o.hello_timeout_s > 0 && o.hello_timeout_s <= 600) || !(o.resume_wait_s >= 0 && o.resume_wait_s <= 3600) ||
      o.max_connections == 0 || o.max_per_address == 0) {
    std::fprintf(stderr,
                 "world-gate: --hello-timeout must be in (0, 600], --resume-wait in [0, 3600], --max-connections and "
                 "--max-per-address at least 1\n");
    return 2;
  }
  spdlog::set_default_logger(
      std::make_shared<spdlog::logger>("", std::make_shared<spdlog::sinks::stderr_color_sink_mt>()));
  spdlog::set_level(spdlog::level::from_str(log_level));
  lease_table table(o);
  if (auto err = table.start()) {
    spdlog::critical("world gate: {}", *err);
    return 1;
  }
  // Declared before the event loop: sessions still held when it is destroyed count themselves out.
  gate_state g{o, table};
  asio::io_context io;
  tcp::acceptor acceptor(io);
  asio::steady_timer pause(io);
  boost::system::error_code ec;
  const auto addr = asio::ip::make_address(o.listen, ec);
  if (ec) {
    spdlog::critical("world gate: --listen '{}': {}", o.listen, ec.message());
    return 2;
  }
  const tcp::endpoint at(addr, o.port);
  acceptor.open(at.protocol(), ec);
  if (!ec) acceptor.set_option(tcp::acceptor::reuse_address(true), ec);
  if (!ec) acceptor.bind(at, ec);
  if (!ec) acceptor.listen(asio::socket_base::max_listen_connections, ec);
  if (ec) {
    spdlog::critical("world gate: cannot listen on {}:{}: {}", o.listen, o.port, ec.message());
    return 1;
  }
  accept(acceptor, pause, g);
  asio::signal_set signals(io, SIGINT, SIGTERM);
  signals.async_wait([&](const boost::system::error_code&, int) {
    acceptor.close();
    pause.cancel();
    io.stop();
  });
  spdlog::info("world gate listening on {}:{} for world '{}' (NATS {})", o.listen, acceptor.local_endpoint().port(),
               o.world, o.nats_url);
  io.run();
  table.stop();
  spdlog::info(
      "world gate: {} logins redirected, {} refused for want of a zone, {} bad, {} timed out, {} refused (full), {} "
      "refused (over --max-per-address); {} resumes redirected, {} gave up (no zone for their region)",
      g.c.redirected, g.c.no_zone, g.c.bad, g.c.timeouts, g.c.refused_full, g.c.refused_address, g.c.resumed,
      g.c.resume_timeouts);
  return 0;
}
