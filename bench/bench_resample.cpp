// Resampling (issue 15, item 8): Surfel's particle resampling against CGAL's
// edge_aware_upsample_point_set (EAR, with our normals) and wlop_simplify_and_regularize_point_set
// (WLOP), at the same output count. One process runs one side of one case and prints one JSON
// object (time, count reached, distance to the mesh, coverage, nearest-neighbour CV, peak RSS);
// bench/bench_resample.py runs the sides in interleaved processes and writes the table. PCL's
// MLS upsampling is bench_resample_pcl. The CGAL sides are compiled only when CGAL is installed.
// For measuring the particle engine's variants, side `ours` reads ResampleOptions from the
// environment: SURFEL_BENCH_ITERATIONS (iterations), SURFEL_BENCH_TOLERANCE (relax_tolerance),
// SURFEL_BENCH_SPREAD=disk|jitter (spread_disk), SURFEL_BENCH_CACHED=0|1 (cached_fits).
// Every side reports time_ms (wall) and cpu_ms (user + system CPU of all threads) of its
// resampling alone; on a loaded machine compare cpu_ms. SURFEL_BENCH_BREAKDOWN=1 (every side,
// bench_resample_pcl too) adds the mean distance to the mesh and the share of the output per
// quartile of the input's sampling spacing around each output point.
#include <cstdlib>

#include "bench_resample_common.h"
#include "surfel/io/ply.h"
#include "surfel/resample/resample.h"
#include "surfel/surface/local_analysis.h"

#ifdef SURFEL_BENCH_CGAL
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/edge_aware_upsample_point_set.h>
#include <CGAL/wlop_simplify_and_regularize_point_set.h>
#endif

using namespace surfel;
using namespace surfel::bench;

namespace {

nlohmann::json Ours(const ResampleCase& c) {
    nlohmann::json j;
    // SURFEL_BENCH_MEASURE=FILE.ply: the case's measures of a cloud resampled elsewhere (e.g. by
    // `surfel resample --method split` of two builds), no resampling here.
    if (const char* path = std::getenv("SURFEL_BENCH_MEASURE")) {
        MeasureResample(c, ReadPly(path).positions, j);
        return j;
    }
    PointCloud input;
    input.positions = Dataset(c.dataset).positions;  // points only: normals are estimated inside
    ResampleOptions o;
    o.target = c.target();
    o.measure_error = false;
    if (const char* v = std::getenv("SURFEL_BENCH_ITERATIONS")) o.iterations = std::atoi(v);
    if (const char* v = std::getenv("SURFEL_BENCH_TOLERANCE")) o.relax_tolerance = std::atof(v);
    if (const char* v = std::getenv("SURFEL_BENCH_CACHED")) o.cached_fits = std::atoi(v) != 0;
    if (const char* v = std::getenv("SURFEL_BENCH_SPREAD")) o.spread_disk = std::string(v) == "disk";
    const double c0 = ProcessCpuMs();
    const auto t0 = Clock::now();
    const ResampleResult r = Resample(input, o);
    const auto t1 = Clock::now();
    j["time_ms"] = Ms(t0, t1);
    j["cpu_ms"] = ProcessCpuMs() - c0;
    j["iterations"] = r.report.iterations;
    j["stages"] = {{"resample", Ms(t0, t1)}};
    j["peak_rss_mb"] = PeakResidentMiB();
    MeasureResample(c, r.cloud.positions, j);
    return j;
}

#ifdef SURFEL_BENCH_CGAL
using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using Point = Kernel::Point_3;
using Vector = Kernel::Vector_3;
using PointNormal = std::pair<Point, Vector>;
using Concurrency = CGAL::Parallel_if_available_tag;

std::vector<Vec3f> FromCgal(const std::vector<PointNormal>& pts) {
    std::vector<Vec3f> out;
    out.reserve(pts.size());
    for (const auto& p : pts) out.emplace_back(float(p.first.x()), float(p.first.y()), float(p.first.z()));
    return out;
}

/// EAR to the case's count. Its number_of_output_points is a lower bound it may stop short of
/// (the count reached is reported); edge_sensitivity 0 = uniform, as ours; sharpness_angle and
/// neighbor_radius at CGAL's defaults (the radius derived from the density).
nlohmann::json Ear(const ResampleCase& c) {
    nlohmann::json j;
    const PointCloud& d = Dataset(c.dataset);
    const auto t0 = Clock::now();
    const KdTree tree(d.positions);
    const NormalResult normals = EstimateNormals(tree);  // ours: EAR needs oriented normals
    const auto t1 = Clock::now();
    std::vector<PointNormal> pts;
    pts.reserve(c.target());
    for (std::size_t i = 0; i < d.size(); ++i)
        pts.emplace_back(Point(d.positions[i].x(), d.positions[i].y(), d.positions[i].z()),
                         Vector(normals.normals[i].x(), normals.normals[i].y(), normals.normals[i].z()));
    const double c2 = ProcessCpuMs();
    const auto t2 = Clock::now();
    CGAL::edge_aware_upsample_point_set<Concurrency>(
        pts, std::back_inserter(pts),
        CGAL::parameters::point_map(CGAL::First_of_pair_property_map<PointNormal>())
            .normal_map(CGAL::Second_of_pair_property_map<PointNormal>())
            .edge_sensitivity(0.0)
            .number_of_output_points(c.target()));
    const auto t3 = Clock::now();
    j["time_ms"] = Ms(t2, t3);
    j["cpu_ms"] = ProcessCpuMs() - c2;
    j["stages"] = {{"our_normals", Ms(t0, t1)}, {"ear", Ms(t2, t3)}};
    j["peak_rss_mb"] = PeakResidentMiB();
    MeasureResample(c, FromCgal(pts), j);
    return j;
}

/// WLOP to the case's share (select_percentage; downsampling only), its other parameters at
/// CGAL's defaults (neighbor_radius from the density, 35 iterations).
nlohmann::json Wlop(const ResampleCase& c) {
    nlohmann::json j;
    std::vector<Point> input;
    for (const auto& p : Dataset(c.dataset).positions) input.emplace_back(p.x(), p.y(), p.z());
    std::vector<Point> out;
    const double c0 = ProcessCpuMs();
    const auto t0 = Clock::now();
    CGAL::wlop_simplify_and_regularize_point_set<Concurrency>(
        input, std::back_inserter(out), CGAL::parameters::select_percentage(100.0 * c.ratio));
    const auto t1 = Clock::now();
    j["time_ms"] = Ms(t0, t1);
    j["cpu_ms"] = ProcessCpuMs() - c0;
    j["stages"] = {{"wlop", Ms(t0, t1)}};
    j["peak_rss_mb"] = PeakResidentMiB();
    std::vector<Vec3f> pts;
    for (const auto& p : out) pts.emplace_back(float(p.x()), float(p.y()), float(p.z()));
    MeasureResample(c, pts, j);
    return j;
}
#endif

}  // namespace

int main(int argc, char** argv) {
    const ResampleArgs a = ParseResampleArgs(argc, argv, "ours|cgal-ear|cgal-wlop");
    const ResampleCase& c = FindResampleCase(a.name);
    if (!HaveDataset(c.dataset)) {
        std::cerr << "bench_resample: " << DataDir() << "/" << c.dataset << ".ply is missing\n";
        return 1;
    }
    nlohmann::json j;
    j["case"] = c.name;
    j["side"] = a.side;
    j["input_points"] = Dataset(c.dataset).size();
    try {
        if (a.side == "ours") {
            j.update(Ours(c));
#ifdef SURFEL_BENCH_CGAL
        } else if (a.side == "cgal-ear") {
            if (c.ratio <= 1) return std::cerr << "cgal-ear only upsamples\n", 1;
            j.update(Ear(c));
        } else if (a.side == "cgal-wlop") {
            if (c.ratio >= 1) return std::cerr << "cgal-wlop only downsamples\n", 1;
            j.update(Wlop(c));
#endif
        } else {
            std::cerr << "bench_resample: side '" << a.side << "' is not built here\n";
            return 1;
        }
    } catch (const std::exception& e) {
        std::cerr << "bench_resample: " << e.what() << "\n";
        return 1;
    }
    std::cout << j.dump() << "\n";
    return 0;
}
