// Issue 19.4, session 12 (hierarchical helper): one process, one PLY read, then `reps` calls of
// hierarchical Simplify (positions only unless told, no error report), each printed as wall ms,
// process CPU ms (getrusage, all threads) and minor page faults of the call alone. The first call
// of a fresh process is bench_core's timed call. Built against a build directory's libraries by
// bench/issue19_hierarchical_h12.sh (not part of the CMake build).
// Usage: issue19_hierarchical_call <cloud.ply> <target> [reps = 1] [positions_only = 1]
#include <sys/resource.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>

#include "surfel/io/ply.h"
#include "surfel/simplify/simplify.h"

namespace {

double CpuMs(const rusage& r) {
    return (r.ru_utime.tv_sec + r.ru_stime.tv_sec) * 1e3 + (r.ru_utime.tv_usec + r.ru_stime.tv_usec) * 1e-3;
}

}  // namespace

int main(int argc, char** argv) {
    if (argc < 3) {
        std::fprintf(stderr, "usage: %s <cloud.ply> <target> [reps] [positions_only]\n", argv[0]);
        return 2;
    }
    const surfel::PointCloud input = surfel::ReadPly(argv[1]);
    surfel::SimplifyOptions o;
    o.method = surfel::SimplifyMethod::kHierarchical;
    o.target = std::strtoul(argv[2], nullptr, 10);
    o.positions_only = argc > 4 ? std::atoi(argv[4]) != 0 : true;
    o.measure_error = false;
    const int reps = argc > 3 ? std::atoi(argv[3]) : 1;
    for (int r = 0; r < reps; ++r) {
        rusage a, b;
        getrusage(RUSAGE_SELF, &a);
        const auto t0 = std::chrono::steady_clock::now();
        const surfel::SimplifyResult result = surfel::Simplify(input, o);
        const auto t1 = std::chrono::steady_clock::now();
        getrusage(RUSAGE_SELF, &b);
        std::printf("wall %.2f cpu %.2f faults %ld points %zu\n",
                    std::chrono::duration<double, std::milli>(t1 - t0).count(), CpuMs(b) - CpuMs(a),
                    b.ru_minflt - a.ru_minflt, result.cloud.size());
    }
}
