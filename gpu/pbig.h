// Public API of the GPU layer: the PBIG pair finder (Lo, Lee, Chung & Chung 2013) on CUDA.
// Built only when CUDA is found; without it every entry point reports that the build has no GPU
// backend, so callers (the `auto` choice) fall back to the CPU finder.
#pragma once

#include <cstddef>
#include <memory>
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

/// Options of the PBIG finder (each optimisation can be switched off for ablation).
struct pbig_options {
  bool load_balancing = true;  ///< Eq. 7 / Algorithm 2 assignment of checks to threads
  bool compression = true;     ///< 3-level encoding of pairs (Eq. 8)
  bool pipelining = true;      ///< 3-stage pipeline: check, device-to-host copy, decode
  double fixed_cell_edge = 0;  ///< 0 = plan by Eq. 6
  std::size_t initial_output_pairs = 0;  ///< initial output buffer capacity (0 = default); tiny values force the overflow path
  interest::thread_pool* decode_pool = nullptr;  ///< threads that decode the output (null = own pool)
};

/// Creates the GPU PBIG finder, or returns null with the reason in `why` when no device can be used.
[[nodiscard]] std::unique_ptr<interest::pair_finder> make_pbig_finder(const pbig_options& options = {},
                                                                      std::string* why = nullptr);

}  // namespace zone::gpu
