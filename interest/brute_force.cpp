// The reference finder: the balanced circular all-pairs loop of Saldanha & Souza (2019),
// Algorithm 4. Box i tests boxes (i + s) mod N for s = 1 .. (N-1)/2 when N is odd; when N is even,
// every box takes steps 1 .. N/2-1 and the first half takes step N/2 as well. Each unordered pair is
// tested exactly once and every box does (almost) the same work, so a plain split of the outer loop
// over threads is balanced.
#include <algorithm>

#include "interest.h"

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

  run_tasks(pool_, chunks, [&](std::size_t c) {
    const std::size_t begin = n * c / chunks;
    const std::size_t end = n * (c + 1) / chunks;
    auto& local = found[c];
    for (std::size_t i = begin; i < end; ++i) {
      const std::size_t last_step = steps + ((even && i < n / 2) ? 1 : 0);
      for (std::size_t s = 1; s <= last_step; ++s) {
        std::size_t j = i + s;
        if (j >= n) j -= n;
        if (qualifies(boxes, i, j)) {
          local.push_back(i < j ? id_pair{static_cast<box_id>(i), static_cast<box_id>(j)}
                                : id_pair{static_cast<box_id>(j), static_cast<box_id>(i)});
        }
      }
    }
  });

  std::size_t total = 0;
  for (const auto& f : found) total += f.size();
  out.reserve(total);
  for (const auto& f : found) out.insert(out.end(), f.begin(), f.end());
  stats_.checks = static_cast<std::uint64_t>(n) * (n - 1) / 2;
}

}  // namespace zone::interest
