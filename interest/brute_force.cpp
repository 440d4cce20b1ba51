// The reference finder: the balanced circular all-pairs loop of Saldanha & Souza (2019),
// Algorithm 4. Box i tests boxes (i + s) mod N for s = 1 .. (N-1)/2 when N is odd; when N is even,
// every box takes steps 1 .. N/2-1 and the first half takes step N/2 as well. Each unordered pair is
// tested exactly once and every box does (almost) the same work, so a plain split of the outer loop
// over threads is balanced.
#include <algorithm>
#include <bit>

#include "interest.h"
#include "thread_pool.h"

namespace zone::interest {

void brute_force_finder::find_valid(const box_set& boxes, pair_list& out) {
  const std::size_t n = boxes.size();
  out.clear();
  if (n < 2) return;

  const std::size_t steps = (n - 1) / 2;         // steps every box takes
  const bool even = n % 2 == 0;                  // even N: the first half take step N/2 too
  const std::size_t threads = pool_ ? pool_->size() : 1;
  const std::size_t chunks = std::min<std::size_t>(n, threads * 8);
  std::vector<pair_list> found(chunks);

  const float *lx = boxes.lo_x.data(), *ly = boxes.lo_y.data(), *lz = boxes.lo_z.data();
  const float *hx = boxes.hi_x.data(), *hy = boxes.hi_y.data(), *hz = boxes.hi_z.data();
  const std::uint32_t *cat = boxes.category.data(), *msk = boxes.mask.data();
  run_tasks(pool_, chunks, [&](std::size_t c) {
    const std::size_t begin = n * c / chunks;
    const std::size_t end = n * (c + 1) / chunks;
    auto& local = found[c];
    // Box i against the boxes j in [first, last): contiguous, branch-free tests (vectorisable).
    auto test_range = [&](std::size_t i, std::size_t first, std::size_t last) {
      const float ax0 = lx[i], ay0 = ly[i], az0 = lz[i], ax1 = hx[i], ay1 = hy[i], az1 = hz[i];
      const std::uint32_t ac = cat[i], am = msk[i];
      for (std::size_t block = first; block < last; block += 64) {
        const std::size_t len = std::min<std::size_t>(last - block, 64);
        alignas(64) std::uint8_t hit[64];
        for (std::size_t k = 0; k < len; ++k) {
          const std::size_t j = block + k;
          hit[k] = static_cast<std::uint8_t>((ax0 <= hx[j]) & (lx[j] <= ax1) & (ay0 <= hy[j]) & (ly[j] <= ay1) &
                                             (az0 <= hz[j]) & (lz[j] <= az1) & (((ac & msk[j]) | (cat[j] & am)) != 0));
        }
        for (std::size_t k = 0; k < len; ++k) {
          if (hit[k] == 0) continue;
          const std::size_t j = block + k;
          local.push_back(i < j ? id_pair{static_cast<box_id>(i), static_cast<box_id>(j)}
                                : id_pair{static_cast<box_id>(j), static_cast<box_id>(i)});
        }
      }
    };
    for (std::size_t i = begin; i < end; ++i) {
      // Steps s = 1 .. last_step reach j = (i + s) mod N: one or two contiguous ranges.
      const std::size_t last_step = steps + ((even && i < n / 2) ? 1 : 0);
      const std::size_t stop = i + last_step + 1;  // one past the last j, before wrapping
      test_range(i, i + 1, std::min(stop, n));
      if (stop > n) test_range(i, 0, stop - n);
    }
  });

  std::size_t total = 0;
  for (const auto& f : found) total += f.size();
  out.reserve(total);
  for (const auto& f : found) out.insert(out.end(), f.begin(), f.end());
  stats_.checks = static_cast<std::uint64_t>(n) * (n - 1) / 2;
}

}  // namespace zone::interest
