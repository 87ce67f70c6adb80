#!/bin/sh
# Runs one GoogleTest suite for ctest (cmake/GTestSuites.cmake):
#   run_gtest_suite.sh SKIPPED_FILE TEST_EXECUTABLE ARGS...
# Exit status: the binary's when it fails; 77 (ctest's SKIP_RETURN_CODE) when it
# passed with every test skipped; else 0. The names of skipped tests, with the
# reason printed before each, go to SKIPPED_FILE (removed when none skipped), so that
# a skip inside a suite that passed is not lost: tools/test.sh lists them.
skipped_file="$1"
shift
out="$("$@" 2>&1)"
rc=$?
printf '%s\n' "$out"
# "[  SKIPPED ] Suite.Test (0 ms)" as each test ends (the summary's lines have no
# time), after GTEST_SKIP's message: "Suite.Test: message".
skips="$(printf '%s\n' "$out" | awk '
  /^\[  SKIPPED \] [^ ]+ \([0-9]+ ms\)$/ { print $4 ": " prev; next }
  { prev = $0 }')"
if [ -n "$skips" ]; then
  printf '%s\n' "$skips" > "$skipped_file"
else
  rm -f "$skipped_file"
fi
[ "$rc" -ne 0 ] && exit "$rc"
if [ -n "$skips" ] && printf '%s\n' "$out" | grep -q '^\[  PASSED  \] 0 tests\.$'; then
  exit 77
fi
exit 0
