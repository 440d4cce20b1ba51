// net/metrics.h: Prometheus text and a minimal Boost.Beast HTTP server for GET /metrics.
#include <utility>  // before Asio: GCC 12 in C++20 mode needs it first

#include <atomic>
#include <boost/asio.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/http.hpp>
#include <cmath>
#include <cstdio>
#include <mutex>
#include <spdlog/spdlog.h>
#include <thread>

#include "metrics.h"
#include "viewer_route.h"

namespace zone::net {

namespace asio = boost::asio;
namespace beast = boost::beast;
namespace http = beast::http;
using tcp = asio::ip::tcp;

// ---- prometheus_text -------------------------------------------------------------------------

namespace {
std::string number(double v) {
  if (std::isnan(v)) return "NaN";
  if (std::isinf(v)) return v > 0 ? "+Inf" : "-Inf";
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.17g", v);
  return buf;
}
}  // namespace

void prometheus_text::header(std::string_view name, std::string_view help, std::string_view type) {
  if (last_header_ == name) return;  // samples of one metric with different labels share it
  last_header_ = std::string(name);
  out_ += "# HELP ";
  out_ += name;
  out_ += ' ';
  out_ += help;
  out_ += "\n# TYPE ";
  out_ += name;
  out_ += ' ';
  out_ += type;
  out_ += '\n';
}

void prometheus_text::counter(std::string_view name, std::string_view help, double value, std::string_view labels) {
  header(name, help, "counter");
  out_ += name;
  if (!labels.empty()) (out_ += '{') += std::string(labels) + '}';
  out_ += ' ' + number(value) + '\n';
}

void prometheus_text::gauge(std::string_view name, std::string_view help, double value, std::string_view labels) {
  header(name, help, "gauge");
  out_ += name;
  if (!labels.empty()) (out_ += '{') += std::string(labels) + '}';
  out_ += ' ' + number(value) + '\n';
}

void prometheus_text::histogram(std::string_view name, std::string_view help, std::span<const double> upper_bounds,
                                std::span<const std::uint64_t> cumulative, double sum, std::uint64_t count,
                                std::string_view labels) {
  header(name, help, "histogram");
  const std::string sep = labels.empty() ? "" : std::string(labels) + ",";
  for (std::size_t i = 0; i < upper_bounds.size() && i < cumulative.size(); ++i) {
    out_ += std::string(name) + "_bucket{" + sep + "le=\"" + number(upper_bounds[i]) + "\"} " +
            std::to_string(cumulative[i]) + '\n';
  }
  out_ += std::string(name) + "_bucket{" + sep + "le=\"+Inf\"} " + std::to_string(count) + '\n';
  const std::string l = labels.empty() ? "" : "{" + std::string(labels) + "}";
  out_ += std::string(name) + "_sum" + l + ' ' + number(sum) + '\n';
  out_ += std::string(name) + "_count" + l + ' ' + std::to_string(count) + '\n';
}

// ---- metrics_server --------------------------------------------------------------------------

struct metrics_server::impl {
  impl(std::string a, std::uint16_t p, metrics_limits l)
      : address(std::move(a)), requested_port(p), limits(l), acceptor(ctx), retry(ctx) {}

  std::string address;
  std::uint16_t requested_port;
  std::uint16_t bound_port = 0;
  metrics_limits limits;
  // Before ctx: the exchanges it still holds when it is destroyed count themselves out here.
  std::atomic<std::uint64_t> requests{0}, refused{0}, accept_errors{0}, open{0};
  asio::io_context ctx{1};  // one thread: every handler runs there, in turn
  tcp::acceptor acceptor;
  asio::steady_timer retry;  // the pause after an accept error
  std::chrono::steady_clock::time_point last_error_log{};
  std::uint64_t errors_since_log = 0;
  std::thread thread;
  bool running = false;

  std::mutex body_mutex;
  std::shared_ptr<const std::string> body = std::make_shared<const std::string>();
  viewer_server* viewer = nullptr;  ///< attach_viewer

  void do_accept();
};

namespace {

/// One HTTP exchange: read a request, answer, close.
class http_exchange : public std::enable_shared_from_this<http_exchange> {
 public:
  http_exchange(tcp::socket socket, metrics_server::impl& srv) : stream_(std::move(socket)), srv_(srv) { ++srv_.open; }
  ~http_exchange() { --srv_.open; }
  http_exchange(const http_exchange&) = delete;
  http_exchange& operator=(const http_exchange&) = delete;

  void start() {
    stream_.expires_after(srv_.limits.request_timeout);
    http::async_read(stream_, buffer_, request_, [self = shared_from_this()](beast::error_code ec, std::size_t) {
      if (ec) return;  // closed, timed out or malformed: nothing to answer
      self->answer();
    });
  }

 private:
  void answer() {
    if (srv_.viewer != nullptr && is_viewer_target({request_.target().data(), request_.target().size()})) {
      return viewer_handoff(*srv_.viewer, std::move(stream_), std::move(request_));
    }
    ++srv_.requests;
    response_.version(request_.version());
    response_.keep_alive(false);
    response_.set(http::field::server, "zone-server");
    const auto target = request_.target();
    if (request_.method() != http::verb::get) {
      response_.result(http::status::method_not_allowed);
      response_.body() = "only GET\n";
    } else if (target != "/metrics" && !target.starts_with("/metrics?")) {
      response_.result(http::status::not_found);
      response_.body() = "try /metrics\n";
    } else {
      std::shared_ptr<const std::string> body;
      {
        const std::lock_guard lock(srv_.body_mutex);
        body = srv_.body;
      }
      response_.result(http::status::ok);
      response_.set(http::field::content_type, "text/plain; version=0.0.4; charset=utf-8");
      response_.body() = *body;
    }
    response_.prepare_payload();
    http::async_write(stream_, response_, [self = shared_from_this()](beast::error_code, std::size_t) {
      beast::error_code ignored;
      self->stream_.socket().shutdown(tcp::socket::shutdown_send, ignored);
    });
  }

  beast::tcp_stream stream_;
  metrics_server::impl& srv_;
  beast::flat_buffer buffer_{8192};
  http::request<http::string_body> request_;
  http::response<http::string_body> response_;
};

}  // namespace

void metrics_server::impl::do_accept() {
  acceptor.async_accept(ctx, [this](beast::error_code ec, tcp::socket socket) {
    if (ec) {
      if (ec == asio::error::operation_aborted || !acceptor.is_open()) return;
      // Out of descriptors (or another error): pause instead of spinning on it, and say so at
      // most once a second (a full table made ~530,000 lines a second before).
      ++accept_errors;
      ++errors_since_log;
      const auto now = std::chrono::steady_clock::now();
      if (now - last_error_log >= std::chrono::seconds(1)) {
        spdlog::warn("metrics: accept failed: {} ({} failures since the last such line; pausing 50 ms each)", ec.message(),
                     errors_since_log);
        last_error_log = now;
        errors_since_log = 0;
      }
      retry.expires_after(std::chrono::milliseconds(50));
      retry.async_wait([this](const beast::error_code& e) {
        if (!e && acceptor.is_open()) do_accept();
      });
      return;
    }
    if (open.load() >= limits.max_connections) {
      ++refused;  // closed at once: a scraper needs one connection, not hundreds
      beast::error_code ignored;
      socket.close(ignored);
    } else {
      std::make_shared<http_exchange>(std::move(socket), *this)->start();
    }
    do_accept();
  });
}

metrics_server::metrics_server(std::string address, std::uint16_t port, metrics_limits limits)
    : impl_(std::make_unique<impl>(std::move(address), port, limits)) {}

metrics_server::~metrics_server() { stop(); }

std::optional<std::string> metrics_server::start() {
  auto& m = *impl_;
  if (m.running) return "metrics server already started";
  beast::error_code ec;
  const auto address = asio::ip::make_address(m.address, ec);
  if (ec) return "bad metrics address '" + m.address + "': " + ec.message();
  const tcp::endpoint endpoint(address, m.requested_port);
  m.acceptor.open(endpoint.protocol(), ec);
  if (!ec) m.acceptor.set_option(tcp::acceptor::reuse_address(true), ec);
  if (!ec) m.acceptor.bind(endpoint, ec);
  if (!ec) m.acceptor.listen(asio::socket_base::max_listen_connections, ec);
  if (ec) {
    beast::error_code ignored;
    m.acceptor.close(ignored);
    return "cannot listen for metrics on " + m.address + ":" + std::to_string(m.requested_port) + ": " + ec.message();
  }
  m.bound_port = m.acceptor.local_endpoint(ec).port();
  m.do_accept();
  m.thread = std::thread([&m] { m.ctx.run(); });
  m.running = true;
  spdlog::info("metrics on http://{}:{}/metrics", m.address, m.bound_port);
  return std::nullopt;
}

void metrics_server::stop() {
  auto& m = *impl_;
  if (!m.running) return;
  m.running = false;
  asio::post(m.ctx, [&m] {
    beast::error_code ignored;
    m.acceptor.close(ignored);
    m.retry.cancel();
  });
  m.ctx.stop();
  m.thread.join();
}

std::uint16_t metrics_server::port() const { return impl_->bound_port; }

void metrics_server::publish(std::string body) {
  auto shared = std::make_shared<const std::string>(std::move(body));
  const std::lock_guard lock(impl_->body_mutex);
  impl_->body = std::move(shared);
}

std::uint64_t metrics_server::requests() const { return impl_->requests.load(); }
std::uint64_t metrics_server::connections_refused() const { return impl_->refused.load(); }
std::uint64_t metrics_server::accept_errors() const { return impl_->accept_errors.load(); }
std::uint64_t metrics_server::connections_open() const { return impl_->open.load(); }

void metrics_server::attach_viewer(viewer_server* viewer) { impl_->viewer = viewer; }

}  // namespace zone::net
