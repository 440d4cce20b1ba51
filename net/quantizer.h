// Position and velocity quantization of the wire protocol (docs/protocol.md): 16 bits per axis
// relative to the world bounds, velocities in cm/s.
#pragma once

#include <array>
#include <cstdint>

#include "net/messages.h"

namespace zone::net {

/// Positions as 16 bits per axis relative to the world bounds: q = round((p - lo) / step) with
/// step = (hi - lo) / 65535, clamped to [0, 65535] (positions outside the bounds clamp to them).
/// Round-trip error per axis for a position inside the bounds: at most max_error() = step / 2
/// plus float rounding (a few ulps of the coordinate). A zero-width axis always decodes to lo.
class position_quantizer {
 public:
  explicit position_quantizer(const world_bounds& world);
  /// Inline (replication quantizes every update it sends); exactly the rounding of std::lround.
  [[nodiscard]] std::array<std::uint16_t, 3> quantize(const vec3f& p) const;
  [[nodiscard]] vec3f dequantize(const std::array<std::uint16_t, 3>& q) const;
  /// Guaranteed bound on |dequantize(quantize(p)) - p| per axis for p inside the bounds.
  [[nodiscard]] vec3f max_error() const;
  [[nodiscard]] const world_bounds& world() const { return world_; }
  /// The step of axis 0, 1 or 2 (0 for a zero-width or non-finite axis): what a device quantizing
  /// the same way needs (gpu/replication/replication_shared.h).
  [[nodiscard]] double step(int axis) const { return step_[axis]; }

 private:
  world_bounds world_;
  double step_[3];
};

/// Velocity in centimetres per second per axis, clamped to [-32767, 32767] (+-327.67 m/s).
/// Round-trip error within the range: at most velocity_max_error = 0.005 m/s (plus float rounding).
inline constexpr float velocity_max_error = 0.005f;
inline constexpr float velocity_limit = 327.67f;
[[nodiscard]] std::array<std::int16_t, 3> quantize_velocity(const vec3f& v);
[[nodiscard]] vec3f dequantize_velocity(const std::array<std::int16_t, 3>& q);

namespace detail {
/// std::lround(t) for 0 <= t < 2^31 without the library call: round half away from zero.
/// t - trunc(t) is exact in double, so the comparison with 0.5 decides exactly as lround does.
inline std::uint32_t round_half_up(double t) {
  const auto i = static_cast<std::uint32_t>(t);
  return i + (t - static_cast<double>(i) >= 0.5 ? 1u : 0u);
}
}  // namespace detail

inline std::array<std::uint16_t, 3> position_quantizer::quantize(const vec3f& p) const {
  const float v[3] = {p.x, p.y, p.z};
  const float lo[3] = {world_.lo.x, world_.lo.y, world_.lo.z};
  std::array<std::uint16_t, 3> q{};
  for (int d = 0; d < 3; ++d) {
    if (step_[d] <= 0) continue;
    const double t = (static_cast<double>(v[d]) - static_cast<double>(lo[d])) / step_[d];
    // NaN and below-range clamp to 0, above-range to 65535.
    q[d] = !(t > 0) ? 0 : t >= 65535.0 ? 65535 : static_cast<std::uint16_t>(detail::round_half_up(t));
  }
  return q;
}

inline std::array<std::int16_t, 3> quantize_velocity(const vec3f& v) {
  const auto axis = [](float x) -> std::int16_t {
    const double t = static_cast<double>(x) * 100.0;
    if (!(t == t)) return 0;  // NaN
    const double c = std::clamp(t, -32767.0, 32767.0);
    const auto r = static_cast<std::int32_t>(detail::round_half_up(c < 0 ? -c : c));
    return static_cast<std::int16_t>(c < 0 ? -r : r);
  };
  return {axis(v.x), axis(v.y), axis(v.z)};
}

}  // namespace zone::net
