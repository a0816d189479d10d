// Booleans on point sets (issue 14, item 10): Surfel's Boolean against the path a user would
// take without it — Open3D normals + Poisson reconstruction of each input, CGAL's corefinement
// boolean of the two meshes, the result sampled back to the same number of points.
//
// One process runs one side of one case (`--side ours|peer --case NAME`) and prints one JSON
// object: stage times, the output count, peak RSS and, for the analytic cases, the distance of
// the output to the exact boundary and the coverage of that boundary. bench/bench_boolean.py
// runs the sides in interleaved processes and writes the table. A benchmark program, never part
// of the product; the peer side is compiled only when CGAL and Open3D are installed.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <functional>
#include <iostream>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "surfel/base/error.h"
#include "surfel/base/point_cloud.h"
#include "surfel/base/shapes.h"
#include "surfel/boolean/boolean.h"
#include "surfel/io/ply.h"
#include "surfel/simplify/simplify.h"
#include "surfel/spatial/kd_tree.h"

#ifdef SURFEL_BENCH_PEERS
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Polygon_mesh_processing/corefinement.h>
#include <CGAL/Surface_mesh.h>

#include <open3d/geometry/PointCloud.h>
#include <open3d/geometry/TriangleMesh.h>
#include <open3d/geometry/KDTreeSearchParam.h>
#endif

namespace {

using namespace surfel;
using Clock = std::chrono::steady_clock;

double Ms(Clock::time_point a, Clock::time_point b) { return std::chrono::duration<double, std::milli>(b - a).count(); }

/// CPU time of the whole process (every thread), ms: on a shared machine the wall clock counts
/// other sessions' load, this does not.
double ProcessCpuMs() {
    timespec ts{};
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
    return 1e3 * static_cast<double>(ts.tv_sec) + 1e-6 * static_cast<double>(ts.tv_nsec);
}

std::string DataDir() {
    if (const char* env = std::getenv("SURFEL_DATA")) return env;
    return SURFEL_SHARED_DATA_DIR;
}

/// Signed distance of an analytic solid (negative inside), in its own frame.
using Sdf = std::function<double(const Vec3d&)>;

double SphereSd(const Vec3d& x, double r) { return x.norm() - r; }
double BoxSd(const Vec3d& x, double s) {
    const Vec3d q = x.cwiseAbs() - Vec3d::Constant(s);
    return q.cwiseMax(0.0).norm() + std::min(q.maxCoeff(), 0.0);
}

struct Case {
    std::string name;
    PointCloud a, b;  ///< B in its own frame.
    BooleanOp op = BooleanOp::kUnion;
    Similarity transform;  ///< Places B in A's frame.
    int poisson_depth = 8;
    /// Analytic cases: the signed distances of A and of B (in A's frame) and dense samples of
    /// each solid's surface (in A's frame) to measure coverage of the exact boundary.
    Sdf sd_a, sd_b;
    PointCloud dense_a, dense_b;
};

Similarity Place(const Vec3d& axis, double degrees, const Vec3d& translation, double scale = 1.0) {
    Similarity s;
    s.rotation = Eigen::AngleAxisd(degrees * M_PI / 180.0, axis.normalized()).toRotationMatrix();
    s.translation = translation;
    s.scale = scale;
    return s;
}

PointCloud Positions(PointCloud c) {
    PointCloud out;
    out.positions = std::move(c.positions);
    return out;
}

Case MakeCase(const std::string& name) {
    Case c;
    c.name = name;
    auto sphere_box = [&](std::size_t n, BooleanOp op) {
        ShapeOptions so;
        so.points = n;
        c.a = SampleShape(Shape::kSphere, so);  // unit sphere; points only, as a scan gives them
        so.scale = 0.6;
        so.seed = 2;
        c.b = SampleShape(Shape::kBox, so);
        c.op = op;
        c.transform = Place(Vec3d(0, 0, 1), 0, Vec3d(0.55, 0.45, 0.35));
        c.poisson_depth = n > 100000 ? 9 : 8;
        const Similarity t = c.transform;
        c.sd_a = [](const Vec3d& x) { return SphereSd(x, 1.0); };
        c.sd_b = [t](const Vec3d& x) { return BoxSd(x - t.translation, 0.6); };
        ShapeOptions dense;
        dense.points = 400000;
        dense.seed = 7;
        c.dense_a = SampleShape(Shape::kSphere, dense);
        dense.scale = 0.6;
        c.dense_b = SampleShape(Shape::kBox, dense);
        for (auto& p : c.dense_b.positions) p += t.translation.cast<float>();
    };
    auto scan = [&](const std::string& file) {
        PointCloud p = Positions(ReadPly(DataDir() + "/" + file + ".ply"));
        return p;
    };
    auto copy_placed = [&](const PointCloud& a, double deg, double shift) {
        const BoundingBox box = a.Bounds();
        const Vec3d ext = (box.max - box.min).cast<double>();
        const Vec3d centre = ((box.max + box.min) * 0.5f).cast<double>();
        // Rotate about the centre, then shift by a share of the extent: x' = R(x - c) + c + d.
        const Eigen::Matrix3d r = Eigen::AngleAxisd(deg * M_PI / 180.0, Vec3d(0.3, 1, 0.2).normalized()).toRotationMatrix();
        return Place(Vec3d(0.3, 1, 0.2), deg, centre - r * centre + shift * ext);
    };
    if (name == "sphere-box-35k") sphere_box(35000, BooleanOp::kDifference);
    else if (name == "sphere-box-350k") sphere_box(350000, BooleanOp::kDifference);
    else if (name == "bunny-union-bunny" || name == "bunny-minus-bunny") {
        c.a = scan("bunny");
        c.b = c.a;
        c.op = name == "bunny-union-bunny" ? BooleanOp::kUnion : BooleanOp::kDifference;
        c.transform = copy_placed(c.a, 35, 0.25);
    } else if (name == "dragon-union-dragon") {
        c.a = scan("dragon");
        c.b = c.a;
        c.op = BooleanOp::kUnion;
        c.transform = copy_placed(c.a, 60, 0.2);
    } else if (name == "bunny-minus-sphere") {
        c.a = scan("bunny");
        const BoundingBox box = c.a.Bounds();
        const double diag = (box.max - box.min).norm();
        ShapeOptions so;
        so.points = c.a.size();
        so.seed = 3;
        c.b = SampleShape(Shape::kSphere, so);  // unit sphere, placed by a scale
        const Vec3d centre = ((box.max + box.min) * 0.5f).cast<double>();
        c.transform = Place(Vec3d(0, 0, 1), 0, centre + Vec3d(0.15, 0.2, 0.1) * diag, 0.22 * diag);
        c.op = BooleanOp::kDifference;
    } else {
        throw Error(ErrorCode::kInvalidArgument, "--case: unknown case '" + name + "'");
    }
    return c;
}

/// Signed distance of the boolean solid: min for a union, max for an intersection, max(a, −b)
/// for a difference. Near the boundary and away from the curve its magnitude is the distance to
/// the exact boundary; near the curve it is a lower bound (the same for both sides).
double CsgSd(const Case& c, const Vec3d& x) {
    const double a = c.sd_a(x), b = c.sd_b(x);
    switch (c.op) {
        case BooleanOp::kUnion: return std::min(a, b);
        case BooleanOp::kIntersection: return std::max(a, b);
        case BooleanOp::kDifference: return std::max(a, -b);
        case BooleanOp::kReverseDifference: return std::max(b, -a);
    }
    return 0;
}

/// Distance figures relative to A's bounding-box diagonal (analytic cases only).
void Accuracy(const Case& c, const std::vector<Vec3f>& out, nlohmann::json& j) {
    if (!c.sd_a || out.empty()) return;
    const BoundingBox box = c.a.Bounds();
    const double diag = (box.max - box.min).norm();
    std::vector<double> d;
    d.reserve(out.size());
    for (const auto& p : out) d.push_back(std::abs(CsgSd(c, p.cast<double>())) / diag);
    std::sort(d.begin(), d.end());
    double mean = 0;
    for (double v : d) mean += v;
    j["dist_mean_rel"] = mean / d.size();
    j["dist_p95_rel"] = d[d.size() * 95 / 100];
    j["dist_max_rel"] = d.back();
    // Coverage: dense samples of the exact boundary (each solid's surface where the other keeps
    // it) -> the nearest output point.
    std::vector<Vec3f> truth;
    const double eps = 1e-9;
    for (const auto& p : c.dense_a.positions) {
        const double b = c.sd_b(p.cast<double>());
        const bool keep = c.op == BooleanOp::kUnion || c.op == BooleanOp::kDifference ? b > eps : b < -eps;
        if (keep) truth.push_back(p);
    }
    for (const auto& p : c.dense_b.positions) {
        const double a = c.sd_a(p.cast<double>());
        const bool keep = c.op == BooleanOp::kUnion || c.op == BooleanOp::kReverseDifference ? a > eps : a < -eps;
        if (keep) truth.push_back(p);
    }
    KdTree tree(out);
    std::vector<double> cov;
    cov.reserve(truth.size());
    for (const auto& p : truth) cov.push_back(std::sqrt(tree.Nearest(p).dist2) / diag);
    std::sort(cov.begin(), cov.end());
    j["coverage_p95_rel"] = cov[cov.size() * 95 / 100];
    j["coverage_max_rel"] = cov.back();
}

/// FNV-1a over the output's positions, normals, radii and extras: equal hashes, equal output (to
/// check that a speed-up leaves the result as it was).
std::string OutputHash(const PointCloud& cloud) {
    std::uint64_t h = 1469598103934665603ull;
    auto add = [&](const void* data, std::size_t bytes) {
        const auto* p = static_cast<const unsigned char*>(data);
        for (std::size_t i = 0; i < bytes; ++i) h = (h ^ p[i]) * 1099511628211ull;
    };
    add(cloud.positions.data(), cloud.positions.size() * sizeof(Vec3f));
    add(cloud.normals.data(), cloud.normals.size() * sizeof(Vec3f));
    add(cloud.radii.data(), cloud.radii.size() * sizeof(float));
    for (const auto& e : cloud.extras) add(e.values.data(), e.values.size() * sizeof(double));
    char buf[17];
    std::snprintf(buf, sizeof buf, "%016llx", static_cast<unsigned long long>(h));
    return buf;
}

nlohmann::json RunOurs(const Case& c) {
    nlohmann::json j;
    const auto t0 = Clock::now();
    const double cpu0 = ProcessCpuMs();
    BooleanOptions options;
    options.transform = c.transform;
    const BooleanResult r = Boolean(c.a, c.b, c.op, options);
    const auto t1 = Clock::now();
    j["time_ms"] = Ms(t0, t1);
    j["cpu_ms"] = ProcessCpuMs() - cpu0;
    j["stages"] = {{"boolean", Ms(t0, t1)}};
    j["points"] = r.cloud.size();
    j["output_hash"] = OutputHash(r.cloud);
    j["curve_samples"] = r.report.curve_samples;
    j["mean_newton_iterations"] = r.report.mean_newton_iterations;
    j["queries_saved_share"] = r.report.queries_saved_share;
    j["peak_rss_mb"] = PeakResidentMiB();
    Accuracy(c, r.cloud.positions, j);
    return j;
}

#ifdef SURFEL_BENCH_PEERS
using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using Mesh = CGAL::Surface_mesh<Kernel::Point_3>;
namespace PMP = CGAL::Polygon_mesh_processing;

/// Open3D normals (k = 16), their orientation (Open3D's consistent tangent plane, k = 10) and
/// Poisson reconstruction at `depth`; adds each stage's time to `stages`.
std::shared_ptr<open3d::geometry::TriangleMesh> Poisson(const std::vector<Vec3f>& pts, int depth,
                                                        std::map<std::string, double>& stages) {
    auto pcd = std::make_shared<open3d::geometry::PointCloud>();
    pcd->points_.reserve(pts.size());
    for (const auto& p : pts) pcd->points_.emplace_back(p.cast<double>());
    const auto t0 = Clock::now();
    pcd->EstimateNormals(open3d::geometry::KDTreeSearchParamKNN(16));
    const auto t1 = Clock::now();
    pcd->OrientNormalsConsistentTangentPlane(10);
    const auto t2 = Clock::now();
    auto [mesh, densities] = open3d::geometry::TriangleMesh::CreateFromPointCloudPoisson(*pcd, depth);
    const auto t3 = Clock::now();
    stages["o3d_normals"] += Ms(t0, t1);
    stages["o3d_orient"] += Ms(t1, t2);
    stages["o3d_poisson"] += Ms(t2, t3);
    return mesh;
}

Mesh ToCgal(const open3d::geometry::TriangleMesh& m) {
    Mesh out;
    std::vector<Mesh::Vertex_index> v;
    v.reserve(m.vertices_.size());
    for (const auto& p : m.vertices_) v.push_back(out.add_vertex(Kernel::Point_3(p.x(), p.y(), p.z())));
    for (const auto& t : m.triangles_) out.add_face(v[t[0]], v[t[1]], v[t[2]]);
    return out;
}

open3d::geometry::TriangleMesh ToOpen3d(const Mesh& m) {
    open3d::geometry::TriangleMesh out;
    std::map<Mesh::Vertex_index, int> index;
    for (auto vi : m.vertices()) {
        index[vi] = int(out.vertices_.size());
        const auto& p = m.point(vi);
        out.vertices_.emplace_back(p.x(), p.y(), p.z());
    }
    for (auto f : m.faces()) {
        Eigen::Vector3i t;
        int k = 0;
        for (auto h : CGAL::halfedges_around_face(m.halfedge(f), m)) {
            if (k < 3) t[k] = index[m.target(h)];
            ++k;
        }
        if (k == 3) out.triangles_.push_back(t);
    }
    return out;
}

nlohmann::json RunPeer(const Case& c, std::size_t count) {
    nlohmann::json j;
    const auto t0 = Clock::now();
    std::vector<Vec3f> b_world;
    b_world.reserve(c.b.size());
    for (const auto& p : c.b.positions)
        b_world.push_back((c.transform.scale * (c.transform.rotation * p.cast<double>()) + c.transform.translation).cast<float>());
    std::map<std::string, double> stages;
    auto ma = Poisson(c.a.positions, c.poisson_depth, stages);
    auto mb = Poisson(b_world, c.poisson_depth, stages);
    const auto t1 = Clock::now();
    Mesh a = ToCgal(*ma), b = ToCgal(*mb), out;
    bool ok = false;
    switch (c.op) {
        case BooleanOp::kUnion: ok = PMP::corefine_and_compute_union(a, b, out); break;
        case BooleanOp::kIntersection: ok = PMP::corefine_and_compute_intersection(a, b, out); break;
        case BooleanOp::kDifference: ok = PMP::corefine_and_compute_difference(a, b, out); break;
        case BooleanOp::kReverseDifference: ok = PMP::corefine_and_compute_difference(b, a, out); break;
    }
    const auto t2 = Clock::now();
    std::vector<Vec3f> pts;
    if (ok) {
        const auto sampled = ToOpen3d(out).SamplePointsUniformly(count);
        for (const auto& p : sampled->points_) pts.push_back(p.cast<float>());
    }
    const auto t3 = Clock::now();
    j["time_ms"] = Ms(t0, t3);
    stages["cgal_corefine"] = Ms(t1, t2);
    stages["sample"] = Ms(t2, t3);
    j["stages"] = stages;
    j["ok"] = ok;
    j["mesh_triangles"] = {ma->triangles_.size(), mb->triangles_.size(), out.number_of_faces()};
    j["points"] = pts.size();
    j["peak_rss_mb"] = PeakResidentMiB();
    Accuracy(c, pts, j);
    return j;
}
#endif

int Usage() {
    std::cerr << "usage: bench_boolean --side ours|peer --case NAME [--count N]\n"
                 "  cases: sphere-box-35k sphere-box-350k bunny-union-bunny bunny-minus-bunny\n"
                 "         dragon-union-dragon bunny-minus-sphere\n"
                 "  --count: output points the peer samples its mesh to (ours' count)\n"
                 "  the peer side needs CGAL and Open3D at build time\n";
    return 2;
}

}  // namespace

int main(int argc, char** argv) {
    std::string side, name;
    std::size_t count = 0;
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        if (a == "--side" && i + 1 < argc) side = argv[++i];
        else if (a == "--case" && i + 1 < argc) name = argv[++i];
        else if (a == "--count" && i + 1 < argc) count = std::strtoull(argv[++i], nullptr, 10);
        else return Usage();
    }
    if (name.empty() || (side != "ours" && side != "peer")) return Usage();
    try {
        const auto t0 = Clock::now();
        const Case c = MakeCase(name);
        nlohmann::json j;
        j["case"] = name;
        j["side"] = side;
        j["op"] = BooleanOpName(c.op);
        j["input_points"] = {c.a.size(), c.b.size()};
        j["setup_ms"] = Ms(t0, Clock::now());
        if (side == "ours") {
            j.update(RunOurs(c));
        } else {
#ifdef SURFEL_BENCH_PEERS
            if (count == 0) count = c.a.size() + c.b.size();
            j.update(RunPeer(c, count));
#else
            (void)count;
            std::cerr << "bench_boolean: built without CGAL + Open3D; no peer side\n";
            return 1;
#endif
        }
        std::cout << j.dump() << "\n";
    } catch (const std::exception& e) {
        std::cerr << "bench_boolean: " << e.what() << "\n";
        return 1;
    }
    return 0;
}
