#!/usr/bin/env bash
# Builds the libFuzzer targets (fuzz/: clang, ASan + UBSan) and runs each for SECONDS (default 3)
# on its seed corpus in fuzz/corpus/<target> (read only: new inputs go to a scratch folder).
# Exit 0 when every target ran without a finding; 77 (CTest's "skipped") when clang or its
# fuzzer runtime is missing. Usage: scripts/fuzz.sh [SECONDS] [TARGET...]
set -euo pipefail
cd "$(dirname "$0")/.."
seconds=${1:-3}
shift || true
targets=("$@")
[[ ${#targets[@]} -gt 0 ]] || targets=(fuzz_frame fuzz_session fuzz_box_csv fuzz_box_binary fuzz_truth)
build=${ZONE_FUZZ_BUILD_DIR:-build-fuzz}

cxx=$(command -v clang++ || true)
if [[ -z $cxx ]]; then
  echo "fuzz: clang++ not found: skipped (apt-get install clang)"
  exit 77
fi
probe=$(mktemp -d)
trap 'rm -rf "$probe"' EXIT
echo 'extern "C" int LLVMFuzzerTestOneInput(const unsigned char*, unsigned long) { return 0; }' > "$probe/p.cpp"
if ! "$cxx" -fsanitize=fuzzer,address,undefined "$probe/p.cpp" -o "$probe/p" 2> "$probe/err"; then
  echo "fuzz: clang++ cannot link libFuzzer with ASan/UBSan: skipped"; cat "$probe/err"
  exit 77
fi

launcher=()
command -v ccache > /dev/null && launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache)
cmake -S fuzz -B "$build" -DCMAKE_CXX_COMPILER="$cxx" -DCMAKE_BUILD_TYPE=RelWithDebInfo "${launcher[@]}" > "$probe/configure.log" ||
  { cat "$probe/configure.log"; exit 1; }
cmake --build "$build" -j "${ZONE_FUZZ_JOBS:-2}" --target "${targets[@]}"

status=0
for t in "${targets[@]}"; do
  scratch=$(mktemp -d)
  log="$build/$t.log"
  # The first directory collects new inputs; the corpus in the tree is only read.
  if ASAN_OPTIONS=detect_leaks=1:allocator_may_return_null=1 UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1 \
      "$build/$t" -max_total_time="$seconds" -timeout=10 -rss_limit_mb=2048 -max_len=16384 \
      -artifact_prefix="$build/$t-" "$scratch" "fuzz/corpus/${t#fuzz_}" > "$log" 2>&1; then
    echo "fuzz: $t: $(grep -Eo 'Done [0-9]+ runs in [0-9]+ second\(s\)' "$log" | tail -1), no finding"
  else
    echo "fuzz: $t FAILED (log $log; the input that failed is $build/$t-*)"
    tail -40 "$log"
    status=1
  fi
  rm -rf "$scratch"
done
exit $status
