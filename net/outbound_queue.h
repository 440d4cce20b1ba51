// A session's outbound queue and its drop policy (private to net/; server.cpp uses it under the
// session's write lock, tests use it without sockets). Not thread-safe: one owner at a time.
//
// State frames are deltas: each one moves the client's view on from the view the previous state
// frame left. So once one is dropped, every later delta is useless to the client until a frame
// that rebuilds the view from scratch (a reset). The policy:
//
// - control frames (welcome, pong, error) are never dropped and keep their order; more than
//   twice the bound queued means a stuck client (`overflow`: the caller closes the session);
// - a state frame arriving at a full queue (`bound` frames, the one being written included)
//   starts a drop episode: every queued state frame that is not being written is dropped, and so
//   is the new frame; the queue awaits a reset, and push() says so once (`resync`: report it to
//   the game, which makes the client's next frame a reset);
// - while awaiting a reset, plain state frames are dropped on arrival (counted, not reported
//   again);
// - a reset frame ends the wait, and replaces every state frame queued before it (they are
//   superseded; counted as dropped, not reported);
// - a reset frame that cannot be queued (control frames fill the queue) is dropped and reported
//   again, so a reset is never lost without another resync being asked for.
//
// Hence the client gets, in order, the frames being written when the episode began, then nothing
// but control frames until a reset: every state frame it receives is a reset or the successor of
// the state frame it received before. At most `bound` state frames and 2 x `bound` frames in all
// are held.
//
// Writes are gathered: start_write() marks the first few queued frames (at most `bound` - 1, so a
// reset always fits behind them, and about `gather_bytes`) as being written, and the session
// writes them with one gathered write; finish_write() retires them all, finish_frames(k) the first
// k of them (a partial write: the others stay in flight). "The frame being written" above means
// these frames.
#pragma once

#include <algorithm>
#include <cstddef>
#include <iterator>
#include <vector>

#include "server.h"

namespace zone::net {

class outbound_queue {
 public:
  struct entry {
    shared_frame frame;
    delivery kind = delivery::state;
    std::uint64_t stamp_us = 0;  ///< what the frame's age counts from (outgoing_frame::stamp_us)
  };

  /// The queued frames, oldest first: a ring of 2 x bound slots allocated with the queue, so
  /// pushing and retiring frames allocates nothing (a std::deque allocated a block every 16
  /// frames and freed one as many). Random access and iteration, like the deque it replaced.
  class ring {
   public:
    explicit ring(std::size_t capacity) : slots_(std::max<std::size_t>(1, capacity)) {}
    [[nodiscard]] std::size_t size() const { return size_; }
    [[nodiscard]] bool empty() const { return size_ == 0; }
    [[nodiscard]] std::size_t capacity() const { return slots_.size(); }
    [[nodiscard]] const entry& operator[](std::size_t i) const { return slots_[at(i)]; }
    [[nodiscard]] entry& operator[](std::size_t i) { return slots_[at(i)]; }
    [[nodiscard]] const entry& front() const { return slots_[head_]; }
    [[nodiscard]] const entry& back() const { return (*this)[size_ - 1]; }

    class const_iterator {
     public:
      using iterator_category = std::forward_iterator_tag;
      using value_type = entry;
      using difference_type = std::ptrdiff_t;
      using pointer = const entry*;
      using reference = const entry&;
      const_iterator() = default;
      const_iterator(const ring* r, std::size_t i) : r_(r), i_(i) {}
      reference operator*() const { return (*r_)[i_]; }
      pointer operator->() const { return &(*r_)[i_]; }
      const_iterator& operator++() {
        ++i_;
        return *this;
      }
      const_iterator operator++(int) {
        auto t = *this;
        ++i_;
        return t;
      }
      friend bool operator==(const const_iterator& a, const const_iterator& b) { return a.i_ == b.i_; }

     private:
      const ring* r_ = nullptr;
      std::size_t i_ = 0;
    };
    [[nodiscard]] const_iterator begin() const { return {this, 0}; }
    [[nodiscard]] const_iterator end() const { return {this, size_}; }

    /// The caller keeps size() < capacity() (the queue's bounds do).
    void push_back(entry e) {
      slots_[at(size_)] = std::move(e);
      ++size_;
    }
    /// Retires the first k entries (their frames are released now).
    void pop_front(std::size_t k) {
      k = std::min(k, size_);
      for (std::size_t i = 0; i < k; ++i) {
        slots_[head_] = entry{};
        head_ = head_ + 1 == slots_.size() ? 0 : head_ + 1;
      }
      size_ -= k;
      if (size_ == 0) head_ = 0;
    }
    /// Keeps the first n entries.
    void truncate(std::size_t n) {
      for (std::size_t i = n; i < size_; ++i) (*this)[i] = entry{};
      size_ = std::min(n, size_);
    }
    /// Removes the entries from `first` on that `drop` selects, keeping the others in order; how many.
    template <class Pred>
    std::size_t remove_from_if(std::size_t first, Pred drop) {
      std::size_t w = first;
      for (std::size_t i = first; i < size_; ++i) {
        if (drop((*this)[i])) continue;
        if (w != i) (*this)[w] = std::move((*this)[i]);
        ++w;
      }
      const std::size_t removed = size_ - w;
      truncate(w);
      return removed;
    }
    void clear() { truncate(0); head_ = 0; }

   private:
    [[nodiscard]] std::size_t at(std::size_t i) const {
      const std::size_t j = head_ + i;
      return j >= slots_.size() ? j - slots_.size() : j;
    }
    std::vector<entry> slots_;
    std::size_t head_ = 0, size_ = 0;
  };

  /// What push() did.
  struct push_result {
    bool queued = false;       ///< the frame was queued
    bool resync = false;       ///< a drop episode began (or a reset was dropped): ask the game for a reset
    bool overflow = false;     ///< control frames beyond twice the bound: a stuck client, close it
    std::size_t dropped = 0;   ///< state frames dropped by this push (queued ones, and the new one if not queued)
  };

  /// Most bytes one gathered write takes (a larger first frame is still taken alone).
  static constexpr std::size_t gather_bytes = 64 * 1024;

  explicit outbound_queue(std::size_t bound) : bound_(std::max<std::size_t>(1, bound)), queue_(2 * bound_) {}

  push_result push(shared_frame frame, delivery d, std::uint64_t stamp_us = 0) {
    push_result r;
    switch (d) {
      case delivery::control:
        if (queue_.size() >= 2 * bound_) {
          r.overflow = true;
          return r;
        }
        break;
      case delivery::state_reset:
        r.dropped = drop_queued_state();  // superseded by the reset
        if (queue_.size() >= bound_) {    // control frames alone fill the queue
          awaiting_reset_ = true;
          r.resync = true;
          ++r.dropped;
          return r;
        }
        awaiting_reset_ = false;
        break;
      case delivery::state:
        if (awaiting_reset_) {
          r.dropped = 1;
          return r;
        }
        if (queue_.size() >= bound_) {
          r.dropped = drop_queued_state() + 1;
          awaiting_reset_ = true;
          r.resync = true;
          return r;
        }
        break;
    }
    queue_.push_back({std::move(frame), d, stamp_us});
    r.queued = true;
    return r;
  }

  /// The next frame to write, marked as being written; null when a write is in flight already or
  /// nothing is queued. (One frame per write; start_write_many() gathers.)
  [[nodiscard]] const entry* start_write() { return start_write_many(1) == 0 ? nullptr : &queue_.front(); }
  /// Marks the first queued frames as being written, one gathered write: at most `max_frames`,
  /// at most bound - 1, and no more than gather_bytes (at least one frame). How many (they are
  /// entries()[0, n)); 0 when a write is in flight already or nothing is queued.
  [[nodiscard]] std::size_t start_write_many(std::size_t max_frames) {
    if (in_flight_ != 0 || queue_.empty()) return 0;
    const std::size_t most = std::min({max_frames, std::max<std::size_t>(1, bound_ - 1), queue_.size()});
    std::size_t n = 0, bytes = 0;
    while (n < std::max<std::size_t>(1, most)) {
      const std::size_t b = queue_[n].frame.size();
      if (n != 0 && bytes + b > gather_bytes) break;
      bytes += b;
      ++n;
    }
    in_flight_ = n;
    return n;
  }
  /// The frames being written are done (written or failed): they leave the queue.
  void finish_write() {
    queue_.pop_front(in_flight_);
    in_flight_ = 0;
  }
  /// The first `k` frames being written are done (a partial write: the rest stay in flight, so
  /// the next write goes on with them and the drop policy still never touches them).
  void finish_frames(std::size_t k) {
    k = std::min(k, in_flight_);
    queue_.pop_front(k);
    in_flight_ -= k;
  }
  /// Control frames queued behind the frames being written.
  [[nodiscard]] std::size_t control_waiting() const {
    std::size_t n = 0;
    for (std::size_t i = in_flight_; i < queue_.size(); ++i) n += queue_[i].kind == delivery::control ? 1 : 0;
    return n;
  }
  /// The client is not draining its socket (the game decided: net::server::drop_stale_state):
  /// every queued state frame that is not being written is dropped (it would be stale when the
  /// client reads it), and the queue awaits a reset, as after a drop episode (plain state frames
  /// dropped on arrival). Not reported (the caller resyncs the client itself). How many dropped.
  std::size_t drop_stale() {
    const std::size_t n = drop_queued_state();
    awaiting_reset_ = true;
    return n;
  }
  /// Keeps only the frames being written (a closing session queues its error frame next).
  void keep_only_in_flight() { queue_.truncate(in_flight_); }
  void clear() {
    queue_.clear();
    in_flight_ = 0;
  }

  [[nodiscard]] bool writing() const { return in_flight_ != 0; }
  /// Frames being written (the first ones of entries()).
  [[nodiscard]] std::size_t in_flight() const { return in_flight_; }
  [[nodiscard]] bool empty() const { return queue_.empty(); }
  [[nodiscard]] std::size_t size() const { return queue_.size(); }
  [[nodiscard]] bool awaiting_reset() const { return awaiting_reset_; }
  [[nodiscard]] const ring& entries() const { return queue_; }

 private:
  /// Drops every queued state frame (plain or reset) except those being written; how many.
  std::size_t drop_queued_state() {
    return queue_.remove_from_if(in_flight_, [](const entry& e) { return e.kind != delivery::control; });
  }

  std::size_t bound_;
  ring queue_;                  // the first in_flight_ entries are being written; at most 2 x bound_
  std::size_t in_flight_ = 0;
  bool awaiting_reset_ = false;
};

}  // namespace zone::net
