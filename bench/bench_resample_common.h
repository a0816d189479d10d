#pragma once
// Shared by bench_resample (ours, CGAL) and bench_resample_pcl (PCL): the resampling cases of
// issue 15 item 8 and the measures applied to every output alike. A benchmark program, never
// part of the product.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <iostream>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include <sys/resource.h>

#include "bench_common.h"
#include "surfel/surface/local_analysis.h"

namespace surfel::bench {

using Clock = std::chrono::steady_clock;
inline double Ms(Clock::time_point a, Clock::time_point b) {
    return std::chrono::duration<double, std::milli>(b - a).count();
}

/// CPU time (user + system, every thread) of this process so far, ms: on a loaded machine the
/// difference around a stage measures its work where wall time does not.
inline double ProcessCpuMs() {
    rusage u{};
    getrusage(RUSAGE_SELF, &u);
    const auto ms = [](const timeval& t) { return t.tv_sec * 1e3 + t.tv_usec * 1e-3; };
    return ms(u.ru_utime) + ms(u.ru_stime);
}

/// A case: a dataset of ../shared/data and the output count as a ratio of its size.
struct ResampleCase {
    std::string name, dataset;
    double ratio = 4.0;
    std::size_t target() const { return std::size_t(std::llround(Dataset(dataset).size() * ratio)); }
};

inline const std::vector<ResampleCase>& ResampleCases() {
    static const std::vector<ResampleCase> c = {
        {"bunny-x4", "bunny", 4.0},
        {"bunny_scan-x4", "bunny_scan", 4.0},
        {"bunny_scan-half", "bunny_scan", 0.5},
        {"person_scan-half", "person_scan", 0.5},
    };
    return c;
}

inline const ResampleCase& FindResampleCase(const std::string& name) {
    for (const auto& c : ResampleCases())
        if (c.name == name) return c;
    std::cerr << "unknown --case '" << name << "'; cases:";
    for (const auto& c : ResampleCases()) std::cerr << " " << c.name;
    std::cerr << "\n";
    std::exit(2);
}

/// Area-uniform samples of a triangle mesh (a fixed portable generator: same samples every run).
inline std::vector<Vec3f> SampleMesh(const PointCloud& mesh, std::size_t n) {
    std::vector<double> cum;
    cum.reserve(mesh.triangles.size());
    double total = 0;
    for (const auto& t : mesh.triangles) {
        const Vec3f a = mesh.positions[t[0]], b = mesh.positions[t[1]], c = mesh.positions[t[2]];
        total += 0.5 * double((b - a).cross(c - a).norm());
        cum.push_back(total);
    }
    std::uint64_t s = 0x9E3779B97F4A7C15ull;
    auto uniform = [&s] {
        s = s * 6364136223846793005ull + 1442695040888963407ull;
        return double(s >> 11) * (1.0 / 9007199254740992.0);
    };
    std::vector<Vec3f> out;
    out.reserve(n);
    for (std::size_t i = 0; i < n; ++i) {
        const std::size_t k = std::lower_bound(cum.begin(), cum.end(), uniform() * total) - cum.begin();
        const auto& t = mesh.triangles[std::min(k, cum.size() - 1)];
        double u = uniform(), v = uniform();
        if (u + v > 1) u = 1 - u, v = 1 - v;
        const Vec3d a = mesh.positions[t[0]].cast<double>(), b = mesh.positions[t[1]].cast<double>(),
                    c = mesh.positions[t[2]].cast<double>();
        out.push_back((a + u * (b - a) + v * (c - a)).cast<float>());
    }
    return out;
}

/// The measures of issue 15 item 8, the same for every implementation, relative to the input's
/// bounding-box diagonal: distance to the ground-truth mesh (mean, RMS, max) and its coverage
/// (p95 of mesh samples -> nearest output point) where a mesh exists; the coefficient of
/// variation of nearest-neighbour distances; the count reached.
inline void MeasureResample(const ResampleCase& c, const std::vector<Vec3f>& out, nlohmann::json& j) {
    const BoundingBox box = Dataset(c.dataset).Bounds();
    const double diag = (box.max - box.min).norm();
    j["points"] = out.size();
    j["target"] = c.target();
    j["count_error"] = double(out.size()) / double(c.target()) - 1.0;
    if (out.size() < 2) return;
    KdTree tree(out);
    std::vector<Neighbor> nn;
    double sum = 0, sum2 = 0;
    for (const auto& p : out) {
        tree.Knn(p, 2, &nn);
        const double d = std::sqrt(double(nn.back().dist2));
        sum += d, sum2 += d * d;
    }
    const double mean = sum / out.size();
    j["nn_mean_rel"] = mean / diag;
    j["nn_cv"] = std::sqrt(std::max(0.0, sum2 / out.size() - mean * mean)) / mean;
    if (MeshOf(c.dataset).empty()) return;
    const auto s = MeshFor(c.dataset).Measure(out);
    j["mesh_mean_rel"] = s.mean / diag;
    j["mesh_rms_rel"] = s.rms / diag;
    j["mesh_max_rel"] = s.max / diag;
    if (std::getenv("SURFEL_BENCH_BREAKDOWN")) {
        // Where the distance comes from: output points grouped by the sampling spacing eta of
        // their closest input point, in quartiles of the input's eta (1 = densest input).
        const PointCloud& in = Dataset(c.dataset);
        const KdTree in_tree(in.positions);
        const std::vector<float> eta = ComputeSamplingDensity(in_tree).spacing;
        std::vector<float> sorted(eta);
        std::sort(sorted.begin(), sorted.end());
        const float q[3] = {sorted[sorted.size() / 4], sorted[sorted.size() / 2], sorted[sorted.size() * 3 / 4]};
        double dsum[4] = {}, dcount[4] = {};
        for (const auto& p : out) {
            const float e = eta[in_tree.Nearest(p).index];
            const int b = (e > q[0]) + (e > q[1]) + (e > q[2]);
            dsum[b] += MeshFor(c.dataset).Closest(p).first;
            dcount[b] += 1;
        }
        for (int b = 0; b < 4; ++b) {
            j["mesh_mean_rel_by_input_eta_quartile"].push_back(dcount[b] ? dsum[b] / dcount[b] / diag : 0.0);
            j["share_by_input_eta_quartile"].push_back(dcount[b] / double(out.size()));
        }
    }
    const std::vector<Vec3f> truth = SampleMesh(Dataset(MeshOf(c.dataset)), 200000);
    std::vector<double> cov;
    cov.reserve(truth.size());
    for (const auto& p : truth) cov.push_back(std::sqrt(double(tree.Nearest(p).dist2)) / diag);
    std::nth_element(cov.begin(), cov.begin() + cov.size() * 95 / 100, cov.end());
    j["coverage_p95_rel"] = cov[cov.size() * 95 / 100];
}

/// Parses "--side S --case C [--param X]"; exits 2 with usage on anything else.
struct ResampleArgs {
    std::string side, name;
    double param = 0;  ///< The peer's size parameter found by --search (0: search in process).
    bool search = false;
};
inline ResampleArgs ParseResampleArgs(int argc, char** argv, const char* sides) {
    ResampleArgs a;
    for (int i = 1; i < argc; ++i) {
        const std::string s = argv[i];
        if (s == "--side" && i + 1 < argc) a.side = argv[++i];
        else if (s == "--case" && i + 1 < argc) a.name = argv[++i];
        else if (s == "--param" && i + 1 < argc) a.param = std::atof(argv[++i]);
        else if (s == "--search") a.search = true;
        else a.side.clear(), i = argc;
    }
    if (a.side.empty() || a.name.empty()) {
        std::cerr << "usage: " << argv[0] << " --side " << sides << " --case NAME [--search | --param X]\n"
                  << "  --search: find the peer's size parameter that reaches the case's count and print it\n"
                  << "  --param X: run once with that parameter (the timed run, in a fresh process)\n";
        std::exit(2);
    }
    return a;
}

/// Bisection on a size parameter whose output count falls as it grows: the value in [lo, hi]
/// whose count is closest to the target after `steps` halvings (each a full untimed run).
template <class CountFn>
double SearchDecreasing(CountFn count, double lo, double hi, std::size_t target, int steps = 12) {
    double best = lo, best_err = 1e300;
    for (int i = 0; i < steps; ++i) {
        const double mid = std::sqrt(lo * hi);
        const std::size_t n = count(mid);
        const double err = std::abs(double(n) - double(target));
        if (err < best_err) best_err = err, best = mid;
        if (n > target) lo = mid; else hi = mid;
        if (err <= 0.005 * double(target)) break;
    }
    return best;
}

}  // namespace surfel::bench
