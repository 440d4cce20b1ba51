// The ground-truth stream of zone-server --oracle (docs/protocol.md, net/truth.h): a loopback
// listener and one sender thread; the tick loop hands it each tick's entities after the world step.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <memory>
#include <mutex>
#include <optional>
#include <span>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "net/truth.h"
#include "zone.h"

namespace zone {

/// What the stream cost (the tick loop's side: encoding and queueing).
struct truth_stats {
  std::uint64_t ticks = 0;         ///< ticks published (with a subscriber, or while the first frames are recorded)
  std::uint64_t bytes = 0;         ///< bytes of those frames
  std::uint64_t layouts = 0;       ///< frames that carried the whole layout
  std::uint64_t changes = 0;       ///< frames that carried changes to it (net/truth.h)
  std::uint64_t changed_entities = 0;     ///< entities in those changes
  std::uint64_t refused_subscribers = 0;  ///< subscribers refused: max_subscribers were connected
  std::uint64_t prefix_subscribers = 0;   ///< subscribers that read the first frames' record first (sender thread)
  std::uint64_t dropped_subscribers = 0;  ///< subscribers closed for falling too far behind
  double publish_ms = 0;           ///< summed time of publish() on the tick loop
};

/// The sets an interest update carried (interest_tracker::carried_by_last_update: (observer,
/// target) pairs ascending, each observer's null marker first) as the stream's columns
/// (net::truth::carried_view): observers ascending, each one's targets ascending.
struct carried_columns {
  std::vector<std::uint32_t> observers, off, targets;
  void assign(std::span<const std::pair<entity_id, entity_id>> pairs);
  [[nodiscard]] net::truth::carried_view view() const { return {observers, off, targets}; }
};

class truth_publisher {
 public:
  /// Most bytes queued for one subscriber; beyond, it is disconnected (an oracle that cannot keep
  /// up must not grow the server without bound, and a gap would make its checks meaningless).
  static constexpr std::size_t max_queued_bytes = std::size_t{512} << 20;
  /// Subscribers served at once unless start() is told otherwise (zone-server --oracle-subscribers).
  static constexpr int default_max_subscribers = 4;

  truth_publisher() = default;
  ~truth_publisher();
  truth_publisher(const truth_publisher&) = delete;
  truth_publisher& operator=(const truth_publisher&) = delete;

  /// Listens on 127.0.0.1:port (0 = ephemeral) and starts the sender thread. Beyond
  /// `max_subscribers` connected at once, a subscriber gets a refusal (net/truth.h) that names the
  /// limit and is closed.
  [[nodiscard]] std::optional<std::string> start(std::uint16_t port, int max_subscribers = default_max_subscribers);
  [[nodiscard]] std::uint16_t port() const { return port_; }
  /// The world after the step of `tick`: encoded once and queued for every subscriber (nothing
  /// done while there is none and the first frames' record is over), with the sets that step
  /// carried (interest_tracker::carried_by_last_update); `first_step`: the server's first step
  /// (net/truth.h). Game thread only.
  void publish(const entity_store& store, std::uint64_t tick,
               std::span<const std::pair<entity_id, entity_id>> carried = {}, bool first_step = false);
  /// The frames from the first one published are kept for prefix_window_s (at most
  /// max_prefix_bytes): a subscriber that connects meanwhile reads them first, so it has every
  /// entity's whole history on this server, those present from its first step included (a zone
  /// restored from a checkpoint; an oracle following a restarted zone connects a few seconds in).
  static constexpr double prefix_window_s = 10;
  static constexpr std::size_t max_prefix_bytes = std::size_t{64} << 20;
  void stop();
  [[nodiscard]] const truth_stats& stats() const { return stats_; }

 private:
  struct subscriber {
    int fd = -1;
    bool has_layout = false;  ///< got a frame with the whole layout (frames before it are not sent)
    std::deque<std::shared_ptr<const std::vector<std::uint8_t>>> queue;
    std::size_t queued_bytes = 0, offset = 0;  // offset into queue.front()
  };
  void run();
  void wake();

  int listen_fd_ = -1, wake_fd_ = -1;
  std::uint16_t port_ = 0;
  std::thread thread_;
  std::atomic<bool> stopping_{false};
  std::atomic<int> subscribers_{0};
  std::atomic<bool> need_layout_{false};  ///< a subscriber joined: the next frame carries the whole layout
  int max_subscribers_ = default_max_subscribers;
  std::mutex mutex_;  // guards subs_
  std::vector<subscriber> subs_;
  std::uint64_t layout_version_ = 0;
  bool any_published_ = false;
  /// The first frames' record (publish_prefix): on while it lasts (game thread); the frames and
  /// their bytes under mutex_ (the sender copies them to a subscriber that connects).
  bool recording_ = true;
  std::chrono::steady_clock::time_point first_publish_{};
  std::deque<std::shared_ptr<const std::vector<std::uint8_t>>> prefix_;
  std::size_t prefix_bytes_ = 0;
  net::truth::encoder encoder_;  // the layout last sent: the whole of it, changes to it, or nothing
  // Scratch columns (the store's types are plain floats and integers; copied as they are).
  std::vector<std::uint8_t> kinds_;
  carried_columns carried_;
  std::vector<std::shared_ptr<std::vector<std::uint8_t>>> pool_;  // frames' buffers, reused
  truth_stats stats_;
};

}  // namespace zone
