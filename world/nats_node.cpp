// nats_node (nats_node.h): a zone's membership in a world over NATS.
#include "nats_node.h"

#include <nats/nats.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <ctime>
#include <sstream>
#include <unordered_set>

namespace zone::world {

namespace {

std::uint64_t monotonic_us() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<std::uint64_t>(ts.tv_sec) * 1000000u + static_cast<std::uint64_t>(ts.tv_nsec) / 1000u;
}

std::string status_text(natsStatus s) {
  const char* last = nats_GetLastError(nullptr);
  return std::string(natsStatus_GetText(s)) + (last && *last ? std::string(" (") + last + ")" : std::string());
}

/// Creates a KV bucket, or binds to it when it exists.
natsStatus open_bucket(kvStore** kv, jsCtx* js, const std::string& name, std::int64_t ttl_ns) {
  kvConfig kc;
  kvConfig_Init(&kc);
  kc.Bucket = name.c_str();
  kc.History = 1;
  kc.TTL = ttl_ns;  // nanoseconds (libnats 3.4 passes it on as the stream's MaxAge)
  kc.StorageType = js_FileStorage;
  natsStatus s = js_CreateKeyValue(kv, js, &kc);
  if (s != NATS_OK) s = js_KeyValue(kv, js, name.c_str());
  return s;
}

/// An ownership record's value: the owner's region and the entity's epoch there.
std::string owner_value(std::uint32_t region, std::uint64_t epoch) {
  return std::to_string(region) + " " + std::to_string(epoch);
}
/// An entity's ownership record's key in the world's KV bucket.
std::string owner_key(global_id g) { return "e." + hex16(g); }
/// The epoch an ownership record's value names (0 when it names none).
std::uint64_t owner_epoch(const std::string& value) {
  const auto space = value.find(' ');
  return space == std::string::npos ? 0 : std::strtoull(value.c_str() + space + 1, nullptr, 10);
}

/// When the world's KV bucket (its stream) was made, in *created: NATS_OK; NATS_NOT_FOUND when
/// there is none; another status when NATS did not tell. One made again since a zone read it means
/// the world's JetStream state was lost meanwhile.
natsStatus kv_stream_created(jsCtx* js, const std::string& world, std::int64_t* created) {
  jsStreamInfo* si = nullptr;
  jsErrCode jerr = static_cast<jsErrCode>(0);
  natsStatus s = js_GetStreamInfo(&si, js, ("KV_world-" + world).c_str(), nullptr, &jerr);
  if (s == NATS_OK && si) *created = si->Created;
  if (si) jsStreamInfo_Destroy(si);
  if (jerr == JSStreamNotFoundErr) s = NATS_NOT_FOUND;
  return s;
}

std::string handoff_stream(const std::string& world) { return "WORLD_" + world; }
std::string checkpoint_stream(const std::string& world) { return "WORLDCK_" + world; }

/// A file-stored stream `name` over `subject`, `tune` setting the rest (idempotent: an existing
/// one is fine).
template <class Tune>
natsStatus add_stream(jsCtx* js, const std::string& name, const std::string& subject, Tune&& tune) {
  jsStreamConfig sc;
  jsStreamConfig_Init(&sc);
  const char* subjects[1] = {subject.c_str()};
  sc.Name = name.c_str();
  sc.Subjects = subjects;
  sc.SubjectsLen = 1;
  sc.Storage = js_FileStorage;
  tune(sc);
  jsErrCode jerr = static_cast<jsErrCode>(0);
  const natsStatus s = js_AddStream(nullptr, js, &sc, nullptr, &jerr);
  return s != NATS_OK && jerr == JSStreamNameExistErr ? NATS_OK : s;
}

/// The world's handoff stream: records kept an hour, with 2 minutes of message-id dedupe.
natsStatus add_handoff_stream(jsCtx* js, const std::string& world) {
  return add_stream(js, handoff_stream(world), "world." + world + ".handoff.>", [](jsStreamConfig& sc) {
    sc.Duplicates = static_cast<std::int64_t>(120) * 1000000000;
    sc.MaxAge = static_cast<std::int64_t>(3600) * 1000000000;
  });
}

/// The world's checkpoint stream: per region its chunks and its head, the last two messages of
/// each subject kept (a checkpoint being written never overwrites the one its head names;
/// docs/world.md, "Checkpoints").
natsStatus add_checkpoint_stream(jsCtx* js, const std::string& world) {
  return add_stream(js, checkpoint_stream(world), "world." + world + ".ck.>",
                    [](jsStreamConfig& sc) { sc.MaxMsgsPerSubject = 2; });
}

}  // namespace

std::string nats_node::checkpoint_subject(const std::string& part) const {
  return "world." + opt_.world + ".ck." + std::to_string(region_) + "." + part;
}

int nats_node::subscribe_handoffs() {
  jsSubOptions so;
  jsSubOptions_Init(&so);
  const std::string name = handoff_stream(opt_.world);
  so.Stream = name.c_str();
  so.Config.AckWait = static_cast<std::int64_t>(5) * 1000000000;
  const std::string durable = "region-" + std::to_string(region_);
  const std::string hsubj = subject("handoff", region_);
  jsErrCode jerr = static_cast<jsErrCode>(0);
  return js_PullSubscribe(&sub_handoff_, js_, hsubj.c_str(), durable.c_str(), nullptr, &so, &jerr);
}

std::string nats_node::subject(const char* what, std::uint32_t region) const {
  return "world." + opt_.world + "." + what + "." + std::to_string(region);
}

std::unique_ptr<nats_node> nats_node::join(const node_options& opt, const zone_config& zone, std::string* error) {
  const auto fail = [&](const std::string& why) -> std::unique_ptr<nats_node> {
    if (error) *error = "world '" + opt.world + "': " + why;
    return nullptr;
  };
  std::unique_ptr<nats_node> n(new nats_node());
  n->opt_ = opt;
  n->tick_rate_hz_ = zone.tick_rate_hz;
  natsOptions* no = nullptr;
  natsOptions_Create(&no);
  natsOptions_SetURL(no, opt.url.c_str());
  const int timeout_ms = std::max(1, static_cast<int>(opt.nats_timeout_s * 1000));
  natsOptions_SetTimeout(no, timeout_ms);
  natsOptions_SetMaxReconnect(no, -1);  // keep trying: a NATS restart must not kill the zone
  natsOptions_SetReconnectWait(no, 200);
  natsStatus s = natsConnection_Connect(&n->nc_, no);
  natsOptions_Destroy(no);
  if (s != NATS_OK) return fail("cannot connect to NATS at " + opt.url + ": " + status_text(s));
  jsOptions jo;
  jsOptions_Init(&jo);
  jo.Wait = timeout_ms;
  if ((s = natsConnection_JetStream(&n->js_, n->nc_, &jo)) != NATS_OK) return fail("JetStream: " + status_text(s));
  if ((s = open_bucket(&n->kv_, n->js_, "world-" + opt.world, 0)) != NATS_OK) {
    return fail("KV bucket world-" + opt.world + ": " + status_text(s) + " (is JetStream on: nats-server -js?)");
  }
  if ((s = open_bucket(&n->lease_, n->js_, "world-" + opt.world + "-lease",
                       static_cast<std::int64_t>(opt.lease_ttl_s * 1e9))) != NATS_OK) {
    return fail("KV lease bucket: " + status_text(s));
  }
  {
    std::int64_t created = 0;
    if (kv_stream_created(n->js_, opt.world, &created) == NATS_OK) n->kv_created_ = created;
  }
  // The lease bucket's TTL is the first zone's (an existing bucket keeps its own): renew by it.
  if (const auto ttl_s = world::lease_ttl_s(n->lease_); ttl_s && std::abs(*ttl_s - opt.lease_ttl_s) > 1e-3) {
    spdlog::warn(
        "world '{}': the world's leases last {} s (its lease bucket's TTL), not the {} s asked: renewing by {} s",
        opt.world, *ttl_s, opt.lease_ttl_s, *ttl_s);
    n->opt_.lease_ttl_s = *ttl_s;
  }
  // The layout: the first zone writes it (create = only if absent); everyone reads what is there.
  const layout proposed(opt.bounds, opt.cols, opt.rows);
  std::uint64_t rev = 0;
  kvStore_CreateString(&rev, n->kv_, "layout", proposed.encode().c_str());
  kvEntry* e = nullptr;
  if ((s = kvStore_Get(&e, n->kv_, "layout")) != NATS_OK) return fail("cannot read the layout: " + status_text(s));
  const auto map = layout::decode(kvEntry_ValueString(e));
  const std::string text = kvEntry_ValueString(e);
  kvEntry_Destroy(e);
  if (!map) return fail("the layout in KV is malformed: '" + text + "'");
  if (!(map->bounds() == zone.world)) return fail("the layout's bounds differ from this zone's --world-size");
  n->map_ = *map;
  // A free region: its lease key created (fails while another zone holds it). The running zones'
  // census first: a region one of them serves is not claimed even where its lease is missing (the
  // world's JetStream state lost and not made again yet), and the claim's incarnation counts on
  // from the highest among the ids alive in the world. While every region is held, wait
  // (claim_wait_s) for a lease to lapse: the leases polled, the census taken again once one has.
  const auto started = std::chrono::steady_clock::now();
  const bool forever = !std::isfinite(opt.claim_wait_s);
  const auto give_up = started + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                     std::chrono::duration<double>(forever ? 0.0 : std::max(0.0, opt.claim_wait_s)));
  const auto lease_missing = [&] {
    for (std::uint32_t r = 0; r < n->map_.count(); ++r) {
      kvEntry* le = nullptr;
      const natsStatus ls = kvStore_Get(&le, n->lease_, ("r." + std::to_string(r)).c_str());
      if (ls == NATS_OK) kvEntry_Destroy(le);
      if (ls == NATS_NOT_FOUND) return true;
    }
    return false;
  };
  running_zones running;
  bool claimed = false, said = false;
  auto next_note = forever ? started + std::chrono::minutes(10) : std::chrono::steady_clock::time_point::max();
  std::uint32_t served_unleased = 0;
  for (;;) {
    running = read_running({}, n->map_.count());
    if (opt.join_census_s > 0) {
      std::string why;
      const auto census = take_census(opt.url, opt.world, static_cast<int>(opt.join_census_s * 1000), &why);
      if (!census) return fail("the census of the running zones: " + why);
      running = read_running(*census, n->map_.count());
    }
    served_unleased = 0;
    for (std::uint32_t r = 0; r < n->map_.count() && !claimed; ++r) {
      const std::string key = "r." + std::to_string(r);
      if (running.served[r]) {
        kvEntry* le = nullptr;
        if (kvStore_Get(&le, n->lease_, key.c_str()) == NATS_OK) {
          kvEntry_Destroy(le);
        } else {
          ++served_unleased;
        }
        continue;
      }
      if (kvStore_CreateString(&rev, n->lease_, key.c_str(), "claiming") == NATS_OK) {
        n->region_ = r;
        n->lease_key_ = key;
        n->lease_revision_ = rev;
        claimed = true;
      }
    }
    if (claimed) break;
    const std::string taken =
        "every region of the layout (" + std::to_string(n->map_.count()) + ") is taken" +
        (served_unleased == 0
             ? std::string()
             : " (" + std::to_string(served_unleased) +
                   " by running zones without a lease: the world's JetStream state is being made again)");
    if (!said && (forever || opt.claim_wait_s > 0)) {
      said = true;
      if (forever) {
        spdlog::info("world '{}': {}: standing by for a region whose lease lapses", opt.world, taken);
      } else {
        spdlog::info("world '{}': {}: waiting up to {} s for a lease to lapse", opt.world, taken, opt.claim_wait_s);
      }
    }
    do {
      const auto now = std::chrono::steady_clock::now();
      if ((!forever && now >= give_up) || (opt.keep_waiting && !opt.keep_waiting())) return fail(taken);
      if (now >= next_note) {  // a standby says now and then that it still stands by
        spdlog::info("world '{}': still standing by ({:.0f} s)", opt.world,
                     std::chrono::duration<double>(now - started).count());
        next_note = now + std::chrono::minutes(10);
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(250));
    } while (!lease_missing());
  }
  if (said) {
    spdlog::info("world '{}': region {} free after {:.1f} s of waiting", opt.world, n->region_,
                 std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count());
  }
  const std::uint32_t alive = running.incarnation[n->region_];
  // This claim's incarnation: inc.r counted up by CAS (ids of a restarted zone differ).
  const std::string inc_key = "inc." + std::to_string(n->region_);
  for (int attempt = 0; attempt < 50 && n->incarnation_ == 0; ++attempt) {
    kvEntry* ie = nullptr;
    if (kvStore_Get(&ie, n->kv_, inc_key.c_str()) == NATS_OK) {
      const std::uint64_t have = std::max<std::uint64_t>(std::strtoull(kvEntry_ValueString(ie), nullptr, 10), alive);
      const std::uint64_t last = kvEntry_Revision(ie);
      kvEntry_Destroy(ie);
      if (kvStore_UpdateString(&rev, n->kv_, inc_key.c_str(), std::to_string(have + 1).c_str(), last) == NATS_OK) {
        n->incarnation_ = static_cast<std::uint32_t>(have + 1);
      }
    } else if (kvStore_CreateString(&rev, n->kv_, inc_key.c_str(), std::to_string(alive + 1).c_str()) == NATS_OK) {
      n->incarnation_ = alive + 1;
    }
  }
  if (n->incarnation_ == 0 || n->incarnation_ > 0xffff) return fail("cannot count the region's incarnation");
  // The handoff stream (idempotent: an existing one is fine) and this region's durable consumer.
  if ((s = add_handoff_stream(n->js_, opt.world)) != NATS_OK) return fail("handoff stream: " + status_text(s));
  if ((s = static_cast<natsStatus>(n->subscribe_handoffs())) != NATS_OK)
    return fail("handoff consumer: " + status_text(s));
  if ((s = add_checkpoint_stream(n->js_, opt.world)) != NATS_OK) return fail("checkpoint stream: " + status_text(s));
  n->link_ = std::make_unique<zone_link>([&] {
    link_options lo;
    lo.map = n->map_;
    lo.region = n->region_;
    lo.incarnation = n->incarnation_;
    lo.handoff_margin = opt.handoff_margin;
    lo.ghost_band = opt.ghost_band > 0 ? opt.ghost_band : ghost_band(zone, opt.handoff_margin);
    lo.ghost_timeout_ticks = opt.ghost_timeout_ticks;
    lo.capacity = opt.capacity;
    lo.hold_for_room = opt.hold_for_room;
    return lo;
  }());
  n->read_checkpoint();
  // Core subscriptions: their callbacks only queue (the game thread applies).
  using kind = inbound_msg::kind;
  for (const kind k : {kind::ghosts, kind::snapshot_request, kind::input, kind::census}) {
    n->sub_ctx_[static_cast<std::size_t>(k)] = {n.get(), k};
  }
  const auto sub = [&](natsSubscription** out, const std::string& subj, kind k) {
    if (natsConnection_Subscribe(out, n->nc_, subj.c_str(), &nats_node::on_message, &n->sub_ctx_[static_cast<std::size_t>(k)]) !=
        NATS_OK) {
      return false;
    }
    natsSubscription_SetPendingLimits(*out, 100000, 256 * 1024 * 1024);
    return true;
  };
  if (!sub(&n->sub_ghosts_, n->subject("ghost", n->region_), kind::ghosts) ||
      !sub(&n->sub_snap_, n->subject("snap", n->region_), kind::snapshot_request) ||
      !sub(&n->sub_input_, n->subject("input", n->region_), kind::input) ||
      !sub(&n->sub_census_, "world." + opt.world + ".census", kind::census)) {
    return fail("cannot subscribe");
  }
  natsConnection_Flush(n->nc_);
  n->addresses_.assign(n->map_.count(), {std::string(), 0});
  n->lease_value_ = opt.advertise_host + " 0 " + std::to_string(n->incarnation_);
  n->heartbeat_ = std::thread([p = n.get()] { p->heartbeat_loop(); });
  n->fetcher_ = std::thread([p = n.get()] { p->fetch_loop(); });
  n->sender_ = std::thread([p = n.get()] { p->send_loop(); });
  if (opt.checkpoint_s > 0) n->checkpointer_ = std::thread([p = n.get()] { p->checkpoint_loop(); });
  spdlog::info("world '{}': region {} of {} ({}x{}), incarnation {}, neighbours {}, ghost band {:.0f} m", opt.world,
               n->region_, n->map_.count(), n->map_.cols(), n->map_.rows(), n->incarnation_,
               n->map_.neighbours(n->region_).size(), n->link_->options().ghost_band);
  return n;
}

zone_config nats_node::zone_for_region(zone_config c) const {
  const rect r = map_.region(region_);
  c.spawn_area = {{r.lo_x, r.lo_y, c.world.lo.z}, {r.hi_x, r.hi_y, c.world.hi.z}};
  c.seed = c.seed * 1000003u + region_ * 7919u + incarnation_;
  if (have_checkpoint_) c.populate = false;  // its entities come back from the checkpoint instead
  return c;
}

void nats_node::leave() {
  if (stopping_.exchange(true)) return;
  out_cv_.notify_all();
  ckpt_cv_.notify_all();
  if (checkpointer_.joinable()) checkpointer_.join();
  if (sender_.joinable()) sender_.join();
  if (fetcher_.joinable()) fetcher_.join();
  if (heartbeat_.joinable()) heartbeat_.join();
  for (auto* s : {&sub_ghosts_, &sub_snap_, &sub_input_, &sub_census_}) {
    if (*s) {
      natsSubscription_Unsubscribe(*s);
      natsSubscription_Destroy(*s);
      *s = nullptr;
    }
  }
  // The region's durable consumer stays (destroyed, not unsubscribed: an unsubscribe deletes the
  // consumer the library made): the region's next zone goes on from its acks, so it gets the
  // records this zone left unapplied, and never again one it applied (a stale record adopted
  // again would own an entity handed on since twice).
  if (sub_handoff_) natsSubscription_Destroy(sub_handoff_), sub_handoff_ = nullptr;
  for (auto* s : retired_subs_) natsSubscription_Destroy(s);
  retired_subs_.clear();
  {
    std::lock_guard lock(inbox_mutex_);
    // Unapplied handoffs are not acked: JetStream gives them to the region's next zone.
    for (auto* m : handoff_inbox_) natsMsg_Destroy(m);
    handoff_inbox_.clear();
  }
  if (lease_ && !lease_lost_.load() && !crashed_) {
    // A zone that stops gives its region up and its entities with it: its checkpoint goes too
    // (the region's next zone starts a new population; a killed zone's is restored instead). One
    // that never served (its server did not start) keeps the checkpoint it may have restored from
    // (a killed zone's): the region's next zone restores it.
    if (served_.load()) {
      jsOptions po;
      jsOptions_Init(&po);
      const std::string all = checkpoint_subject(">");
      po.Stream.Purge.Subject = all.c_str();
      jsErrCode jerr = static_cast<jsErrCode>(0);
      js_PurgeStream(js_, checkpoint_stream(opt_.world).c_str(), &po, &jerr);
    } else if (have_checkpoint_) {
      spdlog::warn("world '{}': region {} given up before it was served: its checkpoint is kept for the next zone",
                   opt_.world, region_);
    }
    kvStore_Delete(lease_, lease_key_.c_str());
  }
  if (kv_) kvStore_Destroy(kv_);
  if (lease_) kvStore_Destroy(lease_);
  if (js_) jsCtx_Destroy(js_);
  if (nc_) {
    natsConnection_FlushTimeout(nc_, 500);
    natsConnection_Destroy(nc_);
  }
  kv_ = lease_ = nullptr;
  js_ = nullptr;
  nc_ = nullptr;
}

nats_node::~nats_node() { leave(); }

void nats_node::on_message(natsConnection*, natsSubscription*, natsMsg* msg, void* closure) {
  const auto* ctx = static_cast<const sub_context*>(closure);
  nats_node* n = ctx->node;
  inbound_msg m{};
  m.what = ctx->what;
  if (m.what == inbound_msg::kind::census) {
    if (const char* r = natsMsg_GetReply(msg)) m.reply = r;
  }
  const auto* d = reinterpret_cast<const std::uint8_t*>(natsMsg_GetData(msg));
  m.data.assign(d, d + natsMsg_GetDataLength(msg));
  natsMsg_Destroy(msg);
  std::lock_guard lock(n->inbox_mutex_);
  if (n->inbox_.size() > 100000) {  // a stalled game thread must not grow memory without bound
    ++n->stats_.ghost_inbox_dropped;
    return;
  }
  n->inbox_.push_back(std::move(m));
}

void nats_node::started(std::uint16_t port) {
  served_ = true;
  std::lock_guard lock(lease_mutex_);
  lease_value_ = opt_.advertise_host + " " + std::to_string(port) + " " + std::to_string(incarnation_);
  std::uint64_t rev = 0;
  if (kvStore_UpdateString(&rev, lease_, lease_key_.c_str(), lease_value_.c_str(), lease_revision_) == NATS_OK) {
    lease_revision_ = rev;
  } else {
    lease_lost_ = true;
  }
  refresh_addresses();
}

void nats_node::refresh_addresses() {
  std::vector<std::pair<std::string, std::uint16_t>> table;
  {
    std::lock_guard lock(addr_mutex_);
    table = addresses_;
  }
  for (std::uint32_t r = 0; r < map_.count(); ++r) {
    kvEntry* e = nullptr;
    const natsStatus s = kvStore_Get(&e, lease_, ("r." + std::to_string(r)).c_str());
    if (s == NATS_NOT_FOUND) table[r] = {std::string(), 0};  // nobody holds the region now
    if (s != NATS_OK) continue;  // unreadable (NATS unreachable): the address known before stays
    const lease_info l = parse_lease(kvEntry_ValueString(e));
    table[r] = {l.host, l.port};
    kvEntry_Destroy(e);
  }
  std::lock_guard lock(addr_mutex_);
  addresses_ = std::move(table);
}

void nats_node::heartbeat_loop() {
  const auto period = std::chrono::duration<double>(std::max(0.05, opt_.lease_ttl_s / 4));
  auto next = std::chrono::steady_clock::now();
  while (!stopping_.load()) {
    next += std::chrono::duration_cast<std::chrono::steady_clock::duration>(period);
    while (!stopping_.load() && std::chrono::steady_clock::now() < next) {
      // A redirect waits for an address the table lacks (the game thread never waits on NATS).
      if (addresses_wanted_.exchange(false)) refresh_addresses();
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    if (stopping_.load()) break;
    {
      std::lock_guard lock(lease_mutex_);
      std::uint64_t rev = 0;
      const natsStatus s = kvStore_UpdateString(&rev, lease_, lease_key_.c_str(), lease_value_.c_str(), lease_revision_);
      if (s == NATS_OK) {
        lease_revision_ = rev;
        world_confirmed_ = true;
        if (served_.load()) {
          // The load a gate balances logins by, beside the lease (its TTL: gone with the zone).
          const std::string load = std::to_string(players_.load()) + " " + std::to_string(slots_.load());
          std::uint64_t lrev = 0;
          kvStore_PutString(&lrev, lease_, ("p." + std::to_string(region_)).c_str(), load.c_str());
        }
      } else if (s == NATS_ERR || s == NATS_NOT_FOUND) {
        // The update was refused (wrong last revision): the key read back tells why. Timeouts
        // and a lost connection are transient: the next renewal tries again.
        kvEntry* e = nullptr;
        const natsStatus g = kvStore_Get(&e, lease_, lease_key_.c_str());  // NATS_NOT_FOUND: none, or deleted
        const std::string have = g == NATS_OK ? kvEntry_ValueString(e) : "";
        const std::uint64_t have_revision = g == NATS_OK ? kvEntry_Revision(e) : 0;
        if (e) kvEntry_Destroy(e);
        natsStatus c = NATS_OK;
        switch (judge_lease_readback(lease_value_, g == NATS_OK || g == NATS_NOT_FOUND, g == NATS_OK, have)) {
          case lease_readback::ours: lease_revision_ = have_revision; break;
          case lease_readback::lapsed:
            c = kvStore_CreateString(&rev, lease_, lease_key_.c_str(), lease_value_.c_str());
            if (c == NATS_OK) {
              lease_revision_ = rev;
              ++stats_.lease_reclaims;
              spdlog::warn(
                  "world '{}': the lease of region {} had lapsed ({}); nobody had claimed the region: taken back",
                  opt_.world, region_, status_text(s));
              break;
            }
            if (c != NATS_ERR) break;  // transient
            [[fallthrough]];           // someone claimed it first
          case lease_readback::taken:
            spdlog::error("world '{}': lost the lease of region {} ({}): another zone holds it", opt_.world, region_,
                          status_text(s));
            lease_lost_ = true;
            return;
          case lease_readback::unknown: break;
        }
      }
      if ((s != NATS_OK || remake_wanted_.exchange(false)) && world_state_check() == 1) remake_world();
    }
    refresh_addresses();
  }
}

int nats_node::world_state_check() {
  if (natsConnection_Status(nc_) != NATS_CONN_STATUS_CONNECTED) return -1;
  std::int64_t created = 0;
  const natsStatus s = kv_stream_created(js_, opt_.world, &created);
  const bool missing = s == NATS_NOT_FOUND;
  if (!missing && s != NATS_OK) return -1;
  if (!missing && created == kv_created_.load()) return 0;
  put_back_pending_ = true;
  if (!stats_.jetstream_state_lost.exchange(true)) {
    spdlog::error(
        "world '{}': the world's JetStream state was lost ({}: a nats-server restarted without its store?): making it "
        "again (docs/world.md, \"Faults\")",
        opt_.world, missing ? "its KV bucket is gone" : "its KV bucket was made again since this zone joined");
  }
  return 1;
}

bool nats_node::remake_world() {
  const auto refused = [&](const char* what, natsStatus s) {
    spdlog::warn("world '{}': making the world's JetStream state again: {}: {} (tried again at the next renewal)",
                 opt_.world, what, status_text(s));
    return false;
  };
  kvStore* made = nullptr;
  natsStatus s = open_bucket(&made, js_, "world-" + opt_.world, 0);
  if (made) kvStore_Destroy(made), made = nullptr;
  if (s != NATS_OK) return refused("the KV bucket", s);
  s = open_bucket(&made, js_, "world-" + opt_.world + "-lease", static_cast<std::int64_t>(opt_.lease_ttl_s * 1e9));
  if (made) kvStore_Destroy(made), made = nullptr;
  if (s != NATS_OK) return refused("the lease bucket", s);
  if ((s = add_handoff_stream(js_, opt_.world)) != NATS_OK) return refused("the handoff stream", s);
  if ((s = add_checkpoint_stream(js_, opt_.world)) != NATS_OK) return refused("the checkpoint stream", s);
  std::uint64_t rev = 0;
  kvStore_CreateString(&rev, kv_, "layout", map_.encode().c_str());  // the first zone back writes it
  // This region's incarnation, so that a later zone here counts on from it (ids never reused).
  const std::string inc_key = "inc." + std::to_string(region_);
  for (int attempt = 0; attempt < 5; ++attempt) {
    kvEntry* ie = nullptr;
    s = kvStore_Get(&ie, kv_, inc_key.c_str());
    if (s == NATS_NOT_FOUND) {
      if (kvStore_CreateString(&rev, kv_, inc_key.c_str(), std::to_string(incarnation_).c_str()) == NATS_OK) break;
      continue;
    }
    if (s != NATS_OK) return refused("the incarnation", s);
    const std::uint64_t have = std::strtoull(kvEntry_ValueString(ie), nullptr, 10), last = kvEntry_Revision(ie);
    kvEntry_Destroy(ie);
    if (have >= incarnation_) break;
    if (kvStore_UpdateString(&rev, kv_, inc_key.c_str(), std::to_string(incarnation_).c_str(), last) == NATS_OK) break;
  }
  // The lease: ours again, unless a zone claimed the region meanwhile (it joined a world it found
  // empty): then that zone serves it and this one stops.
  s = kvStore_CreateString(&rev, lease_, lease_key_.c_str(), lease_value_.c_str());
  if (s == NATS_OK) {
    lease_revision_ = rev;
  } else {
    kvEntry* e = nullptr;
    const natsStatus g = kvStore_Get(&e, lease_, lease_key_.c_str());
    const std::string have = g == NATS_OK ? kvEntry_ValueString(e) : "";
    const std::uint64_t have_revision = g == NATS_OK ? kvEntry_Revision(e) : 0;
    if (e) kvEntry_Destroy(e);
    switch (judge_lease_readback(lease_value_, g == NATS_OK || g == NATS_NOT_FOUND, g == NATS_OK, have)) {
      case lease_readback::ours: lease_revision_ = have_revision; break;
      case lease_readback::taken:
        spdlog::error(
            "world '{}': making the world's JetStream state again: region {} was claimed by another zone: stopping",
            opt_.world, region_);
        lease_lost_ = true;
        return false;
      case lease_readback::lapsed:  // the create failed, yet no key: tried again
      case lease_readback::unknown: return refused("the lease", s);
    }
  }
  {
    std::int64_t created = 0;
    if ((s = kv_stream_created(js_, opt_.world, &created)) != NATS_OK) return refused("the KV bucket's stream", s);
    kv_created_ = created;
  }
  resubscribe_ = true;
  owners_wanted_ = true;
  ++stats_.world_remade;
  stats_.jetstream_state_lost = false;
  spdlog::warn(
      "world '{}': the world's JetStream state made again (region {}, incarnation {}); the ownership records "
      "of what this zone owns and sends follow",
      opt_.world, region_, incarnation_);
  return true;
}

void nats_node::checkpoint_loop() {
  bool failing = false;
  while (!stopping_.load()) {
    checkpoint_chunk job;
    {
      std::unique_lock lock(ckpt_mutex_);
      ckpt_cv_.wait(lock, [&] { return stopping_.load() || ckpt_job_.has_value(); });
      if (stopping_.load()) return;
      job = std::move(*ckpt_job_);
      ckpt_job_.reset();
    }
    // The chunks first (each under the head's size limit), then the head that names them: a
    // reader follows the last head, never a checkpoint half written.
    checkpoint_head head;
    head.region = job.region;
    head.incarnation = job.incarnation;
    head.generation = job.generation = ++ckpt_generation_;
    head.tick = job.tick;
    head.entities = job.records.size();
    std::uint64_t bytes = 0;
    natsStatus s = NATS_OK;
    std::size_t at = 0;
    do {
      checkpoint_chunk part;
      part.region = job.region, part.incarnation = job.incarnation, part.generation = job.generation,
      part.tick = job.tick;
      std::size_t size = 40;
      while (at < job.records.size() && (part.records.empty() || size + 200 <= opt_.checkpoint_chunk_bytes)) {
        size += 4 + 166 + job.records[at].visible.size() * 8;
        part.records.push_back(std::move(job.records[at++]));
      }
      const auto data = encode(part);
      jsPubAck* ack = nullptr;
      jsErrCode jerr = static_cast<jsErrCode>(0);
      std::string part_name = std::to_string(head.chunks.size());
      part_name.insert(part_name.begin(), 'c');  // not "c" + ...: GCC 12 warns of a false overlap there (-Wrestrict)
      const std::string subj = checkpoint_subject(part_name);
      s = js_Publish(&ack, js_, subj.c_str(), data.data(), static_cast<int>(data.size()), nullptr, &jerr);
      if (s == NATS_OK && ack) head.chunks.push_back(ack->Sequence);
      if (ack) jsPubAck_Destroy(ack);
      bytes += data.size();
    } while (s == NATS_OK && at < job.records.size() && head.chunks.size() < max_checkpoint_chunks);
    if (s == NATS_OK && at < job.records.size()) s = NATS_INSUFFICIENT_BUFFER;  // more chunks than a head names
    {
      std::lock_guard lock(ckpt_mutex_);  // the records' vector back for the next copy
      job.records.clear();
      if (ckpt_spare_.capacity() < job.records.capacity()) ckpt_spare_.swap(job.records);
    }
    if (s == NATS_OK) {
      const auto data = encode(head);
      jsErrCode jerr = static_cast<jsErrCode>(0);
      s = js_Publish(nullptr, js_, checkpoint_subject("head").c_str(), data.data(), static_cast<int>(data.size()),
                     nullptr, &jerr);
      bytes += data.size();
    }
    if (s != NATS_OK) {
      ++stats_.checkpoint_failures;
      if (!failing)
        spdlog::warn("world '{}': a checkpoint was not written ({}): the next one is tried on time", opt_.world,
                     status_text(s));
      failing = true;
      continue;
    }
    if (failing) spdlog::info("world '{}': checkpoints written again", opt_.world);
    failing = false;
    ++stats_.checkpoints_written;
    stats_.checkpoint_entities = head.entities;
    stats_.checkpoint_bytes = bytes;
  }
}

void nats_node::read_checkpoint() {
  const std::string stream = checkpoint_stream(opt_.world);
  const auto get = [&](natsMsg** m, std::uint64_t seq, const std::string& subject) {
    jsErrCode jerr = static_cast<jsErrCode>(0);
    natsStatus s = NATS_OK;
    for (int attempt = 0; attempt < 3; ++attempt) {
      s = seq ? js_GetMsg(m, js_, stream.c_str(), seq, nullptr, &jerr)
              : js_GetLastMsg(m, js_, stream.c_str(), subject.c_str(), nullptr, &jerr);
      if (s == NATS_OK || jerr == JSNoMessageFoundErr || jerr == JSStreamNotFoundErr) break;
    }
    return s;
  };
  natsMsg* m = nullptr;
  if (get(&m, 0, checkpoint_subject("head")) != NATS_OK) return;  // none: a new population
  const auto bytes = [](natsMsg* msg) {
    return std::span<const std::uint8_t>(reinterpret_cast<const std::uint8_t*>(natsMsg_GetData(msg)),
                                         static_cast<std::size_t>(natsMsg_GetDataLength(msg)));
  };
  const auto head = decode_checkpoint_head(bytes(m));
  const std::int64_t head_time_ns = natsMsg_GetTime(m);  // when the stream stored it: after the copy
  natsMsg_Destroy(m);
  if (!head || head->region != region_) {
    spdlog::warn("world '{}': region {}'s checkpoint head is malformed: ignored (a new population)", opt_.world,
                 region_);
    return;
  }
  std::vector<handoff_record> records;
  records.reserve(head->entities);
  for (std::size_t k = 0; k < head->chunks.size(); ++k) {
    m = nullptr;
    const natsStatus s = get(&m, head->chunks[k], {});
    auto chunk = s == NATS_OK ? decode_checkpoint_chunk(bytes(m)) : std::nullopt;
    if (m) natsMsg_Destroy(m);
    if (!chunk || chunk->generation != head->generation || chunk->region != region_) {
      spdlog::error(
          "world '{}': region {}'s checkpoint (tick {}) cannot be read whole (part {} of {}: {}): a new "
          "population instead",
          opt_.world, region_, head->tick, k + 1, head->chunks.size(), s == NATS_OK ? "malformed" : status_text(s));
      return;
    }
    for (auto& r : chunk->records) records.push_back(std::move(r));
  }
  // Whether KV names this region for `r` at its epoch (no record: only for epoch 0, never handed
  // off: a record is made at the first handoff); then r.owner_revision is the record's.
  const auto ours = [&](handoff_record& r) {
    kvEntry* e = nullptr;
    natsStatus s = NATS_OK;
    for (int attempt = 0; attempt < 3; ++attempt) {
      if ((s = kvStore_Get(&e, kv_, owner_key(r.gid).c_str())) == NATS_OK || s == NATS_NOT_FOUND) break;
    }
    const bool yes =
        s == NATS_NOT_FOUND ? r.epoch == 0 : s == NATS_OK && kvEntry_ValueString(e) == owner_value(region_, r.epoch);
    r.owner_revision = s == NATS_OK ? kvEntry_Revision(e) : 0;
    if (e) kvEntry_Destroy(e);
    return yes;
  };
  // Only what KV still names this region for, at the epoch the checkpoint holds: an entity
  // handed off since belongs to its new zone (or is on its way there).
  std::uint64_t skipped = 0;
  for (auto& r : records) {
    if (!ours(r)) {
      ++skipped;
      r.gid = 0;
    }
  }
  std::erase_if(records, [](const handoff_record& r) { return r.gid == 0; });
  // What the zone adopted after the copy is not in it: the handoff stream keeps every record an
  // hour (acked or not), so the records to this region since 10 s before the checkpoint are read
  // again, and an entity none of the checkpoint's comes back from its latest one where KV still
  // names this region at that epoch (it was adopted here, or is on its way: either way ours).
  std::unordered_map<global_id, handoff_record> since;
  {
    std::unordered_set<global_id> have;
    for (const auto& r : records) have.insert(r.gid);
    jsSubOptions so;
    jsSubOptions_Init(&so);
    const std::string stream_name = handoff_stream(opt_.world);
    so.Stream = stream_name.c_str();
    so.Ordered = true;
    so.Config.DeliverPolicy = js_DeliverByStartTime;
    so.Config.OptStartTime = head_time_ns - static_cast<std::int64_t>(10) * 1000000000;
    natsSubscription* sub = nullptr;
    jsErrCode jerr = static_cast<jsErrCode>(0);
    natsStatus s = js_SubscribeSync(&sub, js_, subject("handoff", region_).c_str(), nullptr, &so, &jerr);
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(5);
    while (s == NATS_OK && std::chrono::steady_clock::now() < deadline) {
      natsMsg* hm = nullptr;
      if (natsSubscription_NextMsg(&hm, sub, 500) != NATS_OK) break;  // none left (or none at all)
      std::uint64_t pending = 0;
      jsMsgMetaData* meta = nullptr;
      if (natsMsg_GetMetaData(&meta, hm) == NATS_OK) pending = meta->NumPending, jsMsgMetaData_Destroy(meta);
      // A player's record comes with its redirect token, which its client kept as its resume
      // token (the zone it was adopted by told it so): restored, it waits for that client.
      if (auto r = decode_handoff(bytes(hm)); r && r->to == region_ &&
                                              (r->behaviour.kind != behaviour::player || r->token != 0) &&
                                              !have.contains(r->gid)) {
        auto [it, fresh] = since.emplace(r->gid, *r);
        if (!fresh && it->second.epoch < r->epoch) it->second = std::move(*r);
      }
      natsMsg_Destroy(hm);
      if (pending == 0) break;
    }
    if (sub) natsSubscription_Unsubscribe(sub), natsSubscription_Destroy(sub);  // an ephemeral consumer
  }
  std::uint64_t from_records = 0;
  for (auto& [g, r] : since) {
    if (r.epoch > 0 && ours(r)) {  // a handoff's record has an epoch of 1 or more, and KV its record
      r.from = region_;
      if (r.behaviour.kind != behaviour::player) r.token = 0;
      r.visible.clear();
      records.push_back(std::move(r));
      ++from_records;
    }
  }
  // A player stands still until its client is back (its last input was given seconds ago).
  for (auto& r : records) {
    if (r.behaviour.kind == behaviour::player) r.behaviour.intent = {};
  }
  have_checkpoint_ = true;
  stats_.restore_skipped = skipped;
  stats_.restored_from_records = from_records;
  spdlog::info(
      "world '{}': region {}'s checkpoint of tick {} (incarnation {}): {} entities to restore ({} of them from "
      "handoff records since: adopted after it, or on their way here), {} left out (handed off since)",
      opt_.world, region_, head->tick, head->incarnation, records.size(), from_records, skipped);
  to_restore_ = std::move(records);
}

bool nats_node::put_record(global_id g, std::uint32_t region, std::uint64_t epoch) {
  // The highest epoch wins (epochs only grow along an entity's handoffs, so it is its owner's):
  // created when missing, replaced when it names an older epoch (another zone put back what it
  // had published before the entity moved on), left when it names this epoch or a newer one.
  const std::string key = owner_key(g);
  const std::string value = owner_value(region, epoch);
  for (int attempt = 0; attempt < 5; ++attempt) {
    std::uint64_t rev = 0;
    kvEntry* e = nullptr;
    const natsStatus got = kvStore_Get(&e, kv_, key.c_str());
    if (got == NATS_NOT_FOUND) {
      const natsStatus c = kvStore_CreateString(&rev, kv_, key.c_str(), value.c_str());
      if (c == NATS_OK) {
        ++stats_.owners_reput;
        return true;
      }
      if (c != NATS_ERR) return false;  // NATS_ERR: created meanwhile: read it again
      continue;
    }
    if (got != NATS_OK) return false;
    const std::uint64_t have_epoch = owner_epoch(kvEntry_ValueString(e));
    const std::uint64_t have_revision = kvEntry_Revision(e);
    kvEntry_Destroy(e);
    if (have_epoch >= epoch) return true;
    if (kvStore_UpdateString(&rev, kv_, key.c_str(), value.c_str(), have_revision) == NATS_OK) {
      ++stats_.owners_reput;
      return true;
    }
  }
  return false;
}

bool nats_node::put_back(const std::vector<std::pair<global_id, std::uint64_t>>& owned) {
  // Ownership records: what the game thread owns, and what the queued records hand on (ours at
  // epoch - 1 until their CAS; the new owner's once it was done), and the last 10 s of published
  // records' (the new owner's: it may not have fetched them from the lost stream).
  struct owner_record {
    global_id gid;
    std::uint32_t region;
    std::uint64_t epoch;
  };
  std::vector<owner_record> records;
  for (const auto& [g, epoch] : owned) records.push_back({g, region_, epoch});
  {
    std::lock_guard lock(out_mutex_);
    for (const outgoing& o : outbox_) {
      if (o.record.epoch == 0) continue;
      records.push_back(o.cas_done ? owner_record{o.record.gid, o.record.to, o.record.epoch}
                                   : owner_record{o.record.gid, region_, o.record.epoch - 1});
    }
  }
  std::vector<handoff_record> published;
  {
    std::lock_guard lock(published_mutex_);
    for (const auto& p : published_) published.push_back(p.record);
  }
  for (const auto& r : published) records.push_back({r.gid, r.to, r.epoch});
  for (const auto& r : records) {
    if (!put_record(r.gid, r.region, r.epoch)) {
      spdlog::warn("world '{}': the ownership record of {:x} not put back: tried again", opt_.world, r.gid);
      return false;
    }
  }
  // The records published in the last 10 s again: the lost stream may have held them unfetched
  // (their new zone adopts an epoch once: one it had is a duplicate there).
  for (const auto& r : published) {
    const auto bytes = encode(r);
    const std::string msg_id = hex16(r.gid) + "-" + std::to_string(r.epoch);
    jsPubOptions po;
    jsPubOptions_Init(&po);
    po.MsgId = msg_id.c_str();
    const natsStatus s = js_Publish(nullptr, js_, subject("handoff", r.to).c_str(), bytes.data(),
                                    static_cast<int>(bytes.size()), &po, nullptr);
    if (s != NATS_OK) {
      spdlog::warn("world '{}': handoff of {:x} not published again ({}): tried again", opt_.world, r.gid,
                   status_text(s));
      return false;
    }
    ++stats_.records_republished;
  }
  return true;
}

void nats_node::fetch_loop() {
  while (!stopping_.load()) {
    if (resubscribe_.exchange(false)) {  // the world's JetStream state was made again: a new consumer
      // The old one is kept until leave(): messages fetched from it may still wait for their ack.
      if (sub_handoff_) retired_subs_.push_back(sub_handoff_), sub_handoff_ = nullptr;
      if (const auto s = static_cast<natsStatus>(subscribe_handoffs()); s != NATS_OK) {
        spdlog::warn("world '{}': the handoff consumer not made again ({}): tried again", opt_.world, status_text(s));
        resubscribe_ = true;
        std::this_thread::sleep_for(std::chrono::milliseconds(250));
        continue;
      }
    }
    if (!sub_handoff_) {
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
      continue;
    }
    natsMsgList list{};
    const natsStatus s = natsSubscription_Fetch(&list, sub_handoff_, 256, 100, nullptr);
    if (s != NATS_OK) {
      if (s != NATS_TIMEOUT) std::this_thread::sleep_for(std::chrono::milliseconds(50));
      continue;
    }
    std::lock_guard lock(inbox_mutex_);
    for (int i = 0; i < list.Count; ++i) {
      handoff_inbox_.push_back(list.Msgs[i]);
      list.Msgs[i] = nullptr;  // ours now (acked and destroyed by the game thread)
    }
    natsMsgList_Destroy(&list);
  }
}

void nats_node::send_loop() {
  // One record at a time, in order; the first stays queued until it is settled. While NATS is
  // unreachable the sender pauses (250 ms, doubling to 4 s) and tries the same record again: the
  // records wait, none is dropped. Stopping with NATS unreachable abandons what is left (lost with
  // the zone, like a kill's).
  constexpr std::chrono::milliseconds first_pause(250), longest_pause(4000);
  std::chrono::milliseconds pause = first_pause;
  while (true) {
    outgoing o;
    std::optional<std::vector<std::pair<global_id, std::uint64_t>>> owned;
    {
      std::unique_lock lock(out_mutex_);
      out_cv_.wait(lock, [&] { return stopping_.load() || !outbox_.empty() || put_back_job_.has_value(); });
      if (put_back_job_ && !stopping_.load()) {
        owned = std::move(put_back_job_);
        put_back_job_.reset();
      } else if (outbox_.empty()) {
        return;  // stopping, nothing left
      } else {
        o = outbox_.front();  // only this thread takes records off
      }
    }
    if (owned) {
      // The world's JetStream state was made again: its ownership records and the last records
      // first, then the queued records go on (their CAS finds our records put back).
      if (put_back(*owned)) {
        put_back_pending_ = false;
        spdlog::warn("world '{}': put back {} ownership records and published {} records again", opt_.world,
                     stats_.owners_reput.load(), stats_.records_republished.load());
        continue;
      }
      std::unique_lock lock(out_mutex_);
      if (!put_back_job_) put_back_job_ = std::move(owned);
      out_cv_.wait_for(lock, first_pause, [&] { return stopping_.load(); });
      continue;
    }
    const send_outcome outcome = send(o, 0);
    std::unique_lock lock(out_mutex_);
    if (outcome == send_outcome::done) {
      outbox_.pop_front();
      pause = first_pause;
      sender_stalled_ = false;
      continue;
    }
    ++stats_.handoff_retries;
    sender_stalled_ = true;
    outbox_.front() = o;  // a publish still to do remembers its CAS
    if (!stopping_.load()) out_cv_.wait_for(lock, pause, [&] { return stopping_.load() || put_back_job_.has_value(); });
    if (stopping_.load()) {
      stats_.handoffs_abandoned += outbox_.size();
      spdlog::error(
          "world '{}': stopping with NATS unreachable: {} handoff records not sent (their entities are lost "
          "with this zone)",
          opt_.world, outbox_.size());
      outbox_.clear();
      return;
    }
    pause = std::min(pause * 2, longest_pause);
  }
}

lease_readback judge_lease_readback(std::string_view ours, bool readable, bool found, std::string_view value) {
  if (!readable) return lease_readback::unknown;
  if (!found) return lease_readback::lapsed;
  return value == ours ? lease_readback::ours : lease_readback::taken;
}

cas_readback judge_cas_readback(std::string_view wanted, std::uint64_t from_revision, std::string_view ours, bool found,
                                std::string_view value, std::uint64_t revision) {
  if (found && value == wanted) return cas_readback::publish;
  if (from_revision == 0 ? !found : (found && revision == from_revision)) return cas_readback::retry;
  if (found && value == ours) return cas_readback::rebase;
  return cas_readback::conflict;
}

nats_node::cas_outcome nats_node::ownership_cas(handoff_record& r, int fail_first) {
  // From (us, epoch - 1) at the revision we know to (them, epoch). A failed CAS may have taken
  // effect (a timeout whose update went through) or changed nothing (a timeout before it): the
  // key read back tells which. KV unreadable: unsettled at once (the sender pauses and comes back).
  const std::string key = owner_key(r.gid);
  const std::string value = owner_value(r.to, r.epoch);
  const std::string ours = owner_value(r.from, r.epoch - 1);
  constexpr int attempts = 5;
  natsStatus last = NATS_OK;
  for (int attempt = 0; attempt < attempts; ++attempt) {
    if (attempt > 0) std::this_thread::sleep_for(std::chrono::milliseconds(20 << (attempt - 1)));
    std::uint64_t rev = 0;
    const natsStatus s = attempt < fail_first       ? NATS_TIMEOUT
                         : r.owner_revision == 0 ? kvStore_CreateString(&rev, kv_, key.c_str(), value.c_str())
                                                 : kvStore_UpdateString(&rev, kv_, key.c_str(), value.c_str(), r.owner_revision);
    if (s == NATS_OK) {
      r.owner_revision = rev;
      return cas_outcome::ours;
    }
    last = s;
    kvEntry* e = nullptr;
    const natsStatus g = kvStore_Get(&e, kv_, key.c_str());  // NATS_NOT_FOUND: no entry, or deleted
    if (g != NATS_OK && g != NATS_NOT_FOUND) {
      if (e) kvEntry_Destroy(e);
      spdlog::warn(
          "world '{}': handoff of {:x} to region {}: the ownership CAS failed ({}) and KV is unreadable ({}): "
          "tried again later",
          opt_.world, r.gid, r.to, status_text(s), status_text(g));
      return cas_outcome::unsettled;
    }
    const char* have = g == NATS_OK ? kvEntry_ValueString(e) : nullptr;
    const std::string have_value = have ? have : "";
    const std::uint64_t have_revision = g == NATS_OK ? kvEntry_Revision(e) : 0;
    if (e) kvEntry_Destroy(e);
    if (g == NATS_NOT_FOUND && r.owner_revision != 0 && (put_back_pending_.load() || world_state_check() == 1)) {
      // The world's JetStream state was lost: its ownership records come back with put_back()
      // (the heartbeat thread makes the state again if no zone did yet).
      remake_wanted_ = true;
      return cas_outcome::unsettled;
    }
    switch (judge_cas_readback(value, r.owner_revision, ours, g == NATS_OK, have_value, have_revision)) {
      case cas_readback::publish:
        ++stats_.handoff_cas_confirmed;
        spdlog::info("world '{}': handoff of {:x} to region {}: the CAS failed ({}) but had taken effect (revision {})",
                     opt_.world, r.gid, r.to, status_text(s), have_revision);
        r.owner_revision = have_revision;
        return cas_outcome::ours;
      case cas_readback::conflict:
        // Not ours per KV: the entity is not handed on; our in-transit copy expires.
        ++stats_.handoff_cas_conflicts;
        spdlog::warn("world '{}': handoff of {:x} to region {} refused by the ownership CAS ({}): KV holds '{}'",
                     opt_.world, r.gid, r.to, status_text(s), have_value);
        return cas_outcome::refused;
      case cas_readback::rebase:
        r.owner_revision = have_revision;  // ours, put back at another revision: from there
        break;
      case cas_readback::retry:
        break;
    }
  }
  spdlog::warn(
      "world '{}': handoff of {:x} to region {}: {} CAS attempts failed ({}) while KV stayed unchanged: tried "
      "again later",
      opt_.world, r.gid, r.to, attempts, status_text(last));
  return cas_outcome::unsettled;
}

nats_node::send_outcome nats_node::send(outgoing& o, int fail_first) {
  handoff_record& r = o.record;
  if (r.epoch == 0) {
    // The entity left the world here (a player logged out): its ownership record goes too.
    const natsStatus s = kvStore_Delete(kv_, owner_key(r.gid).c_str());
    if (s != NATS_OK && s != NATS_NOT_FOUND) {
      spdlog::warn("world '{}': the ownership record of {:x} (left the world) not deleted: {}: tried again later",
                   opt_.world, r.gid, status_text(s));
      return send_outcome::retry;
    }
    spdlog::debug("world '{}': {:x} left the world in region {}: its ownership record deleted", opt_.world, r.gid,
                  region_);
    return send_outcome::done;
  }
  // 1. Ownership by compare-and-set (with the read-back after a failure).
  if (!o.cas_done) {
    switch (ownership_cas(r, fail_first)) {
      case cas_outcome::ours: o.cas_done = true; break;
      case cas_outcome::refused: return send_outcome::done;
      case cas_outcome::unsettled: return send_outcome::retry;
    }
  }
  // 2. The record on the stream, deduplicated by (gid, epoch) if a retry sends it twice (and, past
  // the stream's 2-minute dedupe window, made harmless by the epoch: the new zone applies an
  // epoch once).
  const auto bytes = encode(r);
  const std::string subj = subject("handoff", r.to);
  const std::string msg_id = hex16(r.gid) + "-" + std::to_string(r.epoch);
  jsPubOptions po;
  jsPubOptions_Init(&po);
  po.MsgId = msg_id.c_str();
  const natsStatus s =
      js_Publish(nullptr, js_, subj.c_str(), bytes.data(), static_cast<int>(bytes.size()), &po, nullptr);
  if (s != NATS_OK) {
    spdlog::warn("world '{}': handoff of {:x} to region {} not published ({}): tried again later", opt_.world, r.gid,
                 r.to, status_text(s));
    return send_outcome::retry;
  }
  ++stats_.handoffs_sent;
  {
    // Kept 10 s: published again if the world's JetStream state is lost meanwhile (put_back).
    std::lock_guard lock(published_mutex_);
    const auto now = std::chrono::steady_clock::now();
    published_.push_back({r, now});
    while (!published_.empty() &&
           (published_.size() > 10000 || now - published_.front().at > std::chrono::seconds(10))) {
      published_.pop_front();
    }
  }
  return send_outcome::done;
}

void nats_node::answer_census(const std::string& reply) {
  // region u32, incarnation u32, tick u64, count u32, then (gid u64, epoch u64) per owned entity,
  // then count u32 and gid u64 per entity in transit from here, then count u32 and gid u64 per
  // player handed off here whose client has not come yet.
  const auto ids = link_->owned_epochs();
  auto transit = link_->transit_ids();
  {
    // Records the sender still holds (NATS unreachable): in transit even once their copy here expired.
    std::lock_guard lock(out_mutex_);
    for (const outgoing& o : outbox_) {
      if (o.record.epoch != 0) transit.push_back(o.record.gid);
    }
  }
  std::sort(transit.begin(), transit.end());
  transit.erase(std::unique(transit.begin(), transit.end()), transit.end());
  std::vector<global_id> awaiting;
  for (const auto& [token, p] : tokens_) {
    const entity_id local = link_->local_of(p.gid);
    if (local != null_entity && link_->owns(local)) awaiting.push_back(p.gid);
  }
  std::sort(awaiting.begin(), awaiting.end());
  std::vector<std::uint8_t> out(20 + ids.size() * 16 + 4 + transit.size() * 8 + 4 + awaiting.size() * 8);
  const std::uint32_t head[2] = {region_, incarnation_};
  const auto count = static_cast<std::uint32_t>(ids.size());
  std::memcpy(out.data(), head, 8);
  std::memcpy(out.data() + 8, &tick_, 8);
  std::memcpy(out.data() + 16, &count, 4);
  for (std::size_t k = 0; k < ids.size(); ++k) {
    std::memcpy(out.data() + 20 + 16 * k, &ids[k].first, 8);
    std::memcpy(out.data() + 28 + 16 * k, &ids[k].second, 8);
  }
  const auto tcount = static_cast<std::uint32_t>(transit.size());
  std::uint8_t* t = out.data() + 20 + ids.size() * 16;
  std::memcpy(t, &tcount, 4);
  if (tcount) std::memcpy(t + 4, transit.data(), transit.size() * 8);
  const auto acount = static_cast<std::uint32_t>(awaiting.size());
  std::uint8_t* a = t + 4 + transit.size() * 8;
  std::memcpy(a, &acount, 4);
  if (acount) std::memcpy(a + 4, awaiting.data(), awaiting.size() * 8);
  natsConnection_Publish(nc_, reply.c_str(), out.data(), static_cast<int>(out.size()));
}

void nats_node::before_step(zone_world& w) {
  tick_ = w.tick();
  if (!to_restore_.empty()) {
    // The region's checkpoint (read at the join): its entities back, with their ids and epochs.
    std::uint64_t back = 0, no_room = 0, players = 0;
    const auto wait = static_cast<std::uint64_t>(opt_.resume_s * tick_rate_hz_);
    for (const auto& r : to_restore_) {
      const auto st = link_->restore(w, r);
      back += st == handoff_status::adopted;
      no_room += st == handoff_status::no_room;
      if (st == handoff_status::adopted && r.behaviour.kind == behaviour::player && r.token != 0) {
        tokens_[r.token] = {r.gid, tick_ + wait, true};  // its client comes back with it (resume)
        resume_[link_->local_of(r.gid)] = r.token;       // and the next checkpoint keeps it waiting
        ++players;
      }
    }
    stats_.players_restored += players;
    restored_waiting_ = players;
    restored_tick_ = tick_;
    stats_.restore_skipped += to_restore_.size() - back;
    if (no_room)
      spdlog::error("world '{}': {} entities of the checkpoint did not fit in the zone: lost", opt_.world, no_room);
    spdlog::info(
        "world '{}': {} entities restored from region {}'s checkpoint ({} players waiting {:.0f} s for their clients)",
        opt_.world, back, region_, players, opt_.resume_s);
    to_restore_.clear();
    to_restore_.shrink_to_fit();
  }
  std::vector<inbound_msg> inbox;
  std::vector<natsMsg*> handoffs;
  {
    std::lock_guard lock(inbox_mutex_);
    inbox.swap(inbox_);
    handoffs.swap(handoff_inbox_);
  }
  // Handoffs first (a ghost of an entity adopted here is then ignored).
  for (natsMsg* m : handoffs) {
    const auto* d = reinterpret_cast<const std::uint8_t*>(natsMsg_GetData(m));
    const auto r = decode_handoff({d, static_cast<std::size_t>(natsMsg_GetDataLength(m))});
    if (r) {
      entity_id local = null_entity;
      const auto st = link_->apply_handoff(w, *r, &local);
      if (st == handoff_status::adopted) {
        ++stats_.handoffs_applied;
        const std::uint64_t now = monotonic_us();
        const double ms = now > r->sent_us ? static_cast<double>(now - r->sent_us) / 1000.0 : 0.0;
        handoff_ms_.record(ms);
        handoff_ticks_.record(ms * tick_rate_hz_ / 1000.0);
        if (r->token != 0) {
          tokens_[r->token] = {r->gid, tick_ + static_cast<std::uint64_t>(opt_.unclaimed_player_s * tick_rate_hz_)};
          resume_[local] = r->token;  // its checkpoint record waits for the client under the same token
        }
        if (const auto it = early_inputs_.find(r->gid); it != early_inputs_.end()) {
          w.set_intent(local, it->second.first);
          early_inputs_.erase(it);
        }
      } else if (st == handoff_status::duplicate) {
        ++stats_.handoff_duplicates;
      } else if (st == handoff_status::no_room) {
        // A full zone: the record goes back to the stream and comes again (KV names this zone
        // already, so no other zone may take the entity; dropping it would lose it).
        ++stats_.handoffs_no_room;
        natsMsg_NakWithDelay(m, static_cast<std::int64_t>(opt_.no_room_retry_s * 1000), nullptr);  // ms
        natsMsg_Destroy(m);
        continue;
      }
    }
    natsMsg_Ack(m, nullptr);  // applied (or refused for good): not again
    natsMsg_Destroy(m);
  }
  for (const auto& m : inbox) {
    switch (m.what) {
      case inbound_msg::kind::ghosts:
        if (link_->apply_ghosts(w, m.data) == ghost_status::gap) {
          const auto from = decode_ghosts(m.data);
          if (from) {
            const std::string me = std::to_string(region_);
            natsConnection_Publish(nc_, subject("snap", from->from).c_str(), me.data(), static_cast<int>(me.size()));
            ++stats_.snapshot_requests;
          }
        }
        break;
      case inbound_msg::kind::snapshot_request: {
        const std::string text(m.data.begin(), m.data.end());
        char* end = nullptr;
        const unsigned long r = std::strtoul(text.c_str(), &end, 10);
        if (end != text.c_str() && r < map_.count()) link_->snapshot_requested(static_cast<std::uint32_t>(r));
        break;
      }
      case inbound_msg::kind::input: {
        if (m.data.size() != 8 + 4 + 12) break;
        global_id g;
        std::uint32_t seq;
        float v[3];
        std::memcpy(&g, m.data.data(), 8);
        std::memcpy(&seq, m.data.data() + 8, 4);
        std::memcpy(v, m.data.data() + 12, 12);
        ++stats_.inputs_received;
        const entity_id local = link_->local_of(g);
        if (local != null_entity && link_->owns(local)) {
          w.set_intent(local, {v[0], v[1], v[2]});
        } else {
          early_inputs_[g] = {{v[0], v[1], v[2]}, seq};  // the entity is still on its way
        }
        break;
      }
      case inbound_msg::kind::census:
        if (!m.reply.empty()) census_replies_.push_back(m.reply);  // answered at the end of the tick
        break;
    }
  }
  // Neighbours that lost deltas and still wait: ask again now and then.
  if (tick_ % 15 == 0) {
    for (const auto n : link_->snapshot_wanted()) {
      const std::string me = std::to_string(region_);
      natsConnection_Publish(nc_, subject("snap", n).c_str(), me.data(), static_cast<int>(me.size()));
    }
  }
  link_->expire(w);
  // Handed-off players whose clients never came: removed (documented loss, docs/world.md).
  for (auto it = tokens_.begin(); it != tokens_.end();) {
    if (tick_ > it->second.deadline_tick) {
      const entity_id local = link_->local_of(it->second.gid);
      if (local != null_entity && link_->owns(local) && w.despawn(local)) ++stats_.players_abandoned;
      const bool restored = it->second.restored;
      if (it->second.lingering) --lingering_;
      it = tokens_.erase(it);
      if (restored) restored_player_done();
    } else {
      ++it;
    }
  }
  if (early_inputs_.size() > 100000) early_inputs_.clear();
}

void nats_node::take_class_changes(std::vector<class_change>& out) {
  const auto changed = link_->take_class_changes();
  out.insert(out.end(), changed.begin(), changed.end());
}

void nats_node::after_step(zone_world& w, std::vector<redirect>& out) {
  tick_ = w.tick();
  link_->assign_ids(w);
  if (owners_wanted_.exchange(false)) {
    // The world's JetStream state was made again: what this zone owns (handed off at least once:
    // the others have no ownership record) goes back to KV by the sender.
    std::vector<std::pair<global_id, std::uint64_t>> owned;
    for (const auto& [g, epoch] : link_->owned_epochs()) {
      if (epoch > 0) owned.emplace_back(g, epoch);
    }
    std::lock_guard lock(out_mutex_);
    put_back_job_ = std::move(owned);
    out_cv_.notify_one();
  }
  if (auto gone = link_->take_departed(); !gone.empty()) {
    std::lock_guard lock(out_mutex_);
    for (const global_id g : gone) {
      outgoing o;
      o.record.gid = g;
      o.record.epoch = 0;
      outbox_.push_back(std::move(o));
    }
    out_cv_.notify_one();
  }
  // While NATS is unreachable (the connection down, or the sender unable to settle its first
  // record) no entity is handed off: it stays owned and served here, beyond the border, and goes
  // once NATS answers again (a prompt handoff, with its view as it is then). After the connection
  // was down, not before a lease renewal went through: NATS may be back without the world's
  // JetStream state (made again first), and a player redirected meanwhile would wait for its
  // handoff longer than its new zone waits for it.
  const bool connected = natsConnection_Status(nc_) == NATS_CONN_STATUS_CONNECTED;
  if (!connected) world_confirmed_ = false;
  const bool hold = !connected || !world_confirmed_.load() || sender_stalled_.load();
  if (hold) ++stats_.handoff_hold_ticks;
  auto records = hold ? std::vector<handoff_record>{} : link_->collect_handoffs(w, monotonic_us());
  for (auto& r : records) {
    if (r.behaviour.kind != behaviour::player) continue;
    r.token = new_token(r.to);
    resume_.erase(link_->local_of(r.gid));  // the new zone's client now
    pending_redirects_.push_back({link_->local_of(r.gid), r.gid, r.to, hex16(r.token), tick_});
    forward_target_[r.gid] = r.to;
    if (forward_target_.size() > 100000) forward_target_.clear();
  }
  if (!records.empty()) {
    {
      std::lock_guard lock(out_mutex_);
      for (auto& r : records) outbox_.push_back(outgoing{std::move(r)});
    }
    out_cv_.notify_one();
  }
  if (checkpointer_.joinable() && (checkpoint_due_.exchange(false) || tick_ >= next_checkpoint_tick_)) {
    next_checkpoint_tick_ =
        tick_ + std::max<std::uint64_t>(1, static_cast<std::uint64_t>(opt_.checkpoint_s * tick_rate_hz_));
    // A copy of what the zone owns after this tick's handoffs (no encoding here); the checkpoint
    // thread writes it.
    checkpoint_chunk job;
    job.region = region_;
    job.incarnation = incarnation_;
    job.tick = tick_;
    {
      std::lock_guard lock(ckpt_mutex_);
      job.records.swap(ckpt_spare_);  // the last one's vector: no allocation, no fresh pages
    }
    const std::uint64_t t0 = monotonic_us();
    // Players gone (logged out, handed off) leave the resume tokens (a handle is never reused as is).
    std::erase_if(resume_,
                  [&](const auto& p) { return !link_->owns(p.first) || w.behaviour_of(p.first) != behaviour::player; });
    link_->checkpoint(w, job.records, &resume_);
    const std::uint64_t took = monotonic_us() - t0;
    if (took > stats_.checkpoint_copy_max_us.load()) stats_.checkpoint_copy_max_us = took;
    stats_.checkpoint_copy_total_us += took;
    ++stats_.checkpoint_copies;
    std::lock_guard lock(ckpt_mutex_);
    if (ckpt_job_) ++stats_.checkpoints_skipped;
    ckpt_job_ = std::move(job);
    ckpt_cv_.notify_one();
  }
  // Redirects go out once the new zone's address is known (a zone that just started may not be
  // in the table yet: read KV again then); the client's inputs are forwarded meanwhile.
  if (!pending_redirects_.empty()) {
    std::vector<std::pair<std::string, std::uint16_t>> addr;
    {
      std::lock_guard lock(addr_mutex_);
      addr = addresses_;
    }
    const bool unknown = std::any_of(pending_redirects_.begin(), pending_redirects_.end(),
                                     [&](const pending_redirect& p) { return addr[p.to].second == 0; });
    if (unknown) addresses_wanted_ = true;  // read by the heartbeat thread; the redirect goes out on a later tick
    const auto give_up = static_cast<std::uint64_t>(opt_.unclaimed_player_s * tick_rate_hz_);
    std::erase_if(pending_redirects_, [&](const pending_redirect& p) {
      const auto& [host, port] = addr[p.to];
      if (port != 0) {
        out.push_back({p.local, host, port, p.token});
        ++stats_.redirects;
        return true;
      }
      return tick_ > p.since_tick + give_up;
    });
  }
  for (const auto& reply : census_replies_) answer_census(reply);
  census_replies_.clear();
  link_->build_ghosts(w, ghost_out_);
  for (const auto& m : ghost_out_) {
    const auto bytes = encode(m);
    if (natsConnection_Publish(nc_, subject("ghost", m.to).c_str(), bytes.data(), static_cast<int>(bytes.size())) != NATS_OK) {
      ++stats_.ghost_publish_failures;
    }
  }
}

zone_extension::claim nats_node::claim_token(const std::string& token, zone_world& w, entity_id& entity) {
  const auto t = parse_token(token);
  if (!t) return claim::refused;
  const auto it = tokens_.find(*t);
  if (it == tokens_.end()) return claim::wait;  // the handoff (or the region's restore) may not have landed yet
  const entity_id local = link_->local_of(it->second.gid);
  const bool restored = it->second.restored, lingered = it->second.lingering;
  if (lingered) --lingering_;
  tokens_.erase(it);
  if (local == null_entity || !link_->owns(local) || w.behaviour_of(local) != behaviour::player) return claim::refused;
  entity = local;
  resume_[local] = *t;  // the client keeps this token: it resumes with it should this zone be lost
  ++(restored ? stats_.players_resumed : lingered ? stats_.players_back_after_linger : stats_.redirect_claims);
  if (restored) {
    resumed_after_ticks_.push_back(tick_ - restored_tick_);
    restored_player_done();
  }
  return claim::ready;
}

bool nats_node::keep_for_resume(entity_id e, zone_world& w) {
  if (!(opt_.linger_s > 0) || !link_->owns(e) || w.behaviour_of(e) != behaviour::player) return false;
  const auto it = resume_.find(e);
  const global_id g = link_->gid_of(e);
  const std::size_t cap = slots_.load() > 0 ? slots_.load() : 100000;
  if (it == resume_.end() || g == 0 || lingering_ >= cap) return false;
  w.set_intent(e, {});  // it stands where it was until its client is back
  tokens_[it->second] = {g, tick_ + static_cast<std::uint64_t>(opt_.linger_s * tick_rate_hz_), false, true};
  ++lingering_;
  ++stats_.players_lingered;
  return true;
}

void nats_node::restored_player_done() {
  if (restored_waiting_ == 0 || --restored_waiting_ != 0) return;
  auto& d = resumed_after_ticks_;
  std::sort(d.begin(), d.end());
  const auto s = [&](std::uint64_t ticks) { return static_cast<double>(ticks) / tick_rate_hz_; };
  spdlog::info(
      "world '{}': the restored players: {} back with their clients (after {:.1f} s at the median, {:.1f} s at the "
      "latest), {} removed (their client never came)",
      opt_.world, d.size(), d.empty() ? 0.0 : s(d[d.size() / 2]), d.empty() ? 0.0 : s(d.back()),
      stats_.players_restored.load() - d.size());
  d.clear();
}

std::string nats_node::resume_token(entity_id e, const std::string& claimed) {
  if (!claimed.empty()) return claimed;  // claim_token kept it
  const std::uint64_t t = new_token(region_);
  resume_[e] = t;
  return hex16(t);
}

std::uint64_t nats_node::new_token(std::uint32_t r) {
  std::uint64_t low = 0;
  while (low == 0) low = os_random_u64() & 0xffffffffffffull;
  return static_cast<std::uint64_t>(r + 1) << 48 | low;
}

void nats_node::forward_input(entity_id e, const vec3& intent, std::uint32_t sequence) {
  const global_id g = link_->gid_of(e);
  if (g == 0) return;
  // Where it went: the zone this one handed it to.
  std::uint8_t buf[24];
  std::memcpy(buf, &g, 8);
  std::memcpy(buf + 8, &sequence, 4);
  const float v[3] = {intent.x, intent.y, intent.z};
  std::memcpy(buf + 12, v, 12);
  const auto target = forward_target_.find(g);
  if (target == forward_target_.end()) return;
  natsConnection_Publish(nc_, subject("input", target->second).c_str(), buf, sizeof buf);
  ++stats_.inputs_forwarded;
}

// ---- checking a world from outside ---------------------------------------------------------------

std::optional<std::vector<census_entry>> take_census(const std::string& url, const std::string& world, int wait_ms,
                                                     std::string* error, const std::function<void()>& pump) {
  natsConnection* nc = nullptr;
  if (natsStatus s = natsConnection_ConnectTo(&nc, url.c_str()); s != NATS_OK) {
    if (error) *error = "cannot connect to " + url + ": " + status_text(s);
    return std::nullopt;
  }
  std::vector<census_entry> out;
  char inbox[64];
  std::snprintf(inbox, sizeof inbox, "census.%llx", static_cast<unsigned long long>(monotonic_us()));
  natsSubscription* sub = nullptr;
  natsConnection_SubscribeSync(&sub, nc, inbox);
  natsConnection_PublishRequest(nc, ("world." + world + ".census").c_str(), inbox, "", 0);
  natsConnection_Flush(nc);
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(wait_ms);
  while (std::chrono::steady_clock::now() < deadline) {
    if (pump) pump();
    natsMsg* m = nullptr;
    if (natsSubscription_NextMsg(&m, sub, 20) != NATS_OK) continue;
    const auto* d = reinterpret_cast<const std::uint8_t*>(natsMsg_GetData(m));
    const auto len = static_cast<std::size_t>(natsMsg_GetDataLength(m));
    census_entry e;
    std::uint32_t count = 0;
    if (len >= 20) {
      std::memcpy(&e.region, d, 4);
      std::memcpy(&e.incarnation, d + 4, 4);
      std::memcpy(&e.tick, d + 8, 8);
      std::memcpy(&count, d + 16, 4);
    }
    std::uint32_t tcount = 0;
    const std::size_t head = 20 + std::size_t{count} * 16;
    if (len >= 20 && len >= head + 4) std::memcpy(&tcount, d + head, 4);
    const std::size_t tail = head + 4 + std::size_t{tcount} * 8;
    std::uint32_t acount = 0;
    if (len >= 20 && len >= tail + 4) std::memcpy(&acount, d + tail, 4);
    if (len >= 20 && len >= tail + 4 && len == tail + 4 + std::size_t{acount} * 8) {
      e.owned.resize(count);
      for (std::size_t k = 0; k < count; ++k) {
        std::memcpy(&e.owned[k].first, d + 20 + 16 * k, 8);
        std::memcpy(&e.owned[k].second, d + 28 + 16 * k, 8);
      }
      e.transit.resize(tcount);
      if (tcount) std::memcpy(e.transit.data(), d + head + 4, std::size_t{tcount} * 8);
      e.awaiting.resize(acount);
      if (acount) std::memcpy(e.awaiting.data(), d + tail + 4, std::size_t{acount} * 8);
      out.push_back(std::move(e));
    }
    natsMsg_Destroy(m);
  }
  natsSubscription_Destroy(sub);
  natsConnection_Destroy(nc);
  std::sort(out.begin(), out.end(), [](const census_entry& a, const census_entry& b) { return a.region < b.region; });
  return out;
}

running_zones read_running(const std::vector<census_entry>& census, std::uint32_t regions) {
  running_zones out;
  out.served.assign(regions, false);
  out.incarnation.assign(regions, 0);
  const auto seen = [&](global_id g) {
    const std::uint32_t r = region_of_gid(g);
    if (r < regions) out.incarnation[r] = std::max(out.incarnation[r], incarnation_of_gid(g));
  };
  for (const auto& z : census) {
    if (z.region >= regions) continue;
    out.served[z.region] = true;
    out.incarnation[z.region] = std::max(out.incarnation[z.region], z.incarnation);
    for (const auto& [g, epoch] : z.owned) seen(g);
    for (const global_id g : z.transit) seen(g);
    for (const global_id g : z.awaiting) seen(g);
  }
  return out;
}

namespace {

/// A connection of its own to one KV bucket, for the tools that read a world from outside it
/// (world-check: read_owners, read_leases); closed when it goes.
struct kv_reader {
  natsConnection* nc = nullptr;
  jsCtx* js = nullptr;
  kvStore* kv = nullptr;
  kv_reader() = default;
  kv_reader(const kv_reader&) = delete;
  kv_reader& operator=(const kv_reader&) = delete;
  ~kv_reader() {
    if (kv) kvStore_Destroy(kv);
    if (js) jsCtx_Destroy(js);
    if (nc) natsConnection_Destroy(nc);
  }
  /// Opens `bucket` at `url`; why not (`missing`: what to say when there is no such bucket).
  std::optional<std::string> open(const std::string& url, const std::string& bucket, const std::string& missing) {
    if (natsStatus s = natsConnection_ConnectTo(&nc, url.c_str()); s != NATS_OK) return "cannot connect: " + status_text(s);
    if (natsConnection_JetStream(&js, nc, nullptr) != NATS_OK) return std::string("no JetStream");
    if (js_KeyValue(&kv, js, bucket.c_str()) != NATS_OK) return missing;
    return std::nullopt;
  }
};

}  // namespace

std::optional<std::map<global_id, std::pair<std::uint32_t, std::uint64_t>>> read_owners(const std::string& url,
                                                                                        const std::string& world,
                                                                                        std::string* error,
                                                                                        const std::vector<global_id>* only) {
  const auto fail = [&](const std::string& why) {
    if (error) *error = why;
    return std::nullopt;
  };
  kv_reader r;
  if (auto why = r.open(url, "world-" + world, "no world '" + world + "' in KV")) return fail(*why);
  kvStore* kv = r.kv;
  std::map<global_id, std::pair<std::uint32_t, std::uint64_t>> out;
  // One record; a read that fails for another reason than "no such key" (a timeout on a loaded
  // host) is tried again: a record silently skipped would read as a missing one.
  const auto read = [&](const std::string& k) {
    for (int attempt = 0; attempt < 3; ++attempt) {
      kvEntry* e = nullptr;
      const natsStatus s = kvStore_Get(&e, kv, k.c_str());
      if (s == NATS_NOT_FOUND) return;
      if (s != NATS_OK) continue;
      std::istringstream in(kvEntry_ValueString(e));
      std::uint32_t region = 0;
      std::uint64_t epoch = 0;
      if (in >> region >> epoch) out[std::strtoull(k.c_str() + 2, nullptr, 16)] = {region, epoch};
      kvEntry_Destroy(e);
      return;
    }
  };
  if (only != nullptr) {
    for (const global_id g : *only) read(owner_key(g));
  } else {
    kvKeysList keys{};
    const natsStatus ks = kvStore_Keys(&keys, kv, nullptr);
    if (ks == NATS_OK) {
      for (int i = 0; i < keys.Count; ++i) {
        const std::string k = keys.Keys[i];
        if (k.rfind("e.", 0) == 0) read(k);
      }
      kvKeysList_Destroy(&keys);
    } else if (ks != NATS_NOT_FOUND) {
      return fail("cannot list keys: " + status_text(ks));
    }
  }
  return out;
}

std::optional<double> lease_ttl_s(__kvStore* leases) {
  kvStatus* st = nullptr;
  if (kvStore_Status(&st, leases) != NATS_OK) return std::nullopt;
  const double ttl_s = static_cast<double>(kvStatus_TTL(st)) / 1e9;
  kvStatus_Destroy(st);
  if (!(ttl_s > 0)) return std::nullopt;
  return ttl_s;
}

lease_info parse_lease(std::string raw) {
  lease_info l;
  std::istringstream in(raw);
  unsigned port = 0;
  std::uint32_t inc = 0;
  if (in >> l.host >> port >> inc && port <= 0xffff) {
    l.port = static_cast<std::uint16_t>(port);
    l.incarnation = inc;
  } else {
    l.host.clear();
  }
  l.raw = std::move(raw);
  return l;
}

std::optional<std::map<std::uint32_t, lease_info>> read_leases(__kvStore* kv, std::string* error) {
  std::map<std::uint32_t, lease_info> out;
  std::map<std::uint32_t, std::string> loads;  // "p.<region>"
  kvKeysList keys{};
  const natsStatus ks = kvStore_Keys(&keys, kv, nullptr);
  if (ks == NATS_NOT_FOUND) return out;  // no lease at all
  if (ks != NATS_OK) {
    if (error) *error = "cannot list the leases: " + status_text(ks);
    return std::nullopt;
  }
  for (int i = 0; i < keys.Count; ++i) {
    const std::string k = keys.Keys[i];
    const bool lease = k.rfind("r.", 0) == 0, load = k.rfind("p.", 0) == 0;
    if (!lease && !load) continue;
    kvEntry* e = nullptr;
    if (kvStore_Get(&e, kv, k.c_str()) != NATS_OK) continue;  // lapsed since the listing
    const std::string value = kvEntry_ValueString(e);
    const std::uint64_t revision = kvEntry_Revision(e);
    kvEntry_Destroy(e);
    const auto region = static_cast<std::uint32_t>(std::strtoul(k.c_str() + 2, nullptr, 10));
    if (lease) {
      out[region] = parse_lease(value);
      out[region].revision = revision;
    } else {
      loads[region] = value;
    }
  }
  kvKeysList_Destroy(&keys);
  for (const auto& [region, text] : loads) {
    const auto it = out.find(region);
    if (it == out.end()) continue;
    std::istringstream in(text);
    std::int64_t players = 0, slots = 0;
    if (in >> players >> slots && players >= 0 && slots >= 0) {
      it->second.players = players;
      it->second.slots = slots;
      it->second.load_raw = text;
    }
  }
  return out;
}

std::optional<std::map<std::uint32_t, lease_info>> read_leases(const std::string& url, const std::string& world,
                                                               std::string* error) {
  kv_reader r;
  if (auto why = r.open(url, "world-" + world + "-lease", "no world '" + world + "' leases in KV")) {
    if (error) *error = *why;
    return std::nullopt;
  }
  return read_leases(r.kv, error);
}

lease_check check_leases(const std::vector<census_entry>& census, const std::map<std::uint32_t, lease_info>& leases) {
  lease_check c;
  std::map<std::uint32_t, std::vector<std::uint32_t>> answered;  // region -> incarnations answering
  for (const auto& z : census) answered[z.region].push_back(z.incarnation);
  for (const auto& [region, incs] : answered) {
    const auto it = leases.find(region);
    std::string who;
    for (const std::uint32_t i : incs) who += (who.empty() ? "" : ", ") + std::to_string(i);
    if (incs.size() > 1) {
      c.problems.push_back("region " + std::to_string(region) + " answered by " + std::to_string(incs.size()) +
                           " zones (incarnations " + who + "); its lease: " +
                           (it == leases.end() ? std::string("none") : "'" + it->second.raw + "'"));
      continue;
    }
    if (it == leases.end()) {
      c.notes.push_back("region " + std::to_string(region) + " answered by incarnation " + who +
                        " without a lease (lapsed; taken back at its zone's next renewal)");
    } else if (it->second.incarnation != incs.front()) {
      c.problems.push_back("region " + std::to_string(region) + " answered by incarnation " + who +
                           ", but its lease is '" + it->second.raw + "': served by a zone that does not hold it");
    }
  }
  return c;
}

world_check check_world(const std::vector<census_entry>& census,
                        const std::map<global_id, std::pair<std::uint32_t, std::uint64_t>>& owners) {
  world_check c;
  c.zones = census.size();
  c.kv_records = owners.size();
  std::unordered_map<global_id, std::vector<std::pair<std::uint32_t, std::uint64_t>>> seen;  // id -> (region, epoch)
  // Players whose client never followed its redirect are removed (and their KV record deleted)
  // unclaimed_player_s after the handoff; that may fall between the census and the KV read.
  std::unordered_map<global_id, bool> awaiting;
  for (const auto& z : census) {
    for (const global_id g : z.awaiting) awaiting[g] = true;
  }
  for (const auto& z : census) {
    c.owned += z.owned.size();
    for (const auto& [g, epoch] : z.owned) seen[g].emplace_back(z.region, epoch);
  }
  for (const auto& [g, where] : seen) {
    for (std::size_t a = 0; a < where.size(); ++a) {
      for (std::size_t b = a + 1; b < where.size(); ++b) {
        if (where[a].second == where[b].second) {
          ++c.owned_twice;
        } else {
          ++c.moving;
        }
      }
    }
    for (const auto& [region, epoch] : where) {
      if (epoch == 0) continue;  // never handed off: no record needed
      const auto it = owners.find(g);
      if (it == owners.end()) {
        if (awaiting.contains(g)) continue;  // leaving now: its record may be gone already
        ++c.kv_missing;
        c.missing_ids.push_back(g);
        if (c.problem_examples.size() < 10) {
          c.problem_examples.push_back("missing: id " + hex16(g) + " owned by region " + std::to_string(region) +
                                       " at epoch " + std::to_string(epoch) + ", no KV record");
        }
      } else if (it->second.second < epoch || (it->second.second == epoch && it->second.first != region)) {
        ++c.kv_disagree;
        if (c.problem_examples.size() < 10) {
          c.problem_examples.push_back("disagree: id " + hex16(g) + " owned by region " + std::to_string(region) +
                                       " at epoch " + std::to_string(epoch) + ", KV says region " +
                                       std::to_string(it->second.first) + " epoch " +
                                       std::to_string(it->second.second));
        }
      }
    }
  }
  std::unordered_map<global_id, bool> transit;
  for (const auto& z : census) {
    for (const global_id g : z.transit) {
      if (!seen.contains(g)) transit[g] = true;
    }
  }
  c.transit_only = transit.size();
  for (const auto& z : census) c.awaiting_players += z.awaiting.size();
  for (const auto& [g, rec] : owners) {
    const auto it = seen.find(g);
    bool current = false;
    if (it != seen.end()) {
      for (const auto& [region, epoch] : it->second) current = current || epoch >= rec.second;
    }
    if (!current) {
      ++c.kv_in_flight;
      if (c.in_flight_examples.size() < 10) {
        std::string what = "id " + hex16(g) + ": KV says region " + std::to_string(rec.first) + " epoch " +
                           std::to_string(rec.second) + "; zones:";
        if (it != seen.end()) {
          for (const auto& [region, epoch] : it->second) what += " region " + std::to_string(region) + " epoch " + std::to_string(epoch);
        } else {
          what += transit.contains(g) ? " in transit" : " none";
        }
        c.in_flight_examples.push_back(what);
      }
    }
  }
  return c;
}

}  // namespace zone::world
