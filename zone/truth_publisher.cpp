// The ground-truth stream's server side (truth_publisher.h).
#include "truth_publisher.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <unistd.h>

#include <spdlog/spdlog.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>

#include "net/truth.h"

namespace zone {

static_assert(sizeof(vec3) == 3 * sizeof(float), "positions are copied as float triples");

truth_publisher::~truth_publisher() { stop(); }

std::optional<std::string> truth_publisher::start(std::uint16_t port, int max_subscribers) {
  max_subscribers_ = std::max(1, max_subscribers);
  listen_fd_ = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (listen_fd_ < 0) return std::string("oracle stream: socket: ") + std::strerror(errno);
  const int one = 1;
  ::setsockopt(listen_fd_, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(port);
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);  // loopback only, whatever --listen says
  if (::bind(listen_fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0 || ::listen(listen_fd_, 4) != 0) {
    return "oracle stream: cannot listen on 127.0.0.1:" + std::to_string(port) + ": " + std::strerror(errno);
  }
  socklen_t len = sizeof addr;
  ::getsockname(listen_fd_, reinterpret_cast<sockaddr*>(&addr), &len);
  port_ = ntohs(addr.sin_port);
  wake_fd_ = ::eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (wake_fd_ < 0) return std::string("oracle stream: eventfd: ") + std::strerror(errno);
  thread_ = std::thread([this] { run(); });
  return std::nullopt;
}

void truth_publisher::stop() {
  if (!thread_.joinable()) {
    if (listen_fd_ >= 0) ::close(listen_fd_), listen_fd_ = -1;
    return;
  }
  stopping_ = true;
  wake();
  thread_.join();
  for (auto& s : subs_) ::close(s.fd);
  subs_.clear();
  ::close(listen_fd_), listen_fd_ = -1;
  ::close(wake_fd_), wake_fd_ = -1;
}

void carried_columns::assign(std::span<const std::pair<entity_id, entity_id>> pairs) {
  observers.clear();
  off.assign(1, 0);
  targets.clear();
  for (const auto& [observer, target] : pairs) {
    if (observers.empty() || observers.back() != observer) {
      if (!observers.empty()) off.push_back(static_cast<std::uint32_t>(targets.size()));
      observers.push_back(observer);
    }
    if (target != null_entity) targets.push_back(target);
  }
  if (!observers.empty()) off.push_back(static_cast<std::uint32_t>(targets.size()));
}

void truth_publisher::wake() {
  const std::uint64_t one = 1;
  [[maybe_unused]] const auto n = ::write(wake_fd_, &one, sizeof one);
}

void truth_publisher::publish(const entity_store& store, std::uint64_t tick,
                              std::span<const std::pair<entity_id, entity_id>> carried, bool first_step) {
  if (subscribers_.load(std::memory_order_acquire) == 0 && !recording_) return;
  const auto t0 = std::chrono::steady_clock::now();
  const std::size_t n = store.size();
  // The columns go to the encoder only when the store says something but positions changed; it
  // then sends the whole layout, the changed rows, or nothing of them (net/truth.h, encoder).
  const bool layout = !any_published_ || store.layout_version() != layout_version_;
  const bool force = need_layout_.exchange(false);
  // A buffer no subscriber still holds (the sender drops its reference once written), else a new one.
  std::shared_ptr<std::vector<std::uint8_t>> frame;
  for (const auto& b : pool_) {
    if (b.use_count() == 1) {
      std::atomic_thread_fence(std::memory_order_acquire);  // the sender's last read of it came before
      frame = b;
      break;
    }
  }
  if (!frame) {
    frame = std::make_shared<std::vector<std::uint8_t>>();
    if (pool_.size() < 16) pool_.push_back(frame);
  }
  const auto floats = [](std::span<const vec3> v) {
    return std::span<const float>(reinterpret_cast<const float*>(v.data()), 3 * v.size());
  };
  net::truth::layout_view lv;
  if (layout) {
    kinds_.resize(n);
    const auto kinds = store.kinds();
    for (std::size_t k = 0; k < n; ++k) kinds_[k] = static_cast<std::uint8_t>(kinds[k]);
    lv = {store.ids(), floats(store.aoi_half_extents()), floats(store.presence_half_extents()),
          store.visibility_classes(), store.sees(), kinds_};
  }
  carried_.assign(carried);
  const net::truth::carried_view cv = carried_.view();
  const auto sent = encoder_.encode(*frame, tick, floats(store.positions()), layout ? &lv : nullptr, force, &cv);
  if (first_step) net::truth::mark_first_step(*frame);
  const bool whole = sent == net::truth::encoder::sent::layout;
  layout_version_ = store.layout_version();
  any_published_ = true;
  ++stats_.ticks;
  stats_.bytes += frame->size();
  stats_.layouts += whole ? 1 : 0;
  if (sent == net::truth::encoder::sent::changes) {
    ++stats_.changes;
    stats_.changed_entities += encoder_.last_changes();
  }
  {
    const std::lock_guard lock(mutex_);
    if (recording_) {
      const auto now = std::chrono::steady_clock::now();
      if (prefix_.empty()) first_publish_ = now;
      if (now - first_publish_ > std::chrono::duration<double>(prefix_window_s) ||
          prefix_bytes_ + frame->size() > max_prefix_bytes) {
        recording_ = false;  // over: later subscribers start from the frame after they connect
        prefix_.clear();
        prefix_bytes_ = 0;
      } else {
        prefix_.push_back(frame);
        prefix_bytes_ += frame->size();
      }
    }
    for (auto& s : subs_) {
      if (!s.has_layout && !whole) continue;  // its first frame must carry the whole layout
      s.has_layout = true;
      s.queue.push_back(frame);
      s.queued_bytes += frame->size();
    }
  }
  wake();
  stats_.publish_ms += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

void truth_publisher::run() {
  std::vector<pollfd> fds;
  while (!stopping_.load()) {
    fds.clear();
    fds.push_back({wake_fd_, POLLIN, 0});
    fds.push_back({listen_fd_, POLLIN, 0});
    {
      const std::lock_guard lock(mutex_);
      for (const auto& s : subs_) fds.push_back({s.fd, static_cast<short>(POLLIN | (s.queue.empty() ? 0 : POLLOUT)), 0});
    }
    if (::poll(fds.data(), fds.size(), 200) < 0 && errno != EINTR) break;
    if (fds[0].revents & POLLIN) {
      std::uint64_t v = 0;
      [[maybe_unused]] const auto n = ::read(wake_fd_, &v, sizeof v);
    }
    if (fds[1].revents & POLLIN) {
      const int fd = ::accept4(listen_fd_, nullptr, nullptr, SOCK_NONBLOCK | SOCK_CLOEXEC);
      if (fd >= 0) {
        const std::lock_guard lock(mutex_);
        if (static_cast<int>(subs_.size()) >= max_subscribers_) {
          // A refusal the subscriber reads as its error (a fresh socket's buffer takes it whole).
          const std::string why = "zone-server serves at most " + std::to_string(max_subscribers_) +
                                  " truth-stream subscribers at once (--oracle-subscribers) and has them";
          std::vector<std::uint8_t> refusal;
          net::truth::encode_refusal(refusal, why);
          [[maybe_unused]] const auto w = ::send(fd, refusal.data(), refusal.size(), MSG_NOSIGNAL | MSG_DONTWAIT);
          ::close(fd);
          ++stats_.refused_subscribers;
          spdlog::warn("oracle stream: refused a subscriber: {} connected, the limit (--oracle-subscribers)",
                       max_subscribers_);
        } else {
          const int buf = 4 << 20;
          ::setsockopt(fd, SOL_SOCKET, SO_SNDBUF, &buf, sizeof buf);
          subscriber sub;
          sub.fd = fd;
          if (!prefix_.empty()) {  // the first frames, from the first (a whole layout), then the live ones
            sub.queue.assign(prefix_.begin(), prefix_.end());
            sub.queued_bytes = prefix_bytes_;
            sub.has_layout = true;
            ++stats_.prefix_subscribers;
          }
          subs_.push_back(std::move(sub));
          subscribers_.store(static_cast<int>(subs_.size()), std::memory_order_release);
          need_layout_ = true;
          spdlog::info("oracle stream: subscriber connected");
        }
      }
    }
    const std::lock_guard lock(mutex_);
    for (std::size_t i = 0; i < subs_.size();) {
      subscriber& s = subs_[i];
      bool drop = false;
      const char* why = "";
      // Anything readable is a close (a subscriber sends nothing).
      char ignored[256];
      const auto r = ::recv(s.fd, ignored, sizeof ignored, MSG_DONTWAIT);
      if (r == 0 || (r < 0 && errno != EAGAIN && errno != EWOULDBLOCK)) drop = true, why = "closed";
      while (!drop && !s.queue.empty()) {
        const auto& f = *s.queue.front();
        const auto w = ::send(s.fd, f.data() + s.offset, f.size() - s.offset, MSG_NOSIGNAL | MSG_DONTWAIT);
        if (w < 0) {
          if (errno != EAGAIN && errno != EWOULDBLOCK) drop = true, why = "send failed";
          break;
        }
        s.offset += static_cast<std::size_t>(w);
        if (s.offset == f.size()) {
          s.queued_bytes -= f.size();
          s.offset = 0;
          s.queue.pop_front();
        }
      }
      if (!drop && s.queued_bytes > max_queued_bytes) {
        drop = true, why = "too far behind";
        ++stats_.dropped_subscribers;
      }
      if (drop) {
        spdlog::log(std::strcmp(why, "closed") == 0 ? spdlog::level::info : spdlog::level::err,
                    "oracle stream: subscriber dropped ({})", why);
        ::close(s.fd);
        subs_.erase(subs_.begin() + static_cast<std::ptrdiff_t>(i));
        subscribers_.store(static_cast<int>(subs_.size()), std::memory_order_release);
      } else {
        ++i;
      }
    }
  }
}

}  // namespace zone
