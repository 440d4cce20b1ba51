// A client's token as the protocol carries it (welcome.resume_token, redirect.token, hello.token):
// 16 hex digits of a nonzero 64-bit value. A single zone's resume tokens (zone/resume_book.h) and a
// world's (world/world.h: the region in the top 16 bits) are both read and written here.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

namespace zone {

/// A token's value from its text: 16 lowercase or uppercase hex digits, not all 0; nullopt otherwise.
[[nodiscard]] std::optional<std::uint64_t> parse_token(std::string_view token);
/// `v` as 16 lowercase hex digits (a token's text; also any 64-bit id written so).
[[nodiscard]] std::string hex16(std::uint64_t v);
/// 64 bits from the OS's random source (std::random_device: getrandom or rdrand), not a seeded
/// generator whose next outputs a client could work out from the tokens it was told.
[[nodiscard]] std::uint64_t os_random_u64();

}  // namespace zone
