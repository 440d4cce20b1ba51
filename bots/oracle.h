// The oracle (docs/bots.md): an independent check of every bot's view against the server's ground
// truth. The server (zone-server --oracle) publishes each tick's entities, boxes and classes on a
// loopback stream (net/truth.h); the oracle recomputes every player's visible set from that
// truth alone (every observer tested against every entity its own grid over the truth does not
// rule out; brute force is the reference it is tested against) under the zone's rules (the
// visibility rule, the hysteresis, the cap), and each bot, right after applying the frame of tick
// t, has its view compared with the visible set of tick t. With a sample of 1 in K, only the
// players whose id is sampled (a fixed subset, see sampled()) are recomputed and checked. What
// the server promises after a frame of tick t (and the oracle checks exactly):
//   - the view holds every visible entity but `deferred.enters` of them, and no entity that is
//     not visible but `deferred.leaves` of them (the frame says what the byte budget left for
//     later); never one of a class the observer does not see (a leak);
//   - every held entity has its true visibility class;
//   - every held entity's position is its true position at the tick it was last sent (enter:
//     exact; update: within the quantization error), and the bot's own position is exact;
//   - an entity held and visible is updated when its distance tier makes it due, but
//     `deferred.updates` of them.
// The bots, not the server, hold the views; nothing the server says about its own view is trusted.
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <shared_mutex>
#include <span>
#include <string>
#include <thread>
#include <vector>

#include "net/protocol.h"
#include "net/truth.h"

namespace zone::bots {

/// Mismatches by kind, and what was checked (relaxed atomics: bots on several threads add to them).
struct oracle_counters {
  std::atomic<std::uint64_t> frames_checked{0}, frames_unchecked{0}, entities_checked{0}, positions_checked{0},
      positions_unchecked{0};
  std::atomic<std::uint64_t> frames_unsampled{0};  ///< frames of bots outside the sample (not checked by design)
  std::atomic<std::uint64_t> missing{0}, extra{0}, leaked{0}, wrong_class{0}, position{0}, stale{0}, deferral{0};
  [[nodiscard]] std::uint64_t mismatches() const {
    return missing.load() + extra.load() + leaked.load() + wrong_class.load() + position.load() + stale.load() +
           deferral.load();
  }
};

/// A plain copy of the counters and the oracle's own costs (for the report).
struct oracle_report {
  std::uint64_t frames_checked = 0, frames_unchecked = 0, entities_checked = 0, positions_checked = 0,
                positions_unchecked = 0;
  std::uint64_t frames_unsampled = 0;  ///< frames of bots outside the sample (neither checked nor failed)
  unsigned sample = 1;                 ///< 1 in `sample` players recomputed and checked
  std::uint64_t missing = 0, extra = 0, leaked = 0, wrong_class = 0, position = 0, stale = 0, deferral = 0;
  std::uint64_t truth_ticks = 0, truth_bytes = 0, truth_layouts = 0;
  std::uint64_t truth_changes = 0;  ///< truth frames that carried changes to the layout instead of the whole of it
  double compute_cpu_ms = 0;  ///< CPU of decoding and recomputing the visible sets, all ticks
  double compute_max_ms = 0;  ///< the slowest tick's wall time (recomputing and the checks that waited for it)
  double drain_cpu_ms = 0;    ///< CPU of the oracle's thread checking the views that waited for their truth
  double check_ms = 0;        ///< wall time of the comparisons, summed (bots' threads and the oracle's)
  std::uint64_t deferred_checks = 0;  ///< frames checked by the oracle's thread (they came before their truth)
  std::uint64_t pending_overflow = 0;  ///< frames not checked: too many waiting for their truth
  std::uint64_t observers_max = 0;     ///< players in the zone (the most in one tick)
  std::uint64_t sampled_max = 0;       ///< of them, recomputed and checked (the most in one tick)
  /// Wall time of the oracle's thread by phase, summed over the ticks: decoding the frame, the
  /// layout and the index over the targets, the scan of every sampled observer (all threads),
  /// publishing the sets, and checking the views that waited for them.
  double decode_ms = 0, index_ms = 0, scan_ms = 0, publish_ms = 0, drain_ms = 0;
  std::string stream_error;  ///< why the stream ended early (empty: it ran to the end)
  /// A swarm's sum: truth streams that ended because their zone's server was restarted, and that
  /// the swarm followed to the new server's stream (their end is then no error); and the frames
  /// checked against the truth of such restarted servers.
  std::uint64_t truth_restarts = 0, frames_checked_after_restart = 0;
  [[nodiscard]] std::uint64_t mismatches() const {
    return missing + extra + leaked + wrong_class + position + stale + deferral;
  }
};

class oracle {
 public:
  /// Called with a readable line for each of the first few mismatches of every kind.
  using problem_fn = void (*)(void* ctx, std::string line);

  /// `rules` and `world` as the server's welcome tells them; `threads` recompute the visible sets
  /// (0 = 1 per 8 hardware threads, at least 1).
  oracle(const net::world_bounds& world, const net::interest_rules& rules, unsigned threads, problem_fn problem,
         void* ctx);
  ~oracle();
  oracle(const oracle&) = delete;
  oracle& operator=(const oracle&) = delete;

  /// Connects to the truth stream at 127.0.0.1:port and starts reading; waits (up to `timeout_s`)
  /// for the first tick, so that every entity spawned afterwards has its whole history seen.
  [[nodiscard]] std::optional<std::string> start(std::uint16_t port, double timeout_s);
  void stop();
  /// Whether the stream is over (the server closed it, it broke, or stop() was called).
  [[nodiscard]] bool ended() const { return ended_.load(); }

  /// Checks `observer`'s view right after it applied the frame of `tick` (with what that frame
  /// said it deferred and the observer's own position, when it carried one). Never waits: when
  /// the truth of that tick is not computed yet, a snapshot of the view waits for it and the
  /// oracle's thread checks it then. Thread-safe; `bot` names the bot in the log.
  void check(std::uint32_t observer, std::uint64_t tick, const net::client_view& view,
             const net::deferred_counts& deferred, const std::optional<net::vec3f>& self_position, std::size_t bot);

  /// One entity of a bot's view after a frame, as the checks read it.
  struct held_entity {
    std::uint32_t id, visibility_class;
    float x, y, z;
    std::uint64_t last_tick;  ///< the tick it was last sent (enter or update)
  };
  /// A bot's view after the frame of `tick` (entities by ascending id) and what that frame said.
  struct view_snapshot {
    std::uint32_t observer = 0;
    std::uint64_t tick = 0;
    net::deferred_counts deferred;
    std::optional<net::vec3f> self_position;
    std::size_t bot = 0;
    std::vector<held_entity> held;
  };
  /// Most bytes of snapshots waiting for their tick's truth; beyond, a frame is counted unchecked.
  static constexpr std::size_t max_pending_bytes = std::size_t{1} << 30;

  /// Feeds one truth frame's body directly (tests; start() does this from the socket).
  [[nodiscard]] std::optional<std::string> feed(std::span<const std::uint8_t> body);

  /// The visible set the oracle computed for `observer` at `tick` (tests), or nothing when that
  /// tick is gone or the observer's history is unknown.
  [[nodiscard]] std::optional<std::vector<std::uint32_t>> visible(std::uint32_t observer, std::uint64_t tick) const;

  /// The layout the oracle holds for `tick`, column by column (tests: what sharing and patching
  /// made of it), and how many of its chunks it shares with the layout of the tick before; nothing
  /// when that tick is gone.
  struct layout_columns {
    std::vector<std::uint32_t> ids, classes, sees;
    std::vector<std::uint8_t> kinds;
    std::vector<float> aoi, presence;  // 3 per entity
    std::size_t chunks = 0, chunks_shared_with_prev = 0;
  };
  [[nodiscard]] std::optional<layout_columns> layout_at(std::uint64_t tick) const;

  [[nodiscard]] const oracle_counters& counters() const { return c_; }
  [[nodiscard]] oracle_report report() const;
  /// Ticks of truth kept for checks of late frames and of positions last sent long ago.
  static constexpr std::size_t ring_ticks = 64;
  /// Which targets each observer's scan tests (all three give the same sets; test_bots_oracle
  /// holds each to the tracker's brute-force finder and to each other): `full`, every entity
  /// (brute force); `x_window`, those whose x lies within reach (sorted by x once per tick);
  /// `grid` (the default), those in the cells of a uniform x-y grid of the oracle's own, built
  /// over the truth once per tick, that the observer's grown AOI can reach (entities with a wide
  /// presence box or a non-finite position are tested by every observer).
  enum class scan_mode : std::uint8_t { grid, x_window, full };
  scan_mode scan = scan_mode::grid;
  /// The grid's cell side (m); 0 = half the observers' mean grown AOI half-extent (tests set it).
  float grid_cell = 0;
  /// 1 in `sample` players is recomputed and checked (1 = every one): those whose id sampled()
  /// picks, a fixed subset, so that each one's history (the hysteresis) is continuous. A frame of
  /// another bot is counted in frames_unsampled and not checked. Set before start() or feed().
  unsigned sample = 1;
  /// Entries (8 bytes each) of a block of the stored visible sets: each recompute thread writes
  /// its observers' sets one after another into a block (a set larger than that gets a block of
  /// its own), the blocks kept with their tick's truth and reused when its slot is (tests set it
  /// small, so that sets cross blocks all the time). Set before start() or feed().
  std::size_t set_block = std::size_t{1} << 16;
  /// Whether `id` is in the sample of 1 in `k` (a hash of the id: fixed for the entity's life,
  /// the same on every side that asks).
  [[nodiscard]] static bool sampled(std::uint32_t id, unsigned k) {
    if (k <= 1) return true;
    std::uint32_t h = id;  // murmur3's finalizer: ids that differ in any bit spread over every residue
    h ^= h >> 16, h *= 0x85ebca6bu, h ^= h >> 13, h *= 0xc2b2ae35u, h ^= h >> 16;
    return h % k == 0;
  }
  /// Waits (at most `timeout_s`) until the truth of every tick a bot checked so far is computed
  /// and the views that waited for it are checked: called at the end of a run, before stop().
  void catch_up(double timeout_s);

 private:
  struct layout;
  struct tick_truth;
  struct index;
  struct scratch;
  void run(int fd);
  /// An error when the truth cannot be checked by (a layout naming an id twice).
  [[nodiscard]] std::optional<std::string> compute(const net::truth::tick_frame& f);
  /// Runs work(0) on this thread and work(1 .. threads - 1) on as many others, and waits; their
  /// CPU is added to *cpu_ms (nullptr: the recompute's).
  void run_parallel(unsigned threads, const std::function<void(unsigned)>& work, double* cpu_ms = nullptr);
  void log(const char* kind, std::atomic<std::uint32_t>& logged, const std::string& line);
  /// Compares a snapshot with the truth of its tick (unchecked when that tick is gone or unknown).
  void check_snapshot(const view_snapshot& v);
  /// Checks up to `max_jobs` waiting snapshots whose tick's truth is there (`all`: every one; those
  /// whose truth never came are counted unchecked).
  void drain_pending(bool all, std::size_t max_jobs);

  net::world_bounds world_;
  net::interest_rules rules_;
  net::vec3f tolerance_;
  unsigned threads_;
  problem_fn problem_;
  void* ctx_;
  oracle_counters c_;
  std::vector<std::unique_ptr<tick_truth>> ring_;
  std::shared_ptr<const layout> layout_;
  std::uint64_t next_lineage_ = 1;
  net::truth::tick_frame frame_;
  std::uint64_t prev_tick_ = 0;
  bool any_tick_ = false;
  // Ready ticks: the newest computed (valid while any_ready_).
  mutable std::mutex ready_mutex_;
  std::condition_variable ready_cv_;
  std::atomic<std::uint64_t> ready_tick_{0};
  std::atomic<bool> any_ready_{false}, ended_{false}, stopping_{false};
  std::thread thread_;
  int fd_ = -1;
  std::string stream_error_;
  std::atomic<std::uint32_t> logged_missing_{0}, logged_extra_{0}, logged_leaked_{0}, logged_class_{0},
      logged_position_{0}, logged_stale_{0}, logged_deferral_{0};
  // Costs.
  std::uint64_t truth_ticks_ = 0, truth_bytes_ = 0, truth_layouts_ = 0, truth_changes_ = 0, observers_max_ = 0,
                sampled_max_ = 0;
  double compute_cpu_ms_ = 0, compute_max_ms_ = 0, drain_cpu_ms_ = 0, own_drain_cpu_ms_ = 0;
  double decode_ms_ = 0, index_ms_ = 0, scan_ms_ = 0, publish_ms_ = 0, drain_ms_ = 0;
  std::atomic<std::uint64_t> check_ns_{0};
  // Snapshots of frames that came before their tick's truth (checked by the oracle's thread).
  std::mutex pending_mutex_;
  std::deque<view_snapshot> pending_;
  std::atomic<std::size_t> pending_bytes_{0};  // reserved before a snapshot is made
  /// The oldest waiting snapshot's tick (max when none): a bot checks whether any is due without the lock.
  std::atomic<std::uint64_t> pending_front_tick_{~std::uint64_t{0}};
  std::atomic<std::uint64_t> deferred_checks_{0}, pending_overflow_{0};
  std::atomic<std::uint64_t> newest_checked_tick_{0};  // the newest tick a bot asked to check
  // Scratch of compute(), reused tick to tick: the targets' index, each thread's scratch, and
  // each sampled observer's set as (id << 32) | dense index, stored in blocks of set_block
  // entries that the ring's slots hand back when they are reused.
  std::unique_ptr<index> index_;
  std::vector<std::unique_ptr<scratch>> scratch_;
  /// One observer's visible set where it was stored: `size` entries from `data` (in one block).
  struct set_at {
    const std::uint64_t* data = nullptr;
    std::size_t size = 0;
  };
  std::vector<set_at> sets_;        // by observer index, handed to the tick's slot
  std::vector<std::uint8_t> known_;  // by observer index: whole history seen
  std::mutex blocks_mutex_;
  std::vector<std::vector<std::uint64_t>> free_blocks_;  // blocks of sets no tick holds any more
};

}  // namespace zone::bots
