// The ground-truth stream's codec (truth.h).
#include "truth.h"

#include <algorithm>
#include <bit>
#include <cstring>

namespace zone::net::truth {

static_assert(std::endian::native == std::endian::little, "the truth stream is written in host order");

namespace {

template <class T>
void put(std::uint8_t*& at, const T& v) {
  std::memcpy(at, &v, sizeof v);
  at += sizeof v;
}

void put_bytes(std::uint8_t*& at, const void* data, std::size_t bytes) {
  if (bytes != 0) std::memcpy(at, data, bytes);
  at += bytes;
}

std::size_t padded4(std::size_t n) { return (n + 3) & ~std::size_t{3}; }

/// The columns a layout and a change list share, `n` rows each: a u32 key per row (the entity's id
/// or its index), then the AOI and presence half-extents, classes, masks and kinds, padded to 4.
void put_rows(std::uint8_t*& at, std::size_t n, const std::uint32_t* keys, const float* aoi_half,
              const float* presence_half, const std::uint32_t* classes, const std::uint32_t* sees,
              const std::uint8_t* kinds) {
  put_bytes(at, keys, 4 * n);
  put_bytes(at, aoi_half, 12 * n);
  put_bytes(at, presence_half, 12 * n);
  put_bytes(at, classes, 4 * n);
  put_bytes(at, sees, 4 * n);
  put_bytes(at, kinds, n);
  for (std::size_t k = n; k < padded4(n); ++k) *at++ = 0;
}

std::size_t layout_bytes(std::size_t n) { return n * (layout_entity_bytes - 1) + padded4(n); }
std::size_t changes_bytes(std::size_t m) { return 4 + m * (change_entity_bytes - 1) + padded4(m); }
std::size_t carried_bytes(std::size_t k, std::size_t t) { return 8 + 8 * k + 4 * t; }

template <class T>
void take(const std::uint8_t*& at, std::vector<T>& v, std::size_t n) {
  v.resize(n);
  if (n != 0) std::memcpy(v.data(), at, n * sizeof(T));
  at += n * sizeof(T);
}

template <class T>
T read_at(const std::uint8_t* at) {
  T v;
  std::memcpy(&v, at, sizeof v);
  return v;
}

}  // namespace

void encode_tick(std::vector<std::uint8_t>& out, std::uint64_t tick, std::span<const float> positions,
                 const layout_view* layout, std::uint32_t layout_seq, const changes_view* changes,
                 const carried_view* carried) {
  const std::size_t n = positions.size() / 3;
  const bool with_changes = changes != nullptr && layout == nullptr;
  const std::size_t m = with_changes ? changes->index.size() : 0;
  const bool with_carried = carried != nullptr && !carried->observers.empty();
  const std::size_t kc = with_carried ? carried->observers.size() : 0;
  const std::size_t tc = with_carried ? carried->off[kc] - carried->off[0] : 0;
  const std::size_t total = header_bytes + 12 * n + (layout ? layout_bytes(n) : 0) +
                            (with_changes ? changes_bytes(m) : 0) + (with_carried ? carried_bytes(kc, tc) : 0);
  out.resize(total);
  std::uint8_t* at = out.data();
  put(at, static_cast<std::uint32_t>(total - 4));
  put(at, magic);
  put(at, (layout ? flag_layout : with_changes ? flag_changes : 0u) | (with_carried ? flag_carried : 0u));
  put(at, tick);
  put(at, static_cast<std::uint32_t>(n));
  put(at, layout_seq);
  put_bytes(at, positions.data(), 12 * n);
  if (layout) {
    put_rows(at, n, layout->ids.data(), layout->aoi_half.data(), layout->presence_half.data(), layout->classes.data(),
             layout->sees.data(), layout->kinds.data());
  } else if (with_changes) {
    put(at, static_cast<std::uint32_t>(m));
    put_rows(at, m, changes->index.data(), changes->aoi_half.data(), changes->presence_half.data(),
             changes->classes.data(), changes->sees.data(), changes->kinds.data());
  }
  if (with_carried) {
    put(at, static_cast<std::uint32_t>(kc));
    put(at, static_cast<std::uint32_t>(tc));
    put_bytes(at, carried->observers.data(), 4 * kc);
    for (std::size_t o = 0; o < kc; ++o) put(at, carried->off[o + 1] - carried->off[o]);
    put_bytes(at, carried->targets.data() + carried->off[0], 4 * tc);
  }
}

void encode_refusal(std::vector<std::uint8_t>& out, std::string_view why) {
  out.resize(8 + why.size());
  std::uint8_t* at = out.data();
  put(at, static_cast<std::uint32_t>(4 + why.size()));
  put(at, refused_magic);
  put_bytes(at, why.data(), why.size());
}

void mark_first_step(std::vector<std::uint8_t>& frame) {
  if (frame.size() < header_bytes) return;
  std::uint32_t flags = 0;
  std::memcpy(&flags, frame.data() + 8, 4);
  flags |= flag_first_step;
  std::memcpy(frame.data() + 8, &flags, 4);
}

encoder::sent encoder::encode(std::vector<std::uint8_t>& out, std::uint64_t tick, std::span<const float> positions,
                              const layout_view* layout, bool force_layout, const carried_view* carried) {
  const std::size_t n = positions.size() / 3;
  changed_.clear();
  const auto keep = [&](const layout_view& l) {
    ids_.assign(l.ids.begin(), l.ids.end());
    aoi_.assign(l.aoi_half.begin(), l.aoi_half.end());
    presence_.assign(l.presence_half.begin(), l.presence_half.end());
    classes_.assign(l.classes.begin(), l.classes.end());
    sees_.assign(l.sees.begin(), l.sees.end());
    kinds_.assign(l.kinds.begin(), l.kinds.end());
  };
  const auto whole = [&]() {
    const layout_view kept{ids_, aoi_, presence_, classes_, sees_, kinds_};
    encode_tick(out, tick, positions, &kept, ++seq_, nullptr, carried);
    have_ = true;
    return sent::layout;
  };
  if (layout != nullptr && (!have_ || force_layout || layout->ids.size() != ids_.size() ||
                            !std::equal(layout->ids.begin(), layout->ids.end(), ids_.begin()))) {
    keep(*layout);
    return whole();
  }
  if (layout == nullptr) {
    if (force_layout) return whole();
    encode_tick(out, tick, positions, nullptr, seq_, nullptr, carried);
    return sent::positions;
  }
  // The same ids: which rows changed (bit for bit), stopping once the changes are too many.
  const std::size_t cap = n / max_changes_divisor;
  const auto same = [](const void* a, const void* b, std::size_t bytes) { return std::memcmp(a, b, bytes) == 0; };
  for (std::size_t k = 0; k < n; ++k) {
    if (layout->classes[k] != classes_[k] || layout->sees[k] != sees_[k] || layout->kinds[k] != kinds_[k] ||
        !same(&layout->aoi_half[3 * k], &aoi_[3 * k], 12) ||
        !same(&layout->presence_half[3 * k], &presence_[3 * k], 12)) {
      if (changed_.size() == cap) {  // one more than the cap: the whole layout
        changed_.clear();
        keep(*layout);
        return whole();
      }
      changed_.push_back(static_cast<std::uint32_t>(k));
    }
  }
  if (changed_.empty()) {  // nothing the stream carries changed
    encode_tick(out, tick, positions, nullptr, seq_, nullptr, carried);
    return sent::positions;
  }
  const std::size_t m = changed_.size();
  ch_aoi_.resize(3 * m), ch_presence_.resize(3 * m), ch_classes_.resize(m), ch_sees_.resize(m), ch_kinds_.resize(m);
  for (std::size_t c = 0; c < m; ++c) {
    const std::size_t k = changed_[c];
    for (int a = 0; a < 3; ++a) {
      ch_aoi_[3 * c + a] = aoi_[3 * k + a] = layout->aoi_half[3 * k + a];
      ch_presence_[3 * c + a] = presence_[3 * k + a] = layout->presence_half[3 * k + a];
    }
    ch_classes_[c] = classes_[k] = layout->classes[k];
    ch_sees_[c] = sees_[k] = layout->sees[k];
    ch_kinds_[c] = kinds_[k] = layout->kinds[k];
  }
  const changes_view cv{changed_, ch_aoi_, ch_presence_, ch_classes_, ch_sees_, ch_kinds_};
  encode_tick(out, tick, positions, nullptr, ++seq_, &cv, carried);
  return sent::changes;
}

std::optional<std::string> decode_tick(std::span<const std::uint8_t> body, tick_frame& out) {
  if (body.size() >= 4 && read_at<std::uint32_t>(body.data()) == refused_magic) {
    const auto text = body.subspan(4, std::min<std::size_t>(body.size() - 4, 512));
    return "the server refused this subscriber: " + std::string(text.begin(), text.end());
  }
  const std::size_t head = header_bytes - 4;
  if (body.size() < head) return "truth frame of " + std::to_string(body.size()) + " bytes is shorter than its header";
  const auto m0 = read_at<std::uint32_t>(body.data());
  const auto flags = read_at<std::uint32_t>(body.data() + 4);
  const auto tick = read_at<std::uint64_t>(body.data() + 8);
  const auto count = read_at<std::uint32_t>(body.data() + 16);
  const auto seq = read_at<std::uint32_t>(body.data() + 20);
  if (m0 != magic) return "not a truth frame (bad magic)";
  if ((flags & ~(flag_layout | flag_changes | flag_carried | flag_first_step)) != 0 ||
      (flags & (flag_layout | flag_changes)) == (flag_layout | flag_changes)) {
    return "truth frame with unknown flags " + std::to_string(flags);
  }
  const bool has_layout = (flags & flag_layout) != 0, has_changes = (flags & flag_changes) != 0;
  const bool has_carried = (flags & flag_carried) != 0;
  const std::size_t n = count;
  const auto where = [&] { return "truth frame of tick " + std::to_string(tick) + ": "; };
  std::size_t m = 0;
  if (has_changes) {
    if (body.size() < head + 12 * n + 4) {
      return where() + std::to_string(body.size()) + " bytes, too short for its changes";
    }
    m = read_at<std::uint32_t>(body.data() + head + 12 * n);
    if (m > n) return where() + std::to_string(m) + " changes of " + std::to_string(n) + " entities";
  }
  const std::size_t before_carried =
      head + 12 * n + (has_layout ? layout_bytes(n) : 0) + (has_changes ? changes_bytes(m) : 0);
  std::size_t kc = 0, tc = 0;
  if (has_carried) {
    if (body.size() < before_carried + 8)
      return where() + std::to_string(body.size()) + " bytes, too short for its carried sets";
    kc = read_at<std::uint32_t>(body.data() + before_carried);
    tc = read_at<std::uint32_t>(body.data() + before_carried + 4);
    if (kc == 0 || kc > n || tc > (body.size() - before_carried) / 4) {
      return where() + std::to_string(kc) + " carried sets of " + std::to_string(tc) + " targets for " +
             std::to_string(n) + " entities in " + std::to_string(body.size()) + " bytes";
    }
  }
  const std::size_t expect = before_carried + (has_carried ? carried_bytes(kc, tc) : 0);
  if (body.size() != expect) {
    return where() + std::to_string(body.size()) + " bytes for " + std::to_string(n) + " entities" +
           (has_changes ? " and " + std::to_string(m) + " changes" : std::string()) +
           (has_carried ? " and " + std::to_string(kc) + " carried sets" : std::string()) + ", expected " +
           std::to_string(expect);
  }
  const std::uint8_t* carried_at = body.data() + before_carried + 8;
  if (has_carried) {
    std::size_t sum = 0;
    for (std::size_t o = 0; o < kc; ++o) {
      const auto id = read_at<std::uint32_t>(carried_at + 4 * o);
      if (o > 0 && id <= read_at<std::uint32_t>(carried_at + 4 * (o - 1)))
        return where() + "carried observers do not ascend";
      const auto c = read_at<std::uint32_t>(carried_at + 4 * (kc + o));
      for (std::size_t j = 1; j < c && sum + j < tc; ++j) {
        const std::uint8_t* tg = carried_at + 8 * kc + 4 * (sum + j);
        if (read_at<std::uint32_t>(tg) <= read_at<std::uint32_t>(tg - 4))
          return where() + "carried targets do not ascend";
      }
      sum += c;
      if (sum > tc) break;
    }
    if (sum != tc) return where() + "carried target counts do not sum to " + std::to_string(tc);
  }
  if (!has_layout) {
    if (!out.layout_known) return where() + "no layout yet (a stream starts with a frame that has it)";
    if (n != out.ids.size()) {
      return where() + std::to_string(n) + " entities without a layout, the last layout had " +
             std::to_string(out.ids.size());
    }
    const std::uint32_t want = has_changes ? out.layout_seq + 1 : out.layout_seq;
    if (seq != want) {
      return where() + "layout " + std::to_string(seq) + ", the reader has layout " + std::to_string(out.layout_seq) +
             (has_changes ? " (changes apply to the layout just before them)" : "") +
             ": a frame that changed the layout was missed";
    }
  }
  const std::uint8_t* changes_at = body.data() + head + 12 * n + 4;
  if (has_changes) {
    for (std::size_t c = 0; c < m; ++c) {
      const auto k = read_at<std::uint32_t>(changes_at + 4 * c);
      if (k >= n || (c > 0 && k <= read_at<std::uint32_t>(changes_at + 4 * (c - 1)))) {
        return where() + "change " + std::to_string(c) + " is at index " + std::to_string(k) +
               " (indices must ascend below " + std::to_string(n) + ")";
      }
    }
  }
  // Valid: fill `out`.
  const std::uint8_t* at = body.data() + head;
  out.tick = tick;
  out.first_step = (flags & flag_first_step) != 0;
  out.count = count;
  out.layout_seq = seq;
  out.has_layout = has_layout;
  out.has_changes = has_changes;
  out.changed.clear();
  take(at, out.positions, 3 * n);
  if (has_layout) {
    take(at, out.ids, n);
    take(at, out.aoi_half, 3 * n);
    take(at, out.presence_half, 3 * n);
    take(at, out.classes, n);
    take(at, out.sees, n);
    take(at, out.kinds, n);
    out.layout_known = true;
  } else if (has_changes) {
    take(changes_at, out.changed, m);
    const std::uint8_t* aoi = changes_at;
    const std::uint8_t* presence = aoi + 12 * m;
    const std::uint8_t* classes = presence + 12 * m;
    const std::uint8_t* sees = classes + 4 * m;
    const std::uint8_t* kinds = sees + 4 * m;
    for (std::size_t c = 0; c < m; ++c) {
      const std::size_t k = out.changed[c];
      std::memcpy(&out.aoi_half[3 * k], aoi + 12 * c, 12);
      std::memcpy(&out.presence_half[3 * k], presence + 12 * c, 12);
      out.classes[k] = read_at<std::uint32_t>(classes + 4 * c);
      out.sees[k] = read_at<std::uint32_t>(sees + 4 * c);
      out.kinds[k] = kinds[c];
    }
  }
  out.carried_observers.clear();
  out.carried_off.clear();
  out.carried_targets.clear();
  if (has_carried) {
    take(carried_at, out.carried_observers, kc);
    out.carried_off.assign(1, 0);
    for (std::size_t o = 0; o < kc; ++o)
      out.carried_off.push_back(out.carried_off.back() + read_at<std::uint32_t>(carried_at + 4 * o));
    carried_at += 4 * kc;
    take(carried_at, out.carried_targets, tc);
  }
  return std::nullopt;
}

}  // namespace zone::net::truth
