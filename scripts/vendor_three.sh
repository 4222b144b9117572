#!/usr/bin/env bash
# Refresh the vendored three.js under service/api/static/vendor/three/ from the npm registry.
#
#   scripts/vendor_three.sh VERSION        e.g. scripts/vendor_three.sh 0.187.0
#
# Reproducible: `npm pack three@VERSION` fetches the published tarball, its sha512 is checked
# against the registry's `dist.integrity`, and only the files the viewer imports are copied (with
# the licence). README.md records the version, the tarball's integrity and each file's sha256, so
# running it twice with the same VERSION gives the same tree (no dates). Needs node/npm, tar,
# openssl. The viewer (service/api/static/viewer/) imports them through the import map in index.html.
set -euo pipefail

if [ $# -ne 1 ] || ! [[ $1 =~ ^[0-9]+\.[0-9]+\.[0-9]+$ ]]; then
  echo "usage: $0 VERSION   (an exact release, e.g. 0.187.0)" >&2
  exit 2
fi
VERSION=$1
ROOT=$(cd "$(dirname "$0")/.." && pwd)
DEST="$ROOT/service/api/static/vendor/three"
# What the viewer uses: the core build, and OrbitControls (it parses the PLY itself, so no loader).
FILES=(
  LICENSE
  build/three.module.js
  build/three.core.js
  examples/jsm/controls/OrbitControls.js
)

WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
cd "$WORK"

expected=$(npm view "three@$VERSION" dist.integrity)
tarball=$(npm pack "three@$VERSION" --silent)
actual="sha512-$(openssl dgst -sha512 -binary "$tarball" | openssl base64 -A)"
if [ "$expected" != "$actual" ]; then
  echo "integrity mismatch for three@$VERSION: registry $expected, tarball $actual" >&2
  exit 1
fi
tar xzf "$tarball"

# Every relative import of a vendored module must be vendored too (a new release may split files).
for f in "${FILES[@]}"; do
  case $f in *.js) ;; *) continue ;; esac
  dir=$(dirname "$f")
  for rel in $(grep -oE "from '\.{1,2}/[^']+'" "package/$f" | sed -E "s/^from '(.*)'$/\1/" | sort -u); do
    target=$(realpath -m --relative-to=package "package/$dir/$rel")
    if ! printf '%s\n' "${FILES[@]}" | grep -qxF "$target"; then
      echo "$f imports $target, which is not in FILES; add it" >&2
      exit 1
    fi
  done
done

rm -rf "$DEST"
for f in "${FILES[@]}"; do
  install -D -m 0644 "package/$f" "$DEST/$f"
done
{
  echo "# three.js $VERSION (vendored)"
  echo
  echo "The files the fleetmap viewer (\`service/api/static/viewer/\`) imports, copied unchanged from the"
  echo "npm registry's \`three@$VERSION\` tarball; MIT licence in \`LICENSE\`. Refresh with"
  echo "\`scripts/vendor_three.sh VERSION\` (never edit these files by hand)."
  echo
  echo "- package: \`three@$VERSION\` (https://www.npmjs.com/package/three)"
  echo "- tarball integrity: \`$expected\`"
  echo
  echo "| file | sha256 |"
  echo "|---|---|"
  for f in "${FILES[@]}"; do
    echo "| \`$f\` | \`$(sha256sum "$DEST/$f" | cut -d' ' -f1)\` |"
  done
} >"$DEST/README.md"
echo "$VERSION" >"$DEST/VERSION"
echo "vendored three@$VERSION into ${DEST#"$ROOT"/}"
