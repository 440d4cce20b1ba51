// tools/cli.h: the tools' command lines on Boost.Program_options, as zone-server's and bot-swarm's:
// long options by their full name only (no abbreviations), values checked by their type, no
// positional arguments unless the tool names them, --help (-h) prints the tool's usage text.
#pragma once

#include <boost/program_options.hpp>

#include <charconv>
#include <cmath>
#include <cstdio>
#include <initializer_list>
#include <map>
#include <optional>
#include <string>
#include <string_view>
#include <type_traits>

namespace zone::tools {

namespace po = boost::program_options;

/// Parses argv against `options` (--help and -h are added). Returns nothing when the tool goes on;
/// otherwise the exit code: 0 after `usage` went to stdout (--help), `bad_exit` after one line naming
/// the error went to stderr (an unknown option, a missing or ill-typed value, a stray argument), then
/// `error_tail` where given (e.g. the tool's usage line). `positional`, where given, names the
/// arguments that are not options (without it, any such argument is an error).
[[nodiscard]] inline std::optional<int> parse_command_line(int argc, char** argv, const char* tool,
                                                           const std::string& usage, po::options_description options,
                                                           int bad_exit,
                                                           const po::positional_options_description* positional = nullptr,
                                                           const char* error_tail = nullptr) {
  options.add_options()("help,h", "print the usage");
  po::variables_map vm;
  try {
    // Without a positional description Boost ignores a stray argument; with an empty one it
    // refuses it ("too many positional options").
    const po::positional_options_description none;
    po::command_line_parser parser(argc, argv);
    parser.options(options)
        .style(po::command_line_style::unix_style & ~po::command_line_style::allow_guessing)
        .positional(positional != nullptr ? *positional : none);
    po::store(parser.run(), vm);
    po::notify(vm);
  } catch (const po::error& e) {
    std::fprintf(stderr, "%s: %s (see --help)\n", tool, e.what());
    if (error_tail != nullptr) std::fputs(error_tail, stderr);
    return bad_exit;
  }
  if (vm.count("help") != 0) {
    std::fputs(usage.c_str(), stdout);
    return 0;
  }
  return std::nullopt;
}

/// `text`, all of it, as a T (std::from_chars: no leading space or '+', no sign for an unsigned T,
/// no suffix; a floating-point T must be finite); nothing otherwise.
template <class T>
[[nodiscard]] std::optional<T> parse_value(std::string_view text) {
  T v{};
  const auto r = std::from_chars(text.data(), text.data() + text.size(), v);
  if (r.ec != std::errc{} || r.ptr != text.data() + text.size()) return std::nullopt;
  if constexpr (std::is_floating_point_v<T>) {
    if (!std::isfinite(v)) return std::nullopt;
  }
  return v;
}

/// Valued options that the tool checks itself (its own messages and ranges): adds each of `names`
/// ("name" or "name,c" with a one-letter alias) to `options`, taking one value as text; after
/// parse_command_line, `given` holds each given option's value under its long name.
inline void add_text_options(po::options_description& options, std::map<std::string, std::string>& given,
                             std::initializer_list<const char*> names) {
  for (const char* spec : names) {
    std::string name(spec);
    if (const auto comma = name.find(','); comma != std::string::npos) name.resize(comma);
    options.add_options()(spec, po::value<std::string>()->notifier([&given, name](const std::string& v) { given[name] = v; }));
  }
}

/// Sets `out` to the text of option `name` (see add_text_options) when it was given.
inline void take_text(const std::map<std::string, std::string>& given, const char* name, std::string& out) {
  if (const auto it = given.find(name); it != given.end()) out = it->second;
}

}  // namespace zone::tools
