// Grow-only device and pinned host arrays (header-only; host code). Contents are not kept when an
// array grows: callers size them before use, once, and they are reused across calls.
#pragma once

#include <cuda_runtime.h>

#include <algorithm>
#include <cstddef>
#include <string>
#include <utility>

#include "cuda_check.h"

namespace zone::gpu::detail::mem {

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
    if (n <= cap_) return;
    const std::size_t want = std::max(n, cap_ + cap_ / 2);
    release();
    void* p = nullptr;
    const cudaError_t err =
        Device ? cudaMalloc(&p, want * sizeof(T)) : cudaHostAlloc(&p, want * sizeof(T), cudaHostAllocDefault);
    if (err != cudaSuccess) {
      const std::string what = std::string(Device ? "cudaMalloc" : "cudaHostAlloc") + " of " +
                               std::to_string(want * sizeof(T)) + " bytes (" + std::to_string(n) + " elements asked)";
      cuda_fail(err, what.c_str(), __FILE__, __LINE__);
    }
    ptr_ = static_cast<T*>(p);
    cap_ = want;
  }
  void swap(array& other) noexcept {
    std::swap(ptr_, other.ptr_);
    std::swap(cap_, other.cap_);
  }
  [[nodiscard]] T* get() const { return ptr_; }
  [[nodiscard]] std::size_t capacity() const { return cap_; }

 private:
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
};

template <class T>
using device_array = array<T, true>;
template <class T>
using pinned_array = array<T, false>;

}  // namespace zone::gpu::detail::mem
