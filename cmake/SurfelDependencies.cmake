# Every dependency comes from Debian 12's packages. A missing one stops configure with the name
# of the package that provides it (scripts/install-deps installs them all).
include_guard(GLOBAL)
find_package(PkgConfig)
if(NOT PkgConfig_FOUND)
    message(FATAL_ERROR "pkg-config not found: apt-get install pkg-config (or run scripts/install-deps)")
endif()

macro(surfel_require_package name debian)
    find_package(${name} ${ARGN} QUIET)
    if(NOT ${name}_FOUND)
        message(FATAL_ERROR "${name} not found: apt-get install ${debian} (or run scripts/install-deps)")
    endif()
endmacro()

macro(surfel_require_pkgconfig prefix module debian)
    pkg_check_modules(${prefix} QUIET IMPORTED_TARGET ${module})
    if(NOT ${prefix}_FOUND)
        message(FATAL_ERROR "${module} (pkg-config) not found: apt-get install ${debian} (or run scripts/install-deps)")
    endif()
endmacro()

surfel_require_package(Eigen3 libeigen3-dev 3.3 NO_MODULE)
surfel_require_package(TBB libtbb-dev CONFIG)
surfel_require_package(embree libembree-dev 3)
surfel_require_package(CLI11 libcli11-dev CONFIG)
surfel_require_package(spdlog libspdlog-dev CONFIG)
surfel_require_package(Threads libc6-dev)
# FLANN has no CMake config on Debian; pkg-config works (it pulls lz4).
surfel_require_pkgconfig(FLANN flann libflann-dev)
# flann.pc also lists libflann, libflann_cpp, HDF5 and MPI (its optional HDF5 file support). We use
# only the header-only kd-tree, which calls LZ4. Linking just LZ4 keeps HDF5's folder out of every
# binary's RUNPATH, where the loader would first look for each of the ~60 libraries at start-up
# (issue 19.2: ~10 failed opens per library).
set_property(TARGET PkgConfig::FLANN PROPERTY INTERFACE_LINK_LIBRARIES "${pkgcfg_lib_FLANN_lz4}")
# OpenImageIO's CMake config points at /usr/include/opencv4 and breaks generation; use pkg-config.
surfel_require_pkgconfig(OIIO OpenImageIO libopenimageio-dev)
# OpenEXR alone, for the EXR plugin (the render's output without OpenImageIO's ~260 libraries).
surfel_require_pkgconfig(OPENEXR OpenEXR libopenexr-dev)

if(SURFEL_BUILD_TESTS)
    surfel_require_package(GTest libgtest-dev)
endif()
if(SURFEL_BUILD_BENCH)
    surfel_require_package(benchmark libbenchmark-dev)
endif()

# The service's dependencies (gRPC needs protobuf-compiler-grpc installed to configure).
# OFF builds only the core (the fuzzer build does that).
option(SURFEL_REQUIRE_SERVICE_DEPS "Build the service, worker and client (gRPC, Protobuf, SQLiteCpp, ...)" ON)
if(SURFEL_REQUIRE_SERVICE_DEPS)
    surfel_require_package(Protobuf "libprotobuf-dev protobuf-compiler")
    surfel_require_package(gRPC "libgrpc++-dev protobuf-compiler-grpc" CONFIG)
    surfel_require_package(SQLiteCpp libsqlitecpp-dev CONFIG)
    surfel_require_pkgconfig(PQ libpq libpq-dev)
    surfel_require_package(OpenSSL libssl-dev)
    surfel_require_package(nlohmann_json nlohmann-json3-dev 3 CONFIG)
    surfel_require_package(prometheus-cpp prometheus-cpp-dev CONFIG)
endif()
