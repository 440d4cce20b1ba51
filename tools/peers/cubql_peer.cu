// The cuBQL peer (see cubql_peer.h). cuBQL is header-only; its GPU builder is instantiated here
// (CUBQL_GPU_BUILDER_IMPLEMENTATION), as its own instantiate_builders.cu does.
#define CUBQL_GPU_BUILDER_IMPLEMENTATION 1
#include "cuBQL/bvh.h"
#include "cuBQL/builder/cuda.h"
#include "cuBQL/builder/cuda/radix.h"
#include "cuBQL/builder/cuda/rebinMortonBuilder.h"
#include "cuBQL/traversal/fixedBoxQuery.h"

#include <cub/device/device_scan.cuh>

#include <chrono>
#include <stdexcept>
#include <string>

#include "cubql_peer.h"

namespace zone::peers {

namespace {

void check(cudaError_t e, const char* what) {
  if (e != cudaSuccess) throw std::runtime_error(std::string("cubql peer: ") + what + ": " + cudaGetErrorString(e));
}
#define PEER_CHECK(x) check((x), #x)

static_assert(sizeof(cuBQL::box3f) == 24, "cuBQL's box3f is 6 floats: lo x, y, z, hi x, y, z");

/// Grow-only device or pinned host buffer.
template <typename T, bool Host>
struct buffer {
  T* ptr = nullptr;
  std::size_t cap = 0;
  void reserve(std::size_t n) {
    if (n <= cap) return;
    release();
    const std::size_t want = n + n / 8;
    if (Host) {
      PEER_CHECK(cudaMallocHost(reinterpret_cast<void**>(&ptr), want * sizeof(T)));
    } else {
      PEER_CHECK(cudaMalloc(reinterpret_cast<void**>(&ptr), want * sizeof(T)));
    }
    cap = want;
  }
  void release() {
    if (ptr != nullptr) {
      if (Host) cudaFreeHost(ptr); else cudaFree(ptr);
    }
    ptr = nullptr;
    cap = 0;
  }
  ~buffer() { release(); }
};

/// Whether boxes i and j (j != i) form a qualifying pair given the classes (null: plain join).
__device__ inline bool qualifies(const std::uint32_t* category, const std::uint32_t* mask, std::uint32_t ci,
                                 std::uint32_t mi, std::uint32_t j) {
  return category == nullptr || ((ci & mask[j]) | (category[j] & mi)) != 0;
}

/// counts[i] = the boxes j > i that overlap box i and qualify; counts[n] = 0 (for the scan).
__global__ void count_kernel(cuBQL::bvh3f bvh, const cuBQL::box3f* boxes, const std::uint32_t* category,
                             const std::uint32_t* mask, std::uint32_t n, unsigned long long* counts) {
  const std::uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i == n) counts[n] = 0;
  if (i >= n) return;
  const cuBQL::box3f q = boxes[i];
  const std::uint32_t ci = category != nullptr ? category[i] : 0, mi = category != nullptr ? mask[i] : 0;
  unsigned long long c = 0;
  auto visit = [&](std::uint32_t j) -> int {
    if (j > i && q.overlaps(boxes[j]) && qualifies(category, mask, ci, mi, j)) ++c;
    return CUBQL_CONTINUE_TRAVERSAL;
  };
  cuBQL::fixedBoxQuery::forEachPrim(visit, bvh, q);
  counts[i] = c;
}

/// Writes box i's pairs (i, j), j > i, from offsets[i] on.
__global__ void fill_kernel(cuBQL::bvh3f bvh, const cuBQL::box3f* boxes, const std::uint32_t* category,
                            const std::uint32_t* mask, std::uint32_t n, const unsigned long long* offsets,
                            uint2* pairs) {
  const std::uint32_t i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= n) return;
  const cuBQL::box3f q = boxes[i];
  const std::uint32_t ci = category != nullptr ? category[i] : 0, mi = category != nullptr ? mask[i] : 0;
  unsigned long long at = offsets[i];
  auto visit = [&](std::uint32_t j) -> int {
    if (j > i && q.overlaps(boxes[j]) && qualifies(category, mask, ci, mi, j)) pairs[at++] = make_uint2(i, j);
    return CUBQL_CONTINUE_TRAVERSAL;
  };
  cuBQL::fixedBoxQuery::forEachPrim(visit, bvh, q);
}

}  // namespace

struct cubql_join::impl {
  int leaf_threshold = 0;
  cubql_builder builder = cubql_builder::spatial_median;
  cudaStream_t stream = nullptr;
  cudaEvent_t ev[7]{};
  buffer<cuBQL::box3f, false> d_boxes;
  buffer<std::uint32_t, false> d_bits;
  buffer<unsigned long long, false> d_counts, d_offsets;
  buffer<unsigned char, false> d_temp;
  buffer<uint2, false> d_pairs;
  buffer<std::uint32_t, true> h_pairs;  // 2 per pair
  buffer<unsigned long long, true> h_total;
  cuBQL::bvh3f bvh{};
  bool have_bvh = false;
  cubql_timing t;

  impl() {
    PEER_CHECK(cudaSetDevice(0));
    PEER_CHECK(cudaStreamCreateWithFlags(&stream, cudaStreamNonBlocking));
    for (auto& e : ev) PEER_CHECK(cudaEventCreate(&e));
    h_total.reserve(1);
  }
  ~impl() {
    if (stream != nullptr) cudaStreamSynchronize(stream);
    if (have_bvh) {
      try {
        cuBQL::cuda::free(bvh, stream);
      } catch (...) {
      }
    }
    for (auto& e : ev) cudaEventDestroy(e);
    if (stream != nullptr) cudaStreamDestroy(stream);
  }
  float between(int a, int b) const {
    float ms = 0;
    PEER_CHECK(cudaEventElapsedTime(&ms, ev[a], ev[b]));
    return ms;
  }
};

cubql_join::cubql_join(int leaf_threshold, cubql_builder builder) : p_(std::make_unique<impl>()) {
  p_->leaf_threshold = leaf_threshold;
  p_->builder = builder;
}
cubql_join::~cubql_join() = default;

const std::uint32_t* cubql_join::pairs() const { return p_->h_pairs.ptr; }
const cubql_timing& cubql_join::timing() const { return p_->t; }

bool cubql_join::device_usable() {
  int count = 0;
  return cudaGetDeviceCount(&count) == cudaSuccess && count > 0;
}

void* alloc_pinned(std::size_t bytes) {
  void* p = nullptr;
  PEER_CHECK(cudaMallocHost(&p, bytes > 0 ? bytes : 1));
  return p;
}
void free_pinned(void* p) {
  if (p != nullptr) cudaFreeHost(p);
}

std::uint64_t cubql_join::run(const float* boxes, const std::uint32_t* category, const std::uint32_t* mask,
                              std::size_t count) {
  impl& m = *p_;
  if (count > 0xffffffffull - 1) throw std::length_error("cubql peer: too many boxes");
  if ((category == nullptr) != (mask == nullptr)) throw std::invalid_argument("cubql peer: category and mask go together");
  // The last call's BVH is freed before this call's clock starts (a user could keep it).
  if (m.have_bvh) {
    cuBQL::cuda::free(m.bvh, m.stream);
    m.have_bvh = false;
  }
  const auto n = static_cast<std::uint32_t>(count);
  m.d_boxes.reserve(n);
  m.d_counts.reserve(n + 1ull);
  m.d_offsets.reserve(n + 1ull);
  if (category != nullptr) m.d_bits.reserve(2ull * n);
  std::size_t scan_bytes = 0;
  PEER_CHECK(cub::DeviceScan::ExclusiveSum(nullptr, scan_bytes, m.d_counts.ptr, m.d_offsets.ptr, n + 1, m.stream));
  m.d_temp.reserve(scan_bytes);
  m.t = {};
  if (n == 0) return 0;

  const auto t0 = std::chrono::steady_clock::now();
  cudaStream_t s = m.stream;
  const std::uint32_t* d_cat = nullptr;
  const std::uint32_t* d_mask = nullptr;
  PEER_CHECK(cudaEventRecord(m.ev[0], s));
  PEER_CHECK(cudaMemcpyAsync(m.d_boxes.ptr, boxes, n * sizeof(cuBQL::box3f), cudaMemcpyHostToDevice, s));
  if (category != nullptr) {
    PEER_CHECK(cudaMemcpyAsync(m.d_bits.ptr, category, n * 4ull, cudaMemcpyHostToDevice, s));
    PEER_CHECK(cudaMemcpyAsync(m.d_bits.ptr + n, mask, n * 4ull, cudaMemcpyHostToDevice, s));
    d_cat = m.d_bits.ptr;
    d_mask = m.d_bits.ptr + n;
  }
  PEER_CHECK(cudaEventRecord(m.ev[1], s));
  cuBQL::BuildConfig config;
  config.makeLeafThreshold = m.leaf_threshold;
  switch (m.builder) {
    case cubql_builder::spatial_median: cuBQL::gpuBuilder(m.bvh, m.d_boxes.ptr, n, config, s); break;
    case cubql_builder::radix: cuBQL::cuda::radixBuilder(m.bvh, m.d_boxes.ptr, n, config, s); break;
    case cubql_builder::rebin_radix: cuBQL::cuda::rebinRadixBuilder(m.bvh, m.d_boxes.ptr, n, config, s); break;
  }
  m.have_bvh = true;
  PEER_CHECK(cudaEventRecord(m.ev[2], s));
  const std::uint32_t block = 128;
  count_kernel<<<(n + 1 + block - 1) / block, block, 0, s>>>(m.bvh, m.d_boxes.ptr, d_cat, d_mask, n, m.d_counts.ptr);
  PEER_CHECK(cudaGetLastError());
  PEER_CHECK(cudaEventRecord(m.ev[3], s));
  PEER_CHECK(cub::DeviceScan::ExclusiveSum(m.d_temp.ptr, scan_bytes, m.d_counts.ptr, m.d_offsets.ptr, n + 1, s));
  PEER_CHECK(cudaMemcpyAsync(m.h_total.ptr, m.d_offsets.ptr + n, sizeof(unsigned long long), cudaMemcpyDeviceToHost, s));
  PEER_CHECK(cudaStreamSynchronize(s));
  const std::uint64_t total = *m.h_total.ptr;
  PEER_CHECK(cudaEventRecord(m.ev[4], s));
  // Growing the pair buffers (first calls only) is an allocation outside the timed phases'
  // events but inside total_ms, as for any user.
  m.d_pairs.reserve(total > 0 ? total : 1);
  m.h_pairs.reserve(2 * (total > 0 ? total : 1));
  fill_kernel<<<(n + block - 1) / block, block, 0, s>>>(m.bvh, m.d_boxes.ptr, d_cat, d_mask, n, m.d_offsets.ptr,
                                                        m.d_pairs.ptr);
  PEER_CHECK(cudaGetLastError());
  PEER_CHECK(cudaEventRecord(m.ev[5], s));
  if (total > 0) {
    PEER_CHECK(cudaMemcpyAsync(m.h_pairs.ptr, m.d_pairs.ptr, total * sizeof(uint2), cudaMemcpyDeviceToHost, s));
  }
  PEER_CHECK(cudaEventRecord(m.ev[6], s));
  PEER_CHECK(cudaStreamSynchronize(s));
  m.t.total_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  m.t.in_ms = m.between(0, 1);
  m.t.build_ms = m.between(1, 2);
  m.t.count_ms = m.between(2, 3);
  m.t.scan_ms = m.between(3, 4);
  m.t.fill_ms = m.between(4, 5);
  m.t.out_ms = m.between(5, 6);
  return total;
}

}  // namespace zone::peers
