// net/viewer.h: the page, the /viewer/ws sessions (Boost.Beast WebSocket) and the frame encoders.
#include <utility>  // before Asio: GCC 12 in C++20 mode needs it first

#include <algorithm>
#include <atomic>
#include <bit>
#include <cerrno>
#include <boost/asio.hpp>
#include <boost/beast/core.hpp>
#include <boost/beast/http.hpp>
#include <boost/beast/websocket.hpp>
#include <chrono>
#include <cmath>
#include <cstring>
#include <deque>
#include <nlohmann/json.hpp>
#include <optional>
#include <future>
#include <pthread.h>
#include <sched.h>
#include <spdlog/spdlog.h>
#include <sys/resource.h>
#include <thread>
#include <unistd.h>

#include "viewer.h"
#include "viewer_route.h"

namespace zone::net {

namespace asio = boost::asio;
namespace beast = boost::beast;
namespace http = beast::http;
namespace websocket = beast::websocket;
using tcp = asio::ip::tcp;

// ---- wire format ---------------------------------------------------------------------------

namespace {

template <class T>
void put(std::vector<std::uint8_t>& out, T v) {
  static_assert(std::is_trivially_copyable_v<T>);
  const auto at = out.size();
  out.resize(at + sizeof(T));
  std::memcpy(out.data() + at, &v, sizeof(T));  // little-endian hosts only (x86-64, aarch64)
}

template <class T>
T get(std::span<const std::uint8_t> in, std::size_t at) {
  T v;
  std::memcpy(&v, in.data() + at, sizeof(T));
  return v;
}

void put_header(std::vector<std::uint8_t>& out, std::uint8_t type, std::uint16_t grid, const viewer_snapshot& s,
                std::uint32_t count, const viewer_request& r) {
  out.clear();
  put<std::uint8_t>(out, type);
  put<std::uint8_t>(out, 0);
  put<std::uint16_t>(out, grid);
  put<std::uint32_t>(out, static_cast<std::uint32_t>(s.tick));
  put<std::uint32_t>(out, static_cast<std::uint32_t>(s.size()));
  put<std::uint32_t>(out, count);
  put<float>(out, r.x0);
  put<float>(out, r.y0);
  put<float>(out, r.x1);
  put<float>(out, r.y1);
}

/// clamp(round((v - lo) * scale), 0, 65535), rounding half away from zero as std::round, which
/// GCC calls out of line without SSE4.1 (a call per coordinate, 40% of the encoding): clamped
/// first (the same result), the value's integer part and fraction are exact; NaN gives 0.
std::uint16_t quantize(float v, float lo, float scale) {
  float q = (v - lo) * scale;
  q = q > 0.0f ? (q < 65535.0f ? q : 65535.0f) : 0.0f;
  const auto i = static_cast<std::uint32_t>(q);
  return static_cast<std::uint16_t>(i + (q - static_cast<float>(i) >= 0.5f ? 1u : 0u));
}

}  // namespace

std::optional<viewer_request> parse_viewer_request(std::span<const std::uint8_t> bytes) {
  if (bytes.size() != viewer_request_bytes || bytes[0] != viewer_request_type) return std::nullopt;
  if (bytes[1] != 0 || bytes[2] != 0 || bytes[3] != 0) return std::nullopt;
  viewer_request r;
  r.x0 = get<float>(bytes, 4);
  r.y0 = get<float>(bytes, 8);
  r.x1 = get<float>(bytes, 12);
  r.y1 = get<float>(bytes, 16);
  r.selected = get<std::uint32_t>(bytes, 20);
  r.max_points = get<std::uint32_t>(bytes, 24);
  if (r.max_points > viewer_max_points) return std::nullopt;
  for (const float v : {r.x0, r.y0, r.x1, r.y1}) {
    if (!std::isfinite(v) || std::fabs(v) > 1e9f) return std::nullopt;
  }
  if (!(r.x0 < r.x1) || !(r.y0 < r.y1)) return std::nullopt;
  return r;
}

void encode_viewer_view(const viewer_snapshot& s, const viewer_request& r, std::uint32_t grid_cells,
                        std::vector<std::uint8_t>& out) {
  const std::size_t n = s.size();
  const float* xy = s.xy.data();
  const auto in_view = [&](std::size_t i) {
    const float x = xy[2 * i], y = xy[2 * i + 1];
    return (x >= r.x0) & (x <= r.x1) & (y >= r.y0) & (y <= r.y1);  // no branches: the count pass vectorizes
  };
  std::uint32_t inside = 0;
  for (std::size_t i = 0; i < n; ++i) inside += in_view(i) ? 1u : 0u;
  if (inside > r.max_points) {
    // Too many to draw one by one: counts per cell of a grid_cells^2 grid over the viewport.
    const std::uint32_t g = std::clamp<std::uint32_t>(grid_cells, 1, 1024);
    put_header(out, viewer_frame_density, static_cast<std::uint16_t>(g), s, inside, r);
    const std::size_t at = out.size();
    out.resize(at + std::size_t{g} * g * 2, 0);
    auto* counts = out.data() + at;
    const float sx = static_cast<float>(g) / (r.x1 - r.x0), sy = static_cast<float>(g) / (r.y1 - r.y0);
    for (std::size_t i = 0; i < n; ++i) {
      if (!in_view(i)) continue;
      const auto cx = std::min<std::uint32_t>(g - 1, static_cast<std::uint32_t>((xy[2 * i] - r.x0) * sx));
      const auto cy = std::min<std::uint32_t>(g - 1, static_cast<std::uint32_t>((xy[2 * i + 1] - r.y0) * sy));
      auto* cell = counts + (std::size_t{cy} * g + cx) * 2;
      std::uint16_t c;
      std::memcpy(&c, cell, 2);
      if (c != 0xffff) ++c;
      std::memcpy(cell, &c, 2);
    }
    return;
  }
  put_header(out, viewer_frame_entities, 0, s, inside, r);
  const std::size_t at = out.size();
  out.resize(at + std::size_t{inside} * viewer_entity_record_bytes);
  auto* p = out.data() + at;
  const float sx = 65535.0f / (r.x1 - r.x0), sy = 65535.0f / (r.y1 - r.y0);
  for (std::size_t i = 0; i < n; ++i) {
    if (!in_view(i)) continue;
    const std::uint16_t qx = quantize(xy[2 * i], r.x0, sx), qy = quantize(xy[2 * i + 1], r.y0, sy);
    std::memcpy(p, &s.ids[i], 4);
    std::memcpy(p + 4, &qx, 2);
    std::memcpy(p + 6, &qy, 2);
    p[8] = static_cast<std::uint8_t>(std::countr_zero(s.classes[i]));  // the class's bit index (32 for none)
    p[9] = s.kind[i];
    p += viewer_entity_record_bytes;
  }
}

void encode_viewer_selection(const viewer_snapshot& s, const viewer_snapshot::selection& sel, std::vector<std::uint8_t>& out) {
  out.clear();
  put<std::uint8_t>(out, viewer_frame_selection);
  put<std::uint8_t>(out, sel.alive ? 1 : 0);
  put<std::uint8_t>(out, sel.visibility);
  put<std::uint8_t>(out, sel.kind);
  put<std::uint32_t>(out, static_cast<std::uint32_t>(s.tick));
  put<std::uint32_t>(out, sel.id);
  for (const float v : sel.position) put<float>(out, v);
  for (const float v : sel.aoi_half) put<float>(out, v);
  for (const float v : sel.presence_half) put<float>(out, v);
  put<float>(out, sel.hysteresis);
  put<std::uint32_t>(out, sel.sees);
  put<std::uint32_t>(out, static_cast<std::uint32_t>(sel.visible.size()));
  put<std::uint32_t>(out, static_cast<std::uint32_t>(sel.events.size()));
  for (const auto id : sel.visible) put<std::uint32_t>(out, id);
  for (std::size_t k = 0; k < sel.visible.size(); ++k) put<std::uint8_t>(out, k < sel.tier.size() ? sel.tier[k] : 0);
  for (const auto& e : sel.events) {
    put<std::uint32_t>(out, static_cast<std::uint32_t>(e.tick));
    put<std::uint32_t>(out, e.id);
    put<std::uint8_t>(out, e.enter ? 1 : 0);
  }
}

std::string viewer_selection_json(const viewer_snapshot& s, const viewer_snapshot::selection& sel) {
  nlohmann::ordered_json j;
  j["tick"] = s.tick;
  j["id"] = sel.id;
  j["alive"] = sel.alive;
  j["visible"] = sel.visible;
  j["tier"] = sel.tier;
  return j.dump();
}

std::string viewer_stats_json(const viewer_stats& s, std::size_t viewers, std::uint64_t viewer_bytes) {
  std::string j = "{\"type\":\"stats\",\"tick\":" + std::to_string(s.tick);
  const auto field = [&j](const char* name, double v) {
    char buf[64];
    std::snprintf(buf, sizeof buf, ",\"%s\":%.10g", name, v);  // counts exact to 10 digits
    j += buf;
  };
  field("tick_rate", s.tick_rate);
  field("budget_ms", s.budget_ms);
  field("entities", s.entities);
  field("clients", s.clients);
  field("pairs", s.pairs);
  field("candidates", s.candidates);
  field("visible", s.visible);
  field("enters", s.enters);
  field("leaves", s.leaves);
  field("viewers", static_cast<double>(viewers));
  field("viewer_bytes", static_cast<double>(viewer_bytes));
  field("overruns", s.overruns);
  field("byte_budget", s.byte_budget);
  field("update_near", s.update_near);
  field("update_mid", s.update_mid);
  field("tick_p99_ms", s.tick_p99_ms);
  field("interest_p99_ms", s.interest_p99_ms);
  j += ",\"interest_on\":" + nlohmann::json(s.interest_on).dump();
  char world[160];
  std::snprintf(world, sizeof world, ",\"world\":[%.6g,%.6g,%.6g,%.6g]", s.world[0], s.world[1], s.world[2], s.world[3]);
  j += world;
  j += ",\"phases\":[\"inputs\",\"behaviours\",\"integrate\",\"interest\",\"replicate\",\"viewer\"],\"ticks\":[";
  for (std::size_t k = 0; k < s.ticks.size(); ++k) {
    const auto& t = s.ticks[k];
    char buf[256];
    std::snprintf(buf, sizeof buf, "%s[%llu,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f]", k ? "," : "",
                  static_cast<unsigned long long>(t.tick), t.inputs, t.behaviours, t.integrate, t.interest, t.replicate,
                  t.viewer, t.total);
    j += buf;
  }
  j += "]}";
  return j;
}

// ---- the server ------------------------------------------------------------------------------

namespace {

/// Three buffers between one producer and one consumer: the producer fills its own, then swaps it
/// with the middle one (marked fresh) in one atomic exchange; the consumer swaps its own with the
/// middle one when that is fresh. Neither side ever waits for the other.
template <class T>
struct triple_buffer {
  static constexpr std::uint32_t fresh = 4;
  T slot[3];
  std::uint32_t back = 0;                 // the producer's
  std::atomic<std::uint32_t> middle{1};   // index | fresh
  std::uint32_t front = 2;                // the consumer's
  std::uint64_t front_seq = 0;            // the consumer's: how many it has taken (0: none yet)
  std::atomic<std::uint64_t> published{0};

  T& producer() { return slot[back]; }
  void publish() {
    back = middle.exchange(back | fresh, std::memory_order_acq_rel) & 3;
    published.fetch_add(1, std::memory_order_relaxed);
  }
  /// The consumer's: takes the newest if there is a fresher one than its own; true if it did.
  bool take() {
    if ((middle.load(std::memory_order_relaxed) & fresh) == 0) return false;
    front = middle.exchange(front, std::memory_order_acq_rel) & 3;
    ++front_seq;
    return true;
  }
  const T& consumer() const { return slot[front]; }
};

}  // namespace

class ws_session;

struct viewer_server::impl {
  explicit impl(viewer_options o)
      : opt(o), selected(std::make_unique<std::atomic<std::uint32_t>[]>(std::max<std::size_t>(1, o.max_viewers))),
        slot_used(std::max<std::size_t>(1, o.max_viewers), false) {
    for (auto& st : stats.slot) st.ticks.reserve(viewer_stats::max_ticks);
  }
  viewer_options opt;

  // The producer's side (lock-free).
  triple_buffer<viewer_snapshot> snapshots;
  triple_buffer<viewer_stats> stats;
  std::unique_ptr<std::atomic<std::uint32_t>[]> selected;  // one slot per session (0: none)
  std::atomic<std::uint64_t> selection_version{0};
  std::atomic<std::size_t> open{0};
  // When the last snapshot was published and the time between the last two (steady clock, ns):
  // the sessions' timers wake when the next is due (viewer_poll_delay_ns).
  std::atomic<std::int64_t> published_ns{0}, period_ns{0};
  std::int64_t producer_last_ns = 0;  // the producer's own copy

  // The viewer's thread (everything below is touched only there, but the counters).
  std::unique_ptr<asio::io_context> ioc = std::make_unique<asio::io_context>(1);
  std::optional<asio::executor_work_guard<asio::io_context::executor_type>> work;
  std::thread thread;
  thread_priority priority;  // written by the thread before the constructor returns
  std::vector<ws_session*> sessions;
  std::vector<bool> slot_used;
  std::shared_ptr<const std::string> stats_json;
  std::uint64_t stats_seq = 0;

  std::atomic<std::uint64_t> opened{0}, refused{0}, stalled{0}, hostile{0}, frames{0}, bytes{0};

  /// The newest snapshot on the viewer's thread (null before the first), and its number.
  const viewer_snapshot* latest(std::uint64_t* seq) {
    snapshots.take();
    *seq = snapshots.front_seq;
    return snapshots.front_seq == 0 ? nullptr : &snapshots.consumer();
  }
  /// The newest stats message on the viewer's thread, formatted once when it is new.
  void refresh_stats() {
    if (!stats.take()) return;
    stats_json = std::make_shared<const std::string>(
        viewer_stats_json(stats.consumer(), open.load(std::memory_order_relaxed), bytes.load(std::memory_order_relaxed)));
    ++stats_seq;
  }
};

namespace {

using clock_type = std::chrono::steady_clock;

/// One plain HTTP answer on a handed-over connection, then close.
class http_reply : public std::enable_shared_from_this<http_reply> {
 public:
  http_reply(beast::tcp_stream stream, unsigned version, http::status status, std::string content_type, std::string body)
      : stream_(std::move(stream)) {
    response_.version(version);
    response_.keep_alive(false);
    response_.result(status);
    response_.set(http::field::server, "zone-server");
    response_.set(http::field::content_type, content_type);
    response_.set(http::field::cache_control, "no-store");
    response_.body() = std::move(body);
    response_.prepare_payload();
  }
  void start() {
    stream_.expires_after(std::chrono::seconds(5));
    http::async_write(stream_, response_, [self = shared_from_this()](beast::error_code, std::size_t) {
      beast::error_code ignored;
      self->stream_.socket().shutdown(tcp::socket::shutdown_send, ignored);
    });
  }

 private:
  beast::tcp_stream stream_;
  http::response<http::string_body> response_;
};

}  // namespace

/// One page's WebSocket: reads view requests, writes the newest snapshot's frames, one write in flight.
class ws_session : public std::enable_shared_from_this<ws_session> {
 public:
  /// `slot`: this session's selection slot in `srv` (free; the session frees it when it ends).
  ws_session(beast::tcp_stream stream, std::shared_ptr<viewer_server::impl> srv, std::size_t slot)
      : ws_(std::move(stream)), srv_(std::move(srv)), timer_(ws_.get_executor()), slot_(slot) {}

  // On the viewer's thread (or in ~viewer_server, once that thread has ended).
  ~ws_session() {
    auto& s = srv_->sessions;
    s.erase(std::remove(s.begin(), s.end(), this), s.end());
    srv_->slot_used[slot_] = false;
    srv_->selected[slot_].store(0, std::memory_order_relaxed);
    srv_->selection_version.fetch_add(1, std::memory_order_release);
    srv_->open.store(s.size(), std::memory_order_relaxed);
  }

  void start(http::request<http::string_body> request) {
    beast::get_lowest_layer(ws_).expires_never();
    websocket::stream_base::timeout t;
    t.handshake_timeout = std::chrono::seconds(5);
    t.idle_timeout = std::chrono::seconds(20);  // a ping after 10 s of silence; no answer: closed
    t.keep_alive_pings = true;
    ws_.set_option(t);
    ws_.read_message_max(64);  // a view request is 28 bytes; anything larger closes the session
    ws_.binary(true);
    // One frame per message, written at once (Beast's default splits a message into 4 KB frames,
    // one write each: a 200 KB entities frame took 50 writes). The page sees the same messages.
    ws_.auto_fragment(false);
    ws_.async_accept(request, [self = shared_from_this()](beast::error_code ec) {
      if (ec) return;
      self->last_refill_ = clock_type::now();
      self->tokens_ = self->srv_->opt.max_requests_per_s;
      self->read();
      self->arm_timer();
    });
  }

 private:
  void read() {
    ws_.async_read(in_, [self = shared_from_this()](beast::error_code ec, std::size_t) { self->on_read(ec); });
  }

  void on_read(beast::error_code ec) {
    if (ec) {
      // A WebSocket protocol violation (a message over read_message_max, a text message that is
      // not UTF-8, a bad frame) is hostile; a close or a socket error is not.
      const beast::error_code closed = websocket::error::closed;
      const bool violation = ec.category() == closed.category() && ec != closed;
      return close(violation ? &srv_->hostile : nullptr);
    }
    const auto data = in_.cdata();
    const std::span<const std::uint8_t> bytes(static_cast<const std::uint8_t*>(data.data()), data.size());
    const auto request = ws_.got_binary() ? parse_viewer_request(bytes) : std::nullopt;
    in_.consume(in_.size());
    // A token bucket: a page sends a request when its view changes (a few a second while panning).
    const auto now = clock_type::now();
    const double rate = srv_->opt.max_requests_per_s;
    tokens_ = std::min(rate, tokens_ + rate * std::chrono::duration<double>(now - last_refill_).count());
    last_refill_ = now;
    if (!request || tokens_ < 1) return close(&srv_->hostile);
    tokens_ -= 1;
    request_ = *request;
    if (srv_->selected[slot_].exchange(request->selected, std::memory_order_relaxed) != request->selected) {
      srv_->selection_version.fetch_add(1, std::memory_order_release);
    }
    sent_snapshot_ = 0;  // the new view gets the newest snapshot at once
    pump();
    read();
  }

  void arm_timer() {
    const std::int64_t now = std::chrono::duration_cast<std::chrono::nanoseconds>(clock_type::now().time_since_epoch()).count();
    timer_.expires_after(std::chrono::nanoseconds(viewer_poll_delay_ns(
        now, srv_->published_ns.load(std::memory_order_relaxed), srv_->period_ns.load(std::memory_order_relaxed))));
    timer_.async_wait([self = shared_from_this()](beast::error_code ec) {
      if (ec || self->closed_) return;
      if (self->writing_ && clock_type::now() - self->write_started_ >
                                std::chrono::duration<double>(self->srv_->opt.stall_close_s)) {
        return self->close(&self->srv_->stalled);
      }
      self->pump();
      self->arm_timer();
    });
  }

  /// Starts the next write: the queued frames, else the newest snapshot's and stats if new.
  void pump() {
    if (writing_ || closed_) return;
    if (queue_.empty()) fill_queue();
    if (queue_.empty()) return;
    current_ = std::move(queue_.front());
    queue_.pop_front();
    writing_ = true;
    write_started_ = clock_type::now();
    ws_.binary(!current_.text);
    ws_.async_write(asio::buffer(current_.bytes), [self = shared_from_this()](beast::error_code ec, std::size_t n) {
      self->writing_ = false;
      if (ec) return self->close(nullptr);
      self->srv_->frames.fetch_add(1, std::memory_order_relaxed);
      self->srv_->bytes.fetch_add(n, std::memory_order_relaxed);
      self->spare_.push_back(std::move(self->current_.bytes));
      self->pump();
    });
  }

  void fill_queue() {
    std::uint64_t snap_seq = 0;
    const viewer_snapshot* snap = srv_->latest(&snap_seq);  // stable until this thread takes a newer one
    srv_->refresh_stats();
    if (srv_->stats_json && srv_->stats_seq != sent_stats_) {
      sent_stats_ = srv_->stats_seq;
      queue_.push_back({std::vector<std::uint8_t>(srv_->stats_json->begin(), srv_->stats_json->end()), true});
    }
    if (!snap || !request_ || snap_seq == sent_snapshot_) return;
    sent_snapshot_ = snap_seq;
    queue_.push_back({take_spare(), false});
    encode_viewer_view(*snap, *request_, srv_->opt.grid_cells, queue_.back().bytes);
    if (request_->selected != 0) {
      for (const auto& sel : snap->selections) {
        if (sel.id != request_->selected) continue;
        queue_.push_back({take_spare(), false});
        encode_viewer_selection(*snap, sel, queue_.back().bytes);
      }
    }
  }

  std::vector<std::uint8_t> take_spare() {
    if (spare_.empty()) return {};
    auto v = std::move(spare_.back());
    spare_.pop_back();
    return v;
  }

  void close(std::atomic<std::uint64_t>* reason) {
    if (closed_) return;
    closed_ = true;
    if (reason) reason->fetch_add(1, std::memory_order_relaxed);
    timer_.cancel();
    beast::error_code ignored;
    beast::get_lowest_layer(ws_).socket().shutdown(tcp::socket::shutdown_both, ignored);
    beast::get_lowest_layer(ws_).socket().close(ignored);
  }

  struct frame {
    std::vector<std::uint8_t> bytes;
    bool text = false;
  };
  websocket::stream<beast::tcp_stream> ws_;
  std::shared_ptr<viewer_server::impl> srv_;
  asio::steady_timer timer_;
  beast::flat_buffer in_;
  std::optional<viewer_request> request_;
  std::size_t slot_ = 0;
  std::uint64_t sent_snapshot_ = 0, sent_stats_ = 0;
  std::deque<frame> queue_;
  std::vector<std::vector<std::uint8_t>> spare_;
  frame current_;
  bool writing_ = false, closed_ = false;
  clock_type::time_point write_started_{}, last_refill_{};
  double tokens_ = 0;
};

viewer_server::viewer_server(viewer_options opt) : impl_(std::make_shared<impl>(opt)) {
  auto& m = *impl_;
  m.work.emplace(m.ioc->get_executor());
  std::promise<thread_priority> applied;
  auto got = applied.get_future();
  m.thread = std::thread([&m, applied = std::move(applied)]() mutable {
    pthread_setname_np(pthread_self(), "zone-viewer");  // per-thread CPU readings (top -H, /proc/<pid>/task/*/comm)
    // Below the tick's threads: nice 19 and SCHED_IDLE (lower_thread_priority), so that the
    // tick's threads take a core back from an encode or a write at once and are woken onto a
    // core that runs only this thread as if it were idle.
    applied.set_value(lower_thread_priority(m.opt.idle, m.opt.nice));
    m.ioc->run();
  });
  m.priority = got.get();
}

viewer_server::~viewer_server() {
  auto& m = *impl_;
  m.work.reset();
  m.ioc->stop();
  if (m.thread.joinable()) m.thread.join();
  m.ioc.reset();  // destroys the sessions' pending handlers, and so the sessions
}

std::size_t viewer_server::viewers() const { return impl_->open.load(std::memory_order_relaxed); }

std::uint64_t viewer_server::selection_version() const {
  return impl_->selection_version.load(std::memory_order_acquire);
}

std::vector<std::uint32_t> viewer_server::selected() const {
  std::vector<std::uint32_t> ids;
  for (std::size_t k = 0; k < impl_->slot_used.size(); ++k) {
    if (const auto id = impl_->selected[k].load(std::memory_order_relaxed); id != 0) ids.push_back(id);
  }
  std::sort(ids.begin(), ids.end());
  ids.erase(std::unique(ids.begin(), ids.end()), ids.end());
  return ids;
}

viewer_snapshot& viewer_server::next_snapshot() { return impl_->snapshots.producer(); }
void viewer_server::publish() {
  auto& m = *impl_;
  m.snapshots.publish();
  // Two relaxed stores (the clock is the vDSO's: no system call): when the sessions look next.
  const std::int64_t now = std::chrono::duration_cast<std::chrono::nanoseconds>(clock_type::now().time_since_epoch()).count();
  if (m.producer_last_ns != 0) m.period_ns.store(now - m.producer_last_ns, std::memory_order_relaxed);
  m.producer_last_ns = now;
  m.published_ns.store(now, std::memory_order_relaxed);
}

std::int64_t viewer_poll_delay_ns(std::int64_t now_ns, std::int64_t last_ns, std::int64_t period_ns) {
  constexpr std::int64_t ms = 1'000'000, idle = 50 * ms, late = 10 * ms, after = ms / 5;
  if (last_ns <= 0 || period_ns <= 0 || period_ns > 1000 * ms) return idle;
  const std::int64_t due = last_ns + period_ns;
  if (now_ns < due) return std::min(idle, due - now_ns + after);
  if (now_ns - due <= late) return ms;
  return idle;
}

viewer_stats& viewer_server::next_stats() { return impl_->stats.producer(); }
void viewer_server::publish_stats() {
  impl_->stats.publish();
  impl_->stats.producer().ticks.clear();
}

thread_priority viewer_server::thread_info() const { return impl_->priority; }

thread_priority lower_thread_priority(bool idle, int nice, int (*set_idle)()) {
  thread_priority r;
  r.tid = static_cast<long>(::gettid());
  static std::atomic<bool> logged{false};
  const auto once = [](const char* what, int err) {
    if (!logged.exchange(true)) spdlog::info("background thread priority: {} refused ({}); running without it", what, std::strerror(err));
  };
  // Linux: a thread's own nice value (PRIO_PROCESS with a thread id); raising it needs no privilege.
  if (nice > 0 && ::setpriority(PRIO_PROCESS, static_cast<id_t>(r.tid), nice) != 0) once("nice", errno);
  if (idle) {
    const int rc = set_idle ? set_idle() : [] {
      const sched_param p{};
      return ::sched_setscheduler(0, SCHED_IDLE, &p);  // 0: the calling thread
    }();
    if (rc != 0) {
      r.idle_refused = true;
      once("SCHED_IDLE", errno);
    }
  }
  errno = 0;
  r.nice = ::getpriority(PRIO_PROCESS, static_cast<id_t>(r.tid));
  r.idle = ::sched_getscheduler(0) == SCHED_IDLE;
  return r;
}

viewer_server::counters viewer_server::stats() const {
  const auto& m = *impl_;
  return {m.opened.load(), m.refused.load(), m.stalled.load(), m.hostile.load(), m.frames.load(), m.bytes.load(),
          m.snapshots.published.load()};
}

// ---- the routes (viewer_route.h) -------------------------------------------------------------

bool is_viewer_target(std::string_view target) {
  return target == "/viewer" || target.starts_with("/viewer/") || target.starts_with("/viewer?");
}

namespace {

/// Answers a /viewer request on the viewer's thread (the connection already moved there).
void viewer_answer(const std::shared_ptr<viewer_server::impl>& srv, beast::tcp_stream stream,
                   http::request<http::string_body> request, const tcp::endpoint& peer) {
  auto& m = *srv;
  const auto reply = [&](http::status status, std::string type, std::string body) {
    std::make_shared<http_reply>(std::move(stream), request.version(), status, std::move(type), std::move(body))->start();
  };
  if (!m.opt.allow_remote && !peer.address().is_loopback()) {
    return reply(http::status::forbidden, "text/plain", "the viewer serves loopback peers only (zone-server --viewer-remote 1)\n");
  }
  if (request.method() != http::verb::get) return reply(http::status::method_not_allowed, "text/plain", "only GET\n");
  std::string_view target(request.target().data(), request.target().size());
  std::string_view query;
  if (const auto q = target.find('?'); q != std::string_view::npos) {
    query = target.substr(q + 1);
    target = target.substr(0, q);
  }
  if (target == "/viewer" || target == "/viewer/") {
    return reply(http::status::ok, "text/html; charset=utf-8", std::string(viewer_page()));
  }
  if (target == "/viewer/entity.json") {
    std::uint32_t id = 0;
    if (query.starts_with("id=")) {
      for (const char c : query.substr(3)) {
        if (c < '0' || c > '9' || id > 400'000'000u) {
          id = 0;
          break;
        }
        id = id * 10 + static_cast<std::uint32_t>(c - '0');
      }
    }
    if (id == 0) return reply(http::status::bad_request, "text/plain", "usage: /viewer/entity.json?id=N\n");
    std::uint64_t seq = 0;
    if (const viewer_snapshot* snap = m.latest(&seq)) {
      for (const auto& sel : snap->selections) {
        if (sel.id == id) return reply(http::status::ok, "application/json", viewer_selection_json(*snap, sel));
      }
    }
    return reply(http::status::not_found, "text/plain", "entity not selected by any viewer in the latest snapshot\n");
  }
  if (target == "/viewer/ws") {
    if (!websocket::is_upgrade(request)) return reply(http::status::bad_request, "text/plain", "a WebSocket upgrade\n");
    const auto free = std::find(m.slot_used.begin(), m.slot_used.end(), false);
    if (m.sessions.size() >= m.opt.max_viewers || free == m.slot_used.end()) {
      m.refused.fetch_add(1, std::memory_order_relaxed);
      return reply(http::status::service_unavailable, "text/plain", "too many viewers\n");
    }
    const auto slot = static_cast<std::size_t>(free - m.slot_used.begin());
    m.slot_used[slot] = true;
    auto session = std::make_shared<ws_session>(std::move(stream), srv, slot);
    m.sessions.push_back(session.get());
    m.open.store(m.sessions.size(), std::memory_order_relaxed);
    m.opened.fetch_add(1, std::memory_order_relaxed);
    spdlog::info("viewer: page connected from {}", peer.address().to_string());
    session->start(std::move(request));
    return;
  }
  return reply(http::status::not_found, "text/plain", "try /viewer\n");
}

}  // namespace

void viewer_handoff(viewer_server& viewer, beast::tcp_stream stream, http::request<http::string_body> request) {
  // The connection moves onto the viewer's own thread (its io_context): the page, the JSON and
  // every session's reads, encodes and writes run there, never on the HTTP server's thread.
  auto srv = viewer.shared_impl();
  beast::error_code ec;
  auto& from = stream.socket();
  const auto peer = from.remote_endpoint(ec);
  if (ec) return;
  const auto protocol = from.local_endpoint(ec).protocol();
  if (ec) return;
  const auto fd = from.release(ec);
  if (ec) return;
  tcp::socket to(*srv->ioc);
  to.assign(protocol, fd, ec);
  if (ec) {
    ::close(fd);
    return;
  }
  asio::post(*srv->ioc, [srv, s = beast::tcp_stream(std::move(to)), r = std::move(request), peer]() mutable {
    viewer_answer(srv, std::move(s), std::move(r), peer);
  });
}

}  // namespace zone::net
