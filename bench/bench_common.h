#pragma once
// Shared by the benchmark programs (ours and the peers'): the datasets of ../shared/data, the
// distance of points to a ground-truth mesh, normal accuracy against that mesh, process memory.
// A benchmark program, never part of the product.

#include <benchmark/benchmark.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <functional>
#include <map>
#include <random>
#include <string>
#include <vector>

#include "surfel/base/point_cloud.h"
#include "surfel/io/ply.h"
#include "surfel/render/renderer.h"
#include "surfel/simplify/simplify.h"
#include "surfel/spatial/kd_tree.h"

namespace surfel::bench {

inline std::string DataDir() {
    if (const char* env = std::getenv("SURFEL_DATA")) return env;
    return SURFEL_SHARED_DATA_DIR;
}

/// A dataset of ../shared/data by name (without .ply), loaded once.
inline const PointCloud& Dataset(const std::string& name) {
    static std::map<std::string, PointCloud> cache;
    auto it = cache.find(name);
    if (it == cache.end()) it = cache.emplace(name, ReadPly(DataDir() + "/" + name + ".ply")).first;
    return it->second;
}

inline bool HaveDataset(const std::string& name) { return std::filesystem::exists(DataDir() + "/" + name + ".ply"); }

/// The ground-truth mesh a dataset lies on (the bunny scans and reconstruction lie on
/// bunny_mesh), or "" when there is none.
inline std::string MeshOf(const std::string& dataset) {
    if (dataset.rfind("bunny", 0) == 0) return "bunny_mesh";
    for (const char* m : {"dragon", "buddha", "armadillo", "lucy", "igea", "horse", "maxplanck"})
        if (dataset == m) return std::string(m) + "_mesh";
    // The range scans registered into their reconstruction's frame (data/README.md).
    for (const char* m : {"dragon", "buddha"})
        if (dataset == std::string(m) + "_scan") return std::string(m) + "_mesh";
    return "";
}

/// Exact point-to-triangle-mesh distances: a kd-tree over triangle centroids, then every
/// triangle whose centroid lies within (nearest centroid distance + largest circumradius).
class MeshDistance {
public:
    explicit MeshDistance(const PointCloud& mesh) : mesh_(mesh) {
        for (const auto& t : mesh.triangles) {
            const Vec3f a = mesh.positions[t[0]], b = mesh.positions[t[1]], c = mesh.positions[t[2]];
            const Vec3f g = (a + b + c) / 3.0f;
            centroids_.push_back(g);
            reach_ = std::max({reach_, (a - g).norm(), (b - g).norm(), (c - g).norm()});
            Vec3f n = (b - a).cross(c - a);
            normals_.push_back(n.norm() > 0 ? Vec3f(n.normalized()) : Vec3f::Zero());
        }
        tree_ = std::make_unique<KdTree>(centroids_);
    }
    /// Distance and the outward normal of the closest triangle.
    std::pair<double, Vec3f> Closest(const Vec3f& p) const {
        const Neighbor nn = tree_->Nearest(p);
        std::vector<Neighbor> near;
        tree_->Radius(p, std::sqrt(nn.dist2) + reach_ * 1.0001f, &near);
        double best = 1e300;
        Vec3f normal = Vec3f::Zero();
        for (const Neighbor& t : near) {
            const auto& tri = mesh_.triangles[t.index];
            const double d = PointTriangle(p.cast<double>(), mesh_.positions[tri[0]].cast<double>(),
                                           mesh_.positions[tri[1]].cast<double>(), mesh_.positions[tri[2]].cast<double>());
            if (d < best) best = d, normal = normals_[t.index];
        }
        return {best, normal};
    }
    struct Stats {
        double mean = 0, rms = 0, max = 0;
    };
    Stats Measure(std::span<const Vec3f> points) const {
        Stats s;
        for (const Vec3f& p : points) {
            const double d = Closest(p).first;
            s.mean += d;
            s.rms += d * d;
            s.max = std::max(s.max, d);
        }
        if (!points.empty()) s.mean /= points.size(), s.rms = std::sqrt(s.rms / points.size());
        return s;
    }
    /// Fraction of normals within `deg` degrees of the closest triangle's outward normal.
    double NormalAgreement(std::span<const Vec3f> points, std::span<const Vec3f> normals, double deg = 30) const {
        const double c = std::cos(deg * M_PI / 180.0);
        std::size_t ok = 0;
        for (std::size_t i = 0; i < points.size(); ++i) ok += Closest(points[i]).second.dot(normals[i]) >= c;
        return points.empty() ? 0.0 : double(ok) / double(points.size());
    }

private:
    static double PointTriangle(const Vec3d& p, const Vec3d& a, const Vec3d& b, const Vec3d& c) {
        // Ericson, Real-Time Collision Detection, 5.1.5.
        const Vec3d ab = b - a, ac = c - a, ap = p - a;
        const double d1 = ab.dot(ap), d2 = ac.dot(ap);
        if (d1 <= 0 && d2 <= 0) return (p - a).norm();
        const Vec3d bp = p - b;
        const double d3 = ab.dot(bp), d4 = ac.dot(bp);
        if (d3 >= 0 && d4 <= d3) return (p - b).norm();
        const double vc = d1 * d4 - d3 * d2;
        if (vc <= 0 && d1 >= 0 && d3 <= 0) return (p - (a + ab * (d1 / (d1 - d3)))).norm();
        const Vec3d cp = p - c;
        const double d5 = ab.dot(cp), d6 = ac.dot(cp);
        if (d6 >= 0 && d5 <= d6) return (p - c).norm();
        const double vb = d5 * d2 - d1 * d6;
        if (vb <= 0 && d2 >= 0 && d6 <= 0) return (p - (a + ac * (d2 / (d2 - d6)))).norm();
        const double va = d3 * d6 - d5 * d4;
        if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0)
            return (p - (b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6))))).norm();
        const double denom = 1.0 / (va + vb + vc);
        return (p - (a + ab * (vb * denom) + ac * (vc * denom))).norm();
    }
    const PointCloud& mesh_;
    std::vector<Vec3f> centroids_, normals_;
    float reach_ = 0;
    std::unique_ptr<KdTree> tree_;
};

inline const MeshDistance& MeshFor(const std::string& dataset) {
    static std::map<std::string, std::unique_ptr<MeshDistance>> cache;
    const std::string mesh = MeshOf(dataset);
    auto& slot = cache[mesh];
    if (!slot) slot = std::make_unique<MeshDistance>(Dataset(mesh));
    return *slot;
}

/// Points spread over the surface a dataset samples, for coverage: kCoverSamples points on the
/// ground-truth mesh, uniform by area (a fixed seed), or the dataset's own points where it has no
/// mesh (person_scan).
inline const std::vector<Vec3f>& SurfaceSamples(const std::string& dataset) {
    static std::map<std::string, std::vector<Vec3f>> cache;
    auto& s = cache[dataset];
    if (!s.empty()) return s;
    if (MeshOf(dataset).empty()) return s = Dataset(dataset).positions;
    constexpr std::size_t kCoverSamples = 200000;
    const PointCloud& mesh = Dataset(MeshOf(dataset));
    std::vector<double> cum;
    double total = 0;
    for (const auto& t : mesh.triangles) {
        const Vec3f a = mesh.positions[t[0]], b = mesh.positions[t[1]], c = mesh.positions[t[2]];
        total += 0.5 * double((b - a).cross(c - a).norm());
        cum.push_back(total);
    }
    std::mt19937_64 rng(19);
    std::uniform_real_distribution<double> u(0.0, 1.0);
    for (std::size_t i = 0; i < kCoverSamples; ++i) {
        const std::size_t t = std::size_t(std::lower_bound(cum.begin(), cum.end(), u(rng) * total) - cum.begin());
        const auto& tri = mesh.triangles[std::min(t, mesh.triangles.size() - 1)];
        double r1 = std::sqrt(u(rng)), r2 = u(rng);
        const Vec3f a = mesh.positions[tri[0]], b = mesh.positions[tri[1]], c = mesh.positions[tri[2]];
        s.push_back(float(1 - r1) * a + float(r1 * (1 - r2)) * b + float(r1 * r2) * c);
    }
    return s;
}

/// Coverage (issue 19.4): the 95th percentile over SurfaceSamples of the distance to the nearest
/// output point, relative to the input's bounding-box diagonal. A result that leaves part of the
/// surface bare, or bunches its points, has a high p95 whatever its mean error.
inline double CoverageP95(const std::string& dataset, std::span<const Vec3f> out) {
    if (out.empty()) return 0.0;
    const KdTree tree(out);
    const auto& samples = SurfaceSamples(dataset);
    std::vector<float> d(samples.size());
    for (std::size_t i = 0; i < samples.size(); ++i) d[i] = std::sqrt(tree.Nearest(samples[i]).dist2);
    const auto k = d.begin() + std::ptrdiff_t(d.size() * 95 / 100);
    std::nth_element(d.begin(), k, d.end());
    return double(*k) / double(Dataset(dataset).Bounds().Diagonal());
}

/// Simplification targets of issue 5: 1 % and 10 % of the input.
inline std::size_t Target(const std::string& dataset, int percent) { return Dataset(dataset).size() * percent / 100; }

/// Adds quality counters for a simplified cloud: count, Delta_avg/max relative (surfel's
/// metric, the same for every implementation) and the distance to the ground-truth mesh.
inline void SimplifyCounters(benchmark::State& state, const std::string& dataset, const PointCloud& out) {
    state.counters["points"] = double(out.size());
    SurfaceErrorOptions eo;
    eo.max_samples = 20000;
    const SurfaceError e = MeasureSurfaceError(Dataset(dataset), out, eo);
    state.counters["err_avg_rel"] = e.avg_relative();
    state.counters["err_avg_ps_rel"] = e.avg_per_sample_relative();
    eo.degree = 1;  // the notes' own measure: a linear basis for the projection onto S'
    state.counters["err_avg_lin_rel"] = MeasureSurfaceError(Dataset(dataset), out, eo).avg_relative();
    state.counters["err_max_rel"] = e.max_relative();
    state.counters["cover_p95"] = CoverageP95(dataset, out.positions);
    if (!MeshOf(dataset).empty()) {
        const auto s = MeshFor(dataset).Measure(out.positions);
        state.counters["mesh_mean"] = s.mean;
        state.counters["mesh_max"] = s.max;
        if (out.has_normals()) state.counters["within30"] = MeshFor(dataset).NormalAgreement(out.positions, out.normals);
    }
    state.counters["peak_rss_mb"] = PeakResidentMiB();
}

/// Datasets of issue 3 (core) and issue 5 (simplification).
inline const std::vector<std::string>& CoreDatasets() {
    static const std::vector<std::string> d = {"bunny", "bunny_scans_merged"};
    return d;
}
/// MLS (issue 19.5): the bunny, every raw range scan that has a mesh (three of the bunny, the
/// merged ten, the dragon's and the buddha's; person_scan has none).
inline const std::vector<std::string>& MlsDatasets() {
    static const std::vector<std::string> d = {"bunny",         "bunny_scan",  "bunny_scan_045",
                                               "bunny_scans_merged", "dragon_scan", "buddha_scan"};
    return d;
}
inline const std::vector<std::string>& SimplifyDatasets() {
    static const std::vector<std::string> d = {"bunny_scans_merged", "person_scan"};
    return d;
}

/// Registers fn for each dataset that exists, named "task/dataset[/suffix]".
inline void Register(const std::string& task, const std::vector<std::string>& datasets,
                     std::function<void(benchmark::State&, const std::string&)> fn, int iterations = 0) {
    for (const auto& d : datasets) {
        if (!HaveDataset(d)) continue;
        auto* b = benchmark::RegisterBenchmark((task + "/" + d).c_str(), [fn, d](benchmark::State& s) { fn(s, d); });
        // cpu_time: every thread of the process (ours use two, CGAL's simplification one), the
        // figure to read when the shared machine is loaded and wall-clock times swing.
        b->Unit(benchmark::kMillisecond)->UseRealTime()->MeasureProcessCPUTime();
        if (iterations) b->Iterations(iterations);
    }
}

// The paper's framing (Adamson & Alexa 2003, section 6: 42,463 of 80,000 rays hit their rabbit):
// 320 x 250 = 80,000 rays, the eye on the +z axis through the bunny's bounding-box centre, 0.2515
// in front of it, fovy 40 (the default), the default light (over the camera's left shoulder) with
// shadows. The same image as
//   surfel render bunny.ply --width 320 --height 250 --eye -0.0168,0.1102,0.25
//       --target -0.0168,0.1102,-0.0015 -o bunny.exr --json
// (32,856 hits: 41 %). The loose framing (Camera::Framing, 89 % misses) is the second row.
inline Camera PaperCamera() {
    Camera c;
    c.width = 320;
    c.height = 250;
    c.eye = Vec3d(-0.0168, 0.1102, 0.25);
    c.target = Vec3d(-0.0168, 0.1102, -0.0015);
    return c;
}

}  // namespace surfel::bench
