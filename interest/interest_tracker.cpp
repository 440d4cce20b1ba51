// The interest tracker (interest_tracker.h): every update on a visibility engine, the rows and the
// lists of the last update, the hand-over of the sets when the engine changes.
#include "interest_tracker.h"

#include <algorithm>
#include <chrono>
#include <functional>
#include <utility>

#include "measure.h"

namespace zone::interest {

namespace {

using clock_type = std::chrono::steady_clock;

constexpr std::uint32_t no_row = 0xffffffffu;

template <class F>
void run_each(thread_pool* pool, std::size_t n, F&& task) {
  run_tasks(pool, n, std::ref(task));
}

std::uint64_t mix(std::uint64_t h, std::uint64_t v) {
  h ^= v + 0x9e3779b97f4a7c15ull + (h << 6) + (h >> 2);
  return h * 0xff51afd7ed558ccdull;
}

/// Entries of a list's n rows (compact: off[n] - off[0]).
std::uint64_t list_total(const std::uint32_t* off, const std::uint32_t* len, std::size_t n) {
  if (n == 0) return 0;
  if (len == nullptr) return off[n] - off[0];
  std::uint64_t sum = 0;
  for (std::size_t r = 0; r < n; ++r) sum += len[r];
  return sum;
}

host_engine_options engine_options(const interest_options& opt) {
  host_engine_options e;
  e.rows_per_task = opt.rows_per_task;
  e.finder_view = opt.finder_view;
  e.presence_grid = opt.presence_grid;
  return e;
}

}  // namespace

interest_tracker::interest_tracker(pair_finder& finder, thread_pool* pool, interest_options opt)
    : pool_(pool), opt_(opt), reference_(finder, pool, engine_options(opt)) {}

void interest_tracker::set_options(const interest_options& opt) {
  opt_ = opt;
  reference_.set_options(engine_options(opt));
}

std::size_t interest_tracker::row_of(entity_id id) const {
  const std::uint32_t slot = slot_of(id);
  if (id == null_entity || slot >= row_of_slot_.size()) return npos;
  const std::uint32_t row = row_of_slot_[slot];
  if (row >= ids_.size() || ids_[row] != id) return npos;
  return row;
}

visibility_input interest_tracker::input_of(const entity_columns& in) const {
  visibility_input v;
  v.n = in.n;
  v.ids = in.ids;
  v.slot_bits = slot_bits_;
  v.slot_count = slot_count_;
  v.position = reinterpret_cast<const float*>(in.position);
  v.aoi_half = reinterpret_cast<const float*>(in.aoi_half);
  v.body_half = reinterpret_cast<const float*>(in.presence_half);
  v.visibility = in.visibility;
  v.sees = in.sees;
  v.hysteresis = opt_.hysteresis;
  v.max_visible = opt_.max_visible;
  v.static_version = in.layout_version;
  return v;
}

void interest_tracker::build_boxes(const entity_columns& in, box_set& out) const {
  visibility_input v = input_of(in);
  v.slot_bits = in.slot_bits;
  build_step_boxes(v, out, pool_);
}

void interest_tracker::begin_update(const entity_columns& in) {
  slot_bits_ = in.slot_bits;
  std::size_t slots = in.slot_count;
  if (slots == 0) {
    for (std::size_t i = 0; i < in.n; ++i) slots = std::max<std::size_t>(slots, slot_of(in.ids[i]) + std::size_t{1});
  }
  slot_count_ = std::max(slot_count_, slots);
}

std::optional<box_error> interest_tracker::update(const entity_columns& in) {
  begin_update(in);
  visibility_engine* e = active();
  if (e != &reference_) {
    try {
      return run(*e, in);
    } catch (const std::exception& ex) {
      // A device error: the host reference takes over from the last update's sets, which are
      // intact (run changes the tracker only after the engine's call succeeded).
      engine_error_ = ex.what();
      holder_ = nullptr;  // the failed engine's state is unspecified
    }
  }
  try {
    return run(reference_, in);
  } catch (const std::length_error& ex) {
    return box_error{0, ex.what()};  // more candidates than 32-bit offsets hold: nothing changed
  }
}

std::optional<box_error> interest_tracker::name_box_error(const entity_columns& in, std::optional<box_error> err) const {
  if (!err) return err;
  const std::size_t k = err->index / 2;
  if (k >= in.n) return err;
  err->message = "entity " + std::to_string(in.ids[k]) + (err->index % 2 ? " (presence box): " : " (AOI box): ") +
                 err->message;
  return err;
}

void interest_tracker::set_engine(visibility_engine* engine) {
  adopt();  // the lists stay readable whatever becomes of the engine they came from
  if (holder_ != &reference_) holder_ = nullptr;
  engine_ = engine;
  engine_error_.clear();
}

void interest_tracker::map_rows_into(const std::vector<entity_id>& ids, std::vector<std::uint32_t>& row_of_slot) const {
  // Entries of slots not in `ids` may be stale; row_of() checks the handle.
  const std::size_t n = ids.size();
  if (row_of_slot.size() < slot_count_) row_of_slot.resize(slot_count_, no_row);
  const std::size_t chunk = 16384;
  run_each(n > chunk ? pool_ : nullptr, (n + chunk - 1) / chunk, [&](std::size_t c) {
    for (std::size_t i = c * chunk, e = std::min(n, (c + 1) * chunk); i < e; ++i) {
      row_of_slot[slot_of(ids[i])] = static_cast<std::uint32_t>(i);
    }
  });
}

std::span<const entity_id> interest_tracker::fetched_row(std::size_t row) const {
  if (!fetched_.load(std::memory_order_acquire)) {
    const std::lock_guard lock(fetch_mutex_);
    if (!fetched_.load(std::memory_order_relaxed)) {
      const visibility_lists all = producer_->fetch_all_visible();
      full_list_ = {all.data, all.off, nullptr};
      fetched_.store(true, std::memory_order_release);
    }
  }
  return full_list_.row(row);
}

void interest_tracker::adopt() {
  if (producer_ == nullptr) return;
  const std::size_t n = ids_.size();
  // Every row's visible set: the engine may have kept some rows' sets on the device. If the device
  // is gone (an engine failure), those rows start again from empty sets (their targets enter anew;
  // nothing on the host read them).
  bool device_lost = false;
  if (partial_ && n > 0) {
    try {
      (void)fetched_row(0);
    } catch (const std::exception&) {
      device_lost = true;
    }
  }
  const auto visible_row = [&](std::size_t r) -> std::span<const entity_id> {
    if (!partial_ || demand_rows_[r] != 0) return vis_list_.row(r);
    if (device_lost) return {};
    return full_list_.row(r);
  };
  own_vis_off_.resize(n + 1);
  own_enter_off_.resize(n + 1);
  own_leave_off_.resize(n + 1);
  own_vis_off_[0] = own_enter_off_[0] = own_leave_off_[0] = 0;
  for (std::size_t r = 0; r < n; ++r) {
    const std::size_t len = visible_row(r).size();
    const std::size_t en = enter_list_.row(r).size();
    own_vis_off_[r + 1] = own_vis_off_[r] + static_cast<std::uint32_t>(len);
    // Enters are a subset of the visible set: none for a row lost with the device.
    own_enter_off_[r + 1] = own_enter_off_[r] + static_cast<std::uint32_t>(en <= len ? en : 0);
    own_leave_off_[r + 1] = own_leave_off_[r] + static_cast<std::uint32_t>(leave_list_.row(r).size());
  }
  own_vis_.resize(own_vis_off_[n]);
  own_enter_.resize(own_enter_off_[n]);
  own_leave_.resize(own_leave_off_[n]);
  for (std::size_t r = 0; r < n; ++r) {
    const auto vis = visible_row(r);
    std::copy(vis.begin(), vis.end(), own_vis_.begin() + own_vis_off_[r]);
    const auto en = enter_list_.row(r).first(own_enter_off_[r + 1] - own_enter_off_[r]);
    std::copy(en.begin(), en.end(), own_enter_.begin() + own_enter_off_[r]);
    const auto lv = leave_list_.row(r);
    std::copy(lv.begin(), lv.end(), own_leave_.begin() + own_leave_off_[r]);
  }
  vis_list_ = {own_vis_.data(), own_vis_off_.data(), nullptr};
  enter_list_ = {own_enter_.data(), own_enter_off_.data(), nullptr};
  leave_list_ = {own_leave_.data(), own_leave_off_.data(), nullptr};
  partial_ = false;
  producer_ = nullptr;
}

void interest_tracker::hand_over(visibility_engine& e) {
  adopt();
  if (ids_.empty()) {
    e.load_previous({}, slot_bits_, {}, {});
  } else {
    e.load_previous(ids_, slot_bits_, own_vis_off_, own_vis_);
  }
  holder_ = &e;
}

void interest_tracker::carry_visible(entity_id observer, std::span<const entity_id> targets) {
  if (observer == null_entity) return;
  carry_.emplace_back(observer, null_entity);  // the observer is carried, even with no targets
  for (const entity_id t : targets) {
    if (t != null_entity && t != observer) carry_.emplace_back(observer, t);
  }
}

void interest_tracker::hand_over_carried(visibility_engine& e, const entity_columns& in) {
  adopt();
  // This update's rows and slot map (commit swaps them in): which carried handles it holds.
  next_ids_.assign(in.ids, in.ids + in.n);
  map_rows_into(next_ids_, spare_row_of_slot_);
  const auto in_update = [&](entity_id id) {
    const std::uint32_t slot = slot_of(id);
    if (slot >= spare_row_of_slot_.size()) return false;
    const std::uint32_t r = spare_row_of_slot_[slot];
    return r < next_ids_.size() && next_ids_[r] == id;
  };
  std::sort(carry_.begin(), carry_.end());
  carry_.erase(std::unique(carry_.begin(), carry_.end()), carry_.end());
  // Groups of carried targets per observer (ascending, unique), each with the last update's row of
  // its slot (the observer's own or another generation's: either is replaced), or none.
  struct group {
    entity_id observer;
    std::size_t first, last;  // in targets
  };
  std::vector<group> groups;
  std::vector<entity_id> targets;
  std::vector<std::uint32_t> group_of_row(ids_.size(), no_row);
  for (std::size_t k = 0; k < carry_.size();) {
    const entity_id o = carry_[k].first;
    std::size_t end = k;
    while (end < carry_.size() && carry_[end].first == o) ++end;
    if (in_update(o)) {
      const std::size_t first = targets.size();
      for (std::size_t j = k; j < end; ++j) {
        if (carry_[j].second != null_entity && in_update(carry_[j].second)) targets.push_back(carry_[j].second);
      }
      const std::uint32_t slot = slot_of(o);
      std::uint32_t r = slot < row_of_slot_.size() ? row_of_slot_[slot] : no_row;
      if (r >= ids_.size() || slot_of(ids_[r]) != slot) r = no_row;  // a stale entry
      if (r != no_row) group_of_row[r] = static_cast<std::uint32_t>(groups.size());
      groups.push_back({o, first, targets.size()});
    }
    k = end;
  }
  // The previous rows: the last update's, the carried sets in place of their observers' rows (and
  // of rows of another generation of their slots), then the carried observers that had none.
  carry_ids_.clear();
  carry_vis_.clear();
  carry_off_.assign(1, 0);
  const auto close_row = [&] { carry_off_.push_back(static_cast<std::uint32_t>(carry_vis_.size())); };
  for (std::size_t r = 0; r < ids_.size(); ++r) {
    const auto old = vis_list_.row(r);
    const std::uint32_t g = group_of_row[r];
    if (g == no_row) {
      carry_ids_.push_back(ids_[r]);
      carry_vis_.insert(carry_vis_.end(), old.begin(), old.end());
      close_row();
    }
  }
  for (const group& c : groups) {
    carry_ids_.push_back(c.observer);
    carry_vis_.insert(carry_vis_.end(), targets.begin() + static_cast<std::ptrdiff_t>(c.first),
                      targets.begin() + static_cast<std::ptrdiff_t>(c.last));
    close_row();
  }
  e.load_previous(carry_ids_, slot_bits_, carry_off_, carry_vis_);
  holder_ = nullptr;  // `e` holds these sets, not the last update's: until the commit
}

std::optional<box_error> interest_tracker::run(visibility_engine& e, const entity_columns& in) {
  const auto t0 = clock_type::now();
  const std::size_t n = in.n;
  if (!carry_.empty()) {
    hand_over_carried(e, in);
  } else if (holder_ != &e) {
    hand_over(e);  // the engine does not hold the last update's sets
  }
  visibility_input vin = input_of(in);
  if (view_demand_ != nullptr) {
    // Per row: is its visible set read on the host (by slot, from the caller).
    next_demand_rows_.resize(n);
    const std::vector<std::uint8_t>& by_slot = *view_demand_;
    const std::size_t chunk = 16384;
    run_each(n > chunk ? pool_ : nullptr, (n + chunk - 1) / chunk, [&](std::size_t c) {
      for (std::size_t i = c * chunk, end = std::min(n, (c + 1) * chunk); i < end; ++i) {
        const std::uint32_t slot = slot_of(in.ids[i]);
        next_demand_rows_[i] = slot < by_slot.size() ? by_slot[slot] : std::uint8_t{0};
      }
    });
    vin.wanted = next_demand_rows_.data();
  }
  // While the device works (an engine with one calls this): this update's rows and slot map,
  // into spare buffers (swapped in only if the update succeeds, so that a refused one changes
  // nothing here either).
  double host_ms = 0;
  bool host_done = false;
  const auto host_work = [&] {
    host_done = true;
    const auto th = clock_type::now();
    next_ids_.assign(in.ids, in.ids + n);
    map_rows_into(next_ids_, spare_row_of_slot_);
    host_ms = ms_since(th);
    if (while_device_works_ != nullptr && *while_device_works_) (*while_device_works_)();
  };
  // By reference: std::function keeps a reference_wrapper in place (the lambda's captures would
  // be copied to the heap, one allocation a tick).
  vin.while_waiting = std::ref(host_work);
  const auto t_engine = clock_type::now();
  const auto bad = e.update(vin, out_);
  const double engine_ms = ms_since(t_engine);
  if (bad) {
    // Nothing changed, on the engine or here. The box is described as the host's validation
    // would (the same float expressions).
    std::optional<box_error> err;
    if (*bad < 2 * n) err = validate_box(step_box(vin, *bad), *bad);
    if (!err) err = box_error{*bad, "box " + std::to_string(*bad) + " is invalid"};
    return name_box_error(in, std::move(err));
  }
  commit(e, in, engine_ms, host_ms, host_done);
  stats_.diff_ms += ms_since(t0) - engine_ms;
  return std::nullopt;
}

void interest_tracker::commit(visibility_engine& e, const entity_columns& in, double engine_ms, double host_ms,
                              bool host_done) {
  const std::size_t n = in.n;
  if (!host_done) {
    const auto th = clock_type::now();
    next_ids_.assign(in.ids, in.ids + n);
    map_rows_into(next_ids_, spare_row_of_slot_);
    host_ms = ms_since(th);
  }
  std::swap(ids_, next_ids_);
  std::swap(row_of_slot_, spare_row_of_slot_);
  if (view_demand_ != nullptr) {
    std::swap(demand_rows_, next_demand_rows_);
  } else {
    demand_rows_.clear();
  }
  partial_ = !out_.visible_complete && view_demand_ != nullptr;
  fetched_.store(false, std::memory_order_relaxed);
  vis_list_ = {out_.visible, out_.visible_off, out_.visible_len};
  enter_list_ = {out_.enters, out_.enter_off, out_.enter_len};
  leave_list_ = {out_.leaves, out_.leave_off, out_.leave_len};
  producer_ = &e;
  holder_ = &e;
  last_carry_.clear();
  last_carry_.swap(carry_);  // taken by this update (kept for carried_by_last_update)
  last_on_engine_ = &e != &reference_;

  const visibility_timing& t = out_.timing;
  stats_ = {};
  stats_.pairs = out_.pairs;
  stats_.candidates = out_.candidates;
  stats_.visible = out_.visible_total;
  stats_.enters = list_total(out_.enter_off, out_.enter_len, n);
  stats_.leaves = list_total(out_.leave_off, out_.leave_len, n);
  stats_.capped = out_.capped;
  stats_.boxes_ms = t.boxes_ms;
  stats_.find_ms = std::max(0.0, engine_ms - t.boxes_ms - t.diff_ms);
  stats_.diff_ms = t.diff_ms + host_ms;  // run() adds the rest of the tracker's own time
  stats_.count_ms = t.count_ms;
  stats_.offsets_ms = t.offsets_ms;
  stats_.fill_ms = t.fill_ms;
  stats_.rows_ms = t.rows_ms;
  stats_.on_engine = last_on_engine_;
  stats_.engine_timing = t;
}

std::optional<box_error> interest_tracker::apply_pairs(const entity_columns& in, const box_set& boxes,
                                                       std::span<const id_pair> pairs) {
  begin_update(in);
  if (!carry_.empty()) {
    hand_over_carried(reference_, in);
  } else if (holder_ != &reference_) {
    hand_over(reference_);
  }
  const auto t0 = clock_type::now();
  if (auto err = reference_.apply_pairs(input_of(in), boxes, pairs, out_)) return err;
  const double engine_ms = ms_since(t0);
  commit(reference_, in, engine_ms, 0, false);
  stats_.find_ms = 0;  // the caller found the pairs
  return std::nullopt;
}

std::uint64_t interest_tracker::digest() const {
  std::uint64_t h = 0x5a4f4e45ull;  // "ZONE"
  for (std::size_t i = 0; i < ids_.size(); ++i) {
    h = mix(h, ids_[i]);
    for (const auto id : visible(i)) h = mix(h, id);
    h = mix(h, 0xfffffffd);
    for (const auto id : enters(i)) h = mix(h, id);
    h = mix(h, 0xfffffffe);
    for (const auto id : leaves(i)) h = mix(h, id);
    h = mix(h, 0xffffffff);
  }
  return h;
}

}  // namespace zone::interest
