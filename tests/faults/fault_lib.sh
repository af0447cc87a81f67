# Shared by the fault suites (sourced): check counters and the two expectations every case uses.
fails=0 checks=0 skips=0
# A sanitizer build (RAYSTREAM_SANITIZE from tests/faults/meson.build, get_option('b_sanitize')):
# cases that need RLIMIT_AS use another limit under ASan, or say why they are skipped.
case "${RAYSTREAM_SANITIZE:-none}" in *address*) asan=1 ;; *) asan=0 ;; esac
skip() { skips=$((skips+1)); echo "skip $*"; }
ok() { checks=$((checks+1)); echo "ok   $*"; }
bad() { checks=$((checks+1)); fails=$((fails+1)); echo "FAIL $*"; }

# expect_error NAME PATTERN CMD...: exit 1, exactly one line on stderr, matching PATTERN.
expect_error() {
  local name=$1 pattern=$2; shift 2
  "$@" >out.txt 2>err.txt </dev/null; local rc=$?
  local lines; lines=$(wc -l <err.txt)
  if [ $rc -ne 1 ]; then bad "$name: exit $rc (want 1)"; cat err.txt; return; fi
  if [ "$lines" -ne 1 ]; then bad "$name: $lines lines on stderr (want 1)"; cat err.txt; return; fi
  if grep -qE "^raystream: error: $pattern" err.txt; then ok "$name: $(cat err.txt)"
  else bad "$name: stderr does not match /^raystream: error: $pattern/:"; cat err.txt; fi
}
# expect_empty NAME DIR: DIR holds no file at all (hidden temporaries included).
expect_empty() {
  if [ -z "$(ls -A "$2")" ]; then ok "$1: nothing left in $2"; else bad "$1: left behind: $(ls -A "$2")"; fi
}
