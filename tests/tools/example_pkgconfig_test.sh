#!/usr/bin/env bash
# Installs raystream into a staging directory and builds examples/trace_quad.cc against it with
# nothing but `pkg-config raystream`, as a tracer outside this tree would; then runs it.
# usage: example_pkgconfig_test.sh BUILD_DIR SOURCE_DIR [B_SANITIZE]
# In a sanitizer build the installed library needs the sanitizer runtime, so the example is
# built with the same -fsanitize flags (a user's own build would do the same).
set -euo pipefail
build=$1 src=$2 sanitize=${3:-none}
extra=()
[ "$sanitize" = none ] || extra=("-fsanitize=$sanitize")
stage=$(mktemp -d)
trap 'rm -rf "$stage"' EXIT
meson install -C "$build" --destdir "$stage" --no-rebuild >"$stage/install.log" 2>&1 \
  || { cat "$stage/install.log"; exit 1; }
pc=$(find "$stage" -name raystream.pc | head -1)
[ -n "$pc" ] || { echo "raystream.pc was not installed"; exit 1; }
prefix=$(sed -n 's/^prefix=//p' "$pc")
export PKG_CONFIG_PATH=$(dirname "$pc")
flags=$(pkg-config --define-variable=prefix="$stage$prefix" --cflags --libs raystream)
echo "pkg-config raystream: $flags"
${CXX:-c++} -std=c++20 -O2 "$src/examples/trace_quad.cc" -o "$stage/trace_quad" "${extra[@]}" $flags
libdir=$(pkg-config --define-variable=prefix="$stage$prefix" --variable=libdir raystream)
LD_LIBRARY_PATH="$libdir" "$stage/trace_quad"
