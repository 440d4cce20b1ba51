// Client strings: what the server accepts as a player name, and how it logs client-supplied text.
#pragma once

#include <cstddef>
#include <optional>
#include <string>
#include <string_view>

namespace zone::net {

/// Why `name` is not an acceptable player name, or nothing when it is: 1 .. max_bytes bytes of
/// printable ASCII (0x20-0x7E), no leading or trailing space. Pure; any bytes are safe input.
[[nodiscard]] std::optional<std::string> check_player_name(std::string_view name, std::size_t max_bytes);

/// A client-supplied string made safe for one log line: printable ASCII except the backslash is
/// kept, every other byte (newlines, escape sequences, UTF-8, NUL) is written as \xNN and the
/// backslash as \\; at most `max_bytes` input bytes are shown, then "...(N bytes)". The result
/// holds no byte below 0x20 or above 0x7E and is at most 4 * max_bytes + 32 bytes long.
[[nodiscard]] std::string escape_for_log(std::string_view s, std::size_t max_bytes = 64);

}  // namespace zone::net
