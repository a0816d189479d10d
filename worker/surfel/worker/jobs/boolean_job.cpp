// The boolean job: union, intersection and differences of two point-sampled solids
// (core/surfel/boolean). The one job with two input clouds.

#include <algorithm>

#include "surfel/base/error.h"
#include "surfel/boolean/boolean.h"
#include "surfel/io/ply.h"
#include "surfel/worker/jobs/jobs.h"

namespace surfel::worker {
namespace {

/// Memory estimate constants (docs/memory.md).
constexpr std::uint64_t kBooleanBytesPerPoint = 150;
/// position, normal, radius, crease, crease normal (3 doubles), source: as held and written.
constexpr std::uint64_t kBooleanOutputBytesPerPoint = 12 + 12 + 4 + 8 + 24 + 8;

// ---- proto -> BooleanOp, BooleanOptions --------------------------------------------------------
// Proto3's "0 / unset means the default" is resolved here; every default and limit is core's.

BooleanOp ToBooleanOp(const v1::BooleanJob& job) { return BooleanOpFromProto(job.op(), "boolean.op"); }

BooleanOptions ToBooleanOptions(const v1::BooleanJob& job) {
    BooleanOptions o;
    if (job.has_transform_b()) o.transform = SimilarityFromProto(job.transform_b(), "boolean.transform_b");
    o.blend_radius = job.blend_radius();
    if (job.blend_iterations() != 0)
        o.blend_iterations = static_cast<int>(std::min<std::uint32_t>(job.blend_iterations(), kMaxBlendIterations + 1));
    return o;
}

/// Core messages name B's placement "transform"; the spec calls it "transform_b".
void ValidateOptions(const BooleanOptions& options) {
    try {
        options.Validate();
    } catch (const Error& e) {
        std::string what = e.what();
        if (what.rfind("transform.", 0) == 0) what = "transform_b." + what.substr(10);
        throw Error(e.code(), "boolean." + what);
    }
}

nlohmann::json BooleanReportJson(const BooleanReport& r, std::size_t points) {
    return {{"points", points},
            {"op", r.op},
            {"input_points_a", r.input_points_a},
            {"input_points_b", r.input_points_b},
            {"kept_a", r.kept_a},
            {"kept_b", r.kept_b},
            {"upsampled_a", r.upsampled_a},
            {"upsampled_b", r.upsampled_b},
            {"added_a", r.added_a},
            {"added_b", r.added_b},
            {"curve_samples", r.curve_samples},
            {"curve_seeds", r.curve_seeds},
            {"curve_refined", r.curve_refined},
            {"mean_newton_iterations", r.mean_newton_iterations},
            {"newton_failures", r.newton_failures},
            {"classification_queries", r.classification_queries},
            {"queries_saved", r.queries_saved},
            {"queries_saved_share", r.queries_saved_share},
            {"mls_classifications", r.mls_classifications},
            {"normals_estimated_a", r.normals_estimated_a},
            {"normals_estimated_b", r.normals_estimated_b},
            {"overlap", r.overlap},
            {"notes", r.notes},
            {"blend",
             {{"radius", r.blend_radius},
              {"moved", r.blend.moved},
              {"fixed", r.blend.fixed},
              {"creases_cleared", r.blend.creases_cleared},
              {"knife_edges", r.blend.knife_edges},
              {"iterations", r.blend.iterations},
              {"max_displacement", r.blend.max_displacement},
              {"mean_displacement", r.blend.mean_displacement}}},
            {"time_ms", r.time_ms}};
}

// ---- The kind ---------------------------------------------------------------------------------

class BooleanJobKind final : public JobKind {
public:
    v1::JobSpec::JobCase Case() const override { return v1::JobSpec::kBoolean; }
    std::string_view Name() const override { return "boolean"; }
    std::string_view Stage() const override { return "combining"; }
    std::size_t InputCount(const v1::JobSpec&) const override { return 2; }

    std::vector<CloudInput> Inputs(const v1::JobSpec& spec) const override {
        return {{"boolean.cloud_id_a", spec.boolean().cloud_id_a()},
                {"boolean.cloud_id_b", spec.boolean().cloud_id_b()}};
    }
    void SetInput(v1::JobSpec& spec, std::size_t index, const std::string& cloud_id) const override {
        SURFEL_CHECK(index < 2, index);
        if (index == 0) spec.mutable_boolean()->set_cloud_id_a(cloud_id);
        else spec.mutable_boolean()->set_cloud_id_b(cloud_id);
    }

    void Validate(const v1::JobSpec& spec) const override {
        ToBooleanOp(spec.boolean());
        ValidateOptions(ToBooleanOptions(spec.boolean()));
    }

    std::pair<std::string, std::string> ResultType(const v1::JobSpec&) const override {
        return {"application/ply", ".ply"};
    }

    JobOutput Run(const v1::JobSpec& spec, const Clouds& clouds, const ProgressFn& progress) const override {
        const v1::BooleanJob& job = spec.boolean();
        const BooleanOptions options = ToBooleanOptions(job);
        BooleanResult r;
        WithFieldPrefix("boolean", [&] {
            r = Boolean(*clouds.at(0), *clouds.at(1), ToBooleanOp(job), options, progress);
        });
        PlyWriteOptions w;
        w.format = job.ascii() ? PlyFormat::kAscii : PlyFormat::kBinaryLittleEndian;
        w.comments.push_back(std::string("surfel boolean ") + r.report.op);
        JobOutput out;
        std::tie(out.media_type, out.extension) = ResultType(spec);
        out.bytes = FormatPly(r.cloud, w);
        out.report = BooleanReportJson(r.report, r.cloud.size());
        out.points = r.cloud.size();
        out.time_ms = r.report.time_ms;
        return out;
    }

    /// Both clouds; per input point its kd-tree, normals, the inside/outside classification and
    /// the upsampling near the curve (kBooleanBytesPerPoint); the output (at most both inputs
    /// plus the curve) as a cloud with its crease attributes and as PLY bytes.
    std::uint64_t EstimateMemory(const v1::JobSpec&, std::span<const CloudFacts> inputs) const override {
        std::uint64_t clouds = 0, points = 0, file = 0;
        for (const CloudFacts& in : inputs) {
            clouds += CloudBytes(in);
            points += in.points;
            file = std::max(file, in.file_bytes);
        }
        const std::uint64_t work = kBooleanBytesPerPoint * points + 2 * points * kBooleanOutputBytesPerPoint;
        return clouds + std::max(file, work);
    }

    v1::JobSpec Example() const override {
        v1::JobSpec spec;
        v1::BooleanJob& b = *spec.mutable_boolean();
        b.set_op(v1::BooleanJob::UNION);
        // The second solid: the first moved by half its radius, so the two overlap.
        *b.mutable_transform_b()->mutable_translation() = ToProto(Vec3d(0.5, 0, 0));
        return spec;
    }
};

}  // namespace

BooleanOp BooleanOpFromProto(int op, const std::string& field) {
    switch (static_cast<v1::BooleanJob::Op>(op)) {
        case v1::BooleanJob::UNION: return BooleanOp::kUnion;
        case v1::BooleanJob::INTERSECTION: return BooleanOp::kIntersection;
        case v1::BooleanJob::DIFFERENCE: return BooleanOp::kDifference;
        case v1::BooleanJob::REVERSE_DIFFERENCE: return BooleanOp::kReverseDifference;
        case v1::BooleanJob::OP_UNSPECIFIED:
            throw Error(ErrorCode::kInvalidArgument,
                        field + ": is required (UNION, INTERSECTION, DIFFERENCE or REVERSE_DIFFERENCE)");
        default: break;
    }
    throw Error(ErrorCode::kInvalidArgument, field + ": unknown operation " + std::to_string(op));
}

Similarity SimilarityFromProto(const v1::Similarity& t, const std::string& field) {
    Similarity s;
    if (t.rotation_size() != 0 && t.rotation_size() != 9)
        throw Error(ErrorCode::kInvalidArgument, field + ".rotation: must have 9 numbers (a row-major "
                                                 "3x3 matrix) or none, got " + std::to_string(t.rotation_size()));
    if (t.rotation_size() == 9)
        for (int r = 0; r < 3; ++r)
            for (int c = 0; c < 3; ++c) s.rotation(r, c) = t.rotation(3 * r + c);
    s.translation = FromProto(t.translation());
    if (t.scale() != 0) s.scale = t.scale();
    s.Validate(field);
    return s;
}

const JobKind& BooleanKind() {
    static const BooleanJobKind kind;
    return kind;
}

}  // namespace surfel::worker
