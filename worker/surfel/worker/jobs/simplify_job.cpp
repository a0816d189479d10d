// The simplify job: point-cloud simplification (core/surfel/simplify).

#include <algorithm>

#include "surfel/base/error.h"
#include "surfel/io/ply.h"
#include "surfel/simplify/simplify.h"
#include "surfel/worker/jobs/jobs.h"
#include "surfel/worker/jobs/reports.h"

namespace surfel::worker {
namespace {

/// Memory estimate: bytes per input point of each method's own data, the default quality report
/// included (docs/memory.md); fitted to peak RSS on bunny_scans_merged (362k points) and
/// buddha_scan (78k) with every method (bench/results-memory.md).
std::uint64_t SimplifyBytesPerPoint(SimplifyMethod method) {
    switch (method) {
        case SimplifyMethod::kHierarchical: return 80;
        case SimplifyMethod::kIncremental: return 140;  // region growing's neighbour lists
        case SimplifyMethod::kIterative: return 400;    // quadrics, the pair graph and its heap
        case SimplifyMethod::kParticle: return 170;     // the particle engine on the input's MLS surface
        case SimplifyMethod::kVoxel: return 80;
    }
    return 400;
}

// ---- proto -> SimplifyOptions ----------------------------------------------------------------
// Proto3's "0 / unset means the default" is resolved here; every default and limit is core's.

SimplifyOptions ToSimplifyOptions(const v1::SimplifyJob& job) {
    const SimplifyOptions defaults;
    SimplifyOptions o;
    switch (job.method()) {
        case v1::SimplifyJob::METHOD_UNSPECIFIED: o.method = defaults.method; break;
        case v1::SimplifyJob::HIERARCHICAL: o.method = SimplifyMethod::kHierarchical; break;
        case v1::SimplifyJob::INCREMENTAL: o.method = SimplifyMethod::kIncremental; break;
        case v1::SimplifyJob::ITERATIVE: o.method = SimplifyMethod::kIterative; break;
        case v1::SimplifyJob::PARTICLE: o.method = SimplifyMethod::kParticle; break;
        case v1::SimplifyJob::VOXEL: o.method = SimplifyMethod::kVoxel; break;
        default:
            throw Error(ErrorCode::kInvalidArgument, "simplify.method: unknown method " + std::to_string(job.method()));
    }
    switch (job.representative()) {
        case v1::SimplifyJob::REPRESENTATIVE_UNSPECIFIED: o.representative = defaults.representative; break;
        case v1::SimplifyJob::CENTROID: o.representative = SimplifyRepresentative::kCentroid; break;
        case v1::SimplifyJob::MEMBER: o.representative = SimplifyRepresentative::kMember; break;
        default:
            throw Error(ErrorCode::kInvalidArgument,
                        "simplify.representative: unknown representative " + std::to_string(job.representative()));
    }
    o.target = job.target();
    o.error = job.error();
    o.adaptive = job.adaptive();
    if (job.seed()) o.seed = job.seed();
    if (job.max_variation() != 0) o.max_variation = job.max_variation();
    if (job.max_cluster_size()) o.max_cluster_size = job.max_cluster_size();
    o.measure_error = !job.no_error_report();
    return o;
}

nlohmann::json SimplifyReportJson(const SimplifyReport& r) {
    nlohmann::json j = {{"points", r.output_points},
                        {"input_points", r.input_points},
                        {"method", r.method},
                        {"representative", r.representative},
                        {"adaptive", r.adaptive},
                        {"time_ms", r.time_ms},
                        {"peak_rss_mb", r.peak_rss_mb},
                        {"normals_estimated", r.normals_estimated}};
    if (r.error) j["error"] = SurfaceErrorJson(*r.error, r.error_time_ms);
    return j;
}

// ---- The kind ---------------------------------------------------------------------------------

class SimplifyJobKind final : public JobKind {
public:
    v1::JobSpec::JobCase Case() const override { return v1::JobSpec::kSimplify; }
    std::string_view Name() const override { return "simplify"; }
    std::string_view Stage() const override { return "simplifying"; }
    std::size_t InputCount(const v1::JobSpec&) const override { return 1; }

    std::vector<CloudInput> Inputs(const v1::JobSpec& spec) const override {
        return {{"simplify.cloud_id", spec.simplify().cloud_id()}};
    }
    void SetInput(v1::JobSpec& spec, std::size_t index, const std::string& cloud_id) const override {
        SURFEL_CHECK(index == 0, index);
        spec.mutable_simplify()->set_cloud_id(cloud_id);
    }

    void Validate(const v1::JobSpec& spec) const override {
        const SimplifyOptions options = ToSimplifyOptions(spec.simplify());
        WithFieldPrefix("simplify", [&] { options.Validate(); });
    }

    std::pair<std::string, std::string> ResultType(const v1::JobSpec&) const override {
        return {"application/ply", ".ply"};
    }

    JobOutput Run(const v1::JobSpec& spec, const Clouds& clouds, const ProgressFn& progress) const override {
        const v1::SimplifyJob& job = spec.simplify();
        SimplifyResult r;
        WithFieldPrefix("simplify", [&] { r = Simplify(*clouds.at(0), ToSimplifyOptions(job), progress); });
        PlyWriteOptions w;
        w.format = job.ascii() ? PlyFormat::kAscii : PlyFormat::kBinaryLittleEndian;
        w.comments.push_back(std::string("surfel simplify ") + r.report.method);
        JobOutput out;
        std::tie(out.media_type, out.extension) = ResultType(spec);
        out.bytes = FormatPly(r.cloud, w);
        out.report = SimplifyReportJson(r.report);
        out.points = r.cloud.size();
        out.time_ms = r.report.time_ms;
        return out;
    }

    /// The cloud; per input point the neighbour graph, covariances and the method's clusters or
    /// heap (SimplifyBytesPerPoint); the output cloud and its PLY bytes.
    std::uint64_t EstimateMemory(const v1::JobSpec& spec, std::span<const CloudFacts> inputs) const override {
        const CloudFacts& in = inputs[0];
        const std::uint64_t out = spec.simplify().target() ? std::min<std::uint64_t>(spec.simplify().target(), in.points)
                                                           : in.points;
        const std::uint64_t per_point = SimplifyBytesPerPoint(ToSimplifyOptions(spec.simplify()).method);
        const std::uint64_t work = per_point * in.points + 2 * out * PointBytes(in.attributes);
        return CloudBytes(in) + std::max(in.file_bytes, work);
    }

    v1::JobSpec Example() const override {
        v1::JobSpec spec;
        spec.mutable_simplify()->set_target(200);
        return spec;
    }
};

}  // namespace

const JobKind& SimplifyKind() {
    static const SimplifyJobKind kind;
    return kind;
}

}  // namespace surfel::worker
