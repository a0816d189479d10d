// Surfel's side of the comparisons of issues 3, 4 and 5 (bench/compare.py runs it beside the
// peers and writes the tables in bench/README.md). Run alone: build/bin/bench_core
#include "bench_common.h"
#include "surfel/render/renderer.h"
#include "surfel/surface/local_analysis.h"
#include "surfel/surface/mls.h"

namespace surfel::bench {
namespace {

void Knn(benchmark::State& state, const std::string& d) {
    const PointCloud& c = Dataset(d);
    for (auto _ : state) {
        const KdTree tree(c.positions);  // the build is part of the job
        benchmark::DoNotOptimize(tree.KnnAll(16));
    }
    state.counters["points"] = double(c.size());
}

void Normals(benchmark::State& state, const std::string& d) {
    const PointCloud& c = Dataset(d);
    NormalResult r;
    for (auto _ : state) {
        const KdTree tree(c.positions);
        NormalOptions o;
        o.k = 16;
        o.orient_k = 10;
        r = EstimateNormals(tree, o);
    }
    state.counters["points"] = double(c.size());
    state.counters["within30"] = MeshFor(d).NormalAgreement(c.positions, r.normals);
}

// MLS support (issue 19.5): theta(d) = exp(-d^2 / h^2) over the neighbours within cutoff x h.
// mls_project: the defaults (h = 2 x median spacing, cutoff 3); mls_project_c<C>: cutoff C / 10
// (fewer neighbours, the weights beyond are below exp(-C^2/100)). SURFEL_BENCH_MLS_H (a multiple
// of the default h) and SURFEL_BENCH_MLS_CUTOFF override the first row for sweeps;
// SURFEL_BENCH_MLS_MIN_NEIGHBORS sets min_neighbors (PCL projects a point with 3 or more
// neighbours within its radius, itself included; Surfel's default asks for 4).
void Mls(benchmark::State& state, const std::string& d, float cutoff) {
    const PointCloud& c = Dataset(d);
    MlsSurface::Batch b;
    float h = 0;
    float h_scale = 1.0f;
    if (const char* e = std::getenv("SURFEL_BENCH_MLS_H")) h_scale = float(std::atof(e));
    if (const char* e = std::getenv("SURFEL_BENCH_MLS_CUTOFF"); e && cutoff == 3.0f) cutoff = float(std::atof(e));
    // A given scale (h_scale != 1) is worked out before the timed loop, as the PCL rows' radius
    // is (bench_peer_pcl.cpp): each side is handed its parameter. The default rows time the
    // spacing rule (MedianSpacing over the kd-tree), a step PCL has no counterpart for.
    const float given_h = h_scale != 1.0f ? h_scale * 2.0f * MedianSpacing(KdTree(c.positions)) : 0.0f;
    for (auto _ : state) {
        const KdTree tree(c.positions);
        MlsOptions o;
        o.degree = 2;
        o.cutoff = cutoff;
        if (const char* e = std::getenv("SURFEL_BENCH_MLS_MIN_NEIGHBORS")) o.min_neighbors = std::atoi(e);
        o.h = given_h;
        const MlsSurface mls(c, tree, o);
        h = mls.h();
        b = mls.ProjectAll(c.positions);
    }
    state.counters["h"] = h;
    state.counters["radius"] = cutoff * h;
    state.counters["failed"] = double(b.failed);
    // Like PCL's output, the projected points only: a point with too few neighbours within the
    // cutoff (an isolated outlier) is not projected and stays where it was.
    std::vector<Vec3f> projected;
    for (std::size_t i = 0; i < b.positions.size(); ++i)
        if (b.normals[i] != Vec3f::Zero()) projected.push_back(b.positions[i]);
    state.counters["points"] = double(projected.size());
    const auto s = MeshFor(d).Measure(projected);
    const auto before = MeshFor(d).Measure(c.positions);
    state.counters["mesh_mean"] = s.mean;
    state.counters["mesh_rms"] = s.rms;
    state.counters["mesh_mean_rel"] = s.mean / c.Bounds().Diagonal();
    state.counters["input_mesh_mean"] = before.mean;
}

void SimplifyWith(benchmark::State& state, const std::string& d, SimplifyMethod m, int percent, bool adaptive,
                  bool positions_only = false, std::size_t target = 0,
                  SimplifyRepresentative representative = SimplifyRepresentative::kCentroid) {
    SimplifyOptions o;
    o.positions_only = positions_only;
    o.representative = representative;
    o.method = m;
    const PointCloud& input = Dataset(d);  // read before the timed loop
    o.target = target ? target : Target(d, percent);
    o.adaptive = adaptive;
    o.measure_error = false;
    SimplifyResult r;
    for (auto _ : state) r = Simplify(input, o);
    SimplifyCounters(state, d, r.cloud);
}

void RenderBench(benchmark::State& state, const std::string& d, const Camera& camera,
                 RenderQuality quality = RenderQuality::kFull) {
    const PointCloud& c = Dataset(d);
    RenderOptions o;
    ApplyRenderQuality(quality, &o);
    o.camera = camera;
    RenderResult r;
    double setup_ms = 0;
    for (auto _ : state) {
        r = Render(c, o);
        setup_ms += r.stats.setup_ms;
    }
    const RenderStats& s = r.stats;
    const double hits = double(s.hits);
    state.counters["primary"] = double(s.primary_rays);
    state.counters["shadow"] = double(s.shadow_rays);
    state.counters["hits"] = hits;
    state.counters["hit_ratio"] = s.primary_rays ? hits / double(s.primary_rays) : 0.0;
    state.counters["avg_iterations"] = s.AverageIterations();
    state.counters["fits_per_hit"] = hits > 0 ? double(s.surface.evaluations) / hits : 0.0;
    const double lookups = double(s.surface.cache_hits + s.surface.evaluations - s.surface.iterations);
    state.counters["center_cache"] = lookups > 0 ? double(s.surface.cache_hits) / lookups : 0.0;
    state.counters["setup_ms"] = state.iterations() ? setup_ms / double(state.iterations()) : 0.0;
    state.counters["rays_per_s"] = benchmark::Counter(double(s.primary_rays + s.shadow_rays),
                                                      benchmark::Counter::kIsIterationInvariantRate);
}

[[maybe_unused]] const bool kRegistered = [] {
    Register("knn16", CoreDatasets(), Knn);
    Register("normals_oriented", CoreDatasets(), Normals, 1);
    Register("mls_project", MlsDatasets(), [](benchmark::State& s, const std::string& d) { Mls(s, d, 3.0f); }, 1);
    for (float cut : {1.5f, 2.0f})
        Register("mls_project_c" + std::to_string(int(cut * 10)), MlsDatasets(),
                 [cut](benchmark::State& s, const std::string& d) { Mls(s, d, cut); }, 1);
    for (auto [m, name] : {std::pair{SimplifyMethod::kHierarchical, "hierarchical"},
                           std::pair{SimplifyMethod::kIncremental, "incremental"},
                           std::pair{SimplifyMethod::kIterative, "iterative"},
                           std::pair{SimplifyMethod::kParticle, "particle"}, std::pair{SimplifyMethod::kVoxel, "voxel"}})
        for (int pct : {1, 10})
            Register(std::string("simplify_") + name + "_" + std::to_string(pct) + "pct", SimplifyDatasets(),
                     [m = m, pct](benchmark::State& s, const std::string& d) { SimplifyWith(s, d, m, pct, false); }, 1);
    // Positions alone (no normals, radii): the output CGAL's hierarchy_simplify_point_set gives.
    for (int pct : {1, 10})
        Register("simplify_hierarchical-positions_" + std::to_string(pct) + "pct", SimplifyDatasets(),
                 [pct](benchmark::State& s, const std::string& d) {
                     SimplifyWith(s, d, SimplifyMethod::kHierarchical, pct, false, true);
                 }, 1);
    // At the count CGAL's hierarchy_simplify_point_set reaches in bench_peer_cgal (its integer
    // cluster size nearest the target; `points` there): the same output count for the error
    // comparison. person_scan at 10 %: CGAL's sizes 14 and 15 straddle the target, size 14 gives
    // 1.1 % more points than the target, so the 10pct row is not at CGAL's count (issue 19.4).
    for (int pct : {1, 10})
        Register("simplify_hierarchical-positions-cgal-count_" + std::to_string(pct) + "pct", SimplifyDatasets(),
                 [pct](benchmark::State& s, const std::string& d) {
                     const bool merged = d == "bunny_scans_merged";
                     const std::size_t count = pct == 1 ? (merged ? 3627 : 2431) : (merged ? 36122 : 24550);
                     SimplifyWith(s, d, SimplifyMethod::kHierarchical, pct, false, true, count);
                 }, 1);
    // The same with CGAL's representative, each cluster's member nearest its centroid
    // (--representative member): the same kind of output as CGAL's, a subset of the input.
    for (int pct : {1, 10})
        Register("simplify_hierarchical-members-cgal-count_" + std::to_string(pct) + "pct", SimplifyDatasets(),
                 [pct](benchmark::State& s, const std::string& d) {
                     const bool merged = d == "bunny_scans_merged";
                     const std::size_t count = pct == 1 ? (merged ? 3627 : 2431) : (merged ? 36122 : 24550);
                     SimplifyWith(s, d, SimplifyMethod::kHierarchical, pct, false, true, count,
                                  SimplifyRepresentative::kMember);
                 }, 1);
    Register("render_paper_320x250", {"bunny"},
             [](benchmark::State& s, const std::string& d) { RenderBench(s, d, PaperCamera()); });
    // Session 18: the same at RenderQuality::kPreview (surfel render --quality preview).
    Register("render_paper_preview_320x250", {"bunny"}, [](benchmark::State& s, const std::string& d) {
        RenderBench(s, d, PaperCamera(), RenderQuality::kPreview);
    });
    Register("render_loose_200x400", {"bunny"}, [](benchmark::State& s, const std::string& d) {
        RenderBench(s, d, Camera::Framing(Dataset(d).Bounds(), 200, 400));
    });
    Register("render_1024x1024", {"bunny_scans_merged"}, [](benchmark::State& s, const std::string& d) {
        RenderBench(s, d, Camera::Framing(Dataset(d).Bounds(), 1024, 1024));
    }, 1);
    return true;
}();

}  // namespace
}  // namespace surfel::bench

BENCHMARK_MAIN();
