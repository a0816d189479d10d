// surfel normals | project | error
#include "cli_common.h"
#include "surfel/base/error.h"
#include "surfel/spatial/kd_tree.h"
#include "surfel/surface/local_analysis.h"
#include "surfel/surface/mls.h"
#include "surfel/surface/surface_error.h"

namespace surfel::cli {
namespace {

// Defaults come from the default-constructed Options each Args holds, ranges from core's named
// limits (local_analysis.h, mls.h); core's Validate() checks again.

struct NormalsArgs {
    std::string input, output;
    NormalOptions opt;
    bool no_orient = false;
    bool ascii = false;
    CommonFlags flags;
};

void RunNormals(NormalsArgs& a) {
    PointCloud cloud = LoadCloud(a.input);
    a.opt.orient = !a.no_orient;
    Stopwatch watch;
    KdTree tree(cloud.positions);
    NormalResult r = EstimateNormals(tree, a.opt, MakeProgressBar("normals", a.flags));
    const double ms = watch.ElapsedMs();
    cloud.normals = std::move(r.normals);
    SaveCloud(cloud, a.output, a.ascii);
    double sv = 0;
    for (float v : r.surface_variation) sv += v;
    PrintReport({{"points", cloud.size()}, {"output", a.output}, {"k", a.opt.k}, {"oriented", a.opt.orient},
                 {"components", r.components}, {"flipped", r.flipped},
                 {"mean_surface_variation", cloud.empty() ? 0.0 : sv / cloud.size()}, {"time_ms", ms}},
                a.flags);
}

struct ProjectArgs {
    std::string input, output;
    MlsOptions opt;
    bool ascii = false;
    CommonFlags flags;
};

void RunProject(ProjectArgs& a) {
    PointCloud cloud = LoadCloud(a.input);
    Stopwatch watch;
    KdTree tree(cloud.positions);
    if (!cloud.has_normals()) {  // the projected normals take their orientation from these
        NormalResult nr = EstimateNormals(tree);
        cloud.normals = std::move(nr.normals);
    }
    MlsSurface mls(cloud, tree, a.opt);
    auto batch = mls.ProjectAll(cloud.positions, MakeProgressBar("project", a.flags));
    const double ms = watch.ElapsedMs();
    double moved_max = 0, moved_sum = 0;
    for (std::size_t i = 0; i < cloud.size(); ++i) {
        const double d = (batch.positions[i] - cloud.positions[i]).norm();
        moved_max = std::max(moved_max, d);
        moved_sum += d;
        if (batch.normals[i].squaredNorm() > 0) cloud.normals[i] = batch.normals[i];
    }
    cloud.positions = std::move(batch.positions);
    SaveCloud(cloud, a.output, a.ascii);
    PrintReport({{"points", cloud.size()}, {"output", a.output}, {"h", mls.h()}, {"degree", a.opt.degree},
                 {"adaptive", a.opt.adaptive}, {"failed", batch.failed}, {"mean_iterations", batch.mean_iterations},
                 {"max_displacement", moved_max}, {"mean_displacement", cloud.empty() ? 0.0 : moved_sum / cloud.size()},
                 {"time_ms", ms}},
                a.flags);
}

struct ErrorArgs {
    std::string reference, other;
    SurfaceErrorOptions opt;
    CommonFlags flags;
};

void RunError(ErrorArgs& a) {
    const PointCloud p = LoadCloud(a.reference);
    const PointCloud q = LoadCloud(a.other);
    Stopwatch watch;
    const SurfaceError e = MeasureSurfaceError(p, q, a.opt, MakeProgressBar("error", a.flags));
    PrintReport({{"points", e.samples}, {"max", e.max}, {"avg", e.avg}, {"rms", e.rms}, {"diagonal", e.diagonal},
                 {"max_relative", e.max_relative()}, {"avg_relative", e.avg_relative()},
                 {"avg_per_sample", e.avg_per_sample}, {"avg_per_sample_relative", e.avg_per_sample_relative()}, {"failed", e.failed},
                 {"time_ms", watch.ElapsedMs()}},
                a.flags);
}

}  // namespace

void RegisterSurfaceCommands(CLI::App& app) {
    {
        auto a = std::make_shared<NormalsArgs>();
        auto* sub = app.add_subcommand("normals", "Estimate normals by covariance analysis and orient them consistently (MST)");
        sub->add_option("input", a->input, "PLY or XYZ file")->required()->check(CLI::ExistingFile);
        sub->add_option("-o,--output", a->output, "Output file with normals (.ply or .xyz)")->required();
        sub->add_option("-k,--k", a->opt.k, "Neighbours per point for the covariance")
            ->capture_default_str()
            ->check(CLI::Range(kMinNormalNeighbors, kMaxNormalNeighbors));
        sub->add_flag("--weighted", a->opt.weighted, "Gaussian-weighted covariance instead of plain PCA");
        sub->add_option("--orient-k", a->opt.orient_k, "Neighbours in the orientation graph")
            ->capture_default_str()
            ->check(CLI::Range(kMinOrientNeighbors, kMaxOrientNeighbors));
        sub->add_option("--orient-crossing-weight", a->opt.orient_crossing_weight,
                        "Weight of an edge's tilt out of the tangent planes in the orientation's MST cost "
                        "(0 = Hoppe's 1 - |ni.nj| alone)")
            ->capture_default_str()
            ->check(CLI::Range(0.0, kMaxOrientCrossingWeight));
        sub->add_flag("--no-orient", a->no_orient, "Leave the normals' signs as estimated");
        sub->add_flag("--ascii", a->ascii, "Write ASCII PLY");
        AddCommonFlags(sub, &a->flags);
        sub->footer("Point order is kept. Example:\n  surfel normals scan.ply -o scan_normals.ply --k 16 --json");
        sub->callback([a] { RunNormals(*a); });
    }
    {
        auto a = std::make_shared<ProjectArgs>();
        auto* sub = app.add_subcommand("project", "MLS-project every point onto the cloud's MLS surface (smoothing)");
        sub->add_option("input", a->input, "PLY or XYZ file")->required()->check(CLI::ExistingFile);
        sub->add_option("-o,--output", a->output, "Output file (.ply or .xyz)")->required();
        sub->add_option("--h", a->opt.h, "Gaussian scale h (0 = 2 x median sample spacing)")
            ->capture_default_str()
            ->check(CLI::NonNegativeNumber);
        sub->add_option("--degree", a->opt.degree, "Polynomial degree over the reference plane")
            ->capture_default_str()
            ->check(CLI::Range(kMinMlsDegree, kMaxMlsDegree));
        sub->add_flag("--adaptive", a->opt.adaptive, "Adaptive MLS: h follows the local sample spacing");
        sub->add_option("--cutoff", a->opt.cutoff, "Neighbour radius in units of h")
            ->capture_default_str()
            ->check(CLI::Range(kMinMlsCutoff, kMaxMlsCutoff));
        sub->add_flag("--ascii", a->ascii, "Write ASCII PLY");
        AddCommonFlags(sub, &a->flags);
        sub->footer("Point order is kept; normals are the MLS surface's. Example:\n  surfel project noisy.ply -o smooth.ply --degree 2 --json");
        sub->callback([a] { RunProject(*a); });
    }
    {
        auto a = std::make_shared<ErrorArgs>();
        auto* sub = app.add_subcommand("error", "Surface error (max and average, Metro-style via MLS) of OTHER against REFERENCE");
        sub->add_option("reference", a->reference, "Cloud sampling the surface S")->required()->check(CLI::ExistingFile);
        sub->add_option("other", a->other, "Cloud sampling the surface S'")->required()->check(CLI::ExistingFile);
        sub->add_option("--samples", a->opt.max_samples, "Measure at most this many points of REFERENCE (0 = all)")
            ->capture_default_str();
        sub->add_flag("--symmetric", a->opt.symmetric, "Measure both directions");
        sub->add_option("--degree", a->opt.degree, "MLS degree of the projection onto OTHER (the notes use 1)")
            ->capture_default_str()
            ->check(CLI::Range(kMinMlsDegree, kMaxMlsDegree));
        sub->add_option("--seed", a->opt.seed, "Seed for the sample subset")->capture_default_str();
        AddCommonFlags(sub, &a->flags);
        sub->footer(
            "Each sample of REFERENCE is projected onto its own MLS surface S, giving q; d is the distance\n"
            "from q to its MLS projection onto OTHER's surface S'. `max` is the largest d, `avg` the mean over\n"
            "S's area (each sample counts for the area it stands for, as in the notes' 2.4.1), and\n"
            "`avg_per_sample` the plain mean over the samples; *_relative divide by REFERENCE's\n"
            "bounding-box diagonal.\n"
            "Example:\n  surfel error bunny.ply bunny_simplified.ply --json");
        sub->callback([a] { RunError(*a); });
    }
}

}  // namespace surfel::cli
