// bot-swarm: many scripted bots against a zone server, with measurements and verification
// (docs/bots.md). `bot-swarm --help` lists the options.
#include <boost/program_options.hpp>
#include <nlohmann/json.hpp>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <sstream>

#include "interest/measure.h"
#include "net/os_limits.h"
#include "swarm.h"

namespace {

namespace po = boost::program_options;
using zone::bots::latency_histogram_us;
using zone::bots::percentile_ms;
using zone::bots::swarm_options;
using zone::bots::swarm_result;

/// "walk=0.6,patrol=0.2,follow=0.1,crowd=0.1" -> shares; an error text on a bad entry.
std::string parse_mix(const std::string& text, std::array<double, zone::bots::behaviour_count>& mix) {
  mix = {};
  std::stringstream in(text);
  std::string item;
  while (std::getline(in, item, ',')) {
    const auto eq = item.find('=');
    if (eq == std::string::npos) return "mix entry '" + item + "' is not name=share";
    const std::string name = item.substr(0, eq);
    double share = 0;
    try {
      share = std::stod(item.substr(eq + 1));
    } catch (...) {
      return "mix entry '" + item + "' has no number";
    }
    if (!(share >= 0)) return "mix share of '" + name + "' must be >= 0";
    bool found = false;
    for (std::size_t k = 0; k < zone::bots::behaviour_names.size(); ++k) {
      if (name == zone::bots::behaviour_names[k]) mix[k] += share, found = true;
    }
    if (!found) return "unknown behaviour '" + name + "' (walk, patrol, follow, crowd, teleport)";
  }
  double total = 0;
  for (const double m : mix) total += m;
  if (total <= 0) return "the mix must have a positive share";
  return {};
}

void print_progress(const zone::bots::second_sample& s, const zone::bots::swarm_counters& c, const swarm_options& o) {
  std::fprintf(stderr,
               "[%5.1fs] bots %llu/%u  fail %llu  drop %llu | %6llu msg/s %8.1f KB/s | latency p50 %6.2f p99 %6.2f ms | "
               "enters %llu leaves %llu | mismatches %llu\n",
               s.t, static_cast<unsigned long long>(s.connected), o.bots,
               static_cast<unsigned long long>(c.connect_failures.load()),
               static_cast<unsigned long long>(c.unexpected_disconnects.load()), static_cast<unsigned long long>(s.frames),
               static_cast<double>(s.bytes) / 1024.0, s.p50_ms, s.p99_ms, static_cast<unsigned long long>(s.enters),
               static_cast<unsigned long long>(s.leaves), static_cast<unsigned long long>(s.mismatches));
}

using zone::quantile;

struct summary {
  double p50 = 0, p95 = 0, p99 = 0, max = 0;
  std::uint64_t samples = 0;
  // The same from when every bot was connected (swarm_result::steady_latency).
  double steady_p50 = 0, steady_p95 = 0, steady_p99 = 0;
  std::uint64_t steady_samples = 0;
  double kbps_median = 0, kbps_p95 = 0, msgs_median = 0;
  double total_kbps = 0;
};

summary summarize(const swarm_result& r) {
  summary s;
  s.p50 = zone::bots::percentile_ms(r.latency, 0.5);
  s.p95 = zone::bots::percentile_ms(r.latency, 0.95);
  s.p99 = zone::bots::percentile_ms(r.latency, 0.99);
  s.max = r.latency_max_ms;
  s.samples = latency_histogram_us::total(r.latency);
  s.steady_samples = latency_histogram_us::total(r.steady_latency);
  if (s.steady_samples > 0) {
    s.steady_p50 = zone::bots::percentile_ms(r.steady_latency, 0.5);
    s.steady_p95 = zone::bots::percentile_ms(r.steady_latency, 0.95);
    s.steady_p99 = zone::bots::percentile_ms(r.steady_latency, 0.99);
  }
  std::vector<double> kbps, msgs;
  for (const auto& slot : r.slots) {
    if (slot.connected_s < 1.0) continue;
    kbps.push_back(static_cast<double>(slot.bytes_in) / 1024.0 / slot.connected_s);
    msgs.push_back(static_cast<double>(slot.frames_in) / slot.connected_s);
  }
  s.kbps_median = quantile(kbps, 0.5);
  s.kbps_p95 = quantile(kbps, 0.95);
  s.msgs_median = quantile(msgs, 0.5);
  s.total_kbps = r.elapsed_s > 0 ? static_cast<double>(r.bytes_in) / 1024.0 / r.elapsed_s : 0;
  return s;
}

void print_table(const swarm_result& r, const summary& s) {
  const auto row = [](const char* name, const std::string& value) { std::printf("  %-34s %s\n", name, value.c_str()); };
  const auto num = [](auto v) { return std::to_string(v); };
  const auto ms = [](double v) {
    char b[32];
    std::snprintf(b, sizeof b, "%.2f ms", v);
    return std::string(b);
  };
  const auto fmt = [](double v, const char* unit) {
    char b[48];
    std::snprintf(b, sizeof b, "%.1f %s", v, unit);
    return std::string(b);
  };
  std::printf("bot-swarm report (%u bots, %.1f s, %s:%u)\n", r.options.bots, r.elapsed_s, r.options.host.c_str(),
              r.options.port);
  row("bots connected (ever) / asked", num(r.bots_connected) + " / " + num(r.options.bots));
  row("connection attempts", num(r.connect_attempts));
  row("connection failures", num(r.connect_failures));
  row("unexpected disconnects", num(r.unexpected_disconnects));
  row("server errors received", num(r.server_errors));
  row("churn logouts", num(r.logouts));
  if (r.cuts > 0) row("connections cut (--cut)", num(r.cuts));
  row("teleports sent", num(r.teleports_sent));
  row("joined stealthed / in a team", num(r.stealth_joins) + " / " + num(r.team_joins));
  row("visibility switches sent", num(r.visibility_switches_sent));
  row("class notes received", num(r.class_notes));
  row("redirects followed (world of zones)", num(r.redirects));
  if (r.gate_redirects > 0) row("logins a world's gate sent to a zone", num(r.gate_redirects));
  row("logins again after a disconnect", num(r.reconnects));
  if (r.resumes + r.resumes_refused > 0)
    row("resumes: entity back / token refused", num(r.resumes) + " / " + num(r.resumes_refused));
  const auto login = [&](const latency_histogram_us::counts& c, double max_ms) {
    return ms(percentile_ms(c, 0.5)) + " / " + ms(percentile_ms(c, 0.99)) + " / " + ms(max_ms) + " (" +
           num(latency_histogram_us::total(c)) + ")";
  };
  row("login: launch to connected p50 / p99 / max", login(r.connect_time, r.connect_max_ms));
  row("login: connected to welcome p50 / p99 / max", login(r.welcome_time, r.welcome_max_ms));
  row("update latency p50", ms(s.p50));
  row("update latency p95", ms(s.p95));
  row("update latency p99", ms(s.p99));
  row("update latency max", ms(s.max));
  row("latency samples (unsynced)", num(s.samples) + " (" + num(r.latency_unsynced) + ")");
  if (s.steady_samples > 0) {
    char from[32];
    std::snprintf(from, sizeof from, "%.0f", r.steady_from_s);
    row((std::string("all connected (from ") + from + " s): p50").c_str(), ms(s.steady_p50));
    row("all connected: p95 / p99", ms(s.steady_p95) + " / " + ms(s.steady_p99));
    row("all connected: latency samples", num(s.steady_samples));
  } else {
    row("all connected", std::string("never (no second with every bot connected)"));
  }
  row("clock", r.host_clock ? std::string("host clock (same host: exact)") : "ping sync, fastest RTT " + ms(r.min_rtt_ms));
  row("downstream per bot, median", fmt(s.kbps_median, "KB/s"));
  row("downstream per bot, p95", fmt(s.kbps_p95, "KB/s"));
  row("messages per bot per s, median", fmt(s.msgs_median, "msg/s"));
  row("downstream, all bots", fmt(s.total_kbps, "KB/s"));
  row("tick updates", num(r.tick_updates));
  row("enters / leaves / updates", num(r.enters) + " / " + num(r.leaves) + " / " + num(r.updates));
  row("resyncs (reset after the first)", num(r.resets));
  row("inputs sent", num(r.inputs_sent) + (r.options.inputs_on_change
                                               ? " (" + num(r.inputs_unchanged) + " unchanged intents not sent)"
                                               : std::string()));
  row("digests checked", num(r.digests_checked) + (r.options.verify ? "" : " (not compared: no --verify)"));
  row("digest mismatches", num(r.digest_mismatches));
  row("inconsistent updates", num(r.inconsistent));
  row("frames with the bot's own position", num(r.self_positions));
  row("AOI checks / unchecked / violations", num(r.aoi_checked) + " / " + num(r.aoi_unchecked) + " / " + num(r.aoi_violations));
  row("AOI check's rules", r.rules_from_server ? std::string("from the server's welcome") : std::string("from the flags (the server told none)"));
  if (r.oracle_on) {
    const auto& q = r.oracle;
    row("oracle: frames checked / unchecked", num(q.frames_checked) + " / " + num(q.frames_unchecked));
    if (q.sample > 1) {
      row("oracle: sample", "1 in " + num(q.sample) + " bots: up to " + num(q.sampled_max) + " of " +
                                num(q.observers_max) + " checked on every frame; " + num(q.frames_unsampled) +
                                " frames of the others (not checked)");
    }
    row("oracle: entities checked", num(q.entities_checked) + " (positions " + num(q.positions_checked) + ", unchecked " +
                                        num(q.positions_unchecked) + ")");
    row("oracle: missing / extra / leaked", num(q.missing) + " / " + num(q.extra) + " / " + num(q.leaked));
    row("oracle: wrong class / position / stale", num(q.wrong_class) + " / " + num(q.position) + " / " + num(q.stale));
    row("oracle: wrong deferral counts", num(q.deferral));
    const double ticks = static_cast<double>(std::max<std::uint64_t>(1, q.truth_ticks));
    row("oracle: truth ticks, KB per tick",
        num(q.truth_ticks) + ", " + fmt(static_cast<double>(q.truth_bytes) / 1024.0 / ticks, "KB") + " (" +
            num(q.truth_layouts) + " with the whole layout, " + num(q.truth_changes) + " with changes to it)");
    row("oracle: recompute CPU per tick", fmt(q.compute_cpu_ms / ticks, "ms") + " (up to " + num(q.sampled_max) +
                                              " observers; slowest tick with its checks " + ms(q.compute_max_ms) + ")");
    row("oracle: its threads' checks, CPU per tick", fmt(q.drain_cpu_ms / ticks, "ms"));
    row("oracle: its thread's wall per tick",
        "decode " + fmt(q.decode_ms / ticks, "ms") + ", layout and index " + fmt(q.index_ms / ticks, "ms") + ", scan " +
            fmt(q.scan_ms / ticks, "ms") + ", publish " + fmt(q.publish_ms / ticks, "ms") + ", waiting checks " +
            fmt(q.drain_ms / ticks, "ms"));
    row("oracle: comparisons per tick", fmt(q.check_ms / ticks, "ms") + " (" + num(q.deferred_checks) +
                                             " frames checked after they waited for their truth, " +
                                             num(q.pending_overflow) + " not: too many waiting)");
    if (q.truth_restarts > 0) {
      row("oracle: zone servers restarted, followed", num(q.truth_restarts) + " (" +
                                                          num(q.frames_checked_after_restart) +
                                                          " frames checked against the new servers' truth)");
    }
    if (!q.stream_error.empty()) row("oracle: TRUTH STREAM FAILED", q.stream_error);
  }
  row("MISMATCHES", num(r.mismatches()));
  row("bot-swarm CPU time (user + system)", fmt(r.cpu_s, "s"));
  if (!r.problems.empty()) {
    std::printf("problems (%llu; first %zu):\n", static_cast<unsigned long long>(r.problems_total), std::min<std::size_t>(r.problems.size(), 20));
    for (std::size_t i = 0; i < r.problems.size() && i < 20; ++i) std::printf("  %s\n", r.problems[i].c_str());
  }
}

bool write_json(const std::string& path, const swarm_result& r, const summary& s) {
  using json = nlohmann::ordered_json;  // keys in the order written, for a reader of the file
  json j;
  j["bots"] = r.options.bots;
  j["duration_s"] = r.elapsed_s;
  j["input_hz"] = r.options.input_hz;
  j["churn_per_s"] = r.options.churn;
  j["verify"] = r.options.verify;
  j["bots_connected"] = r.bots_connected;
  j["connect_attempts"] = r.connect_attempts;
  j["connect_failures"] = r.connect_failures;
  j["unexpected_disconnects"] = r.unexpected_disconnects;
  j["server_errors"] = r.server_errors;
  j["logouts"] = r.logouts;
  j["cuts"] = r.cuts;
  j["threads"] = r.options.threads;
  j["teleports_sent"] = r.teleports_sent;
  j["redirects"] = r.redirects;
  j["gate_redirects"] = r.gate_redirects;
  j["reconnects"] = r.reconnects;
  j["resumes"] = r.resumes;
  j["resumes_refused"] = r.resumes_refused;
  j["stealth_joins"] = r.stealth_joins;
  j["team_joins"] = r.team_joins;
  j["visibility_switches_sent"] = r.visibility_switches_sent;
  j["class_notes"] = r.class_notes;
  j["class_changes"] = r.options.class_changes;
  j["self_positions"] = r.self_positions;
  j["host_clock"] = r.host_clock;
  j["latency_ms"] = {{"p50", s.p50},         {"p95", s.p95},
                     {"p99", s.p99},         {"max", s.max},
                     {"samples", s.samples}, {"unsynced", r.latency_unsynced},
                     {"min_rtt", r.min_rtt_ms}};
  const auto login_json = [](const latency_histogram_us::counts& c, double max_ms) {
    return nlohmann::json{{"p50", percentile_ms(c, 0.5)},
                          {"p99", percentile_ms(c, 0.99)},
                          {"max", max_ms},
                          {"samples", latency_histogram_us::total(c)}};
  };
  j["login_connect_ms"] = login_json(r.connect_time, r.connect_max_ms);
  j["login_welcome_ms"] = login_json(r.welcome_time, r.welcome_max_ms);
  j["latency_steady_ms"] = {{"from_s", r.steady_from_s}, {"p50", s.steady_p50},          {"p95", s.steady_p95},
                            {"p99", s.steady_p99},       {"samples", s.steady_samples}};
  j["per_bot"] = {{"kbps_median", s.kbps_median}, {"kbps_p95", s.kbps_p95}, {"msgs_per_s_median", s.msgs_median}};
  j["downstream_kbps_total"] = s.total_kbps;
  j["frames"] = r.frames_in;
  j["bytes"] = r.bytes_in;
  j["tick_updates"] = r.tick_updates;
  j["enters"] = r.enters;
  j["leaves"] = r.leaves;
  j["updates"] = r.updates;
  j["resets"] = r.resets;
  j["inputs_sent"] = r.inputs_sent;
  j["inputs_unchanged"] = r.inputs_unchanged;
  j["inputs_mode"] = r.options.inputs_on_change ? "changes" : "every";
  j["digests_checked"] = r.digests_checked;
  j["digest_mismatches"] = r.digest_mismatches;
  j["inconsistent"] = r.inconsistent;
  j["aoi_checked"] = r.aoi_checked;
  j["aoi_unchecked"] = r.aoi_unchecked;
  j["aoi_violations"] = r.aoi_violations;
  j["rules_from_server"] = r.rules_from_server;
  if (r.oracle_on) {
    const auto& q = r.oracle;
    j["oracle"] = {{"frames_checked", q.frames_checked},
                   {"frames_unchecked", q.frames_unchecked},
                   {"frames_unsampled", q.frames_unsampled},
                   {"sample", q.sample},
                   {"sampled_max", q.sampled_max},
                   {"entities_checked", q.entities_checked},
                   {"positions_checked", q.positions_checked},
                   {"positions_unchecked", q.positions_unchecked},
                   {"missing", q.missing},
                   {"extra", q.extra},
                   {"leaked", q.leaked},
                   {"wrong_class", q.wrong_class},
                   {"position", q.position},
                   {"stale", q.stale},
                   {"deferral", q.deferral},
                   {"oracle_mismatches", q.mismatches()},
                   {"truth_restarts", q.truth_restarts},
                   {"frames_checked_after_restart", q.frames_checked_after_restart},
                   {"truth_ticks", q.truth_ticks},
                   {"truth_bytes", q.truth_bytes},
                   {"truth_layouts", q.truth_layouts},
                   {"truth_changes", q.truth_changes},
                   {"compute_cpu_ms", q.compute_cpu_ms},
                   {"drain_cpu_ms", q.drain_cpu_ms},
                   {"compute_max_ms", q.compute_max_ms},
                   {"check_ms", q.check_ms},
                   {"deferred_checks", q.deferred_checks},
                   {"pending_overflow", q.pending_overflow},
                   {"observers_max", q.observers_max},
                   {"wall_ms",
                    {{"decode", q.decode_ms},
                     {"layout_and_index", q.index_ms},
                     {"scan", q.scan_ms},
                     {"publish", q.publish_ms},
                     {"waiting_checks", q.drain_ms}}},
                   {"stream_error", q.stream_error}};
  }
  j["mismatches"] = r.mismatches();
  j["swarm_cpu_s"] = r.cpu_s;
  j["problems_total"] = r.problems_total;
  j["problems"] = r.problems;
  json series = json::array();
  for (const auto& x : r.series) {
    series.push_back({{"t", x.t},
                      {"connected", x.connected},
                      {"frames", x.frames},
                      {"bytes", x.bytes},
                      {"p50_ms", x.p50_ms},
                      {"p99_ms", x.p99_ms},
                      {"mismatches", x.mismatches}});
  }
  j["series"] = std::move(series);
  std::ofstream o(path);
  if (!o) return false;
  // Problems quote client text: invalid UTF-8 is replaced rather than thrown on.
  o << j.dump(2, ' ', false, json::error_handler_t::replace) << '\n';
  return static_cast<bool>(o);
}

bool write_csv(const std::string& path, const swarm_result& r) {
  std::ofstream o(path);
  if (!o) return false;
  o << "t_s,connected,frames_per_s,kbytes_per_s,enters,leaves,updates,latency_p50_ms,latency_p99_ms,latency_max_ms,mismatches\n";
  for (const auto& x : r.series) {
    o << x.t << ',' << x.connected << ',' << x.frames << ',' << static_cast<double>(x.bytes) / 1024.0 << ',' << x.enters << ','
      << x.leaves << ',' << x.updates << ',' << x.p50_ms << ',' << x.p99_ms << ',' << x.max_window_ms << ',' << x.mismatches
      << '\n';
  }
  return static_cast<bool>(o);
}

/// A PNG of latency p50/p99 per second through gnuplot, when it is installed; false otherwise.
bool write_plot(const std::string& png, const swarm_result& r) {
  if (std::system("command -v gnuplot >/dev/null 2>&1") != 0) return false;
  const std::string data = png + ".dat";
  {
    std::ofstream d(data);
    for (const auto& x : r.series) d << x.t << ' ' << x.p50_ms << ' ' << x.p99_ms << ' ' << x.connected << '\n';
  }
  FILE* g = popen("gnuplot", "w");
  if (!g) return false;
  std::fprintf(g,
               "set terminal png size 900,500\nset output '%s'\nset title 'bot-swarm: update latency (%u bots)'\n"
               "set xlabel 'time (s)'\nset ylabel 'latency (ms)'\nset y2label 'bots connected'\nset y2tics\nset ytics nomirror\n"
               "set grid\nplot '%s' using 1:2 with lines title 'p50', '' using 1:3 with lines title 'p99', "
               "'' using 1:4 axes x1y2 with lines title 'bots'\n",
               png.c_str(), r.options.bots, data.c_str());
  const int rc = pclose(g);
  std::remove(data.c_str());
  return rc == 0;
}

/// A scenario file (JSON) as command-line arguments: each top-level key is an option name with its
/// value ("bots": 1000, "verify": true), and "mix" may be an object of shares ({"walk": 0.6,
/// "crowd": 0.4}). An error text on failure.
std::string scenario_args(const std::string& path, std::vector<std::string>& args) {
  using json = nlohmann::ordered_json;  // the file's order: the command line's order
  std::ifstream in(path);
  if (!in) return "scenario " + path + ": cannot open the file";
  json tree;
  try {
    tree = json::parse(in);
  } catch (const json::exception& e) {
    return "scenario " + path + ": " + e.what();
  }
  if (!tree.is_object()) return "scenario " + path + ": the file must hold one JSON object";
  const auto text = [](const json& v) { return v.is_string() ? v.get<std::string>() : v.dump(); };
  args.push_back("bot-swarm");
  for (const auto& [key, value] : tree.items()) {
    if (key == "scenario") return "scenario " + path + ": a scenario cannot name another";
    if (value.is_object()) {  // only "mix" has one
      if (key != "mix") return "scenario " + path + ": '" + key + "' must be a plain value";
      std::string mix;
      for (const auto& [name, share] : value.items()) {
        if (!share.is_number()) return "scenario " + path + ": mix share '" + name + "' must be a number";
        mix += (mix.empty() ? "" : ",") + name + "=" + text(share);
      }
      args.push_back("--mix=" + mix);
    } else if (value.is_array() || value.is_null()) {
      return "scenario " + path + ": '" + key + "' must be a plain value";
    } else if (value.is_boolean()) {
      if (value.get<bool>()) args.push_back("--" + key);
    } else {
      args.push_back("--" + key + "=" + text(value));
    }
  }
  return {};
}

}  // namespace

int main(int argc, char** argv) {
  swarm_options o;
  std::string mix = "walk=1", json, csv, plot, hotspot, inputs_mode = "changes";
  unsigned port = o.port;
  std::string oracle_zones, oracle_zones_later;
  po::options_description desc("bot-swarm options");
  desc.add_options()                                                                                                 //
      ("help,h", "print this help and exit")                                                                         //
      ("host", po::value(&o.host)->default_value(o.host), "zone server host")                                        //
      ("port", po::value(&port)->default_value(port), "zone server port")                                            //
      ("bots", po::value(&o.bots)->default_value(o.bots), "number of bots")                                          //
      ("duration", po::value(&o.duration_s)->default_value(o.duration_s), "run time in seconds (ramp-up included)")  //
      ("ramp", po::value(&o.ramp)->default_value(o.ramp), "new bots per second during ramp-up")                      //
      ("max-connecting", po::value(&o.max_connecting)->default_value(o.max_connecting),
       "at most this many bots connecting at once (from connect until the welcome; the ramp waits for welcomes "
       "so a lagging swarm or server never holds more connections without a hello read than the server's --max-pending caps; 0 = no limit)")  //
      ("input-hz", po::value(&o.input_hz)->default_value(o.input_hz),
       "intent evaluations per second per bot (an input each with --inputs every)")  //
      ("inputs", po::value(&inputs_mode)->default_value(inputs_mode),
       "changes: send an input when the intent changes (and as a keep-alive); every: at every evaluation")  //
      ("input-keepalive", po::value(&o.input_keepalive_s)->default_value(o.input_keepalive_s),
       "--inputs changes: resend an unchanged intent after this many seconds")                  //
      ("ping-hz", po::value(&o.ping_hz)->default_value(o.ping_hz), "pings per second per bot")  //
      ("mix", po::value(&mix)->default_value(mix),
       "behaviour shares, e.g. walk=0.5,patrol=0.2,follow=0.1,crowd=0.1,teleport=0.1")  //
      ("teleport-hz", po::value(&o.teleport_hz)->default_value(o.teleport_hz, "0.2"),
       "teleport bots: jumps per second per bot (random times and targets)")  //
      ("stealth-bots", po::value(&o.stealth_share)->default_value(o.stealth_share, "0.1"),
       "share of bots that join stealthed (the server must allow stealth: zone-server --allow-stealth)")  //
      ("team-bots", po::value(&o.team_share)->default_value(o.team_share, "0.2"),
       "share of bots that join a team, red or blue (the server must allow 2 teams: --player-teams)")  //
      ("visibility-switch-hz", po::value(&o.visibility_switch_hz)->default_value(o.visibility_switch_hz, "0.2"),
       "stealth and team bots: visibility switches per second per bot (set_visibility; 0 = never)")  //
      ("class-changes", po::value(&o.class_changes)->default_value(o.class_changes, "1"),
       "1: bots say hello{class_changes} and apply class notes; 0: as an older client, whose view the server resets when an entity it holds changes class")  //
      ("hotspot", po::value(&hotspot), "flash-crowd target x,y,z (default: where the leader bot first is)")  //
      ("crowd-at", po::value(&o.crowd_at_s)->default_value(o.crowd_at_s),
       "seconds into the run when the crowd bots start converging")                                          //
      ("churn", po::value(&o.churn)->default_value(o.churn), "logouts per second (each bot logs in again)")  //
      ("relogin-delay", po::value(&o.relogin_delay_s)->default_value(o.relogin_delay_s, "0.2"),
       "seconds before a churned bot logs in again")  //
      ("churn-for", po::value(&o.churn_for_s)->default_value(o.churn_for_s),
       "seconds into the run when churn and --cut stop (0 = until the end)")  //
      ("cut", po::value(&o.cut)->default_value(o.cut),
       "connections dropped per second as a network would drop them: a random playing bot closes its socket without a leave and logs in again after --relogin-delay, with its resume token when --resume and the zone told one (zone-server --linger), else as a new player")  //
      ("reconnect", po::bool_switch(&o.reconnect),
       "after an unexpected disconnect, log in again at the same address (retrying for --connect-timeout)")  //
      ("relogin-port", po::value(&o.relogin_port)->default_value(o.relogin_port),
       "with --reconnect: log in again at this port on --host instead (a world's gate, docs/world.md: it sends each login to a zone that serves now); 0 = the zone the bot was in")  //
      ("resume", po::value(&o.resume)->default_value(o.resume),
       "with --reconnect: say the resume token of the bot's last welcome (a world's zone) when logging in again, to get its entity back after its zone was lost (0 or 1); a token refused: a new login")  //
      ("verify", po::bool_switch(&o.verify),
       "compare the server's visible-set digests with each bot's tracked view")  //
      ("oracle", po::bool_switch(&o.oracle),
       "check every bot's view against the server's ground truth (the server runs with --oracle): missing, extra, leaked, wrong class, wrong or stale position")  //
      ("oracle-threads", po::value(&o.oracle_threads)->default_value(o.oracle_threads),
       "threads recomputing the visible sets for the oracle (0 = one per 8 hardware threads)")  //
      ("oracle-sample", po::value(&o.oracle_sample)->default_value(o.oracle_sample),
       "the oracle's scale knob: 1 in K bots (a fixed subset, by a hash of the entity id) is recomputed and checked on every frame, the others' frames are counted as unsampled (1 = every bot)")  //
      ("oracle-zones", po::value(&oracle_zones),
       "a world of zones (docs/world.md): the other zones' client ports on --host, comma-separated; with --oracle each zone's truth is read and a bot is checked against the zone it is in now (following redirects)")  //
      ("oracle-zones-later", po::value(&oracle_zones_later),
       "with --oracle: zones that may start after the swarm (a world's standby), ports on --host, comma-separated: each one's truth is read once it answers, and a bot a gate sends there waits for that (at most 10 s)")  //
      ("threads", po::value(&o.threads)->default_value(o.threads),
       "I/O threads (0 = one per 2,500 bots, 2 .. half the cores)")  //
      ("aoi", po::value(&o.aoi)->default_value(o.aoi),
       "for servers whose welcome tells no rules: the players' AOI half-extent (its --player-aoi), for the AOI check")  //
      ("hysteresis", po::value(&o.hysteresis)->default_value(o.hysteresis),
       "for servers whose welcome tells no rules: the server's --hysteresis (m)")  //
      ("max-speed", po::value(&o.max_speed)->default_value(o.max_speed),
       "for servers whose welcome tells no rules: the fastest entity speed on the server (m/s)")  //
      ("connect-timeout", po::value(&o.connect_timeout_s)->default_value(o.connect_timeout_s),
       "seconds to connect and get a welcome")                                            //
      ("report-json", po::value(&json), "write the report as JSON to this file")          //
      ("report-csv", po::value(&csv), "write the per-second series as CSV to this file")  //
      ("plot", po::value(&plot), "write a PNG latency plot (needs gnuplot)")              //
      ("scenario", po::value<std::string>(),
       "JSON file of options (keys as above, \"mix\" may be an object); the command line wins")  //
      ("quiet", "no progress line");
  po::variables_map vm;
  try {
    po::store(po::parse_command_line(argc, argv, desc), vm);
    if (vm.count("scenario")) {
      std::vector<std::string> args;
      if (const auto err = scenario_args(vm["scenario"].as<std::string>(), args); !err.empty()) {
        std::fprintf(stderr, "bot-swarm: %s\n", err.c_str());
        return 64;
      }
      std::vector<const char*> argp;
      for (const auto& a : args) argp.push_back(a.c_str());
      po::store(po::parse_command_line(static_cast<int>(argp.size()), argp.data(), desc), vm);  // the command line, stored first, wins
    }
    po::notify(vm);
  } catch (const po::error& e) {
    std::fprintf(stderr, "bot-swarm: %s (try --help)\n", e.what());
    return 64;
  }
  if (vm.count("help")) {
    std::cout << "Usage: bot-swarm [options]\n"
              << desc
              << "\nExit status: 0 all bots connected and no mismatch; 1 mismatches; 2 connection failures, "
                 "unexpected disconnects or bots that never connected; 64 bad options.\n";
    return 0;
  }
  if (port == 0 || port > 65535) {
    std::fprintf(stderr, "bot-swarm: --port must be in 1..65535\n");
    return 64;
  }
  o.port = static_cast<std::uint16_t>(port);
  if (o.oracle_sample == 0) {
    std::fprintf(stderr, "bot-swarm: --oracle-sample must be at least 1\n");
    return 64;
  }
  // A comma-separated list of ports into `out`; false (said) when an item is not a port.
  const auto ports = [](const std::string& text, const char* flag, std::vector<std::uint16_t>& out) {
    std::stringstream list(text);
    for (std::string item; std::getline(list, item, ',');) {
      char* end = nullptr;
      const unsigned long p = std::strtoul(item.c_str(), &end, 10);
      if (item.empty() || end != item.c_str() + item.size() || p == 0 || p > 65535) {
        std::fprintf(stderr, "bot-swarm: %s must be ports 1..65535, comma-separated (got '%s')\n", flag, item.c_str());
        return false;
      }
      out.push_back(static_cast<std::uint16_t>(p));
    }
    return true;
  };
  if (!oracle_zones.empty() && !ports(oracle_zones, "--oracle-zones", o.oracle_zones)) return 64;
  if (!oracle_zones_later.empty() && !ports(oracle_zones_later, "--oracle-zones-later", o.oracle_zones_later)) return 64;
  if ((!o.oracle_zones.empty() || !o.oracle_zones_later.empty()) && !o.oracle) {
    std::fprintf(stderr, "bot-swarm: --oracle-zones and --oracle-zones-later need --oracle\n");
    return 64;
  }
  if (o.relogin_port != 0 && !o.reconnect) {
    std::fprintf(stderr, "bot-swarm: --relogin-port needs --reconnect\n");
    return 64;
  }
  if (const auto err = parse_mix(mix, o.mix); !err.empty()) {
    std::fprintf(stderr, "bot-swarm: %s\n", err.c_str());
    return 64;
  }
  if (!hotspot.empty()) {
    float x = 0, y = 0, z = 0;
    if (std::sscanf(hotspot.c_str(), "%f,%f,%f", &x, &y, &z) < 2) {
      std::fprintf(stderr, "bot-swarm: --hotspot wants x,y[,z]\n");
      return 64;
    }
    o.hotspot = {x, y, z};
    o.hotspot_set = true;
  }
  if (inputs_mode != "changes" && inputs_mode != "every") {
    std::fprintf(stderr, "bot-swarm: --inputs must be 'changes' or 'every', not '%s'\n", inputs_mode.c_str());
    return 64;
  }
  o.inputs_on_change = inputs_mode == "changes";
  if (o.bots == 0 || !(o.duration_s > 0) || !(o.ramp > 0) || !(o.input_hz > 0)) {
    std::fprintf(stderr, "bot-swarm: --bots, --duration, --ramp and --input-hz must be > 0\n");
    return 64;
  }
  if (!(o.stealth_share >= 0 && o.stealth_share <= 1) || !(o.team_share >= 0 && o.team_share <= 1) ||
      !(o.visibility_switch_hz >= 0 && std::isfinite(o.visibility_switch_hz))) {
    std::fprintf(stderr, "bot-swarm: --stealth-bots and --team-bots must be in [0, 1], --visibility-switch-hz >= 0\n");
    return 64;
  }
  if (!(o.teleport_hz >= 0) || !(o.churn_for_s >= 0) || !(o.churn >= 0 && std::isfinite(o.churn)) ||
      !(o.cut >= 0 && std::isfinite(o.cut))) {
    std::fprintf(stderr, "bot-swarm: --teleport-hz, --churn, --cut and --churn-for must be >= 0\n");
    return 64;
  }
  // Every bot is a socket: raise the open-file limit to the hard limit, and refuse a swarm that
  // cannot fit rather than counting thousands of "Too many open files" connection failures.
  const auto files = zone::net::raise_open_file_limit();
  if (!files.error.empty()) std::fprintf(stderr, "bot-swarm: %s\n", files.error.c_str());
  if (files.soft != 0 && o.bots + zone::net::reserved_file_descriptors > files.soft) {
    std::fprintf(stderr,
                 "bot-swarm: %u bots need about %llu file descriptors, but the open-file limit is %llu (hard limit %llu): "
                 "raise the hard limit (ulimit -Hn as root, or LimitNOFILE=) or run fewer bots per process\n",
                 o.bots, static_cast<unsigned long long>(o.bots + zone::net::reserved_file_descriptors),
                 static_cast<unsigned long long>(files.soft), static_cast<unsigned long long>(files.hard));
    return 64;
  }
  if (!vm.count("quiet")) {
    std::fprintf(stderr, "bot-swarm: open-file limit %llu (was %llu, hard %llu)\n", static_cast<unsigned long long>(files.soft),
                 static_cast<unsigned long long>(files.before), static_cast<unsigned long long>(files.hard));
  }

  const auto outcome = zone::bots::run_swarm(o, vm.count("quiet") ? nullptr : print_progress);
  if (!outcome.error.empty()) {
    std::fprintf(stderr, "bot-swarm: %s\n", outcome.error.c_str());
    return 2;
  }
  const auto& r = outcome.result;
  const auto s = summarize(r);
  print_table(r, s);
  if (!json.empty() && !write_json(json, r, s)) std::fprintf(stderr, "bot-swarm: cannot write %s\n", json.c_str());
  if (!csv.empty() && !write_csv(csv, r)) std::fprintf(stderr, "bot-swarm: cannot write %s\n", csv.c_str());
  if (!plot.empty() && !write_plot(plot, r)) std::fprintf(stderr, "bot-swarm: no plot (gnuplot missing or failed)\n");
  std::fflush(stdout);
  if (r.mismatches() > 0) return 1;
  if (r.bots_connected < r.options.bots || r.connect_failures > 0 || r.unexpected_disconnects > 0) return 2;
  return 0;
}
