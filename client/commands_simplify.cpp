// surfel simplify
#include "cli_common.h"
#include "job_exec.h"
#include "surfel/io/cloud_io.h"
#include "surfel/base/error.h"
#include "surfel/simplify/simplify.h"

namespace surfel::cli {
namespace {

// Defaults come from a default-constructed SimplifyOptions, ranges from core's named limits.
struct SimplifyArgs {
    SimplifyOptions defaults;
    std::string input, output, method = SimplifyMethodName(defaults.method),
                               representative = SimplifyRepresentativeName(defaults.representative);
    std::uint64_t target = 0, seed = defaults.seed, max_size = defaults.max_cluster_size;
    double error = 0, max_variation = defaults.max_variation;
    bool adaptive = defaults.adaptive, no_error = !defaults.measure_error, ascii = false;
    CommonFlags flags;
    JobFlags job;
};

std::vector<std::string> MethodNames() {
    std::vector<std::string> names;
    for (const SimplifyMethod m : kSimplifyMethods) names.emplace_back(SimplifyMethodName(m));
    return names;
}

void RunSimplify(SimplifyArgs& a) {
    const bool xyz = UsageOnBadValue("--output", [&] { return FormatFromPath(a.output); }) == CloudFileFormat::kXyz;
    v1::JobSpec spec;
    v1::SimplifyJob& s = *spec.mutable_simplify();
    s.set_method(ParseProtoEnum("--method", a.method, &v1::SimplifyJob::Method_Parse));
    s.set_representative(
        ParseProtoEnum("--representative", a.representative, &v1::SimplifyJob::Representative_Parse));
    s.set_target(a.target);
    s.set_error(a.error);
    s.set_adaptive(a.adaptive);
    s.set_seed(a.seed);
    s.set_max_variation(a.max_variation);
    s.set_max_cluster_size(a.max_size);
    s.set_ascii(a.ascii);
    s.set_no_error_report(a.no_error);
    nlohmann::json report = ExecuteJob(spec, {a.input}, a.output, a.flags, a.job);
    if (xyz && report.contains("output")) WritePointCloud(ReadPointCloud(a.output), a.output);
    PrintReport(report, a.flags);
}

}  // namespace

void RegisterSimplifyCommands(CLI::App& app) {
    auto a = std::make_shared<SimplifyArgs>();
    auto* sub = app.add_subcommand("simplify", "Simplify a point cloud (Pauly: clustering, iterative, particle; voxel baseline)");
    sub->add_option("input", a->input, "PLY or XYZ file")->required()->check(CLI::ExistingFile);
    sub->add_option("-o,--output", a->output, "Output file (.ply or .xyz): positions, normals, radius, colours")->required();
    sub->add_option("-m,--method", a->method, "hierarchical | incremental | iterative | particle | voxel")
        ->capture_default_str()
        ->check(CLI::IsMember(MethodNames()));
    sub->add_option("-n,--target", a->target, "Exact number of output points")->check(CLI::PositiveNumber);
    sub->add_option("-e,--error", a->error,
                    "Error bound in model units instead of a count (iterative: RMS distance to the tangent planes; "
                    "hierarchical: distance of a cluster's points from its plane)")
        ->check(CLI::PositiveNumber);
    sub->add_option("--representative", a->representative,
                    "centroid: each cluster's centroid on its fitted surface, normals and colours averaged (the "
                    "notes' rule); member: the input point nearest it, every attribute unchanged, so the output "
                    "is a subset of the input (not for particle)")
        ->capture_default_str()
        ->check(CLI::IsMember({"centroid", "member"}));
    sub->add_flag("--adaptive", a->adaptive, "Curvature-adaptive: more points where the surface bends");
    sub->add_option("--max-variation", a->max_variation, "sigma_max: largest surface variation of a cluster in adaptive clustering")
        ->capture_default_str()
        ->check(CLI::Range(kMinMaxVariation, kMaxMaxVariation));
    sub->add_option("--max-size", a->max_size, "n_max, the largest cluster without a target (clustering)")
        ->capture_default_str()
        ->check(CLI::Range(std::uint64_t{1}, std::uint64_t{kMaxMaxClusterSize}));
    sub->add_option("--seed", a->seed, "Seed (incremental seeds, particle spreading)")->capture_default_str();
    sub->add_flag("--no-error", a->no_error, "Skip the quality report (surface error)");
    sub->add_flag("--ascii", a->ascii, "Write ASCII PLY");
    AddCommonFlags(sub, &a->flags);
    AddJobFlags(sub, &a->job);
    sub->footer(
        "Runs in-process, or on a server with --server host:port. Every method hits --target\n"
        "exactly. The report gives the surface error of the input against the result\n"
        "(Delta_max, Delta_avg; absolute and relative to the bounding-box diagonal).\n"
        "Examples:\n"
        "  surfel simplify bunny.ply -o bunny_1k.ply --method hierarchical --target 1000\n"
        "  surfel simplify scan.ply -o scan_s.ply --method iterative --error 0.0005 --json\n"
        "  surfel simplify scan.ply -o scan_p.ply --method particle --target 5000 --adaptive\n"
        "  surfel simplify scan.ply -o scan_subset.ply --target 5000 --representative member");
    sub->callback([a] { RunSimplify(*a); });
}

}  // namespace surfel::cli
