# One ctest per GoogleTest suite, where CMake's gtest_discover_tests makes one per
# test: each test process loads the binary's ~260 shared libraries (OpenCV's video
# and image I/O pull in FFmpeg and GDAL), which costs ~0.3 s of CPU before the first
# test runs: more than most tests take. `ctest -R Selector` picks suites; the binary's
# own --gtest_filter picks single tests.
#
#   keyframed_gtest_suites(TARGET [FIRST SUITE...])
#
# FIRST names the suites that take longest (seconds, mostly waiting on threads and
# sockets): ctest starts them first (a COST), so that they do not run alone at the
# end of a cold run, which has no timings of an earlier run to order by.
#
# After each link, this file runs in script mode: it lists the tests and writes an
# add_test() per suite into a file that ctest includes. Each suite runs through
# run_gtest_suite.sh: a suite in which every test skipped (GTEST_SKIP: no camera, for
# instance) is reported as skipped, and the tests that skipped in any suite are listed
# in skipped-tests/ beside the binary (tools/test.sh reports them). (Not ctest's
# SKIP_REGULAR_EXPRESSION on "[  PASSED  ] 0 tests": it wins over the exit status, so
# a suite whose every test failed passed as skipped.)

if(CMAKE_SCRIPT_MODE_FILE)
  execute_process(COMMAND "${TEST_EXECUTABLE}" --gtest_list_tests
                  OUTPUT_VARIABLE listing ERROR_VARIABLE errors RESULT_VARIABLE rc TIMEOUT 60)
  if(NOT rc EQUAL 0)
    message(FATAL_ERROR "${TEST_EXECUTABLE} --gtest_list_tests failed (${rc}):\n${listing}${errors}")
  endif()
  # Suite lines start in the first column ("Suite." or "Prefix/Suite."); test lines
  # are indented.
  string(REGEX MATCHALL "(^|\n)[A-Za-z0-9_/]+\\." suites "${listing}")
  set(content "")
  string(REPLACE "," ";" first "${FIRST_SUITES}")
  get_filename_component(exe_name "${TEST_EXECUTABLE}" NAME)
  file(MAKE_DIRECTORY "${WORKING_DIRECTORY}/skipped-tests")
  foreach(suite IN LISTS suites)
    string(STRIP "${suite}" suite)
    string(REGEX REPLACE "\\.$" "" suite "${suite}")
    list(FIND first "${suite}" at)  # (no IN_LIST: script mode runs without policies)
    set(cost 0)
    if(at GREATER -1)
      set(cost 100)
    endif()
    string(REPLACE "/" "_" file_suite "${suite}")
    set(skipped_file "${WORKING_DIRECTORY}/skipped-tests/${exe_name}.${file_suite}.txt")
    string(APPEND content
      "add_test([=[${suite}]=] [=[${RUNNER}]=] [=[${skipped_file}]=] [=[${TEST_EXECUTABLE}]=] "
      "[=[--gtest_filter=${suite}.*]=])\n"
      "set_tests_properties([=[${suite}]=] PROPERTIES WORKING_DIRECTORY "
      "[=[${WORKING_DIRECTORY}]=] SKIP_RETURN_CODE 77 COST ${cost})\n")
  endforeach()
  if(content STREQUAL "")
    message(FATAL_ERROR "${TEST_EXECUTABLE} lists no test suites")
  endif()
  file(WRITE "${CTEST_FILE}" "${content}")
  return()
endif()

set(_KEYFRAMED_GTEST_SUITES_SCRIPT "${CMAKE_CURRENT_LIST_FILE}")
set(_KEYFRAMED_GTEST_SUITE_RUNNER "${CMAKE_CURRENT_LIST_DIR}/run_gtest_suite.sh")

function(keyframed_gtest_suites target)
  cmake_parse_arguments(PARSE_ARGV 1 arg "" "" "FIRST")
  list(JOIN arg_FIRST "," first)
  set(ctest_file "${CMAKE_CURRENT_BINARY_DIR}/${target}_suites.cmake")
  set(include_file "${CMAKE_CURRENT_BINARY_DIR}/${target}_suites_include.cmake")
  add_custom_command(TARGET ${target} POST_BUILD
    COMMAND "${CMAKE_COMMAND}" "-DTEST_EXECUTABLE=$<TARGET_FILE:${target}>"
            "-DCTEST_FILE=${ctest_file}" "-DWORKING_DIRECTORY=${CMAKE_CURRENT_BINARY_DIR}"
            "-DFIRST_SUITES=${first}" "-DRUNNER=${_KEYFRAMED_GTEST_SUITE_RUNNER}"
            -P "${_KEYFRAMED_GTEST_SUITES_SCRIPT}"
    BYPRODUCTS "${ctest_file}"
    VERBATIM)
  # ctest reads this one: the list of suites exists once the binary is built.
  file(WRITE "${include_file}"
    "if(EXISTS [=[${ctest_file}]=])\n"
    "  include([=[${ctest_file}]=])\n"
    "else()\n"
    "  add_test([=[${target}_NOT_BUILT]=] [=[${target}_NOT_BUILT]=])\n"
    "endif()\n")
  set_property(DIRECTORY APPEND PROPERTY TEST_INCLUDE_FILES "${include_file}")
endfunction()
