// id_map: the hash map from 32-bit entity ids to values behind the client view's entity table.
#pragma once

#include <algorithm>
#include <bit>
#include <cstddef>
#include <cstdint>
#include <utility>
#include <vector>

namespace zone::net {

/// A hash map from 32-bit ids to values: the values in one dense array (iteration runs over it;
/// erase moves the last value into the hole) and an open-addressing index of (id, position)
/// pairs with linear probing and backward-shift deletion (load at most 1/2), so a lookup touches
/// a cache line or two rather than a bucket and a node. The client view's entity table: a bot
/// swarm looks entities up hundreds of thousands of times a second. Any id, 0 included.
/// try_emplace and erase invalidate iterators and references; iteration order is unspecified.
template <class V>
class id_map {
 public:
  using value_type = std::pair<std::uint32_t, V>;
  using iterator = typename std::vector<value_type>::iterator;
  using const_iterator = typename std::vector<value_type>::const_iterator;

  [[nodiscard]] std::size_t size() const { return values_.size(); }
  [[nodiscard]] bool empty() const { return values_.empty(); }
  iterator begin() { return values_.begin(); }
  iterator end() { return values_.end(); }
  const_iterator begin() const { return values_.begin(); }
  const_iterator end() const { return values_.end(); }

  iterator find(std::uint32_t id) {
    const std::size_t i = slot_of(id);
    return i == npos ? values_.end() : values_.begin() + static_cast<std::ptrdiff_t>(slots_[i].at - 1);
  }
  const_iterator find(std::uint32_t id) const {
    const std::size_t i = slot_of(id);
    return i == npos ? values_.end() : values_.begin() + static_cast<std::ptrdiff_t>(slots_[i].at - 1);
  }
  [[nodiscard]] std::size_t count(std::uint32_t id) const { return slot_of(id) == npos ? 0 : 1; }

  /// A cache hint only (contents unchanged): starts fetching the index slot where a lookup of
  /// `id` begins, so that a batch of lookups overlaps its cache misses instead of taking them in turn.
  void prefetch(std::uint32_t id) const {
    if (!slots_.empty()) __builtin_prefetch(&slots_[home(id)]);
  }

  /// The entry of `id`, appended with a value-initialised V when absent (second: inserted).
  std::pair<iterator, bool> try_emplace(std::uint32_t id) {
    if ((values_.size() + 1) * 2 > slots_.size()) rehash(std::max<std::size_t>(64, slots_.size() * 2));
    const std::size_t mask = slots_.size() - 1;
    for (std::size_t i = home(id);; i = (i + 1) & mask) {
      if (slots_[i].at == 0) {
        values_.emplace_back(id, V{});
        slots_[i] = {id, static_cast<std::uint32_t>(values_.size())};
        return {values_.end() - 1, true};
      }
      if (slots_[i].id == id) return {values_.begin() + static_cast<std::ptrdiff_t>(slots_[i].at - 1), false};
    }
  }

  /// Removes `id`; returns how many entries were removed (0 or 1).
  std::size_t erase(std::uint32_t id) {
    std::size_t i = slot_of(id);
    if (i == npos) return 0;
    const std::uint32_t at = slots_[i].at;
    // Backward shift: move later entries of the probe run into the hole when their home allows.
    const std::size_t mask = slots_.size() - 1;
    for (std::size_t j = (i + 1) & mask; slots_[j].at != 0; j = (j + 1) & mask) {
      const std::size_t k = home(slots_[j].id);
      if (i <= j ? (k <= i || k > j) : (k <= i && k > j)) {
        slots_[i] = slots_[j];
        i = j;
      }
    }
    slots_[i] = {};
    // The last value fills the erased one's place.
    if (at != values_.size()) {
      values_[at - 1] = std::move(values_.back());
      slots_[slot_of(values_[at - 1].first)].at = at;
    }
    values_.pop_back();
    return 1;
  }

  void clear() {
    values_.clear();
    std::fill(slots_.begin(), slots_.end(), slot{});
  }

 private:
  struct slot {
    std::uint32_t id = 0;
    std::uint32_t at = 0;  ///< 1 + position in values_; 0 = empty
  };
  static constexpr std::size_t npos = static_cast<std::size_t>(-1);
  [[nodiscard]] std::size_t home(std::uint32_t id) const {
    // Fibonacci hashing: the top bits of id * 2^64/phi.
    return static_cast<std::size_t>((std::uint64_t{id} * 0x9e3779b97f4a7c15ull) >> shift_);
  }
  [[nodiscard]] std::size_t slot_of(std::uint32_t id) const {
    if (values_.empty()) return npos;
    const std::size_t mask = slots_.size() - 1;
    for (std::size_t i = home(id); slots_[i].at != 0; i = (i + 1) & mask) {
      if (slots_[i].id == id) return i;
    }
    return npos;
  }
  void rehash(std::size_t capacity) {
    slots_.assign(capacity, slot{});
    shift_ = 64 - static_cast<unsigned>(std::countr_zero(capacity));
    const std::size_t mask = capacity - 1;
    for (std::size_t k = 0; k < values_.size(); ++k) {
      std::size_t i = home(values_[k].first);
      while (slots_[i].at != 0) i = (i + 1) & mask;
      slots_[i] = {values_[k].first, static_cast<std::uint32_t>(k + 1)};
    }
  }

  std::vector<value_type> values_;
  std::vector<slot> slots_;
  unsigned shift_ = 64;
};

}  // namespace zone::net
