// A zone server's membership in a world of zones over NATS (docs/world.md): the layout and the
// region leases in NATS KV (changed only by compare-and-set), ghosts on core NATS subjects, and
// handoffs on a JetStream stream (message-id dedupe) with entity ownership CAS'd in KV. Built
// only when libnats is found (ZONE_HAVE_NATS).
//
// Subjects (W = the world's name, r = a region):
//   world.W.ghost.r     ghost messages to region r (one per neighbour per tick)
//   world.W.snap.r      "send me a snapshot" to region r (payload: the asking region)
//   world.W.input.r     inputs forwarded to region r (a handed-off player's client not moved yet)
//   world.W.handoff.r   handoff records to region r (JetStream stream WORLD_W, durable consumer per region)
//   world.W.census      request: every zone answers with the world-wide ids it owns (and their epochs)
// KV buckets: world-W (key "layout", "inc.r" = region r's claim count, "e.<gid>" = an entity's
// owner "region epoch"), world-W-lease (key "r.r" = "host port incarnation" of region r's zone,
// with a TTL: a zone that stops renewing it loses the region).
#pragma once

#include <array>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <random>
#include <string>
#include <string_view>
#include <thread>
#include <unordered_map>
#include <vector>

#include "world.h"
#include "zone/zone_server.h"

struct __natsConnection;
struct __natsSubscription;
struct __natsMsg;
struct __jsCtx;
struct __kvStore;

namespace zone::world {

struct node_options {
  std::string world;   ///< the world's name
  std::string url;     ///< NATS server URL
  std::uint32_t cols = 2, rows = 2;  ///< layout of a new world (an existing layout wins)
  net::world_bounds bounds{{0, 0, 0}, {4096, 4096, 256}};
  std::string advertise_host = "127.0.0.1";  ///< where redirected clients reach this zone
  double lease_ttl_s = 3;                    ///< a region's lease lapses this long after its zone's last renewal
  double nats_timeout_s = 2;                 ///< how long a connect, or a KV or JetStream request, waits for NATS
  float handoff_margin = 8;
  float ghost_band = 0;  ///< 0: world::ghost_band(zone config)
  std::uint32_t ghost_timeout_ticks = 60;
  double unclaimed_player_s = 10;  ///< a handed-off player whose client never came is removed after this
  /// A player restored from a checkpoint (its zone was lost) waits this long for its client to
  /// come back with its resume token (welcome.resume_token), then is removed.
  double resume_s = 30;
  /// A player whose client's connection ended (the zone alive) is kept this long, standing, for
  /// that client to come back with its resume token (0: removed at once). At most as many wait as
  /// the zone has player slots.
  double linger_s = 0;
  /// Most entities the zone owns (link_options::capacity; 0: the store's capacity): a handoff
  /// into a full zone is not acked but offered again after `no_room_retry_s` (docs/world.md).
  std::size_t capacity = 0;
  /// link_options::hold_for_room: keep an entity past the border while its neighbour is full.
  bool hold_for_room = true;
  double no_room_retry_s = 0.25;
  /// How long a joining zone listens for the running zones' census answers before it claims a
  /// region (0: it does not ask). A region a running zone answers for is not claimed even where
  /// its lease is missing (the world's JetStream state lost and not made again yet), and the
  /// incarnation claimed counts on from the highest among the ids alive in the world.
  double join_census_s = 0.5;
  /// How long join() waits for a region while every region is held, polling the leases every
  /// quarter of a second (cheap: the census is taken only once one has lapsed): 0 tries once;
  /// a restarted zone waits for its predecessor's lease to lapse; a standby
  /// (`zone-server --world-standby`) waits forever and takes the first region whose zone died.
  double claim_wait_s = 0;
  /// Asked between the polls of that wait: false gives up (a stop signal). Tests tick their
  /// in-process zones in it.
  std::function<bool()> keep_waiting;
  /// How often the zone writes a checkpoint of its entities (players with their resume tokens) to JetStream (0:
  /// never). A zone that claims a region restores the region's last checkpoint (whatever this
  /// says) instead of a new population: a killed zone's entities come back (docs/world.md,
  /// "Checkpoints").
  double checkpoint_s = 1;
  /// Most bytes of one checkpoint message (a checkpoint is cut into as many as it needs).
  std::size_t checkpoint_chunk_bytes = 256 * 1024;
};

/// Counters of a node (game thread writes, any thread may read roughly).
struct node_stats {
  std::atomic<std::uint64_t> handoffs_sent{0}, handoff_cas_conflicts{0};
  /// Ownership CASes that failed but had taken effect (the read-back found our value): published.
  std::atomic<std::uint64_t> handoff_cas_confirmed{0};
  /// Rounds of the sender that did not settle its first record (NATS unreachable or slow: the CAS
  /// unsettled, the publish or a delete failed): the record stays first and is tried again.
  std::atomic<std::uint64_t> handoff_retries{0};
  /// Ticks on which no entity was handed off because NATS was unreachable (the connection down, or
  /// the sender unable to settle its first record): entities past the border stayed owned here.
  std::atomic<std::uint64_t> handoff_hold_ticks{0};
  /// Records the sender still held when the zone stopped with NATS unreachable: lost with the zone.
  std::atomic<std::uint64_t> handoffs_abandoned{0};
  /// Leases that lapsed while NATS was unreachable and were taken back (nobody had claimed the region).
  std::atomic<std::uint64_t> lease_reclaims{0};
  std::atomic<std::uint64_t> handoffs_applied{0}, handoff_duplicates{0}, redirects{0}, redirect_claims{0};
  std::atomic<std::uint64_t> inputs_forwarded{0}, inputs_received{0}, snapshot_requests{0}, players_abandoned{0};
  /// Players restored from a checkpoint to wait for their clients, and those whose client came back
  /// with its resume token (the others are removed after node_options::resume_s, in players_abandoned).
  std::atomic<std::uint64_t> players_restored{0}, players_resumed{0};
  /// Players kept after their client's connection ended (node_options::linger_s), and those whose
  /// client came back with its token (the others are removed, in players_abandoned).
  std::atomic<std::uint64_t> players_lingered{0}, players_back_after_linger{0};
  std::atomic<std::uint64_t> ghost_publish_failures{0}, ghost_inbox_dropped{0};
  std::atomic<std::uint64_t> handoffs_no_room{0};  ///< records offered to a full zone, handed back to the stream to retry
  /// NATS answers, but the world's JetStream state is gone (its lease bucket's stream not found: a
  /// nats-server restarted without its store): true until this zone has made it again
  /// (docs/world.md, "Faults").
  std::atomic<bool> jetstream_state_lost{false};
  /// Times this zone made the world's JetStream state again (buckets, stream, layout, its
  /// incarnation, lease and consumer), and what its sender put back: ownership records of the
  /// entities it owns or sends, and records it had published in the last 10 s (published again).
  std::atomic<std::uint64_t> world_remade{0}, owners_reput{0}, records_republished{0};
  /// Checkpoints written (with the entities and bytes of the last one), skipped (the previous one
  /// still being written when the next was due) and failed (NATS refused a message: the next one
  /// is tried on time).
  std::atomic<std::uint64_t> checkpoints_written{0}, checkpoints_skipped{0}, checkpoint_failures{0};
  std::atomic<std::uint64_t> checkpoint_entities{0}, checkpoint_bytes{0};
  /// The game thread's part of a checkpoint (the copy of what it owns): the longest and the sum, in
  /// microseconds, over `checkpoint_copies`.
  std::atomic<std::uint64_t> checkpoint_copy_max_us{0}, checkpoint_copy_total_us{0}, checkpoint_copies{0};
  /// At the join: entities of the region's last checkpoint left out because KV no longer names
  /// this region at their epoch (handed off since) or could not be read, or that did not fit (those
  /// taken back: link_stats::restored).
  std::atomic<std::uint64_t> restore_skipped{0};
  /// Of link_stats::restored: entities not in the checkpoint taken from their handoff records
  /// (adopted after it, or handed to this region and not adopted yet).
  std::atomic<std::uint64_t> restored_from_records{0};
};

/// What a failed ownership CAS was, judged by the key read back after it (docs/world.md "Handoff").
enum class cas_readback : std::uint8_t {
  publish,   ///< KV holds the value we wanted: the CAS took effect (only its reply was lost)
  retry,     ///< KV unchanged (still at the revision we CAS'd from; no entry when we created): try again
  rebase,    ///< KV names us, at the epoch we hold, at another revision (the record put back after
             ///< the world's JetStream state was made again): try again from that revision
  conflict,  ///< anything else (another value, or the record gone): the entity is not ours
};
/// `wanted`: the value the CAS wrote; `from_revision`: the revision it CAS'd from (0: a create);
/// `ours`: the value naming this zone at the epoch it holds; `found`: the key has a live entry
/// (false: none, or deleted), whose `value` and `revision` follow.
[[nodiscard]] cas_readback judge_cas_readback(std::string_view wanted, std::uint64_t from_revision,
                                              std::string_view ours, bool found, std::string_view value,
                                              std::uint64_t revision);

/// Why a lease renewal was refused, judged by the lease key read back (docs/world.md "Regions").
enum class lease_readback : std::uint8_t {
  ours,     ///< our value (its incarnation is this claim's alone) at another revision: an earlier
            ///< renewal took effect but its reply was lost; renew from that revision
  lapsed,   ///< no key: the lease lapsed (NATS unreachable longer than its TTL); create it again
            ///< (succeeds only if nobody claimed the region meanwhile)
  taken,    ///< another value: another zone holds the region; stop serving it
  unknown,  ///< the key unreadable: try again at the next renewal
};
/// `ours`: this zone's lease value; `readable`: the read answered; `found`: the key has a live
/// entry (false: none, or deleted), whose `value` follows.
[[nodiscard]] lease_readback judge_lease_readback(std::string_view ours, bool readable, bool found,
                                                  std::string_view value);

/// One zone's NATS side; a zone_extension for zone_server.
class nats_node final : public zone_extension {
 public:
  /// Connects, reads or creates the layout, and claims a free region (lease by CAS). nullptr and
  /// `*error` when the server is unreachable or every region is taken.
  static std::unique_ptr<nats_node> join(const node_options& opt, const zone_config& zone, std::string* error);
  ~nats_node() override;
  nats_node(const nats_node&) = delete;
  nats_node& operator=(const nats_node&) = delete;

  [[nodiscard]] std::uint32_t region() const { return region_; }
  [[nodiscard]] std::uint32_t incarnation() const { return incarnation_; }
  /// How long the region's lease lasts after a renewal: the world's (its lease bucket's TTL, set
  /// by the world's first zone), whatever node_options::lease_ttl_s asked.
  [[nodiscard]] double lease_ttl_s() const { return opt_.lease_ttl_s; }
  [[nodiscard]] const layout& map() const { return map_; }
  /// The zone config to run this region with: NPCs and towns inside the region, a seed of its own.
  [[nodiscard]] zone_config zone_for_region(zone_config c) const;
  [[nodiscard]] const zone_link& link() const { return *link_; }
  [[nodiscard]] const node_stats& stats() const { return stats_; }
  /// Handoff latency (decision in the old zone to adoption in the new one), ms and ticks.
  [[nodiscard]] const latency_histogram& handoff_ms() const { return handoff_ms_; }
  [[nodiscard]] const latency_histogram& handoff_ticks() const { return handoff_ticks_; }
  /// Gives the region up (deletes the lease) on the way out; the destructor calls it. A zone that
  /// served (started() was called) gives its checkpoint up too; one that never did (its server
  /// failed to start: a port in use) leaves the region's checkpoint to the next zone.
  void leave();

  // zone_extension
  void started(std::uint16_t port) override;
  void before_step(zone_world& w) override;
  void take_class_changes(std::vector<class_change>& out) override;
  void after_step(zone_world& w, std::vector<redirect>& out) override;
  claim claim_token(const std::string& token, zone_world& w, entity_id& entity) override;
  std::string resume_token(entity_id e, const std::string& claimed) override;
  bool keep_for_resume(entity_id e, zone_world& w) override;
  [[nodiscard]] bool owns(entity_id e) const override { return link_->owns(e); }
  void forward_input(entity_id e, const vec3& intent, std::uint32_t sequence) override;
  [[nodiscard]] bool must_stop() const override { return lease_lost_.load(); }
  void clients(std::size_t players, std::size_t slots) override {
    players_ = players;
    slots_ = slots;
  }

  /// Testing hook (tests/world/test_world_nats.cpp): one round of the sender thread for `r` (the
  /// ownership CAS with its read-back, then the publish) on the calling thread, the first
  /// `fail_first` CAS attempts taken as failed without being sent (a timeout that changed
  /// nothing). Returns the KV revision its CAS settled at when the record was published (0: not
  /// ours, or not settled: the sender would try it again).
  /// Testing hook: put_record() of the sender thread (an ownership record put back after the
  /// world's JetStream state was made again) on the calling thread.
  bool put_record_for_testing(global_id g, std::uint32_t region, std::uint64_t epoch) {
    return put_record(g, region, epoch);
  }
  /// Testing hook: a checkpoint at the end of the next tick (whatever checkpoint_s says).
  void checkpoint_next_tick_for_testing() { checkpoint_due_ = true; }
  /// Testing hook: stops as a killed zone would (no lease given up, no checkpoint removed, no
  /// handoff acked): its threads end and its connection closes.
  void crash_for_testing() {
    crashed_ = true;
    leave();
  }
  std::uint64_t send_handoff_for_testing(handoff_record r, int fail_first = 0) {
    outgoing o{std::move(r)};
    return send(o, fail_first) == send_outcome::done && o.cas_done ? o.record.owner_revision : 0;
  }

 private:
  nats_node() = default;
  struct inbound_msg {
    enum class kind : std::uint8_t { ghosts, snapshot_request, input, census } what;
    std::vector<std::uint8_t> data;
    std::string reply;
  };
  struct sub_context {
    nats_node* node = nullptr;
    inbound_msg::kind what = inbound_msg::kind::ghosts;
  };
  std::array<sub_context, 4> sub_ctx_{};  ///< one per core subscription (its callback's closure)
  static void on_message(__natsConnection*, __natsSubscription*, __natsMsg* msg, void* closure);
  void heartbeat_loop();
  void fetch_loop();
  void send_loop();
  /// A record for the sender thread: a handoff (epoch > 0), or the removal of a departed entity's
  /// ownership record (epoch 0).
  struct outgoing {
    handoff_record record;
    bool cas_done = false;  ///< KV names the new owner by our CAS (record.owner_revision): publish only
  };
  enum class send_outcome : std::uint8_t {
    done,   ///< published (or deleted), or refused by the ownership CAS: off the queue
    retry,  ///< not settled (NATS unreachable or slow): try the same record again later
  };
  enum class cas_outcome : std::uint8_t { ours, refused, unsettled };
  send_outcome send(outgoing& o, int fail_first);                ///< one round for the sender's first record
  cas_outcome ownership_cas(handoff_record& r, int fail_first);  ///< ours: KV names r.to by our CAS
  [[nodiscard]] std::string subject(const char* what, std::uint32_t region) const;
  void refresh_addresses();  ///< the region address table from the leases (not on the game thread)
  void answer_census(const std::string& reply);

  node_options opt_;
  layout map_;
  std::uint32_t region_ = 0, incarnation_ = 0;
  std::unique_ptr<zone_link> link_;
  __natsConnection* nc_ = nullptr;
  __jsCtx* js_ = nullptr;
  __kvStore* kv_ = nullptr;
  __kvStore* lease_ = nullptr;
  __natsSubscription* sub_ghosts_ = nullptr;
  __natsSubscription* sub_snap_ = nullptr;
  __natsSubscription* sub_input_ = nullptr;
  __natsSubscription* sub_census_ = nullptr;
  __natsSubscription* sub_handoff_ = nullptr;  // pull consumer
  std::string lease_key_, lease_value_;
  std::uint64_t lease_revision_ = 0;
  /// Whether the world's JetStream state was lost since this zone joined or last made it again:
  /// its KV bucket gone, or made again (by another zone) since (its stream's creation time): 1
  /// (stats_.jetstream_state_lost, put_back_pending_; an error logged when first found), 0 intact,
  /// -1 unknown (NATS unreachable). Heartbeat and sender threads.
  [[nodiscard]] int world_state_check();
  std::atomic<std::int64_t> kv_created_{0};  ///< the world's KV bucket's stream: when it was made
  std::atomic<bool> remake_wanted_{false};   ///< the sender found the state lost: heartbeat, check now
  /// Makes the world's JetStream state again (heartbeat thread, lease_mutex_ held): the buckets and
  /// the handoff stream, the layout, this region's incarnation and lease; then asks the fetch
  /// thread for a new consumer and the game thread for what it owns (the sender puts it back).
  /// False when NATS refused a step (tried again at the next renewal) or the region was taken.
  bool remake_world();
  /// The sender's part (sender thread): ownership records of `owned` and of the queued records'
  /// entities put back, the records published in the last 10 s published again.
  bool put_back(const std::vector<std::pair<global_id, std::uint64_t>>& owned);
  /// One ownership record put back (`region` owns it at `epoch`): the highest epoch wins (sender thread).
  bool put_record(global_id g, std::uint32_t region, std::uint64_t epoch);
  [[nodiscard]] int subscribe_handoffs();          ///< this region's durable pull consumer (a natsStatus)
  std::atomic<bool> resubscribe_{false};           ///< fetch thread: make the consumer again
  std::vector<__natsSubscription*> retired_subs_;  ///< consumers made again: destroyed by leave()
  std::atomic<bool> owners_wanted_{false};         ///< game thread: hand owned_epochs() to the sender
  /// Game thread -> sender: what the zone owns (id, epoch), to put back (remake_world).
  std::optional<std::vector<std::pair<global_id, std::uint64_t>>> put_back_job_;  // under out_mutex_
  struct published_record {
    handoff_record record;
    std::chrono::steady_clock::time_point at;
  };
  std::mutex published_mutex_;
  std::deque<published_record> published_;  ///< the last 10 s of published records (send())
  /// The world's JetStream state was found lost and put_back() has not finished: a CAS that finds
  /// no ownership record waits for it instead of taking the entity for someone else's.
  std::atomic<bool> put_back_pending_{false};
  std::mutex lease_mutex_;
  std::atomic<bool> lease_lost_{false}, stopping_{false};
  /// A lease renewal went through since the game thread last saw the connection down (handoffs wait
  /// for it: the world's JetStream state may be gone and made again first).
  std::atomic<bool> world_confirmed_{true};
  std::atomic<bool> sender_stalled_{false};  ///< the sender's last round left its first record unsettled

  // Inboxes filled by NATS threads, drained by the game thread.
  std::mutex inbox_mutex_;
  std::vector<inbound_msg> inbox_;
  std::vector<__natsMsg*> handoff_inbox_;  // JetStream messages: acked after they are applied
  // Handoff records for the sender thread.
  std::mutex out_mutex_;
  std::condition_variable out_cv_;
  std::deque<outgoing> outbox_;  ///< the first stays until it is settled (the census counts it in transit)
  // Region addresses (host, port), refreshed by the heartbeat thread.
  mutable std::mutex addr_mutex_;
  std::vector<std::pair<std::string, std::uint16_t>> addresses_;
  std::atomic<bool> addresses_wanted_{false};  ///< a redirect waits for an address: refresh now

  // Checkpoints (docs/world.md, "Checkpoints"): the game thread copies what it owns, the
  // checkpoint thread encodes and writes it.
  void checkpoint_loop();
  /// The region's last checkpoint, less what KV no longer names this region for (join).
  void read_checkpoint();
  [[nodiscard]] std::string checkpoint_subject(const std::string& part) const;
  std::mutex ckpt_mutex_;
  std::condition_variable ckpt_cv_;
  std::optional<checkpoint_chunk> ckpt_job_;  ///< under ckpt_mutex_: records, tick (generation set by the thread)
  std::vector<handoff_record> ckpt_spare_;    ///< under ckpt_mutex_: the last job's records, emptied, for the next copy
  std::uint64_t ckpt_generation_ = 0;         ///< checkpoint thread
  std::uint64_t next_checkpoint_tick_ = 0;    ///< game thread
  std::atomic<bool> checkpoint_due_{false};
  bool have_checkpoint_ = false;            ///< join found one: no new population
  std::vector<handoff_record> to_restore_;  ///< join -> the first before_step
  bool crashed_ = false;
  std::atomic<bool> served_{false};  ///< started() was called: the zone served its region
  /// clients(): told with the lease as key "p.<region>" = "players slots" (the gate's load).
  std::atomic<std::size_t> players_{0}, slots_{0};

  std::thread heartbeat_, fetcher_, sender_, checkpointer_;
  struct pending_player {
    global_id gid;
    std::uint64_t deadline_tick;
    bool restored = false;   ///< from a checkpoint: a client resuming after its zone was lost
    bool lingering = false;  ///< its client's connection ended here (node_options::linger_s)
  };
  std::unordered_map<std::uint64_t, pending_player> tokens_;                         // token -> player
  /// Each player here with a client: the token its welcome told it (welcome.resume_token). Its
  /// checkpoint record carries it, so the zone that restores the region knows the client again.
  std::unordered_map<entity_id, std::uint64_t> resume_;
  /// Restored players still waiting for their clients, the restore's tick, and how many ticks after
  /// it each one that came back did (logged once none waits any more).
  std::size_t restored_waiting_ = 0;
  std::size_t lingering_ = 0;  ///< players kept for their clients after a lost connection (in tokens_)
  std::uint64_t restored_tick_ = 0;
  std::vector<std::uint64_t> resumed_after_ticks_;
  void restored_player_done();
  /// A new token for a client of region r: (r + 1) << 48 | 48 random bits (never 0), so the
  /// world's gate tells the region from the token alone (token_region).
  [[nodiscard]] std::uint64_t new_token(std::uint32_t r);
  std::unordered_map<global_id, std::pair<vec3, std::uint32_t>> early_inputs_;       // forwarded before the entity came
  std::unordered_map<global_id, std::uint32_t> forward_target_;                     // handed-off player -> its zone
  std::vector<ghost_message> ghost_out_;
  std::vector<std::string> census_replies_;
  struct pending_redirect {
    entity_id local;
    global_id gid;
    std::uint32_t to;
    std::string token;
    std::uint64_t since_tick;
  };
  std::vector<pending_redirect> pending_redirects_;
  std::uint64_t tick_ = 0;
  double tick_rate_hz_ = 30;
  node_stats stats_;
  latency_histogram handoff_ms_, handoff_ticks_;
};

// ---------------------------------------------------------------------------------------------
// Checking a running world from outside (world-check, the tests).

/// One zone's answer to the census.
struct census_entry {
  std::uint32_t region = 0, incarnation = 0;
  std::uint64_t tick = 0;
  std::vector<std::pair<global_id, std::uint64_t>> owned;  ///< (id, epoch)
  std::vector<global_id> transit;                          ///< handed off from here, not confirmed yet
  /// Players handed off to this zone whose client has not come with its token yet (removed after
  /// node_options::unclaimed_player_s): owned here, but no longer any client's.
  std::vector<global_id> awaiting;
};
/// Asks every zone of the world (world.W.census) and collects the answers for `wait_ms`;
/// `pump` (when set) is called while waiting (in-process zones answer from their game thread).
[[nodiscard]] std::optional<std::vector<census_entry>> take_census(const std::string& url, const std::string& world,
                                                                   int wait_ms, std::string* error,
                                                                   const std::function<void()>& pump = {});
/// What a joining zone reads in the census of the running zones: the regions they serve, and per
/// region the highest incarnation among the ids they own, hand off or wait for (0: none).
struct running_zones {
  std::vector<bool> served;
  std::vector<std::uint32_t> incarnation;
};
[[nodiscard]] running_zones read_running(const std::vector<census_entry>& census, std::uint32_t regions);
/// The ownership records in KV: id -> (region, epoch). Every record (listing the bucket's keys), or
/// with `only` just those ids' (read one by one: a listing taken while zones keep handing entities
/// off can miss a key that changed under it).
[[nodiscard]] std::optional<std::map<global_id, std::pair<std::uint32_t, std::uint64_t>>> read_owners(
    const std::string& url, const std::string& world, std::string* error, const std::vector<global_id>* only = nullptr);

/// A region's lease as KV holds it ("host port incarnation"; "claiming" while a zone joins, port 0
/// until its server listens).
struct lease_info {
  std::string host;
  std::uint16_t port = 0;
  std::uint32_t incarnation = 0;  ///< 0: not parsed ("claiming")
  std::string raw;                ///< the value as stored
  std::uint64_t revision = 0;     ///< the lease key's KV revision (its zone renews it every quarter of the TTL)
  /// The zone's load, as its heartbeat last told it (key "p.<region>" beside the lease): players
  /// and player slots; -1 and 0 when it told none.
  std::int64_t players = -1;
  std::int64_t slots = 0;
  std::string load_raw;  ///< that key's value as stored (empty: none)
};
/// A lease's value read: host, port and incarnation, or (anything else: "claiming") only `raw`.
[[nodiscard]] lease_info parse_lease(std::string raw);
/// The world's leases: region -> lease (a region whose lease lapsed, or never claimed, is absent).
[[nodiscard]] std::optional<std::map<std::uint32_t, lease_info>> read_leases(const std::string& url,
                                                                             const std::string& world,
                                                                             std::string* error);
/// The TTL of a world's lease bucket (`world-W-lease`), in seconds: how long a lease lasts after
/// its zone's last renewal (the first zone's choice; zones renew every quarter of it). Nothing
/// when it cannot be read.
[[nodiscard]] std::optional<double> lease_ttl_s(__kvStore* leases);
/// The same from the world's lease bucket (`world-W-lease`) held open by the caller.
[[nodiscard]] std::optional<std::map<std::uint32_t, lease_info>> read_leases(__kvStore* leases, std::string* error);
/// What the census says of the leases. `problems`: a region served by a zone that does not hold
/// it: answered by two zones, or by a zone whose incarnation is not the one its lease names (a zone
/// cut off from NATS whose lease lapsed and was claimed by another: it serves on until its next
/// renewal finds the region taken). `notes`: regions answered without a lease (it lapsed while
/// NATS was unreachable; the zone takes it back at its next renewal), readable.
struct lease_check {
  std::vector<std::string> problems, notes;
};
[[nodiscard]] lease_check check_leases(const std::vector<census_entry>& census,
                                       const std::map<std::uint32_t, lease_info>& leases);

/// What a census and the KV records say together.
struct world_check {
  std::size_t zones = 0, owned = 0;
  std::size_t transit_only = 0;    ///< handed off and owned by no zone yet (on the stream)
  std::size_t awaiting_players = 0;  ///< owned players whose client has not followed its redirect (yet)
  std::size_t owned_twice = 0;     ///< the same (id, epoch) in two zones: a broken guarantee
  std::size_t moving = 0;          ///< the same id in two zones with different epochs (the census caught a handoff)
  std::size_t kv_records = 0;
  std::size_t kv_disagree = 0;     ///< a zone owns (id, epoch) while KV names another zone for it, or an older epoch
  std::size_t kv_missing = 0;      ///< a zone owns an id handed off (epoch > 0) that has no KV record (but
                                   ///< a player awaiting its client: removed with its record any moment)
  std::size_t kv_in_flight = 0;    ///< KV is ahead of every zone (CAS done, the record not applied yet)
  std::vector<std::string> in_flight_examples;  ///< the first few of those, readable
  std::vector<std::string> problem_examples;    ///< the first few kv_missing and kv_disagree, readable
  std::vector<global_id> missing_ids;            ///< every kv_missing id (to read again: read_owners' `only`)
  [[nodiscard]] bool ok() const { return owned_twice == 0 && kv_disagree == 0 && kv_missing == 0; }
};
[[nodiscard]] world_check check_world(const std::vector<census_entry>& census,
                                      const std::map<global_id, std::pair<std::uint32_t, std::uint64_t>>& owners);

}  // namespace zone::world
