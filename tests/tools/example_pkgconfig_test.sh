#!/usr/bin/env bash
# The installed library as a tracer outside this tree sees it: installs raystream into a staging
# directory, then
#   - libraystream.so links only Highway (and the C/C++ runtime), exports only the RS_API names of
#     include/raystream/raystream.h (no Highway per-target code, no renderer, no fmt), and has no
#     source-tree path baked in;
#   - raystream.pc requires only libhwy (privately) and builds examples/trace_quad.cc (C++) and
#     examples/trace_quad_c.c (the C API) with nothing but `pkg-config raystream`; CMake's find_package(raystream) builds it too; both run;
#   - used as a meson subproject, raystream adds its library alone (no command, tests, benchmarks
#     or examples) and no -Werror to the parent's build.
# usage: example_pkgconfig_test.sh BUILD_DIR SOURCE_DIR [B_SANITIZE]
# In a sanitizer build the installed library needs the sanitizer runtime, so the example is
# built with the same -fsanitize flags (a user's own build would do the same).
set -euo pipefail
build=$1 src=$2 sanitize=${3:-none}
extra=()
[ "$sanitize" = none ] || extra=("-fsanitize=$sanitize")
stage=$(mktemp -d)
trap 'rm -rf "$stage"' EXIT
fail() { echo "FAIL: $*"; exit 1; }
meson install -C "$build" --destdir "$stage" --no-rebuild >"$stage/install.log" 2>&1 \
  || { cat "$stage/install.log"; exit 1; }
pc=$(find "$stage" -name raystream.pc | head -1)
[ -n "$pc" ] || fail "raystream.pc was not installed"
prefix=$(sed -n 's/^prefix=//p' "$pc")
export PKG_CONFIG_PATH=$(dirname "$pc")
libdir=$(pkg-config --define-variable=prefix="$stage$prefix" --variable=libdir raystream)
lib="$libdir/libraystream.so"
[ -e "$lib" ] || fail "no $lib"

# Links: Highway and the runtime only.
others=$(ldd "$lib" | awk '{print $1}' | grep -vE '^(linux-vdso|/lib64/ld-linux-x86-64|libhwy|libstdc\+\+|libm|libgcc_s|libc|libasan|libubsan|libtsan)\.' || true)
[ -z "$others" ] || fail "libraystream.so links more than Highway: $others"
echo "ok: links $(ldd "$lib" | wc -l) objects (Highway and the runtime)"
# Exports: rs:: names of the public header, plus the standard library's vague-linkage templates.
exports=$(nm -D --defined-only "$lib" | c++filt | cut -d' ' -f3-)
bad=$(echo "$exports" | grep -E 'rs::' | grep -vE '^(rs::Accel::|rs::LightBuffer::|rs::TraceScene::|rs::RayBuffer::|rs::HitBuffer::|rs::RayKindName\(|rs::Version\(|(typeinfo|typeinfo name|vtable) for rs::Error$)' || true)
[ -z "$bad" ] || fail "libraystream.so exports internal names: $bad"
bad=$(echo "$exports" | grep -vE 'rs::|^rs[A-Z][A-Za-z]+$|^std::|^__gnu_cxx::|^_init$|^_fini$|^__bss_start|^_edata|^_end' || true)
[ -z "$bad" ] || fail "libraystream.so exports foreign names: $bad"
echo "ok: exports $(echo "$exports" | grep -c 'rs::') rs:: symbols, all in the public header"
if strings "$lib" | grep -q "$src"; then fail "libraystream.so holds the source path $src"; fi
echo "ok: no source-tree path in the library"

# pkg-config: only libhwy, privately.
req=$(pkg-config --print-requires raystream | tr -d ' ')
priv=$(pkg-config --print-requires-private raystream | awk '{print $1}' | tr '\n' ' ')
[ -z "$req" ] || fail "raystream.pc Requires: $req"
[ "$priv" = "libhwy " ] || fail "raystream.pc Requires.private: '$priv' (want libhwy)"
flags=$(pkg-config --define-variable=prefix="$stage$prefix" --cflags --libs raystream)
echo "ok: pkg-config raystream: $flags"
${CXX:-c++} -std=c++20 -O2 "$src/examples/trace_quad.cc" -o "$stage/trace_quad" "${extra[@]}" $flags
LD_LIBRARY_PATH="$libdir" "$stage/trace_quad" >"$stage/pc.out"
echo "ok: trace_quad built with pkg-config and ran"
${CC:-cc} -std=c11 -O2 "$src/examples/trace_quad_c.c" -o "$stage/trace_quad_c" "${extra[@]}" $flags -lm
LD_LIBRARY_PATH="$libdir" "$stage/trace_quad_c" >"$stage/c.out" || { cat "$stage/c.out"; fail "the C example"; }
echo "ok: trace_quad_c (the C API) built with pkg-config and ran"

# CMake: find_package(raystream) and the imported target.
if command -v cmake >/dev/null; then
  mkdir -p "$stage/cm"
  cat >"$stage/cm/CMakeLists.txt" <<CMAKE
cmake_minimum_required(VERSION 3.16)
project(trace_quad CXX)
find_package(raystream 0.1 REQUIRED)
add_executable(trace_quad "$src/examples/trace_quad.cc")
target_link_libraries(trace_quad PRIVATE raystream::raystream)
CMAKE
  # raystream_DIR: the installed package's folder (libdir/cmake/raystream; libdir is lib64 where
  # meson cannot tell the multiarch folder, e.g. without dpkg-dev).
  cfg=$(find "$stage" -name raystreamConfig.cmake | head -1)
  [ -n "$cfg" ] || fail "raystreamConfig.cmake was not installed"
  cmake -G Ninja -S "$stage/cm" -B "$stage/cm/build" -DCMAKE_PREFIX_PATH="$stage$prefix" \
    -Draystream_DIR="$(dirname "$cfg")" \
    -DCMAKE_CXX_FLAGS="${extra[*]}" >"$stage/cm.log" 2>&1 || { cat "$stage/cm.log"; fail "cmake configure"; }
  cmake --build "$stage/cm/build" >>"$stage/cm.log" 2>&1 || { cat "$stage/cm.log"; fail "cmake build"; }
  LD_LIBRARY_PATH="$libdir" "$stage/cm/build/trace_quad" >"$stage/cm.out"
  cmp -s "$stage/pc.out" "$stage/cm.out" || fail "the CMake build's output differs"
  echo "ok: trace_quad built with find_package(raystream) and ran"
fi

# A meson subproject: the library alone, no -Werror.
mkdir -p "$stage/parent/subprojects"
ln -s "$src" "$stage/parent/subprojects/raystream"
cat >"$stage/parent/meson.build" <<'MESON'
project('parent', 'cpp', default_options : ['cpp_std=c++20'])
rs = subproject('raystream').get_variable('raystream_dep')
executable('trace_quad', 'trace_quad.cc', dependencies : rs)
MESON
cp "$src/examples/trace_quad.cc" "$stage/parent/"
meson setup "$stage/parent/build" "$stage/parent" >"$stage/sub.log" 2>&1 || { cat "$stage/sub.log"; fail "meson setup of a parent project"; }
targets=$(meson introspect --targets "$stage/parent/build" | python3 -c "import json,sys; print(' '.join(sorted(t['name'] for t in json.load(sys.stdin))))")
tests=$(meson introspect --tests "$stage/parent/build" | python3 -c "import json,sys; print(len(json.load(sys.stdin)))")
echo "subproject targets: $targets; tests: $tests"
[ "$tests" = 0 ] || fail "the subproject adds $tests tests to the parent"
echo "$targets" | grep -qE '(^| )raystream( |$)' || fail "no raystream library in the parent"
[ "$(echo "$targets" | wc -w)" -le 6 ] || fail "the subproject adds more than its libraries"
if grep -q -- '-Werror' "$stage/parent/build/compile_commands.json"; then fail "-Werror in the parent's build"; fi
ninja -C "$stage/parent/build" >"$stage/sub-build.log" 2>&1 || { tail -20 "$stage/sub-build.log"; fail "parent build"; }
"$stage/parent/build/trace_quad" >"$stage/sub.out"
cmp -s "$stage/pc.out" "$stage/sub.out" || fail "the subproject build's output differs"
echo "ok: as a subproject: the library alone, no -Werror, trace_quad runs"
