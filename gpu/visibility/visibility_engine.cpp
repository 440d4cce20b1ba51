// Host dispatch of the GPU visibility engine (gpu/visibility.h; algorithm in docs/zone.md, "The
// interest step on the GPU").
//
// One update, on one stream, with one host synchronisation in the usual case:
//  1. Pack the rows' inputs into pinned staging memory (on the pool) and copy them up at once.
//  2. Boxes, validation, presence bounds and mean sizes, each observer's previous row from the
//     device's slot map (one kernel); the grid plan (one thread).
//  3. The grid over the presence boxes: counts per cell, scan, scatter (entries carry their box).
//  4. Candidates, one warp per observer over the grid, each classified as it is found against
//     the previous sets (device-resident): a stay flags its previous entry, an enter is appended.
//  5. Scans of the three list sizes, the enters placed in their rows, and the writing of the
//     sorted enters, the leaves and the merged visible sets.
//  6. This update's rows become the previous rows on the device (slot map; only if the update is
//     valid); copy back the state, the offsets and the lists (sized by the last update's totals);
//     run the caller's while_waiting work; wait.
//  Then, rarely: a buffer that overflowed is grown and the device passes run again (nothing was
//  committed), or the lists were longer than prefetched and the rest is copied.
//  Only a successful update replaces the previous sets (two device buffers swapped).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>
#include <utility>

#include "gpu/common/cuda_check.h"
#include "gpu/common/gpu_buffers.h"
#include "gpu/device.h"
#include "gpu/visibility.h"
#include "interest/measure.h"
#include "interest/thread_pool.h"
#include "visibility_launch.h"

namespace zone::gpu {
namespace detail::vis {
namespace {

using clock_type = std::chrono::steady_clock;

/// Most cells of the grid (its counters are allocated once: 3 x 4 MiB).
constexpr std::uint32_t max_cells = 1u << 20;
/// Rows per packing task.
constexpr std::size_t pack_chunk = 32768;
/// Most rows per update (cell entries and box indices stay within 32 bits).
constexpr std::size_t max_rows = std::size_t{1} << 26;
/// Most slot bits (the slot map has 2^slot_bits entries).
constexpr std::uint32_t max_slot_bits = 26;

template <class T>
using device_array = mem::device_array<T>;
template <class T>
using pinned_array = mem::pinned_array<T>;

class engine final : public interest::visibility_engine {
 public:
  explicit engine(interest::thread_pool* pool) : pool_(pool) {
    CUDA_CHECK(cudaSetDevice(0));
    CUDA_CHECK(cudaStreamCreateWithFlags(&stream_, cudaStreamNonBlocking));
    for (cudaEvent_t* e : {&ev_begin_, &ev_up_, &ev_grid_, &ev_query_, &ev_classify_, &ev_kernels_, &ev_down_}) {
      CUDA_CHECK(cudaEventCreate(e));
    }
    d_st_.reserve(1);
    h_st_.reserve(1);
    d_counts_.reserve(max_cells + 1);
    d_cursor_.reserve(max_cells);
    d_start_.reserve(max_cells + 1);
  }

  ~engine() override {
    if (stream_ != nullptr) cudaStreamSynchronize(stream_);
    for (cudaEvent_t e : {ev_begin_, ev_up_, ev_grid_, ev_query_, ev_classify_, ev_kernels_, ev_down_}) {
      if (e != nullptr) cudaEventDestroy(e);
    }
    if (stream_ != nullptr) cudaStreamDestroy(stream_);
  }

  [[nodiscard]] const char* name() const override { return "gpu"; }

  [[nodiscard]] resident_lists resident_visible() const override {
    if (d_prev_off_.get() == nullptr || prev_rows_ == 0) return {};
    return {d_prev_vis_.get(), d_prev_off_.get(), prev_rows_, prev_total_};
  }

  void prepare() noexcept override {
    // A kernel and a small copy each way: the SMs and both copy engines see work before the tick.
    (void)launch_touch(stream_);
    (void)cudaMemcpyAsync(d_st_.get(), h_st_.get(), sizeof(std::uint32_t), cudaMemcpyHostToDevice, stream_);
    (void)cudaMemcpyAsync(h_st_.get(), d_st_.get(), sizeof(std::uint32_t), cudaMemcpyDeviceToHost, stream_);
  }

  interest::visibility_lists fetch_all_visible() override {
    // The last committed sets are the device's previous ones now.
    if (!full_fetched_) {
      h_full_off_.reserve(std::size_t{prev_rows_} + 1);
      h_full_vis_.reserve(prev_total_);
      if (prev_rows_ > 0) {
        CUDA_CHECK(cudaMemcpyAsync(h_full_off_.get(), d_prev_off_.get(), (std::size_t{prev_rows_} + 1) * sizeof(std::uint32_t),
                                   cudaMemcpyDeviceToHost, stream_));
      } else {
        h_full_off_.get()[0] = 0;
      }
      if (prev_total_ > 0) {
        CUDA_CHECK(cudaMemcpyAsync(h_full_vis_.get(), d_prev_vis_.get(), prev_total_ * sizeof(std::uint32_t),
                                   cudaMemcpyDeviceToHost, stream_));
      }
      CUDA_CHECK(cudaStreamSynchronize(stream_));
      full_fetched_ = true;
    }
    return {h_full_vis_.get(), h_full_off_.get()};
  }

  void load_previous(std::span<const std::uint32_t> ids, std::uint32_t slot_bits,
                     std::span<const std::uint32_t> offsets, std::span<const std::uint32_t> visible) override {
    const std::size_t rows = offsets.empty() ? 0 : offsets.size() - 1;
    const std::uint64_t total = rows == 0 ? 0 : offsets[rows];
    if (rows > max_rows || total > visible.size() || ids.size() != rows) {
      throw std::invalid_argument("load_previous: inconsistent sets");
    }
    use_slot_bits(slot_bits);
    d_prev_off_.reserve(rows + 1);
    d_prev_vis_.reserve(total);
    d_prev_ids_.reserve(rows);
    if (rows > 0) {
      CUDA_CHECK(cudaMemcpyAsync(d_prev_ids_.get(), ids.data(), rows * sizeof(std::uint32_t), cudaMemcpyHostToDevice,
                                 stream_));
    }
    CUDA_CHECK(launch_map_slots(d_prev_ids_.get(), static_cast<std::uint32_t>(rows), slot_bits_, d_row_of_slot_.get(),
                                stream_));
    if (rows > 0) {
      CUDA_CHECK(cudaMemcpyAsync(d_prev_off_.get(), offsets.data(), (rows + 1) * sizeof(std::uint32_t),
                                 cudaMemcpyHostToDevice, stream_));
    }
    if (total > 0) {
      CUDA_CHECK(cudaMemcpyAsync(d_prev_vis_.get(), visible.data(), total * sizeof(std::uint32_t),
                                 cudaMemcpyHostToDevice, stream_));
    }
    CUDA_CHECK(cudaStreamSynchronize(stream_));
    prev_rows_ = static_cast<std::uint32_t>(rows);
    prev_total_ = total;
    full_fetched_ = false;
  }

  std::optional<std::size_t> update(const interest::visibility_input& in, interest::visibility_output& result) override {
    // `result` changes only on success: on an error the caller still reads the last output.
    interest::visibility_output out{};
    const auto t0 = clock_type::now();
    if (in.n > max_rows) throw std::length_error("gpu visibility engine: more than 2^26 rows");
    if (!(in.hysteresis >= 0) || !std::isfinite(in.hysteresis)) {
      throw std::invalid_argument("gpu visibility engine: the hysteresis margin must be finite and >= 0");
    }
    const auto n = static_cast<std::uint32_t>(in.n);
    use_slot_bits(in.slot_bits);
    // The columns other than positions are kept from the last upload when the caller says they
    // did not change (same version, same rows).
    bool keep_static = in.static_version != 0 && in.static_version == uploaded_version_ && in.n == uploaded_n_;
    uploaded_version_ = 0;
    keep_static = pack(in, keep_static);
    out.timing.pack_ms = ms_since(t0);

    wanted_ = in.wanted != nullptr;
    CUDA_CHECK(cudaEventRecord(ev_begin_, stream_));
    if (n > 0 && keep_static) {
      CUDA_CHECK(cudaMemcpyAsync(d_in_.get(), h_in_.get(), 12ull * n, cudaMemcpyHostToDevice, stream_));
      if (wanted_) {
        CUDA_CHECK(cudaMemcpyAsync(d_in_.get() + 48ull * n, h_in_.get() + 48ull * n, wanted_bytes(n),
                                   cudaMemcpyHostToDevice, stream_));
      }
    } else if (n > 0) {
      CUDA_CHECK(cudaMemcpyAsync(d_in_.get(), h_in_.get(), upload_bytes(n), cudaMemcpyHostToDevice, stream_));
    }
    uploaded_version_ = in.static_version;
    uploaded_n_ = in.n;
    CUDA_CHECK(cudaEventRecord(ev_up_, stream_));
    size_rows(n);
    entry_cap_ = std::max<std::uint64_t>(entry_cap_, 2ull * n + 1024);
    vis_cap_ = std::max<std::uint64_t>(vis_cap_, 16ull * n + 4096);
    enter_cap_ = std::max<std::uint64_t>(enter_cap_, n / 4 + 4096);

    tick_state st{};
    std::uint64_t got_vis = 0, got_enter = 0, got_leave = 0;
    for (std::uint32_t attempt = 0;; ++attempt) {
      if (attempt == 8) throw std::runtime_error("gpu visibility engine: buffers kept overflowing");
      run_device(n, in.hysteresis);
      // What the last update's totals suggest, capped by what the device can hold.
      got_vis = std::min<std::uint64_t>((wanted_ ? last_dl_ : last_vis_) * 9 / 8 + 1024, vis_cap_);
      got_enter = std::min<std::uint64_t>(last_enter_ + last_enter_ / 2 + 1024, enter_cap_);
      got_leave = std::min<std::uint64_t>(last_leave_ + last_leave_ / 2 + 1024, prev_total_ + 1);
      download(n, got_vis, got_enter, got_leave);
      if (attempt == 0 && in.while_waiting) in.while_waiting();
      const auto t_wait = clock_type::now();
      CUDA_CHECK(cudaStreamSynchronize(stream_));
      if (attempt == 0) out.timing.wait_ms = ms_since(t_wait);
      st = *h_st_.get();
      if (st.overflow == 0) break;
      ++out.timing.reruns;
      if ((st.overflow & 1u) != 0) {
        // The grid overflowed: nothing after it ran, so the other totals mean nothing yet.
        entry_cap_ = std::max<std::uint64_t>(entry_cap_ * 2, st.entries + st.entries / 4 + 1024);
        continue;
      }
      if ((st.overflow & 2u) != 0) {
        enter_cap_ = std::max<std::uint64_t>(enter_cap_ * 2, st.enter_count + st.enter_count / 4 + 4096);
      }
      if ((st.overflow & 4u) != 0) {
        vis_cap_ = std::max<std::uint64_t>(vis_cap_ * 2, std::uint64_t{st.visible_total} + st.visible_total / 4 + 4096);
      }
    }
    out.timing.upload_ms = elapsed_ms(ev_begin_, ev_up_);
    out.timing.device_ms = elapsed_ms(ev_up_, ev_kernels_);
    out.timing.grid_ms = elapsed_ms(ev_up_, ev_grid_);
    out.timing.query_ms = elapsed_ms(ev_grid_, ev_query_);
    out.timing.place_ms = elapsed_ms(ev_query_, ev_classify_);
    out.timing.write_ms = elapsed_ms(ev_classify_, ev_kernels_);
    out.timing.download_ms = elapsed_ms(ev_kernels_, ev_down_);
    if (st.bad_box != no_box) {
      out.timing.total_ms = ms_since(t0);
      return st.bad_box;  // nothing committed: the previous sets stay
    }
    // Lists longer than prefetched: the rest now (a pinned buffer that must grow is refilled whole).
    host_lists& h = host_[1 - cur_];
    bool more = false;
    const std::uint64_t vis_total = wanted_ ? st.download_total : st.visible_total;
    more |= fetch_rest(h.vis, wanted_ ? d_dl_out_ : d_vis_out_, vis_total, got_vis);
    more |= fetch_rest(h.enter, d_enter_out_, st.enter_total, got_enter);
    more |= fetch_rest(h.leave, d_leave_out_, st.leave_total, got_leave);
    if (more) CUDA_CHECK(cudaStreamSynchronize(stream_));

    // Commit: this update's sets become the previous ones.
    d_prev_vis_.swap(d_vis_out_);
    d_prev_off_.swap(d_vis_off_);
    prev_rows_ = n;
    prev_total_ = st.visible_total;
    cur_ = 1 - cur_;  // the host lists written now; the other set keeps the last output until then
    full_fetched_ = false;
    last_vis_ = st.visible_total;
    last_dl_ = st.download_total;
    last_enter_ = st.enter_total;
    last_leave_ = st.leave_total;

    out.visible = h.vis.get();
    out.visible_off = h.off.get();
    out.enters = h.enter.get();
    out.enter_off = h.off.get() + (n + 1);
    out.leaves = h.leave.get();
    out.leave_off = h.off.get() + 2 * (n + 1);
    out.visible_complete = !wanted_;
    out.visible_total = st.visible_total;
    out.candidates = st.candidates;
    out.pairs = st.candidates + st.self_pairs;
    out.timing.total_ms = ms_since(t0);
    result = out;
    return std::nullopt;
  }

 private:
  /// The slot map for handles of `bits` slot bits (rebuilt from the previous rows when it changes).
  void use_slot_bits(std::uint32_t bits) {
    if (bits == slot_bits_) return;
    if (bits == 0 || bits > max_slot_bits) throw std::invalid_argument("gpu visibility engine: slot_bits must be 1 .. 26");
    d_row_of_slot_.reserve(std::size_t{1} << bits);
    slot_bits_ = bits;
    CUDA_CHECK(launch_map_slots(d_prev_ids_.get(), prev_rows_, slot_bits_, d_row_of_slot_.get(), stream_));
  }

  /// Bytes of the wanted flags in the input block (n, rounded up to 4).
  static std::size_t wanted_bytes(std::size_t n) { return (n + 3) & ~std::size_t{3}; }
  std::size_t upload_bytes(std::size_t n) const { return 48 * n + (wanted_ ? wanted_bytes(n) : 0); }

  /// Rows' inputs into pinned staging, laid out as the device expects them (input_arrays):
  /// position, aoi, body (12 bytes a row each), then class, sees, id (4 bytes each), the wanted
  /// flags (1 byte each, padded to 4); the device adds the previous row (4 bytes) behind them.
  /// Returns whether the static columns were kept (false when the device block had to grow).
  bool pack(const interest::visibility_input& in, bool keep_static) {
    const std::size_t n = in.n;
    h_in_.reserve(48 * n + wanted_bytes(n));
    if (d_in_.capacity() < 52 * n + wanted_bytes(n)) {
      d_in_.reserve(52 * n + wanted_bytes(n));
      keep_static = false;  // contents lost
    }
    if (d_prev_ids_.capacity() < n) {
      // The previous rows' handles must survive the growth (the prep kernel reads them).
      device_array<std::uint32_t> bigger;
      bigger.reserve(n + n / 4);
      if (prev_rows_ > 0) {
        CUDA_CHECK(cudaMemcpyAsync(bigger.get(), d_prev_ids_.get(), std::size_t{prev_rows_} * sizeof(std::uint32_t),
                                   cudaMemcpyDeviceToDevice, stream_));
      }
      d_prev_ids_.swap(bigger);
    }
    if (n == 0) return keep_static;
    unsigned char* base = h_in_.get();
    const int arrays = in.wanted != nullptr ? 7 : 6;
    const void* src[7] = {in.position, in.aoi_half, in.body_half, in.visibility, in.sees, in.ids, in.wanted};
    const std::size_t width[7] = {12, 12, 12, 4, 4, 4, 1};
    std::size_t offset[7];
    std::size_t at = 0;
    for (int k = 0; k < arrays; ++k) {
      if (src[k] == nullptr) throw std::invalid_argument("gpu visibility engine: an input array is missing");
      offset[k] = at;
      at += width[k] * n;
    }
    const std::size_t chunks = (n + pack_chunk - 1) / pack_chunk;
    interest::run_tasks(chunks > 1 ? pool_ : nullptr, arrays * chunks, [&](std::size_t t) {
      const std::size_t k = t % arrays, c = t / arrays;
      if (keep_static && k >= 1 && k <= 5) return;  // aoi, body, class, sees, id
      const std::size_t b = c * pack_chunk, e = std::min(n, b + pack_chunk);
      std::memcpy(base + offset[k] + b * width[k], static_cast<const unsigned char*>(src[k]) + b * width[k],
                  (e - b) * width[k]);
    });
    return keep_static;
  }

  void size_rows(std::uint32_t n) {
    for (auto* a : {&d_glo_, &d_ghi_, &d_plo_, &d_phi_}) a->reserve(n);
    d_large_.reserve(n);
    d_enter_cursor_.reserve(n);
    for (auto* a : {&d_vis_len_, &d_enter_len_, &d_leave_len_, &d_vis_off_, &d_enter_off_, &d_leave_off_, &d_dl_len_,
                    &d_dl_off_}) {
      a->reserve(n + 1);
    }
    host_[1 - cur_].off.reserve(3 * (std::size_t{n} + 1));
  }

  pass_args args(std::uint32_t n) const {
    pass_args a{};
    a.n = n;
    const unsigned char* in = d_in_.get();
    a.in.pos = reinterpret_cast<const float3*>(in);
    a.in.aoi = reinterpret_cast<const float3*>(in + 12ull * n);
    a.in.body = reinterpret_cast<const float3*>(in + 24ull * n);
    a.in.cls = reinterpret_cast<const std::uint32_t*>(in + 36ull * n);
    a.in.sees = reinterpret_cast<const std::uint32_t*>(in + 40ull * n);
    a.in.ids = reinterpret_cast<const std::uint32_t*>(in + 44ull * n);
    a.in.wanted = wanted_ ? in + 48ull * n : nullptr;
    a.in.prev_row = reinterpret_cast<std::uint32_t*>(d_in_.get() + 48ull * n + (wanted_ ? wanted_bytes(n) : 0));
    a.prev = {d_prev_ids_.get(), d_row_of_slot_.get(), prev_rows_, (1u << slot_bits_) - 1u};
    a.box = {d_glo_.get(), d_ghi_.get(), d_plo_.get(), d_phi_.get()};
    // The kernels' bounds are the capacities as allocated. (entry_cap_, enter_cap_ and vis_cap_ stay
    // what was asked for: the visible list's two buffers trade places every update, and feeding one's
    // grown capacity back as the other's request made both grow by half every update.)
    const std::uint64_t entry_capacity = std::min({d_elo_.capacity(), d_ehi_.capacity(), d_ecx_.capacity()});
    a.grid = {d_start_.get(), d_elo_.get(), d_ehi_.get(), d_ecx_.get(), entry_capacity, d_large_.get()};
    a.st = d_st_.get();
    a.enter_pairs = d_enter_pairs_.get();
    a.enter_capacity = std::min({d_enter_pairs_.capacity(), d_enter_tmp_.capacity(), d_enter_out_.capacity()});
    a.enter_cursor = d_enter_cursor_.get();
    a.vis_capacity = wanted_ ? std::min(d_vis_out_.capacity(), d_dl_out_.capacity()) : d_vis_out_.capacity();
    a.prev_vis = d_prev_vis_.get();
    a.prev_off = d_prev_off_.get();
    a.prev_rows = prev_rows_;
    a.flag = d_flag_.get();
    a.kept_prefix = d_kept_prefix_.get();
    a.enter_tmp = d_enter_tmp_.get();
    a.vis_len = d_vis_len_.get();
    a.enter_len = d_enter_len_.get();
    a.leave_len = d_leave_len_.get();
    a.vis_off = d_vis_off_.get();
    a.enter_off = d_enter_off_.get();
    a.leave_off = d_leave_off_.get();
    a.vis_out = d_vis_out_.get();
    a.enter_out = d_enter_out_.get();
    a.leave_out = d_leave_out_.get();
    a.dl_len = d_dl_len_.get();
    a.dl_off = d_dl_off_.get();
    a.dl_out = d_dl_out_.get();
    return a;
  }

  void grow_temp(std::size_t bytes) { d_temp_.reserve(std::max<std::size_t>(bytes, 256)); }

  /// Steps 2 to 5 on the stream (no synchronisation).
  void run_device(std::uint32_t n, float h) {
    d_elo_.reserve(entry_cap_);
    d_ehi_.reserve(entry_cap_);
    d_ecx_.reserve(entry_cap_);
    d_enter_pairs_.reserve(enter_cap_);
    d_enter_tmp_.reserve(enter_cap_);
    d_enter_out_.reserve(enter_cap_);
    d_vis_out_.reserve(vis_cap_);
    if (wanted_) d_dl_out_.reserve(vis_cap_);
    d_leave_out_.reserve(prev_total_ + 1);
    d_flag_.reserve(prev_total_ + 1);
    d_kept_prefix_.reserve(prev_total_ + 1);
    const pass_args a = args(n);

    CUDA_CHECK(launch_init(a.st, stream_));
    CUDA_CHECK(launch_prep(a.in, n, h, a.box, a.prev, a.st, stream_));
    CUDA_CHECK(launch_plan(a.st, max_cells, stream_));
    CUDA_CHECK(cudaMemsetAsync(d_counts_.get(), 0, (max_cells + 1) * sizeof(std::uint32_t), stream_));
    CUDA_CHECK(cudaMemsetAsync(d_cursor_.get(), 0, max_cells * sizeof(std::uint32_t), stream_));
    CUDA_CHECK(launch_count(a, d_counts_.get(), stream_));
    std::size_t bytes_cells = 0, bytes_u32 = 0;
    CUDA_CHECK(scan_cells(nullptr, bytes_cells, d_counts_.get(), d_start_.get(), max_cells + 1, stream_));
    CUDA_CHECK(scan_u32(nullptr, bytes_u32, d_vis_len_.get(), d_vis_off_.get(), n + 1, stream_));
    grow_temp(std::max(bytes_cells, bytes_u32));
    CUDA_CHECK(scan_cells(d_temp_.get(), bytes_cells, d_counts_.get(), d_start_.get(), max_cells + 1, stream_));
    CUDA_CHECK(launch_scatter(a, d_cursor_.get(), stream_));
    CUDA_CHECK(cudaEventRecord(ev_grid_, stream_));

    for (auto* len : {&d_vis_len_, &d_enter_len_, &d_leave_len_}) {
      CUDA_CHECK(cudaMemsetAsync(len->get() + n, 0, sizeof(std::uint32_t), stream_));
    }
    CUDA_CHECK(cudaMemsetAsync(d_enter_cursor_.get(), 0, std::size_t{n} * sizeof(std::uint32_t), stream_));
    CUDA_CHECK(launch_query(a, stream_));
    CUDA_CHECK(cudaEventRecord(ev_query_, stream_));
    CUDA_CHECK(scan_u32(d_temp_.get(), bytes_u32, d_vis_len_.get(), d_vis_off_.get(), n + 1, stream_));
    CUDA_CHECK(scan_u32(d_temp_.get(), bytes_u32, d_enter_len_.get(), d_enter_off_.get(), n + 1, stream_));
    CUDA_CHECK(scan_u32(d_temp_.get(), bytes_u32, d_leave_len_.get(), d_leave_off_.get(), n + 1, stream_));
    CUDA_CHECK(launch_capacity(a, stream_));
    CUDA_CHECK(launch_place_enters(a, stream_));
    CUDA_CHECK(cudaEventRecord(ev_classify_, stream_));
    if (wanted_) {
      CUDA_CHECK(launch_wanted_sizes(a, stream_));
      CUDA_CHECK(scan_u32(d_temp_.get(), bytes_u32, d_dl_len_.get(), d_dl_off_.get(), n + 1, stream_));
    }
    CUDA_CHECK(launch_write(a, stream_));
    if (wanted_) CUDA_CHECK(launch_gather(a, stream_));
    CUDA_CHECK(launch_totals(a, max_cells, stream_));
    CUDA_CHECK(launch_commit(a, stream_));
    CUDA_CHECK(cudaEventRecord(ev_kernels_, stream_));
  }

  /// Step 6: state, offsets and the first `vis`, `enter`, `leave` entries of the lists.
  void download(std::uint32_t n, std::uint64_t vis, std::uint64_t enter, std::uint64_t leave) {
    CUDA_CHECK(cudaMemcpyAsync(h_st_.get(), d_st_.get(), sizeof(tick_state), cudaMemcpyDeviceToHost, stream_));
    // Into the host set not in use: the last output stays readable until this update commits.
    host_lists& h = host_[1 - cur_];
    const std::size_t rows = std::size_t{n} + 1;
    const std::uint32_t* offs[3] = {wanted_ ? d_dl_off_.get() : d_vis_off_.get(), d_enter_off_.get(), d_leave_off_.get()};
    for (int k = 0; k < 3; ++k) {
      CUDA_CHECK(cudaMemcpyAsync(h.off.get() + k * rows, offs[k], rows * sizeof(std::uint32_t), cudaMemcpyDeviceToHost,
                                 stream_));
    }
    h.vis.reserve(vis);
    h.enter.reserve(enter);
    h.leave.reserve(leave);
    const std::pair<pinned_array<std::uint32_t>*, const device_array<std::uint32_t>*> lists[3] = {
        {&h.vis, wanted_ ? &d_dl_out_ : &d_vis_out_}, {&h.enter, &d_enter_out_}, {&h.leave, &d_leave_out_}};
    const std::uint64_t sizes[3] = {vis, enter, leave};
    for (int k = 0; k < 3; ++k) {
      const std::uint64_t count = std::min<std::uint64_t>(sizes[k], lists[k].second->capacity());
      if (count > 0) {
        CUDA_CHECK(cudaMemcpyAsync(lists[k].first->get(), lists[k].second->get(), count * sizeof(std::uint32_t),
                                   cudaMemcpyDeviceToHost, stream_));
      }
    }
    CUDA_CHECK(cudaEventRecord(ev_down_, stream_));
  }

  /// Copies entries [got, total) of a list (or all of it when its pinned buffer must grow).
  bool fetch_rest(pinned_array<std::uint32_t>& host, const device_array<std::uint32_t>& dev, std::uint64_t total,
                  std::uint64_t got) {
    if (total <= got) return false;
    if (total > host.capacity()) {
      host.reserve(total + total / 8);
      got = 0;
    }
    CUDA_CHECK(cudaMemcpyAsync(host.get() + got, dev.get() + got, (total - got) * sizeof(std::uint32_t),
                               cudaMemcpyDeviceToHost, stream_));
    return true;
  }

  interest::thread_pool* pool_;
  cudaStream_t stream_ = nullptr;
  cudaEvent_t ev_begin_ = nullptr, ev_up_ = nullptr, ev_grid_ = nullptr, ev_query_ = nullptr, ev_classify_ = nullptr,
              ev_kernels_ = nullptr, ev_down_ = nullptr;

  pinned_array<unsigned char> h_in_;
  device_array<unsigned char> d_in_;
  device_array<float4> d_glo_, d_ghi_, d_plo_, d_phi_;
  device_array<tick_state> d_st_;
  pinned_array<tick_state> h_st_;
  device_array<std::uint32_t> d_counts_, d_cursor_, d_start_;
  device_array<float4> d_elo_, d_ehi_;
  device_array<std::uint32_t> d_ecx_, d_large_;
  device_array<unsigned long long> d_enter_pairs_;
  device_array<std::uint32_t> d_enter_cursor_;
  device_array<std::uint32_t> d_prev_vis_, d_prev_off_;
  device_array<std::uint32_t> d_prev_ids_, d_row_of_slot_;  // previous rows' handles; slot -> row
  std::uint32_t slot_bits_ = 0;
  std::uint64_t uploaded_version_ = 0;  // static_version of the columns on the device (0: none)
  std::size_t uploaded_n_ = 0;
  device_array<std::uint8_t> d_flag_;
  device_array<std::uint32_t> d_kept_prefix_, d_enter_tmp_;
  device_array<std::uint32_t> d_vis_len_, d_enter_len_, d_leave_len_, d_vis_off_, d_enter_off_, d_leave_off_;
  device_array<std::uint32_t> d_vis_out_, d_enter_out_, d_leave_out_;
  device_array<std::uint32_t> d_dl_len_, d_dl_off_, d_dl_out_;  // the wanted rows' sets, gathered
  pinned_array<std::uint32_t> h_full_vis_, h_full_off_;           // fetch_all_visible
  bool wanted_ = false, full_fetched_ = false;
  std::uint64_t last_dl_ = 0;
  /// Host copies of the lists, double-buffered: out points into host_[cur_] after an update.
  struct host_lists {
    pinned_array<std::uint32_t> vis, enter, leave, off;
  };
  host_lists host_[2];
  int cur_ = 0;
  device_array<unsigned char> d_temp_;

  std::uint32_t prev_rows_ = 0;
  std::uint64_t prev_total_ = 0;
  std::uint64_t entry_cap_ = 0, vis_cap_ = 0, enter_cap_ = 0;  // sizes asked for (see args())
  std::uint64_t last_vis_ = 0, last_enter_ = 0, last_leave_ = 0;
};

}  // namespace
}  // namespace detail::vis

std::unique_ptr<interest::visibility_engine> make_visibility_engine(interest::thread_pool* pool, std::string* why) {
  if (!device_available(nullptr, why)) return nullptr;
  try {
    return std::make_unique<detail::vis::engine>(pool);
  } catch (const std::exception& e) {
    if (why) *why = e.what();
    return nullptr;
  }
}

}  // namespace zone::gpu
