// PLY read/write throughput on a ~100 MB binary file (positions, normals, colours, radius:
// 31 bytes per point, 3.3 M points). Run: build/bin/bench_io
#include <benchmark/benchmark.h>

#include "surfel/base/shapes.h"
#include "surfel/io/ply.h"

namespace {

const std::string& BigPly(surfel::PlyFormat format) {
    static std::string binary, ascii;
    std::string& s = format == surfel::PlyFormat::kAscii ? ascii : binary;
    if (s.empty()) {
        surfel::ShapeOptions o;
        o.points = format == surfel::PlyFormat::kAscii ? 1'000'000 : 3'300'000;
        o.normals = true;
        o.noise = 0.001;
        surfel::PointCloud c = surfel::SampleShape(surfel::Shape::kTorus, o);
        c.colors.assign(c.size(), {0.2f, 0.4f, 0.6f, 1.0f});
        c.radii.assign(c.size(), 0.001f);
        surfel::PlyWriteOptions w;
        w.format = format;
        s = surfel::FormatPly(c, w);
    }
    return s;
}

void BM_ReadBinaryPly(benchmark::State& state) {
    const std::string& data = BigPly(surfel::PlyFormat::kBinaryLittleEndian);
    for (auto _ : state) benchmark::DoNotOptimize(surfel::ParsePly(data, "bench.ply"));
    state.SetBytesProcessed(std::int64_t(state.iterations()) * std::int64_t(data.size()));
    state.counters["MB"] = double(data.size()) / 1e6;
}
BENCHMARK(BM_ReadBinaryPly)->Unit(benchmark::kMillisecond)->MinTime(2.0);

void BM_ReadAsciiPly(benchmark::State& state) {
    const std::string& data = BigPly(surfel::PlyFormat::kAscii);
    for (auto _ : state) benchmark::DoNotOptimize(surfel::ParsePly(data, "bench.ply"));
    state.SetBytesProcessed(std::int64_t(state.iterations()) * std::int64_t(data.size()));
}
BENCHMARK(BM_ReadAsciiPly)->Unit(benchmark::kMillisecond);

void BM_WriteBinaryPly(benchmark::State& state) {
    const surfel::PointCloud c = surfel::ParsePly(BigPly(surfel::PlyFormat::kBinaryLittleEndian), "bench.ply");
    std::size_t bytes = 0;
    for (auto _ : state) {
        std::string out = surfel::FormatPly(c);
        bytes = out.size();
        benchmark::DoNotOptimize(out);
    }
    state.SetBytesProcessed(std::int64_t(state.iterations()) * std::int64_t(bytes));
}
BENCHMARK(BM_WriteBinaryPly)->Unit(benchmark::kMillisecond);

}  // namespace

BENCHMARK_MAIN();
