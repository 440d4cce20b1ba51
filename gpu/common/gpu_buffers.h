// Grow-only device and pinned host arrays (header-only; host code). Contents are not kept when an
// array grows: callers size them before use, once, and they are reused across calls.
#pragma once

#include <cuda_runtime.h>

#include <algorithm>
#include <chrono>
#include <cstddef>
#include <string>
#include <utility>

#include "cuda_check.h"

namespace zone::gpu::detail::mem {

/// Milliseconds this thread has spent growing arrays (the old one freed, the new one allocated),
/// summed over its life: an engine reads it around a run to report what its allocations cost
/// (a cudaFree waits for the device; a cudaHostAlloc of megabytes pins every page).
inline thread_local double grow_ms = 0;

/// cudaMalloc'ed (Device = true) or cudaHostAlloc'ed (Device = false) array that only grows, by
/// at least 1.5x; freed on destruction.
template <class T, bool Device>
class array {
 public:
  array() = default;
  array(const array&) = delete;
  array& operator=(const array&) = delete;
  ~array() { release(); }
  /// Room for n elements (at least one); contents are lost when it grows.
  void reserve(std::size_t n) {
    n = std::max<std::size_t>(n, 1);
    wanted_ = n;
    if (n <= cap_) return;
    const std::size_t want = std::max(n, cap_ + cap_ / 2);
    const auto t0 = std::chrono::steady_clock::now();
    release();
    void* p = nullptr;
    if (const cudaError_t err = allocate(&p, want); err != cudaSuccess) {
      const std::string what = std::string(Device ? "cudaMalloc" : "cudaHostAlloc") + " of " +
                               std::to_string(want * sizeof(T)) + " bytes (" + std::to_string(n) + " elements asked)";
      cuda_fail(err, what.c_str(), __FILE__, __LINE__);
    }
    take(p, want, t0);
  }
  void swap(array& other) noexcept {
    std::swap(ptr_, other.ptr_);
    std::swap(cap_, other.cap_);
    std::swap(wanted_, other.wanted_);
    std::swap(ahead_refused_, other.ahead_refused_);
  }
  [[nodiscard]] T* get() const { return ptr_; }
  [[nodiscard]] std::size_t capacity() const { return cap_; }
  /// Where less than an eighth of the last reserve()'s n is left above it, grows to 1.5 times
  /// that n now (contents lost, as in reserve), so that a later request a little larger finds
  /// room: for growth between uses, away from the time-critical ones. True if it grew.
  bool grow_ahead() {
    if (wanted_ == 0 || cap_ >= wanted_ + wanted_ / 8) return false;
    return grow_ahead_to(wanted_ + wanted_ / 2);
  }
  /// Grows to at least n elements now (at least 1.5x), contents lost: the new block allocated
  /// before the old one is freed, so that where it cannot be (memory short) the array keeps what
  /// it had and is not grown ahead again (reserve() still grows it when a use needs it). True if
  /// it grew.
  bool grow_ahead_to(std::size_t n) {
    if (n <= cap_ || ahead_refused_) return false;
    const std::size_t want = std::max(n, cap_ + cap_ / 2);
    const auto t0 = std::chrono::steady_clock::now();
    void* p = nullptr;
    if (allocate(&p, want) != cudaSuccess) {
      (void)cudaGetLastError();  // an allocation's failure is not sticky: clear it
      ahead_refused_ = true;
      return false;
    }
    release();
    take(p, want, t0);
    return true;
  }

 private:
  /// A new block of `elements` (cudaMalloc or cudaHostAlloc).
  static cudaError_t allocate(void** p, std::size_t elements) {
    return Device ? cudaMalloc(p, elements * sizeof(T)) : cudaHostAlloc(p, elements * sizeof(T), cudaHostAllocDefault);
  }
  /// `p`, of `elements`, is the array's block now (the old one released); the growth that began
  /// at `since` counted in grow_ms.
  void take(void* p, std::size_t elements, std::chrono::steady_clock::time_point since) {
    ptr_ = static_cast<T*>(p);
    cap_ = elements;
    grow_ms += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - since).count();
  }
  void release() noexcept {
    if (ptr_ == nullptr) return;
    if constexpr (Device) {
      cudaFree(ptr_);
    } else {
      cudaFreeHost(ptr_);
    }
    ptr_ = nullptr;
    cap_ = 0;
  }
  T* ptr_ = nullptr;
  std::size_t cap_ = 0;
  std::size_t wanted_ = 0;      // the last reserve()'s n
  bool ahead_refused_ = false;  // a growth ahead found no memory: no more of them
};

template <class T>
using device_array = array<T, true>;
template <class T>
using pinned_array = array<T, false>;

}  // namespace zone::gpu::detail::mem
