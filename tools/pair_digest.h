// tools/pair_digest.h: an order-independent digest of a pair list, for the benchmarks that compare
// one finder's pairs with another's (bench-gpu, bench-peers) without sorting or storing them.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

#include "interest/interest.h"
#include "interest/thread_pool.h"

namespace zone::bench {

/// Count, sum and xor of a mixed hash of every pair: equal pair sets give equal digests whatever
/// their order or the orientation of each pair.
struct pair_digest {
  std::uint64_t count = 0, sum = 0, xr = 0;
  friend bool operator==(const pair_digest&, const pair_digest&) = default;
};

/// splitmix64's finaliser.
inline std::uint64_t mix(std::uint64_t x) {
  x += 0x9e3779b97f4a7c15ull;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ull;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebull;
  return x ^ (x >> 31);
}

/// Order-independent digest of a pair list (each pair taken as (min, max)), split over the pool.
inline pair_digest digest(std::span<const interest::id_pair> p, interest::thread_pool& pool) {
  const std::size_t chunks = std::max<std::size_t>(1, std::min<std::size_t>(256, p.size() / 65536));
  std::vector<pair_digest> part(chunks);
  interest::run_tasks(&pool, chunks, [&](std::size_t c) {
    const std::size_t b = p.size() * c / chunks, e = p.size() * (c + 1) / chunks;
    pair_digest d;
    for (std::size_t i = b; i < e; ++i) {
      const std::uint64_t a = std::min(p[i].a, p[i].b), z = std::max(p[i].a, p[i].b);
      const std::uint64_t h = mix(a << 32 | z);
      d.sum += h;
      d.xr ^= h;
    }
    d.count = e - b;
    part[c] = d;
  });
  pair_digest all;
  for (const auto& d : part) {
    all.count += d.count;
    all.sum += d.sum;
    all.xr ^= d.xr;
  }
  return all;
}

}  // namespace zone::bench
