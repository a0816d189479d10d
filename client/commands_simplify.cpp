// surfel simplify
#include "cli_common.h"
#include "surfel/base/error.h"
#include "surfel/simplify/simplify.h"

namespace surfel::cli {
namespace {

struct SimplifyArgs {
    std::string input, output, method = "hierarchical";
    SimplifyOptions opt;
    bool no_error = false;
    bool ascii = false;
    CommonFlags flags;
};

void RunSimplify(SimplifyArgs& a) {
    const auto method = ParseSimplifyMethod(a.method);
    if (!method) throw UsageError("--method: unknown method '" + a.method + "'");
    a.opt.method = *method;
    a.opt.measure_error = !a.no_error;
    if (a.opt.target == 0 && a.opt.error == 0 && *method != SimplifyMethod::kHierarchical &&
        *method != SimplifyMethod::kIncremental)
        throw UsageError("--method " + a.method + " needs --target N" +
                         (*method == SimplifyMethod::kIterative ? std::string(" or --error E") : std::string()));
    if (a.opt.target > 0 && a.opt.error > 0) throw UsageError("give --target or --error, not both");
    const PointCloud cloud = LoadCloud(a.input);
    SimplifyResult r;
    try {
        r = Simplify(cloud, a.opt, MakeProgressBar("simplify", a.flags));
    } catch (const Error& e) {
        // A request that does not fit this cloud (target too large, ...) is a usage error.
        if (e.code() == ErrorCode::kInvalidArgument) throw UsageError(e.what());
        throw;
    }
    SaveCloud(r.cloud, a.output, a.ascii);
    PrintReport(SimplifyReportJson(r.report, a.output), a.flags);
}

}  // namespace

nlohmann::json SimplifyReportJson(const SimplifyReport& r, const std::string& output) {
    nlohmann::json j = {{"points", r.output_points},
                        {"input_points", r.input_points},
                        {"method", r.method},
                        {"adaptive", r.adaptive},
                        {"time_ms", r.time_ms},
                        {"peak_rss_mb", r.peak_rss_mb},
                        {"normals_estimated", r.normals_estimated}};
    if (!output.empty()) j["output"] = output;
    if (r.error) {
        j["error"] = {{"max", r.error->max},
                      {"avg", r.error->avg},
                      {"max_relative", r.error->max_relative()},
                      {"avg_relative", r.error->avg_relative()},
                      {"samples", r.error->samples},
                      {"failed", r.error->failed},
                      {"time_ms", r.error_time_ms}};
    }
    return j;
}

void RegisterSimplifyCommands(CLI::App& app) {
    auto a = std::make_shared<SimplifyArgs>();
    auto* sub = app.add_subcommand("simplify", "Simplify a point cloud (Pauly: clustering, iterative, particle; voxel baseline)");
    sub->add_option("input", a->input, "PLY or XYZ file")->required()->check(CLI::ExistingFile);
    sub->add_option("-o,--output", a->output, "Output file (.ply or .xyz): positions, normals, radius, colours")->required();
    sub->add_option("-m,--method", a->method, "hierarchical | incremental | iterative | particle | voxel")
        ->default_val("hierarchical")
        ->check(CLI::IsMember({"hierarchical", "incremental", "iterative", "particle", "voxel"}));
    sub->add_option("-n,--target", a->opt.target, "Exact number of output points")->check(CLI::PositiveNumber);
    sub->add_option("-e,--error", a->opt.error,
                    "Error bound in model units instead of a count (iterative: RMS distance to the tangent planes; "
                    "hierarchical: distance of a cluster's points from its plane)")
        ->check(CLI::PositiveNumber);
    sub->add_flag("--adaptive", a->opt.adaptive, "Curvature-adaptive: more points where the surface bends");
    sub->add_option("--max-variation", a->opt.max_variation, "sigma_max: largest surface variation of a cluster in adaptive clustering")
        ->default_val(0.01)
        ->check(CLI::Range(1e-9, 1.0 / 3.0));
    sub->add_option("--max-size", a->opt.max_cluster_size, "n_max, the largest cluster without a target (clustering)")
        ->default_val(10);
    sub->add_option("--seed", a->opt.seed, "Seed (incremental seeds, particle spreading)")->default_val(1);
    sub->add_option("--k", a->opt.neighbors, "Neighbour graph size (incremental, iterative)")->default_val(6)->check(CLI::Range(1, 64));
    sub->add_option("--iterations", a->opt.particle_iterations, "Particle relaxation steps")->default_val(40)->check(CLI::Range(0, 10000));
    sub->add_option("--error-samples", a->opt.error_samples, "Points measured for the quality report (0 = all)")->default_val(20000);
    sub->add_flag("--no-error", a->no_error, "Skip the quality report (surface error)");
    sub->add_flag("--ascii", a->ascii, "Write ASCII PLY");
    AddCommonFlags(sub, &a->flags);
    sub->footer(
        "Every method hits --target exactly. The report gives the surface error of the input against\n"
        "the result (Delta_max, Delta_avg; absolute and relative to the bounding-box diagonal).\n"
        "Examples:\n"
        "  surfel simplify bunny.ply -o bunny_1k.ply --method hierarchical --target 1000\n"
        "  surfel simplify scan.ply -o scan_s.ply --method iterative --error 0.0005 --json\n"
        "  surfel simplify scan.ply -o scan_p.ply --method particle --target 5000 --adaptive");
    sub->callback([a] { RunSimplify(*a); });
}

}  // namespace surfel::cli
