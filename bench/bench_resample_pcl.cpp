// Resampling (issue 15, item 8): PCL's MovingLeastSquares upsampling in its three modes at the
// case's output count. PCL cannot be asked for a count (PointCloudLibrary/pcl#5439), so
// `--search` bisects each mode's size parameter over untimed runs and prints it; the timed run
// is a fresh process with `--param` (bench/bench_resample.py does both). MLS itself as
// bench_peer_pcl: order 2, search radius 3h and Gaussian h^2 with Surfel's default h.
#include <pcl/point_cloud.h>
#include <pcl/point_types.h>
#include <pcl/search/kdtree.h>
#include <pcl/surface/mls.h>

#include "bench_resample_common.h"
#include "surfel/surface/local_analysis.h"

using namespace surfel;
using namespace surfel::bench;

namespace {

using Mls = pcl::MovingLeastSquares<pcl::PointXYZ, pcl::PointNormal>;

struct Mode {
    const char* side;
    Mls::UpsamplingMethod method;
    const char* param;  ///< What the size parameter sets.
};
constexpr Mode kModes[] = {
    {"pcl-local-plane", Mls::SAMPLE_LOCAL_PLANE, "upsampling step (radius = h)"},
    {"pcl-random", Mls::RANDOM_UNIFORM_DENSITY, "point density (points per search disk)"},
    {"pcl-voxel", Mls::VOXEL_GRID_DILATION, "dilation voxel size"},
};

std::vector<Vec3f> Run(const ResampleCase& c, const Mode& m, double param, double h) {
    auto cloud = pcl::make_shared<pcl::PointCloud<pcl::PointXYZ>>();
    for (const auto& p : Dataset(c.dataset).positions) cloud->push_back(pcl::PointXYZ(p.x(), p.y(), p.z()));
    Mls mls;
    mls.setInputCloud(cloud);
    mls.setSearchMethod(pcl::make_shared<pcl::search::KdTree<pcl::PointXYZ>>());
    mls.setPolynomialOrder(2);
    mls.setSearchRadius(3.0 * h);
    mls.setSqrGaussParam(h * h);
    mls.setNumberOfThreads(2);
    mls.setUpsamplingMethod(m.method);
    switch (m.method) {
        case Mls::SAMPLE_LOCAL_PLANE:
            mls.setUpsamplingRadius(h);
            mls.setUpsamplingStepSize(param);
            break;
        case Mls::RANDOM_UNIFORM_DENSITY: mls.setPointDensity(int(std::lround(param))); break;
        case Mls::VOXEL_GRID_DILATION:
            mls.setDilationVoxelSize(float(param));
            mls.setDilationIterations(1);
            break;
        default: break;
    }
    pcl::PointCloud<pcl::PointNormal> out;
    mls.process(out);
    std::vector<Vec3f> pts;
    pts.reserve(out.size());
    for (const auto& p : out) pts.emplace_back(p.x, p.y, p.z);
    return pts;
}

}  // namespace

int main(int argc, char** argv) {
    const ResampleArgs a = ParseResampleArgs(argc, argv, "pcl-local-plane|pcl-random|pcl-voxel");
    const ResampleCase& c = FindResampleCase(a.name);
    const Mode* mode = nullptr;
    for (const auto& m : kModes)
        if (a.side == m.side) mode = &m;
    if (!mode) return std::cerr << "bench_resample_pcl: unknown side '" << a.side << "'\n", 2;
    if (!HaveDataset(c.dataset)) return std::cerr << "bench_resample_pcl: dataset missing\n", 1;
    if (c.ratio <= 1) return std::cerr << a.side << " only upsamples\n", 1;
    const KdTree tree(Dataset(c.dataset).positions);
    const double h = DefaultScale(tree);
    nlohmann::json j;
    j["case"] = c.name;
    j["side"] = a.side;
    j["input_points"] = Dataset(c.dataset).size();
    j["h"] = h;
    j["param_meaning"] = mode->param;
    double param = a.param;
    if (a.search || param <= 0) {
        // Counts fall as the step and the voxel grow, and rise with the density.
        const auto count = [&](double p) { return Run(c, *mode, p, h).size(); };
        double p;
        if (mode->method == Mls::RANDOM_UNIFORM_DENSITY) {
            const auto inv = [&](double q) { return count(1.0 / q); };
            p = 1.0 / SearchDecreasing(inv, 1.0 / 2000.0, 1.0, c.target());
            p = std::round(p);
        } else {
            p = SearchDecreasing(count, 0.02 * h, 4.0 * h, c.target());
        }
        j["param"] = p;
        if (a.search) return std::cout << j.dump() << "\n", 0;
        j["searched_in_process"] = true;
        param = p;
    }
    j["param"] = param;
    const double c0 = ProcessCpuMs();
    const auto t0 = Clock::now();
    const std::vector<Vec3f> pts = Run(c, *mode, param, h);
    const auto t1 = Clock::now();
    j["time_ms"] = Ms(t0, t1);
    j["cpu_ms"] = ProcessCpuMs() - c0;
    j["stages"] = {{"mls_upsample", Ms(t0, t1)}};
    j["peak_rss_mb"] = PeakResidentMiB();
    MeasureResample(c, pts, j);
    std::cout << j.dump() << "\n";
    return 0;
}
