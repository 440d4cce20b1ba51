// The input boxes of a GPU finder call on the device, as its kernels read them (PBIG and LBVH).
// No host-library headers here: the kernels' translation units include it (see pbig_launch.h).
#pragma once

#include <cstdint>

namespace zone::gpu::detail {

/// The input boxes on the device, structure of arrays (ids are indices).
struct box_arrays {
  const float* lo[3];
  const float* hi[3];
  const std::uint32_t* category;
  const std::uint32_t* mask;
};

}  // namespace zone::gpu::detail
