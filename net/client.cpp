// net/client.h: the Asio client connector (one strand per connection, one write in flight).
#include <utility>  // before Asio: GCC 12 in C++20 mode needs it first

#include <boost/asio.hpp>
#include <deque>
#include <mutex>
#include <thread>

#include "client.h"

namespace zone::net {

namespace asio = boost::asio;
using tcp = asio::ip::tcp;
using steady = std::chrono::steady_clock;

struct client_pool::impl {
  asio::io_context ctx;
  std::optional<asio::executor_work_guard<asio::io_context::executor_type>> work{ctx.get_executor()};
  std::vector<std::thread> threads;
};

client_pool::client_pool(unsigned io_threads) : impl_(std::make_unique<impl>()) {
  for (unsigned i = 0; i < std::max(1u, io_threads); ++i) impl_->threads.emplace_back([this] { impl_->ctx.run(); });
}

client_pool::~client_pool() {
  impl_->work.reset();
  impl_->ctx.stop();
  for (auto& t : impl_->threads) t.join();
}

struct client_connection::impl : std::enable_shared_from_this<client_connection::impl> {
  impl(asio::io_context& ctx, client_options o)
      : opt(std::move(o)), socket(asio::make_strand(ctx)), decoder(opt.inbound), start(steady::now()) {}

  client_options opt;
  tcp::socket socket;  // its executor is the connection's strand
  frame_decoder decoder;
  encoder enc{256};
  std::deque<std::vector<std::uint8_t>> queue;  // front in flight while writing
  bool connected = false;  // nothing is written before the connection (and hello) is up
  bool writing = false;
  bool closed = false;
  std::uint32_t next_sequence = 1;
  steady::time_point start;
  std::optional<client_view> view;

  mutable std::mutex snapshot_mutex;
  client_snapshot snap;  // guarded by snapshot_mutex

  std::uint64_t now_us() const {
    return static_cast<std::uint64_t>(
        std::chrono::duration_cast<std::chrono::microseconds>(steady::now() - start).count());
  }

  template <class F>
  void on_strand(F f) {
    asio::post(socket.get_executor(), [self = shared_from_this(), f = std::move(f)]() mutable { f(*self); });
  }

  void connect() {
    boost::system::error_code ec;
    const auto address = asio::ip::make_address(opt.address, ec);
    if (ec) return close_now("bad address: " + ec.message());
    socket.async_connect(tcp::endpoint(address, opt.port), [self = shared_from_this()](const boost::system::error_code& e) {
      if (e) return self->close_now("connect failed: " + e.message());
      boost::system::error_code ignored;
      self->socket.set_option(tcp::no_delay(true), ignored);
      {
        const std::lock_guard lock(self->snapshot_mutex);
        self->snap.phase = client_snapshot::state::connected;
      }
      // Hello goes first, ahead of anything queued while connecting.
      const auto hello = self->enc.encode(hello_msg{self->opt.name, self->opt.token, protocol_version});
      self->queue.emplace_front(hello.begin(), hello.end());
      self->connected = true;
      self->do_write();
      self->do_read();
    });
  }

  void push(std::vector<std::uint8_t> frame) {
    if (closed) return;
    if (queue.size() >= std::max<std::size_t>(2, opt.max_queued_frames)) {
      queue.erase(queue.begin() + (writing ? 1 : 0));  // drop the oldest not in flight
    }
    queue.push_back(std::move(frame));
    do_write();
  }

  void do_write() {
    if (!connected || writing || queue.empty() || closed) return;
    writing = true;
    asio::async_write(socket, asio::buffer(queue.front()),
                      [self = shared_from_this()](const boost::system::error_code& ec, std::size_t) {
                        self->writing = false;
                        if (ec) {
                          if (ec != asio::error::operation_aborted) self->close_now("write failed: " + ec.message());
                          return;
                        }
                        if (!self->queue.empty()) self->queue.pop_front();
                        self->do_write();
                      });
  }

  void do_read() {
    if (closed) return;
    const auto buf = decoder.prepare(16384);
    socket.async_read_some(asio::buffer(buf.data(), buf.size()),
                           [self = shared_from_this()](const boost::system::error_code& ec, std::size_t n) {
                             self->on_read(ec, n);
                           });
  }

  void on_read(const boost::system::error_code& ec, std::size_t n) {
    if (closed) return;
    if (ec) {
      if (ec == asio::error::operation_aborted) return;
      return close_now(ec == asio::error::eof ? "server closed" : "read failed: " + ec.message());
    }
    decoder.commit(n);
    {
      const std::lock_guard lock(snapshot_mutex);
      snap.bytes_in += n;
    }
    for (;;) {
      const auto step = decoder.next();
      if (step.needs_more()) break;
      if (step.is_error()) return close_now("bad frame from server: " + std::string(to_string(step.error)));
      handle(*step.frame.envelope);
    }
    do_read();
  }

  void handle(const wire::envelope& env) {
    const std::lock_guard lock(snapshot_mutex);
    switch (env.message_type()) {
      case wire::message::welcome: {
        const auto* w = env.message_as_welcome();
        snap.phase = client_snapshot::state::welcomed;
        snap.entity_id = w->entity_id();
        if (const auto* b = w->world()) {
          snap.world = {{b->lo().x(), b->lo().y(), b->lo().z()}, {b->hi().x(), b->hi().y(), b->hi().z()}};
        }
        snap.tick_rate_hz = w->tick_rate_hz();
        view.emplace(snap.world);
        break;
      }
      case wire::message::tick_update: {
        const auto* u = env.message_as_tick_update();
        if (!view) {
          ++snap.problems;  // an update before welcome
          break;
        }
        if (u->reset()) ++snap.resets;
        if (view->apply(*u) != client_view::status::ok) ++snap.problems;
        ++snap.updates;
        snap.digests_checked = view->digests_checked();
        snap.visible = view->size();
        snap.last_tick = u->server_tick();
        snap.last_input_echo = u->last_input_sequence();
        break;
      }
      case wire::message::pong: {
        const auto* p = env.message_as_pong();
        ++snap.pongs;
        snap.last_rtt_ms = static_cast<double>(now_us() - p->client_time_us()) / 1000.0;
        break;
      }
      case wire::message::error: {
        const auto* e = env.message_as_error();
        snap.error = error_msg{e->code(), e->reason() ? e->reason()->str() : std::string()};
        break;
      }
      default:
        ++snap.problems;  // a client-to-server message from the server
        break;
    }
  }

  void close_now(std::string reason) {
    if (closed) return;
    closed = true;
    boost::system::error_code ignored;
    socket.shutdown(tcp::socket::shutdown_both, ignored);
    socket.close(ignored);
    queue.clear();
    const std::lock_guard lock(snapshot_mutex);
    snap.phase = client_snapshot::state::closed;
    snap.close_reason = std::move(reason);
  }
};

client_connection::client_connection(client_pool& pool, client_options opt)
    : impl_(std::make_shared<impl>(pool.get().ctx, std::move(opt))) {}

client_connection::~client_connection() { close(); }

void client_connection::connect() {
  impl_->on_strand([](impl& s) { s.connect(); });
}

void client_connection::send_input(const vec3f& move) {
  impl_->on_strand([move](impl& s) {
    if (s.closed) return;
    const std::uint32_t seq = s.next_sequence++;
    const auto f = s.enc.encode(input_msg{seq, move});
    s.push({f.begin(), f.end()});
    const std::lock_guard lock(s.snapshot_mutex);
    s.snap.inputs_sent = seq;
  });
}

void client_connection::send_ping() {
  impl_->on_strand([](impl& s) {
    const auto f = s.enc.encode(ping_msg{s.now_us()});
    s.push({f.begin(), f.end()});
  });
}

void client_connection::send_raw(std::vector<std::uint8_t> bytes) {
  impl_->on_strand([bytes = std::move(bytes)](impl& s) mutable { s.push(std::move(bytes)); });
}

void client_connection::close() {
  impl_->on_strand([](impl& s) { s.close_now("closed by the client"); });
}

client_snapshot client_connection::snapshot() const {
  const std::lock_guard lock(impl_->snapshot_mutex);
  return impl_->snap;
}

}  // namespace zone::net
