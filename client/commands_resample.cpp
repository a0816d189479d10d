// surfel resample
#include "cli_common.h"
#include "job_exec.h"
#include "surfel/base/error.h"
#include "surfel/io/cloud_io.h"
#include "surfel/resample/resample.h"

namespace surfel::cli {
namespace {

// Defaults come from a default-constructed ResampleOptions, ranges from core's named limits.
struct ResampleArgs {
    ResampleOptions defaults;
    std::string input, output, method = ResampleMethodName(defaults.method);
    std::uint64_t target = 0, seed = defaults.seed;
    double spacing = 0;
    int iterations = defaults.iterations, mls_degree = defaults.mls_degree;
    double mls_h = defaults.mls_h;
    bool adaptive = defaults.adaptive, keep_input = defaults.keep_input, no_error = !defaults.measure_error,
         ascii = false;
    CommonFlags flags;
    JobFlags job;
};

std::vector<std::string> MethodNames() {
    std::vector<std::string> names;
    for (const ResampleMethod m : kResampleMethods) names.emplace_back(ResampleMethodName(m));
    return names;
}

void RunResample(ResampleArgs& a) {
    const bool xyz = UsageOnBadValue("--output", [&] { return FormatFromPath(a.output); }) == CloudFileFormat::kXyz;
    const bool mls = a.method == ResampleMethodName(ResampleMethod::kMls);
    if (mls && (a.target != 0 || a.spacing != 0))
        throw UsageError("--method mls keeps the input's points: give neither --target nor --spacing");
    if (!mls && (a.target == 0) == (a.spacing == 0)) throw UsageError("give --target N or --spacing S (one of them)");
    v1::JobSpec spec;
    v1::ResampleJob& r = *spec.mutable_resample();
    r.set_method(ParseProtoEnum("--method", a.method, &v1::ResampleJob::Method_Parse));
    r.set_target(a.target);
    r.set_spacing(a.spacing);
    r.set_adaptive(a.adaptive);
    r.set_keep_input(a.keep_input);
    r.set_seed(a.seed);
    r.set_iterations(a.iterations);
    r.set_ascii(a.ascii);
    r.set_no_error_report(a.no_error);
    r.set_mls_degree(static_cast<v1::ResampleJob::Degree>(a.mls_degree + 1));  // --mls-degree 0..2
    r.set_mls_h(a.mls_h);
    nlohmann::json report = ExecuteJob(spec, {a.input}, a.output, a.flags, a.job);
    if (xyz && report.contains("output")) WritePointCloud(ReadPointCloud(a.output), a.output);
    PrintReport(report, a.flags);
}

}  // namespace

void RegisterResampleCommands(CLI::App& app) {
    auto a = std::make_shared<ResampleArgs>();
    auto* sub = app.add_subcommand("resample", "Resample the surface to a count or spacing, up or down (particles on the MLS surface)");
    sub->add_option("input", a->input, "PLY or XYZ file")->required()->check(CLI::ExistingFile);
    sub->add_option("-o,--output", a->output, "Output file (.ply or .xyz): positions, normals, radius, colours, attributes")
        ->required();
    sub->add_option("-m,--method", a->method,
                    "particle (notes 2.3: count or spacing, up or down) | mls (smoothing: MLS projection of every "
                    "point) | split (densify to a spacing by splitting, notes 3.2.2)")->capture_default_str()->check(CLI::IsMember(MethodNames()));
    sub->add_option("-n,--target", a->target, "Exact number of output points (above or below the input's)")
        ->check(CLI::Range(std::uint64_t{1}, std::uint64_t{kMaxResampleTarget}));
    sub->add_option("-s,--spacing", a->spacing, "Target spacing between neighbouring points, model units")
        ->check(CLI::PositiveNumber);
    sub->add_flag("--adaptive", a->adaptive, "Curvature-adaptive: denser where the surface bends");
    sub->add_flag("--keep-input", a->keep_input, "Keep every input point unchanged and only add points (needs a larger count)");
    sub->add_option("--iterations", a->iterations, "Relaxation steps of the particle simulation")
        ->capture_default_str()
        ->check(CLI::Range(1, kMaxResampleIterations));
    sub->add_option("--mls-degree", a->mls_degree, "mls: degree of the local polynomial")
        ->capture_default_str()
        ->check(CLI::Range(0, 2));
    sub->add_option("--mls-h", a->mls_h, "mls: Gaussian scale h in model units (0 = chosen from the data's noise)")
        ->capture_default_str()
        ->check(CLI::NonNegativeNumber);
    sub->add_option("--seed", a->seed, "Seed of the initial spreading (same seed, same output)")->capture_default_str();
    sub->add_flag("--no-error", a->no_error, "Skip the quality report (surface error)");
    sub->add_flag("--ascii", a->ascii, "Write ASCII PLY");
    AddCommonFlags(sub, &a->flags);
    AddJobFlags(sub, &a->job);
    sub->footer(
        "Runs in-process, or on a server with --server host:port. --target is met exactly.\n"
        "The report gives the spacing achieved (mean and coefficient of variation of the\n"
        "nearest-neighbour distances: 0 for a hexagonal lattice, ~0.52 for random samples) and\n"
        "the surface error of the input against the result (Delta_max, Delta_avg).\n"
        "Examples:\n"
        "  surfel resample bunny.ply -o bunny_4x.ply --target 140000\n"
        "  surfel resample scan.ply -o scan_even.ply --spacing 0.002 --json\n"
        "  surfel resample scan.ply -o scan_dense.ply --target 200000 --keep-input --adaptive\n"
        "  surfel resample noisy.ply -o smooth.ply --method mls --json\n"
        "  surfel resample sparse.ply -o dense.ply --method split --spacing 0.001");
    sub->callback([a] { RunResample(*a); });
}

}  // namespace surfel::cli
