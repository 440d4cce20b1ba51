#!/usr/bin/env bash
# scripts/pack_data.sh: docs/data.tar.xz unpacked and packed again holds the same files (and stays
# under 1 MB), and 1.1 MB that xz cannot shrink is refused with the archive left as it was.
set -euo pipefail
root=${1:?usage: pack_data_test.sh REPO_ROOT}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir "$work/a" "$work/b" "$work/big"
tar -xJf "$root/docs/data.tar.xz" -C "$work/a"
bash "$root/scripts/pack_data.sh" "$work/a" "$work/again.tar.xz"
tar -xJf "$work/again.tar.xz" -C "$work/b"
diff -r "$work/a" "$work/b"
echo "round trip: the same $(find "$work/b" -type f | wc -l) files"
head -c 1100000 /dev/urandom > "$work/big/noise.bin"
echo kept > "$work/kept.tar.xz"
if bash "$root/scripts/pack_data.sh" "$work/big" "$work/kept.tar.xz"; then
  echo "an archive over 1 MB was not refused" >&2
  exit 1
fi
[ "$(cat "$work/kept.tar.xz")" = kept ] || { echo "the refused archive was overwritten" >&2; exit 1; }
echo "over 1 MB: refused, archive unchanged"
