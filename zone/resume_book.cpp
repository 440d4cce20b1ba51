#include "resume_book.h"

namespace zone {

resume_book::resume_book(std::uint64_t linger_ticks, std::size_t max_kept)
    : linger_ticks_(linger_ticks), max_kept_(max_kept) {}

std::string resume_book::issue(entity_id e) {
  if (const auto it = by_entity_.find(e); it != by_entity_.end()) return hex16(it->second);
  std::uint64_t t = 0;
  while (t == 0 || by_token_.count(t) != 0) t = os_random_u64();
  by_token_[t] = {e, false, 0};
  by_entity_[e] = t;
  return hex16(t);
}

bool resume_book::keep(entity_id e, std::uint64_t tick) {
  const auto it = by_entity_.find(e);
  if (it == by_entity_.end()) return false;
  entry& en = by_token_.at(it->second);
  if (linger_ticks_ == 0 || kept_ >= max_kept_) {
    forget(e);
    return false;
  }
  if (!en.kept) ++kept_;
  en.kept = true;
  en.until = tick + linger_ticks_;
  waits_.emplace_back(en.until, it->second);
  return true;
}

void resume_book::forget(entity_id e) {
  const auto it = by_entity_.find(e);
  if (it == by_entity_.end()) return;
  const auto t = by_token_.find(it->second);
  if (t != by_token_.end()) {
    if (t->second.kept) --kept_;
    by_token_.erase(t);
  }
  by_entity_.erase(it);
}

resume_book::claim resume_book::take(std::string_view token) {
  const auto t = parse_token(token);
  if (!t) return {};
  const auto it = by_token_.find(*t);
  if (it == by_token_.end()) return {};
  claim c{it->second.entity, !it->second.kept};
  if (it->second.kept) --kept_;
  it->second.kept = false;
  return c;
}

void resume_book::expire(std::uint64_t tick, std::vector<entity_id>& out) {
  while (!waits_.empty() && waits_.front().first <= tick) {
    const auto [until, token] = waits_.front();
    waits_.pop_front();
    const auto it = by_token_.find(token);
    // Claimed meanwhile (and perhaps lost again: its later wait is further back), or forgotten.
    if (it == by_token_.end() || !it->second.kept || it->second.until != until) continue;
    out.push_back(it->second.entity);
    forget(it->second.entity);
  }
}

}  // namespace zone
