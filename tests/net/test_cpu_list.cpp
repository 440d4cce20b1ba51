// net/os_limits.h's CPU lists (zone-server --worker-cpus / --io-cpus): what taskset accepts parses
// to the CPUs it names, anything else is refused with a reason; formatting is the inverse; pinning
// the calling thread takes effect and refuses CPUs the process may not use.
#include <doctest/doctest.h>

#include <sched.h>

#include <random>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "../common/seeds.h"
#include "net/os_limits.h"

using namespace zone::net;

TEST_SUITE("net.cpu_list") {
  TEST_CASE("lists taskset accepts: single CPUs, ranges, unordered and repeated") {
    CHECK(parse_cpu_list("")->empty());
    CHECK(*parse_cpu_list("0") == std::vector<int>{0});
    CHECK(*parse_cpu_list("0-5") == std::vector<int>{0, 1, 2, 3, 4, 5});
    CHECK(*parse_cpu_list("8,0-2,10-11") == std::vector<int>{0, 1, 2, 8, 10, 11});
    CHECK(*parse_cpu_list("3,3,2-4") == std::vector<int>{2, 3, 4});
    CHECK(*parse_cpu_list("7-7") == std::vector<int>{7});
    CHECK(*parse_cpu_list("1023") == std::vector<int>{CPU_SETSIZE - 1});
  }

  TEST_CASE("anything else refused, with the reason") {
    for (const char* bad : {",", "0,", ",0", "a", "0-", "-1", "1-a", "0 - 3", " 1", "1.5", "0x2", "1--2", "0--0", "+1",
                            "1-+2", "2-1", "1024", "0-4096", "99999999999999999999"}) {
      CAPTURE(bad);
      std::string why;
      CHECK_FALSE(parse_cpu_list(bad, &why).has_value());
      CHECK(why.find(bad) != std::string::npos);  // the list quoted back
    }
    std::string why;
    (void)parse_cpu_list("1--2", &why);
    CHECK(why.find("not a CPU number") != std::string::npos);
    (void)parse_cpu_list("5-2", &why);
    CHECK(why.find("backwards") != std::string::npos);
    (void)parse_cpu_list("0,2000", &why);
    CHECK(why.find("past the largest") != std::string::npos);
  }

  TEST_CASE("format is parse's inverse on random sets") {
    const std::uint64_t seed = zone::test::fresh_seed();
    CAPTURE(seed);
    std::mt19937_64 rng(seed);
    for (int round = 0; round < 500; ++round) {
      std::set<int> want;
      const int n = static_cast<int>(rng() % 40);
      for (int i = 0; i < n; ++i) want.insert(static_cast<int>(rng() % (round % 2 ? 64 : CPU_SETSIZE)));
      const std::vector<int> cpus(want.begin(), want.end());
      const std::string text = format_cpu_list(cpus);
      CAPTURE(text);
      const auto back = parse_cpu_list(text);
      REQUIRE(back.has_value());
      CHECK(*back == cpus);
    }
    CHECK(format_cpu_list({0, 1, 2, 5, 7, 8}) == "0-2,5,7-8");
    CHECK(format_cpu_list({}).empty());
  }

  TEST_CASE("pinning a thread: it runs only on the CPUs named; CPUs the process may not use refused") {
    const std::vector<int> allowed = allowed_cpus();
    REQUIRE_FALSE(allowed.empty());
    CHECK_FALSE(check_cpus_allowed(allowed).has_value());
    CHECK_FALSE(check_cpus_allowed({}).has_value());
    // An embedder's list in any order, with repeats: judged as the set it names.
    std::vector<int> shuffled(allowed.rbegin(), allowed.rend());
    shuffled.push_back(allowed.front());
    CHECK_FALSE(check_cpus_allowed(shuffled).has_value());
    const auto neg = check_cpus_allowed({allowed.front(), -1});
    REQUIRE(neg.has_value());
    CHECK(neg->find("-1") != std::string::npos);
    CHECK(pin_current_thread({-1}).has_value());  // refused, nothing pinned
    CHECK(pin_current_thread({CPU_SETSIZE}).has_value());
    const auto err = check_cpus_allowed({CPU_SETSIZE - 1});
    if (allowed.back() != CPU_SETSIZE - 1) {
      REQUIRE(err.has_value());
      CHECK(err->find(std::to_string(CPU_SETSIZE - 1)) != std::string::npos);
      CHECK(err->find(format_cpu_list(allowed)) != std::string::npos);
    }
    std::thread t([&] {
      const std::vector<int> one{allowed.back()};
      CHECK_FALSE(pin_current_thread(one).has_value());
      cpu_set_t set;
      CPU_ZERO(&set);
      REQUIRE(sched_getaffinity(0, sizeof set, &set) == 0);
      CHECK(CPU_COUNT(&set) == 1);
      CHECK(CPU_ISSET(allowed.back(), &set));
      for (int i = 0; i < 1000; ++i) CHECK(sched_getcpu() == allowed.back());
      CHECK_FALSE(pin_current_thread({}).has_value());  // empty: nothing changes
      CHECK(sched_getcpu() == allowed.back());
    });
    t.join();
    CHECK(allowed_cpus() == allowed);  // the process's other threads untouched
  }
}
