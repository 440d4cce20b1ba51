// TESTING ONLY (zone-server --test-fault gpu-interest|gpu-replication|gpu-lost): a GPU engine that
// fails mid-run. Each wrapper forwards every call to the real engine until the world reaches the
// fault tick; then the call that would run that tick's step throws instead, as the GPU layer
// throws on a CUDA error (gpu/common/cuda_check.h), and every later call that could touch the device
// throws again (a device that failed stays failed). What throws is `raise`: by default a
// std::runtime_error worded like CUDA_CHECK's; zone-server's gpu-lost passes one that makes the
// device fail for real (gpu::raise_device_fault). The zone's own fallback is under test: the
// interest tracker and the replicator give the engine up and run the same tick on the host
// (docs/zone.md, "A GPU that fails mid-run").
#pragma once

#include <cstdint>
#include <functional>
#include <string>

#include "interest/replication_engine.h"
#include "interest/visibility_engine.h"

namespace zone {

/// When and how an engine wrapper fails.
struct engine_fault {
  std::function<std::uint64_t()> tick;  ///< the world's current tick
  std::uint64_t at_tick = 0;            ///< the first tick whose step fails
  std::function<void()> raise;          ///< throws; empty: a CUDA_CHECK-worded runtime_error
  /// True once the fault fired: every call that touches the device throws from then on.
  [[nodiscard]] bool fired() const { return fired_; }
  /// Throws (and fires) when the fault is due or fired; `what` names the engine's call.
  void check(const char* what);

 private:
  bool fired_ = false;
};

/// The interest step's engine, failing at the fault tick (update, fetch_all_visible, load_previous).
class faulty_visibility_engine final : public interest::visibility_engine {
 public:
  faulty_visibility_engine(interest::visibility_engine& inner, engine_fault fault)
      : inner_(inner), fault_(std::move(fault)) {}
  std::optional<std::size_t> update(const interest::visibility_input& in, interest::visibility_output& out) override {
    fault_.check("visibility update");
    return inner_.update(in, out);
  }
  void load_previous(std::span<const std::uint32_t> ids, std::uint32_t slot_bits, std::span<const std::uint32_t> offsets,
                     std::span<const std::uint32_t> visible) override {
    if (fault_.fired()) fault_.check("visibility load_previous");
    inner_.load_previous(ids, slot_bits, offsets, visible);
  }
  void prepare() noexcept override {
    if (!fault_.fired()) inner_.prepare();
  }
  interest::visibility_lists fetch_all_visible() override {
    if (fault_.fired()) fault_.check("visibility fetch_all_visible");
    return inner_.fetch_all_visible();
  }
  [[nodiscard]] resident_lists resident_visible() const override {
    return fault_.fired() ? resident_lists{} : inner_.resident_visible();
  }
  [[nodiscard]] bool caps_visible() const override { return inner_.caps_visible(); }
  [[nodiscard]] const char* name() const override { return inner_.name(); }
  [[nodiscard]] const engine_fault& fault() const { return fault_; }

 private:
  interest::visibility_engine& inner_;
  engine_fault fault_;
};

/// Replication's engine, failing at the fault tick (stage and run).
class faulty_replication_engine final : public interest::replication_engine {
 public:
  faulty_replication_engine(interest::replication_engine& inner, engine_fault fault)
      : inner_(inner), fault_(std::move(fault)) {}
  staging stage(std::size_t entities, std::size_t slots, std::size_t jobs, std::size_t visible) override {
    if (fault_.fired()) fault_.check("replication stage");
    return inner_.stage(entities, slots, jobs, visible);
  }
  staging stage_entities(std::size_t entities, std::size_t slots) override {
    if (fault_.fired()) fault_.check("replication stage");
    return inner_.stage_entities(entities, slots);
  }
  void upload_entities() override { inner_.upload_entities(); }
  void discard_entities() override { inner_.discard_entities(); }
  output run(const interest::replication_rules& rules, std::size_t client_count,
             const interest::visibility_engine::resident_lists* rows,
             const std::function<void()>* while_waiting) override {
    fault_.check("replication run");  // before while_waiting: the replicator runs it then
    return inner_.run(rules, client_count, rows, while_waiting);
  }
  [[nodiscard]] bool reads_resident() const override { return inner_.reads_resident(); }
  void set_frame_format(const interest::replication_frame_format& format) override { inner_.set_frame_format(format); }
  void set_device_wait(device_wait how) override { inner_.set_device_wait(how); }
  void forget_all() override {
    if (!fault_.fired()) inner_.forget_all();
  }
  double grow_ahead(std::chrono::steady_clock::time_point deadline) override {
    return fault_.fired() ? 0 : inner_.grow_ahead(deadline);
  }
  [[nodiscard]] const interest::replication_timing& timing() const override { return inner_.timing(); }
  [[nodiscard]] const char* name() const override { return inner_.name(); }
  [[nodiscard]] const engine_fault& fault() const { return fault_; }

 private:
  interest::replication_engine& inner_;
  engine_fault fault_;
};

}  // namespace zone
