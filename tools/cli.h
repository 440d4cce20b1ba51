// tools/cli.h: the tools' command lines on Boost.Program_options, as zone-server's and bot-swarm's:
// long options by their full name only (no abbreviations), values checked by their type, no
// positional arguments, --help (-h) prints the tool's usage text.
#pragma once

#include <boost/program_options.hpp>

#include <cstdio>
#include <optional>
#include <string>

namespace zone::tools {

namespace po = boost::program_options;

/// Parses argv against `options` (--help and -h are added). Returns nothing when the tool goes on;
/// otherwise the exit code: 0 after `usage` went to stdout (--help), `bad_exit` after one line naming
/// the error went to stderr (an unknown option, a missing or ill-typed value, a stray argument).
[[nodiscard]] inline std::optional<int> parse_command_line(int argc, char** argv, const char* tool,
                                                           const std::string& usage, po::options_description options,
                                                           int bad_exit) {
  options.add_options()("help,h", "print the usage");
  po::variables_map vm;
  try {
    po::store(po::command_line_parser(argc, argv)
                  .options(options)
                  .style(po::command_line_style::unix_style & ~po::command_line_style::allow_guessing)
                  .run(),
              vm);
    po::notify(vm);
  } catch (const po::error& e) {
    std::fprintf(stderr, "%s: %s (see --help)\n", tool, e.what());
    return bad_exit;
  }
  if (vm.count("help") != 0) {
    std::fputs(usage.c_str(), stdout);
    return 0;
  }
  return std::nullopt;
}

}  // namespace zone::tools
