// The oracle (oracle.h): ground truth in, every player's visible set recomputed by brute force,
// every bot's view compared with it.
#include "oracle.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <bit>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>

namespace zone::bots {

namespace {

constexpr std::uint32_t npos32 = 0xffffffffu;
constexpr std::uint32_t logged_per_kind = 5;

double thread_cpu_ms() {
  timespec ts{};
  ::clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) * 1e3 + static_cast<double>(ts.tv_nsec) / 1e6;
}

/// The candidate flags of one observer: 1 where the target's presence box meets the observer's
/// AOI box grown by the hysteresis and the target's class is one the observer sees. Every target
/// is tested (brute force); written without branches so that it vectorizes (AVX2 where the
/// machine has it).
struct grown_box {
  float lo_x, lo_y, lo_z, hi_x, hi_y, hi_z;
};
__attribute__((target_clones("avx2", "default"))) void candidate_flags(
    const float* __restrict blo_x, const float* __restrict blo_y, const float* __restrict blo_z,
    const float* __restrict bhi_x, const float* __restrict bhi_y, const float* __restrict bhi_z,
    const std::uint32_t* __restrict cls, std::size_t n, grown_box g, std::uint32_t sees, std::uint8_t* __restrict out) {
  for (std::size_t k = 0; k < n; ++k) {
    const bool meets = (blo_x[k] <= g.hi_x) & (g.lo_x <= bhi_x[k]) & (blo_y[k] <= g.hi_y) & (g.lo_y <= bhi_y[k]) &
                       (blo_z[k] <= g.hi_z) & (g.lo_z <= bhi_z[k]);
    out[k] = static_cast<std::uint8_t>(meets & ((cls[k] & sees) != 0));
  }
}

float dist2(const float* a, const float* b) {
  // The replicator's expression (zone/replication.cpp distance_sq(eye, target)), operand order included.
  const float dx = a[0] - b[0], dy = a[1] - b[1], dz = a[2] - b[2];
  return dx * dx + dy * dy + dz * dz;
}

}  // namespace

struct oracle::layout {
  std::vector<std::uint32_t> ids, classes, sees;
  std::vector<std::uint8_t> kinds;
  std::vector<float> aoi, presence;  // 3 per entity
  net::id_map<std::uint32_t> dense;  // id -> dense index
  std::vector<std::uint32_t> observers;  // dense indices of the players
  [[nodiscard]] std::uint32_t dense_of(std::uint32_t id) const {
    const auto it = dense.find(id);
    return it == dense.end() ? npos32 : it->second;
  }
};

struct oracle::tick_truth {
  mutable std::shared_mutex mutex;
  bool valid = false;
  std::uint64_t tick = 0;
  std::shared_ptr<const layout> lay;
  std::vector<float> pos;                  // 3 per entity
  std::vector<std::uint32_t> obs_ids;      // observers (players), ascending
  std::vector<std::uint32_t> obs_off;      // CSR offsets into vis, size + 1
  std::vector<std::uint8_t> obs_known;     // whole history seen (else not checked)
  std::vector<std::uint32_t> vis;          // each observer's visible set, ascending
  std::vector<std::uint32_t> vis_dense;    // beside vis: each entry's dense index in lay
  [[nodiscard]] std::uint32_t find(std::uint32_t observer) const {
    const auto it = std::lower_bound(obs_ids.begin(), obs_ids.end(), observer);
    return it != obs_ids.end() && *it == observer ? static_cast<std::uint32_t>(it - obs_ids.begin()) : npos32;
  }
  [[nodiscard]] std::span<const std::uint32_t> set(std::uint32_t i) const {
    return {vis.data() + obs_off[i], obs_off[i + 1] - obs_off[i]};
  }
  [[nodiscard]] std::span<const std::uint32_t> set_dense(std::uint32_t i) const {
    return {vis_dense.data() + obs_off[i], obs_off[i + 1] - obs_off[i]};
  }
};

oracle::oracle(const net::world_bounds& world, const net::interest_rules& rules, unsigned threads, problem_fn problem,
               void* ctx)
    : world_(world), rules_(rules), problem_(problem), ctx_(ctx) {
  const net::vec3f e = net::position_quantizer(world).max_error();
  // The quantizer's guaranteed error plus a little for the float arithmetic of dequantizing.
  tolerance_ = {e.x * 1.01f + 1e-4f, e.y * 1.01f + 1e-4f, e.z * 1.01f + 1e-4f};
  threads_ = threads != 0 ? threads : std::max(1u, std::thread::hardware_concurrency() / 8);
  for (std::size_t i = 0; i < ring_ticks; ++i) ring_.push_back(std::make_unique<tick_truth>());
  flags_.resize(threads_);
}

oracle::~oracle() { stop(); }

std::optional<std::string> oracle::start(std::uint16_t port, double timeout_s) {
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (fd < 0) return std::string("oracle: socket: ") + std::strerror(errno);
  const int buf = 8 << 20;
  ::setsockopt(fd, SOL_SOCKET, SO_RCVBUF, &buf, sizeof buf);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(port);
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
    const std::string err = std::strerror(errno);
    ::close(fd);
    return "oracle: cannot connect to the truth stream at 127.0.0.1:" + std::to_string(port) + ": " + err;
  }
  fd_ = fd;
  thread_ = std::thread([this, fd] { run(fd); });
  std::unique_lock lock(ready_mutex_);
  const bool got = ready_cv_.wait_for(lock, std::chrono::duration<double>(timeout_s),
                                      [&] { return any_ready_.load() || ended_.load(); });
  if (!got || !any_ready_.load()) {
    lock.unlock();
    const std::string why = stream_error_.empty() ? "no tick within " + std::to_string(timeout_s) + " s" : stream_error_;
    stop();
    return "oracle: the truth stream gave nothing: " + why;
  }
  return std::nullopt;
}

void oracle::stop() {
  stopping_ = true;
  if (fd_ >= 0) ::shutdown(fd_, SHUT_RDWR);
  if (thread_.joinable()) thread_.join();
  if (fd_ >= 0) ::close(fd_), fd_ = -1;
  ended_ = true;
  ready_cv_.notify_all();
  drain_pending(true, static_cast<std::size_t>(-1));  // what still waits: checked if its truth came, else unchecked
}

void oracle::run(int fd) {
  std::vector<std::uint8_t> body;
  const auto read_all = [&](void* to, std::size_t n) {
    auto* p = static_cast<std::uint8_t*>(to);
    while (n > 0) {
      const auto r = ::recv(fd, p, n, 0);
      if (r <= 0) {
        if (r < 0 && errno == EINTR) continue;
        return false;
      }
      p += r;
      n -= static_cast<std::size_t>(r);
    }
    return true;
  };
  std::string error;
  for (;;) {
    std::uint32_t len = 0;
    if (!read_all(&len, sizeof len)) {
      if (!stopping_.load()) error = "the server closed the truth stream";
      break;
    }
    if (len > net::truth::max_body_bytes) {
      error = "truth frame of " + std::to_string(len) + " bytes is too large";
      break;
    }
    body.resize(len);
    if (!read_all(body.data(), len)) {
      if (!stopping_.load()) error = "the truth stream ended in the middle of a frame";
      break;
    }
    truth_bytes_ += len + 4;
    if (auto err = feed(body)) {
      error = *err;
      break;
    }
  }
  {
    std::lock_guard lock(ready_mutex_);
    if (!error.empty()) stream_error_ = error;
    ended_ = true;
  }
  ready_cv_.notify_all();
}

std::optional<std::string> oracle::feed(std::span<const std::uint8_t> body) {
  const double cpu0 = thread_cpu_ms();
  const auto t0 = std::chrono::steady_clock::now();
  if (auto err = net::truth::decode_tick(body, frame_)) return err;
  if (frame_.has_layout) ++truth_layouts_;
  if (frame_.has_changes) ++truth_changes_;
  if (!frame_.has_layout && !layout_) return std::string("the first truth frame has no layout");
  compute(frame_);
  ++truth_ticks_;
  compute_cpu_ms_ += thread_cpu_ms() - cpu0;
  compute_max_ms_ = std::max(compute_max_ms_, std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
  return std::nullopt;
}

void oracle::compute(const net::truth::tick_frame& f) {
  if (f.has_layout) {
    auto l = std::make_shared<layout>();
    l->ids = f.ids;
    l->classes = f.classes;
    l->sees = f.sees;
    l->kinds = f.kinds;
    l->aoi = f.aoi_half;
    l->presence = f.presence_half;
    for (std::uint32_t k = 0; k < f.count; ++k) {
      l->dense.try_emplace(f.ids[k]).first->second = k;
      if (f.kinds[k] == static_cast<std::uint8_t>(net::entity_kind::player)) l->observers.push_back(k);
    }
    layout_ = std::move(l);
  } else if (f.has_changes) {
    // The same entities, some rows replaced (the decoder applied them to f's columns): a new
    // layout, since earlier ticks' truth keeps the one it had.
    auto l = std::make_shared<layout>(*layout_);
    bool kinds_changed = false;
    for (const std::uint32_t k : f.changed) {
      l->classes[k] = f.classes[k];
      l->sees[k] = f.sees[k];
      kinds_changed |= l->kinds[k] != f.kinds[k];
      l->kinds[k] = f.kinds[k];
      std::copy_n(f.aoi_half.begin() + 3 * k, 3, l->aoi.begin() + 3 * k);
      std::copy_n(f.presence_half.begin() + 3 * k, 3, l->presence.begin() + 3 * k);
    }
    if (kinds_changed) {
      l->observers.clear();
      for (std::uint32_t k = 0; k < f.count; ++k) {
        if (l->kinds[k] == static_cast<std::uint8_t>(net::entity_kind::player)) l->observers.push_back(k);
      }
    }
    layout_ = std::move(l);
  }
  const layout& lay = *layout_;
  const std::size_t n = f.count;
  const float* pos = f.positions.data();
  // Presence boxes, as the server builds them (position -+ half-extent, in float), laid out by
  // ascending x of the position (slot s holds dense index by_x[s]): an observer's scan can then
  // skip the entities whose x alone rules them out (below).
  std::vector<std::uint32_t> by_x(n);
  for (std::size_t k = 0; k < n; ++k) by_x[k] = static_cast<std::uint32_t>(k);
  std::sort(by_x.begin(), by_x.end(), [&](std::uint32_t x, std::uint32_t y) {
    return pos[3 * x] < pos[3 * y] || (pos[3 * x] == pos[3 * y] && x < y);
  });
  std::vector<float> b(7 * n);
  float* blo_x = b.data();
  float* blo_y = blo_x + n;
  float* blo_z = blo_y + n;
  float* bhi_x = blo_z + n;
  float* bhi_y = bhi_x + n;
  float* bhi_z = bhi_y + n;
  float* px = bhi_z + n;
  std::vector<std::uint32_t> cls(n);
  float max_half_x = 0;
  for (std::size_t s = 0; s < n; ++s) {
    const std::uint32_t k = by_x[s];
    const float* p = pos + 3 * k;
    const float* hx = lay.presence.data() + 3 * k;
    blo_x[s] = p[0] - hx[0], blo_y[s] = p[1] - hx[1], blo_z[s] = p[2] - hx[2];
    bhi_x[s] = p[0] + hx[0], bhi_y[s] = p[1] + hx[1], bhi_z[s] = p[2] + hx[2];
    px[s] = p[0];
    cls[s] = lay.classes[k];
    max_half_x = std::max(max_half_x, hx[0]);
  }

  // The previous tick's sets (the hysteresis): only when it is the tick just before this one.
  const tick_truth* prev = nullptr;
  if (any_tick_ && prev_tick_ + 1 == f.tick) {
    const tick_truth& p = *ring_[(f.tick - 1) % ring_ticks];
    if (p.valid && p.tick == f.tick - 1) prev = &p;
  }
  const std::size_t obs = lay.observers.size();
  observers_max_ = std::max<std::uint64_t>(observers_max_, obs);
  if (sets_.size() < obs) sets_.resize(obs);
  std::vector<std::uint8_t> known(obs, 0);
  const float h = rules_.hysteresis;
  const std::uint32_t cap = rules_.max_visible;

  const auto work = [&](unsigned t, std::size_t first, std::size_t last) {
    std::vector<std::uint8_t>& flags = flags_[t];
    flags.resize(n + 8);
    std::vector<std::uint64_t> keys;
    for (std::size_t i = first; i < last; ++i) {
      const std::uint32_t a = lay.observers[i];
      const std::uint32_t id = lay.ids[a];
      std::vector<std::uint64_t>& out = sets_[i];  // (id << 32) | dense index
      out.clear();
      // History: a new entity starts from an empty set; one seen last tick continues from its set
      // there; any other (present before the stream began, or after a gap) is not checked.
      std::span<const std::uint32_t> before;
      bool is_known = false;
      if (prev != nullptr) {
        const std::uint32_t j = prev->find(id);
        if (j != npos32) {
          is_known = prev->obs_known[j] != 0;
          before = prev->set(j);
        } else {
          is_known = prev->lay->dense_of(id) == npos32;
        }
      }
      known[i] = is_known ? 1 : 0;
      const float* p = pos + 3 * a;
      const float* e = lay.aoi.data() + 3 * a;
      // The same float expressions as the server's boxes: grown = p -+ (aoi + h), exact = p -+ aoi.
      const float gx = e[0] + h, gy = e[1] + h, gz = e[2] + h;
      const grown_box g{p[0] - gx, p[1] - gy, p[2] - gz, p[0] + gx, p[1] + gy, p[2] + gz};
      const float lo_x = p[0] - e[0], lo_y = p[1] - e[1], lo_z = p[2] - e[2];
      const float hi_x = p[0] + e[0], hi_y = p[1] + e[1], hi_z = p[2] + e[2];
      // Every target is tested (brute force), except, unless full_scan, those whose position's x
      // is farther from the observer's than the grown AOI plus the largest presence half-extent
      // plus 1 m: their boxes cannot meet on x (the 1 m covers any rounding of the box bounds).
      std::size_t first_s = 0, last_s = n;
      if (!full_scan) {
        const float reach = gx + max_half_x + 1;
        first_s = static_cast<std::size_t>(std::lower_bound(px, px + n, p[0] - reach) - px);
        last_s = static_cast<std::size_t>(std::upper_bound(px, px + n, p[0] + reach) - px);
      }
      const std::size_t m = last_s - first_s;
      candidate_flags(blo_x + first_s, blo_y + first_s, blo_z + first_s, bhi_x + first_s, bhi_y + first_s,
                      bhi_z + first_s, cls.data() + first_s, m, g, lay.sees[a], flags.data());
      std::fill(flags.begin() + static_cast<std::ptrdiff_t>(m), flags.begin() + static_cast<std::ptrdiff_t>(m + 8), 0);
      for (std::size_t k0 = 0; k0 < m; k0 += 8) {
        std::uint64_t word;
        std::memcpy(&word, flags.data() + k0, 8);
        if (word == 0) continue;
        for (std::size_t r = k0; r < std::min(m, k0 + 8); ++r) {
          if (flags[r] == 0) continue;
          const std::size_t k = first_s + r;
          if (by_x[k] == a) continue;  // never itself
          const std::uint32_t target = lay.ids[by_x[k]];
          const std::uint64_t entry = (std::uint64_t{target} << 32) | by_x[k];
          // Enter: the presence box meets the exact AOI box; stay: it was visible last tick.
          const bool meets = blo_x[k] <= hi_x && lo_x <= bhi_x[k] && blo_y[k] <= hi_y && lo_y <= bhi_y[k] &&
                             blo_z[k] <= hi_z && lo_z <= bhi_z[k];
          if (meets || std::binary_search(before.begin(), before.end(), target)) out.push_back(entry);
        }
      }
      if (cap != 0 && out.size() > cap) {
        // The cap closest by squared distance (ties by id), as the server keeps them.
        keys.clear();
        for (const std::uint64_t e2 : out) {
          const auto k = static_cast<std::uint32_t>(e2);
          keys.push_back((std::uint64_t{std::bit_cast<std::uint32_t>(dist2(p, pos + 3 * k))} << 32) | (e2 >> 32));
        }
        std::sort(keys.begin(), keys.end());
        keys.resize(cap);
        out.clear();
        for (const std::uint64_t key : keys) {
          const auto t2 = static_cast<std::uint32_t>(key);
          out.push_back((std::uint64_t{t2} << 32) | lay.dense_of(t2));
        }
      }
      std::sort(out.begin(), out.end());
    }
  };
  if (threads_ <= 1 || obs < 64) {
    work(0, 0, obs);
  } else {
    std::vector<std::thread> pool;
    std::vector<double> cpu(threads_, 0);
    for (unsigned t = 1; t < threads_; ++t) {
      pool.emplace_back([&, t] {
        const double c0 = thread_cpu_ms();
        work(t, obs * t / threads_, obs * (t + 1) / threads_);
        cpu[t] = thread_cpu_ms() - c0;
      });
    }
    work(0, 0, obs / threads_);
    for (auto& th : pool) th.join();
    for (const double c : cpu) compute_cpu_ms_ += c;
  }

  // Publish this tick's truth and sets, observers by id.
  std::vector<std::uint32_t> order(obs);
  for (std::size_t i = 0; i < obs; ++i) order[i] = static_cast<std::uint32_t>(i);
  std::sort(order.begin(), order.end(),
            [&](std::uint32_t x, std::uint32_t y) { return lay.ids[lay.observers[x]] < lay.ids[lay.observers[y]]; });
  {
    tick_truth& slot = *ring_[f.tick % ring_ticks];
    std::unique_lock lock(slot.mutex);
    slot.valid = true;
    slot.tick = f.tick;
    slot.lay = layout_;
    slot.pos.assign(f.positions.begin(), f.positions.end());
    slot.obs_ids.clear();
    slot.obs_off.assign(1, 0);
    slot.obs_known.clear();
    slot.vis.clear();
    slot.vis_dense.clear();
    for (const std::uint32_t i : order) {
      slot.obs_ids.push_back(lay.ids[lay.observers[i]]);
      slot.obs_known.push_back(known[i]);
      for (const std::uint64_t e : sets_[i]) {
        slot.vis.push_back(static_cast<std::uint32_t>(e >> 32));
        slot.vis_dense.push_back(static_cast<std::uint32_t>(e));
      }
      slot.obs_off.push_back(static_cast<std::uint32_t>(slot.vis.size()));
    }
  }
  prev_tick_ = f.tick;
  any_tick_ = true;
  {
    std::lock_guard lock(ready_mutex_);
    ready_tick_ = f.tick;
    any_ready_ = true;
  }
  ready_cv_.notify_all();
  const double drain0 = thread_cpu_ms();
  drain_pending(false, static_cast<std::size_t>(-1));
  drain_cpu_ms_ += thread_cpu_ms() - drain0;  // checks, not recomputing: reported apart
}

std::optional<std::vector<std::uint32_t>> oracle::visible(std::uint32_t observer, std::uint64_t tick) const {
  const tick_truth& slot = *ring_[tick % ring_ticks];
  std::shared_lock lock(slot.mutex);
  if (!slot.valid || slot.tick != tick) return std::nullopt;
  const std::uint32_t i = slot.find(observer);
  if (i == npos32 || slot.obs_known[i] == 0) return std::nullopt;
  const auto s = slot.set(i);
  return std::vector<std::uint32_t>(s.begin(), s.end());
}

void oracle::log(const char* kind, std::atomic<std::uint32_t>& logged, const std::string& line) {
  if (problem_ == nullptr || logged.fetch_add(1, std::memory_order_relaxed) >= logged_per_kind) return;
  problem_(ctx_, std::string("oracle: ") + kind + ": " + line);
}

void oracle::check(std::uint32_t observer, std::uint64_t tick, const net::client_view& view,
                   const net::deferred_counts& deferred, const std::optional<net::vec3f>& self_position, std::size_t bot) {
  for (std::uint64_t seen = newest_checked_tick_.load(std::memory_order_relaxed);
       tick > seen && !newest_checked_tick_.compare_exchange_weak(seen, tick, std::memory_order_relaxed);) {
  }
  thread_local view_snapshot v;
  v.observer = observer, v.tick = tick, v.deferred = deferred, v.self_position = self_position, v.bot = bot;
  v.held.clear();
  v.held.reserve(view.size());
  for (const auto& [id, e] : view.entities()) {
    v.held.push_back({id, e.state.visibility_class, e.state.position.x, e.state.position.y, e.state.position.z, e.last_tick});
  }
  std::sort(v.held.begin(), v.held.end(), [](const held_entity& a, const held_entity& b) { return a.id < b.id; });
  // The truth of this tick is usually computed a few milliseconds after its frames arrive: then
  // the snapshot waits, and the bot goes on at once. Waiting snapshots whose truth has come are
  // checked by the next bots to call (a few each) and by the oracle's thread.
  drain_pending(false, 8);
  if (any_ready_.load(std::memory_order_acquire) && ready_tick_.load(std::memory_order_acquire) >= tick) {
    check_snapshot(v);
    return;
  }
  const std::size_t bytes = sizeof(view_snapshot) + v.held.size() * sizeof(held_entity);
  std::lock_guard lock(pending_mutex_);
  if (pending_bytes_ + bytes > max_pending_bytes || ended_.load()) {
    pending_overflow_.fetch_add(1, std::memory_order_relaxed);
    c_.frames_unchecked.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  pending_bytes_ += bytes;
  pending_.push_back(v);
}

void oracle::catch_up(double timeout_s) {
  const std::uint64_t want = newest_checked_tick_.load();
  std::unique_lock lock(ready_mutex_);
  ready_cv_.wait_for(lock, std::chrono::duration<double>(timeout_s),
                     [&] { return (any_ready_.load() && ready_tick_.load() >= want) || ended_.load(); });
}

void oracle::drain_pending(bool all, std::size_t max_jobs) {
  // Oldest first, a few at a time, checked outside the lock (bots' threads and the oracle's
  // thread drain at once).
  std::vector<view_snapshot> batch;
  for (std::size_t done = 0; done < max_jobs;) {
    batch.clear();
    {
      std::lock_guard lock(pending_mutex_);
      const std::uint64_t ready = ready_tick_.load();
      const bool any = any_ready_.load();
      while (!pending_.empty() && batch.size() < 16 && (all || (any && pending_.front().tick <= ready))) {
        pending_bytes_ -= sizeof(view_snapshot) + pending_.front().held.size() * sizeof(held_entity);
        batch.push_back(std::move(pending_.front()));
        pending_.pop_front();
      }
    }
    if (batch.empty()) return;
    for (const auto& v : batch) check_snapshot(v);
    deferred_checks_.fetch_add(batch.size(), std::memory_order_relaxed);
    done += batch.size();
  }
}

void oracle::check_snapshot(const view_snapshot& v) {
  const auto t0 = std::chrono::steady_clock::now();
  const std::uint64_t tick = v.tick;
  const std::uint32_t observer = v.observer;
  const tick_truth& now = *ring_[tick % ring_ticks];
  std::shared_lock lock(now.mutex);
  const std::uint32_t oi = now.valid && now.tick == tick ? now.find(observer) : npos32;
  if (oi == npos32 || now.obs_known[oi] == 0) {
    c_.frames_unchecked.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  const layout& lay = *now.lay;
  const std::span<const std::uint32_t> truth = now.set(oi);
  const std::span<const std::uint32_t> truth_dense = now.set_dense(oi);
  const std::uint32_t self = lay.dense_of(observer);
  const float* eye = now.pos.data() + 3 * self;
  const std::uint32_t sees = lay.sees[self];
  const auto& deferred = v.deferred;
  const auto who = [&] {
    return "tick " + std::to_string(tick) + ", bot " + std::to_string(v.bot) + " (entity " + std::to_string(observer) + ")";
  };
  const auto distance_to = [&](std::uint32_t dense) {
    return dense == npos32 ? -1.0 : std::sqrt(static_cast<double>(dist2(eye, now.pos.data() + 3 * dense)));
  };
  const auto entity_line = [&](std::uint32_t id) {
    const std::uint32_t d = lay.dense_of(id);
    char dist[48];
    std::snprintf(dist, sizeof dist, "%.2f m", distance_to(d));
    return "entity " + std::to_string(id) + " at " + (d == npos32 ? std::string("(gone)") : std::string(dist)) +
           (d == npos32 ? std::string() : ", class " + std::to_string(lay.classes[d]));
  };

  // Own position: exact.
  if (const auto& sp = v.self_position; sp && (sp->x != eye[0] || sp->y != eye[1] || sp->z != eye[2])) {
    c_.position.fetch_add(1, std::memory_order_relaxed);
    log("position", logged_position_,
        who() + ": its own position is (" + std::to_string(sp->x) + ", " + std::to_string(sp->y) + ", " +
            std::to_string(sp->z) + "), the truth (" + std::to_string(eye[0]) + ", " + std::to_string(eye[1]) + ", " +
            std::to_string(eye[2]) + ")");
  }

  const float near = rules_.update_near, mid = rules_.update_mid;
  const std::uint32_t mid_period = std::max<std::uint32_t>(1, rules_.update_mid_period);
  const std::uint32_t far_period = std::max<std::uint32_t>(1, rules_.update_far_period);
  std::uint64_t missing = 0, extra = 0, leaked = 0;
  std::uint32_t first_missing = 0, first_extra = 0, first_leak = 0;
  std::uint64_t due_unsent = 0, due_maybe = 0, checked = 0, pos_checked = 0, pos_unchecked = 0;
  // Slots of earlier ticks (positions last sent then), locked once each.
  struct earlier {
    std::uint64_t tick;
    const tick_truth* slot;
  };
  thread_local std::vector<earlier> seen;
  thread_local std::vector<std::shared_lock<std::shared_mutex>> locks;
  seen.clear();
  locks.clear();
  const auto truth_at = [&](std::uint64_t t) -> const tick_truth* {
    if (t == tick) return &now;
    for (const auto& e : seen) {
      if (e.tick == t) return e.slot;
    }
    const tick_truth* s = ring_[t % ring_ticks].get();
    if (s == &now) return nullptr;  // this tick's slot: the tick asked for is gone
    locks.emplace_back(s->mutex);
    if (!s->valid || s->tick != t) s = nullptr;
    seen.push_back({t, s});
    return s;
  };

  // The visible set and the held entities, both by ascending id, side by side.
  std::size_t i = 0, j = 0;
  while (i < truth.size() || j < v.held.size()) {
    if (j == v.held.size() || (i < truth.size() && truth[i] < v.held[j].id)) {
      if (missing++ == 0) first_missing = truth[i];  // visible, not held
      ++i;
      continue;
    }
    if (i == truth.size() || v.held[j].id < truth[i]) {
      // Held, not visible: a leak when of a class the observer does not see.
      const std::uint32_t id = v.held[j].id;
      const std::uint32_t d = lay.dense_of(id);
      if (d != npos32 && (lay.classes[d] & sees) == 0) {
        if (leaked++ == 0) first_leak = id;
      } else if (extra++ == 0) {
        first_extra = id;
      }
      ++j;
      continue;
    }
    // Held and visible: its class, its position, and whether an update was due.
    const held_entity& e = v.held[j];
    const std::uint32_t id = e.id;
    const std::uint32_t d = truth_dense[i];
    ++i, ++j, ++checked;
    if (e.visibility_class != lay.classes[d]) {
      c_.wrong_class.fetch_add(1, std::memory_order_relaxed);
      log("class", logged_class_, who() + ": " + entity_line(id) + " is held with class " + std::to_string(e.visibility_class));
    }
    const tick_truth* at = e.last_tick <= tick && tick - e.last_tick < ring_ticks ? truth_at(e.last_tick) : nullptr;
    if (at == nullptr) {
      ++pos_unchecked;
    } else {
      ++pos_checked;
      const std::uint32_t dl = at->lay == now.lay ? d : at->lay->dense_of(id);  // same layout: same index
      const float* p = dl == npos32 ? nullptr : at->pos.data() + 3 * dl;
      if (p == nullptr || std::fabs(e.x - p[0]) > tolerance_.x || std::fabs(e.y - p[1]) > tolerance_.y ||
          std::fabs(e.z - p[2]) > tolerance_.z) {
        c_.position.fetch_add(1, std::memory_order_relaxed);
        char line[200];
        if (p != nullptr) {
          std::snprintf(line, sizeof line, " is held at (%.3f, %.3f, %.3f), sent at tick %llu when it was at (%.3f, %.3f, %.3f)",
                        e.x, e.y, e.z, static_cast<unsigned long long>(e.last_tick), p[0], p[1], p[2]);
        } else {
          std::snprintf(line, sizeof line, " did not exist at tick %llu when it was last sent",
                        static_cast<unsigned long long>(e.last_tick));
        }
        log("position", logged_position_, who() + ": " + entity_line(id) + line);
      }
    }
    // Due by its tier (from this tick's distance) but not sent in this frame.
    if (e.last_tick < tick) {
      const float r = std::sqrt(dist2(eye, now.pos.data() + 3 * d));
      const std::uint64_t age = tick - e.last_tick;
      const auto period_for = [&](float dist) { return dist < near ? 1u : dist < mid ? mid_period : far_period; };
      // Near a tier boundary the server's rounding may decide either way.
      const bool boundary =
          std::fabs(r - near) <= 1e-4f * std::max(1.0f, near) || std::fabs(r - mid) <= 1e-4f * std::max(1.0f, mid);
      if (age >= period_for(r)) {
        ++due_unsent;
      } else if (boundary && (age >= period_for(r * (1 - 2e-4f)) || age >= period_for(r * (1 + 2e-4f)))) {
        ++due_maybe;
      }
    }
  }

  if (missing > deferred.enters) {
    c_.missing.fetch_add(missing - deferred.enters, std::memory_order_relaxed);
    log("missing", logged_missing_,
        who() + ": " + std::to_string(missing) + " visible entities not held, the frame deferred " +
            std::to_string(deferred.enters) + " enters; first " + entity_line(first_missing));
  }
  if (leaked > 0) {
    c_.leaked.fetch_add(leaked, std::memory_order_relaxed);
    log("leak", logged_leaked_,
        who() + ": holds " + std::to_string(leaked) + " entities of classes it does not see (sees " + std::to_string(sees) +
            "); first " + entity_line(first_leak));
  }
  if (extra > deferred.leaves) {
    c_.extra.fetch_add(extra - deferred.leaves, std::memory_order_relaxed);
    log("extra", logged_extra_,
        who() + ": holds " + std::to_string(extra) + " entities that are not visible, the frame deferred " +
            std::to_string(deferred.leaves) + " leaves; first " + entity_line(first_extra));
  }
  if (missing < deferred.enters || extra + leaked < deferred.leaves) {
    c_.deferral.fetch_add(1, std::memory_order_relaxed);
    log("deferral", logged_deferral_,
        who() + ": the frame deferred " + std::to_string(deferred.enters) + " enters and " +
            std::to_string(deferred.leaves) + " leaves, but " + std::to_string(missing) + " were missing and " +
            std::to_string(extra + leaked) + " extra");
  }
  if (deferred.updates < due_unsent || deferred.updates > due_unsent + due_maybe) {
    const bool stale = deferred.updates < due_unsent;
    (stale ? c_.stale : c_.deferral).fetch_add(stale ? due_unsent - deferred.updates : 1, std::memory_order_relaxed);
    log(stale ? "stale" : "deferral", stale ? logged_stale_ : logged_deferral_,
        who() + ": " + std::to_string(due_unsent) + " held entities were due an update and got none (" +
            std::to_string(due_maybe) + " more at a tier boundary), the frame deferred " +
            std::to_string(deferred.updates) + " updates");
  }
  locks.clear();  // the earlier ticks' slots, released
  c_.frames_checked.fetch_add(1, std::memory_order_relaxed);
  c_.entities_checked.fetch_add(checked, std::memory_order_relaxed);
  c_.positions_checked.fetch_add(pos_checked, std::memory_order_relaxed);
  if (pos_unchecked != 0) c_.positions_unchecked.fetch_add(pos_unchecked, std::memory_order_relaxed);
  check_ns_.fetch_add(static_cast<std::uint64_t>(
                          std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now() - t0).count()),
                      std::memory_order_relaxed);
}

oracle_report oracle::report() const {
  oracle_report r;
  r.frames_checked = c_.frames_checked, r.frames_unchecked = c_.frames_unchecked, r.entities_checked = c_.entities_checked;
  r.positions_checked = c_.positions_checked, r.positions_unchecked = c_.positions_unchecked;
  r.missing = c_.missing, r.extra = c_.extra, r.leaked = c_.leaked, r.wrong_class = c_.wrong_class;
  r.position = c_.position, r.stale = c_.stale, r.deferral = c_.deferral;
  r.truth_ticks = truth_ticks_, r.truth_bytes = truth_bytes_;
  r.truth_layouts = truth_layouts_, r.truth_changes = truth_changes_;
  r.compute_cpu_ms = compute_cpu_ms_ - drain_cpu_ms_, r.compute_max_ms = compute_max_ms_;
  r.drain_cpu_ms = drain_cpu_ms_;
  r.check_ms = static_cast<double>(check_ns_.load()) / 1e6;
  r.deferred_checks = deferred_checks_.load();
  r.pending_overflow = pending_overflow_.load();
  r.observers_max = observers_max_;
  std::lock_guard lock(ready_mutex_);
  r.stream_error = stream_error_;
  return r;
}

}  // namespace zone::bots
