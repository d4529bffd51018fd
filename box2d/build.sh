#!/usr/bin/env bash
# Build the patched pybox2d wheel into OUTDIR.
#
# Fetches the box2d-py sdist from the package registry (pinned version and
# sha256), applies box2d/deepcontact.patch, regenerates the SWIG wrapper and
# compiles. No upstream source is kept in this repository.
#
# usage: box2d/build.sh OUTDIR        (PYTHON=path/to/python, default .venv/bin/python;
#                                      SDIST=path/to/box2d-py-2.3.8.tar.gz: build from that file,
#                                      on a machine without the registry; its sha256 is checked too)
set -euo pipefail

VERSION=2.3.8
SHA256=bdacfbbc56079bb317548efe49d3d5a86646885cc27f4a2ee97e4b2960921ab7

here=$(cd "$(dirname "$0")" && pwd)
out=${1:?usage: box2d/build.sh OUTDIR}
python=${PYTHON:-.venv/bin/python}
python=$(cd "$(dirname "$python")" && pwd)/$(basename "$python")
bindir=$(dirname "$python")

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

if [ -n "${SDIST:-}" ]; then
    sdist=$SDIST
else
    echo "box2d: fetching box2d-py==$VERSION sdist"
    "$python" -m pip download --quiet --no-deps --no-binary :all: --no-build-isolation \
        "box2d-py==$VERSION" -d "$work/sdist"
    sdist=$(ls "$work"/sdist/box2d-py-"$VERSION".tar.gz)
fi
echo "$SHA256  $sdist" | sha256sum --check --quiet - \
    || { echo "box2d: sha256 of $sdist does not match the pinned $SHA256" >&2; exit 1; }

tar -xzf "$sdist" -C "$work"
src="$work/box2d-py-$VERSION"
echo "box2d: applying deepcontact.patch"
patch --quiet --forward -p1 -d "$src" < "$here/deepcontact.patch"
# The sdist ships a SWIG-generated Box2D.py for the unpatched sources.
rm -f "$src/library/Box2D/Box2D.py"

echo "box2d: building (SWIG + C++, about a minute)"
mkdir -p "$out"
# A failed build prints thousands of lines of warnings around its errors: the
# whole output goes to a log, and the errors are repeated at the end.
log="$out/build.log"
if ! PATH="$bindir:$PATH" "$python" -m pip wheel --quiet --no-deps --no-build-isolation \
        -w "$work/dist" "$src" > "$log" 2>&1; then
    echo "box2d: the build failed; its errors (the whole output is in $log):" >&2
    grep -E "error:|Error:" "$log" | grep -v "subprocess-exited-with-error" | head -20 >&2 || true
    exit 1
fi
wheel=$(ls "$work"/dist/*.whl)
# Land the wheel under its final name only once it is complete.
cp "$wheel" "$out/.$(basename "$wheel").part"
mv "$out/.$(basename "$wheel").part" "$out/$(basename "$wheel")"
echo "box2d: built $out/$(basename "$wheel")"
