// pinned_boxes (gpu/device.h): page-locked box arrays, and the registry the finders consult.
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdint>
#include <utility>
#include <mutex>
#include <vector>

#include "gpu/device.h"

namespace zone::gpu {
namespace {

struct pinned_range {
  const char* begin;
  const char* end;
};

std::mutex& registry_mutex() {
  static std::mutex m;
  return m;
}
std::vector<pinned_range>& registry() {
  static std::vector<pinned_range> r;
  return r;
}

/// The eight arrays of a set with their byte sizes.
int arrays_of(const interest::box_set& b, const void* ptr[8], std::size_t bytes[8]) {
  const std::size_t n = b.size();
  const void* p[8] = {b.lo_x.data(), b.lo_y.data(), b.lo_z.data(), b.hi_x.data(),
                      b.hi_y.data(), b.hi_z.data(), b.category.data(), b.mask.data()};
  for (int k = 0; k < 8; ++k) {
    ptr[k] = p[k];
    bytes[k] = n * 4;
  }
  return 8;
}

constexpr std::size_t min_pinned_bytes = 64 * 1024;

}  // namespace

pinned_boxes::pinned_boxes(const interest::box_set& boxes) {
  const void* ptr[8];
  std::size_t bytes[8];
  arrays_of(boxes, ptr, bytes);
  if (bytes[0] < min_pinned_bytes || !device_available()) return;
  // Whole pages, merged where arrays share or touch a page (the driver refuses to register a
  // page twice; small arrays of one heap often sit side by side).
  const std::uintptr_t page = 4096;
  std::vector<std::pair<std::uintptr_t, std::uintptr_t>> spans;
  for (int k = 0; k < 8; ++k) {
    const auto b = reinterpret_cast<std::uintptr_t>(ptr[k]);
    spans.emplace_back(b & ~(page - 1), (b + bytes[k] + page - 1) & ~(page - 1));
  }
  std::sort(spans.begin(), spans.end());
  std::vector<std::pair<std::uintptr_t, std::uintptr_t>> merged;
  for (const auto& sp : spans) {
    if (!merged.empty() && sp.first <= merged.back().second) {
      merged.back().second = std::max(merged.back().second, sp.second);
    } else {
      merged.push_back(sp);
    }
  }
  const std::lock_guard lock(registry_mutex());
  for (const auto& m : merged) {
    // Pages another guard holds cannot be registered again: stay inactive then.
    const bool taken = std::any_of(registry().begin(), registry().end(), [&](const pinned_range& x) {
      return reinterpret_cast<std::uintptr_t>(x.begin) < m.second && m.first < reinterpret_cast<std::uintptr_t>(x.end);
    });
    if (taken) return;
  }
  for (std::size_t k = 0; k < merged.size(); ++k) {
    void* base = reinterpret_cast<void*>(merged[k].first);
    if (cudaHostRegister(base, merged[k].second - merged[k].first, cudaHostRegisterDefault) != cudaSuccess) {
      cudaGetLastError();  // not sticky; undo what was registered and stay inactive
      for (std::size_t j = 0; j < k; ++j) cudaHostUnregister(reinterpret_cast<void*>(merged[j].first));
      registry().resize(registry().size() - k);
      return;
    }
    registry().push_back({reinterpret_cast<const char*>(merged[k].first), reinterpret_cast<const char*>(merged[k].second)});
    ptr_[count_++] = base;
  }
}

pinned_boxes::~pinned_boxes() {
  if (count_ == 0) return;
  const std::lock_guard lock(registry_mutex());
  auto& r = registry();
  for (int k = 0; k < count_; ++k) {
    cudaHostUnregister(const_cast<void*>(ptr_[k]));
    const auto it = std::find_if(r.begin(), r.end(), [&](const pinned_range& x) { return x.begin == ptr_[k]; });
    if (it != r.end()) r.erase(it);
  }
}

bool boxes_pinned(const interest::box_set& boxes) {
  if (boxes.empty()) return false;
  const void* ptr[8];
  std::size_t bytes[8];
  arrays_of(boxes, ptr, bytes);
  const std::lock_guard lock(registry_mutex());
  for (int k = 0; k < 8; ++k) {
    const char* b = static_cast<const char*>(ptr[k]);
    const char* e = b + bytes[k];
    const bool covered = std::any_of(registry().begin(), registry().end(),
                                     [&](const pinned_range& x) { return x.begin <= b && e <= x.end; });
    if (!covered) return false;
  }
  return true;
}

}  // namespace zone::gpu
