# Run by CTest (tests/install/CMakeLists.txt) as cmake -D... -P check_install.cmake:
#  1. cmake --install BUILD_DIR into WORK_DIR/prefix; only headers, libraries and package files;
#     zone::gpu there iff the build has CUDA;
#  2. configure examples/ against that prefix (CMAKE_PREFIX_PATH only), build it;
#  3. run who-sees-whom, find-pairs and tick-loop and compare what they print with what is known to be right
#     (find-pairs also on a fresh generated set against the brute-force reference, when the
#     interest-pairs tool is built).
# Any failure is a FATAL_ERROR (a non-zero exit: CTest reports a failure).
cmake_minimum_required(VERSION 3.25)
foreach(var BUILD_DIR EXAMPLES_DIR DATA_DIR WORK_DIR GENERATOR CXX_COMPILER HAVE_CUDA)
  if(NOT DEFINED ${var})
    message(FATAL_ERROR "check_install.cmake: -D${var}=... is required")
  endif()
endforeach()
if(NOT BUILD_TYPE)
  set(BUILD_TYPE Release)
endif()

file(REMOVE_RECURSE "${WORK_DIR}")
file(MAKE_DIRECTORY "${WORK_DIR}")
set(prefix "${WORK_DIR}/prefix")

# step(<name> <command>...): runs a command; a failure shows its output.
function(step name)
  execute_process(COMMAND ${ARGN} RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err)
  if(NOT rc EQUAL 0)
    message(FATAL_ERROR "[${name}] exit status ${rc}\nstdout:\n${out}\nstderr:\n${err}")
  endif()
  set(step_out "${out}" PARENT_SCOPE)
  set(step_err "${err}" PARENT_SCOPE)
endfunction()

# ---- 1. install ---------------------------------------------------------------------------------
step(install "${CMAKE_COMMAND}" --install "${BUILD_DIR}" --prefix "${prefix}" --config "${BUILD_TYPE}")
file(GLOB_RECURSE installed RELATIVE "${prefix}" "${prefix}/*")
list(SORT installed)
set(allowed "^include/zone/[a-z_]+\\.h$|^lib(64)?/libzone_(interest|gpu)\\.(a|so[.0-9]*)$|^lib(64)?/cmake/zone/zone[A-Za-z-]*\\.cmake$")
foreach(f IN LISTS installed)
  if(NOT f MATCHES "${allowed}")
    message(FATAL_ERROR "the install holds ${f}: only headers, libraries and package files belong there\n"
                        "installed:\n${installed}")
  endif()
endforeach()
foreach(f include/zone/interest.h include/zone/interest_space.h lib/cmake/zone/zoneConfig.cmake lib/cmake/zone/zoneConfigVersion.cmake)
  if(NOT EXISTS "${prefix}/${f}")
    message(FATAL_ERROR "the install lacks ${f}\ninstalled:\n${installed}")
  endif()
endforeach()
set(gpu_expected NO)
if(HAVE_CUDA)
  set(gpu_expected YES)
endif()
set(gpu_installed NO)
if(EXISTS "${prefix}/include/zone/finders.h" AND EXISTS "${prefix}/lib/libzone_gpu.a")
  set(gpu_installed YES)
endif()
if(NOT gpu_installed STREQUAL gpu_expected)
  message(FATAL_ERROR "GPU backend installed: ${gpu_installed}, expected ${gpu_expected} (HAVE_CUDA=${HAVE_CUDA})")
endif()

# ---- 2. configure and build the examples against the prefix -------------------------------------
set(configure_args -S "${EXAMPLES_DIR}" -B "${WORK_DIR}/build" -G "${GENERATOR}"
    "-DCMAKE_PREFIX_PATH=${prefix}" "-DCMAKE_BUILD_TYPE=${BUILD_TYPE}" "-DCMAKE_CXX_COMPILER=${CXX_COMPILER}")
if(CXX_LAUNCHER)
  list(APPEND configure_args "-DCMAKE_CXX_COMPILER_LAUNCHER=${CXX_LAUNCHER}")
endif()
step(configure "${CMAKE_COMMAND}" ${configure_args})
if(HAVE_CUDA)
  set(gpu_line "find-pairs: GPU finders ON")
else()
  set(gpu_line "find-pairs: GPU finders OFF")
endif()
string(FIND "${step_out}" "${gpu_line}" at)
if(at EQUAL -1)
  message(FATAL_ERROR "configure of the examples did not say \"${gpu_line}\":\n${step_out}")
endif()
step(build "${CMAKE_COMMAND}" --build "${WORK_DIR}/build" -j 2)
set(who "${WORK_DIR}/build/who_sees_whom/who-sees-whom")
set(find "${WORK_DIR}/build/find_pairs/find-pairs")
set(tick "${WORK_DIR}/build/tick_loop/tick-loop")

# ---- 3. run them -------------------------------------------------------------------------------
step(who_sees_whom "${who}")
set(expected "alice sees bob\nbob sees alice\nbob sees dragon\nrogue sees alice\nrogue sees bob\n10 box pairs, 5 sightings\n")
if(NOT step_out STREQUAL expected)
  message(FATAL_ERROR "who_sees_whom printed:\n${step_out}\nexpected:\n${expected}")
endif()

step(find_pairs_known "${find}" "${DATA_DIR}/known.csv" "${WORK_DIR}/known_pairs.txt")
file(READ "${WORK_DIR}/known_pairs.txt" got)
file(READ "${DATA_DIR}/known_expected.txt" expected)
if(NOT got STREQUAL expected OR NOT step_out MATCHES "9 pairs among 8 boxes")
  message(FATAL_ERROR "find_pairs known.csv wrote:\n${got}\nexpected:\n${expected}\nstdout:\n${step_out}")
endif()

execute_process(COMMAND "${find}" "${DATA_DIR}/bad_nan.csv" "${WORK_DIR}/bad_pairs.txt"
                RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err)
if(NOT rc EQUAL 2 OR NOT err MATCHES "bad_nan.csv" OR EXISTS "${WORK_DIR}/bad_pairs.txt")
  message(FATAL_ERROR "find_pairs on bad input: exit ${rc} (expected 2, no output file), stdout:\n${out}\nstderr:\n${err}")
endif()

# The tick API: the same events on the CPU and with auto (the GPU where the package and a device
# allow it); a bad backend name is refused.
set(expected "tick 3: guard + thief\ntick 3: thief + guard\ntick 4: guard + merchant\ntick 4: thief + merchant\n"
             "tick 4: merchant + guard\ntick 6: guard - thief\ntick 6: guard - merchant\ntick 6: thief - merchant\n"
             "guard sees 0 at the end\n")
string(CONCAT expected ${expected})
foreach(backend cpu auto)
  step(tick_loop_${backend} "${tick}" ${backend})
  if(NOT step_out STREQUAL expected)
    message(FATAL_ERROR "tick-loop ${backend} printed:\n${step_out}\nexpected:\n${expected}\nstderr:\n${step_err}")
  endif()
endforeach()
execute_process(COMMAND "${tick}" quantum RESULT_VARIABLE rc OUTPUT_VARIABLE out ERROR_VARIABLE err)
if(NOT rc EQUAL 64 OR NOT err MATCHES "usage")
  message(FATAL_ERROR "tick-loop quantum: exit ${rc} (expected 64 and a usage line), stderr:\n${err}")
endif()

if(INTEREST_PAIRS)  # a fresh set (seed from the clock) against the brute-force reference
  string(TIMESTAMP seed "%s")
  step(gen "${INTEREST_PAIRS}" gen --set mmo --count 4000 --seed ${seed} --output "${WORK_DIR}/fresh.csv")
  step(brute "${INTEREST_PAIRS}" --backend brute --output "${WORK_DIR}/brute.txt" "${WORK_DIR}/fresh.csv")
  step(find_pairs_fresh "${find}" "${WORK_DIR}/fresh.csv" "${WORK_DIR}/fresh_pairs.txt")
  file(READ "${WORK_DIR}/fresh_pairs.txt" got)
  file(READ "${WORK_DIR}/brute.txt" expected)
  if(NOT got STREQUAL expected OR expected STREQUAL "")
    string(LENGTH "${got}" got_len)
    string(LENGTH "${expected}" want_len)
    message(FATAL_ERROR "find_pairs differs from the brute-force reference on the mmo set, seed ${seed} "
                        "(${got_len} vs ${want_len} characters of output)")
  endif()
endif()
message(STATUS "install + examples: ok (GPU backend ${gpu_installed})")
