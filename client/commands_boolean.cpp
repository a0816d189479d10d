// surfel boolean
#include <Eigen/Geometry>
#include <numbers>

#include "cli_common.h"
#include "job_exec.h"
#include "placement.h"
#include "surfel/base/error.h"
#include "surfel/boolean/boolean.h"
#include "surfel/io/cloud_io.h"
#include "surfel/worker/job_kind.h"

namespace surfel::cli {
namespace {

struct BooleanArgs {
    std::string a, b, output, op;
    PlacementFlags place;
    bool ascii = false;
    double blend = 0.0;
    int blend_iterations = kDefaultBlendIterations;
    CommonFlags flags;
    JobFlags job;
};

std::vector<std::string> OpNames() {
    std::vector<std::string> names;
    for (const BooleanOp op : kBooleanOps) names.emplace_back(BooleanOpName(op));
    return names;
}

void RunBoolean(BooleanArgs& a) {
    if (UsageOnBadValue("--output", [&] { return FormatFromPath(a.output); }) != CloudFileFormat::kPly)
        throw UsageError("--output: a boolean result is PLY (its creases are vertex properties XYZ cannot hold)");
    v1::JobSpec spec;
    v1::BooleanJob& job = *spec.mutable_boolean();
    job.set_op(ParseProtoEnum("--op", a.op, &v1::BooleanJob::Op_Parse));
    *job.mutable_transform_b() = PlacementToProto(a.place);
    job.set_ascii(a.ascii);
    job.set_blend_radius(a.blend);
    job.set_blend_iterations(static_cast<std::uint32_t>(a.blend_iterations));
    PrintReport(ExecuteJob(spec, {a.a, a.b}, a.output, a.flags, a.job), a.flags);
}

}  // namespace

void AddPlacementFlags(CLI::App* sub, PlacementFlags* flags) {
    flags->scale = Similarity{}.scale;
    sub->add_option("--translate", flags->translate, "Move B by x,y,z (after rotating and scaling it)");
    sub->add_option("--rotate", flags->rotate, "Rotate B about the axis ax,ay,az through its origin by DEG degrees: ax,ay,az,DEG");
    sub->add_option("--scale", flags->scale, "Scale B uniformly about its origin")
        ->capture_default_str()
        ->check(CLI::Range(kMinBooleanScale, kMaxBooleanScale));
}

v1::Similarity PlacementToProto(const PlacementFlags& flags) {
    v1::Similarity t;
    if (!flags.translate.empty()) *t.mutable_translation() = worker::ToProto(ParseVec3(flags.translate, "--translate"));
    if (!flags.rotate.empty()) {
        const std::vector<double> r = ParseNumbers(flags.rotate, "--rotate", 4);
        const Vec3d axis(r[0], r[1], r[2]);
        if (axis.norm() == 0) throw UsageError("--rotate: the axis must not be zero");
        const Eigen::Matrix3d R = Eigen::AngleAxisd(r[3] * std::numbers::pi / 180.0, axis.normalized()).toRotationMatrix();
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) t.add_rotation(R(i, j));
    }
    t.set_scale(flags.scale);
    return t;
}

void RegisterBooleanCommands(CLI::App& app) {
    auto a = std::make_shared<BooleanArgs>();
    auto* sub = app.add_subcommand("boolean", "Union, intersection or difference of the solids two closed clouds bound (notes 3.1)");
    sub->add_option("a", a->a, "First solid: a closed PLY or XYZ cloud (normals estimated when absent)")
        ->required()
        ->check(CLI::ExistingFile);
    sub->add_option("b", a->b, "Second solid, placed by --translate/--rotate/--scale")->required()->check(CLI::ExistingFile);
    sub->add_option("--op", a->op, "union | intersection | difference (A - B) | reverse-difference (B - A)")
        ->required()
        ->check(CLI::IsMember(OpNames()));
    sub->add_option("-o,--output", a->output, "Output PLY: positions, normals, radius, crease, crease_n{x,y,z}, source")
        ->required();
    AddPlacementFlags(sub, &a->place);
    sub->add_option("--blend", a->blend,
                    "Smooth the creases within R of the intersection curve (model units) by the particle\n"
                    "blending of notes 3.1.4; 0 keeps them sharp")
        ->check(CLI::NonNegativeNumber);
    sub->add_option("--blend-iterations", a->blend_iterations, "Steps of the blending simulation; more give a rounder blend")
        ->capture_default_str()
        ->check(CLI::Range(kMinBlendIterations, kMaxBlendIterations));
    sub->add_flag("--ascii", a->ascii, "Write ASCII PLY");
    AddCommonFlags(sub, &a->flags);
    AddJobFlags(sub, &a->job);
    sub->footer(
        "Runs in-process, or on a server with --server host:port (both clouds uploaded once).\n"
        "Samples of each input are kept or dropped by inside/outside classification (Table 3.1);\n"
        "the intersection curve is sampled by a Newton iteration onto both MLS surfaces, each curve\n"
        "sample a surfel pair: its A-side normal in nx,ny,nz and its B-side normal in crease_n*.\n"
        "The report: points kept from each input, curve samples, mean Newton iterations, the share\n"
        "of classification queries the coherence spheres saved, time_ms; with --blend, how many\n"
        "samples moved and how far (blend.moved, blend.max_displacement).\n"
        "--blend R: every sample within R of the curve becomes an oriented particle (normals drawn\n"
        "towards their neighbours', positions onto circles tangent to both normals, the particle\n"
        "engine's repulsion), the samples just beyond R stay fixed; a 90-degree crease becomes a\n"
        "fillet of radius about R. Try R = 3-10 times the sample spacing.\n"
        "Examples:\n"
        "  surfel boolean sphere.ply box.ply --op difference -o carved.ply --json\n"
        "  surfel boolean bunny.ply bunny.ply --op union --rotate 0,1,0,30 --translate 0.02,0,0 -o two.ply\n"
        "  surfel boolean bunny.ply sphere.ply --op difference --scale 0.03 --blend 0.004 -o rounded.ply");
    sub->callback([a] { RunBoolean(*a); });
}

}  // namespace surfel::cli
