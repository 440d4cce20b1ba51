// The bot swarm (swarm.h): one Boost.Asio io_context on several threads, one strand per bot.
#include <utility>

#include <boost/asio.hpp>

#include "swarm.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <deque>
#include <memory>
#include <random>
#include <span>
#include <thread>
#include <variant>

#include <sys/resource.h>

namespace zone::bots {

namespace asio = boost::asio;
using tcp = asio::ip::tcp;
using steady = std::chrono::steady_clock;

// ---------------------------------------------------------------------------------------------
// The swarm

namespace {

std::uint64_t local_us(steady::time_point epoch) {
  return static_cast<std::uint64_t>(std::chrono::duration_cast<std::chrono::microseconds>(steady::now() - epoch).count());
}

/// Latest known position of each bot's own entity, written by whichever bot sees it (the server
/// never tells an observer its own position). Indexed by slot of the entity handle; striped locks.
class position_board {
 public:
  struct fix {
    std::uint64_t tick = 0;
    net::vec3f pos{};
    bool known = false;
  };
  position_board() : entries_(std::size_t{1} << 20) {}
  void claim(std::uint32_t id) {
    auto& e = entries_[id & mask];
    std::lock_guard lock(stripe(id));
    e.id.store(id, std::memory_order_relaxed);
    e.value = {};
  }
  void release(std::uint32_t id) {
    auto& e = entries_[id & mask];
    std::lock_guard lock(stripe(id));
    if (e.id.load(std::memory_order_relaxed) == id) e.id.store(0, std::memory_order_relaxed);
  }
  /// Records a position of `id` at `tick` if `id` is a bot's entity and the fix is newer.
  void report(std::uint32_t id, std::uint64_t tick, const net::vec3f& p) {
    auto& e = entries_[id & mask];
    if (e.id.load(std::memory_order_relaxed) != id) return;
    std::lock_guard lock(stripe(id));
    if (e.id.load(std::memory_order_relaxed) == id && (!e.value.known || tick >= e.value.tick)) e.value = {tick, p, true};
  }
  [[nodiscard]] fix get(std::uint32_t id) {
    auto& e = entries_[id & mask];
    if (e.id.load(std::memory_order_relaxed) != id) return {};
    std::lock_guard lock(stripe(id));
    return e.id.load(std::memory_order_relaxed) == id ? e.value : fix{};
  }

 private:
  static constexpr std::uint32_t mask = (1u << 20) - 1;
  struct entry {
    std::atomic<std::uint32_t> id{0};
    fix value;
  };
  std::mutex& stripe(std::uint32_t id) { return stripes_[(id & mask) % stripes_.size()]; }
  std::vector<entry> entries_;
  std::array<std::mutex, 64> stripes_;
};

class swarm;
net::decoder_options client_decoder(std::size_t max_frame);

/// One session of one bot slot: connect, hello, play, close. Churn ends a session and starts a new
/// one for the same slot. All handlers run on the thread of the session's io_context (one thread
/// per context), so they never run concurrently.
class bot_session : public std::enable_shared_from_this<bot_session> {
 public:
  bot_session(swarm& s, std::size_t slot, unsigned thread, behaviour kind, std::uint64_t seed);
  /// A session that follows a redirect: connects to `to` and says hello with `token`.
  void redirect_to(const tcp::endpoint& to, std::string token) {
    endpoint_override_ = to;
    token_ = std::move(token);
  }
  /// A login again after a lost connection (--reconnect): `since` is when the first retry began;
  /// with a resume token (the slot's last welcome's) the hello says it to get the entity back.
  void reconnect_to(const tcp::endpoint& to, steady::time_point since, std::string resume_token = {}) {
    endpoint_override_ = to;
    reconnecting_since_ = since;
    resuming_ = !resume_token.empty();
    token_ = std::move(resume_token);
  }
  void start();
  void logout();  ///< graceful, intended close (churn, end of run)
  /// --cut: the connection drops without a leave (as a network would drop it); the slot logs in
  /// again after relogin_delay_s, saying its resume token when it has one.
  void cut();
  std::size_t slot() const { return slot_; }
  bool playing() const { return playing_.load(std::memory_order_relaxed); }

 private:
  void on_connect(const boost::system::error_code& ec);
  void read_next();
  void on_read(const boost::system::error_code& ec, std::size_t n);
  void on_frame(const net::frame_view& f, std::uint64_t received_us);
  void on_welcome(const net::wire::welcome& w);
  void on_tick_update(const net::wire::tick_update& u, std::uint64_t received_us);
  void on_class_changes(const net::wire::class_changes& c);
  /// 0: unchecked (own position unknown), 1: inside, 2: violation (reported).
  int check_aoi(const position_board::fix& own, std::uint64_t tick, std::uint32_t id, const net::vec3f& p,
                 const net::vec3f& half);
  void send(const net::message& m);
  void write_next();
  void schedule_input();
  void schedule_ping();
  void schedule_teleport();
  void schedule_visibility_switch();
  void send_input();
  void maybe_send_input(std::uint64_t now_us);
  net::vec3f steer();
  void fail(const std::string& why, bool connection_failure);
  /// An error frame the server sent before it closed, still unread in the socket ("code: reason").
  std::optional<std::string> server_error_waiting();
  void close();
  /// Where this session connects: its redirect's or reconnect's zone, else the swarm's --port.
  [[nodiscard]] tcp::endpoint endpoint_now() const;
  /// Closes this session and logs its slot in again at `to` after `delay_s` (-1: --relogin-delay,
  /// at least 50 ms), saying the slot's resume token when --resume.
  void log_in_again(const tcp::endpoint& to, steady::time_point since, double delay_s);
  void flush_counts();

  swarm& s_;
  std::optional<tcp::endpoint> endpoint_override_;
  std::string token_;
  bool resuming_ = false;  ///< token_ is a resume token (the hello asks for the entity back)
  std::optional<steady::time_point> reconnecting_since_;
  std::size_t slot_;
  behaviour kind_;
  std::mt19937_64 rng_;
  unsigned thread_;
  asio::io_context& io_;
  tcp::socket socket_;
  asio::steady_timer input_timer_, ping_timer_, welcome_timer_, teleport_timer_, switch_timer_;
  bool stealth_ = false;   ///< the visibility this session chose (hello, then set_visibility)
  std::uint8_t team_ = 0;
  bool chooses_ = false;   ///< it chose stealth or a team at hello: it also switches during play
  net::frame_decoder decoder_;
  net::encoder encoder_;
  /// Outbound bytes: frames queued while a write is in flight go out together in the next write.
  std::vector<std::uint8_t> out_queued_, out_writing_;
  bool writing_ = false, closed_ = false, intended_ = false, got_error_ = false;
  bool leaving_ = false;     ///< logout(): the leave is being written; closed once it is (or after 1 s)
  bool connecting_ = false;  ///< counted in connecting_now: started, not yet welcomed
  /// The welcome arrived, or the session ended before: it leaves connecting_now.
  void connect_done();
  std::atomic<bool> playing_{false};
  std::uint32_t entity_ = 0;
  std::uint64_t instance_ = 0;  ///< the server's, as its welcome told it (which oracle checks this session)
  std::optional<net::client_view> view_;
  net::vec3f q_err_{};
  // The AOI check's assumptions: the welcome's rules, or the swarm's flags for an older server.
  net::vec3f aoi_{};
  float hysteresis_ = 0, max_speed_ = 0;
  double tick_rate_ = 30;
  steady::time_point welcomed_at_{};
  steady::time_point launched_at_{}, connected_at_{};  ///< start(), on_connect() (the login's durations)
  std::uint32_t sequence_ = 0;
  std::uint64_t inputs_ = 0;  ///< intent evaluations
  std::uint64_t next_input_us_ = 0, last_input_sent_us_ = 0;
  net::vec3f last_move_{};
  bool any_input_sent_ = false;
  net::vec3f heading_{1, 0, 0};
  net::world_bounds world_{};
  bool jumped_ = false;  ///< this session teleported (a board fix from before may be far off)
  position_board::fix own_fix_{};  ///< the latest self_position (only the leader's goes on the board)
  /// Counts not yet added to the swarm's shared counters (flush_counts, every few frames and at close).
  struct {
    std::uint64_t tick_updates = 0, enters = 0, leaves = 0, updates = 0, resets = 0, digests_checked = 0,
                  aoi_checked = 0, aoi_unchecked = 0, self_positions = 0, latency_unsynced = 0, frames_in = 0,
                  bytes_in = 0, inputs_sent = 0, inputs_unchanged = 0;
  } local_;
  std::uint64_t frames_seen_ = 0;
  /// The frame being applied, for the position visitor's AOI check.
  struct {
    position_board::fix own{};
    std::uint64_t tick = 0;
    bool relay = false;
    std::array<std::uint64_t, 3> counts{};  // unchecked, inside, violations
  } frame_check_;
};

/// Frames between two flushes of a bot's counts into the swarm's counters.
constexpr std::uint64_t flush_every_frames = 8;

class swarm {
 public:
  explicit swarm(const swarm_options& opt)
      : opt_(opt), slots_(opt.bots), resume_tokens_(opt.bots), sessions_(opt.bots) {
    // One io_context per I/O thread, each run by that thread alone (concurrency hint 1): a bot's
    // handlers all run on its context's thread, so a bot needs no strand, and the threads share
    // no scheduler queue, reactor or timer heap. Each thread records latencies in its own histogram.
    const unsigned threads = std::max(1u, opt.threads);
    for (unsigned t = 0; t < threads; ++t) {
      ios_.push_back(std::make_unique<asio::io_context>(1));
      latency_.push_back(std::make_unique<latency_histogram_us>());
    }
    double total = 0;
    for (const double m : opt_.mix) total += std::max(0.0, m);
    if (total <= 0) opt_.mix = {1, 0, 0, 0, 0}, total = 1;
    // Deterministic, proportional assignment of behaviours to slots (largest remainder by prefix).
    for (std::size_t i = 0; i < opt.bots; ++i) {
      double acc = 0;
      const double x = (static_cast<double>(i) + 0.5) / static_cast<double>(opt.bots) * total;
      std::size_t k = 0;
      for (; k < behaviour_count; ++k) {
        acc += std::max(0.0, opt_.mix[k]);
        if (x < acc) break;
      }
      slots_[i].kind = static_cast<behaviour>(std::min<std::size_t>(k, behaviour_count - 1));
    }
  }

  run_outcome run(progress_fn progress) {
    run_outcome out;
    try {
      tcp::resolver resolver(*ios_[0]);
      auto results = resolver.resolve(opt_.host, std::to_string(opt_.port));
      if (results.empty()) throw std::runtime_error("no address");
      endpoint_ = results.begin()->endpoint();
      loopback_ = endpoint_.address().is_loopback();
    } catch (const std::exception& e) {
      out.error = "cannot resolve " + opt_.host + ": " + e.what();
      return out;
    }
    if (opt_.oracle) {
      if (auto err = start_oracles()) {
        out.error = *err;
        return out;
      }
      follower_ = std::thread([this] { follow_restarts(); });
    }
    epoch_ = steady::now();
    std::vector<asio::executor_work_guard<asio::io_context::executor_type>> guards;
    std::vector<std::thread> threads;
    for (auto& io : ios_) {
      guards.push_back(asio::make_work_guard(*io));
      threads.emplace_back([&ctx = *io] { ctx.run(); });
    }

    // Ramp-up: launch bots at opt.ramp per second, in 10 ms steps; then churn.
    const auto start = steady::now();
    const auto end = start + std::chrono::duration_cast<steady::duration>(std::chrono::duration<double>(opt_.duration_s));
    std::size_t launched = 0;
    auto next_second = start + std::chrono::seconds(1);
    auto prev_lat = latency_snapshot();
    latency_histogram_us::counts steady_start{};  // the counts when every bot was first connected
    double steady_from = -1;
    second_sample prev{};
    double churn_debt = 0, cut_debt = 0;
    std::mt19937_64 churn_rng(12345);
    auto last_step = start;
    while (steady::now() < end) {
      const auto now = steady::now();
      const double since = std::chrono::duration<double>(now - start).count();
      const auto due = std::min<std::size_t>(opt_.bots, static_cast<std::size_t>(opt_.ramp * since) + 1);
      for (; launched < due && (opt_.max_connecting == 0 || c_.connecting_now.load() < opt_.max_connecting); ++launched) {
        launch(launched);
      }
      if (opt_.churn > 0 && launched == opt_.bots && (opt_.churn_for_s <= 0 || since < opt_.churn_for_s)) {
        churn_debt += opt_.churn * std::chrono::duration<double>(now - last_step).count();
        for (; churn_debt >= 1; churn_debt -= 1) churn_one(churn_rng);
      }
      if (opt_.cut > 0 && launched == opt_.bots && (opt_.churn_for_s <= 0 || since < opt_.churn_for_s)) {
        cut_debt += opt_.cut * std::chrono::duration<double>(now - last_step).count();
        for (; cut_debt >= 1; cut_debt -= 1) churn_one(churn_rng, true);
      }
      last_step = now;
      if (now >= next_second) {
        next_second += std::chrono::seconds(1);
        second_sample s;
        s.t = since;
        s.connected = c_.connected_now.load();
        s.frames = c_.frames_in.load();
        s.bytes = c_.bytes_in.load();
        s.enters = c_.enters.load();
        s.leaves = c_.leaves.load();
        s.updates = c_.updates.load();
        s.mismatches = c_.mismatches();
        for (const auto& z : oracles()) s.mismatches += z.check->counters().mismatches();
        const auto lat = latency_snapshot();
        if (steady_from < 0 && s.connected >= opt_.bots) {
          steady_from = since;
          steady_start = lat;
        }
        latency_histogram_us::counts window{};
        for (int b = 0; b < latency_histogram_us::buckets; ++b) {
          window[static_cast<std::size_t>(b)] = lat[static_cast<std::size_t>(b)] - prev_lat[static_cast<std::size_t>(b)];
        }
        s.p50_ms = percentile_ms(window, 0.5);
        s.p99_ms = percentile_ms(window, 0.99);
        s.max_window_ms = percentile_ms(window, 1.0);
        prev_lat = lat;
        // The series holds per-second deltas of the counters.
        second_sample d = s;
        d.frames -= prev.frames, d.bytes -= prev.bytes, d.enters -= prev.enters, d.leaves -= prev.leaves,
            d.updates -= prev.updates;
        prev = s;
        series_.push_back(d);
        if (progress) progress(d, c_, opt_);
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    // End of run: log every bot out, let the strands finish, stop.
    stopping_.store(true);
    for (std::size_t i = 0; i < sessions_.size(); ++i) {
      std::shared_ptr<bot_session> b;
      {
        std::lock_guard lock(sessions_mutex_);
        b = sessions_[i];
      }
      if (b) b->logout();
    }
    guards.clear();
    const auto drain_deadline = steady::now() + std::chrono::seconds(3);
    const auto all_stopped = [&] {
      return std::all_of(ios_.begin(), ios_.end(), [](const auto& io) { return io->stopped(); });
    };
    while (!all_stopped() && steady::now() < drain_deadline) std::this_thread::sleep_for(std::chrono::milliseconds(10));
    for (auto& io : ios_) io->stop();
    for (auto& t : threads) t.join();
    {
      std::lock_guard lock(sessions_mutex_);
      for (auto& s : sessions_) s.reset();
    }

    swarm_result& r = out.result;
    if (follower_.joinable()) follower_.join();
    if (!oracles().empty()) {
      // The views still waiting for their truth are checked first; a world's zones' oracles add up,
      // and so do the successive servers of a zone that was restarted.
      for (auto& z : oracles()) z.check->catch_up(60);
      r.oracle_on = true;
      // A zone that started later (a standby) took over a region whose zone died: it explains one
      // stream that ended without a server answering at its address again.
      std::size_t taken_over = 0;
      for (std::size_t k = 0; k < later_count_; ++k) taken_over += later_[k].up.load() ? 1 : 0;
      for (auto& z : oracles()) {
        z.check->stop();
        auto q = z.check->report();
        if (z.followed) {  // its server was replaced: the end of its stream is explained
          q.stream_error.clear();
          ++r.oracle.truth_restarts;
        } else if (!q.stream_error.empty() && taken_over > 0) {
          --taken_over;
          q.stream_error.clear();
          ++r.oracle.truth_restarts;
        }
        if (z.after_restart) r.oracle.frames_checked_after_restart += q.frames_checked;
        add_report(r.oracle, q, z.at);
      }
      r.oracle.frames_unchecked += oracle_unrouted_.load();
      r.oracle.frames_unsampled += oracle_unrouted_unsampled_.load();
    }
    r.rules_from_server = rules_told.load();
    r.options = opt_;
    r.elapsed_s = std::chrono::duration<double>(steady::now() - start).count();
    r.slots = slots_;
    r.series = series_;
    r.latency = latency_snapshot();
    r.connect_time = connect_time_.snapshot();
    r.welcome_time = welcome_time_.snapshot();
    r.connect_max_ms = connect_time_.max() / 1000.0;
    r.welcome_max_ms = welcome_time_.max() / 1000.0;
    for (const auto& h : latency_) r.latency_max_ms = std::max(r.latency_max_ms, h->max() / 1000.0);
    if (steady_from >= 0) {
      r.steady_from_s = steady_from;
      for (std::size_t b = 0; b < r.latency.size(); ++b) r.steady_latency[b] = r.latency[b] - steady_start[b];
    }
    {
      std::lock_guard lock(problems_mutex_);
      r.problems = problems_;
      r.problems_total = problems_total_;
    }
    r.connect_attempts = c_.connect_attempts, r.welcomes = c_.welcomes, r.connect_failures = c_.connect_failures;
    r.unexpected_disconnects = c_.unexpected_disconnects, r.server_errors = c_.server_errors, r.logouts = c_.logouts;
    r.frames_in = c_.frames_in, r.bytes_in = c_.bytes_in, r.tick_updates = c_.tick_updates, r.enters = c_.enters;
    r.leaves = c_.leaves, r.updates = c_.updates, r.resets = c_.resets, r.inputs_sent = c_.inputs_sent;
    r.inputs_unchanged = c_.inputs_unchanged;
    r.pongs = c_.pongs, r.digests_checked = c_.digests_checked, r.digest_mismatches = c_.digest_mismatches;
    r.inconsistent = c_.inconsistent, r.aoi_checked = c_.aoi_checked, r.aoi_unchecked = c_.aoi_unchecked;
    r.aoi_violations = c_.aoi_violations, r.latency_unsynced = c_.latency_unsynced;
    r.teleports_sent = c_.teleports_sent, r.self_positions = c_.self_positions, r.redirects = c_.redirects;
    r.gate_redirects = c_.gate_redirects;
    r.stealth_joins = c_.stealth_joins, r.team_joins = c_.team_joins, r.visibility_switches_sent = c_.visibility_switches_sent;
    r.class_notes = c_.class_notes;
    r.reconnects = c_.reconnects;
    r.resumes = c_.resumes;
    r.resumes_refused = c_.resumes_refused;
    r.cuts = c_.cuts;
    r.host_clock = host_clock_.load();
    for (const auto& s : slots_) r.bots_connected += s.ever_connected ? 1 : 0;
    r.min_rtt_ms = best_rtt_us_.load() == UINT64_MAX ? 0 : static_cast<double>(best_rtt_us_.load()) / 1000.0;
    rusage ru{};
    if (::getrusage(RUSAGE_SELF, &ru) == 0) {
      r.cpu_s = static_cast<double>(ru.ru_utime.tv_sec + ru.ru_stime.tv_sec) +
                static_cast<double>(ru.ru_utime.tv_usec + ru.ru_stime.tv_usec) / 1e6;
    }
    return out;
  }

  void launch(std::size_t slot, std::optional<tcp::endpoint> to = std::nullopt, std::string token = {}) {
    std::uint64_t seed = 0;
    {
      std::lock_guard lock(sessions_mutex_);
      seed = 0x9e3779b9ull * (slot + 1) + (seed_++);
    }
    auto b = std::make_shared<bot_session>(*this, slot, thread_of(slot), slots_[slot].kind, seed);
    if (to) b->redirect_to(*to, std::move(token));
    {
      std::lock_guard lock(sessions_mutex_);
      sessions_[slot] = b;
    }
    b->start();
  }

  /// The truth stream of the server at `to` ended and the follower has not read the server that
  /// answers there now, nor given up on it (follow_restarts); not when nothing answers there (the
  /// login is refused and goes elsewhere: nothing to wait for).
  [[nodiscard]] bool truth_pending(const tcp::endpoint& to) const {
    for (const auto& z : oracles()) {
      if (z.at == to && z.check->ended() && !z.followed.load() && !z.given_up.load() && !z.silent.load()) return true;
    }
    for (std::size_t k = 0; k < later_count_; ++k) {
      if (later_[k].at == to && !later_[k].up.load()) return true;  // a zone not started yet
    }
    return false;
  }

  /// A new session for `slot` at `to` after relogin_delay_s (--reconnect). While the oracle waits
  /// to follow a restarted server at `to` (at most 10 s), the login waits too: an entity that
  /// joined before the oracle's new stream began is never checked (it has no history there).
  void relaunch_later(std::size_t slot, const tcp::endpoint& to, steady::time_point since, double delay_s = -1,
                      std::optional<steady::time_point> waiting_since = {}, std::string resume_token = {}) {
    auto timer = std::make_shared<asio::steady_timer>(*ios_[thread_of(slot)]);
    const double delay = delay_s >= 0 ? delay_s : std::max(0.05, opt_.relogin_delay_s);
    timer->expires_after(std::chrono::duration_cast<steady::duration>(std::chrono::duration<double>(delay)));
    timer->async_wait([this, timer, slot, to, since, waiting_since, resume_token](const boost::system::error_code& ec) {
      if (ec || stopping_.load()) return;
      const auto now = steady::now();
      if (truth_pending(to) && now - waiting_since.value_or(now) < std::chrono::seconds(10)) {
        relaunch_later(slot, to, since, 0.05, waiting_since.value_or(now), resume_token);
        return;
      }
      auto b = std::make_shared<bot_session>(*this, slot, thread_of(slot), slots_[slot].kind, next_seed(slot));
      b->reconnect_to(to, since, resume_token);
      {
        std::lock_guard lock(sessions_mutex_);
        sessions_[slot] = b;
      }
      b->start();
    });
  }
  std::uint64_t next_seed(std::size_t slot) {
    std::lock_guard lock(sessions_mutex_);
    return 0x9e3779b9ull * (slot + 1) + (seed_++);
  }

  /// A random playing bot logs out (or, `cut`, loses its connection: no leave, and its login
  /// again says its resume token); its slot logs in again after relogin_delay_s.
  void churn_one(std::mt19937_64& rng, bool cut = false) {
    for (int tries = 0; tries < 8; ++tries) {
      const std::size_t slot = rng() % sessions_.size();
      std::shared_ptr<bot_session> b;
      {
        std::lock_guard lock(sessions_mutex_);
        b = sessions_[slot];
        if (!b || !b->playing()) continue;
        // Claimed: playing() turns false only once the bot's thread has run the logout, so a
        // second pick of this slot meanwhile would log it out again and launch it twice (a bot
        // too many, seen on a loaded machine as "bots 83/80").
        sessions_[slot] = nullptr;
      }
      if (cut) {
        c_.cuts.fetch_add(1, std::memory_order_relaxed);
        b->cut();  // it launches the slot's next session itself (with the token its thread holds)
        return;
      }
      c_.logouts.fetch_add(1, std::memory_order_relaxed);
      b->logout();
      auto timer = std::make_shared<asio::steady_timer>(*ios_[thread_of(slot)]);
      timer->expires_after(std::chrono::duration_cast<steady::duration>(std::chrono::duration<double>(opt_.relogin_delay_s)));
      timer->async_wait([this, timer, slot](const boost::system::error_code& ec) {
        if (!ec && !stopping_.load()) launch(slot);
      });
      return;
    }
  }

  void problem(std::string what) {
    std::lock_guard lock(problems_mutex_);
    ++problems_total_;
    if (problems_.size() < 200) problems_.push_back(std::move(what));
  }

  void on_pong(std::uint64_t client_us, std::uint64_t server_us, std::uint64_t now_us) {
    c_.pongs.fetch_add(1, std::memory_order_relaxed);
    if (now_us < client_us) return;
    const std::uint64_t rtt = now_us - client_us;
    // server clock - local clock, estimated at the midpoint; the estimate from the fastest round
    // trip is kept (error <= rtt / 2).
    const auto offset = static_cast<std::int64_t>(server_us) - static_cast<std::int64_t>(client_us + rtt / 2);
    std::lock_guard lock(offset_mutex_);
    if (rtt < best_rtt_us_.load()) {
      best_rtt_us_.store(rtt);
      if (!host_clock_.load()) {
        offset_us_.store(offset);
        offset_known_.store(true);
      }
    }
  }

  /// A welcome said the server stamps CLOCK_MONOTONIC: on loopback (one host, one clock) the
  /// offset is exactly the swarm epoch's place on that clock; no ping estimate is needed.
  void on_host_clock() {
    if (!loopback_ || host_clock_.load()) return;
    std::lock_guard lock(offset_mutex_);
    offset_us_.store(static_cast<std::int64_t>(
        std::chrono::duration_cast<std::chrono::microseconds>(epoch_.time_since_epoch()).count()));
    host_clock_.store(true);
    offset_known_.store(true);
  }

  const swarm_options& opt_ref() const { return opt_; }
  /// The I/O thread (and context) of a slot: slots in contiguous blocks, so that neighbouring
  /// slot_stats (written per frame) belong to one thread.
  unsigned thread_of(std::size_t slot) const {
    return static_cast<unsigned>(slot * ios_.size() / std::max<std::size_t>(1, slots_.size()));
  }
  asio::io_context& io(unsigned thread) { return *ios_[thread]; }
  const tcp::endpoint& endpoint() const { return endpoint_; }
  steady::time_point epoch() const { return epoch_; }
  swarm_counters& counters() { return c_; }
  slot_stats& slot(std::size_t i) { return slots_[i]; }
  /// The resume token the slot's last welcome told (empty: none); its sessions' thread only.
  std::string& resume_token(std::size_t i) { return resume_tokens_[i]; }
  latency_histogram_us& latency(unsigned thread) { return *latency_[thread]; }
  /// Logins' durations (launch to connected, connected to welcome), shared by the threads (lock-free).
  latency_histogram_us& connect_time() { return connect_time_; }
  latency_histogram_us& welcome_time() { return welcome_time_; }
  latency_histogram_us::counts latency_snapshot() const {
    latency_histogram_us::counts sum{};
    for (const auto& h : latency_) {
      const auto c = h->snapshot();
      for (std::size_t b = 0; b < sum.size(); ++b) sum[b] += c[b];
    }
    return sum;
  }
  position_board& board() { return board_; }
  bool stopping() const { return stopping_.load(); }
  bool offset_known() const { return offset_known_.load(std::memory_order_relaxed); }
  std::int64_t offset_us() const { return offset_us_.load(std::memory_order_relaxed); }
  std::atomic<std::uint32_t> leader{0};
  std::atomic<bool> rules_told{false};
  /// The oracle of the server at `at` whose welcome told `instance` (nullptr: none). When oracles
  /// run but none reads that server (another zone, or a restarted server whose truth is not read
  /// yet), a frame of `observer` counts as unchecked, or as unsampled when the sample leaves it out
  /// (as an oracle of the zone would count it).
  [[nodiscard]] oracle* oracle_for(const tcp::endpoint& at, std::uint64_t instance, std::uint32_t observer) {
    const auto all = oracles();
    if (all.empty()) return nullptr;
    for (const auto& z : all) {
      if (z.at == at && z.instance == instance) return z.check.get();
    }
    const bool in_sample = oracle::sampled(observer, std::max(1u, opt_.oracle_sample));
    (in_sample ? oracle_unrouted_ : oracle_unrouted_unsampled_).fetch_add(1, std::memory_order_relaxed);
    return nullptr;
  }
  std::mutex hotspot_mutex;
  bool hotspot_known = false;
  net::vec3f hotspot{};

 private:
  swarm_options opt_;
  std::vector<std::unique_ptr<asio::io_context>> ios_;
  tcp::endpoint endpoint_;
  steady::time_point epoch_;
  std::vector<slot_stats> slots_;  // each written by its slot's session (one at a time)
  std::vector<std::string> resume_tokens_;  // the same
  std::mutex sessions_mutex_;
  std::vector<std::shared_ptr<bot_session>> sessions_;
  std::uint64_t seed_ = 1;
  swarm_counters c_;
  std::vector<std::unique_ptr<latency_histogram_us>> latency_;  // one per I/O thread
  latency_histogram_us connect_time_, welcome_time_;
  position_board board_;
  std::vector<second_sample> series_;
  std::mutex problems_mutex_;
  std::vector<std::string> problems_;
  std::uint64_t problems_total_ = 0;
  std::mutex offset_mutex_;
  std::atomic<std::uint64_t> best_rtt_us_{UINT64_MAX};
  std::atomic<std::int64_t> offset_us_{0};
  std::atomic<bool> offset_known_{false};
  std::atomic<bool> host_clock_{false};
  bool loopback_ = false;
  std::atomic<bool> stopping_{false};
  /// --oracle: one per zone and server: the swarm's zone, the world's other zones (oracle_zones),
  /// and one more each time a zone's truth stream ends and a new server answers at its address
  /// (follow_restarts). Appended by one thread at a time (start_oracles, then the follower), read
  /// by the bots' threads without a lock: a slot is never moved or removed, and oracle_count_ is
  /// raised (release) after its slot is written.
  struct zone_oracle {
    tcp::endpoint at;
    std::uint64_t instance = 0;  ///< the server's, as the probe's welcome told it (0: an older server)
    std::unique_ptr<oracle> check;
    bool after_restart = false;  ///< started for a server that replaced an earlier one at `at`
    // The follower's, read after it is joined:
    std::atomic<bool> followed{false};  ///< its stream ended and the server that replaced this one is read
    std::atomic<bool> given_up{false};  ///< its stream ended but this same server still answers: not followed
    /// Its stream ended and the follower's last probe found nothing answering at `at` (a zone
    /// killed and not restarted there: a login sent there is refused and tried again elsewhere).
    std::atomic<bool> silent{false};
  };
  /// Restarted servers followed in one run, at most (beyond, a stream that ends stays an error).
  static constexpr std::size_t max_restarts_followed = 64;
  std::unique_ptr<zone_oracle[]> oracles_;
  std::size_t oracle_capacity_ = 0;
  std::atomic<std::size_t> oracle_count_{0};
  std::thread follower_;  ///< follow_restarts
  /// --oracle-zones-later: zones whose truth is read once they answer (set before the bots start).
  struct later_zone {
    tcp::endpoint at;
    std::atomic<bool> up{false};  ///< its oracle runs (the follower's)
  };
  std::unique_ptr<later_zone[]> later_;
  std::size_t later_count_ = 0;
  [[nodiscard]] std::span<zone_oracle> oracles() const {
    return {oracles_.get(), oracle_count_.load(std::memory_order_acquire)};
  }
  std::atomic<std::uint64_t> oracle_unrouted_{0};            ///< frames in zones with no oracle, of sampled bots
  std::atomic<std::uint64_t> oracle_unrouted_unsampled_{0};  ///< and of the others

  static void add_report(oracle_report& sum, const oracle_report& q, const tcp::endpoint& at) {
    sum.frames_checked += q.frames_checked, sum.frames_unchecked += q.frames_unchecked;
    sum.frames_unsampled += q.frames_unsampled, sum.sample = q.sample;
    sum.sampled_max = std::max(sum.sampled_max, q.sampled_max);
    sum.decode_ms += q.decode_ms, sum.index_ms += q.index_ms, sum.scan_ms += q.scan_ms, sum.publish_ms += q.publish_ms;
    sum.drain_ms += q.drain_ms;
    sum.entities_checked += q.entities_checked, sum.positions_checked += q.positions_checked;
    sum.positions_unchecked += q.positions_unchecked;
    sum.missing += q.missing, sum.extra += q.extra, sum.leaked += q.leaked, sum.wrong_class += q.wrong_class;
    sum.position += q.position, sum.stale += q.stale, sum.deferral += q.deferral;
    sum.truth_ticks += q.truth_ticks, sum.truth_bytes += q.truth_bytes, sum.truth_layouts += q.truth_layouts;
    sum.truth_changes += q.truth_changes;
    sum.compute_cpu_ms += q.compute_cpu_ms, sum.compute_max_ms = std::max(sum.compute_max_ms, q.compute_max_ms);
    sum.drain_cpu_ms += q.drain_cpu_ms, sum.check_ms += q.check_ms, sum.deferred_checks += q.deferred_checks;
    sum.pending_overflow += q.pending_overflow, sum.observers_max = std::max(sum.observers_max, q.observers_max);
    if (!q.stream_error.empty()) {
      sum.stream_error += (sum.stream_error.empty() ? "" : "; ") + std::string("port ") + std::to_string(at.port()) + ": " +
                          q.stream_error;
    }
  }

  std::optional<std::string> start_oracles() {
    oracle_capacity_ = 1 + opt_.oracle_zones.size() + opt_.oracle_zones_later.size() + max_restarts_followed;
    oracles_ = std::make_unique<zone_oracle[]>(oracle_capacity_);
    later_count_ = opt_.oracle_zones_later.size();
    later_ = std::make_unique<later_zone[]>(later_count_);
    for (std::size_t k = 0; k < later_count_; ++k) later_[k].at = tcp::endpoint(endpoint_.address(), opt_.oracle_zones_later[k]);
    if (auto err = start_oracle(endpoint_)) return err;
    for (const std::uint16_t port : opt_.oracle_zones) {
      const tcp::endpoint at(endpoint_.address(), port);
      if (at == endpoint_) continue;
      if (auto err = start_oracle(at)) return "zone at port " + std::to_string(port) + ": " + *err;
    }
    return std::nullopt;
  }

  /// One connection before any bot, for the welcome (the rules and the truth stream's port); then
  /// the oracle subscribes, so every bot's entity is born after its first truth tick.
  std::optional<std::string> start_oracle(const tcp::endpoint& at) {
    auto welcome = probe(at);
    if (auto* err = std::get_if<std::string>(&welcome)) return *err;
    return add_oracle(at, std::get<net::welcome_msg>(welcome), false);
  }

  /// The welcome the server at `at` sends a connection that says hello as "oracle-probe" (its
  /// rules, its truth stream's port, its instance), or why none came (within the connect timeout;
  /// sooner once the run stops).
  std::variant<net::welcome_msg, std::string> probe(const tcp::endpoint& at) {
    asio::io_context io;
    tcp::socket sock(io);
    boost::system::error_code ec;
    sock.connect(at, ec);
    if (ec) return "oracle probe: connect: " + ec.message();
    const auto hello = net::encode_frame(net::hello_msg{"oracle-probe", "", net::protocol_version});
    asio::write(sock, asio::buffer(hello), ec);
    if (ec) return "oracle probe: write: " + ec.message();
    net::frame_decoder dec(client_decoder(opt_.max_frame_bytes));
    std::optional<net::welcome_msg> welcome;
    const auto deadline = steady::now() + std::chrono::duration<double>(opt_.connect_timeout_s);
    sock.non_blocking(true, ec);
    while (!welcome && steady::now() < deadline && !stopping_.load()) {
      const auto buf = dec.prepare(64 * 1024);
      const std::size_t n = sock.read_some(asio::buffer(buf.data(), buf.size()), ec);
      if (ec == asio::error::would_block || ec == asio::error::try_again) {
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
        continue;
      }
      if (ec) return "oracle probe: read: " + ec.message();
      dec.commit(n);
      for (auto step = dec.next(); step.is_frame(); step = dec.next()) {
        if (step.frame.type != net::wire::message::welcome) continue;
        if (auto m = net::to_message(*step.frame.envelope)) welcome = std::get<net::welcome_msg>(*m);
      }
    }
    // A leave: the probe's entity goes at once (a zone with --linger would keep it otherwise).
    if (welcome) asio::write(sock, asio::buffer(net::encode_frame(net::leave_msg{})), ec);
    sock.close(ec);
    if (!welcome) return std::string("oracle probe: no welcome within the connect timeout");
    return *welcome;
  }

  /// An oracle reading the truth of the server that sent `welcome` at `at`, in the next slot.
  std::optional<std::string> add_oracle(const tcp::endpoint& at, const net::welcome_msg& welcome, bool after_restart) {
    if (!welcome.rules) return "the server's welcome tells no interest rules (an older server): no oracle";
    if (welcome.oracle_port == 0) return "the server publishes no ground truth: start zone-server with --oracle";
    const std::size_t k = oracle_count_.load(std::memory_order_relaxed);
    if (k == oracle_capacity_)
      return "no room for another oracle (" + std::to_string(oracle_capacity_) + " in this run)";
    auto o = std::make_unique<oracle>(
        welcome.world, *welcome.rules, opt_.oracle_threads,
        [](void* ctx, std::string line) { static_cast<swarm*>(ctx)->problem(std::move(line)); }, this);
    o->sample = std::max(1u, opt_.oracle_sample);
    if (auto err = o->start(welcome.oracle_port, opt_.connect_timeout_s)) return err;
    oracles_[k].at = at;
    oracles_[k].instance = welcome.instance;
    oracles_[k].check = std::move(o);
    oracles_[k].after_restart = after_restart;
    oracle_count_.store(k + 1, std::memory_order_release);
    return std::nullopt;
  }

  /// While the run lasts (its own thread): a truth stream that ended (its server killed or
  /// stopped) is followed to the server that answers at the same address afterwards (a restart:
  /// the probe is tried every 250 ms), so that the bots that log in there again, or cross into
  /// it, are checked too; the old stream's end is then no error. A server that answers with the
  /// instance whose stream ended, or one that publishes no truth, is not followed (that end stays
  /// an error, as without a restart).
  void follow_restarts() {
    while (!stopping_.load()) {
      for (std::size_t k = 0; k < later_count_ && !stopping_.load(); ++k) {
        if (later_[k].up.load()) continue;
        auto welcome = probe(later_[k].at);
        if (std::holds_alternative<std::string>(welcome)) continue;  // not started yet: tried again
        if (!add_oracle(later_[k].at, std::get<net::welcome_msg>(welcome), true)) later_[k].up = true;
      }
      for (auto& z : oracles()) {
        if (stopping_.load()) break;
        if (z.followed || z.given_up || !z.check->ended()) continue;
        auto welcome = probe(z.at);
        z.silent = std::holds_alternative<std::string>(welcome);
        if (z.silent) continue;  // not (yet) back: tried again
        const auto& w = std::get<net::welcome_msg>(welcome);
        if (w.instance == z.instance || w.oracle_port == 0 || !w.rules) {
          z.given_up = true;  // the same server, or a new one without a truth stream: nothing to follow
          continue;
        }
        if (auto err = add_oracle(z.at, w, true)) {
          if (oracle_count_.load() == oracle_capacity_) z.given_up = true;
          continue;  // e.g. its first tick not yet published: tried again
        }
        z.followed = true;
      }
      for (int i = 0; i < 25 && !stopping_.load(); ++i) std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
  }
};

// ---------------------------------------------------------------------------------------------
// bot_session

/// Bytes asked of the socket per read: a frame under the server's default budget (8 KiB) fits in
/// one read, and 20,000 bots keep ~0.4 GB of receive buffers, not 1.3 GB.
constexpr std::size_t read_chunk_bytes = 16 * 1024;

net::decoder_options client_decoder(std::size_t max_frame) {
  net::decoder_options o;
  o.max_frame_bytes = max_frame;
  o.max_tables = 1u << 22;
  return o;
}

net::vec3f to_vec(const net::wire::vec3& v) { return {v.x(), v.y(), v.z()}; }

bot_session::bot_session(swarm& s, std::size_t slot, unsigned thread, behaviour kind, std::uint64_t seed)
    : s_(s),
      slot_(slot),
      kind_(kind),
      rng_(seed),
      thread_(thread),
      io_(s.io(thread)),
      socket_(io_),
      input_timer_(io_),
      ping_timer_(io_),
      welcome_timer_(io_),
      teleport_timer_(io_),
      switch_timer_(io_),
      decoder_(client_decoder(s.opt_ref().max_frame_bytes)) {
  std::uniform_real_distribution<float> angle(0, 6.2831853f);
  const float a = angle(rng_);
  heading_ = {std::cos(a), std::sin(a), 0};
  std::uniform_real_distribution<double> u(0, 1);
  stealth_ = u(rng_) < s.opt_ref().stealth_share;
  team_ = u(rng_) < s.opt_ref().team_share ? static_cast<std::uint8_t>(1 + rng_() % 2) : 0;
  chooses_ = stealth_ || team_ != 0;
}

void bot_session::connect_done() {
  if (!connecting_) return;
  connecting_ = false;
  s_.counters().connecting_now.fetch_sub(1, std::memory_order_relaxed);
}

void bot_session::start() {
  auto self = shared_from_this();
  // Counted at once (the ramp reads it right after launching); the session's thread decrements.
  connecting_ = true;
  s_.counters().connecting_now.fetch_add(1, std::memory_order_relaxed);
  launched_at_ = steady::now();
  asio::dispatch(io_, [this, self] {
    s_.counters().connect_attempts.fetch_add(1, std::memory_order_relaxed);
    welcome_timer_.expires_after(std::chrono::duration_cast<steady::duration>(std::chrono::duration<double>(s_.opt_ref().connect_timeout_s)));
    welcome_timer_.async_wait([this, self](const boost::system::error_code& ec) {
      if (!ec && !closed_ && !playing_) fail("no welcome within the connect timeout", true);
    });
    socket_.async_connect(endpoint_now(), [this, self](const boost::system::error_code& ec) { on_connect(ec); });
  });
}

void bot_session::logout() {
  auto self = shared_from_this();
  asio::dispatch(io_, [this, self] {
    intended_ = true;
    s_.resume_token(slot_).clear();  // its entity leaves the world with it
    if (!playing_ || closed_) return close();
    // A leave first (the server removes the entity at once rather than keeping it for a resume:
    // zone-server --linger), then the close once it is written, or after a second at most.
    leaving_ = true;
    send(net::leave_msg{});
    if (!writing_) return close();
    welcome_timer_.expires_after(std::chrono::seconds(1));
    welcome_timer_.async_wait([this, self](const boost::system::error_code& ec) {
      if (!ec) close();
    });
  });
}

void bot_session::cut() {
  auto self = shared_from_this();
  asio::dispatch(io_, [this, self] {
    if (closed_) return;
    intended_ = true;  // the swarm's own doing: not an unexpected disconnect
    // No leave: the socket just closes, so the server sees the connection end without one (a
    // lost connection, as a dead link would end it).
    log_in_again(endpoint_now(), steady::now(), s_.opt_ref().relogin_delay_s);
  });
}

tcp::endpoint bot_session::endpoint_now() const { return endpoint_override_ ? *endpoint_override_ : s_.endpoint(); }

void bot_session::log_in_again(const tcp::endpoint& to, steady::time_point since, double delay_s) {
  close();
  if (s_.stopping()) return;
  const auto& o = s_.opt_ref();
  s_.relaunch_later(slot_, to, since, delay_s, {}, o.resume ? s_.resume_token(slot_) : std::string());
}

void bot_session::on_connect(const boost::system::error_code& ec) {
  if (closed_) return;
  if (ec) return fail("connect: " + ec.message(), true);
  connected_at_ = steady::now();
  s_.connect_time().record(std::chrono::duration<double, std::micro>(connected_at_ - launched_at_).count());
  boost::system::error_code ignored;
  socket_.set_option(tcp::no_delay(true), ignored);
  net::hello_msg hello{"bot-" + std::to_string(slot_), token_, net::protocol_version};
  if (token_.empty()) hello.stealth = stealth_, hello.team = team_;  // a redirected entity keeps its class
  hello.class_changes = s_.opt_ref().class_changes;
  send(hello);
  send(net::ping_msg{local_us(s_.epoch())});
  s_.counters().pings_sent.fetch_add(1, std::memory_order_relaxed);
  boost::system::error_code ec2;
  socket_.non_blocking(true, ec2);
  if (ec2) return fail("non-blocking mode: " + ec2.message(), true);
  read_next();
}

/// Reads rounds per wakeup in server_error_waiting.
constexpr int max_reads_per_wakeup = 8;

void bot_session::read_next() {
  // One read in flight, into the decoder's room. Asio's reactor reads the socket when it is
  // readable and runs on_read right after, so the receive time of every frame is taken as its
  // bytes come out of the socket. Unlike a wait for readability (`async_wait(wait_read)`, which
  // re-arms the descriptor with an epoll_ctl each time), a pending read costs no system call to
  // start: after a short read asio skips the speculative read and waits for the next edge; after
  // a full one it reads again at once and queues the handler behind the thread's other ready bots.
  auto self = shared_from_this();
  const auto buf = decoder_.prepare(read_chunk_bytes);
  socket_.async_read_some(asio::buffer(buf.data(), buf.size()),
                          [this, self](const boost::system::error_code& ec, std::size_t n) { on_read(ec, n); });
}

void bot_session::on_read(const boost::system::error_code& ec, std::size_t n) {
  if (closed_) return;
  if (ec) {
    if (intended_ || s_.stopping()) return close();
    return fail(got_error_ ? "closed by the server after an error" : "connection lost: " + ec.message(), !playing_);
  }
  // The receive time of every frame these bytes complete: when they were read.
  const std::uint64_t received_us = local_us(s_.epoch());
  auto& st = s_.slot(slot_);
  decoder_.commit(n);
  st.bytes_in += n;
  local_.bytes_in += n;
  for (auto step = decoder_.next(); !closed_; step = decoder_.next()) {
    if (step.needs_more()) break;
    if (step.is_error()) return fail(std::string("bad frame from the server: ") + std::string(net::to_string(step.error)), false);
    ++st.frames_in;
    ++local_.frames_in;
    on_frame(step.frame, received_us);
  }
  if (closed_) return;
  read_next();
}

void bot_session::on_frame(const net::frame_view& f, std::uint64_t received_us) {
  const auto& env = *f.envelope;
  switch (f.type) {
    case net::wire::message::welcome:
      if (const auto* w = env.message_as_welcome()) on_welcome(*w);
      break;
    case net::wire::message::tick_update:
      if (const auto* u = env.message_as_tick_update()) on_tick_update(*u, received_us);
      break;
    case net::wire::message::pong:
      if (const auto* p = env.message_as_pong()) s_.on_pong(p->client_time_us(), p->server_time_us(), received_us);
      break;
    case net::wire::message::class_changes:
      if (const auto* c = env.message_as_class_changes()) on_class_changes(*c);
      break;
    case net::wire::message::redirect: {
      // A world of zones moved this bot's entity: go on at the zone named, with the token.
      const auto* r = env.message_as_redirect();
      if (!r || !r->host() || !r->token()) break;
      boost::system::error_code ec;
      const auto addr = asio::ip::make_address(r->host()->str(), ec);
      if (ec || r->port() == 0) {
        s_.problem("bot " + std::to_string(slot_) + ": redirect to an unusable address '" + r->host()->str() + ":" +
                   std::to_string(r->port()) + "'");
        break;
      }
      intended_ = true;
      close();
      if (resuming_ && r->token()->str() == token_) {
        // A world's gate found the zone that serves this entity's region now: the token goes there.
        if (!s_.stopping()) s_.relaunch_later(slot_, tcp::endpoint(addr, r->port()), steady::now(), 0.0, {}, token_);
        break;
      }
      if (r->token()->size() == 0) {
        // A world's gate: a new login at the zone named (after its oracle, if it is not read yet).
        s_.counters().gate_redirects.fetch_add(1, std::memory_order_relaxed);
        if (!s_.stopping()) s_.relaunch_later(slot_, tcp::endpoint(addr, r->port()), steady::now(), 0.0);
        break;
      }
      s_.counters().redirects.fetch_add(1, std::memory_order_relaxed);
      s_.resume_token(slot_) = r->token()->str();  // the entity's zone now knows its client by it (its welcome says so)
      if (!s_.stopping()) s_.launch(slot_, tcp::endpoint(addr, r->port()), r->token()->str());
      break;
    }
    case net::wire::message::error: {
      const auto* e = env.message_as_error();
      got_error_ = true;
      if (e && e->code() == net::error_code::taken_over) {
        // Another connection resumed this player with the slot's token: never take it back (the two would take turns).
        s_.resume_token(slot_).clear();
      }
      if (resuming_ && !playing_ && e &&
          (e->code() == net::error_code::auth_failed || e->code() == net::error_code::timeout)) {
        // The token refused (unknown or expired) or its region not served in time: the next login
        // is a new player. Another error (rate_limited, server_full) says nothing of the token:
        // a retry says it again.
        resuming_ = false;
        token_.clear();
        s_.resume_token(slot_).clear();
        s_.counters().resumes_refused.fetch_add(1, std::memory_order_relaxed);
        reconnecting_since_ = steady::now();  // the login anew gets its own --connect-timeout
      }
      s_.counters().server_errors.fetch_add(1, std::memory_order_relaxed);
      s_.problem("bot " + std::to_string(slot_) + ": server error " +
                 (e ? std::string(net::wire::EnumNameerror_code(e->code())) + ": " + (e->reason() ? e->reason()->str() : "")
                    : std::string("?")));
      break;
    }
    default:
      break;
  }
}

void bot_session::on_welcome(const net::wire::welcome& w) {
  if (playing_) return;
  welcome_timer_.cancel();
  s_.welcome_time().record(std::chrono::duration<double, std::micro>(steady::now() - connected_at_).count());
  reconnecting_since_.reset();  // logged in again: a later loss starts its own retries
  entity_ = w.entity_id();
  if (resuming_) s_.counters().resumes.fetch_add(1, std::memory_order_relaxed);
  if (const auto* t = w.resume_token()) {
    s_.resume_token(slot_) = t->str();
  } else {
    s_.resume_token(slot_).clear();
  }
  instance_ = w.instance();
  net::world_bounds world{};
  if (w.world()) world = {to_vec(w.world()->lo()), to_vec(w.world()->hi())};
  world_ = world;
  if (w.host_clock()) s_.on_host_clock();
  view_.emplace(world);
  q_err_ = view_->quantizer().max_error();
  const auto& o = s_.opt_ref();
  if (const auto* r = w.rules()) {
    aoi_ = r->player_aoi() ? to_vec(*r->player_aoi()) : net::vec3f{o.aoi, o.aoi, o.aoi};
    hysteresis_ = r->hysteresis();
    max_speed_ = r->max_speed();
    s_.rules_told.store(true, std::memory_order_relaxed);
  } else {
    aoi_ = {o.aoi, o.aoi, o.aoi};
    hysteresis_ = o.hysteresis;
    max_speed_ = o.max_speed;
  }
  tick_rate_ = std::max<double>(1, w.tick_rate_hz());
  welcomed_at_ = steady::now();
  connect_done();
  playing_ = true;
  auto& st = s_.slot(slot_);
  st.ever_connected = true;
  s_.counters().welcomes.fetch_add(1, std::memory_order_relaxed);
  s_.counters().connected_now.fetch_add(1, std::memory_order_relaxed);
  s_.board().claim(entity_);
  if (const auto* spawn = w.spawn_position()) s_.board().report(entity_, w.server_tick(), to_vec(*spawn));
  std::uint32_t none = 0;
  if (kind_ == behaviour::walk) s_.leader.compare_exchange_strong(none, entity_);
  if (s_.opt_ref().inputs_on_change) {
    next_input_us_ = local_us(s_.epoch());  // evaluated as frames arrive (and at each ping)
  } else {
    schedule_input();
  }
  schedule_ping();
  if (kind_ == behaviour::teleport) schedule_teleport();
  if (token_.empty()) {
    if (stealth_) s_.counters().stealth_joins.fetch_add(1, std::memory_order_relaxed);
    if (team_ != 0) s_.counters().team_joins.fetch_add(1, std::memory_order_relaxed);
  }
  if (chooses_) schedule_visibility_switch();
}

void bot_session::schedule_visibility_switch() {
  const double hz = s_.opt_ref().visibility_switch_hz;
  if (!(hz > 0)) return;
  // Switches at random times (a Poisson process of the given rate): stealth toggled, and half the
  // time another team (or none). The server applies them subject to its cooldown.
  std::exponential_distribution<double> gap(hz);
  auto self = shared_from_this();
  switch_timer_.expires_after(std::chrono::duration_cast<steady::duration>(std::chrono::duration<double>(gap(rng_))));
  switch_timer_.async_wait([this, self](const boost::system::error_code& ec) {
    if (ec || closed_) return;
    stealth_ = !stealth_;
    if (rng_() % 2 == 0) team_ = static_cast<std::uint8_t>(rng_() % 3);
    send(net::set_visibility_msg{++sequence_, stealth_, team_});
    s_.counters().visibility_switches_sent.fetch_add(1, std::memory_order_relaxed);
    schedule_visibility_switch();
  });
}

int bot_session::check_aoi(const position_board::fix& own, std::uint64_t tick, std::uint32_t id, const net::vec3f& p,
                            const net::vec3f& half) {
  // The entity must lie inside this bot's AOI grown by the hysteresis band (boxes meet), allowing
  // the staleness of the bot's own position fix, quantization and float slack.
  if (!own.known) return 0;
  const double stale_ticks = std::fabs(static_cast<double>(tick) - static_cast<double>(own.tick));
  const double slack = max_speed_ * stale_ticks / tick_rate_ + 0.01;
  const float qs[3] = {q_err_.x, q_err_.y, q_err_.z};
  const float d[3] = {p.x - own.pos.x, p.y - own.pos.y, p.z - own.pos.z};
  const float h[3] = {half.x, half.y, half.z};
  const float aoi[3] = {aoi_.x, aoi_.y, aoi_.z};
  for (int a = 0; a < 3; ++a) {
    const double bound = aoi[a] + hysteresis_ + h[a] + 2 * qs[a] + slack;
    if (std::fabs(d[a]) > bound) {
      s_.problem("bot " + std::to_string(slot_) + " (entity " + std::to_string(entity_) + ") tick " + std::to_string(tick) +
                 ": entity " + std::to_string(id) + " is " + std::to_string(std::fabs(d[a])) + " m away on axis " +
                 "xyz"[a] + ", beyond the AOI bound " + std::to_string(bound) + " m (own fix from tick " +
                 std::to_string(own.tick) + ")");
      return 2;
    }
  }
  return 1;
}

void bot_session::on_tick_update(const net::wire::tick_update& u, std::uint64_t received_us) {
  if (!view_) {
    s_.problem("bot " + std::to_string(slot_) + ": tick update before welcome");
    s_.counters().inconsistent.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  const std::uint64_t now = received_us;
  ++local_.tick_updates;
  if (s_.offset_known()) {
    const auto sent_local = static_cast<std::int64_t>(u.server_time_us()) - s_.offset_us();
    const auto lat = static_cast<std::int64_t>(now) - sent_local;
    s_.latency(thread_).record(static_cast<double>(static_cast<std::uint64_t>(std::max<std::int64_t>(0, lat))));
  } else {
    ++local_.latency_unsynced;
  }
  const std::uint64_t tick = u.server_tick();
  const auto* enters = u.enters();
  const auto* leaves = u.leaves();
  const auto* updates = u.updates();
  local_.enters += enters ? enters->size() : 0;
  local_.leaves += leaves ? leaves->size() : 0;
  local_.updates += updates ? updates->size() : 0;
  if (u.reset() && view_->updates_applied() > 0) ++local_.resets;

  // This bot's own position at this tick: exact when the server sends it (self_position), else
  // as another bot last saw it on the board (stale by a few ticks; useless after a teleport).
  auto& board = s_.board();
  frame_check_.own = {};
  const auto* self = u.self_position();
  if (self) {
    frame_check_.own = {tick, to_vec(*self), true};
    own_fix_ = frame_check_.own;
    // Other bots read only the leader's entry (followers, the flash crowd's hotspot): the others
    // keep their fix to themselves, which spares a striped lock per frame.
    if (s_.leader.load(std::memory_order_relaxed) == entity_) board.report(entity_, tick, frame_check_.own.pos);
    ++local_.self_positions;
  } else if (!jumped_) {
    frame_check_.own = board.get(entity_);
  }
  // Without self positions, every bot relays the positions it is told of other bots' entities.
  frame_check_.relay = self == nullptr;
  frame_check_.tick = tick;
  frame_check_.counts = {0, 0, 0};

  // Apply, checking consistency and the digest; every position told is AOI-checked on the way
  // (one lookup per entity for the view and the check).
  const std::uint64_t last = view_->last_tick();
  const auto status = view_->apply(
      u,
      [](void* ctx, std::uint32_t id, const net::vec3f& p, const net::vec3f& half) {
        auto& b = *static_cast<bot_session*>(ctx);
        if (b.frame_check_.relay) b.s_.board().report(id, b.frame_check_.tick, p);
        ++b.frame_check_.counts[static_cast<std::size_t>(b.check_aoi(b.frame_check_.own, b.frame_check_.tick, id, p, half))];
      },
      this);
  if (status == net::client_view::status::inconsistent) {
    s_.counters().inconsistent.fetch_add(1, std::memory_order_relaxed);
    const auto& bad = view_->last_bad_ids();
    std::string ids;
    for (std::size_t i = 0; i < bad.size(); ++i) ids += (i ? "," : "") + std::to_string(bad[i]);
    s_.problem("bot " + std::to_string(slot_) + " (entity " + std::to_string(entity_) + ") tick " + std::to_string(tick) +
               ": inconsistent update (previous tick " + std::to_string(last) + "; ids " + (ids.empty() ? "-" : ids) + ")");
  }
  // The oracle: this view against the ground truth of this tick.
  if (auto* o = s_.oracle_for(endpoint_now(), instance_, entity_)) {
    net::deferred_counts deferred;
    if (const auto* d = u.deferred()) deferred = {d->enters(), d->leaves(), d->updates()};
    std::optional<net::vec3f> own;
    if (self) own = to_vec(*self);
    o->check(entity_, tick, *view_, deferred, own, slot_);
  }
  if (const auto* d = u.digest()) {
    ++local_.digests_checked;
    if (s_.opt_ref().verify && (d->hash() != view_->hash() || d->count() != view_->size())) {
      s_.counters().digest_mismatches.fetch_add(1, std::memory_order_relaxed);
      s_.problem("bot " + std::to_string(slot_) + " (entity " + std::to_string(entity_) + ") tick " + std::to_string(tick) +
                 ": digest mismatch: server has " + std::to_string(d->count()) + " entities (digest tick " +
                 std::to_string(d->tick()) + "), the bot tracked " + std::to_string(view_->size()));
    }
  }
  local_.aoi_unchecked += frame_check_.counts[0];
  local_.aoi_checked += frame_check_.counts[1];
  if (frame_check_.counts[2] != 0) s_.counters().aoi_violations.fetch_add(frame_check_.counts[2], std::memory_order_relaxed);
  if (s_.opt_ref().inputs_on_change) maybe_send_input(now);
  if (++frames_seen_ % flush_every_frames == 0) flush_counts();
}

void bot_session::on_class_changes(const net::wire::class_changes& c) {
  if (!view_) {
    s_.problem("bot " + std::to_string(slot_) + ": class change before welcome");
    s_.counters().inconsistent.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  if (c.notes()) s_.counters().class_notes.fetch_add(c.notes()->size(), std::memory_order_relaxed);
  const std::uint64_t last = view_->last_tick();
  if (view_->apply(c) == net::client_view::status::inconsistent) {
    s_.counters().inconsistent.fetch_add(1, std::memory_order_relaxed);
    s_.problem("bot " + std::to_string(slot_) + " (entity " + std::to_string(entity_) + "): class change of tick " +
               std::to_string(c.server_tick()) + " after the update of tick " + std::to_string(last));
  }
}

void bot_session::flush_counts() {
  // The swarm's shared counters are bumped once per few frames, not once per frame, so that
  // thousands of bots on several threads do not fight over their cache lines.
  auto& c = s_.counters();
  const auto add = [](std::atomic<std::uint64_t>& to, std::uint64_t& from) {
    if (from != 0) to.fetch_add(from, std::memory_order_relaxed);
    from = 0;
  };
  add(c.tick_updates, local_.tick_updates);
  add(c.enters, local_.enters);
  add(c.leaves, local_.leaves);
  add(c.updates, local_.updates);
  add(c.resets, local_.resets);
  add(c.digests_checked, local_.digests_checked);
  add(c.aoi_checked, local_.aoi_checked);
  add(c.aoi_unchecked, local_.aoi_unchecked);
  add(c.self_positions, local_.self_positions);
  add(c.latency_unsynced, local_.latency_unsynced);
  add(c.frames_in, local_.frames_in);
  add(c.bytes_in, local_.bytes_in);
  add(c.inputs_sent, local_.inputs_sent);
  add(c.inputs_unchanged, local_.inputs_unchanged);
}

void bot_session::schedule_input() {
  auto self = shared_from_this();
  const double period = 1.0 / std::max(0.1, s_.opt_ref().input_hz);
  input_timer_.expires_after(std::chrono::duration_cast<steady::duration>(std::chrono::duration<double>(period)));
  input_timer_.async_wait([this, self](const boost::system::error_code& ec) {
    if (ec || closed_) return;
    send_input();
    schedule_input();
  });
}

void bot_session::schedule_teleport() {
  const double hz = s_.opt_ref().teleport_hz;
  if (!(hz > 0)) return;
  // Jumps at random times (exponential gaps: a Poisson process of the given rate) to random
  // places in the world; the server applies them subject to its cooldown.
  std::exponential_distribution<double> gap(hz);
  auto self = shared_from_this();
  teleport_timer_.expires_after(std::chrono::duration_cast<steady::duration>(std::chrono::duration<double>(gap(rng_))));
  teleport_timer_.async_wait([this, self](const boost::system::error_code& ec) {
    if (ec || closed_) return;
    std::uniform_real_distribution<float> u(0, 1);
    const net::vec3f to{world_.lo.x + (world_.hi.x - world_.lo.x) * u(rng_),
                        world_.lo.y + (world_.hi.y - world_.lo.y) * u(rng_), world_.lo.z};
    send(net::teleport_msg{++sequence_, to, 0});
    jumped_ = true;
    s_.counters().teleports_sent.fetch_add(1, std::memory_order_relaxed);
    schedule_teleport();
  });
}

void bot_session::schedule_ping() {
  auto self = shared_from_this();
  const double period = 1.0 / std::max(0.05, s_.opt_ref().ping_hz);
  ping_timer_.expires_after(std::chrono::duration_cast<steady::duration>(std::chrono::duration<double>(period)));
  ping_timer_.async_wait([this, self](const boost::system::error_code& ec) {
    if (ec || closed_) return;
    const std::uint64_t now = local_us(s_.epoch());
    send(net::ping_msg{now});
    s_.counters().pings_sent.fetch_add(1, std::memory_order_relaxed);
    // Frames drive the inputs; the ping keeps them going (and the keep-alive) when none come.
    if (s_.opt_ref().inputs_on_change && playing_) maybe_send_input(now);
    schedule_ping();
  });
}

net::vec3f bot_session::steer() {
  const double t = std::chrono::duration<double>(steady::now() - welcomed_at_).count();
  const auto toward = [&](const net::vec3f& target, float stop_at) -> std::optional<net::vec3f> {
    const auto own = own_fix_.known ? own_fix_ : s_.board().get(entity_);
    if (!own.known) return std::nullopt;
    const float dx = target.x - own.pos.x, dy = target.y - own.pos.y;
    const float len = std::sqrt(dx * dx + dy * dy);
    if (len < stop_at) return net::vec3f{0, 0, 0};
    return net::vec3f{dx / len, dy / len, 0};
  };
  switch (kind_) {
    case behaviour::walk:
    case behaviour::teleport:  // walks between jumps
      // A new random heading every ~3 s (per bot, seeded).
      if (inputs_ % static_cast<std::uint64_t>(std::max(1.0, 3 * s_.opt_ref().input_hz)) == 0) {
        std::uniform_real_distribution<float> angle(0, 6.2831853f);
        const float a = angle(rng_);
        heading_ = {std::cos(a), std::sin(a), 0};
      }
      return heading_;
    case behaviour::patrol: {
      // A square: four legs of 4 s each.
      static constexpr net::vec3f legs[4] = {{1, 0, 0}, {0, 1, 0}, {-1, 0, 0}, {0, -1, 0}};
      return legs[static_cast<std::size_t>(t / 4.0) % 4];
    }
    case behaviour::follow: {
      const std::uint32_t lead = s_.leader.load(std::memory_order_relaxed);
      if (lead != 0 && lead != entity_) {
        const auto& known = view_->entities();
        const auto it = known.find(lead);
        const auto fix = s_.board().get(lead);
        if (it != known.end()) {
          if (auto v = toward(it->second.state.position, 3)) return *v;
        } else if (fix.known) {
          if (auto v = toward(fix.pos, 3)) return *v;
        }
      }
      return heading_;  // no leader in sight: keep walking
    }
    case behaviour::crowd: {
      // The flash crowd forms at crowd_at_s into the run: until then, walk.
      if (std::chrono::duration<double>(steady::now() - s_.epoch()).count() < s_.opt_ref().crowd_at_s) return heading_;
      net::vec3f target{};
      {
        std::lock_guard lock(s_.hotspot_mutex);
        if (!s_.hotspot_known) {
          if (s_.opt_ref().hotspot_set) {
            s_.hotspot = s_.opt_ref().hotspot, s_.hotspot_known = true;
          } else if (const auto fix = s_.board().get(s_.leader.load()); fix.known) {
            s_.hotspot = fix.pos, s_.hotspot_known = true;
          }
        }
        if (!s_.hotspot_known) return heading_;
        target = s_.hotspot;
      }
      if (auto v = toward(target, 2)) return *v;
      return heading_;
    }
  }
  return heading_;
}

void bot_session::send_input() {
  const auto move = steer();
  ++inputs_;
  send(net::input_msg{++sequence_, move});
  ++local_.inputs_sent;
}

void bot_session::maybe_send_input(std::uint64_t now_us) {
  // The intent is evaluated input_hz times a second (at the first frame or ping due); an input
  // goes out only when it differs from the last one sent, or as a keep-alive. The zone server
  // keeps a player's last intent until its next input (zone_world::set_intent), so an unchanged
  // intent need not be repeated; the 10 s idle timeout is met by the pings and the keep-alive.
  if (now_us < next_input_us_) return;
  const auto& o = s_.opt_ref();
  const auto period = static_cast<std::uint64_t>(1e6 / std::max(0.1, o.input_hz));
  next_input_us_ += period;
  if (next_input_us_ <= now_us) next_input_us_ = now_us + period;  // fell behind: no catch-up burst
  const auto move = steer();
  ++inputs_;
  const auto keepalive = static_cast<std::uint64_t>(std::max(0.0, o.input_keepalive_s) * 1e6);
  if (any_input_sent_ && move == last_move_ && now_us - last_input_sent_us_ < keepalive) {
    ++local_.inputs_unchanged;
    return;
  }
  send(net::input_msg{++sequence_, move});
  any_input_sent_ = true;
  last_move_ = move;
  last_input_sent_us_ = now_us;
  ++local_.inputs_sent;
}

void bot_session::send(const net::message& m) {
  if (closed_) return;
  const auto frame = encoder_.encode(m);
  out_queued_.insert(out_queued_.end(), frame.begin(), frame.end());
  if (!writing_) write_next();
}

void bot_session::write_next() {
  if (out_queued_.empty() || closed_) {
    writing_ = false;
    if (leaving_) close();  // the leave is written
    return;
  }
  // One write in flight: everything queued so far goes out in it (frames stay in order).
  writing_ = true;
  out_writing_.swap(out_queued_);
  out_queued_.clear();
  auto self = shared_from_this();
  asio::async_write(socket_, asio::buffer(out_writing_), [this, self](const boost::system::error_code& ec, std::size_t) {
    if (closed_) return;
    if (ec) {
      if (intended_ || s_.stopping()) return close();
      // Before the welcome a write fails mostly because the server closed the connection after
      // an error frame (a cap on connections without a hello, a full server): name its reason.
      if (!playing_) {
        if (auto said = server_error_waiting()) return fail("write: " + ec.message() + " (the server closed the connection: " + *said + ")", true);
        return fail("write: " + ec.message() + " (the server closed the connection before the welcome; no reason arrived)", true);
      }
      return fail("write: " + ec.message(), !playing_);
    }
    out_writing_.clear();
    write_next();
  });
}

std::optional<std::string> bot_session::server_error_waiting() {
  boost::system::error_code ec;
  // The pending read holds the decoder's room: take it back (its handler then sees the session
  // closed, as the caller fails it) before reading here.
  socket_.cancel(ec);
  socket_.non_blocking(true, ec);
  for (int round = 0; round < max_reads_per_wakeup && !ec; ++round) {
    const auto buf = decoder_.prepare(read_chunk_bytes);
    const std::size_t n = socket_.read_some(asio::buffer(buf.data(), buf.size()), ec);
    decoder_.commit(ec ? 0 : n);
    for (auto step = decoder_.next(); !step.needs_more() && !step.is_error(); step = decoder_.next()) {
      if (step.frame.type != net::wire::message::error) continue;
      const auto* e = step.frame.envelope->message_as_error();
      if (!e) return std::string("?");
      got_error_ = true;
      s_.counters().server_errors.fetch_add(1, std::memory_order_relaxed);
      return std::string(net::wire::EnumNameerror_code(e->code())) + ": " + (e->reason() ? e->reason()->str() : std::string());
    }
  }
  return std::nullopt;
}

void bot_session::fail(const std::string& why, bool connection_failure) {
  if (closed_) return;
  auto& c = s_.counters();
  const auto& o = s_.opt_ref();
  if (o.reconnect && !s_.stopping()) {
    // Log in again at the same address: after a lost connection, and after refused connects of
    // such a login while its zone restarts (up to connect_timeout_s).
    const auto now = steady::now();
    const auto since = reconnecting_since_.value_or(now);
    // A redirect whose zone is gone (killed as the entity crossed): its token resumes it too.
    const bool redirect_lost = connection_failure && !reconnecting_since_ && !token_.empty() && !resuming_;
    const bool retry = !connection_failure || redirect_lost ||
                       (reconnecting_since_ && now - since < std::chrono::duration<double>(o.connect_timeout_s));
    if (retry) {
      if (!connection_failure) {
        c.unexpected_disconnects.fetch_add(1, std::memory_order_relaxed);
        s_.problem("bot " + std::to_string(slot_) + (entity_ ? " (entity " + std::to_string(entity_) + ")" : std::string()) +
                   ": " + why + " (logging in again)");
        c.reconnects.fetch_add(1, std::memory_order_relaxed);
      }
      log_in_again(o.relogin_port != 0 ? tcp::endpoint(s_.endpoint().address(), o.relogin_port) : endpoint_now(), since,
                   -1);
      return;
    }
  }
  if (connection_failure) {
    c.connect_failures.fetch_add(1, std::memory_order_relaxed);
  } else {
    c.unexpected_disconnects.fetch_add(1, std::memory_order_relaxed);
  }
  s_.problem("bot " + std::to_string(slot_) + (entity_ ? " (entity " + std::to_string(entity_) + ")" : std::string()) + ": " + why);
  close();
}

void bot_session::close() {
  if (closed_) return;
  closed_ = true;
  connect_done();
  flush_counts();
  boost::system::error_code ignored;
  input_timer_.cancel();
  ping_timer_.cancel();
  welcome_timer_.cancel();
  teleport_timer_.cancel();
  switch_timer_.cancel();
  socket_.shutdown(tcp::socket::shutdown_both, ignored);
  socket_.close(ignored);
  if (playing_) {
    playing_ = false;
    s_.counters().connected_now.fetch_sub(1, std::memory_order_relaxed);
    s_.slot(slot_).connected_s += std::chrono::duration<double>(steady::now() - welcomed_at_).count();
    s_.board().release(entity_);
    std::uint32_t me = entity_;
    s_.leader.compare_exchange_strong(me, 0);
  }
}

}  // namespace

run_outcome run_swarm(const swarm_options& opt, progress_fn progress) {
  swarm_options o = opt;
  if (o.threads == 0) {
    // One I/O thread per 2,500 bots, at least 2, at most half the cores (the server is often on the same host).
    const unsigned cores = std::max(2u, std::thread::hardware_concurrency());
    o.threads = std::clamp((o.bots + 2499) / 2500, 2u, std::max(2u, cores / 2));
  }
  auto s = std::make_unique<swarm>(o);
  return s->run(progress);
}

}  // namespace zone::bots
