# Surfel: the two entry points of the README.
#   make demo   install what is missing, build, run the main job on a sample cloud (results in out/);
#               SERVE=1 keeps the server and its web page up until Ctrl-C
#   make test   install what is missing, build, run every test (ctest) and the PLY fuzzer for 60 s
BUILD ?= build
FUZZ_BUILD ?= build-fuzz
FUZZ_SECONDS ?= 60
CMAKE_FLAGS ?=
SERVE ?= 0

.PHONY: all deps build demo test unit-test fuzz bench clean
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

test: unit-test fuzz

fuzz: deps
	@CXX=clang++ cmake -S . -B $(FUZZ_BUILD) -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DSURFEL_BUILD_FUZZ=ON \
	    -DSURFEL_BUILD_TESTS=OFF -DSURFEL_REQUIRE_SERVICE_DEPS=OFF >/dev/null
	@cmake --build $(FUZZ_BUILD) -j $$(nproc) --target ply_fuzzer
	@bash tests/fuzz/run-fuzzer $(FUZZ_BUILD)/bin/ply_fuzzer $(FUZZ_SECONDS)

bench: deps
	@cmake -S . -B $(BUILD) -G Ninja -DCMAKE_BUILD_TYPE=Release -DSURFEL_BUILD_BENCH=ON >/dev/null
	@cmake --build $(BUILD) -j $$(nproc)

clean:
	rm -rf $(BUILD) $(FUZZ_BUILD) out
