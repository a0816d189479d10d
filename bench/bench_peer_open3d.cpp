// Open3D 0.16 (Debian libopen3d-dev) on the tasks it shares with Surfel: kNN, normals +
// consistent orientation, voxel down-sampling at the same output count, and the render path a
// user would otherwise take: normals + Poisson reconstruction + a ray cast of the mesh with
// Open3D's RaycastingScene (Embree). Run through bench/compare.py.
#include <open3d/Open3D.h>
#include <embree3/rtcore.h>
#include <tbb/parallel_for.h>

#include <atomic>
#include <cmath>

#include "bench_common.h"
#include "surfel/render/renderer.h"

namespace surfel::bench {
namespace {

std::shared_ptr<open3d::geometry::PointCloud> ToOpen3D(const PointCloud& c) {
    auto p = std::make_shared<open3d::geometry::PointCloud>();
    p->points_.reserve(c.size());
    for (const Vec3f& x : c.positions) p->points_.emplace_back(x.cast<double>());
    return p;
}

PointCloud FromOpen3D(const open3d::geometry::PointCloud& p) {
    PointCloud c;
    for (const auto& x : p.points_) c.positions.push_back(x.cast<float>());
    return c;
}

void Knn(benchmark::State& state, const std::string& d) {
    const auto pcd = ToOpen3D(Dataset(d));
    for (auto _ : state) {
        open3d::geometry::KDTreeFlann tree(*pcd);
        std::vector<int> all(pcd->points_.size() * 16);
        tbb::parallel_for(std::size_t(0), pcd->points_.size(), [&](std::size_t i) {
            std::vector<int> idx;
            std::vector<double> d2;
            tree.SearchKNN(pcd->points_[i], 17, idx, d2);  // includes the point itself
            std::copy(idx.begin() + 1, idx.end(), all.begin() + i * 16);
        });
        benchmark::DoNotOptimize(all);
    }
}

void Normals(benchmark::State& state, const std::string& d) {
    std::shared_ptr<open3d::geometry::PointCloud> pcd;
    for (auto _ : state) {
        state.PauseTiming();
        pcd = ToOpen3D(Dataset(d));
        state.ResumeTiming();
        pcd->EstimateNormals(open3d::geometry::KDTreeSearchParamKNN(16));
        pcd->OrientNormalsConsistentTangentPlane(10);
    }
    std::vector<Vec3f> n;
    for (const auto& x : pcd->normals_) n.push_back(x.cast<float>());
    state.counters["within30"] = MeshFor(d).NormalAgreement(Dataset(d).positions, n);
}

double VoxelSizeFor(const open3d::geometry::PointCloud& pcd, std::size_t target) {
    const double diag = (pcd.GetMaxBound() - pcd.GetMinBound()).norm();
    double lo = diag * 1e-5, hi = diag;
    for (int i = 0; i < 40; ++i) {
        const double mid = std::sqrt(lo * hi);
        (pcd.VoxelDownSample(mid)->points_.size() >= target ? lo : hi) = mid;
    }
    return lo;  // the largest size still giving >= target points
}

void Voxel(benchmark::State& state, const std::string& d, int percent) {
    const auto pcd = ToOpen3D(Dataset(d));
    const double size = VoxelSizeFor(*pcd, Target(d, percent));
    std::shared_ptr<open3d::geometry::PointCloud> out;
    for (auto _ : state) out = pcd->VoxelDownSample(size);
    state.counters["voxel_size"] = size;
    SimplifyCounters(state, d, FromOpen3D(*out));
}

// Primary rays of `cam` against a triangle mesh with Embree (Debian's Open3D RaycastingScene
// returned no hits at all here, so the cast uses Embree directly); returns the hits.
std::size_t EmbreeCast(const open3d::geometry::TriangleMesh& mesh, const Camera& cam) {
    RTCDevice device = rtcNewDevice(nullptr);
    RTCScene scene = rtcNewScene(device);
    RTCGeometry g = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
    auto* v = static_cast<float*>(rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                                          3 * sizeof(float), mesh.vertices_.size()));
    for (std::size_t i = 0; i < mesh.vertices_.size(); ++i)
        for (int k = 0; k < 3; ++k) v[3 * i + k] = float(mesh.vertices_[i][k]);
    auto* t = static_cast<unsigned*>(rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                                                             3 * sizeof(unsigned), mesh.triangles_.size()));
    for (std::size_t i = 0; i < mesh.triangles_.size(); ++i)
        for (int k = 0; k < 3; ++k) t[3 * i + k] = unsigned(mesh.triangles_[i][k]);
    rtcCommitGeometry(g);
    rtcAttachGeometry(scene, g);
    rtcReleaseGeometry(g);
    rtcCommitScene(scene);
    const Camera::Frame frame = cam.MakeFrame();
    std::atomic<std::size_t> hits{0};
    tbb::parallel_for(0, cam.height, [&](int y) {
        RTCIntersectContext ctx;
        rtcInitIntersectContext(&ctx);
        std::size_t row = 0;
        for (int x = 0; x < cam.width; ++x) {
            const Vec3d d = frame.Direction(x + 0.5, y + 0.5);
            RTCRayHit rh{};
            rh.ray.org_x = float(cam.eye.x());
            rh.ray.org_y = float(cam.eye.y());
            rh.ray.org_z = float(cam.eye.z());
            rh.ray.dir_x = float(d.x());
            rh.ray.dir_y = float(d.y());
            rh.ray.dir_z = float(d.z());
            rh.ray.tfar = std::numeric_limits<float>::infinity();
            rh.ray.mask = ~0u;
            rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
            rtcIntersect1(scene, &ctx, &rh);
            row += rh.hit.geomID != RTC_INVALID_GEOMETRY_ID;
        }
        hits += row;
    });
    rtcReleaseScene(scene);
    rtcReleaseDevice(device);
    return hits;
}

// Normals + Poisson + Embree ray cast of the mesh, the same camera as surfel render.
void PoissonRender(benchmark::State& state, const std::string& d, const Camera& cam, int depth) {
    const PointCloud& c = Dataset(d);
    std::size_t hits = 0, triangles = 0;
    for (auto _ : state) {
        auto pcd = ToOpen3D(c);
        pcd->EstimateNormals(open3d::geometry::KDTreeSearchParamKNN(16));
        pcd->OrientNormalsConsistentTangentPlane(10);
        auto [mesh, densities] = open3d::geometry::TriangleMesh::CreateFromPointCloudPoisson(*pcd, depth);
        triangles = mesh->triangles_.size();
        hits = EmbreeCast(*mesh, cam);
    }
    state.counters["hits"] = double(hits);
    state.counters["triangles"] = double(triangles);
}

[[maybe_unused]] const bool kRegistered = [] {
    open3d::utility::SetVerbosityLevel(open3d::utility::VerbosityLevel::Error);
    Register("knn16", CoreDatasets(), Knn);
    Register("normals_oriented", CoreDatasets(), Normals, 1);
    for (int pct : {1, 10})
        Register("simplify_voxel_" + std::to_string(pct) + "pct", SimplifyDatasets(),
                 [pct](benchmark::State& s, const std::string& d) { Voxel(s, d, pct); }, 1);
    // The names and cameras of bench_core's render rows: the paper's framing, then the loose one.
    Register("render_paper_320x250", {"bunny"},
             [](benchmark::State& s, const std::string& d) { PoissonRender(s, d, PaperCamera(), 8); }, 1);
    Register("render_loose_200x400", {"bunny"}, [](benchmark::State& s, const std::string& d) {
        PoissonRender(s, d, Camera::Framing(Dataset(d).Bounds(), 200, 400), 8);
    }, 1);
    Register("render_1024x1024", {"bunny_scans_merged"},
             [](benchmark::State& s, const std::string& d) {
                 PoissonRender(s, d, Camera::Framing(Dataset(d).Bounds(), 1024, 1024), 9);
             }, 1);
    return true;
}();

}  // namespace
}  // namespace surfel::bench

BENCHMARK_MAIN();
