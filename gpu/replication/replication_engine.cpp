// Host dispatch of the GPU replication engine (gpu/replication.h; algorithm in docs/zone.md,
// "Replication on the GPU").
//
// One run, on one stream, with up to three host synchronisations (dozing, then spinning, by
// default; spinning or blocking throughout: set_device_wait):
//  1. The caller filled the pinned staging (entities, slot map, jobs, visible sets); the client
//     table (where each view is and goes, each client's job) is laid out here from the views'
//     sizes the host mirrors, and everything is copied up at once (the entities and the slot map
//     earlier, when the caller handed them over ahead: stage_entities, upload_entities).
//  2. Every entity's wire update is quantized (one thread per entity); views of clients without a
//     job are copied into the new view buffer (one warp per client); one warp per job decides its
//     frame, writes its record (atomic cursor) and its new view.
//     Each job writes its whole frame in the canonical layout (replication_frame_format) but
//     for its enters' class, extents and kind, which the caller fills in.
//  3. The results and the cursor come back; then the frames, exactly the bytes used.
//  The two view buffers are swapped: a run that fails leaves the engine unusable until
//  forget_all().
#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cstring>
#include <memory>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "gpu/common/cuda_check.h"
#include "gpu/common/gpu_buffers.h"
#include "gpu/device.h"
#include "gpu/replication.h"
#include "replication_launch.h"

namespace zone::gpu {
namespace detail::rep {
namespace {

template <class T>
using device_array = mem::device_array<T>;
template <class T>
using pinned_array = mem::pinned_array<T>;

class engine final : public interest::replication_engine {
 public:
  engine() {
    CUDA_CHECK(cudaSetDevice(0));
    CUDA_CHECK(cudaStreamCreateWithFlags(&stream_, cudaStreamNonBlocking));
    for (cudaEvent_t* e : {&ev_begin_, &ev_up_, &ev_kernels_, &ev_down_}) CUDA_CHECK(cudaEventCreate(e));
    CUDA_CHECK(cudaEventCreateWithFlags(&ev_sync_, cudaEventBlockingSync | cudaEventDisableTiming));
    d_cursor_.reserve(2);
    h_cursor_.reserve(2);
  }
  ~engine() override {
    if (stream_ != nullptr) cudaStreamSynchronize(stream_);
    for (cudaEvent_t e : {ev_begin_, ev_up_, ev_kernels_, ev_down_, ev_sync_}) {
      if (e != nullptr) cudaEventDestroy(e);
    }
    if (stream_ != nullptr) cudaStreamDestroy(stream_);
  }

  [[nodiscard]] const char* name() const override { return "gpu"; }
  [[nodiscard]] const interest::replication_timing& timing() const override { return timing_; }

  staging stage(std::size_t entities, std::size_t slots, std::size_t jobs, std::size_t visible) override {
    if (entities > 0xffffffffu || slots > 0xffffffffu || jobs > 0xffffffffu || visible > 0xffffffffu) {
      throw std::invalid_argument("replication engine: more than 2^32 entities, slots, jobs or visible entries");
    }
    // Entities uploaded ahead (stage_entities, upload_entities) stay if the counts are the same.
    if (uploaded_ && (entities != n_entities_ || slots != n_slots_)) uploaded_ = false;
    h_entities_.reserve(entities);
    h_slot_dense_.reserve(slots);
    h_jobs_.reserve(jobs);
    h_visible_.reserve(visible);
    n_entities_ = entities;
    n_slots_ = slots;
    n_jobs_ = jobs;
    n_visible_ = visible;
    return {h_entities_.get(), h_slot_dense_.get(), h_jobs_.get(), h_visible_.get()};
  }

  staging stage_entities(std::size_t entities, std::size_t slots) override {
    if (entities > 0xffffffffu || slots > 0xffffffffu) {
      throw std::invalid_argument("replication engine: more than 2^32 entities or slots");
    }
    uploaded_ = false;
    h_entities_.reserve(entities);
    h_slot_dense_.reserve(slots);
    n_entities_ = entities;
    n_slots_ = slots;
    return {h_entities_.get(), h_slot_dense_.get(), nullptr, nullptr};
  }

  /// The staged entities and slot map copied up now, on the run's stream (so run()'s kernels see
  /// them), while the caller goes on.
  void upload_entities() override {
    d_entities_.reserve(n_entities_);
    d_slot_dense_.reserve(n_slots_);
    if (n_entities_ > 0) {
      CUDA_CHECK(cudaMemcpyAsync(d_entities_.get(), h_entities_.get(), n_entities_ * sizeof(interest::replication_entity),
                                 cudaMemcpyHostToDevice, stream_));
    }
    if (n_slots_ > 0) {
      CUDA_CHECK(cudaMemcpyAsync(d_slot_dense_.get(), h_slot_dense_.get(), n_slots_ * sizeof(std::uint32_t),
                                 cudaMemcpyHostToDevice, stream_));
    }
    uploaded_ = true;
  }
  void discard_entities() override { uploaded_ = false; }

  [[nodiscard]] bool reads_resident() const override { return true; }
  void set_device_wait(device_wait how) override { how_ = how; }
  void set_frame_format(const interest::replication_frame_format& format) override {
    format_ = format;
    d_format_.reserve(1);
    CUDA_CHECK(cudaMemcpy(d_format_.get(), &format_, sizeof format_, cudaMemcpyHostToDevice));
    has_format_ = true;
  }

  output run(const interest::replication_rules& rules, std::size_t client_count,
             const interest::visibility_engine::resident_lists* rows,
             const std::function<void()>* while_waiting) override {
    const auto t0 = std::chrono::steady_clock::now();
    const double grown_before = mem::grow_ms;
    wait_ms_ = 0;
    dozes_ = 0;
    if (rules.leave_cost == 0 || rules.enter_cost == 0 || rules.update_cost == 0) {
      throw std::invalid_argument("replication engine: entry costs must be positive");
    }
    if (!has_format_) throw std::logic_error("replication engine: run() before set_frame_format()");
    const bool resident = rows != nullptr && rows->data != nullptr && rows->off != nullptr && rows->rows > 0;
    if (resident && rows->rows >= 0xffffffffu) throw std::invalid_argument("replication engine: too many rows");
    grow_clients(client_count);
    h_clients_.reserve(client_count);
    h_new_off_.reserve(client_count + 1);
    client_slot* cl = h_clients_.get();
    const interest::replication_job* jobs = h_jobs_.get();
    table_clients(jobs, n_jobs_, n_visible_, resident ? rows->rows : 0, len_.data(), off_.data(), client_count, cl);
    d_entities_.reserve(n_entities_);
    d_updates_.reserve(4 * n_entities_);
    d_slot_dense_.reserve(n_slots_);
    d_jobs_.reserve(n_jobs_);
    d_visible_.reserve(resident ? 1 : n_visible_);
    d_clients_.reserve(client_count);
    d_new_off_.reserve(client_count + 1);
    d_results_.reserve(n_jobs_);
    h_results_.reserve(n_jobs_);

    run_args a{};
    a.rules = rules;
    a.entities = d_entities_.get();
    a.entity_count = static_cast<std::uint32_t>(n_entities_);
    a.updates = d_updates_.get();
    a.format = d_format_.get();
    a.slot_dense = d_slot_dense_.get();
    a.slot_count = static_cast<std::uint32_t>(n_slots_);
    a.jobs = d_jobs_.get();
    a.job_count = static_cast<std::uint32_t>(n_jobs_);
    a.visible = d_visible_.get();
    if (resident) {
      a.rows_data = rows->data;
      a.rows_off = rows->off;
      a.row_count = static_cast<std::uint32_t>(rows->rows);
    }
    a.clients = d_clients_.get();
    a.client_count = static_cast<std::uint32_t>(client_count);
    a.new_off = d_new_off_.get();

    CUDA_CHECK(cudaEventRecord(ev_begin_, stream_));
    const auto up = [&](void* d, const void* h, std::size_t bytes) {
      if (bytes > 0) CUDA_CHECK(cudaMemcpyAsync(d, h, bytes, cudaMemcpyHostToDevice, stream_));
    };
    if (!uploaded_) upload_entities();  // not handed over ahead: copied up now (reserved above)
    uploaded_ = false;                   // the next run's are staged afresh
    up(d_jobs_.get(), h_jobs_.get(), n_jobs_ * sizeof(interest::replication_job));
    up(d_clients_.get(), h_clients_.get(), client_count * sizeof(client_slot));
    std::uint64_t total = 0, record_cap = 0;
    if (!resident) {
      // The sizes are here: plan on the host.
      total = plan_staged(jobs, cl, client_count, rules, format_, h_new_off_.get(), record_cap);
      up(d_visible_.get(), h_visible_.get(), n_visible_ * sizeof(std::uint32_t));
      up(d_new_off_.get(), h_new_off_.get(), (client_count + 1) * sizeof(std::uint32_t));
    } else if (client_count > 0) {
      // The sizes are on the device (the rows' lengths): plan there, read back the totals.
      d_rooms_.reserve(client_count + 1);
      d_record_bounds_.reserve(client_count);
      d_sum_.reserve(1);
      h_sum_.reserve(1);
      CUDA_CHECK(launch_rooms(a, d_rooms_.get(), d_record_bounds_.get(), stream_));
      std::size_t temp = 0;
      CUDA_CHECK(scan_rooms(nullptr, temp, d_rooms_.get(), d_new_off_.get(), static_cast<std::uint32_t>(client_count + 1),
                            d_record_bounds_.get(), d_sum_.get(), static_cast<std::uint32_t>(client_count), stream_));
      d_temp_.reserve(std::max<std::size_t>(temp, 256));
      temp = d_temp_.capacity();
      CUDA_CHECK(scan_rooms(d_temp_.get(), temp, d_rooms_.get(), d_new_off_.get(),
                            static_cast<std::uint32_t>(client_count + 1), d_record_bounds_.get(), d_sum_.get(),
                            static_cast<std::uint32_t>(client_count), stream_));
      CUDA_CHECK(cudaMemcpyAsync(h_new_off_.get() + client_count, d_new_off_.get() + client_count, sizeof(std::uint32_t),
                                 cudaMemcpyDeviceToHost, stream_));
      CUDA_CHECK(cudaMemcpyAsync(h_sum_.get(), d_sum_.get(), sizeof(std::uint64_t), cudaMemcpyDeviceToHost, stream_));
      wait(wait_totals, std::chrono::steady_clock::now());
      total = h_new_off_.get()[client_count];
      record_cap = h_sum_.get()[0];
    }
    CUDA_CHECK(cudaMemsetAsync(d_cursor_.get(), 0, 2 * sizeof(std::uint32_t), stream_));
    CUDA_CHECK(cudaEventRecord(ev_up_, stream_));
    const int next = 1 - cur_;
    d_id_[next].reserve(total);
    d_sent_[next].reserve(total);
    d_scratch_.reserve(total);
    d_records_.reserve(record_cap);
    a.old_id = d_id_[cur_].get();
    a.old_sent = d_sent_[cur_].get();
    a.new_id = d_id_[next].get();
    a.new_sent = d_sent_[next].get();
    a.scratch = d_scratch_.get();
    a.hash = d_hash_.get();
    a.records = d_records_.get();
    a.record_capacity = record_cap;
    a.cursor = d_cursor_.get();
    a.results = d_results_.get();
    CUDA_CHECK(launch_quantize(a, stream_));
    CUDA_CHECK(launch_carry(a, stream_));
    CUDA_CHECK(launch_decide(a, stream_));
    CUDA_CHECK(cudaEventRecord(ev_kernels_, stream_));
    if (n_jobs_ > 0) {
      CUDA_CHECK(cudaMemcpyAsync(h_results_.get(), d_results_.get(), n_jobs_ * sizeof(interest::replication_result),
                                 cudaMemcpyDeviceToHost, stream_));
    }
    if (resident && client_count > 0) {
      CUDA_CHECK(cudaMemcpyAsync(h_new_off_.get(), d_new_off_.get(), client_count * sizeof(std::uint32_t),
                                 cudaMemcpyDeviceToHost, stream_));
    }
    CUDA_CHECK(cudaMemcpyAsync(h_cursor_.get(), d_cursor_.get(), 2 * sizeof(std::uint32_t), cudaMemcpyDeviceToHost,
                               stream_));
    const auto kernels_queued = std::chrono::steady_clock::now();
    // The caller's host work, in the kernels' shadow (their results and copies are queued).
    if (while_waiting != nullptr && *while_waiting) (*while_waiting)();
    wait(wait_kernels, kernels_queued);
    if (h_cursor_.get()[1] == flag_list_too_long) {
      throw std::invalid_argument("replication engine: a client's view or visible set is longer than 2^29 entries");
    }
    if (h_cursor_.get()[1] != 0) throw std::runtime_error("replication engine: record buffer overflow (a bug)");
    const std::uint32_t used = h_cursor_.get()[0];
    records_peak_ = std::max<std::size_t>(records_peak_, used);
    // The pinned copy is sized by the bytes used, not by the bound (about 14 times more at 20,000
    // clients): its growth, a cudaFreeHost and a cudaHostAlloc, stalled ramp-up ticks for 30-90 ms.
    // It goes to a kept buffer nothing holds any more (the caller may then hand the frames on
    // without a copy: output::records_keep), else to the engine's own.
    std::shared_ptr<kept_records> keep = free_kept(used);
    std::uint8_t* records = nullptr;
    if (keep != nullptr) {
      records = keep->bytes.get();
    } else {
      h_records_.reserve(used);
      records = h_records_.get();
    }
    if (used > 0) {
      CUDA_CHECK(cudaMemcpyAsync(records, d_records_.get(), used, cudaMemcpyDeviceToHost, stream_));
    }
    CUDA_CHECK(cudaEventRecord(ev_down_, stream_));
    wait(wait_records, std::chrono::steady_clock::now());

    // The views moved: the new buffer is the current one.
    cur_ = next;
    const std::uint32_t* new_off = h_new_off_.get();
    for (std::size_t c = 0; c < client_count; ++c) off_[c] = new_off[c];
    const interest::replication_result* res = h_results_.get();
    for (std::size_t k = 0; k < n_jobs_; ++k) len_[jobs[k].client] = res[k].view_size;

    timing_.upload_ms = elapsed_ms(ev_begin_, ev_up_);
    timing_.device_ms = elapsed_ms(ev_up_, ev_kernels_);
    timing_.download_ms = elapsed_ms(ev_kernels_, ev_down_);
    timing_.record_bytes = used;
    timing_.resident = resident;
    timing_.wait_ms = wait_ms_;
    timing_.dozes = dozes_;
    timing_.alloc_ms = mem::grow_ms - grown_before;
    timing_.kept = keep != nullptr;
    timing_.total_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    return {h_results_.get(), records, std::move(keep)};
  }

  void forget_all() override {
    std::fill(len_.begin(), len_.end(), 0u);
    std::fill(off_.begin(), off_.end(), 0u);
  }

  /// Buffer by buffer while the time left exceeds 1.5 times the longest of the last eight of its
  /// growths (10 ms before any, at least 1 ms): a free kept buffer with room for the most record
  /// bytes a run used and an eighth more (the first free one grown, or a new one, to 1.5 times
  /// those bytes), then the device arrays each run fills afresh, each to 1.5 times its last size
  /// where less than an eighth is left. Each new block is allocated before the old one is freed
  /// (mem::array::grow_ahead_to: one that finds no memory keeps its block and is not grown ahead
  /// again). Not the current views (d_id_, d_sent_ of cur_), the hashes, the format, a kept
  /// buffer frames still hold, the staging and results the caller was handed, or entities
  /// uploaded ahead.
  double grow_ahead(std::chrono::steady_clock::time_point deadline) override {
    const double before = mem::grow_ms;
    const auto room = [&] {
      const double expect = recent_grows_ == 0
                                ? 10.0
                                : std::max(1.0, *std::max_element(recent_grow_ms_.begin(),
                                                                  recent_grow_ms_.begin() +
                                                                      std::min(recent_grows_, recent_grow_ms_.size())));
      const double left =
          std::chrono::duration<double, std::milli>(deadline - std::chrono::steady_clock::now()).count();
      return left > 1.5 * expect;
    };
    const auto timed = [&](auto&& grow) {
      const double at = mem::grow_ms;
      if (grow()) recent_grow_ms_[recent_grows_++ % recent_grow_ms_.size()] = mem::grow_ms - at;
    };
    if (records_peak_ > 0) {
      const std::size_t want = records_peak_ + records_peak_ / 8;
      std::shared_ptr<kept_records>* grow = nullptr;
      bool ready = false;
      for (auto& k : kept_) {
        if (k.use_count() != 1) continue;
        if (k->bytes.capacity() >= want) {
          ready = true;
          break;
        }
        if (grow == nullptr) grow = &k;
      }
      if (!ready && room()) {
        if (grow == nullptr && kept_.size() < max_kept) grow = &kept_.emplace_back(std::make_shared<kept_records>());
        if (grow != nullptr) {
          std::atomic_thread_fence(std::memory_order_acquire);  // as in free_kept: its last holder is done
          timed([&] { return (*grow)->bytes.grow_ahead_to(records_peak_ + records_peak_ / 2); });
        }
      }
    }
    const auto ahead = [&](auto&... arrays) { ((room() ? timed([&] { return arrays.grow_ahead(); }) : void()), ...); };
    const int next = 1 - cur_;
    ahead(d_records_, d_scratch_, d_id_[next], d_sent_[next]);
    if (!uploaded_) ahead(d_entities_, d_slot_dense_);
    ahead(d_updates_, d_jobs_, d_clients_, d_new_off_, d_results_, d_rooms_, d_record_bounds_);
    return mem::grow_ms - before;
  }

 private:
  /// The run's three waits: for the plan's totals, the kernels (with the results), the records.
  enum wait_point { wait_totals, wait_kernels, wait_records, wait_points };

  /// Waits for everything queued on the stream, queued by `since`: sleeping on a blocking-sync
  /// event, spinning in cudaStreamSynchronize, or dozing first (set_device_wait). Adds the time
  /// to wait_ms_ and remembers how long the work took, from `since`, for the doze.
  void wait(wait_point point, std::chrono::steady_clock::time_point since) {
    const auto t0 = std::chrono::steady_clock::now();
    if (how_ == device_wait::block) {
      CUDA_CHECK(cudaEventRecord(ev_sync_, stream_));
      CUDA_CHECK(cudaEventSynchronize(ev_sync_));
    } else {
      if (how_ == device_wait::doze) doze(point, since);
      CUDA_CHECK(cudaStreamSynchronize(stream_));
    }
    const auto t1 = std::chrono::steady_clock::now();
    wait_ms_ += std::chrono::duration<double, std::milli>(t1 - t0).count();
    past_[point][next_past_[point]++ % past_[point].size()] = std::chrono::duration<double, std::milli>(t1 - since).count();
  }

  /// Sleeps until the work queued by `since` is expected to be nearly done: the shortest of this
  /// wait's last eight durations, less a margin (a quarter of it, at least 0.15 ms: the sleep's
  /// overshoot and the wake-up stay inside the device's work). Nothing when fewer than eight
  /// are known, when the expectation is under 0.4 ms, or when the stream is already done.
  void doze(wait_point point, std::chrono::steady_clock::time_point since) {
    if (next_past_[point] < past_[point].size()) return;
    const double expect = *std::min_element(past_[point].begin(), past_[point].end());
    if (expect < 0.4) return;
    const double sleep_ms = expect - std::max(0.25 * expect, 0.15);
    const auto until = since + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                   std::chrono::duration<double, std::milli>(sleep_ms));
    if (std::chrono::steady_clock::now() >= until) return;
    if (cudaStreamQuery(stream_) != cudaErrorNotReady) return;  // done (or failed: the synchronize says)
    std::this_thread::sleep_until(until);
    ++dozes_;
  }

  /// A pinned buffer of frames the caller may hold (output::records_keep).
  struct kept_records {
    pinned_array<std::uint8_t> bytes;
  };
  /// The most kept buffers: two alternate while frames are sent within a tick or so; more only
  /// while clients read slowly; past them the frames are copied again (records_keep null).
  static constexpr std::size_t max_kept = 4;

  /// A kept buffer of at least `bytes` bytes that only the engine holds (one already big enough
  /// first; else one grown, or a new one while there are fewer than max_kept), or null.
  std::shared_ptr<kept_records> free_kept(std::size_t bytes) {
    std::shared_ptr<kept_records>* pick = nullptr;
    for (auto& k : kept_) {
      if (k.use_count() != 1) continue;
      if (k->bytes.capacity() >= bytes) {
        pick = &k;
        break;
      }
      if (pick == nullptr) pick = &k;
    }
    if (pick == nullptr) {
      if (kept_.size() >= max_kept) return nullptr;
      pick = &kept_.emplace_back(std::make_shared<kept_records>());
    }
    // The last holder released it (its reads of the frames done) before the count read 1.
    std::atomic_thread_fence(std::memory_order_acquire);
    (*pick)->bytes.reserve(bytes);
    return *pick;
  }

  /// Per-client arrays for client_count clients; the device's hashes keep their values.
  void grow_clients(std::size_t n) {
    if (n > len_.size()) {
      len_.resize(n, 0);
      off_.resize(n, 0);
    }
    if (n > hash_cap_) {
      const std::size_t cap = std::max(n, hash_cap_ + hash_cap_ / 2);
      device_array<std::uint64_t> grown;
      grown.reserve(cap);
      CUDA_CHECK(cudaMemsetAsync(grown.get(), 0, cap * sizeof(std::uint64_t), stream_));
      if (hash_cap_ > 0) {
        CUDA_CHECK(cudaMemcpyAsync(grown.get(), d_hash_.get(), hash_cap_ * sizeof(std::uint64_t),
                                   cudaMemcpyDeviceToDevice, stream_));
      }
      CUDA_CHECK(cudaStreamSynchronize(stream_));
      d_hash_.swap(grown);
      hash_cap_ = cap;
    }
  }

  cudaStream_t stream_ = nullptr;
  cudaEvent_t ev_begin_ = nullptr, ev_up_ = nullptr, ev_kernels_ = nullptr, ev_down_ = nullptr;
  cudaEvent_t ev_sync_ = nullptr;  // blocking-sync: wait() sleeps on it
  device_wait how_ = device_wait::doze;
  bool uploaded_ = false;  // the staged entities and slot map are on the device (upload_entities)
  std::array<std::array<double, 8>, wait_points> past_{};  // by wait point: its last durations (ms)
  std::array<std::size_t, wait_points> next_past_{};
  std::uint32_t dozes_ = 0;  // this run's
  double wait_ms_ = 0;
  std::size_t n_entities_ = 0, n_slots_ = 0, n_jobs_ = 0, n_visible_ = 0;
  pinned_array<interest::replication_entity> h_entities_;
  pinned_array<std::uint32_t> h_slot_dense_, h_visible_, h_cursor_;
  pinned_array<interest::replication_job> h_jobs_;
  pinned_array<client_slot> h_clients_;
  pinned_array<interest::replication_result> h_results_;
  pinned_array<std::uint8_t> h_records_;
  std::vector<std::shared_ptr<kept_records>> kept_;
  std::size_t records_peak_ = 0;            // the most record bytes a run used
  std::array<double, 8> recent_grow_ms_{};  // grow_ahead's last growths, one array each (ms)
  std::size_t recent_grows_ = 0;            // how many so far
  device_array<interest::replication_entity> d_entities_;
  device_array<std::uint32_t> d_updates_;  // 4 words per entity: its wire update
  interest::replication_frame_format format_;
  device_array<interest::replication_frame_format> d_format_;
  bool has_format_ = false;
  device_array<std::uint32_t> d_slot_dense_, d_visible_, d_cursor_;
  device_array<interest::replication_job> d_jobs_;
  device_array<client_slot> d_clients_;
  device_array<interest::replication_result> d_results_;
  device_array<std::uint8_t> d_records_;
  device_array<std::uint32_t> d_id_[2], d_sent_[2];
  device_array<scratch_entry> d_scratch_;
  device_array<std::uint64_t> d_hash_;
  pinned_array<std::uint32_t> h_new_off_;
  pinned_array<std::uint64_t> h_sum_;
  device_array<std::uint32_t> d_new_off_, d_rooms_;
  device_array<std::uint64_t> d_record_bounds_, d_sum_;
  device_array<unsigned char> d_temp_;
  std::size_t hash_cap_ = 0;
  int cur_ = 0;
  std::vector<std::uint32_t> len_, off_;  // by client: its view's size and place in d_id_[cur_]
  interest::replication_timing timing_;
};

}  // namespace
}  // namespace detail::rep

std::unique_ptr<interest::replication_engine> make_replication_engine(std::string* why) {
  if (!device_available(nullptr, why)) return nullptr;
  try {
    return std::make_unique<detail::rep::engine>();
  } catch (const std::exception& e) {
    if (why) *why = e.what();
    return nullptr;
  }
}

}  // namespace zone::gpu
