include_guard(GLOBAL)

# Warnings for our own code only (never for generated or third-party code).
add_library(surfel_warnings INTERFACE)
target_compile_options(surfel_warnings INTERFACE -Wall -Wextra -Wpedantic -Wshadow
                       -Wnon-virtual-dtor $<$<BOOL:${SURFEL_WERROR}>:-Werror>)

# Sanitizers apply to everything we build, so the tests exercise them. Debian's gRPC, protobuf,
# TBB, Embree and FLANN are not instrumented: tests/sanitizers/*.supp says what that hides.
if(SURFEL_SANITIZE)
    set(surfel_sanitizers "${SURFEL_SANITIZE}")
    if(surfel_sanitizers STREQUAL "ON" OR surfel_sanitizers STREQUAL "1" OR surfel_sanitizers STREQUAL "TRUE")
        set(surfel_sanitizers "address,undefined")
    endif()
    if(NOT surfel_sanitizers MATCHES "^(address|undefined|address,undefined|undefined,address|thread)$")
        message(FATAL_ERROR "SURFEL_SANITIZE=${SURFEL_SANITIZE}: expected address,undefined or thread")
    endif()
    # -g1: line tables for the reports' stacks at a fraction of -g's compile time. -O1 (after the
    # build type's -O3, so it wins): what the sanitizers' documentation recommends, and the
    # instrumented -O3 build took 2.7x the CPU of -O1 (server_main.cpp under ASan + UBSan: 100.8 s
    # against 37.2 s of user time; plain -O3 23.3 s), which is what keeps `make test` within CI's
    # budget with both sanitizer steps in it (docs/testing.md, "Cost").
    add_compile_options(-fsanitize=${surfel_sanitizers} -fno-omit-frame-pointer -g1 -O1)
    add_link_options(-fsanitize=${surfel_sanitizers})
    if(surfel_sanitizers MATCHES "undefined")
        # A report is a failure, never a line in a log (UBSan recovers by default).
        add_compile_options(-fno-sanitize-recover=all)
    endif()
endif()

# How much slower an instrumented build runs (ASan + UBSan about 2-3x, TSan 5-15x): ctest's
# per-test limit scales by it, and every test target gets it as the definition SURFEL_TEST_SLOWDOWN
# for the bounds it sets itself (e.g. ManagerTest.TimeoutGivesDeadlineExceeded).
set(SURFEL_TEST_SLOWDOWN 1)
if(SURFEL_SANITIZE MATCHES "thread")
    set(SURFEL_TEST_SLOWDOWN 8)
    add_compile_definitions(SURFEL_TSAN_BUILD)
elseif(SURFEL_SANITIZE)
    set(SURFEL_TEST_SLOWDOWN 3)
endif()

# surfel_add_module(NAME SOURCES ... DEPS ... [PRIVATE_DEPS ...])
# One static library per core module, named surfel_<NAME>, with core/ on the include path.
function(surfel_add_module name)
    cmake_parse_arguments(ARG "" "" "SOURCES;DEPS;PRIVATE_DEPS" ${ARGN})
    add_library(surfel_${name} STATIC ${ARG_SOURCES})
    add_library(surfel::${name} ALIAS surfel_${name})
    target_include_directories(surfel_${name} PUBLIC ${PROJECT_SOURCE_DIR}/core)
    target_link_libraries(surfel_${name} PUBLIC ${ARG_DEPS} PRIVATE ${ARG_PRIVATE_DEPS} surfel_warnings)
    set_target_properties(surfel_${name} PROPERTIES POSITION_INDEPENDENT_CODE ON)
    if(SURFEL_SANITIZE MATCHES "thread")
        # The TSan build is for the threads of the job manager, gRPC and the HTTP front (worker/,
        # server/, the tests); the geometry modules run on the calling thread there (TBB held to
        # one thread, SURFEL_TSAN_BUILD in spatial/kd_tree.cpp), so instrumenting them would find
        # nothing and cost half of that build. Uninstrumented code records no accesses: it cannot
        # cause a report, and the mutexes and allocations it uses are still intercepted.
        target_compile_options(surfel_${name} PRIVATE -fno-sanitize=thread)
    endif()
endfunction()

# surfel_add_test(NAME SOURCES ... DEPS ...): one GoogleTest binary per module.
function(surfel_add_test name)
    cmake_parse_arguments(ARG "" "" "SOURCES;DEPS" ${ARGN})
    add_executable(${name} ${ARG_SOURCES})
    target_link_libraries(${name} PRIVATE ${ARG_DEPS} GTest::gtest GTest::gtest_main surfel_warnings)
    target_compile_options(${name} PRIVATE -Wno-dangling-else)  # EXPECT_* after a bare if
    target_compile_definitions(${name} PRIVATE
        SURFEL_SHARED_DATA_DIR="${PROJECT_SOURCE_DIR}/../shared/data"
        SURFEL_BIN_DIR="${CMAKE_RUNTIME_OUTPUT_DIRECTORY}"
        # A test that bounds a time itself scales the bound by this (1 in a plain build).
        SURFEL_TEST_SLOWDOWN=${SURFEL_TEST_SLOWDOWN})
    set_target_properties(${name} PROPERTIES RUNTIME_OUTPUT_DIRECTORY ${CMAKE_BINARY_DIR}/tests)
    # The image plugin lives in build/bin/, not beside the test binaries (build/tests/). The
    # binary's name is each test's label: `ctest -L '^test_worker$'` runs one module's tests (the
    # TSan build selects its suites so).
    math(EXPR timeout "300 * ${SURFEL_TEST_SLOWDOWN}")
    gtest_discover_tests(${name} DISCOVERY_TIMEOUT 60 PROPERTIES TIMEOUT ${timeout} LABELS ${name}
                         ENVIRONMENT "SURFEL_IMAGE_PLUGIN=${SURFEL_IMAGE_PLUGIN_PATH}"
                         # (a second variable as its own property: gtest_discover_tests splits a list)
                         ENVIRONMENT_MODIFICATION "SURFEL_EXR_PLUGIN=set:${SURFEL_EXR_PLUGIN_PATH}")
endfunction()
