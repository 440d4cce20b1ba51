// TESTING ONLY (zone-server --test-fault gpu-lost): makes the CUDA device fail for real, as a GPU
// that faults mid-run would, to prove that the zone carries on without it.
#pragma once

namespace zone::gpu {

/// Launches a kernel that traps, waits for it and throws the CUDA runtime's error
/// (cudaErrorLaunchFailure, through CUDA_CHECK: std::runtime_error). The error is sticky: every
/// later CUDA call of this process fails too, so every GPU engine and finder in use must fall
/// back to the CPU. In a build without CUDA it throws std::runtime_error saying so.
[[noreturn]] void raise_device_fault();

}  // namespace zone::gpu
