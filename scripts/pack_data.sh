#!/usr/bin/env bash
# Packs docs/data.tar.xz, the raw outputs docs/ cites (docs/zone-benchmarks.md, "Method"), from a
# folder: the archive unpacked, with the new runs' folders added and what nothing cites removed.
#   mkdir /tmp/data && tar -xJf docs/data.tar.xz -C /tmp/data && cp -r RUN_FOLDER /tmp/data/zone/
#   bash scripts/pack_data.sh /tmp/data
# The files go in by extension, then name (each run's tick CSVs beside the others' compress best),
# after the folders; xz at its strongest for text. Refuses an archive of 1 MB or more (the file is
# kept in git: prune before adding).
set -euo pipefail
src=${1:?usage: scripts/pack_data.sh FOLDER [ARCHIVE (default docs/data.tar.xz)]}
out=${2:-$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)/docs/data.tar.xz}
[ -d "$src" ] || { echo "pack_data.sh: $src is not a folder" >&2; exit 2; }
list=$(mktemp) tmp=$(mktemp)
trap 'rm -f "$list" "$tmp"' EXIT
(
  cd "$src"
  find . -mindepth 1 -type d | LC_ALL=C sort
  find . -type f | awk '{ n = split($0, part, "/"); base = part[n]
                          ext = match(base, /\.[^.]*$/) ? substr(base, RSTART) : ""
                          print ext "\t" base "\t" $0 }' | LC_ALL=C sort | cut -f3
) > "$list"
tar --no-recursion --owner=0 --group=0 --numeric-owner --mtime=2026-11-29T00:00Z -cf - -C "$src" -T "$list" |
  xz --lzma2=preset=9e,lc=4,pb=0,nice=273 > "$tmp"
size=$(wc -c < "$tmp")
if [ "$size" -ge 1000000 ]; then
  echo "pack_data.sh: $size bytes, over 1 MB: prune a folder nothing cites first ($out unchanged)" >&2
  exit 1
fi
cp "$tmp" "$out"
echo "$out: $size bytes, $(grep -c . "$list") entries"
