// The live zone viewer (docs/viewer.md): GET /viewer serves one static page (embedded in the
// binary), /viewer/ws streams the latest published snapshot of the zone to each connected page
// over a WebSocket, and GET /viewer/entity.json?id=N answers one selected entity's data as JSON.
//
// The tick never waits for a viewer: it copies the zone's columns into a snapshot buffer (only
// while a viewer is connected) and publishes it with one atomic exchange (three buffers rotate
// between the tick and the viewer's thread: no lock, no allocation). Everything else runs on the
// viewer's own thread, at a low CPU priority (viewer_options::nice): each session encodes the
// newest snapshot for its own viewport when its previous frames are written (so a slow page gets
// fewer, fresher frames), the stats JSON is formatted there, and a session is closed when a write
// stalls, when it sends anything but a well-formed view request, or when it floods. The page can
// only choose what it looks at.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

namespace zone::net {

/// One published state of the zone, as the viewer streams it. Plain data: the zone fills it with
/// plain copies of its columns (converted only when encoded, on the viewer's thread).
struct viewer_snapshot {
  std::uint64_t tick = 0;
  float world_lo[3]{}, world_hi[3]{};
  // Every entity, by dense index (size() entities: ids, classes and kind hold size() values, xy
  // twice as many).
  std::vector<std::uint32_t> ids;
  std::vector<float> xy;  ///< x, y of each entity, as the zone's store holds positions (z: no frame needs it)
  std::vector<std::uint32_t> classes;   ///< visibility class of each entity (one bit set: bit 1 normal, 2 stealth, 3 red, 4 blue)
  std::vector<std::uint8_t> kind;       ///< 0 player, 1 NPC, 2 boss
  /// The filler's own tag for ids, classes and kind (the zone: its store's layout version): equal
  /// tags mean those three need not be copied again; 0 = none.
  std::uint64_t layout = 0;

  /// Entities in the snapshot (the columns' common length; a short column shortens it).
  [[nodiscard]] std::size_t size() const {
    const std::size_t n = ids.size() < classes.size() ? ids.size() : classes.size();
    const std::size_t m = kind.size() < xy.size() / 2 ? kind.size() : xy.size() / 2;
    return n < m ? n : m;
  }
  [[nodiscard]] float x(std::size_t i) const { return xy[2 * i]; }
  [[nodiscard]] float y(std::size_t i) const { return xy[2 * i + 1]; }

  /// What a page shows for the entity it selected (only entities some viewer selected).
  struct event {
    std::uint64_t tick = 0;
    std::uint32_t id = 0;
    bool enter = false;
  };
  struct selection {
    std::uint32_t id = 0;
    bool alive = false;
    float position[3]{};
    float aoi_half[3]{};
    float presence_half[3]{};
    float hysteresis = 0;
    std::uint32_t sees = 0;  ///< visibility-class bit set of its AOI
    std::uint8_t visibility = 0;
    std::uint8_t kind = 0;
    std::vector<std::uint32_t> visible;   ///< its visible set at `tick`, ascending
    std::vector<std::uint8_t> tier;       ///< replication tier of each visible entity: 0 near, 1 mid, 2 far
    std::vector<event> events;            ///< its latest enter/leave events (a sliding window), oldest first
  };
  std::vector<selection> selections;
};

/// What the stats message (a JSON text frame, about twice a second) says: the zone fills it, the
/// viewer's thread formats it (viewer_stats_json).
struct viewer_stats {
  std::uint64_t tick = 0;
  double tick_rate = 0, budget_ms = 0, entities = 0, clients = 0, pairs = 0, candidates = 0, visible = 0, enters = 0,
         leaves = 0, overruns = 0, byte_budget = 0, update_near = 0, update_mid = 0, tick_p99_ms = 0,
         interest_p99_ms = 0;
  std::string interest_on;
  double world[4]{};  ///< x0, y0, x1, y1
  /// One tick's phases (ms): the ticks since the previous message, at most max_ticks.
  struct tick_row {
    std::uint64_t tick = 0;
    double inputs = 0, behaviours = 0, integrate = 0, interest = 0, replicate = 0, viewer = 0, total = 0;
  };
  static constexpr std::size_t max_ticks = 256;
  std::vector<tick_row> ticks;  ///< capacity max_ticks in the viewer's buffers: appending allocates nothing
};

/// The stats message as JSON: `{"type":"stats","tick":...,"ticks":[[tick, inputs, behaviours,
/// integrate, interest, replicate, viewer, total], ...]}` (docs/viewer.md).
[[nodiscard]] std::string viewer_stats_json(const viewer_stats& s, std::size_t viewers, std::uint64_t viewer_bytes);

/// Limits and switches of the viewer.
struct viewer_options {
  std::size_t max_viewers = 4;       ///< WebSocket sessions at once; more are refused (503)
  bool allow_remote = false;         ///< serve peers that are not on a loopback address
  double stall_close_s = 5;          ///< close a session whose frame has not been written for this long
  double max_requests_per_s = 60;    ///< close a session that sends more view requests than this
  std::uint32_t grid_cells = 128;    ///< density grid cells per axis when a viewport holds too many entities
  int nice = 19;                     ///< the viewer thread's nice value (Linux, per thread): it yields the cores to the tick
  bool idle = true;                  ///< and its policy SCHED_IDLE where the OS allows it (lower_thread_priority)
};

/// What lower_thread_priority applied to the calling thread.
struct thread_priority {
  long tid = 0;               ///< the thread (Linux thread id)
  int nice = 0;               ///< its nice value after the call (getpriority)
  bool idle = false;          ///< its policy is SCHED_IDLE
  bool idle_refused = false;  ///< SCHED_IDLE was asked for and the OS refused it (the nice value stands alone)
};
/// Lowers the calling thread's CPU priority below the tick's threads: its nice value to `nice`
/// (0..19; 0 leaves it), then, with `idle`, its policy to SCHED_IDLE (Linux lets any thread take
/// it; the scheduler runs such a thread only on a core no other thread wants, takes the core back
/// at once when one wakes, and places a woken thread on a core that runs only SCHED_IDLE threads
/// as if that core were idle). A refused step is skipped: the thread keeps what it had (the nice
/// value when SCHED_IDLE is refused), logged once per process. `set_idle` (tests: a refusing OS)
/// replaces the sched_setscheduler call; it returns 0 or -1 with errno set.
thread_priority lower_thread_priority(bool idle, int nice, int (*set_idle)() = nullptr);

/// The viewer's HTTP routes, WebSocket sessions and own thread. Two sides:
/// - the producer (the zone's tick, or a thread it hands a snapshot to, never two at once):
///   next_snapshot()/publish(), next_stats()/
///   publish_stats(), selection_version()/selected(), viewers(): no lock, no allocation, no wait;
/// - the viewer's thread: every /viewer request handed over by the HTTP server (handoff moves the
///   connection onto it), every session, every encode.
class viewer_server {
 public:
  explicit viewer_server(viewer_options opt = {});
  ~viewer_server();
  viewer_server(const viewer_server&) = delete;
  viewer_server& operator=(const viewer_server&) = delete;

  /// Open sessions now (a relaxed read: the tick skips building snapshots while it is 0).
  [[nodiscard]] std::size_t viewers() const;
  /// Changes whenever a page's selection may have changed (a relaxed read: the tick reads
  /// selected() only then).
  [[nodiscard]] std::uint64_t selection_version() const;
  /// The entities some page has selected (at most one per session), ascending, for the tick to
  /// fill in (lock-free reads of one slot per session).
  [[nodiscard]] std::vector<std::uint32_t> selected() const;

  /// The snapshot the producer fills next. One of three buffers that rotate: it holds what was
  /// last filled into that buffer (so a filler can skip columns that did not change: `layout`).
  [[nodiscard]] viewer_snapshot& next_snapshot();
  /// Makes next_snapshot() the newest (one atomic exchange; the viewer's thread picks it up); the
  /// next call of next_snapshot() returns another buffer.
  void publish();
  /// Likewise for the stats message; publish_stats() leaves the next buffer's `ticks` empty.
  [[nodiscard]] viewer_stats& next_stats();
  void publish_stats();

  struct counters {
    std::uint64_t sessions_opened = 0, sessions_refused = 0, sessions_closed_stalled = 0, sessions_closed_hostile = 0,
                  frames_sent = 0, bytes_sent = 0, snapshots_published = 0;
  };
  [[nodiscard]] counters stats() const;
  /// The viewer's thread and the priority it runs at (set before the constructor returns).
  [[nodiscard]] thread_priority thread_info() const;

  struct impl;  ///< the Beast implementation (viewer.cpp); sessions share it
  [[nodiscard]] impl& get() { return *impl_; }
  [[nodiscard]] std::shared_ptr<impl> shared_impl() { return impl_; }

 private:
  std::shared_ptr<impl> impl_;
};

/// How long a session's timer sleeps before it looks for a new snapshot (nanoseconds), from the
/// last snapshot's publication (`last_ns`, steady clock; 0: none yet) and the time between the
/// last two (`period_ns`; 0: unknown): until just after the next one is due (so that it is
/// encoded and written as soon as the tick has published it, in the time between ticks, and not
/// in the middle of the next tick), polling each millisecond while it is due but not there (up to
/// 10 ms late), else at most 50 ms (the stall check's and the stats' pace).
[[nodiscard]] std::int64_t viewer_poll_delay_ns(std::int64_t now_ns, std::int64_t last_ns, std::int64_t period_ns);

/// The embedded page (net/viewer/index.html).
[[nodiscard]] std::string_view viewer_page();

// ---- The wire format of /viewer/ws (little-endian; docs/viewer.md) ---------------------------

/// A page's view request: 28 bytes, the only message a session accepts: u8 type (1), three zero
/// bytes, f32 x0 y0 x1 y1, u32 selected, u32 max_points.
struct viewer_request {
  float x0 = 0, y0 = 0, x1 = 0, y1 = 0;  ///< the viewport (world metres), x0 < x1, y0 < y1
  std::uint32_t selected = 0;             ///< entity to follow (0 = none)
  std::uint32_t max_points = 0;           ///< most entities sent one by one; beyond, a density grid
};
inline constexpr std::size_t viewer_request_bytes = 28;
inline constexpr std::uint8_t viewer_request_type = 1;
inline constexpr std::uint32_t viewer_max_points = 1u << 20;
/// Parses a view request; nothing for anything malformed (size, type, non-finite, empty
/// viewport, max_points above viewer_max_points).
[[nodiscard]] std::optional<viewer_request> parse_viewer_request(std::span<const std::uint8_t> bytes);

inline constexpr std::uint8_t viewer_frame_entities = 1, viewer_frame_density = 2, viewer_frame_selection = 3;
inline constexpr std::size_t viewer_frame_header_bytes = 32, viewer_entity_record_bytes = 10;

/// Encodes the entities frame of `s` for request `r` into `out` (replacing it): the entities in
/// the viewport one by one (quantized to 16 bits over the viewport), or the density grid when more
/// than r.max_points are inside.
void encode_viewer_view(const viewer_snapshot& s, const viewer_request& r, std::uint32_t grid_cells,
                        std::vector<std::uint8_t>& out);
/// Encodes the selection frame of one selected entity.
void encode_viewer_selection(const viewer_snapshot& s, const viewer_snapshot::selection& sel, std::vector<std::uint8_t>& out);
/// The selection as JSON (GET /viewer/entity.json).
[[nodiscard]] std::string viewer_selection_json(const viewer_snapshot& s, const viewer_snapshot::selection& sel);

}  // namespace zone::net
