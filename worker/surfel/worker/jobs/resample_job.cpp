// The resample job: particle resampling, MLS smoothing and densification by splitting on the
// MLS surface (core/surfel/resample).

#include <algorithm>

#include "surfel/base/error.h"
#include "surfel/io/ply.h"
#include "surfel/resample/resample.h"
#include "surfel/worker/jobs/jobs.h"
#include "surfel/worker/jobs/reports.h"

namespace surfel::worker {
namespace {

/// Memory estimate constants (docs/memory.md).
constexpr std::uint64_t kResampleBytesPerInput = 250;
/// Per output point of the particle methods (particle, split): the particle, its padded
/// neighbour list, grid cells and the final MLS fit; fitted to peak RSS (bench/results-memory.md).
constexpr std::uint64_t kResampleBytesPerParticle = 320;
/// Per output point of MLS smoothing (one projection per input point).
constexpr std::uint64_t kResampleBytesPerOutput = 100;

// ---- proto -> ResampleOptions ----------------------------------------------------------------
// Proto3's "0 / unset means the default" is resolved here; every default and limit is core's.

ResampleOptions ToResampleOptions(const v1::ResampleJob& job) {
    const ResampleOptions defaults;
    ResampleOptions o;
    switch (job.method()) {
        case v1::ResampleJob::METHOD_UNSPECIFIED: o.method = defaults.method; break;
        case v1::ResampleJob::PARTICLE: o.method = ResampleMethod::kParticle; break;
        case v1::ResampleJob::MLS: o.method = ResampleMethod::kMls; break;
        case v1::ResampleJob::SPLIT: o.method = ResampleMethod::kSplit; break;
        default:
            throw Error(ErrorCode::kInvalidArgument, "resample.method: unknown method " + std::to_string(job.method()));
    }
    o.target = job.target();
    o.spacing = job.spacing();
    o.adaptive = job.adaptive();
    o.keep_input = job.keep_input();
    if (job.seed()) o.seed = job.seed();
    if (job.iterations()) o.iterations = job.iterations();
    o.measure_error = !job.no_error_report();
    if (!v1::ResampleJob::Degree_IsValid(job.mls_degree()))
        throw Error(ErrorCode::kInvalidArgument, "resample.mls_degree: unknown degree " + std::to_string(job.mls_degree()));
    if (job.mls_degree() != v1::ResampleJob::DEGREE_UNSPECIFIED) o.mls_degree = static_cast<int>(job.mls_degree()) - 1;
    o.mls_h = job.mls_h();
    return o;
}

nlohmann::json ResampleReportJson(const ResampleReport& r) {
    nlohmann::json j = {{"points", r.output_points},
                        {"input_points", r.input_points},
                        {"method", r.method},
                        {"adaptive", r.adaptive},
                        {"keep_input", r.keep_input},
                        {"iterations", r.iterations},
                        {"spacing_mean", r.spacing_mean},
                        {"spacing_cv", r.spacing_cv},
                        {"time_ms", r.time_ms},
                        {"normals_estimated", r.normals_estimated}};
    if (r.method == ResampleMethodName(ResampleMethod::kMls)) {
        j["mls_h"] = r.mls_h;
        j["noise"] = r.noise;
        j["mls_failed"] = r.mls_failed;
    }
    if (r.method == ResampleMethodName(ResampleMethod::kSplit)) {
        j["splits"] = r.splits;
        j["max_spacing"] = r.max_spacing;
        j["above_target"] = r.above_target;
        j["above_target_regions"] = r.above_target_regions;
        j["rim_samples"] = r.rim_samples;
    }
    if (r.error) j["error"] = SurfaceErrorJson(*r.error, r.error_time_ms);
    return j;
}

// ---- The kind ---------------------------------------------------------------------------------

class ResampleJobKind final : public JobKind {
public:
    v1::JobSpec::JobCase Case() const override { return v1::JobSpec::kResample; }
    std::string_view Name() const override { return "resample"; }
    std::string_view Stage() const override { return "resampling"; }
    std::size_t InputCount(const v1::JobSpec&) const override { return 1; }

    std::vector<CloudInput> Inputs(const v1::JobSpec& spec) const override {
        return {{"resample.cloud_id", spec.resample().cloud_id()}};
    }
    void SetInput(v1::JobSpec& spec, std::size_t index, const std::string& cloud_id) const override {
        SURFEL_CHECK(index == 0, index);
        spec.mutable_resample()->set_cloud_id(cloud_id);
    }

    void Validate(const v1::JobSpec& spec) const override {
        const ResampleOptions options = ToResampleOptions(spec.resample());
        WithFieldPrefix("resample", [&] { options.Validate(); });
    }

    std::pair<std::string, std::string> ResultType(const v1::JobSpec&) const override {
        return {"application/ply", ".ply"};
    }

    JobOutput Run(const v1::JobSpec& spec, const Clouds& clouds, const ProgressFn& progress) const override {
        const v1::ResampleJob& job = spec.resample();
        ResampleResult r;
        WithFieldPrefix("resample", [&] { r = Resample(*clouds.at(0), ToResampleOptions(job), progress); });
        PlyWriteOptions w;
        w.format = job.ascii() ? PlyFormat::kAscii : PlyFormat::kBinaryLittleEndian;
        w.comments.push_back(std::string("surfel resample ") + r.report.method);
        JobOutput out;
        std::tie(out.media_type, out.extension) = ResultType(spec);
        out.bytes = FormatPly(r.cloud, w);
        out.report = ResampleReportJson(r.report);
        out.points = r.cloud.size();
        out.time_ms = r.report.time_ms;
        return out;
    }

    /// The cloud; per input point its kd-tree and local frames (kResampleBytesPerInput); per
    /// output point the particle, its neighbour list and grid cell (kResampleBytesPerParticle;
    /// MLS smoothing: kResampleBytesPerOutput),
    /// the output cloud and its PLY bytes. The output count: `target`, or from `spacing` over
    /// the bounding box's area (PointsAtSpacing), or the input's (mls).
    std::uint64_t EstimateMemory(const v1::JobSpec& spec, std::span<const CloudFacts> inputs) const override {
        const v1::ResampleJob& job = spec.resample();
        const CloudFacts& in = inputs[0];
        std::uint64_t out = in.points;
        if (job.target()) out = job.target();
        else if (job.spacing() > 0) out = PointsAtSpacing(in.extent, job.spacing());
        if (job.keep_input()) out = std::max(out, in.points);
        const std::uint64_t out_bytes = PointBytes(in.attributes) + 12;  // normals always written
        const std::uint64_t per_output = ToResampleOptions(job).method == ResampleMethod::kMls
                                             ? kResampleBytesPerOutput
                                             : kResampleBytesPerParticle;
        const std::uint64_t work = kResampleBytesPerInput * in.points + out * (per_output + 2 * out_bytes);
        return CloudBytes(in) + std::max(in.file_bytes, work);
    }

    v1::JobSpec Example() const override {
        v1::JobSpec spec;
        spec.mutable_resample()->set_target(600);
        spec.mutable_resample()->set_iterations(10);
        return spec;
    }
};

}  // namespace

const JobKind& ResampleKind() {
    static const ResampleJobKind kind;
    return kind;
}

}  // namespace surfel::worker
