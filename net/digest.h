// The visible-set digest (docs/protocol.md): the order-independent hash of a set of entity ids
// that the server sends in verify_digest and a client keeps to check its view.
#pragma once

#include <cstdint>
#include <span>

#include "net/messages.h"

namespace zone::net {

/// Order-independent hash of a set of entity ids: the sum (mod 2^64) of a 64-bit mix of each id.
/// A client keeps it incrementally (add on enter, remove on leave) and compares it with the
/// server's verify_digest; the server computes it from the sorted visible set.
[[nodiscard]] constexpr std::uint64_t digest_mix(std::uint32_t id) {
  std::uint64_t z = std::uint64_t{id} + 0x9e3779b97f4a7c15ull;  // splitmix64 finaliser
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}
[[nodiscard]] constexpr std::uint64_t digest_add(std::uint64_t hash, std::uint32_t id) { return hash + digest_mix(id); }
[[nodiscard]] constexpr std::uint64_t digest_remove(std::uint64_t hash, std::uint32_t id) { return hash - digest_mix(id); }
/// The digest of a whole set (any order; ids assumed distinct).
[[nodiscard]] verify_digest visible_digest(std::uint64_t tick, std::span<const std::uint32_t> ids);

}  // namespace zone::net
