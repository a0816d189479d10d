# Surfel: the two entry points of the README.
#   make demo   install what is missing, build, run the main job on a sample cloud (results in out/);
#               SERVE=1 keeps the server and its web page up until Ctrl-C
#   make test   install what is missing, build, run every test (ctest), the cloud-file fuzzers for
#               60 s in all, and the suites under ASan + UBSan and under TSan (docs/testing.md);
#               SANITIZE=0 leaves the two sanitizer steps out (a quicker run while working)
BUILD ?= build
FUZZ_BUILD ?= build-fuzz
FUZZ_SECONDS ?= 60
FUZZERS = ply_fuzzer xyz_fuzzer cloud_fuzzer
ASAN_BUILD ?= build-asan
TSAN_BUILD ?= build-tsan
# make test runs the sanitizer steps too (CI included); SANITIZE=0 skips them. Their builds are
# -O1 (cmake/SurfelHelpers.cmake), which keeps CI within its budget (docs/testing.md, "Cost").
SANITIZE ?= 1
# Under ASan + UBSan: a suite of every module (core, worker, store, service, the Python client);
# the slow end-to-end suites (CLI, degenerate inputs, service, HTTP, API fuzzer) run in Release
# only. ASAN_LABELS=. runs everything.
ASAN_TARGETS = surfel-server test_base test_io test_spatial test_surface test_render test_simplify \
               test_resample test_boolean test_worker test_store test_upload_executor test_http_status
ASAN_LABELS ?= ^(test_base|test_io|test_spatial|test_surface|test_render|test_simplify|test_resample|test_boolean|test_worker|test_store|test_upload_executor|test_http_status|grpc_python)$$
# The job manager and the service under TSan: the targets to build and their ctest labels.
TSAN_TARGETS = surfel-server test_worker test_upload_executor
TSAN_LABELS ?= ^(test_worker|test_upload_executor|grpc_python)$$
SAN_SUPP = $(CURDIR)/tests/sanitizers
# A report fails the test: ASan and UBSan stop at the first, TSan too (halt_on_error).
SAN_ENV = ASAN_OPTIONS=detect_leaks=1:halt_on_error=1:strict_string_checks=1:detect_stack_use_after_return=0 \
          LSAN_OPTIONS=suppressions=$(SAN_SUPP)/lsan.supp:print_suppressions=0 \
          UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1:suppressions=$(SAN_SUPP)/ubsan.supp \
          TSAN_OPTIONS=halt_on_error=1:second_deadlock_stack=1:suppressions=$(SAN_SUPP)/tsan.supp:print_suppressions=0
CMAKE_FLAGS ?=
SERVE ?= 0

.PHONY: all deps build demo test unit-test fuzz sanitize asan-test tsan-test bench clean
all: build

deps:
	@bash scripts/install-deps

build: deps
	@cmake -S . -B $(BUILD) -G Ninja -DCMAKE_BUILD_TYPE=Release $(CMAKE_FLAGS) >/dev/null
	@cmake --build $(BUILD) -j $$(nproc)

demo: build
	@SERVE=$(SERVE) bash scripts/demo $(BUILD)/bin out

unit-test: build
	@ctest --test-dir $(BUILD) --output-on-failure -j $$(nproc)

test: unit-test fuzz $(if $(filter 1,$(SANITIZE)),sanitize)

fuzz: deps
	@CXX=clang++ cmake -S . -B $(FUZZ_BUILD) -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DSURFEL_BUILD_FUZZ=ON \
	    -DSURFEL_BUILD_TESTS=OFF -DSURFEL_REQUIRE_SERVICE_DEPS=OFF >/dev/null
	@cmake --build $(FUZZ_BUILD) -j $$(nproc) --target $(FUZZERS)
	@bash tests/fuzz/run-fuzzer $(FUZZ_SECONDS) $(addprefix $(FUZZ_BUILD)/bin/,$(FUZZERS))

sanitize: asan-test tsan-test

# The suites of ASAN_LABELS under AddressSanitizer + UndefinedBehaviorSanitizer.
asan-test: deps
	@cmake -S . -B $(ASAN_BUILD) -G Ninja -DCMAKE_BUILD_TYPE=Release -DSURFEL_SANITIZE=address,undefined \
	    $(CMAKE_FLAGS) >/dev/null
	@cmake --build $(ASAN_BUILD) -j $$(nproc) $(if $(filter .,$(ASAN_LABELS)),,--target $(ASAN_TARGETS))
	@$(SAN_ENV) ctest --test-dir $(ASAN_BUILD) --output-on-failure -j $$(nproc) -L '$(ASAN_LABELS)'

# The job manager, the service and the server it starts under ThreadSanitizer.
tsan-test: deps
	@cmake -S . -B $(TSAN_BUILD) -G Ninja -DCMAKE_BUILD_TYPE=Release -DSURFEL_SANITIZE=thread $(CMAKE_FLAGS) >/dev/null
	@cmake --build $(TSAN_BUILD) -j $$(nproc) --target $(TSAN_TARGETS)
	@$(SAN_ENV) ctest --test-dir $(TSAN_BUILD) --output-on-failure -j $$(nproc) -L '$(TSAN_LABELS)'

bench: deps
	@cmake -S . -B $(BUILD) -G Ninja -DCMAKE_BUILD_TYPE=Release -DSURFEL_BUILD_BENCH=ON >/dev/null
	@cmake --build $(BUILD) -j $$(nproc)

clean:
	rm -rf $(BUILD) $(FUZZ_BUILD) $(ASAN_BUILD) $(TSAN_BUILD) out
