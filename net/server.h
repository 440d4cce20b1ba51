// The zone server's network side: a Boost.Asio TCP server with one session per connection.
// Server-only public header of net/ (bots include net/protocol.h; they never pull this in). No Asio types appear here: the implementation is private.
//
// Threading: the server runs its own I/O threads. The game (tick) thread talks to it through
// three calls only: poll() drains what the clients sent, send() queues a frame for a session,
// disconnect() sends an error and closes. None of them blocks on the network: the tick never waits.
#pragma once

#include <chrono>
#include <cstddef>
#include <atomic>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "latency_histogram.h"
#include "protocol.h"

namespace zone::net {

/// How the I/O threads hand their writes to the kernel (server_options::batching).
enum class write_batching : std::uint8_t {
  automatic,  ///< io_uring where the kernel allows it (and the build has liburing), else sendmsg
  uring,      ///< io_uring, or start() fails saying why
  sendmsg,    ///< one sendmsg per session write
};
/// "auto", "io_uring", "sendmsg".
[[nodiscard]] const char* to_string(write_batching b);
/// Parses "auto", "io_uring" (or "uring"), "sendmsg".
[[nodiscard]] std::optional<write_batching> parse_write_batching(std::string_view s);

struct server_options {
  std::string address = "127.0.0.1";
  std::uint16_t port = 0;       ///< 0 = an ephemeral port (see server::port())
  unsigned io_threads = 1;       ///< each runs its own event loop; a session lives on one of them
  /// Player slots: sessions that said hello. A hello over it gets error server_full. Connections
  /// that have not said hello are counted apart (max_pending, max_pending_per_address).
  std::size_t max_connections = 1000;
  decoder_options inbound{};    ///< max inbound frame size and verifier limits
  /// Outbound queue bound per session, in frames. State frames are deltas, so when a state frame
  /// arrives at a full queue, every queued state frame but the one being written is dropped with
  /// it, and the session delivers no state frame until a reset (delivery::state_reset): plain
  /// state frames arriving meanwhile are dropped too (all counted). The game is told once per
  /// such episode (inbound_event::frames_dropped) so replication makes the next frame a reset.
  /// A reset replaces the state frames queued before it. Control frames (delivery::control) are
  /// never dropped; a session whose control frames exceed twice the bound is disconnected (that is
  /// a stuck client, not a slow one). Policy: net/outbound_queue.h.
  std::size_t max_queued_frames = 8;
  /// SO_SNDBUF of each session's socket in bytes; 0 keeps the system's autotuning (on Linux up
  /// to net.ipv4.tcp_wmem's maximum, 4 MiB by default). What the kernel holds for a client that
  /// does not read is beyond the queue's drop policy: a small buffer bounds how stale its state
  /// gets before frames are dropped (4 MiB is minutes of state at 20 KB/s).
  std::size_t socket_send_buffer = 0;
  /// Who writes a session's frames to its socket. true: the thread that calls send() writes the
  /// frame itself with one non-blocking sendmsg when nothing is queued ahead of it for that session
  /// (no I/O-thread wake-up, no epoll round trip); on EAGAIN or a partial write the rest waits in
  /// the queue and the session's I/O thread finishes it when the socket is writable. false: every
  /// write is made by the session's I/O thread (one wake-up per I/O thread for a burst of sends,
  /// then one gathered write per session). Either way one write at a time per session, in order.
  bool direct_writes = false;
  /// How an I/O thread writes the sessions on its ready list. With io_uring, one drain prepares
  /// every ready session's write (a gathered sendmsg each, as below) and submits them to the
  /// kernel together: one system call for up to 256 sessions instead of one each, and no epoll
  /// round trip. Each completion is then handled as a sendmsg's return would be (retire the frames
  /// written, a partial write or EAGAIN waits for the socket, an error closes). Still one write in
  /// flight per session, in queue order; the slow-client rules are unchanged. Writes made by the
  /// sending thread (direct_writes) stay plain sendmsg calls.
  write_batching batching = write_batching::automatic;
  /// With io_uring: each I/O thread's table of registered files, in slots. A session's socket
  /// takes a slot at its first write and gives it back as it closes; its sends then name the slot,
  /// and the kernel skips looking up the descriptor's file on each. Sessions beyond it (or all,
  /// where the kernel refuses a table: before 5.19) send by descriptor. Capped by the open-file
  /// limit; 0 = no table.
  std::size_t ring_file_slots = 65536;
  /// Ready sessions an I/O thread writes before it turns to its other work (reads, new
  /// connections, timers) and then writes the next as many: on a thread that cannot keep up,
  /// a client's hello or ping waits for one slice of writes, not for every ready session's
  /// (docs/protocol.md, "Server"). 0 is taken as 1.
  std::size_t write_slice = 256;
  /// Nice value the I/O threads give themselves (0 = unchanged; 1-19 = lower priority than the
  /// game's threads, which an unprivileged process may always ask for): where the I/O threads
  /// share cores with the tick's workers, the scheduler then lets a worker run its part of a tick
  /// phase before an I/O thread takes the core, so a phase does not end with a preempted task.
  int io_thread_nice = 0;
  /// CPUs the I/O threads are pinned to (all of them to the whole set; empty = not pinned; see
  /// parse_cpu_list in os_limits.h). Beside pool threads pinned to other CPUs, a tick's phase
  /// never waits for a worker an I/O thread preempted (docs/operating.md, "Pinning the threads").
  std::vector<int> io_thread_cpus;
  /// Inputs per second a client may send (token bucket of `input_burst`); inputs over the rate
  /// are dropped and counted; a client that keeps flooding (more than `flood_limit` drops in
  /// a row) gets error rate_limited and is disconnected.
  double inputs_per_second = 60;
  double input_burst = 30;
  std::uint32_t flood_limit = 200;
  /// Pings per second a client may send (its own token bucket of `ping_burst`): pings over the
  /// rate get no pong and are counted; more than `flood_limit` in a row: error rate_limited.
  double pings_per_second = 10;
  double ping_burst = 10;
  /// A session that sends no complete frame for this long gets error timeout and is closed
  /// (clients ping). Bytes of an unfinished frame do not count: a client that drips a frame is idle.
  std::chrono::milliseconds idle_timeout{10000};

  // Admission: a connection is "pending" from accept until its hello, and holds no player slot.
  /// A pending connection that has not completed its hello this long after accept gets error
  /// timeout and is closed, whatever bytes it sent. Nothing but a hello is served before it (a
  /// ping, an input: error unexpected_message).
  std::chrono::milliseconds hello_timeout{3000};
  /// Pending connections in total: at the cap, the one pending longest is closed (error
  /// server_full) to admit the new one, so connections that never say hello cannot keep a player out.
  std::size_t max_pending = 1024;
  /// Pending connections per source address: at the cap, that address's connection pending
  /// longest is closed (error server_full) to admit the new one. One address thus holds at most
  /// this many, and a player behind it (NAT) who says hello at once still gets in.
  std::size_t max_pending_per_address = 256;
  /// Reconnect churn per source address (a token bucket per IPv4 address or IPv6 /64): each
  /// connection that ends less than `connect_min_session` after its accept (it never said hello,
  /// was refused or cut off, or left soon after joining) takes a token from its address's bucket,
  /// which refills at `connect_rate` per second up to `connect_burst` and may run into debt down to
  /// a minute of refill (so a wave of connections opened at once is paid for afterwards). While the
  /// bucket holds less than one token, a new connection from that address is refused at accept:
  /// one pre-encoded error rate_limited frame written without waiting, then closed: no session, no
  /// pending entry, no join, no log line (counted in connections_rate_limited; the server logs one
  /// summary line at most every 10 s). Connections that stay cost nothing, so a load-test swarm that
  /// ramps thousands of bots from one host, or players behind one NAT, are never limited; a client
  /// that reconnects as fast as it is cut off gets `connect_rate` sessions a second. 0 = no limit.
  double connect_rate = 20;
  double connect_burst = 64;
  std::chrono::milliseconds connect_min_session{10000};
  /// A connection refused for reconnect churn is held this long before its answer (error
  /// rate_limited, then a reset), unread: a client that waits for an answer before it tries again
  /// tries once per hold instead of as fast as the server can refuse (tens of thousands a second
  /// on loopback, each an accept and a close). At most 64 held per address (a newer one releases
  /// that address's oldest) and 512 in all, fewer where the open-file limit leaves less beside
  /// max_connections and max_pending (beyond, answered at once). 0 = answered at once.
  std::chrono::milliseconds connect_refusal_hold{2000};
  /// Longest player name in bytes; a name must be 1 .. max_name_bytes printable ASCII characters
  /// (0x20-0x7E) without leading or trailing spaces (error bad_hello otherwise).
  std::size_t max_name_bytes = 32;
};

using session_id = std::uint64_t;

/// What the network threads report to the game thread (in arrival order per session).
struct inbound_event {
  enum class kind : std::uint8_t {
    connected,       ///< a new session: it said a valid hello (the hello message follows at once)
    message,         ///< a client message (hello, input; pings are answered by the server itself)
    frames_dropped,  ///< state frames were dropped for this slow session: it gets no state frame
                     ///< until a delivery::state_reset frame (one event per episode)
    disconnected,    ///< the session is gone (reason says why); no events follow for it
  };
  kind type = kind::message;
  session_id session = 0;
  std::optional<message> msg;   ///< for kind::message
  std::uint64_t dropped = 0;    ///< for kind::frames_dropped: state frames dropped when the episode began
  /// For a hello (kind::message): when its connection was accepted and when it was read (now_us()).
  std::uint64_t accepted_us = 0, hello_us = 0;
  std::string reason;           ///< for kind::disconnected
  /// For kind::disconnected: the client said leave (a logout) before it closed; otherwise the
  /// connection was lost or closed by the server (its entity may wait for a resume).
  bool left = false;
  /// For kind::disconnected: the server cut the client off for breaking the protocol's rules (a
  /// frame that does not parse or verify, an oversize frame, an unknown or unexpected message, a
  /// flood: error_code::bad_frame .. rate_limited); not a lost connection (no resume).
  bool cut_off = false;
};

/// Shared immutable frame: a message sent to many sessions is serialized once. The reference
/// count and the bytes are one allocation (make_shared_frame); copies share the bytes and are
/// thread-safe like std::shared_ptr. Null when default-constructed.
class shared_frame {
 public:
  shared_frame() = default;
  [[nodiscard]] const std::uint8_t* data() const { return bytes_.get(); }
  [[nodiscard]] std::size_t size() const { return size_; }
  [[nodiscard]] std::span<const std::uint8_t> bytes() const { return {bytes_.get(), size_}; }
  explicit operator bool() const { return bytes_ != nullptr; }
  /// Holders of these bytes (std::shared_ptr::use_count: approximate while other threads copy).
  [[nodiscard]] long use_count() const { return bytes_.use_count(); }

 private:
  friend shared_frame make_shared_frame(std::span<const std::uint8_t> frame);
  friend shared_frame make_shared_frame_in(std::shared_ptr<const void> owner, std::span<const std::uint8_t> bytes);
  friend class frame_arena;
  std::shared_ptr<const std::uint8_t[]> bytes_;
  std::size_t size_ = 0;
};
/// A shared frame holding a copy of `frame` (one allocation).
[[nodiscard]] shared_frame make_shared_frame(std::span<const std::uint8_t> frame);
/// A shared frame of bytes that `owner` keeps (no copy, no allocation): every copy of the frame
/// holds a reference to `owner`, whose bytes must stay valid and unchanged while one lives (e.g.
/// a replication engine's output buffer, reused only once nothing holds it: zone/replicator.h).
/// (Inline: the replicator, which has no network, makes them.)
[[nodiscard]] inline shared_frame make_shared_frame_in(std::shared_ptr<const void> owner, std::span<const std::uint8_t> bytes) {
  shared_frame f;
  // The aliasing constructor: owner's count, the frame's bytes.
  if (owner != nullptr) f.bytes_ = std::shared_ptr<const std::uint8_t[]>(std::move(owner), bytes.data());
  f.size_ = f.bytes_ != nullptr ? bytes.size() : 0;
  return f;
}

/// Shared frames carved out of larger blocks, for one thread (each replication worker has its
/// own); the frames it makes are ordinary shared frames, safe on any thread, and they outlive the
/// arena. A frame is either copied in (make) or written in place: reserve() gives room in the
/// current block, the caller writes the frame there (tick_update_writer::finish_into), and
/// commit() makes the frame of it, with no copy. A block is shared by its frames (one reference
/// count) and the arena; once every frame of a block has been written and released, the arena
/// takes the block again (no allocation and no free in the steady state: the I/O threads, which
/// release the frames, never free a block the workers allocated while it is in use, which made
/// glibc's malloc take the allocating thread's arena lock on every free). The arena keeps at most
/// max_spare earlier blocks; when frames hold every one of them (slow clients), it lets go of one
/// in turn (freed by its last frame). A frame over a quarter of a block gets its own allocation.
class frame_arena {
 public:
  /// A quarter of it holds a frame of the default byte budget (8 KiB): every frame in a block.
  static constexpr std::size_t default_block_bytes = 32 * 1024;
  static constexpr std::size_t max_spare = 64;
  explicit frame_arena(std::size_t block_bytes = default_block_bytes);
  /// A copy of `frame` (reserve, copy, commit).
  [[nodiscard]] shared_frame make(std::span<const std::uint8_t> frame);
  /// Room for a frame of up to `bytes` bytes, 8-byte aligned, valid until the next reserve(),
  /// make() or commit(): write the frame there, then commit() it. Nothing is taken until then.
  [[nodiscard]] std::span<std::uint8_t> reserve(std::size_t bytes);
  /// The frame written into the last reservation: its first `bytes` bytes (at most the
  /// reservation's size; throws std::logic_error without one).
  [[nodiscard]] shared_frame commit(std::size_t bytes);
  /// Whether `frame` lies in the last reservation, from its start (then commit(frame.size())).
  [[nodiscard]] bool in_reservation(std::span<const std::uint8_t> frame) const {
    return reserved_ != nullptr && frame.data() == reserved_ && frame.size() <= reserved_bytes_;
  }
  /// Blocks allocated so far (tests, statistics); blocks taken again are not counted.
  [[nodiscard]] std::uint64_t blocks() const { return blocks_; }
  /// Blocks taken again after their frames were released.
  [[nodiscard]] std::uint64_t reused() const { return reused_; }
  /// Frames that got their own allocation (over a quarter of a block).
  [[nodiscard]] std::uint64_t large() const { return large_; }

 private:
  /// A fresh current block: a spare one whose frames are all released, or a new one.
  void next_block();
  std::size_t block_bytes_;
  std::shared_ptr<std::uint8_t[]> block_;  // the current block (aliases a uint64_t array: 8-byte aligned)
  std::size_t used_ = 0;
  std::vector<std::shared_ptr<std::uint8_t[]>> spare_;  // earlier blocks
  std::size_t spare_head_ = 0;  // the one let go of next when all are held
  std::shared_ptr<std::uint8_t[]> own_;  // the reservation of a large frame
  std::uint8_t* reserved_ = nullptr;
  std::size_t reserved_bytes_ = 0;
  std::uint64_t blocks_ = 0, reused_ = 0, large_ = 0;
};

enum class delivery : std::uint8_t {
  state,        ///< a delta on the previous state frame: may be dropped for a slow client, and is
                ///< dropped while the session awaits a reset (after a drop)
  control,      ///< welcome, pong, errors: never dropped
  state_reset,  ///< a state frame that rebuilds the client's view (tick_update.reset): ends the
                ///< wait after a drop; replaces the state frames queued before it
};

/// One frame for server::send_many().
struct outgoing_frame {
  session_id session = 0;
  shared_frame frame;
  delivery kind = delivery::state;
  /// CLOCK_MONOTONIC microseconds (server::now_us) the frame's age counts from in
  /// server::frame_write_age(), e.g. when its tick began building frames; 0: when it is queued.
  std::uint64_t stamp_us = 0;
};

/// Counters (monotonic, thread-safe snapshot).
struct server_stats {
  std::uint64_t connections_accepted = 0;  ///< TCP connections taken from the backlog and admitted (pending until hello; not those refused at accept)
  std::uint64_t connections_refused = 0;  ///< hellos over max_connections (error server_full)
  std::uint64_t sessions_open = 0;        ///< sessions that said hello and are open (player slots held)
  std::uint64_t pending_open = 0;         ///< connections open that have not said hello yet
  std::uint64_t pending_evicted_address = 0;  ///< pending connections closed for a newer one from their address (max_pending_per_address)
  std::uint64_t pending_evicted = 0;      ///< pending connections closed for a newer one (max_pending)
  std::uint64_t hello_timeouts = 0;       ///< pending connections closed at hello_timeout
  std::uint64_t connections_rate_limited = 0;  ///< connections refused at accept: their address's reconnect churn was over connect_rate
  std::uint64_t connections_charged = 0;  ///< connections that ended within connect_min_session of their accept (took a token)
  std::uint64_t pending_spared = 0;       ///< at a pending cap, connections not evicted because their first bytes (a hello) waited unread
  std::uint64_t hellos_rejected = 0;      ///< hellos with a bad name (error bad_hello)
  std::uint64_t idle_timeouts = 0;        ///< sessions closed at idle_timeout
  std::uint64_t rate_limited = 0;         ///< sessions closed for flooding (error rate_limited)
  std::uint64_t frames_in = 0;
  std::uint64_t frames_out = 0;
  std::uint64_t writes = 0;            ///< gathered socket writes (one may carry several frames; one the
                                       ///< socket takes in part goes on in more sendmsg calls)
  std::uint64_t write_batches = 0;     ///< io_uring submissions of the I/O threads (each carries the
                                       ///< writes of several sessions); 0 without io_uring
  std::uint64_t registered_sends = 0;  ///< of the io_uring sends, those naming a registered file
                                       ///< (server_options::ring_file_slots)
  std::uint64_t bytes_in = 0;
  std::uint64_t bytes_out = 0;
  std::uint64_t frames_dropped = 0;    ///< state frames not delivered to slow clients (dropped or superseded)
  std::uint64_t resyncs_requested = 0; ///< drop episodes reported to the game (frames_dropped events)
  std::uint64_t stale_drops = 0;       ///< drop_stale_state calls that found the session (stalled clients)
  std::uint64_t frames_rejected = 0;   ///< inbound frames that failed decoding (session closed)
  std::uint64_t inputs_dropped = 0;    ///< over the input rate
  std::uint64_t pings_answered = 0;
  std::uint64_t pings_dropped = 0;     ///< over the ping rate, or with half the queue bound of control frames waiting (no pong)
};

class server {
 public:
  explicit server(server_options opt = {});
  ~server();  ///< stops
  server(const server&) = delete;
  server& operator=(const server&) = delete;

  /// Raises the process's soft open-file limit to the hard limit (logged, with a warning when
  /// max_connections does not fit), binds, listens and starts the I/O threads. Returns a readable
  /// error on failure. When the process runs out of file descriptors later, accepting pauses
  /// (50 ms at a time) with an error log naming the limit, and resumes when sessions close.
  /// A stopped server may be started again (with port 0, on a new ephemeral port).
  [[nodiscard]] std::optional<std::string> start();
  /// The bound port (after start).
  [[nodiscard]] std::uint16_t port() const;
  /// Closes every session and joins the I/O threads. Idempotent.
  void stop();

  /// Moves every event reported since the last call into `out` (appended). Game thread.
  void poll(std::vector<inbound_event>& out);
  /// Queues a frame for a session; false when the session is gone. Never blocks on the network;
  /// safe from any thread (the zone server sends each frame from the worker that built it).
  /// Frames of one session are delivered in the order of the calls (state frames may be dropped,
  /// see server_options::max_queued_frames); send a session's state frames from one thread at a
  /// time, in the order they were built. Cost: the frame goes through the session's outbound
  /// queue under the session's own lock; with direct_writes (off by default) a session with nothing
  /// queued gets the frame written at once by the calling thread (one non-blocking sendmsg: the
  /// kernel's loopback or TCP send is then the caller's CPU), otherwise its I/O thread writes it
  /// (a session that was idle is put on its I/O thread's ready list, and only a ready list that
  /// was empty posts a wake-up). frames_out counts frames, writes counts socket writes.
  bool send(session_id s, shared_frame frame, delivery d = delivery::state);
  /// send() for each frame, in order: one lookup lock for all of them, and (without direct
  /// writes) one ready-list append per I/O thread for the sessions that became ready. How many
  /// went to a session that is open (the others are gone and skipped). The replication workers
  /// hand over a chunk of clients' frames at a time this way.
  std::size_t send_many(std::span<const outgoing_frame> frames);
  /// send_many(), taking the frames (each slot's frame is left null): no reference count is
  /// touched for a copy of each frame (the zone server's replication workers hand theirs over so).
  std::size_t send_many_moved(std::span<outgoing_frame> frames);
  /// The session's state backlog: state frames sent to it (send) and neither written to its
  /// socket nor dropped yet. Read it (any thread, relaxed) to pace a client to what it absorbs:
  /// a game that builds no new state frame while the backlog is at a bound never overflows the
  /// queue, so a slow client gets fewer frames instead of drops and resets. The counter outlives
  /// the session (it then stays where it was). Null when the session is gone.
  [[nodiscard]] std::shared_ptr<const std::atomic<std::uint32_t>> state_backlog(session_id s) const;
  /// Bytes written to the session's socket so far (any thread, relaxed): a client that reads, even
  /// slowly, moves it on; one that stopped reading does not once the kernel's buffers are full.
  /// Outlives the session. Null when the session is gone.
  [[nodiscard]] std::shared_ptr<const std::atomic<std::uint64_t>> bytes_written(session_id s) const;
  /// How old each state frame was when the kernel took its last byte (microseconds, from its
  /// outgoing_frame::stamp_us, or from when send() queued it; ~4% buckets, as the bot swarm's
  /// latencies): the server's share of a client's update latency (the rest is the network and the
  /// client). Any thread; summed over the writing threads when read. Frames dropped, or written in
  /// part when their session closed, are not in it.
  [[nodiscard]] latency_histogram_us frame_write_age() const;
  /// The game finds the session stalled (it has not drained its socket for a while): its queued
  /// state frames that are not being written are dropped (counted in frames_dropped; they would be
  /// stale by the time the client reads them) and its queue awaits a reset (outbound_queue::
  /// drop_stale: plain state frames are dropped until one), so the caller makes its next frame a
  /// reset and builds it once state_backlog() is 0 (the socket drained). How many were dropped;
  /// 0 also when the session is gone. Any thread.
  std::size_t drop_stale_state(session_id s);
  /// Sends error(code, reason) to the session, then closes it. Never blocks.
  void disconnect(session_id s, error_code code, std::string reason);

  [[nodiscard]] server_stats stats() const;
  /// Whether the I/O threads write through io_uring (after start; server_options::batching).
  [[nodiscard]] bool uses_io_uring() const;
  [[nodiscard]] const server_options& options() const;

  /// Microseconds on the host's CLOCK_MONOTONIC (steady_clock): what pong and tick updates carry,
  /// so a client on the same host can time updates without clock sync.
  [[nodiscard]] std::uint64_t now_us() const;

  struct impl;  ///< the Asio implementation (server.cpp); opaque to users

 private:
  std::unique_ptr<impl> impl_;
};

}  // namespace zone::net
