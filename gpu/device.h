// Public API of the GPU layer's shared device pieces: device discovery, and box sets page-locked
// for the GPU finders (both used by PBIG, LBVH and the zone's GPU engines). Without CUDA,
// device_available says so and pinned_boxes pins nothing.
#pragma once

#include <cstddef>
#include <string>

#include "interest.h"

namespace zone::gpu {

/// What the CUDA runtime says of device 0.
struct device_info {
  std::string name;
  int compute_major = 0;
  int compute_minor = 0;
  int multiprocessors = 0;
  std::size_t global_memory_bytes = 0;
};

/// True when this build has the GPU backend and a CUDA device can be used. Otherwise false, with
/// the reason in `why` (built without CUDA, no device, driver error). Never throws.
[[nodiscard]] bool device_available(device_info* info = nullptr, std::string* why = nullptr);

/// True when this build was compiled with the CUDA backend.
[[nodiscard]] bool built_with_cuda();

/// Page-locks the eight arrays of a box set while it lives (cudaHostRegister), so that the GPU
/// finders copy them to the device by DMA straight from the caller's memory, without a staging
/// copy on the host, and validate them on the device instead (same rule, same first-error
/// report). For a caller that keeps its box arrays from call to call (a server's per-tick box
/// buffer; a benchmark's data set): registration costs about as much as one staging copy, so it
/// pays from the second call on. The set must not be resized or reallocated while pinned. Without
/// a usable device, for a set under 64 KiB an array, when another live guard holds the same
/// pages, or when the driver refuses, it pins nothing (active() is false) and the finders take the
/// staging path as before. (Whole pages are registered; arrays sharing a page share a range.)
class pinned_boxes {
 public:
  explicit pinned_boxes(const interest::box_set& boxes);
  ~pinned_boxes();
  pinned_boxes(const pinned_boxes&) = delete;
  pinned_boxes& operator=(const pinned_boxes&) = delete;
  [[nodiscard]] bool active() const { return count_ > 0; }

 private:
  const void* ptr_[8]{};  // registered page ranges (at most one per array)
  int count_ = 0;
};

/// True when every array of `boxes` (all of its n elements) lies in memory pinned by a live
/// pinned_boxes.
[[nodiscard]] bool boxes_pinned(const interest::box_set& boxes);

}  // namespace zone::gpu
