// The oracle (oracle.h): ground truth in, every (sampled) player's visible set recomputed from it,
// every (sampled) bot's view compared with it.
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
#include <functional>
#include <limits>

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

/// One tick's layout (every entity's id, class, mask, kind and boxes, by dense index), shared
/// with the ticks around it rather than copied: the ids and their map by the layouts of equal
/// ids (changes keep them), the other columns in chunks of `chunk_size` entities by every layout
/// whose chunk holds equal values (changes copy only the chunks they touch; a whole layout keeps
/// each chunk that equals the last layout's). Nothing shared is written after it is published:
/// earlier ticks' truth keeps reading its own layout.
struct oracle::layout {
  static constexpr unsigned chunk_shift = 9;
  static constexpr std::uint32_t chunk_size = 1u << chunk_shift;
  struct ids_part {
    std::vector<std::uint32_t> ids;
    net::id_map<std::uint32_t> dense;  // id -> dense index
  };
  struct chunk {
    std::uint32_t count = 0;  // entities in it (chunk_size but in the last)
    std::uint32_t classes[chunk_size], sees[chunk_size];
    float aoi[3 * chunk_size], presence[3 * chunk_size];
    std::uint8_t kinds[chunk_size];
    /// Rows [first, first + count) of the frame's columns.
    void fill(const net::truth::tick_frame& f, std::size_t first) {
      count = static_cast<std::uint32_t>(std::min<std::size_t>(chunk_size, f.count - first));
      std::copy_n(f.classes.begin() + first, count, classes);
      std::copy_n(f.sees.begin() + first, count, sees);
      std::copy_n(f.kinds.begin() + first, count, kinds);
      std::copy_n(f.aoi_half.begin() + 3 * first, 3 * count, aoi);
      std::copy_n(f.presence_half.begin() + 3 * first, 3 * count, presence);
    }
    [[nodiscard]] bool equals(const net::truth::tick_frame& f, std::size_t first) const {
      const std::size_t n = std::min<std::size_t>(chunk_size, f.count - first);
      return count == n && std::equal(classes, classes + n, f.classes.begin() + first) &&
             std::equal(sees, sees + n, f.sees.begin() + first) &&
             std::equal(kinds, kinds + n, f.kinds.begin() + first) &&
             std::memcmp(aoi, f.aoi_half.data() + 3 * first, 3 * n * sizeof(float)) == 0 &&
             std::memcmp(presence, f.presence_half.data() + 3 * first, 3 * n * sizeof(float)) == 0;
    }
  };
  std::shared_ptr<const ids_part> idp;
  std::vector<std::shared_ptr<const chunk>> chunks;
  std::vector<std::uint32_t> observers;        // dense indices of the sampled players
  std::vector<std::uint32_t> observers_by_id;  // indices into observers, by ascending id
  std::size_t players = 0;                     // every player, sampled or not
  // Layouts of one lineage only ever appended entities to the ids of the one before (changes keep
  // them): an entity has the same dense index in each that holds it (within its count).
  std::uint64_t lineage = 0;

  [[nodiscard]] std::size_t size() const { return idp->ids.size(); }
  [[nodiscard]] std::uint32_t id(std::uint32_t k) const { return idp->ids[k]; }
  [[nodiscard]] const chunk& at(std::uint32_t k) const { return *chunks[k >> chunk_shift]; }
  [[nodiscard]] const std::uint32_t& cls(std::uint32_t k) const { return at(k).classes[k & (chunk_size - 1)]; }
  [[nodiscard]] std::uint32_t sees(std::uint32_t k) const { return at(k).sees[k & (chunk_size - 1)]; }
  [[nodiscard]] std::uint8_t kind(std::uint32_t k) const { return at(k).kinds[k & (chunk_size - 1)]; }
  [[nodiscard]] const float* aoi(std::uint32_t k) const { return at(k).aoi + 3 * (k & (chunk_size - 1)); }
  [[nodiscard]] const float* presence(std::uint32_t k) const { return at(k).presence + 3 * (k & (chunk_size - 1)); }
  [[nodiscard]] std::uint32_t dense_of(std::uint32_t id) const {
    const auto it = idp->dense.find(id);
    return it == idp->dense.end() ? npos32 : it->second;
  }

  /// The whole layout of `f`, sharing with `prev` (nullptr: none) what equals it. Whether its ids
  /// extend prev's (the same, or prev's with more appended: every entity of prev keeps its dense
  /// index).
  bool build(const net::truth::tick_frame& f, const layout* prev) {
    const std::size_t n = f.count;
    const ids_part* before = prev != nullptr ? prev->idp.get() : nullptr;
    bool extends = false;
    if (before != nullptr && before->ids == f.ids) {
      idp = prev->idp;
      extends = true;
    } else {
      auto p = std::make_shared<ids_part>();
      std::size_t k0 = 0;
      if (before != nullptr && before->ids.size() <= n &&
          std::equal(before->ids.begin(), before->ids.end(), f.ids.begin())) {
        p->dense = before->dense;  // appended to: the map is copied whole, the new ids added
        k0 = before->ids.size();
        extends = true;
      }
      p->ids.assign(f.ids.begin(), f.ids.end());
      for (std::size_t k = k0; k < n; ++k) p->dense.try_emplace(f.ids[k]).first->second = static_cast<std::uint32_t>(k);
      idp = std::move(p);
    }
    chunks.resize((n + chunk_size - 1) >> chunk_shift);
    for (std::size_t c = 0; c < chunks.size(); ++c) {
      const std::size_t first = c << chunk_shift;
      if (prev != nullptr && c < prev->chunks.size() && prev->chunks[c]->equals(f, first)) {
        chunks[c] = prev->chunks[c];
      } else {
        auto ch = std::make_shared<chunk>();
        ch->fill(f, first);
        chunks[c] = std::move(ch);
      }
    }
    return extends;
  }
  /// Rows `f.changed` replaced by the frame's (the decoder applied them to its columns): the
  /// chunks they fall in copied first. Whether a kind changed.
  bool patch(const net::truth::tick_frame& f) {
    bool kinds_changed = false;
    std::size_t copied = ~std::size_t{0};  // the chunk last copied (changed rows ascend)
    chunk* w = nullptr;
    for (const std::uint32_t k : f.changed) {
      const std::size_t c = k >> chunk_shift;
      if (c != copied) {
        auto ch = std::make_shared<chunk>(*chunks[c]);
        w = ch.get();
        chunks[c] = std::move(ch);
        copied = c;
      }
      const std::uint32_t r = k & (chunk_size - 1);
      w->classes[r] = f.classes[k];
      w->sees[r] = f.sees[k];
      kinds_changed |= w->kinds[r] != f.kinds[k];
      w->kinds[r] = f.kinds[k];
      std::copy_n(f.aoi_half.begin() + 3 * k, 3, w->aoi + 3 * r);
      std::copy_n(f.presence_half.begin() + 3 * k, 3, w->presence + 3 * r);
    }
    return kinds_changed;
  }
  void find_observers(unsigned sample) {
    observers.clear();
    players = 0;
    for (std::uint32_t k = 0; k < size(); ++k) {
      if (kind(k) != static_cast<std::uint8_t>(net::entity_kind::player)) continue;
      ++players;
      if (oracle::sampled(id(k), sample)) observers.push_back(k);
    }
    observers_by_id.resize(observers.size());
    for (std::uint32_t i = 0; i < observers.size(); ++i) observers_by_id[i] = i;
    std::sort(observers_by_id.begin(), observers_by_id.end(),
              [&](std::uint32_t x, std::uint32_t y) { return id(observers[x]) < id(observers[y]); });
  }
};

/// One recompute thread's scratch, kept from tick to tick.
struct oracle::scratch {
  std::vector<std::uint8_t> flags;  // candidate flags of one run of slots
  std::vector<std::uint32_t> mark;  // by dense index: in the observer's last set (stamp + 1), and stayed (+ 2)
  std::uint32_t stamp = 0;
  std::vector<std::uint32_t> before;  // the last set's dense indices in this tick's layout
  std::vector<std::uint64_t> fresh, keys;
  std::vector<std::pair<std::size_t, std::size_t>> ranges;  // runs of slots [first, last) to test
  std::vector<std::uint64_t> out;                   // the set of the observer being scanned
  std::vector<std::vector<std::uint64_t>> blocks;  // the sets this thread stored this tick
  std::vector<std::uint64_t> carried;              // a carried set as (id << 32)
};

/// The targets of one tick as the scans read them: presence boxes (position -+ half-extent, the
/// server's float expressions) and classes in columns, in slot order, and which slots an
/// observer's scan must test. The index only leaves targets out; every target it gives is tested
/// exactly (candidate_flags), so it decides how much work a scan is, never its result.
struct oracle::index {
  /// A position's x as the x order takes it: a NaN (a malformed truth) as +infinity, so that it
  /// sorts last, the comparison stays a strict weak order (std::sort's requirement), and no
  /// window, whose bounds are finite, reaches it.
  static float ordered_x(float x) { return std::isnan(x) ? std::numeric_limits<float>::infinity() : x; }
  std::vector<float> blo_x, blo_y, blo_z, bhi_x, bhi_y, bhi_z, px;
  std::vector<std::uint32_t> cls, dense;  // slot -> class, dense index
  scan_mode mode = scan_mode::grid;
  std::size_t n = 0;
  float max_half_x = 0;  // x_window: the largest presence half-extent in x
  // grid: cells of side `cell` from (origin_x, origin_y), row-major, so that one row's run of
  // cells is one run of slots; slots [wide_first, n) hold the targets outside it (a presence box
  // wider than a cell, or a position not finite), tested by every observer.
  double origin_x = 0, origin_y = 0, cell = 1;
  std::uint32_t cols = 1, rows = 1;
  std::size_t wide_first = 0;
  double reach = 0;                  // the gridded targets' largest presence half-extent in x or y
  double max_abs = 0;                // their largest |coordinate| (for the rounding slack)
  std::vector<std::uint32_t> start;  // cols * rows + 1
  std::vector<std::uint32_t> cell_of, order;
  // The sampled observers (indices into the layout's observers) in slot order: consecutive scans
  // read the same cells (in cache) and mark the same targets. By dense index: its observer index.
  std::vector<std::uint32_t> scan_order, observer_of;

  void order_observers(const std::vector<std::uint32_t>& observers) {
    observer_of.assign(n, npos32);
    for (std::uint32_t i = 0; i < observers.size(); ++i) observer_of[observers[i]] = i;
    scan_order.clear();
    for (std::size_t s = 0; s < n; ++s) {
      if (const std::uint32_t i = observer_of[order[s]]; i != npos32) scan_order.push_back(i);
    }
  }

  void put(std::size_t s, std::uint32_t k, const float* pos, const layout& lay) {
    const float* p = pos + 3 * k;
    const float* hx = lay.presence(k);
    blo_x[s] = p[0] - hx[0], blo_y[s] = p[1] - hx[1], blo_z[s] = p[2] - hx[2];
    bhi_x[s] = p[0] + hx[0], bhi_y[s] = p[1] + hx[1], bhi_z[s] = p[2] + hx[2];
    px[s] = ordered_x(p[0]);
    cls[s] = lay.cls(k);
    dense[s] = k;
  }
  [[nodiscard]] std::uint32_t col(double x) const {
    const double q = (x - origin_x) / cell;  // monotone in x: a position within a range is in its cells
    return !(q >= 0) ? 0u : q >= cols ? cols - 1 : static_cast<std::uint32_t>(q);
  }
  [[nodiscard]] std::uint32_t row(double y) const {
    const double q = (y - origin_y) / cell;
    return !(q >= 0) ? 0u : q >= rows ? rows - 1 : static_cast<std::uint32_t>(q);
  }

  void build(const float* pos, const layout& lay, std::size_t count, scan_mode m, float cell_side) {
    mode = m;
    n = count;
    for (auto* v : {&blo_x, &blo_y, &blo_z, &bhi_x, &bhi_y, &bhi_z, &px}) v->resize(n);
    cls.resize(n);
    dense.resize(n);
    order.resize(n);
    if (m != scan_mode::grid) {
      // By ascending x of the position (x_window searches it; full reads every slot).
      for (std::size_t k = 0; k < n; ++k) order[k] = static_cast<std::uint32_t>(k);
      const auto x_of = [&](std::uint32_t k) { return ordered_x(pos[3 * k]); };
      std::sort(order.begin(), order.end(),
                [&](std::uint32_t x, std::uint32_t y) { return x_of(x) < x_of(y) || (x_of(x) == x_of(y) && x < y); });
      max_half_x = 0;
      for (std::size_t s = 0; s < n; ++s) {
        put(s, order[s], pos, lay);
        max_half_x = std::max(max_half_x, lay.presence(order[s])[0]);
      }
      return;
    }
    cell = std::isfinite(cell_side) && cell_side > 0.01f ? cell_side : 0.01;
    // Which targets are gridded is decided by the cell asked for, not the one it grows to below:
    // the bounds and the reach are taken over the same targets that go into the cells.
    const double first_cell = cell;
    const auto gridded = [&](std::size_t k) {
      const float* p = pos + 3 * k;
      const float* hx = lay.presence(static_cast<std::uint32_t>(k));
      return std::isfinite(p[0]) && std::isfinite(p[1]) && hx[0] <= first_cell && hx[1] <= first_cell;
    };
    double lo_x = 0, lo_y = 0, hi_x = 0, hi_y = 0;
    bool any = false;
    reach = 0, max_abs = 0;
    for (std::size_t k = 0; k < n; ++k) {
      if (!gridded(k)) continue;
      const double x = pos[3 * k], y = pos[3 * k + 1];
      if (!any) lo_x = hi_x = x, lo_y = hi_y = y, any = true;
      lo_x = std::min(lo_x, x), hi_x = std::max(hi_x, x), lo_y = std::min(lo_y, y), hi_y = std::max(hi_y, y);
      const float* hx = lay.presence(static_cast<std::uint32_t>(k));
      reach = std::max<double>(reach, std::max(hx[0], hx[1]));
    }
    max_abs = std::max({std::fabs(lo_x), std::fabs(hi_x), std::fabs(lo_y), std::fabs(hi_y)});
    origin_x = lo_x, origin_y = lo_y;
    // At most 4 cells per target (and 4M in all): a sparse world gets larger cells.
    const double max_cells = std::min(4.0 * static_cast<double>(n) + 1024, 4194304.0);
    for (;;) {
      const double c = std::floor((hi_x - lo_x) / cell) + 1, r = std::floor((hi_y - lo_y) / cell) + 1;
      if (c * r <= max_cells) {
        cols = static_cast<std::uint32_t>(c), rows = static_cast<std::uint32_t>(r);
        break;
      }
      cell *= std::max(1.1, std::sqrt(c * r / max_cells));
    }
    // A counting sort by cell (stable: by dense index within a cell); the wide ones last.
    const std::size_t cells = std::size_t{cols} * rows;
    start.assign(cells + 2, 0);
    cell_of.resize(n);
    for (std::size_t k = 0; k < n; ++k) {
      cell_of[k] = gridded(k) ? row(pos[3 * k + 1]) * cols + col(pos[3 * k]) : static_cast<std::uint32_t>(cells);
      ++start[cell_of[k] + 1];
    }
    for (std::size_t c = 0; c <= cells; ++c) start[c + 1] += start[c];
    wide_first = start[cells];
    for (std::size_t k = 0; k < n; ++k) order[start[cell_of[k]]++] = static_cast<std::uint32_t>(k);
    for (std::size_t c = cells + 1; c-- > 1;) start[c] = start[c - 1];  // back to the cells' starts
    start[0] = 0;
    for (std::size_t s = 0; s < n; ++s) put(s, order[s], pos, lay);
  }

  /// Calls f(first, last) for each run of slots an observer at `p` with grown AOI half-extents
  /// (gx, gy) must test: every target whose presence box can meet its grown box is in one.
  template <class F>
  void for_each_range(const float* p, float gx, float gy, F&& f) const {
    if (mode == scan_mode::full) {
      f(0, n);
      return;
    }
    if (mode == scan_mode::x_window) {
      // Farther on x than the grown AOI plus the largest presence half-extent plus 1 m (any
      // rounding of the box bounds): cannot meet.
      const float r = gx + max_half_x + 1;
      const float* b = px.data();
      f(static_cast<std::size_t>(std::lower_bound(b, b + n, p[0] - r) - b),
        static_cast<std::size_t>(std::upper_bound(b, b + n, p[0] + r) - b));
      return;
    }
    // A target meets the grown box on x only if its position is within gx + its half-extent of
    // the observer's, up to the rounding of the float bounds (1 m plus 1e-6 of the magnitudes
    // covers it many times over); likewise on y.
    const double slack_x = 1 + 1e-6 * (std::fabs(static_cast<double>(p[0])) + gx + max_abs + reach);
    const double slack_y = 1 + 1e-6 * (std::fabs(static_cast<double>(p[1])) + gy + max_abs + reach);
    const double rx = static_cast<double>(gx) + reach + slack_x, ry = static_cast<double>(gy) + reach + slack_y;
    const std::uint32_t c0 = col(p[0] - rx), c1 = col(p[0] + rx), r0 = row(p[1] - ry), r1 = row(p[1] + ry);
    if (wide_first != 0) {
      for (std::uint32_t r = r0; r <= r1; ++r)
        f(start[std::size_t{r} * cols + c0], start[std::size_t{r} * cols + c1 + 1]);
    }
    if (wide_first < n) f(wide_first, n);
  }
};

struct oracle::tick_truth {
  mutable std::shared_mutex mutex;
  bool valid = false;
  std::uint64_t tick = 0;
  std::shared_ptr<const layout> lay;
  std::vector<float> pos;                  // 3 per entity
  std::vector<std::uint32_t> obs_ids;      // the sampled observers (players), ascending
  std::vector<std::uint32_t> obs_at;       // beside obs_ids: its observer index (in lay->observers)
  std::vector<std::uint8_t> obs_known;     // beside obs_ids: whole history seen (else not checked)
  // Each observer's visible set, ascending: (id << 32) | its dense index in lay, by observer index
  // (with whether its whole history was seen). The sets lie in `blocks` (set_block entries each
  // but for a larger set's own), handed over from the recompute whole; the blocks of the tick
  // this slot held before go back to the recompute's pool.
  std::vector<set_at> sets;
  std::vector<std::uint8_t> known;
  std::vector<std::vector<std::uint64_t>> blocks;
  [[nodiscard]] std::uint32_t find(std::uint32_t observer) const {
    const auto it = std::lower_bound(obs_ids.begin(), obs_ids.end(), observer);
    return it != obs_ids.end() && *it == observer ? static_cast<std::uint32_t>(it - obs_ids.begin()) : npos32;
  }
  /// The set of the observer of rank `r` (by id; find()).
  [[nodiscard]] std::span<const std::uint64_t> set(std::uint32_t r) const { return of(obs_at[r]); }
  /// The set of observer `i` of lay->observers.
  [[nodiscard]] std::span<const std::uint64_t> of(std::uint32_t i) const { return {sets[i].data, sets[i].size}; }
};

oracle::oracle(const net::world_bounds& world, const net::interest_rules& rules, unsigned threads, problem_fn problem,
               void* ctx)
    : world_(world), rules_(rules), problem_(problem), ctx_(ctx) {
  const net::vec3f e = net::position_quantizer(world).max_error();
  // The quantizer's guaranteed error plus a little for the float arithmetic of dequantizing.
  tolerance_ = {e.x * 1.01f + 1e-4f, e.y * 1.01f + 1e-4f, e.z * 1.01f + 1e-4f};
  threads_ = threads != 0 ? threads : std::max(1u, std::thread::hardware_concurrency() / 8);
  for (std::size_t i = 0; i < ring_ticks; ++i) ring_.push_back(std::make_unique<tick_truth>());
  for (unsigned t = 0; t < threads_; ++t) scratch_.push_back(std::make_unique<scratch>());
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
    // Read under the lock: on a timeout the reading thread still runs and may set it.
    const std::string why = stream_error_.empty() ? "no tick within " + std::to_string(timeout_s) + " s" : stream_error_;
    lock.unlock();
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
  decode_ms_ += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  if (frame_.has_layout) ++truth_layouts_;
  if (frame_.has_changes) ++truth_changes_;
  if (!frame_.has_layout && !layout_) return std::string("the first truth frame has no layout");
  if (auto err = compute(frame_)) {
    frame_.layout_known = false;  // the decoder's layout was not taken: no frame may apply to it
    return err;
  }
  ++truth_ticks_;
  compute_cpu_ms_ += thread_cpu_ms() - cpu0;
  compute_max_ms_ = std::max(compute_max_ms_, std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());
  return std::nullopt;
}

std::optional<std::string> oracle::compute(const net::truth::tick_frame& f) {
  auto t0 = std::chrono::steady_clock::now();
  const auto lap = [&t0](double& sum) {
    const auto t1 = std::chrono::steady_clock::now();
    sum += std::chrono::duration<double, std::milli>(t1 - t0).count();
    t0 = t1;
  };
  if (f.has_layout) {
    auto l = std::make_shared<layout>();
    const bool extends = l->build(f, layout_.get());
    if (l->idp->dense.size() != l->size()) {  // an id on two rows: no truth to check views by
      return "truth frame of tick " + std::to_string(f.tick) + ": its layout names an id twice";
    }
    l->find_observers(sample);
    l->lineage = extends ? layout_->lineage : next_lineage_++;
    layout_ = std::move(l);
  } else if (f.has_changes) {
    // The same entities, some rows replaced: a new layout (earlier ticks' truth keeps the one it
    // had) sharing the ids and every chunk the changes do not touch.
    auto l = std::make_shared<layout>(*layout_);
    if (l->patch(f)) l->find_observers(sample);
    layout_ = std::move(l);
  }
  const layout& lay = *layout_;
  const std::size_t n = f.count;
  const float* pos = f.positions.data();
  const float h = rules_.hysteresis;
  const std::uint32_t cap = rules_.max_visible;
  const std::size_t obs = lay.observers.size();
  observers_max_ = std::max<std::uint64_t>(observers_max_, lay.players);
  sampled_max_ = std::max<std::uint64_t>(sampled_max_, obs);

  // The targets' boxes (position -+ presence half-extent, the server's float expressions) in scan
  // order, and the index each scan reads: slot order by x (x_window, full) or by grid cell.
  if (!index_) index_ = std::make_unique<index>();
  index& ix = *index_;
  // The grid's cell: half the observers' mean grown AOI half-extent (a query then spans about 5
  // cells a side, and tests about 1.5 times the targets its grown box holds).
  double reach_sum = 0;
  std::size_t reaches = 0;
  for (const std::uint32_t a : lay.observers) {
    const double r = std::max(lay.aoi(a)[0], lay.aoi(a)[1]) + h;
    if (std::isfinite(r)) reach_sum += r, ++reaches;
  }
  const float mean_reach = reaches != 0 ? static_cast<float>(reach_sum / static_cast<double>(reaches)) : 64.0f;
  ix.build(pos, lay, n, scan, grid_cell > 0 ? grid_cell : mean_reach / 2);
  ix.order_observers(lay.observers);
  lap(index_ms_);

  // The previous tick's sets (the hysteresis): only when it is the tick just before this one.
  const tick_truth* prev = nullptr;
  if (any_tick_ && prev_tick_ + 1 == f.tick) {
    const tick_truth& p = *ring_[(f.tick - 1) % ring_ticks];
    if (p.valid && p.tick == f.tick - 1) prev = &p;
  }
  sets_.assign(obs, set_at{});
  known_.assign(obs, 0);

  // Where last tick's sets name an entity by its dense index in this tick's layout too: the same
  // layout, or one that only appended entities to it.
  const bool prev_dense_same = prev != nullptr && prev->lay->lineage == lay.lineage;
  // The same layout (a tick of positions only): the same observers, by the same index.
  const bool prev_same_layout = prev != nullptr && prev->lay.get() == &lay;

  // A set into this thread's last block (another from the pool when it has no room): never moved
  // once written, so that the span published for it stays valid.
  const auto store = [&](scratch& sc, const std::vector<std::uint64_t>& set) -> set_at {
    if (set.empty()) return {};
    if (sc.blocks.empty() || sc.blocks.back().capacity() - sc.blocks.back().size() < set.size()) {
      std::vector<std::uint64_t> b;
      {
        std::lock_guard lock(blocks_mutex_);
        if (!free_blocks_.empty()) b = std::move(free_blocks_.back()), free_blocks_.pop_back();
      }
      b.clear();
      const std::size_t want = std::max(set_block, set.size());
      if (b.capacity() < want) b = std::vector<std::uint64_t>(), b.reserve(want);
      sc.blocks.push_back(std::move(b));  // the blocks before keep their storage (moved, not copied)
    }
    std::vector<std::uint64_t>& b = sc.blocks.back();
    const std::uint64_t* at = b.data() + b.size();
    b.insert(b.end(), set.begin(), set.end());
    return {at, set.size()};
  };

  // The observers whose previous set this tick's step took from a handoff (net/truth.h): their
  // targets as the server was given them, ascending.
  const auto carried_of = [&](std::uint32_t id) -> std::optional<std::span<const std::uint32_t>> {
    const auto& obs_ids = f.carried_observers;
    const auto it = std::lower_bound(obs_ids.begin(), obs_ids.end(), id);
    if (it == obs_ids.end() || *it != id) return std::nullopt;
    const auto k = static_cast<std::size_t>(it - obs_ids.begin());
    return std::span<const std::uint32_t>(f.carried_targets)
        .subspan(f.carried_off[k], f.carried_off[k + 1] - f.carried_off[k]);
  };

  const auto observe = [&](scratch& sc, std::size_t i) {
    const std::uint32_t a = lay.observers[i];
    const std::uint32_t id = lay.id(a);
    std::vector<std::uint64_t>& out = sc.out;  // (id << 32) | dense index
    out.clear();
    // History: a new entity starts from an empty set; one seen last tick continues from its set
    // there; any other (present before the stream began, or after a gap) is not checked. One the
    // server carried a set to this tick (a handoff) continues from that set; at the server's first
    // step every one starts from an empty set (net/truth.h).
    std::span<const std::uint64_t> before;  // (id << 32) | dense index in prev's layout
    bool is_known = false;
    const auto carried = carried_of(id);
    if (carried) {
      sc.carried.clear();
      for (const std::uint32_t t : *carried) sc.carried.push_back(std::uint64_t{t} << 32);
      before = sc.carried;  // by id only: mapped to this layout below
      is_known = true;
    } else if (f.first_step) {
      is_known = true;  // no step before this one: its set starts empty
    } else if (prev_same_layout) {
      is_known = prev->known[i] != 0;
      before = prev->of(static_cast<std::uint32_t>(i));
    } else if (prev != nullptr) {
      const std::uint32_t j = prev->find(id);
      if (j != npos32) {
        is_known = prev->obs_known[j] != 0;
        before = prev->set(j);
      } else {
        is_known = prev->lay->dense_of(id) == npos32;
      }
    }
    known_[i] = is_known ? 1 : 0;
    // Last tick's set, marked by dense index in this tick's layout (an entity gone since cannot stay).
    if (sc.mark.size() < n) sc.mark.assign(n, 0), sc.stamp = 0;
    if (sc.stamp >= 0xfffffff0u) std::fill(sc.mark.begin(), sc.mark.end(), 0), sc.stamp = 0;
    const std::uint32_t in_before = sc.stamp + 1, kept = sc.stamp + 2;
    sc.stamp += 2;
    std::uint32_t* const mark = sc.mark.data();
    sc.before.resize(before.size());
    std::uint32_t* const before_dense = sc.before.data();
    if (prev_dense_same && !carried) {
      for (std::size_t b = 0; b < before.size(); ++b) {
        __builtin_prefetch(before.data() + std::min(b + 64, before.size() - 1));  // 8 lines on
        const auto d = static_cast<std::uint32_t>(before[b]);
        before_dense[b] = d;
        mark[d] = in_before;
      }
    } else {
      for (std::size_t b = 0; b < before.size(); ++b) {
        const std::uint32_t d = lay.dense_of(static_cast<std::uint32_t>(before[b] >> 32));
        before_dense[b] = d;
        if (d != npos32) mark[d] = in_before;
      }
    }
    const float* p = pos + 3 * a;
    const float* e = lay.aoi(a);
    // The same float expressions as the server's boxes: grown = p -+ (aoi + h), exact = p -+ aoi.
    const float gx = e[0] + h, gy = e[1] + h, gz = e[2] + h;
    const grown_box g{p[0] - gx, p[1] - gy, p[2] - gz, p[0] + gx, p[1] + gy, p[2] + gz};
    const float lo_x = p[0] - e[0], lo_y = p[1] - e[1], lo_z = p[2] - e[2];
    const float hi_x = p[0] + e[0], hi_y = p[1] + e[1], hi_z = p[2] + e[2];
    const std::uint32_t sees = lay.sees(a);
    // Every target in the ranges the index gives is tested exactly (the index only leaves out
    // targets whose boxes cannot meet the grown box). A candidate (its class seen, its presence
    // box meeting the grown AOI box) stays when it was visible last tick, and enters when its
    // presence box meets the exact AOI box.
    std::vector<std::uint8_t>& flags = sc.flags;
    const float *const blo_x = ix.blo_x.data(), *const blo_y = ix.blo_y.data(), *const blo_z = ix.blo_z.data();
    const float *const bhi_x = ix.bhi_x.data(), *const bhi_y = ix.bhi_y.data(), *const bhi_z = ix.bhi_z.data();
    const std::uint32_t* const dense = ix.dense.data();
    // The runs of slots first, then each tested here, where the loop's pointers and marks stay
    // in registers.
    sc.ranges.clear();
    ix.for_each_range(p, gx, gy, [&](std::size_t first_s, std::size_t last_s) {
      if (last_s > first_s) sc.ranges.emplace_back(first_s, last_s);
    });
    std::size_t entered = 0;  // sc.fresh[0, entered): (id << 32) | dense index of those that entered
    const std::uint32_t* const ids = lay.idp->ids.data();
    for (const auto& [first_s, last_s] : sc.ranges) {
      const std::size_t m = last_s - first_s;
      if (flags.size() < m + 8) flags.resize(m + 8);
      if (sc.fresh.size() < entered + m) sc.fresh.resize(entered + m);
      std::uint8_t* const fl = flags.data();
      std::uint64_t* const fresh = sc.fresh.data();
      candidate_flags(blo_x + first_s, blo_y + first_s, blo_z + first_s, bhi_x + first_s, bhi_y + first_s,
                      bhi_z + first_s, ix.cls.data() + first_s, m, g, sees, fl);
      std::fill_n(fl + m, 8, 0);
      // The flags 8 at a time; within a word, each set one by its lowest bit (a flag is 0 or 1:
      // clearing the word's lowest set bit clears that flag), no branch per flag.
      for (std::size_t k0 = 0; k0 < m; k0 += 8) {
        std::uint64_t word;
        std::memcpy(&word, fl + k0, 8);
        static_assert(std::endian::native == std::endian::little, "flag r of a word is its byte r");
        for (; word != 0; word &= word - 1) {
          const std::size_t k = first_s + k0 + static_cast<std::size_t>(std::countr_zero(word) >> 3);
          const std::uint32_t d = dense[k];
          if (d == a) continue;  // never itself
          if (mark[d] == in_before) {
            mark[d] = kept;
          } else if (blo_x[k] <= hi_x && lo_x <= bhi_x[k] && blo_y[k] <= hi_y && lo_y <= bhi_y[k] && blo_z[k] <= hi_z &&
                     lo_z <= bhi_z[k]) {
            fresh[entered++] = (std::uint64_t{ids[d]} << 32) | d;
          }
        }
      }
    }
    // The set by id: those that stayed, in last tick's order (by id), merged with those that entered.
    std::sort(sc.fresh.begin(), sc.fresh.begin() + static_cast<std::ptrdiff_t>(entered));
    out.resize(before.size() + entered);
    std::uint64_t* o = out.data();
    const std::uint64_t* fr = sc.fresh.data();
    const std::uint64_t* const fr_end = fr + entered;
    for (std::size_t b = 0; b < before.size(); ++b) {
      const std::uint32_t d = before_dense[b];
      if (d == npos32 || mark[d] != kept) continue;
      const std::uint64_t entry = (before[b] & 0xffffffff00000000ull) | d;
      while (fr != fr_end && *fr < entry) *o++ = *fr++;
      *o++ = entry;
    }
    o = std::copy(fr, fr_end, o);
    out.resize(static_cast<std::size_t>(o - out.data()));
    if (cap != 0 && out.size() > cap) {
      // The cap closest by squared distance (ties by id), as the server keeps them.
      std::vector<std::uint64_t>& keys = sc.keys;
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
      std::sort(out.begin(), out.end());
    }
    sets_[i] = store(sc, out);
  };

  // The observers in chunks, taken by the threads as they come free (towns cost more than fields).
  constexpr std::size_t chunk = 32;
  std::atomic<std::size_t> next{0};
  const auto scan_all = [&](unsigned t) {
    scratch& sc = *scratch_[t];
    for (std::size_t first; (first = next.fetch_add(chunk, std::memory_order_relaxed)) < obs;) {
      for (std::size_t r = first; r < std::min(obs, first + chunk); ++r) observe(sc, ix.scan_order[r]);
    }
  };
  run_parallel(obs >= 64 ? threads_ : 1, scan_all);
  lap(scan_ms_);

  // Publish this tick's truth and sets, observers by id (the sets handed over, not copied).
  {
    tick_truth& slot = *ring_[f.tick % ring_ticks];
    std::unique_lock lock(slot.mutex);
    slot.valid = true;
    slot.tick = f.tick;
    slot.lay = layout_;
    slot.pos.assign(f.positions.begin(), f.positions.end());
    slot.obs_ids.resize(obs);
    slot.obs_at.resize(obs);
    slot.obs_known.resize(obs);
    for (std::size_t r = 0; r < obs; ++r) {
      const std::uint32_t i = lay.observers_by_id[r];
      slot.obs_ids[r] = lay.id(lay.observers[i]);
      slot.obs_at[r] = i;
      slot.obs_known[r] = known_[i];
    }
    slot.sets.swap(sets_);
    slot.known.swap(known_);
    // The blocks of the tick this slot held go back to the pool; this tick's take their place.
    std::lock_guard blocks_lock(blocks_mutex_);
    for (auto& b : slot.blocks) free_blocks_.push_back(std::move(b));
    slot.blocks.clear();
    for (auto& sc : scratch_) {
      for (auto& b : sc->blocks) slot.blocks.push_back(std::move(b));
      sc->blocks.clear();
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
  lap(publish_ms_);
  // The views that waited for this tick: checked on every thread of the oracle (the bots' threads
  // take some too, a few per frame).
  const double drain0 = thread_cpu_ms();
  double helpers_ms = 0;
  run_parallel(
      pending_front_tick_.load() <= f.tick ? threads_ : 1,
      [&](unsigned) { drain_pending(false, static_cast<std::size_t>(-1)); }, &helpers_ms);
  const double own_ms = thread_cpu_ms() - drain0;  // checks, not recomputing: reported apart
  own_drain_cpu_ms_ += own_ms;
  drain_cpu_ms_ += own_ms + helpers_ms;
  lap(drain_ms_);
  return std::nullopt;
}

void oracle::run_parallel(unsigned threads, const std::function<void(unsigned)>& work, double* cpu_ms) {
  // The calling thread is thread 0; the others' CPU is added to `cpu_ms` (the recompute's, unless given).
  std::vector<std::thread> pool;
  std::vector<double> cpu(threads, 0);
  for (unsigned t = 1; t < threads; ++t) {
    pool.emplace_back([&, t] {
      const double c0 = thread_cpu_ms();
      work(t);
      cpu[t] = thread_cpu_ms() - c0;
    });
  }
  work(0);
  for (auto& th : pool) th.join();
  for (const double c : cpu) (cpu_ms != nullptr ? *cpu_ms : compute_cpu_ms_) += c;
}

std::optional<std::vector<std::uint32_t>> oracle::visible(std::uint32_t observer, std::uint64_t tick) const {
  const tick_truth& slot = *ring_[tick % ring_ticks];
  std::shared_lock lock(slot.mutex);
  if (!slot.valid || slot.tick != tick) return std::nullopt;
  const std::uint32_t i = slot.find(observer);
  if (i == npos32 || slot.obs_known[i] == 0) return std::nullopt;
  std::vector<std::uint32_t> ids;
  for (const std::uint64_t e : slot.set(i)) ids.push_back(static_cast<std::uint32_t>(e >> 32));
  return ids;
}

std::optional<oracle::layout_columns> oracle::layout_at(std::uint64_t tick) const {
  const tick_truth& slot = *ring_[tick % ring_ticks];
  std::shared_lock lock(slot.mutex);
  if (!slot.valid || slot.tick != tick) return std::nullopt;
  const layout& lay = *slot.lay;
  layout_columns c;
  for (std::uint32_t k = 0; k < lay.size(); ++k) {
    c.ids.push_back(lay.id(k));
    c.classes.push_back(lay.cls(k));
    c.sees.push_back(lay.sees(k));
    c.kinds.push_back(lay.kind(k));
    c.aoi.insert(c.aoi.end(), lay.aoi(k), lay.aoi(k) + 3);
    c.presence.insert(c.presence.end(), lay.presence(k), lay.presence(k) + 3);
  }
  c.chunks = lay.chunks.size();
  if (tick > 0 && &slot != ring_[(tick - 1) % ring_ticks].get()) {
    const tick_truth& before = *ring_[(tick - 1) % ring_ticks];
    std::shared_lock lock2(before.mutex);
    if (before.valid && before.tick == tick - 1) {
      for (std::size_t i = 0; i < c.chunks && i < before.lay->chunks.size(); ++i)
        c.chunks_shared_with_prev += lay.chunks[i] == before.lay->chunks[i];
    }
  }
  return c;
}

void oracle::log(const char* kind, std::atomic<std::uint32_t>& logged, const std::string& line) {
  if (problem_ == nullptr || logged.fetch_add(1, std::memory_order_relaxed) >= logged_per_kind) return;
  problem_(ctx_, std::string("oracle: ") + kind + ": " + line);
}

void oracle::check(std::uint32_t observer, std::uint64_t tick, const net::client_view& view,
                   const net::deferred_counts& deferred, const std::optional<net::vec3f>& self_position, std::size_t bot) {
  if (!sampled(observer, sample)) {
    c_.frames_unsampled.fetch_add(1, std::memory_order_relaxed);  // outside the sample: by design, not a failure
    return;
  }
  for (std::uint64_t seen = newest_checked_tick_.load(std::memory_order_relaxed);
       tick > seen && !newest_checked_tick_.compare_exchange_weak(seen, tick, std::memory_order_relaxed);) {
  }
  // The truth of this tick is usually computed a few milliseconds after its frames arrive: then
  // a snapshot of the view waits, and the bot goes on at once. Waiting snapshots whose truth has
  // come are checked by the oracle's threads after each tick and by the next bots to call (a few each).
  drain_pending(false, 8);
  const bool ready = any_ready_.load(std::memory_order_acquire) && ready_tick_.load(std::memory_order_acquire) >= tick;
  const std::size_t bytes = sizeof(view_snapshot) + view.size() * sizeof(held_entity);
  if (!ready) {
    // Room for it first (no copy of a view that could not wait).
    bool room = false;
    const bool ended = ended_.load();  // the stream is over: its truth will not come (not an overflow)
    if (!ended) {
      room = pending_bytes_.fetch_add(bytes, std::memory_order_relaxed) + bytes <= max_pending_bytes;
      if (!room) pending_bytes_.fetch_sub(bytes, std::memory_order_relaxed);
    }
    if (!room) {
      if (!ended) pending_overflow_.fetch_add(1, std::memory_order_relaxed);
      c_.frames_unchecked.fetch_add(1, std::memory_order_relaxed);
      return;
    }
  }
  thread_local view_snapshot reused;
  view_snapshot waiting;
  view_snapshot& v = ready ? reused : waiting;
  v.observer = observer, v.tick = tick, v.deferred = deferred, v.self_position = self_position, v.bot = bot;
  v.held.clear();
  v.held.reserve(view.size());
  const auto held_of = [](std::uint32_t id, const net::client_view::entity& e) {
    const auto& p = e.state.position;
    return held_entity{id, e.state.visibility_class, p.x, p.y, p.z, e.last_tick};
  };
  // With the truth there, the view is first read in the order of the visible set (ascending id):
  // when every held entity is visible (the usual frame), that is the snapshot, already by id,
  // with no copy of the whole view to sort. Otherwise (an extra or a leak, the truth gone) the
  // snapshot is made whole and sorted. Either way check_snapshot gets the same snapshot.
  bool by_truth = false;
  if (ready) {
    const tick_truth& now = *ring_[tick % ring_ticks];
    std::shared_lock lock(now.mutex);
    const std::uint32_t oi = now.valid && now.tick == tick ? now.find(observer) : npos32;
    if (oi != npos32 && now.obs_known[oi] != 0) {
      const auto& entities = view.entities();
      for (const std::uint64_t entry : now.set(oi)) {
        const auto id = static_cast<std::uint32_t>(entry >> 32);
        if (const auto it = entities.find(id); it != entities.end()) v.held.push_back(held_of(id, it->second));
      }
      by_truth = v.held.size() == view.size();
    }
  }
  if (!by_truth) {
    v.held.clear();
    for (const auto& [id, e] : view.entities()) v.held.push_back(held_of(id, e));
    std::sort(v.held.begin(), v.held.end(), [](const held_entity& a, const held_entity& b) { return a.id < b.id; });
  }
  if (ready) {
    check_snapshot(v);
    return;
  }
  std::lock_guard lock(pending_mutex_);
  if (ended_.load()) {  // stopped meanwhile: its last drain is over, nothing would check this one
    pending_bytes_.fetch_sub(bytes, std::memory_order_relaxed);
    c_.frames_unchecked.fetch_add(1, std::memory_order_relaxed);
    return;
  }
  pending_.push_back(std::move(waiting));
  if (pending_.size() == 1) pending_front_tick_.store(tick, std::memory_order_release);
}

void oracle::catch_up(double timeout_s) {
  const std::uint64_t want = newest_checked_tick_.load();
  std::unique_lock lock(ready_mutex_);
  ready_cv_.wait_for(lock, std::chrono::duration<double>(timeout_s),
                     [&] { return (any_ready_.load() && ready_tick_.load() >= want) || ended_.load(); });
}

void oracle::drain_pending(bool all, std::size_t max_jobs) {
  // Oldest first, a few at a time, checked outside the lock (bots' threads and the oracle's
  // threads drain at once). Without the lock first: is the oldest one's truth there?
  if (!all && (!any_ready_.load(std::memory_order_acquire) ||
               pending_front_tick_.load(std::memory_order_acquire) > ready_tick_.load(std::memory_order_acquire))) {
    return;
  }
  std::vector<view_snapshot> batch;
  for (std::size_t done = 0; done < max_jobs;) {
    batch.clear();
    {
      std::lock_guard lock(pending_mutex_);
      const std::uint64_t ready = ready_tick_.load();
      const bool any = any_ready_.load();
      while (!pending_.empty() && batch.size() < 16 && (all || (any && pending_.front().tick <= ready))) {
        pending_bytes_.fetch_sub(sizeof(view_snapshot) + pending_.front().held.size() * sizeof(held_entity),
                                 std::memory_order_relaxed);
        batch.push_back(std::move(pending_.front()));
        pending_.pop_front();
      }
      pending_front_tick_.store(pending_.empty() ? ~std::uint64_t{0} : pending_.front().tick,
                                std::memory_order_release);
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
  const std::span<const std::uint64_t> truth = now.set(oi);  // (id << 32) | dense index
  const auto id_at = [&](std::size_t i) { return static_cast<std::uint32_t>(truth[i] >> 32); };
  const std::uint32_t self = lay.dense_of(observer);
  const float* eye = now.pos.data() + 3 * self;
  const std::uint32_t sees = lay.sees(self);
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
           (d == npos32 ? std::string() : ", class " + std::to_string(lay.cls(d)));
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

  // The visible set and the held entities, both by ascending id, side by side; those in both are
  // checked in a second pass, after their truth (this tick's and the tick each was last sent)
  // was asked of memory for all of them at once.
  struct held_and_visible {
    const held_entity* e;
    const tick_truth* at;  // the tick it was last sent (nullptr: gone from the ring)
    std::uint32_t d, dl;   // its dense index now and then
  };
  thread_local std::vector<held_and_visible> both;
  both.clear();
  std::size_t i = 0, j = 0;
  while (i < truth.size() || j < v.held.size()) {
    if (j == v.held.size() || (i < truth.size() && id_at(i) < v.held[j].id)) {
      if (missing++ == 0) first_missing = id_at(i);  // visible, not held
      ++i;
      continue;
    }
    if (i == truth.size() || v.held[j].id < id_at(i)) {
      // Held, not visible: a leak when of a class the observer does not see.
      const std::uint32_t id = v.held[j].id;
      const std::uint32_t d = lay.dense_of(id);
      if (d != npos32 && (lay.cls(d) & sees) == 0) {
        if (leaked++ == 0) first_leak = id;
      } else if (extra++ == 0) {
        first_extra = id;
      }
      ++j;
      continue;
    }
    // Held and visible: checked in the second pass below (its truth fetched meanwhile).
    const held_entity& e = v.held[j];
    const auto d = static_cast<std::uint32_t>(truth[i]);
    ++i, ++j;
    const tick_truth* at = e.last_tick <= tick && tick - e.last_tick < ring_ticks ? truth_at(e.last_tick) : nullptr;
    // The same lineage: the same index, if the entity existed then (else it was not sent then).
    const std::uint32_t dl = at == nullptr                     ? npos32
                             : at->lay->lineage != lay.lineage ? at->lay->dense_of(e.id)
                             : d < at->lay->size()             ? d
                                                               : npos32;
    if (at != nullptr && dl != npos32) __builtin_prefetch(at->pos.data() + 3 * dl);
    __builtin_prefetch(now.pos.data() + 3 * d);
    __builtin_prefetch(&lay.cls(d));
    both.push_back({&e, at, d, dl});
  }
  // Held and visible: its class, its position, and whether an update was due.
  for (const held_and_visible& hv : both) {
    const held_entity& e = *hv.e;
    const std::uint32_t id = e.id, d = hv.d, dl = hv.dl;
    const tick_truth* at = hv.at;
    ++checked;
    if (e.visibility_class != lay.cls(d)) {
      c_.wrong_class.fetch_add(1, std::memory_order_relaxed);
      log("class", logged_class_, who() + ": " + entity_line(id) + " is held with class " + std::to_string(e.visibility_class));
    }
    if (at == nullptr) {
      ++pos_unchecked;
    } else {
      ++pos_checked;
      const float* p = dl == npos32 ? nullptr : at->pos.data() + 3 * dl;
      // Written as "not within": a NaN on either side is a wrong position, never a pass.
      if (p == nullptr || !(std::fabs(e.x - p[0]) <= tolerance_.x) || !(std::fabs(e.y - p[1]) <= tolerance_.y) ||
          !(std::fabs(e.z - p[2]) <= tolerance_.z)) {
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
  r.compute_cpu_ms = compute_cpu_ms_ - own_drain_cpu_ms_, r.compute_max_ms = compute_max_ms_;
  r.drain_cpu_ms = drain_cpu_ms_;
  r.check_ms = static_cast<double>(check_ns_.load()) / 1e6;
  r.deferred_checks = deferred_checks_.load();
  r.pending_overflow = pending_overflow_.load();
  r.observers_max = observers_max_, r.sampled_max = sampled_max_;
  r.frames_unsampled = c_.frames_unsampled, r.sample = sample;
  r.decode_ms = decode_ms_, r.index_ms = index_ms_, r.scan_ms = scan_ms_, r.publish_ms = publish_ms_,
  r.drain_ms = drain_ms_;
  std::lock_guard lock(ready_mutex_);
  r.stream_error = stream_error_;
  return r;
}

}  // namespace zone::bots
