// Boost.Asio implementation of net/server.h: an acceptor, one session per socket, one write in
// flight per session (gathering what is queued), a bounded outbound queue that drops state for a
// slow client until a reset (outbound_queue.h), per-session input rate limits and idle timeouts,
// and a mutex-guarded event list that the game thread drains with poll().
//
// Threads: one io_context per I/O thread (an "I/O lane"); each session is bound to one lane, so
// its handlers run on that thread only, one at a time (no strand needed). The write side of a
// session (its outbound queue, the partial write, whether it waits for the socket) is guarded by
// the session's own write lock, and every write is one non-blocking sendmsg made under it: so one
// write at a time per session, in queue order, whichever thread makes it. The hand-off from the
// game's threads (send): the frame goes through the outbound queue's policy under that lock; with
// direct writes (off by default) the sending thread then writes it at once unless the session waits
// for its socket (EAGAIN or a partial write: the lane arms a writable wait and finishes the queue,
// gathered). Without, a session that was idle is appended to its lane's ready list, and a ready
// list that was empty posts one drain to the lane, which writes each ready session's queue with
// one gathered write, a slice of sessions at a time; an idle session made ready by a control frame
// (a welcome) is written at the start of the next slice. With io_uring
// (server_options::batching) a drain prepares the writes of every ready session and submits them
// together; each completion is handled as a sendmsg's return.
#include <utility>  // before Asio: GCC 12 in C++20 mode needs it first

#include <arpa/inet.h>
#include <netinet/in.h>
#include <pthread.h>
#include <spdlog/spdlog.h>
#include <sys/ioctl.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <sys/uio.h>
#include <unistd.h>
#include <array>
#include <atomic>
#include <boost/asio.hpp>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <deque>
#include <iterator>
#include <list>
#include <mutex>
#include <shared_mutex>
#include <stdexcept>
#include <thread>
#include <type_traits>
#include <unordered_map>

#if ZONE_HAVE_LIBURING
#include <liburing.h>
#endif

#include "os_limits.h"
#include "outbound_queue.h"
#include "server.h"

namespace zone::net {

namespace asio = boost::asio;
using tcp = asio::ip::tcp;
using steady = std::chrono::steady_clock;

shared_frame make_shared_frame(std::span<const std::uint8_t> frame) {
  // One allocation for the count and the bytes (not a control block plus a vector and its buffer).
  auto bytes = std::make_shared_for_overwrite<std::uint8_t[]>(std::max<std::size_t>(1, frame.size()));
  if (!frame.empty()) std::memcpy(bytes.get(), frame.data(), frame.size());
  shared_frame f;
  f.bytes_ = std::move(bytes);
  f.size_ = frame.size();
  return f;
}

namespace {
/// `bytes` bytes, 8-byte aligned, in one allocation with their reference count.
std::shared_ptr<std::uint8_t[]> aligned_bytes(std::size_t bytes) {
  auto words = std::make_shared_for_overwrite<std::uint64_t[]>(std::max<std::size_t>(1, (bytes + 7) / 8));
  return std::shared_ptr<std::uint8_t[]>(words, reinterpret_cast<std::uint8_t*>(words.get()));
}
}  // namespace

frame_arena::frame_arena(std::size_t block_bytes) : block_bytes_(std::max<std::size_t>(64, (block_bytes + 7) & ~std::size_t{7})) {
  spare_.reserve(max_spare);
}

void frame_arena::next_block() {
  std::shared_ptr<std::uint8_t[]> old = std::move(block_);
  used_ = 0;
  for (auto& b : spare_) {
    // Only the arena holds it: no frame of it is left, and none can be made but by this arena.
    // The acquire fence pairs with the release of the last frame's count (that thread's reads of
    // the bytes, the socket write, happen before this thread writes them again).
    if (b.use_count() == 1) {
      std::atomic_thread_fence(std::memory_order_acquire);
      block_ = std::move(b);
      b = std::move(old);  // the block just filled takes its place (none: an empty slot)
      if (!b) {
        b = std::move(spare_.back());
        spare_.pop_back();
      }
      ++reused_;
      return;
    }
  }
  if (old) {
    if (spare_.size() < max_spare) {
      spare_.push_back(std::move(old));
    } else {
      // Frames hold every spare block (slow clients): let go of one in turn (its last frame frees it).
      spare_[spare_head_] = std::move(old);
      spare_head_ = (spare_head_ + 1) % max_spare;
    }
  }
  block_ = aligned_bytes(block_bytes_);
  ++blocks_;
}

std::span<std::uint8_t> frame_arena::reserve(std::size_t bytes) {
  own_.reset();
  if (bytes > block_bytes_ / 4) {
    own_ = aligned_bytes(bytes);
    ++large_;
    reserved_ = own_.get();
  } else {
    if (!block_ || used_ + bytes > block_bytes_) next_block();
    reserved_ = block_.get() + used_;
  }
  reserved_bytes_ = bytes;
  return {reserved_, bytes};
}

shared_frame frame_arena::commit(std::size_t bytes) {
  if (reserved_ == nullptr || bytes > reserved_bytes_) throw std::logic_error("frame_arena::commit: no reservation of that size");
  shared_frame f;
  if (own_) {
    f.bytes_ = std::move(own_);
  } else {
    f.bytes_ = std::shared_ptr<const std::uint8_t[]>(block_, reserved_);  // shares the block's count
    used_ += (bytes + 15) & ~std::size_t{15};  // frames at 16-byte offsets in the block
  }
  f.size_ = bytes;
  reserved_ = nullptr;
  reserved_bytes_ = 0;
  return f;
}

shared_frame frame_arena::make(std::span<const std::uint8_t> frame) {
  const auto room = reserve(frame.size());
  if (!frame.empty()) std::memcpy(room.data(), frame.data(), frame.size());
  return commit(frame.size());
}

namespace {

struct atomic_counters {
  std::atomic<std::uint64_t> connections_accepted{0}, connections_refused{0}, sessions_open{0}, frames_in{0},
      bytes_in{0}, frames_dropped{0}, resyncs_requested{0}, stale_drops{0}, frames_rejected{0}, inputs_dropped{0}, pings_answered{0},
      pending_open{0}, pending_evicted_address{0}, pending_evicted{0}, hello_timeouts{0}, hellos_rejected{0}, idle_timeouts{0},
      rate_limited{0}, pings_dropped{0}, connections_rate_limited{0}, connections_charged{0}, pending_spared{0};
};

/// A source address as the reconnect-churn limit keys it: an IPv4 address (also when mapped into
/// IPv6), or an IPv6 address's /64 (one host's or one subscriber's usual allocation).
struct address_key {
  std::uint64_t hi = 0, lo = 0;
  bool operator==(const address_key&) const = default;
};
struct address_key_hash {
  std::size_t operator()(const address_key& k) const {
    return static_cast<std::size_t>((k.hi ^ (k.lo * 0x9E3779B97F4A7C15ull)) * 0xBF58476D1CE4E5B9ull >> 16);
  }
};
address_key key_of(const asio::ip::address& a) {
  if (a.is_v4()) return {0, a.to_v4().to_uint()};
  const auto v6 = a.to_v6();
  if (v6.is_v4_mapped()) return {0, asio::ip::make_address_v4(asio::ip::v4_mapped, v6).to_uint()};
  const auto b = v6.to_bytes();
  address_key k;
  std::memcpy(&k.hi, b.data(), sizeof k.hi);
  k.lo = std::uint64_t{1} << 40;  // apart from every IPv4 key
  return k;
}

address_key key_of(const sockaddr_storage& a) {
  if (a.ss_family == AF_INET) return {0, ntohl(reinterpret_cast<const sockaddr_in&>(a).sin_addr.s_addr)};
  const auto& in6 = reinterpret_cast<const sockaddr_in6&>(a).sin6_addr;
  asio::ip::address_v6::bytes_type b;
  std::memcpy(b.data(), &in6, b.size());
  return key_of(asio::ip::address(asio::ip::address_v6(b)));
}

/// An address's reconnect churn (server_options::connect_rate): tokens, in debt down to a minute
/// of refill.
struct churn_bucket {
  double tokens = 0;
  std::chrono::steady_clock::time_point last;
};
/// Most addresses tracked at once (full buckets are dropped; about 64 bytes each).
constexpr std::size_t max_churn_addresses = std::size_t{1} << 16;
/// Connections refused at accept that are held (server_options::connect_refusal_hold): at most
/// this many per address (a newer one releases the address's oldest) and in all (beyond it a
/// refusal is answered at once).
constexpr std::size_t max_held_per_address = 64;
constexpr std::size_t max_held = 512;
/// At most one summary line of refusals at accept this often.
constexpr std::chrono::seconds refusal_log_interval{10};

/// A token bucket (one per message kind and session; the session's lane only).
struct token_bucket {
  double tokens;
  std::chrono::steady_clock::time_point last;
  explicit token_bucket(double burst) : tokens(burst), last(std::chrono::steady_clock::now()) {}
  /// Takes a token if one is there (refilled at `rate` per second up to `burst`).
  bool take(double rate, double burst) {
    const auto now = std::chrono::steady_clock::now();
    tokens = std::min(burst, tokens + std::chrono::duration<double>(now - last).count() * rate);
    last = now;
    if (tokens < 1.0) return false;
    tokens -= 1.0;
    return true;
  }
};

/// The write counters, striped by thread: every sending thread counts each frame it writes, and
/// one shared cache line for all of them would bounce between the workers' cores.
struct alignas(64) write_counters {
  std::atomic<std::uint64_t> frames_out{0}, writes{0}, bytes_out{0};
};
constexpr std::size_t write_counter_stripes = 16;
std::size_t write_counter_stripe() {
  static std::atomic<std::size_t> next{0};
  thread_local const std::size_t stripe = next.fetch_add(1, std::memory_order_relaxed) % write_counter_stripes;
  return stripe;
}

constexpr std::size_t read_chunk_bytes = 4096;
/// How long a closing session may take to flush its final error frame before it is cut.
constexpr std::chrono::milliseconds close_grace{1000};
/// Most connections taken from the backlog per accept completion.
constexpr std::size_t accept_batch = 256;
/// Most frames one gathered write takes (also at most the queue bound - 1; outbound_queue.h).
constexpr std::size_t max_gather_frames = 64;
static_assert(max_gather_frames <= IOV_MAX);
/// Most session writes in one io_uring submission (the ring's size).
constexpr unsigned ring_entries = 256;

}  // namespace

const char* to_string(write_batching b) {
  switch (b) {
    case write_batching::automatic: return "auto";
    case write_batching::uring: return "io_uring";
    case write_batching::sendmsg: return "sendmsg";
  }
  return "?";
}

std::optional<write_batching> parse_write_batching(std::string_view s) {
  if (s == "auto") return write_batching::automatic;
  if (s == "io_uring" || s == "uring") return write_batching::uring;
  if (s == "sendmsg") return write_batching::sendmsg;
  return std::nullopt;
}

class session;

/// One I/O thread with its own event loop, and the sessions bound to it that have frames waiting
/// for it to write (the ready list; without direct writes). Any thread appends; the lane's thread
/// drains.
struct io_lane {
  io_lane(std::atomic<std::uint64_t>& batches, std::atomic<std::uint64_t>& registered)
      : write_batches(batches), registered_sends(registered) {}
  ~io_lane();
  io_lane(const io_lane&) = delete;
  io_lane& operator=(const io_lane&) = delete;

  asio::io_context ctx{1};
  std::optional<asio::executor_work_guard<asio::io_context::executor_type>> work;
  std::thread thread;
  std::mutex ready_mutex;
  std::vector<std::shared_ptr<session>> ready;     // guarded by ready_mutex
  bool drain_posted = false;                       // guarded by ready_mutex
  std::vector<std::shared_ptr<session>> draining;  // the lane's thread only: this round's sessions
  std::size_t drained = 0;                         // the lane's thread only: of them, written so far
  std::size_t drain_slice = 256;                   // sessions a drain writes before the lane's other work
  /// The lane's thread: sessions whose batched write completed with more queued behind it; the
  /// next drain writes them again (they stay marked as on the ready list).
  std::vector<std::shared_ptr<session>> again;
  /// Sessions that became ready with a control frame sent by server::send (a welcome; a redirect
  /// or an error to a session with nothing else queued): each drain writes up to a slice of them
  /// before its slice, so they wait for a slice, not for the rest of a round (tens of
  /// milliseconds on a busy lane). A session already on a list stays there. Guarded by
  /// ready_mutex; `urgent_now` is the lane's.
  std::vector<std::shared_ptr<session>> urgent;
  std::vector<std::shared_ptr<session>> urgent_now;

  // io_uring (server_options::batching): the ring and, per submission slot, the session whose
  // write it carries, its gathered buffers and its msghdr (valid until the completion).
#if ZONE_HAVE_LIBURING
  io_uring ring{};
#endif
  bool ring_ok = false;    // the lane writes through the ring
  bool ring_live = false;  // the ring exists (until drop_ring; ring_ok may have gone false before)
  std::atomic<std::uint64_t>& write_batches;
  std::atomic<std::uint64_t>& registered_sends;
  std::vector<std::shared_ptr<session>> slots;
  std::vector<std::array<iovec, max_gather_frames>> slot_iov;
  std::vector<msghdr> slot_msg;
  // The ring's table of registered files (server_options::ring_file_slots; the lane's thread):
  // a session's socket takes a slot at its first write through the ring and gives it back as it
  // closes, so its sends skip the kernel's lookup of the descriptor's file.
  unsigned file_slots = 0;       // the table's size (0: no table)
  unsigned file_slots_used = 0;  // slots handed out so far (then the free list)
  std::vector<unsigned> free_file_slots;

  /// Sets up the ring and its table of `file_slot_count` registered files (none where the kernel
  /// refuses one); the reason when the ring cannot be (then the lane writes with sendmsg).
  std::optional<std::string> init_ring(unsigned file_slot_count);
  /// Before the lane runs: back to sendmsg.
  void drop_ring();
  /// The lane's thread: a slot of the table holding `fd`, or -1 (no table, all taken, refused).
  int register_file(int fd);
  /// The lane's thread: slot `slot` (from register_file) empty again and free. Before the
  /// descriptor closes: the table holds a reference to the socket, which stays open while it does.
  void unregister_file(int slot);
  /// Any thread: `s` has frames for the lane to write (once until the lane has taken it); with
  /// `urgent` (a control frame made it ready) ahead of the round's other sessions.
  void schedule(std::shared_ptr<session> s, bool urgent = false);
  /// schedule() for several sessions of this lane under one lock (moves them out).
  void schedule_many(std::span<std::shared_ptr<session>> sessions);
  /// Any thread: `sessions` moved onto `list` (ready or urgent) under the lock, and a drain posted
  /// unless one is.
  void append(std::vector<std::shared_ptr<session>>& list, std::span<std::shared_ptr<session>> sessions);
  /// The lane's thread: the ready sessions write what they have queued, `drain_slice` of them at
  /// a time: after each slice the drain posts itself behind the lane's other handlers (reads,
  /// accepts, timers), which so wait for one slice, not for a round of every ready session. What
  /// becomes ready meanwhile gets one more round, posted by the drain itself, so the senders of a
  /// burst do not post (nor wake the lane) once per chunk; urgent sessions are written first, at
  /// the start of the next slice.
  void drain();
  /// The lane's thread: draining[begin, end) written through the ring, ring_entries sessions a
  /// submission.
  void write_batched(std::size_t begin, std::size_t end);
  /// After the lane's thread stopped: what its rounds still hold let go.
  void forget_ready();
  /// Submits the prepared slots [0, n), waits for their completions and hands each to its session.
  void submit_slots(unsigned n);
};

struct server::impl {
  explicit impl(server_options o)
      : opt(std::move(o)),
        lanes(make_lanes(opt.io_threads, write_batches, registered_sends)),
        acceptor(lanes[0]->ctx),
        accept_retry(acceptor.get_executor()),
        refusal_frame(encode_frame(
            error_msg{error_code::rate_limited, "too many short connections from this address: try again later"})),
        held_timer(acceptor.get_executor()) {}

  static std::vector<std::unique_ptr<io_lane>> make_lanes(unsigned n, std::atomic<std::uint64_t>& batches,
                                                          std::atomic<std::uint64_t>& registered) {
    std::vector<std::unique_ptr<io_lane>> v;
    for (unsigned i = 0; i < std::max(1u, n); ++i) v.push_back(std::make_unique<io_lane>(batches, registered));
    return v;
  }
  /// The lane of the next session (round robin; the acceptor's thread only).
  io_lane& next_lane() { return *lanes[next_lane_index++ % lanes.size()]; }

  server_options opt;
  std::atomic<std::uint64_t> write_batches{0};  // io_uring submissions (before the lanes: they count into it)
  std::atomic<std::uint64_t> registered_sends{0};  // of their sends, those naming a registered file
  bool uring = false;                           // the lanes write through io_uring
  std::vector<std::unique_ptr<io_lane>> lanes;
  std::size_t next_lane_index = 0;
  tcp::acceptor acceptor;  // on lane 0
  asio::steady_timer accept_retry;  // on the acceptor's thread (lane 0): a pause after an accept error
  std::uint64_t file_limit = 0;     // the open-file limit after start() raised it
  steady::time_point last_accept_warning{};
  bool running = false;
  std::uint16_t bound_port = 0;

  /// server::send_many (const frames: copied) and send_many_moved (taken).
  template <class Frames>
  std::size_t send_many(Frames frames);

  std::shared_mutex sessions_mutex;  // shared: lookups (send, disconnect, the count); unique: insert, erase
  std::unordered_map<session_id, std::shared_ptr<session>> sessions;
  std::atomic<session_id> next_id{1};

  std::mutex events_mutex;
  std::vector<inbound_event> events;

  // Connections that have not said hello: oldest first, and how many each source address has.
  std::mutex pending_mutex;
  std::list<std::shared_ptr<session>> pending;                   // guarded by pending_mutex
  std::unordered_map<std::string, std::size_t> pending_by_address;  // guarded by pending_mutex
  /// Takes `s` off the pending list (its hello came, or it closed). Any thread.
  void leave_pending(session& s);
  // Reconnect churn per source address (server_options::connect_rate).
  std::mutex churn_mutex;
  std::unordered_map<address_key, churn_bucket, address_key_hash> churn;  // guarded by churn_mutex; absent = full
  /// Refills `b` to `now` (churn_mutex held).
  void refill(churn_bucket& b, steady::time_point now) const {
    b.tokens = std::min(opt.connect_burst, b.tokens + std::chrono::duration<double>(now - b.last).count() * opt.connect_rate);
    b.last = now;
  }
  /// Whether a new connection from `k` may be admitted (the acceptor's thread).
  bool churn_allows(const address_key& k) {
    if (!(opt.connect_rate > 0)) return true;
    const std::lock_guard lock(churn_mutex);
    const auto it = churn.find(k);
    if (it == churn.end()) return true;
    refill(it->second, steady::now());
    if (it->second.tokens >= opt.connect_burst) {
      churn.erase(it);  // full again: forget the address
      return true;
    }
    return it->second.tokens >= 1.0;
  }
  /// A connection from `k` ended within connect_min_session of its accept: a token. Any thread.
  void charge(const address_key& k) {
    if (!(opt.connect_rate > 0)) return;
    const auto now = steady::now();
    const std::lock_guard lock(churn_mutex);
    auto it = churn.find(k);
    if (it == churn.end()) {
      if (churn.size() >= max_churn_addresses) {
        for (auto at = churn.begin(); at != churn.end();) {
          refill(at->second, now);
          at = at->second.tokens >= opt.connect_burst ? churn.erase(at) : std::next(at);
        }
        if (churn.size() >= max_churn_addresses) return;  // every tracked address in churn: this one goes free
      }
      it = churn.emplace(k, churn_bucket{opt.connect_burst, now}).first;
    }
    refill(it->second, now);
    it->second.tokens = std::max(it->second.tokens - 1.0, -60.0 * opt.connect_rate);
    ++counters.connections_charged;
  }
  /// Refused at accept (the acceptor's thread): the error frame, encoded once, and the summary line.
  std::vector<std::uint8_t> refusal_frame;
  std::uint64_t refusals_unlogged = 0;
  steady::time_point refusals_logged{};
  void refuse(int fd, const sockaddr_storage& peer, const address_key& key);
  // Refused connections held before their answer (connect_refusal_hold; the acceptor's thread).
  struct held_connection {
    int fd;
    steady::time_point since;
  };
  std::unordered_map<address_key, std::deque<held_connection>, address_key_hash> held;
  std::size_t held_total = 0;
  std::size_t held_cap = max_held;  // start(): what the open-file limit leaves beside the players and pending connections
  asio::steady_timer held_timer;
  bool held_timer_armed = false;
  /// The refusal's answer: the error frame written without waiting, then a reset (no TIME_WAIT).
  void answer_refused(int fd) {
    (void)::send(fd, refusal_frame.data(), refusal_frame.size(), MSG_DONTWAIT | MSG_NOSIGNAL);
    const linger reset{1, 0};
    (void)::setsockopt(fd, SOL_SOCKET, SO_LINGER, &reset, sizeof reset);
    ::close(fd);
  }
  /// Answers the held connections older than the hold (all: every one). The acceptor's thread.
  void release_held(bool all) {
    const auto now = steady::now();
    for (auto it = held.begin(); it != held.end();) {
      auto& q = it->second;
      while (!q.empty() && (all || now - q.front().since >= opt.connect_refusal_hold)) {
        answer_refused(q.front().fd);
        q.pop_front();
        --held_total;
      }
      it = q.empty() ? held.erase(it) : std::next(it);
    }
  }
  void arm_held_timer() {
    if (held_timer_armed || held_total == 0) return;
    held_timer_armed = true;
    held_timer.expires_after(std::max<std::chrono::milliseconds>(opt.connect_refusal_hold / 4, std::chrono::milliseconds(10)));
    held_timer.async_wait([this](const boost::system::error_code& ec) {
      held_timer_armed = false;
      if (ec || !acceptor.is_open()) return;
      release_held(false);
      arm_held_timer();
    });
  }

  /// Players (sessions past their hello): claims a slot, false when max_connections are taken.
  bool claim_player_slot() {
    auto open = counters.sessions_open.load();
    do {
      if (open >= opt.max_connections) return false;
    } while (!counters.sessions_open.compare_exchange_weak(open, open + 1));
    return true;
  }

  atomic_counters counters;
  std::array<write_counters, write_counter_stripes> write_stats;
  /// server::frame_write_age, one histogram per stripe of writing threads (summed when read).
  std::array<latency_histogram_us, write_counter_stripes> write_age;

  /// The host's CLOCK_MONOTONIC (steady_clock on Linux) in microseconds: a client on the same
  /// host reads the same clock, so its update latency needs no clock sync.
  static std::uint64_t now_us() {
    return static_cast<std::uint64_t>(
        std::chrono::duration_cast<std::chrono::microseconds>(steady::now().time_since_epoch()).count());
  }
  void report(inbound_event e) {
    const std::lock_guard lock(events_mutex);
    events.push_back(std::move(e));
  }
  /// Waits until the listening socket is readable, then accept_ready().
  void do_accept();
  /// Takes what waits in the backlog (up to accept_batch connections; raw accept4, so that a
  /// connection refused at accept costs no more than the accept, a write and the close).
  void accept_ready();
  /// An accept error: logged at most once a second, accepting resumes after a pause.
  void accept_failed(int err);
  /// Makes a session of an accepted descriptor on the next lane (or refuses it: reconnect churn).
  void admit(int fd, const sockaddr_storage& peer, socklen_t peer_len);
  void remove(session_id id);
};

class session : public std::enable_shared_from_this<session> {
 public:
  session(server::impl& srv, io_lane& lane, tcp::socket socket, session_id id, std::string address, address_key key)
      : srv_(srv),
        lane_(lane),
        socket_(std::move(socket)),
        idle_(socket_.get_executor()),
        id_(id),
        address_(std::move(address)),
        key_(key),
        decoder_(srv.opt.inbound),
        input_tokens_(srv.opt.input_burst),
        ping_tokens_(srv.opt.ping_burst),
        queue_(srv.opt.max_queued_frames) {}

  [[nodiscard]] session_id id() const { return id_; }
  [[nodiscard]] const std::string& address() const { return address_; }
  /// Bytes that wait unread in the socket (FIONREAD; 0 on error). Any thread: the descriptor may
  /// have been closed meanwhile (and its number reused), so this is a hint, never a guarantee.
  [[nodiscard]] int unread_bytes() const {
    int n = 0;
    return ::ioctl(fd_, FIONREAD, &n) == 0 ? n : 0;
  }

  /// Starts reading and the hello deadline (on the session's I/O thread).
  void start() {
    asio::post(socket_.get_executor(), [self = shared_from_this()] {
      self->arm_idle(self->srv_.opt.hello_timeout);
      self->do_read();
    });
  }

  // Admission bookkeeping (impl::pending_mutex held).
  std::list<std::shared_ptr<session>>::iterator pending_at;
  bool pending = false;

  /// Any thread.
  [[nodiscard]] std::shared_ptr<const std::atomic<std::uint32_t>> backlog() const { return backlog_; }
  [[nodiscard]] std::shared_ptr<const std::atomic<std::uint64_t>> written() const { return written_; }

  /// Any thread: outbound_queue::control_waiting under the write lock.
  std::size_t control_waiting() {
    const std::unique_lock lock(write_mutex_);
    return queue_.control_waiting();
  }

  /// Any thread: outbound_queue::drop_stale under the write lock, counted (server::drop_stale_state).
  std::size_t drop_stale() {
    const std::unique_lock lock(write_mutex_);
    if (closing_ || closed_) return 0;
    const std::size_t n = queue_.drop_stale();
    if (n != 0) {
      backlog_->fetch_sub(static_cast<std::uint32_t>(n), std::memory_order_relaxed);
      srv_.counters.frames_dropped += n;
    }
    ++srv_.counters.stale_drops;
    return n;
  }

  /// Any thread: enqueue(), and the lane told now when it must write.
  void enqueue_and_schedule(shared_frame frame, delivery d) {
    if (enqueue(std::move(frame), d, 0)) lane_.schedule(shared_from_this(), d == delivery::control);
  }
  [[nodiscard]] io_lane& lane() const { return lane_; }
  [[nodiscard]] int native_fd() const { return fd_; }
  /// The lane's thread (its ring's writes): the socket's slot in the lane's table of registered
  /// files, taken at the first write (once: a session refused one sends by descriptor), or -1.
  [[nodiscard]] int ring_file(io_lane& lane) {
    if (!file_slot_tried_) {
      file_slot_tried_ = true;
      file_slot_ = lane.register_file(fd_);
    }
    return file_slot_;
  }

  /// Any thread: through the outbound queue's policy, then written at once by this thread (direct
  /// writes) unless the session waits for its socket. True: the lane must be told to write it
  /// (io_lane::schedule; the session is marked as on its ready list).
  [[nodiscard]] bool enqueue(shared_frame frame, delivery d, std::uint64_t stamp_us) {
    if (d != delivery::control) backlog_->fetch_add(1, std::memory_order_relaxed);
    std::unique_lock lock(write_mutex_);
    const auto r = push_locked(std::move(frame), d, stamp_us);
    if (r.overflow) {
      lock.unlock();
      close("outbound queue overflow with control frames");
      return false;
    }
    if (!r.queued || blocked_ || flush_posted_ || closed_) return false;
    if (srv_.opt.direct_writes) {
      switch (flush_locked()) {
        case flush_result::drained: return false;
        case flush_result::blocked:
          // The lane retries once before it waits: an EPOLLOUT edge its event loop took before
          // that handler runs found no waiter (edge-triggered: it would not come again).
          lock.unlock();
          asio::post(socket_.get_executor(), [self = shared_from_this()] { self->resume_write(); });
          return false;
        case flush_result::failed: {
          std::string why = "write failed: " + write_error_;
          lock.unlock();
          close(std::move(why));
          return false;
        }
      }
      return false;
    }
    flush_posted_ = true;
    return true;
  }

  /// The lane's thread (its ready list): write what is queued.
  void lane_flush() {
    std::unique_lock lock(write_mutex_);
    flush_posted_ = false;
    if (!blocked_) flush_on_lane(lock);
  }

  /// The lane's thread (its ready list, io_uring): the next write into `iov` / `msg` for the
  /// lane's submission. True: prepared (the session stays marked as on the ready list, so no
  /// other writer starts one, until ring_complete). False: nothing to submit (done here).
  bool ring_prepare(std::array<iovec, max_gather_frames>& iov, msghdr& msg) {
    std::unique_lock lock(write_mutex_);
    if (closed_ || blocked_ || queue_.empty()) {
      flush_posted_ = false;
      if (!blocked_) flush_on_lane(lock);  // nothing queued: a closing session closes now
      return false;
    }
    ring_frames_ = prepare_write_locked(iov.data());
    msg = msghdr{};
    msg.msg_iov = iov.data();
    msg.msg_iovlen = ring_frames_;
    return true;
  }

  /// The lane's thread: the kernel's answer to the write ring_prepare made (bytes, or -errno).
  /// More queued behind it: the session goes on `again` (written by the lane's next drain).
  void ring_complete(int result, std::vector<std::shared_ptr<session>>& again) {
    std::unique_lock lock(write_mutex_);
    flush_posted_ = false;
    if (closed_) return;
    switch (finish_write_locked(result, ring_frames_)) {
      case write_outcome::complete:
      case write_outcome::retry:
        if (!queue_.empty()) {
          flush_posted_ = true;
          again.push_back(shared_from_this());
        } else if (closing_) {
          lock.unlock();
          close_now(close_reason_);
        }
        return;
      case write_outcome::blocked:
        wait_writable();
        return;
      case write_outcome::failed:
        close_after_write_error(lock);
        return;
    }
  }

  /// Any thread: error frame, then close.
  void fail(error_code code, std::string reason) {
    asio::post(socket_.get_executor(), [self = shared_from_this(), code, reason = std::move(reason)]() mutable {
      self->fail_now(code, std::move(reason));
    });
  }

  /// Any thread: close at once (server stop).
  void close(std::string reason) {
    asio::post(socket_.get_executor(),
               [self = shared_from_this(), reason = std::move(reason)]() mutable { self->close_now(std::move(reason)); });
  }

 private:
  /// The session times out `after` from now (the lane's thread). Every read pushes the deadline
  /// on; the timer is not re-armed for that (a re-arm cancels the pending wait, whose handler
  /// then runs too: two timer operations and a handler per read): it fires at the deadline it was
  /// armed for and waits again for the rest when reads have pushed the deadline on. It is
  /// re-armed only when the new deadline comes sooner (a closing session's grace period).
  void arm_idle(std::chrono::milliseconds after) {
    const auto deadline = steady::now() + after;
    idle_deadline_ = deadline;
    if (idle_armed_ && idle_.expiry() <= deadline) return;
    idle_armed_ = true;
    wait_idle(deadline);
  }

  void wait_idle(steady::time_point at) {
    idle_.expires_at(at);  // cancels a pending wait: its handler sees operation_aborted
    idle_.async_wait([self = shared_from_this()](const boost::system::error_code& ec) {
      if (ec == asio::error::operation_aborted || self->closed_) return;
      if (steady::now() < self->idle_deadline_) {
        self->wait_idle(self->idle_deadline_);  // reads came meanwhile: wait for the rest
        return;
      }
      self->idle_armed_ = false;
      if (self->closing_) {
        self->close_now("closing: the final frame was not taken in time");
      } else if (!self->hello_seen_) {
        ++self->srv_.counters.hello_timeouts;
        self->fail_now(error_code::timeout, "no hello in time");
      } else {
        ++self->srv_.counters.idle_timeouts;
        self->fail_now(error_code::timeout, "idle for too long");
      }
    });
  }

  void do_read() {
    if (closing_ || closed_) return;
    const auto buf = decoder_.prepare(read_chunk_bytes);
    socket_.async_read_some(asio::buffer(buf.data(), buf.size()),
                            [self = shared_from_this()](const boost::system::error_code& ec, std::size_t n) {
                              self->on_read(ec, n);
                            });
  }

  void on_read(const boost::system::error_code& ec, std::size_t n) {
    if (closed_) return;
    if (ec) {
      // While closing, the write path (or the grace timer) closes: the error frame goes out first.
      if (ec == asio::error::operation_aborted || closing_) return;
      if (ec == asio::error::eof) {
        const auto tail = decoder_.close();
        close_now(tail ? "client closed inside a frame" : "client closed");
      } else {
        close_now("read failed: " + ec.message());
      }
      return;
    }
    decoder_.commit(n);
    srv_.counters.bytes_in += n;
    if (closing_) return;  // only the final frame matters now
    bool any_frame = false;
    for (;;) {
      const decode_step step = decoder_.next();
      if (step.needs_more()) break;
      if (step.is_error()) {
        ++srv_.counters.frames_rejected;
        spdlog::debug("session {}: {}", id_, to_string(step.error));
        fail_now(to_error_code(step.error), std::string(to_string(step.error)));
        return;
      }
      ++srv_.counters.frames_in;
      handle(step.frame);
      if (closing_ || closed_) return;
      // The idle timer restarts on a complete frame of a session past its hello (the hello
      // included): before it, the deadline from accept stands, and bytes of an unfinished frame
      // are no sign of life.
      any_frame = any_frame || hello_seen_;
    }
    if (any_frame) arm_idle(srv_.opt.idle_timeout);
    do_read();
  }

  void handle(const frame_view& f) {
    // Before its hello a connection is served nothing: any other message closes it.
    if (!hello_seen_ && f.type != wire::message::hello) {
      if (f.type == wire::message::input || f.type == wire::message::teleport || f.type == wire::message::ping ||
          f.type == wire::message::set_visibility || f.type == wire::message::leave) {
        return fail_now(error_code::unexpected_message, std::string(type_name(f.type)) + " before hello");
      }
    }
    switch (f.type) {
      case wire::message::hello:
        if (hello_seen_) return fail_now(error_code::unexpected_message, "second hello");
        return on_hello(f);
      case wire::message::input:
      case wire::message::teleport:
      case wire::message::set_visibility:
        // Teleports and visibility switches count against the same input rate as inputs (the
        // game adds its own cooldowns).
        if (input_tokens_.take(srv_.opt.inputs_per_second, srv_.opt.input_burst)) {
          input_drops_ = 0;
          return forward(f);
        }
        ++srv_.counters.inputs_dropped;
        if (++input_drops_ > srv_.opt.flood_limit) return flood("input flood");
        return;
      case wire::message::ping: {
        if (!ping_tokens_.take(srv_.opt.pings_per_second, srv_.opt.ping_burst)) {
          ++srv_.counters.pings_dropped;
          if (++ping_drops_ > srv_.opt.flood_limit) return flood("ping flood");
          return;
        }
        ping_drops_ = 0;
        // A client that pings but does not read (stalled) would pile up pongs until its queue
        // overflows with control frames and it is closed as stuck: with half the bound of
        // control frames already waiting, this ping gets no pong (counted as dropped).
        if (control_waiting() * 2 >= srv_.opt.max_queued_frames) {
          ++srv_.counters.pings_dropped;
          return;
        }
        const auto* p = f.envelope->message_as_ping();
        ++srv_.counters.pings_answered;
        push_from_lane(make_shared_frame(pong_encoder_.encode(pong_msg{p->client_time_us(), srv_.now_us()})),
                       delivery::control);
        return;
      }
      case wire::message::leave:
        // A logout: nothing is sent back; the game hears it with the disconnect (inbound_event::left).
        left_ = true;
        return close_now("left");
      default:
        return fail_now(error_code::unexpected_message,
                        "a client may not send " + std::string(type_name(f.type)));
    }
  }

  void flood(const char* what) {
    ++srv_.counters.rate_limited;
    fail_now(error_code::rate_limited, what);
  }

  /// The hello of a pending connection: the name checked, a player slot claimed, then the game
  /// hears of the session (connected, then the hello).
  void on_hello(const frame_view& f) {
    hello_seen_ = true;
    srv_.leave_pending(*this);
    const auto* h = f.envelope->message_as_hello();
    const std::string_view name = h->name() ? std::string_view(h->name()->c_str(), h->name()->size()) : std::string_view();
    if (auto why = check_player_name(name, srv_.opt.max_name_bytes)) {
      ++srv_.counters.hellos_rejected;
      return fail_now(error_code::bad_hello, "bad name: " + *why);
    }
    if (!srv_.claim_player_slot()) {
      ++srv_.counters.connections_refused;
      return fail_now(error_code::server_full, "connection limit reached");
    }
    announced_ = true;
    inbound_event e;
    e.type = inbound_event::kind::connected;
    e.session = id_;
    srv_.report(std::move(e));
    // The hello with its connection's times (now_us()'s clock: steady_clock in microseconds).
    forward(f, static_cast<std::uint64_t>(
                   std::chrono::duration_cast<std::chrono::microseconds>(accepted_at_.time_since_epoch()).count()),
            srv_.now_us());
  }

  void forward(const frame_view& f, std::uint64_t accepted_us = 0, std::uint64_t hello_us = 0) {
    inbound_event e;
    e.type = inbound_event::kind::message;
    e.session = id_;
    e.msg = to_message(*f.envelope);
    e.accepted_us = accepted_us;
    e.hello_us = hello_us;
    srv_.report(std::move(e));
  }

  /// Through the queue's policy (write lock held; any thread): counts drops, reports a resync.
  outbound_queue::push_result push_locked(shared_frame frame, delivery d, std::uint64_t stamp_us = 0) {
    if (closing_ || closed_ || !frame) {
      if (d != delivery::control && frame) backlog_->fetch_sub(1, std::memory_order_relaxed);
      return {};
    }
    // A state frame's age (server::frame_write_age) counts from its stamp, or from now.
    if (d != delivery::control && stamp_us == 0) stamp_us = srv_.now_us();
    const auto r = queue_.push(std::move(frame), d, stamp_us);
    // Every state frame ends queued (then written: flush_locked) or counted in `dropped`.
    if (r.dropped != 0) backlog_->fetch_sub(static_cast<std::uint32_t>(r.dropped), std::memory_order_relaxed);
    if (r.overflow) return r;
    if (r.dropped != 0) srv_.counters.frames_dropped += r.dropped;
    if (r.resync) {
      // Why the queue was full (evidence for resyncs under pacing, which should leave at most
      // client_max_backlog state frames queued): the first 20 episodes and every 1000th.
      const auto episode = srv_.counters.resyncs_requested.load(std::memory_order_relaxed);
      if (episode < 20 || episode % 1000 == 0) {
        std::size_t control = 0;
        for (const auto& e : queue_.entries()) control += e.kind == delivery::control ? 1 : 0;
        spdlog::info("session {}: drop episode {}: queue held {} frames ({} control, {} being written), state backlog {}",
                     id_, episode + 1, queue_.size(), control, queue_.in_flight(),
                     backlog_->load(std::memory_order_relaxed));
      }
      // Once per episode: the game makes this client's next frame a reset; until it is queued,
      // the queue drops the deltas built meanwhile (the client could not apply them).
      ++srv_.counters.resyncs_requested;
      inbound_event e;
      e.type = inbound_event::kind::frames_dropped;
      e.session = id_;
      e.dropped = r.dropped;
      srv_.report(std::move(e));
    }
    return r;
  }

  /// The lane's thread: a frame of its own (pong) into the queue and out.
  void push_from_lane(shared_frame frame, delivery d) {
    std::unique_lock lock(write_mutex_);
    const auto r = push_locked(std::move(frame), d);
    if (r.overflow) {
      lock.unlock();
      close_now("outbound queue overflow with control frames");
      return;
    }
    if (r.queued && !blocked_) flush_on_lane(lock);
  }

  enum class flush_result { drained, blocked, failed };

  /// Marks the next write (write lock held; the queue not empty): the rest of a partial write, or
  /// a new gathered write of the first queued frames (at most bound - 1, about 64 KiB); points
  /// iov[0, n) at it, the first from where a partial write left it. How many frames (n).
  std::size_t prepare_write_locked(iovec* iov) {
    std::size_t n = queue_.in_flight();
    write_is_new_ = n == 0;  // else the rest of a partial write
    if (write_is_new_) n = queue_.start_write_many(max_gather_frames);
    const auto& entries = queue_.entries();
    for (std::size_t i = 0; i < n; ++i) {
      const std::size_t skip = i == 0 ? partial_ : 0;
      iov[i].iov_base = const_cast<std::uint8_t*>(entries[i].frame.data() + skip);
      iov[i].iov_len = entries[i].frame.size() - skip;
    }
    return n;
  }

  enum class write_outcome { complete, retry, blocked, failed };

  /// The kernel's answer to the write prepared over `n` frames (write lock held): `result` bytes
  /// taken, or -errno. Retires the frames written whole (a frame written in part stays first, in
  /// flight). complete: all n written; retry: EINTR, nothing changed; blocked: EAGAIN or a
  /// partial write (the kernel's buffer is full: blocked_ holds every other writer off until the
  /// lane resumes); failed: an error (blocked_ too; the caller closes the session).
  write_outcome finish_write_locked(long result, std::size_t n) {
    if (result < 0) {
      const int err = static_cast<int>(-result);
      if (err == EINTR) return write_outcome::retry;
      blocked_ = true;
      if (err == EAGAIN || err == EWOULDBLOCK) return write_outcome::blocked;
      write_error_ = std::strerror(err);
      return write_outcome::failed;
    }
    const auto& entries = queue_.entries();
    auto left = static_cast<std::size_t>(result);
    std::size_t done = 0, offset = partial_;
    std::uint32_t state_done = 0;
    const std::size_t stripe = write_counter_stripe();
    std::uint64_t now = 0;
    while (done < n) {
      const std::size_t rest = entries[done].frame.size() - offset;
      if (left < rest) {
        offset += left;
        break;
      }
      left -= rest;
      offset = 0;
      if (entries[done].kind != delivery::control) {
        ++state_done;
        if (now == 0) now = srv_.now_us();
        const std::uint64_t stamp = entries[done].stamp_us;
        srv_.write_age[stripe].record(now > stamp ? static_cast<double>(now - stamp) : 0.0);
      }
      ++done;
    }
    partial_ = offset;
    queue_.finish_frames(done);
    if (state_done != 0) backlog_->fetch_sub(state_done, std::memory_order_relaxed);
    auto& c = srv_.write_stats[stripe];
    if (write_is_new_) c.writes.fetch_add(1, std::memory_order_relaxed);
    write_is_new_ = false;  // what is left of this write goes on as its rest
    c.bytes_out.fetch_add(static_cast<std::uint64_t>(result), std::memory_order_relaxed);
    written_->fetch_add(static_cast<std::uint64_t>(result), std::memory_order_relaxed);
    if (done != 0) c.frames_out.fetch_add(done, std::memory_order_relaxed);
    if (done < n) {
      blocked_ = true;  // the kernel took less than offered: its buffer is full
      return write_outcome::blocked;
    }
    return write_outcome::complete;
  }

  /// Writes the queue's frames in order (write lock held; any thread), each write one
  /// non-blocking sendmsg of the frames prepare_write_locked marks. Stops at EAGAIN or a partial
  /// write (blocked: the rest stays queued, in flight, and blocked_ holds every other writer off
  /// until the lane resumes) or an error (failed: blocked_ too; the caller closes the session).
  flush_result flush_locked() {
    if (closed_) return flush_result::drained;
    std::array<iovec, max_gather_frames> iov;
    while (!queue_.empty()) {
      const std::size_t n = prepare_write_locked(iov.data());
      msghdr msg{};
      msg.msg_iov = iov.data();
      msg.msg_iovlen = n;
      const ssize_t written = ::sendmsg(fd_, &msg, MSG_DONTWAIT | MSG_NOSIGNAL);
      switch (finish_write_locked(written < 0 ? -errno : written, n)) {
        case write_outcome::complete:
        case write_outcome::retry: continue;
        case write_outcome::blocked: return flush_result::blocked;
        case write_outcome::failed: return flush_result::failed;
      }
    }
    return flush_result::drained;
  }

  /// The lane's thread, write lock held (released here): close with the failed write's error.
  void close_after_write_error(std::unique_lock<std::mutex>& lock) {
    std::string why = "write failed: " + write_error_;
    lock.unlock();
    close_now(std::move(why));
  }

  /// The lane's thread, write lock held (released on return): flush; wait for the socket when it
  /// blocks; close on an error, or once a closing session's queue is out.
  void flush_on_lane(std::unique_lock<std::mutex>& lock) {
    switch (flush_locked()) {
      case flush_result::blocked:
        wait_writable();
        return;
      case flush_result::failed:
        close_after_write_error(lock);
        return;
      case flush_result::drained:
        if (closing_ && queue_.empty()) {
          lock.unlock();
          close_now(close_reason_);
        }
        return;
    }
  }

  /// The lane's thread, after EAGAIN or a partial write: resume when the socket is writable. The
  /// lane's thread runs its event loop: no EPOLLOUT edge is taken between the EAGAIN and this
  /// wait, so none is lost.
  void wait_writable() {
    socket_.async_wait(tcp::socket::wait_write,
                       [self = shared_from_this()](const boost::system::error_code& ec) { self->on_writable(ec); });
  }

  /// The lane's thread: a direct write blocked; try again here, then wait for the socket.
  void resume_write() {
    std::unique_lock lock(write_mutex_);
    if (closed_ || !blocked_) return;
    blocked_ = false;
    flush_on_lane(lock);
  }

  void on_writable(const boost::system::error_code& ec) {
    if (ec == asio::error::operation_aborted || closed_) return;
    if (ec) {
      close_now("write failed: " + ec.message());
      return;
    }
    resume_write();
  }

  void fail_now(error_code code, std::string reason) {
    if (closing_ || closed_) return;
    spdlog::debug("session {}: closing with error {}: {}", id_, wire::EnumNameerror_code(code), reason);
    boost::system::error_code ignored;
    socket_.shutdown(tcp::socket::shutdown_receive, ignored);
    arm_idle(close_grace);
    std::unique_lock lock(write_mutex_);
    // Keep only the frames being written; the error is the last frame this client gets.
    queue_.keep_only_in_flight();
    (void)queue_.push(make_shared_frame(pong_encoder_.encode(error_msg{code, reason})), delivery::control);
    closing_ = true;
    close_reason_ = std::move(reason);
    cut_off_ = code == error_code::bad_frame || code == error_code::oversize ||
               code == error_code::verification_failed || code == error_code::unknown_type ||
               code == error_code::unexpected_message || code == error_code::rate_limited;
    if (!blocked_) flush_on_lane(lock);
  }

  void close_now(std::string reason) {
    if (closed_) return;
    {
      // No sender is inside a write now, and none writes after this (the descriptor is closed).
      const std::lock_guard lock(write_mutex_);
      closed_ = true;
      queue_.clear();
      partial_ = 0;
      if (closing_) reason = close_reason_;  // the error that started the close is the reason
      boost::system::error_code ignored;
      socket_.shutdown(tcp::socket::shutdown_both, ignored);
      // Out of the ring's table first: it holds the socket open (no write of it is in flight:
      // the lane reaps every submission before its next handler runs, and this is one).
      lane_.unregister_file(file_slot_);
      file_slot_ = -1;
      socket_.close(ignored);
    }
    idle_.cancel();
    srv_.leave_pending(*this);
    // Reconnect churn: a connection that ends this soon after its accept takes a token from its
    // address (server_options::connect_rate).
    if (steady::now() - accepted_at_ < srv_.opt.connect_min_session) srv_.charge(key_);
    if (announced_) {
      spdlog::debug("session {}: disconnected ({})", id_, reason);
      inbound_event e;
      e.type = inbound_event::kind::disconnected;
      e.session = id_;
      e.reason = std::move(reason);
      e.left = left_;
      e.cut_off = cut_off_;
      srv_.report(std::move(e));
      --srv_.counters.sessions_open;
    }
    srv_.remove(id_);
  }

  server::impl& srv_;
  io_lane& lane_;
  tcp::socket socket_;  // its executor is the lane's io_context (one thread): every handler runs there
  const int fd_ = socket_.native_handle();  // what flush_locked writes to (while !closed_)
  int file_slot_ = -1;                      // the lane's thread: its slot in the ring's table of files (ring_file)
  bool file_slot_tried_ = false;
  asio::steady_timer idle_;
  steady::time_point idle_deadline_{};  // the lane's thread: when the session times out
  bool idle_armed_ = false;             // the lane's thread: a wait on idle_ is pending
  const session_id id_;
  const std::string address_;  // the peer's address (the pending cap's key)
  const address_key key_;      // the reconnect-churn limit's key
  const steady::time_point accepted_at_ = steady::now();
  bool announced_ = false;     // the game heard of it (a valid hello in a free slot); lane only
  bool left_ = false;          // the client said leave; lane only
  bool cut_off_ = false;       // closed for breaking the rules (fail_now's code); lane only
  frame_decoder decoder_;
  encoder pong_encoder_{256};
  bool hello_seen_ = false;
  token_bucket input_tokens_, ping_tokens_;
  std::uint32_t input_drops_ = 0, ping_drops_ = 0;  // over the rate in a row
  std::shared_ptr<std::atomic<std::uint32_t>> backlog_ = std::make_shared<std::atomic<std::uint32_t>>(0);
  std::shared_ptr<std::atomic<std::uint64_t>> written_ = std::make_shared<std::atomic<std::uint64_t>>(0);
  // The write side. Written under write_mutex_ only; the lane's thread also reads closing_ and
  // closed_ without it (it is their only writer).
  std::mutex write_mutex_;
  outbound_queue queue_;  // its first in_flight() frames are being written
  std::size_t partial_ = 0;      // bytes of the first frame being written already in the socket
  bool blocked_ = false;         // the socket took less than offered: only the lane writes next
  bool flush_posted_ = false;    // on the lane's ready list, or its io_uring write in flight
  bool write_is_new_ = false;    // the write prepared starts new frames (not the rest of a partial one)
  std::size_t ring_frames_ = 0;  // frames of the write submitted through the lane's ring
  bool closing_ = false;  // an error frame is queued; close once it is written
  bool closed_ = false;
  std::string close_reason_;
  std::string write_error_;
};

void io_lane::schedule(std::shared_ptr<session> s, bool urgent_write) {
  append(urgent_write ? urgent : ready, std::span(&s, 1));
}

void io_lane::schedule_many(std::span<std::shared_ptr<session>> sessions) { append(ready, sessions); }

void io_lane::append(std::vector<std::shared_ptr<session>>& list, std::span<std::shared_ptr<session>> sessions) {
  if (sessions.empty()) return;
  bool post;
  {
    const std::lock_guard lock(ready_mutex);
    for (auto& s : sessions) list.push_back(std::move(s));
    post = !drain_posted;
    drain_posted = true;
  }
  if (post) asio::post(ctx, [this] { drain(); });
}

void io_lane::drain() {
  const bool new_round = drained == draining.size();  // a new round: every session ready now
  if (new_round) {
    draining.clear();
    drained = 0;
  }
  {
    const std::lock_guard lock(ready_mutex);
    urgent_now.swap(urgent);  // empty: the last drain wrote and cleared it
    if (urgent_now.size() > drain_slice) {  // a burst (many joins at once): a slice of them a drain
      urgent.assign(std::make_move_iterator(urgent_now.begin() + static_cast<std::ptrdiff_t>(drain_slice)),
                    std::make_move_iterator(urgent_now.end()));
      urgent_now.resize(drain_slice);
    }
    if (new_round) draining.swap(ready);
  }
  if (new_round) {
    for (auto& s : again) draining.push_back(std::move(s));
    again.clear();
  }
  // Control frames first (a welcome waited for the rest of a round: up to ~30 ms on a busy lane).
  // Few: written one by one, not through the ring.
  for (auto& s : urgent_now) s->lane_flush();
  urgent_now.clear();
  const std::size_t begin = drained, end = std::min(draining.size(), begin + drain_slice);  // start(): >= 1
  if (ring_ok) {
    write_batched(begin, end);
  } else {
    for (std::size_t i = begin; i < end; ++i) draining[i]->lane_flush();
  }
  for (std::size_t i = begin; i < end; ++i) draining[i].reset();
  drained = end;
  if (drained < draining.size()) {
    // The round's next slice, behind the lane's other handlers: a lane that cannot keep up still
    // reads its clients (a new one's hello, pings) within a slice's time, not a round's (a round
    // of thousands of sessions on a busy lane took up to half a second during a ramp, H200
    // 2026-11-30). drain_posted stays set, so senders do not post.
    asio::post(ctx, [this] { drain(); });
    return;
  }
  draining.clear();
  drained = 0;
  {
    const std::lock_guard lock(ready_mutex);
    if (ready.empty() && again.empty() && urgent.empty()) {
      drain_posted = false;  // the next schedule() posts a new drain
      return;
    }
  }
  // More became ready meanwhile: one more round, behind the lane's other handlers (accepts, reads,
  // timers: a drain that looped until its list stayed empty held them off for seconds on a lane
  // that cannot keep up, H100 2026-11-25). drain_posted stays set, so senders do not post.
  asio::post(ctx, [this] { drain(); });
}

void io_lane::forget_ready() {
  draining.clear();
  drained = 0;
  again.clear();
  urgent_now.clear();
  const std::lock_guard lock(ready_mutex);
  ready.clear();
  urgent.clear();
  drain_posted = false;
}

io_lane::~io_lane() { drop_ring(); }

void io_lane::drop_ring() {
#if ZONE_HAVE_LIBURING
  if (ring_live) io_uring_queue_exit(&ring);  // releases the registered files too
#endif
  ring_ok = ring_live = false;
  file_slots = file_slots_used = 0;
  free_file_slots.clear();
}

int io_lane::register_file(int fd) {
#if ZONE_HAVE_LIBURING
  if (!ring_live || file_slots == 0) return -1;
  unsigned slot;
  if (!free_file_slots.empty()) {
    slot = free_file_slots.back();
    free_file_slots.pop_back();
  } else if (file_slots_used < file_slots) {
    slot = file_slots_used++;
  } else {
    return -1;  // every slot held by an open session: this one sends by descriptor
  }
  if (io_uring_register_files_update(&ring, slot, &fd, 1) != 1) {
    free_file_slots.push_back(slot);
    return -1;
  }
  return static_cast<int>(slot);
#else
  (void)fd;
  return -1;
#endif
}

void io_lane::unregister_file(int slot) {
#if ZONE_HAVE_LIBURING
  if (slot < 0 || !ring_live) return;
  int none = -1;
  // Refused only for a slot out of range (never handed out so): the slot is not reused then.
  if (io_uring_register_files_update(&ring, static_cast<unsigned>(slot), &none, 1) == 1) {
    free_file_slots.push_back(static_cast<unsigned>(slot));
  }
#else
  (void)slot;
#endif
}

std::optional<std::string> io_lane::init_ring(unsigned file_slot_count) {
#if ZONE_HAVE_LIBURING
  drop_ring();  // a server started again
  io_uring_params p{};
  // Every submission is taken whole even where one fails; completions posted without IPIs.
  p.flags = IORING_SETUP_SUBMIT_ALL | IORING_SETUP_COOP_TASKRUN;
  int r = io_uring_queue_init_params(ring_entries, &ring, &p);
  if (r == -EINVAL) {  // a kernel before 5.19 knows neither flag
    p = io_uring_params{};
    r = io_uring_queue_init_params(ring_entries, &ring, &p);
  }
  if (r < 0) return std::string("io_uring_queue_init: ") + std::strerror(-r);
  // A send marked MSG_DONTWAIT must fail with EAGAIN instead of waiting in the kernel (the lane
  // then waits for the socket itself, as with sendmsg): IORING_FEAT_NODROP and the nowait
  // semantics of socket ops came with 5.5; older kernels are refused.
  if ((p.features & IORING_FEAT_NODROP) == 0) {
    io_uring_queue_exit(&ring);
    return std::string("the kernel's io_uring is too old (no IORING_FEAT_NODROP)");
  }
  ring_ok = ring_live = true;
  // The table of registered files, empty (sparse: 5.19): where the kernel refuses it (or its
  // size, over RLIMIT_NOFILE), the sends name descriptors.
  file_slots = 0;
  if (file_slot_count != 0 && io_uring_register_files_sparse(&ring, file_slot_count) == 0) file_slots = file_slot_count;
  slots.resize(ring_entries);
  slot_iov.resize(ring_entries);
  slot_msg.resize(ring_entries);
  return std::nullopt;
#else
  return std::string("built without liburing");
#endif
}

void io_lane::write_batched(std::size_t begin, std::size_t end) {
  unsigned n = 0;
  for (std::size_t i = begin; i < end; ++i) {
    auto& s = draining[i];
    if (!ring_ok) {  // the ring failed earlier in this slice (submit_slots): the rest by sendmsg
      s->lane_flush();
      continue;
    }
    if (!s->ring_prepare(slot_iov[n], slot_msg[n])) continue;
    slots[n++] = std::move(s);
    if (n == ring_entries) {
      submit_slots(n);
      n = 0;
    }
  }
  if (n != 0) submit_slots(n);
}

void io_lane::submit_slots(unsigned n) {
#if ZONE_HAVE_LIBURING
  std::uint64_t registered = 0;
  for (unsigned i = 0; i < n; ++i) {
    io_uring_sqe* sqe = io_uring_get_sqe(&ring);  // never null: at most ring_entries per submission, all reaped
    const msghdr& m = slot_msg[i];
    // The socket's slot in the ring's table where it has one (no file lookup), else its descriptor.
    const int file_slot = slots[i]->ring_file(*this);
    const int target = file_slot >= 0 ? file_slot : slots[i]->native_fd();
    if (m.msg_iovlen == 1) {
      // One buffer (the common case: a frame a tick): a plain send, no msghdr to import.
      io_uring_prep_send(sqe, target, m.msg_iov[0].iov_base, m.msg_iov[0].iov_len, MSG_DONTWAIT | MSG_NOSIGNAL);
    } else {
      io_uring_prep_sendmsg(sqe, target, &m, MSG_DONTWAIT | MSG_NOSIGNAL);
    }
    if (file_slot >= 0) {
      sqe->flags |= IOSQE_FIXED_FILE;
      ++registered;
    }
    io_uring_sqe_set_data64(sqe, i);
  }
  if (registered != 0) registered_sends.fetch_add(registered, std::memory_order_relaxed);
  write_batches.fetch_add(1, std::memory_order_relaxed);
  // MSG_DONTWAIT: every send completes within the submission (EAGAIN rather than a wait), so
  // waiting for all n completions returns at once.
  unsigned submitted = 0, reaped = 0;
  std::string failure;
  while (submitted < n) {
    const int r = io_uring_submit_and_wait(&ring, n - submitted);
    if (r >= 0) {
      submitted += static_cast<unsigned>(r);
      if (r == 0) break;
      continue;
    }
    if (r == -EINTR || r == -EAGAIN || r == -EBUSY) continue;
    failure = std::string("io_uring submit: ") + std::strerror(-r);
    break;
  }
  while (reaped < submitted) {
    io_uring_cqe* cqe = nullptr;
    const int r = io_uring_wait_cqe(&ring, &cqe);
    if (r == -EINTR) continue;
    if (r < 0) {
      failure = std::string("io_uring wait: ") + std::strerror(-r);
      break;
    }
    const auto i = static_cast<unsigned>(io_uring_cqe_get_data64(cqe));
    const int res = cqe->res;
    io_uring_cqe_seen(&ring, cqe);
    ++reaped;
    if (i < n && slots[i]) {
      slots[i]->ring_complete(res, again);
      slots[i].reset();
    }
  }
  if (!failure.empty() || reaped < n) {
    ring_ok = false;  // the ring may still hold answers to these writes: never read it again
    // Never seen: the kernel refused the submission. The sessions it left without an answer
    // cannot know what reached their sockets; they are closed (their clients reconnect).
    spdlog::error("I/O lane: {} ({} of {} writes answered): closing their sessions", failure.empty() ? "io_uring" : failure,
                  reaped, n);
    for (unsigned i = 0; i < n; ++i) {
      if (slots[i]) {
        slots[i]->ring_complete(-EIO, again);
        slots[i].reset();
      }
    }
  }
#else
  (void)n;
#endif
}

void server::impl::remove(session_id id) {
  const std::lock_guard lock(sessions_mutex);
  sessions.erase(id);
}

void server::impl::leave_pending(session& s) {
  const std::lock_guard lock(pending_mutex);
  if (!s.pending) return;
  s.pending = false;
  pending.erase(s.pending_at);
  const auto it = pending_by_address.find(s.address());
  if (it != pending_by_address.end() && --it->second == 0) pending_by_address.erase(it);
  --counters.pending_open;
}

void server::impl::refuse(int fd, const sockaddr_storage& peer, const address_key& key) {
  ++counters.connections_rate_limited;
  // Held unanswered for connect_refusal_hold (a client that waits for its answer before it tries
  // again then tries once per hold, instead of as fast as the server can refuse), within the
  // caps; then (or at once) the answer.
  if (opt.connect_refusal_hold.count() > 0 && held_total < held_cap) {
    auto& q = held[key];
    if (q.size() >= max_held_per_address) {
      answer_refused(q.front().fd);
      q.pop_front();
      --held_total;
    }
    q.push_back({fd, steady::now()});
    ++held_total;
    arm_held_timer();
  } else {
    answer_refused(fd);
  }
  ++refusals_unlogged;
  const auto now = steady::now();
  if (now - refusals_logged >= refusal_log_interval) {
    char text[INET6_ADDRSTRLEN] = "?";
    if (peer.ss_family == AF_INET) ::inet_ntop(AF_INET, &reinterpret_cast<const sockaddr_in&>(peer).sin_addr, text, sizeof text);
    else ::inet_ntop(AF_INET6, &reinterpret_cast<const sockaddr_in6&>(peer).sin6_addr, text, sizeof text);
    spdlog::warn("refused {} new connection{} at accept since the last such line: reconnect churn over {} a second from "
                 "one address (the latest from {}; zone_net_connections_rate_limited_total counts them all)",
                 refusals_unlogged, refusals_unlogged == 1 ? "" : "s", opt.connect_rate, text);
    refusals_logged = now;
    refusals_unlogged = 0;
  }
}

void server::impl::admit(int fd, const sockaddr_storage& peer_addr, socklen_t peer_len) {
  const bool known = peer_addr.ss_family == AF_INET || peer_addr.ss_family == AF_INET6;
  const address_key key = known ? key_of(peer_addr) : address_key{};
  // Before anything else: an address over its reconnect churn is refused here, at the cost of a
  // lookup, a write and a close.
  if (known && !churn_allows(key)) return refuse(fd, peer_addr, key);
  io_lane& lane = next_lane();
  tcp::endpoint peer;
  if (known) {
    std::memcpy(peer.data(), &peer_addr, peer_len);
    peer.resize(peer_len);
  }
  boost::system::error_code ignored;
  tcp::socket socket(lane.ctx);
  socket.assign(known ? peer.protocol() : tcp::v4(), fd, ignored);
  if (ignored) {
    ::close(fd);
    return;
  }
  socket.set_option(tcp::no_delay(true), ignored);
  if (opt.socket_send_buffer > 0) {
    socket.set_option(asio::socket_base::send_buffer_size(static_cast<int>(opt.socket_send_buffer)), ignored);
  }
  const session_id id = next_id++;
  std::string address = known ? peer.address().to_string() : std::string("?");
  ++counters.connections_accepted;
  auto s = std::make_shared<session>(*this, lane, std::move(socket), id, std::move(address), key);
  // Admission: the connection is pending until its hello, within the per-address and total caps
  // (never against the player slots).
  // At a cap, the connection pending longest (of the address, or of all) makes room for the new
  // one: a player who connects and says hello at once always gets in, and an attacker who holds
  // many connections without a hello only closes his own oldest (one closed or past its hello
  // has left the list).
  std::shared_ptr<session> evicted_address, evicted_total;
  {
    const std::lock_guard lock(pending_mutex);
    auto& from_address = pending_by_address[s->address()];
    const auto evict = [&](std::list<std::shared_ptr<session>>::iterator at) {
      std::shared_ptr<session> old = *at;
      old->pending = false;
      pending.erase(at);
      const auto it = pending_by_address.find(old->address());
      if (it != pending_by_address.end() && --it->second == 0 && &it->second != &from_address) pending_by_address.erase(it);
      --counters.pending_open;
      return old;
    };
    // The victim: the oldest candidate whose socket holds no unread bytes. One with bytes waiting
    // has sent its first frame (a client says hello at once) that its lane has not read yet (this
    // accept batch ran first): it is spared while a candidate without any is found among the 16
    // oldest; failing that the oldest goes (the cap holds).
    const auto victim = [&](auto match) {
      auto first = pending.end();
      std::size_t looked = 0;
      for (auto it = pending.begin(); it != pending.end() && looked < 16; ++it) {
        if (!match(**it)) continue;
        if (first == pending.end()) first = it;
        if ((*it)->unread_bytes() == 0) {
          counters.pending_spared += looked;
          return it;
        }
        ++looked;
      }
      return first;
    };
    if (from_address >= opt.max_pending_per_address) {
      const auto oldest = victim([&](const session& p) { return p.address() == s->address(); });
      if (oldest != pending.end()) {
        evicted_address = evict(oldest);
        ++counters.pending_evicted_address;
      }
    }
    if (pending.size() >= opt.max_pending && !pending.empty()) {
      evicted_total = evict(victim([](const session&) { return true; }));
      ++counters.pending_evicted;
    }
    ++from_address;
    s->pending = true;
    s->pending_at = pending.insert(pending.end(), s);
    ++counters.pending_open;
  }
  if (evicted_address) evicted_address->fail(error_code::server_full, "too many connections from this address waiting for their hello");
  if (evicted_total) evicted_total->fail(error_code::server_full, "too many connections waiting for their hello");
  {
    const std::lock_guard lock(sessions_mutex);
    sessions.emplace(id, s);
  }
  s->start();
}

void server::impl::do_accept() {
  acceptor.async_wait(tcp::acceptor::wait_read, [this](const boost::system::error_code& ec) {
    if (ec == asio::error::operation_aborted || !acceptor.is_open()) return;
    if (ec) return accept_failed(ec.value());
    accept_ready();
  });
}

void server::impl::accept_ready() {
  // Take what waits in the backlog now, not one connection per completion: a completion waits its
  // turn behind every ready handler of the I/O threads, so a busy server accepted about one
  // connection per round of its I/O queue (~1 per tick), the backlog filled, and once the wait
  // passed the clients' connect timeout every later client failed while the server spent its
  // accepts on clients that had given up.
  for (std::size_t n = 0; n < accept_batch; ++n) {
    sockaddr_storage peer{};
    socklen_t len = sizeof peer;
    const int fd = ::accept4(acceptor.native_handle(), reinterpret_cast<sockaddr*>(&peer), &len, SOCK_NONBLOCK | SOCK_CLOEXEC);
    if (fd >= 0) {
      admit(fd, peer, len);
      continue;
    }
    const int err = errno;
    if (err == EAGAIN || err == EWOULDBLOCK) return do_accept();  // the backlog is empty: wait for the next
    if (err == EINTR || err == ECONNABORTED || err == EPROTO) continue;  // that connection is gone; go on
    return accept_failed(err);
  }
  // A full batch: the rest after the lane's other handlers (reads, writes), not after a wait that
  // only a new connection would end.
  asio::post(acceptor.get_executor(), [this] {
    if (acceptor.is_open()) accept_ready();
  });
}

void server::impl::accept_failed(int err) {
  // Out of file descriptors (or memory): the pending connection stays in the backlog; say why (at
  // most once a second) and try again shortly instead of spinning on the error.
  const bool out_of_files = err == EMFILE || err == ENFILE;
  const auto now = steady::now();
  if (now - last_accept_warning > std::chrono::seconds(1)) {
    last_accept_warning = now;
    if (out_of_files) {
      spdlog::error("accept failed: {} ({} sessions open, open-file limit {}): raise the hard limit "
                    "(ulimit -Hn, or LimitNOFILE= under systemd) or lower --max-clients",
                    std::strerror(err), counters.sessions_open.load(), file_limit);
    } else {
      spdlog::warn("accept failed: {}", std::strerror(err));
    }
  }
  accept_retry.expires_after(std::chrono::milliseconds(out_of_files ? 50 : 1));
  accept_retry.async_wait([this](const boost::system::error_code& e) {
    if (!e && acceptor.is_open()) accept_ready();
  });
}

// ---------------------------------------------------------------------------------------------

server::server(server_options opt) : impl_(std::make_unique<impl>(std::move(opt))) {}

server::~server() { stop(); }

const server_options& server::options() const { return impl_->opt; }

std::uint64_t server::now_us() const { return impl_->now_us(); }

std::optional<std::string> server::start() {
  auto& m = *impl_;
  if (m.running) return "server already started";
  if (auto err = check_cpus_allowed(m.opt.io_thread_cpus)) return "io_thread_cpus: " + *err;
  // Every session is a file descriptor: raise the soft limit to the hard one and say whether
  // max_connections fits.
  const auto files = raise_open_file_limit();
  m.file_limit = files.soft;
  if (!files.error.empty()) spdlog::warn("{}", files.error);
  spdlog::info("open-file limit {} (was {}, hard {})", files.soft, files.before, files.hard);
  // Player slots and pending connections together must fit (the metrics server's few come out of
  // the reserve): then nothing else in the process can take a player's descriptor.
  if (files.soft != 0 && m.opt.max_connections + m.opt.max_pending + reserved_file_descriptors > files.soft) {
    spdlog::warn("max-clients {} plus max-pending {} exceed what the open-file limit {} allows (about {} connections): "
                 "raise the hard limit (ulimit -Hn) or connections beyond it are refused by the system",
                 m.opt.max_connections, m.opt.max_pending, files.soft,
                 files.soft > reserved_file_descriptors ? files.soft - reserved_file_descriptors : 0);
  }
  // Refused connections are held only in descriptors nobody else is counted on for.
  const std::size_t budgeted = m.opt.max_connections + m.opt.max_pending + reserved_file_descriptors;
  m.held_cap = files.soft == 0 ? max_held : (files.soft > budgeted ? std::min<std::size_t>(max_held, files.soft - budgeted) : 0);
  boost::system::error_code ec;
  const auto address = asio::ip::make_address(m.opt.address, ec);
  if (ec) return "bad listen address '" + m.opt.address + "': " + ec.message();
  const tcp::endpoint endpoint(address, m.opt.port);
  m.acceptor.open(endpoint.protocol(), ec);
  if (!ec) m.acceptor.set_option(tcp::acceptor::reuse_address(true), ec);
  if (!ec) m.acceptor.bind(endpoint, ec);
  if (!ec) m.acceptor.listen(asio::socket_base::max_listen_connections, ec);
  if (!ec) m.acceptor.non_blocking(true, ec);  // do_accept drains the backlog with synchronous accepts
  if (ec) {
    boost::system::error_code ignored;
    m.acceptor.close(ignored);
    return "cannot listen on " + m.opt.address + ":" + std::to_string(m.opt.port) + ": " + ec.message();
  }
  m.bound_port = m.acceptor.local_endpoint(ec).port();
  // The writes: io_uring on every lane, or sendmsg on every lane. Each lane's table of registered
  // files as large as asked, within the open-file limit (the kernel's bound on it).
  std::string why_not;
  const auto file_slots = static_cast<unsigned>(
      std::min<std::size_t>({m.opt.ring_file_slots, files.soft == 0 ? m.opt.ring_file_slots : files.soft, 1u << 20}));
  for (auto& lane : m.lanes) lane->drain_slice = std::max<std::size_t>(m.opt.write_slice, 1);
  if (m.opt.batching != write_batching::sendmsg) {
    for (auto& lane : m.lanes) {
      if (auto err = lane->init_ring(file_slots)) {
        why_not = *err;
        break;
      }
    }
    m.uring = why_not.empty();
    if (!m.uring) {
      for (auto& lane : m.lanes) lane->drop_ring();  // all lanes alike
      if (m.opt.batching == write_batching::uring) {
        boost::system::error_code ignored;
        m.acceptor.close(ignored);
        return "io_uring writes asked for but unavailable: " + why_not;
      }
    }
  }
  const auto n = static_cast<unsigned>(m.lanes.size());
  for (auto& lane : m.lanes) {
    lane->ctx.restart();  // a server started again: its stop() stopped the event loops
    lane->work.emplace(lane->ctx.get_executor());
  }
  m.do_accept();
  for (std::size_t i = 0; i < m.lanes.size(); ++i) {
    m.lanes[i]->thread =
        std::thread([l = m.lanes[i].get(), i, nice = m.opt.io_thread_nice, cpus = m.opt.io_thread_cpus] {
          // Named for per-thread CPU readings (top -H, /proc/<pid>/task/*/comm).
          char name[16];
          std::snprintf(name, sizeof name, "zone-io-%zu", i);
          pthread_setname_np(pthread_self(), name);
          if (nice != 0 && ::setpriority(PRIO_PROCESS, static_cast<id_t>(::gettid()), nice) != 0) {
            spdlog::warn("I/O thread {}: setpriority({}) failed: {}", i, nice, std::strerror(errno));
          }
          if (auto err = pin_current_thread(cpus)) spdlog::warn("I/O thread {}: not pinned: {}", i, *err);
          l->ctx.run();
        });
  }
  m.running = true;
  spdlog::info(
      "zone server listening on {}:{} ({} I/O threads{}{}, {}, {})", m.opt.address, port(), n,
      m.opt.io_thread_nice != 0 ? " at nice " + std::to_string(m.opt.io_thread_nice) : std::string(),
      m.opt.io_thread_cpus.empty() ? std::string() : " on CPUs " + format_cpu_list(m.opt.io_thread_cpus),
      m.opt.direct_writes ? "direct writes"
                          : "I/O-thread writes, " + std::to_string(m.lanes.front()->drain_slice) + " sessions a slice",
      m.uring ? std::string("batched through io_uring")
              : "sendmsg per write" + (why_not.empty() ? std::string() : " (io_uring unavailable: " + why_not + ")"));
  return std::nullopt;
}

std::uint16_t server::port() const { return impl_->bound_port; }

void server::stop() {
  auto& m = *impl_;
  if (!m.running) return;
  m.running = false;
  asio::post(m.acceptor.get_executor(), [&m] {  // on lane 0, like the acceptor's handlers
    boost::system::error_code ignored;
    m.acceptor.close(ignored);
    m.accept_retry.cancel();
    m.held_timer.cancel();
    m.release_held(true);
  });
  std::vector<std::shared_ptr<session>> open;
  {
    const std::shared_lock lock(m.sessions_mutex);
    for (auto& [id, s] : m.sessions) open.push_back(s);
  }
  for (auto& s : open) s->close("server stopping");
  open.clear();
  for (auto& lane : m.lanes) lane->work.reset();
  // Sessions close on their I/O threads; give them a moment, then stop whatever is left.
  const auto deadline = steady::now() + std::chrono::seconds(2);
  for (;;) {
    {
      const std::shared_lock lock(m.sessions_mutex);
      if (m.sessions.empty()) break;
    }
    if (steady::now() > deadline) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  for (auto& lane : m.lanes) lane->ctx.stop();
  for (auto& lane : m.lanes) {
    if (lane->thread.joinable()) lane->thread.join();
    if (lane.get() == m.lanes.front().get()) m.release_held(true);  // the acceptor's lane has stopped: what it still held
    // Sessions left on a ready list hold themselves; let them go.
    lane->forget_ready();
  }
  {
    const std::lock_guard lock(m.sessions_mutex);
    m.sessions.clear();
  }
  {
    const std::lock_guard lock(m.pending_mutex);
    for (auto& s : m.pending) s->pending = false;
    m.pending.clear();
    m.pending_by_address.clear();
  }
  spdlog::info("zone server stopped");
}

void server::poll(std::vector<inbound_event>& out) {
  auto& m = *impl_;
  const std::lock_guard lock(m.events_mutex);
  if (out.empty()) {
    out.swap(m.events);
  } else {
    std::move(m.events.begin(), m.events.end(), std::back_inserter(out));
    m.events.clear();
  }
}

std::shared_ptr<const std::atomic<std::uint32_t>> server::state_backlog(session_id s) const {
  const std::shared_lock lock(impl_->sessions_mutex);
  const auto it = impl_->sessions.find(s);
  if (it == impl_->sessions.end()) return nullptr;
  return it->second->backlog();
}

std::size_t server::drop_stale_state(session_id s) {
  std::shared_ptr<session> target;
  {
    const std::shared_lock lock(impl_->sessions_mutex);
    const auto it = impl_->sessions.find(s);
    if (it == impl_->sessions.end()) return 0;
    target = it->second;
  }
  return target->drop_stale();
}

std::shared_ptr<const std::atomic<std::uint64_t>> server::bytes_written(session_id s) const {
  const std::shared_lock lock(impl_->sessions_mutex);
  const auto it = impl_->sessions.find(s);
  if (it == impl_->sessions.end()) return nullptr;
  return it->second->written();
}

bool server::send(session_id s, shared_frame frame, delivery d) {
  std::shared_ptr<session> target;
  {
    const std::shared_lock lock(impl_->sessions_mutex);
    const auto it = impl_->sessions.find(s);
    if (it == impl_->sessions.end()) return false;
    target = it->second;
  }
  target->enqueue_and_schedule(std::move(frame), d);
  return true;
}

std::size_t server::send_many(std::span<const outgoing_frame> frames) { return impl_->send_many(frames); }

std::size_t server::send_many_moved(std::span<outgoing_frame> frames) { return impl_->send_many(frames); }

template <class Frames>
std::size_t server::impl::send_many(Frames frames) {
  auto& m = *this;
  // Per thread, reused: the sessions of the frames, then those their lanes must be told of.
  thread_local std::vector<std::shared_ptr<session>> targets, ready;
  targets.clear();
  {
    const std::shared_lock lock(m.sessions_mutex);
    for (const auto& f : frames) {
      const auto it = m.sessions.find(f.session);
      targets.push_back(it == m.sessions.end() ? nullptr : it->second);
    }
  }
  std::size_t sent = 0;
  ready.clear();
  for (std::size_t i = 0; i < frames.size(); ++i) {
    if (!targets[i]) {
      if constexpr (!std::is_const_v<typename Frames::element_type>) frames[i].frame = {};
      continue;
    }
    ++sent;
    // A span of non-const frames is taken (moved from), so no count is touched for a copy.
    auto frame = [&]() -> decltype(auto) {
      if constexpr (std::is_const_v<typename Frames::element_type>) {
        return frames[i].frame;
      } else {
        return std::move(frames[i].frame);
      }
    };
    if (targets[i]->enqueue(frame(), frames[i].kind, frames[i].stamp_us)) ready.push_back(std::move(targets[i]));
  }
  targets.clear();
  // One append per lane (few lanes: a pass over the list for each lane that has a session in it).
  for (std::size_t i = 0; i < ready.size(); ++i) {
    if (!ready[i]) continue;
    io_lane& lane = ready[i]->lane();
    std::size_t n = 0;
    for (std::size_t j = i; j < ready.size(); ++j) {
      if (ready[j] && &ready[j]->lane() == &lane) std::swap(ready[i + n++], ready[j]);
    }
    lane.schedule_many(std::span(ready).subspan(i, n));  // leaves them null
    i += n - 1;
  }
  ready.clear();
  return sent;
}

void server::disconnect(session_id s, error_code code, std::string reason) {
  std::shared_ptr<session> target;
  {
    const std::shared_lock lock(impl_->sessions_mutex);
    const auto it = impl_->sessions.find(s);
    if (it == impl_->sessions.end()) return;
    target = it->second;
  }
  target->fail(code, std::move(reason));
}

latency_histogram_us server::frame_write_age() const {
  latency_histogram_us sum;
  for (const auto& h : impl_->write_age) sum.add(h);
  return sum;
}

server_stats server::stats() const {
  const auto& c = impl_->counters;
  std::uint64_t frames_out = 0, writes = 0, bytes_out = 0;
  for (const auto& w : impl_->write_stats) {
    frames_out += w.frames_out.load();
    writes += w.writes.load();
    bytes_out += w.bytes_out.load();
  }
  server_stats st;
  st.connections_accepted = c.connections_accepted.load();
  st.connections_refused = c.connections_refused.load();
  st.sessions_open = c.sessions_open.load();
  st.pending_open = c.pending_open.load();
  st.pending_evicted_address = c.pending_evicted_address.load();
  st.pending_evicted = c.pending_evicted.load();
  st.hello_timeouts = c.hello_timeouts.load();
  st.connections_rate_limited = c.connections_rate_limited.load();
  st.connections_charged = c.connections_charged.load();
  st.pending_spared = c.pending_spared.load();
  st.hellos_rejected = c.hellos_rejected.load();
  st.idle_timeouts = c.idle_timeouts.load();
  st.rate_limited = c.rate_limited.load();
  st.frames_in = c.frames_in.load();
  st.frames_out = frames_out;
  st.writes = writes;
  st.write_batches = impl_->write_batches.load();
  st.registered_sends = impl_->registered_sends.load();
  st.bytes_in = c.bytes_in.load();
  st.bytes_out = bytes_out;
  st.frames_dropped = c.frames_dropped.load();
  st.resyncs_requested = c.resyncs_requested.load();
  st.stale_drops = c.stale_drops.load();
  st.frames_rejected = c.frames_rejected.load();
  st.inputs_dropped = c.inputs_dropped.load();
  st.pings_answered = c.pings_answered.load();
  st.pings_dropped = c.pings_dropped.load();
  return st;
}

bool server::uses_io_uring() const { return impl_->uring; }

}  // namespace zone::net
