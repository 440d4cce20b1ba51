#include <algorithm>
#include <cmath>
#include <charconv>
#include <limits>
#include <sstream>

#include "interest.h"
#include "thread_pool.h"

namespace zone::interest {

void box_set::clear() { resize(0); }

void box_set::reserve(std::size_t n) {
  for (auto* v : {&lo_x, &lo_y, &lo_z, &hi_x, &hi_y, &hi_z}) v->reserve(n);
  category.reserve(n);
  mask.reserve(n);
}

void box_set::resize(std::size_t n) {
  for (auto* v : {&lo_x, &lo_y, &lo_z, &hi_x, &hi_y, &hi_z}) v->resize(n, 0.0f);
  category.resize(n, 1u);
  mask.resize(n, 1u);
}

void box_set::push_back(const box& b) {
  lo_x.push_back(b.lo[0]);
  lo_y.push_back(b.lo[1]);
  lo_z.push_back(b.lo[2]);
  hi_x.push_back(b.hi[0]);
  hi_y.push_back(b.hi[1]);
  hi_z.push_back(b.hi[2]);
  category.push_back(b.category);
  mask.push_back(b.mask);
}

void box_set::set(std::size_t i, const box& b) {
  lo_x[i] = b.lo[0];
  lo_y[i] = b.lo[1];
  lo_z[i] = b.lo[2];
  hi_x[i] = b.hi[0];
  hi_y[i] = b.hi[1];
  hi_z[i] = b.hi[2];
  category[i] = b.category;
  mask[i] = b.mask;
}

box box_set::get(std::size_t i) const {
  box b;
  b.lo[0] = lo_x[i];
  b.lo[1] = lo_y[i];
  b.lo[2] = lo_z[i];
  b.hi[0] = hi_x[i];
  b.hi[1] = hi_y[i];
  b.hi[2] = hi_z[i];
  b.category = category[i];
  b.mask = mask[i];
  return b;
}

namespace {
/// Shortest text that reads back as exactly this float (so "1.0000001 > 1" is not shown as "1 > 1").
std::string exact(float v) {
  char buf[32];
  const auto res = std::to_chars(buf, buf + sizeof buf, v);
  return std::string(buf, res.ptr);
}
}  // namespace

std::optional<box_error> validate_box(const box& b, std::size_t index) {
  static constexpr char axis_name[3] = {'x', 'y', 'z'};
  for (int d = 0; d < 3; ++d) {
    for (const auto& [value, which] : {std::pair{b.lo[d], "lo"}, std::pair{b.hi[d], "hi"}}) {
      if (!std::isfinite(value)) {
        std::ostringstream msg;
        msg << "box " << index << ": " << which << '.' << axis_name[d] << " is " << (std::isnan(value) ? "NaN" : "infinite");
        return box_error{index, msg.str()};
      }
    }
    if (b.lo[d] > b.hi[d]) {
      std::ostringstream msg;
      msg << "box " << index << ": lo." << axis_name[d] << " = " << exact(b.lo[d]) << " > hi." << axis_name[d] << " = "
          << exact(b.hi[d]);
      return box_error{index, msg.str()};
    }
  }
  return std::nullopt;
}

std::optional<box_error> validate(const box_set& boxes, thread_pool* pool) {
  const std::size_t n = boxes.size();
  // Fast vectorisable scan of fixed chunks first; only a failing chunk is searched for the
  // first bad box and described, and the lowest failing chunk wins.
  const std::size_t chunks = std::clamp<std::size_t>(n / 65536, 1, 64);
  std::vector<std::uint8_t> chunk_ok(chunks, 1);
  run_tasks(n >= 65536 ? pool : nullptr, chunks, [&](std::size_t c) {
    bool ok = true;
    for (std::size_t i = n * c / chunks, e = n * (c + 1) / chunks; i < e; ++i) {
      ok &= valid_bounds(boxes.lo_x[i], boxes.lo_y[i], boxes.lo_z[i], boxes.hi_x[i], boxes.hi_y[i], boxes.hi_z[i]);
    }
    chunk_ok[c] = ok ? 1 : 0;
  });
  for (std::size_t c = 0; c < chunks; ++c) {
    if (chunk_ok[c]) continue;
    for (std::size_t i = n * c / chunks, e = n * (c + 1) / chunks; i < e; ++i) {
      if (auto err = validate_box(boxes.get(i), i)) return err;
    }
  }
  return std::nullopt;
}

std::optional<box_error> pair_finder::find(const box_set& boxes, pair_list& out) {
  out.clear();
  if (boxes.size() > std::numeric_limits<box_id>::max()) {
    return box_error{boxes.size() - 1, "the set has " + std::to_string(boxes.size()) +
                                           " boxes; ids are 32-bit, so at most 4294967295 boxes are supported"};
  }
  if (auto err = validate(boxes, worker_pool())) return err;
  stats_ = {};
  find_valid(boxes, out);
  return std::nullopt;
}

void sort_canonical(pair_list& pairs, std::size_t box_count, thread_pool* pool) {
  for (auto& p : pairs) {
    if (p.a > p.b) std::swap(p.a, p.b);
  }
  if (pairs.size() < 2) return;
  if (box_count == 0 || pairs.size() < box_count / 8) {
    std::sort(pairs.begin(), pairs.end());
    return;
  }
  // Bucket by first id (counting sort), then sort each bucket by second id, buckets in parallel.
  std::vector<std::uint64_t> start(box_count + 1, 0);
  for (const auto& p : pairs) ++start[p.a + 1];
  for (std::size_t i = 0; i < box_count; ++i) start[i + 1] += start[i];
  std::vector<box_id> second(pairs.size());
  {
    std::vector<std::uint64_t> cursor(start.begin(), start.end() - 1);
    for (const auto& p : pairs) second[cursor[p.a]++] = p.b;
  }
  const std::size_t chunks = std::clamp<std::size_t>(box_count / 4096, 1, 256);
  run_tasks(pool, chunks, [&](std::size_t c) {
    for (std::size_t a = box_count * c / chunks, e = box_count * (c + 1) / chunks; a < e; ++a) {
      auto first = second.begin() + static_cast<std::ptrdiff_t>(start[a]);
      auto last = second.begin() + static_cast<std::ptrdiff_t>(start[a + 1]);
      std::sort(first, last);
      for (auto k = start[a]; k < start[a + 1]; ++k) pairs[k] = id_pair{static_cast<box_id>(a), second[k]};
    }
  });
}

adjacency to_adjacency(const pair_list& pairs, std::size_t box_count) {
  adjacency adj;
  adj.offsets.assign(box_count + 1, 0);
  for (const auto& p : pairs) {
    ++adj.offsets[p.a + 1];
    ++adj.offsets[p.b + 1];
  }
  for (std::size_t i = 0; i < box_count; ++i) adj.offsets[i + 1] += adj.offsets[i];
  adj.neighbors.resize(adj.offsets[box_count]);
  std::vector<std::uint64_t> cursor(adj.offsets.begin(), adj.offsets.end() - 1);
  for (const auto& p : pairs) {
    adj.neighbors[cursor[p.a]++] = p.b;
    adj.neighbors[cursor[p.b]++] = p.a;
  }
  for (std::size_t i = 0; i < box_count; ++i) {
    std::sort(adj.neighbors.begin() + static_cast<std::ptrdiff_t>(adj.offsets[i]),
              adj.neighbors.begin() + static_cast<std::ptrdiff_t>(adj.offsets[i + 1]));
  }
  return adj;
}

std::optional<box_error> pair_finder::find_view(const box_set& boxes, pair_list& scratch,
                                                std::span<const id_pair>& view) {
  view = {};
  auto err = find(boxes, scratch);
  if (!err) view = scratch;
  return err;
}

}  // namespace zone::interest
