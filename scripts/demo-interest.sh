#!/usr/bin/env bash
# The interest core on its own: installs what is missing, builds, generates the PBIG paper's
# uniform data set and an MMO-like zone, finds their pairs with every available finder through the
# `interest-pairs` tool (brute force, the fast CPU finder, the GPU finder when a device is present),
# and prints a table of pair counts, times and whether the outputs are identical.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
scripts/build.sh

bin=build/tools/interest-pairs
work=build/demo
mkdir -p "$work"
boxes=${DEMO_BOXES:-100000}

backends=(brute cpu)
if "$bin" --backend gpu --count-only /dev/null >/dev/null 2>&1; then
  backends+=(gpu)
else
  echo "demo: no usable GPU finder here; running the CPU finders only"
fi

failed=0
printf '\n%-10s %-8s %10s %12s %10s  %s\n' set backend boxes pairs seconds "output"
for set in uniform mmo; do
  input="$work/$set.boxes"
  "$bin" gen --set "$set" --count "$boxes" --seed 1 --format binary --output "$input"
  reference=""
  for backend in "${backends[@]}"; do
    output="$work/$set-$backend.pairs"
    start=$(date +%s.%N)
    "$bin" --backend "$backend" --output "$output" "$input"
    end=$(date +%s.%N)
    pairs=$(wc -l <"$output")
    digest=$(sha256sum "$output" | cut -c1-12)
    if [ -z "$reference" ]; then
      reference=$digest
      verdict="sha256 $digest (reference)"
    elif [ "$digest" = "$reference" ]; then
      verdict="sha256 $digest identical"
    else
      verdict="sha256 $digest DIFFERS from brute force"
      failed=1
    fi
    printf '%-10s %-8s %10s %12s %10.3f  %s\n' "$set" "$backend" "$boxes" "$pairs" "$(awk -v a="$start" -v b="$end" 'BEGIN { print b - a }')" "$verdict"
  done
done
echo
if [ "$failed" -ne 0 ]; then
  echo "demo: the finders disagree: this is a bug, please report it" >&2
  exit 1
fi
echo "demo: pair files are in $work/ (one 'i j' line per pair, sorted). See docs/ for the benchmarks."
