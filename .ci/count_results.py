#!/usr/bin/env python3
"""Prints 'N passed, N failed' from meson's own test log (testlog.json).

A meson test whose output carries doctest's summary counts as its doctest test cases; any other
meson test (fuzz replays, command-line and packaging scripts) counts as one test with meson's
verdict. A doctest executable that crashed before printing its summary counts as one failure.
"""
import json
import re
import sys

SUMMARY = re.compile(r"^\[doctest\] test cases:\s*(\d+)\s*\|\s*(\d+) passed\s*\|\s*(\d+) failed",
                     re.M)


def main(path):
    passed = failed = 0
    try:
        lines = open(path, encoding="utf-8", errors="replace").read().splitlines()
    except OSError as e:
        print(f"no test log: {e}", file=sys.stderr)
        lines = []
    for line in lines:
        if not line.strip():
            continue
        rec = json.loads(line)
        ok = rec.get("result") in ("OK", "EXPECTEDFAIL", "SKIP")
        out = (rec.get("stdout") or "") + (rec.get("stderr") or "")
        found = SUMMARY.findall(out)
        if found:
            p = sum(int(m[1]) for m in found)
            f = sum(int(m[2]) for m in found)
            if not ok and f == 0:
                f = 1  # the executable failed after its summary (e.g. a sanitizer at exit)
            passed += p
            failed += f
        elif ok:
            passed += 1
        else:
            failed += 1
    print(f"{passed} passed, {failed} failed")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else "build/meson-logs/testlog.json"))
