#include "surfel/worker/job_kind.h"

#include <google/protobuf/descriptor.h>

#include <map>

#include "surfel/base/error.h"
#include "surfel/worker/jobs/jobs.h"

namespace surfel::worker {

// ---- The lookup: the one switch over the spec's oneof ----------------------------------------

const JobKind* FindJobKind(v1::JobSpec::JobCase job_case) {
    switch (job_case) {
        case v1::JobSpec::kRender: return &RenderKind();
        case v1::JobSpec::kSimplify: return &SimplifyKind();
        case v1::JobSpec::kResample: return &ResampleKind();
        case v1::JobSpec::kBoolean: return &BooleanKind();
        case v1::JobSpec::JOB_NOT_SET: return nullptr;
    }
    return nullptr;  // a value outside the enum (never produced by protobuf)
}

std::span<const JobKind* const> JobKinds() {
    // Every field of the oneof, in declaration order: a kind the proto gains is listed here
    // without an edit, and the switch above fails to compile until it has its entry.
    static const std::vector<const JobKind*> kinds = [] {
        std::vector<const JobKind*> all;
        const google::protobuf::OneofDescriptor* oneof = v1::JobSpec::descriptor()->FindOneofByName("job");
        for (int i = 0; i < oneof->field_count(); ++i) {
            const auto job_case = static_cast<v1::JobSpec::JobCase>(oneof->field(i)->number());
            const JobKind* kind = FindJobKind(job_case);
            SURFEL_CHECK(kind != nullptr && kind->Case() == job_case, "no job kind for " << oneof->field(i)->name());
            all.push_back(kind);
        }
        return all;
    }();
    return kinds;
}

const JobKind* FindJobKind(std::string_view name) {
    for (const JobKind* kind : JobKinds())
        if (kind->Name() == name) return kind;
    return nullptr;
}

std::string JobKindNames() {
    std::string names;
    for (const JobKind* kind : JobKinds()) names += (names.empty() ? "" : ", ") + std::string(kind->Name());
    return names;
}

const JobKind& KindOf(const v1::JobSpec& spec) {
    const JobKind* kind = FindJobKind(spec.job_case());
    if (!kind) throw Error(ErrorCode::kInvalidArgument, "spec: no job given (" + JobKindNames() + ")");
    return *kind;
}

// ---- The path every job takes -----------------------------------------------------------------

void ValidateSpec(const v1::JobSpec& spec) {
    const JobKind& kind = KindOf(spec);
    if (spec.timeout_ms() < 0) throw Error(ErrorCode::kInvalidArgument, "timeout_ms: must be >= 0");
    for (const CloudInput& input : kind.Inputs(spec))
        if (input.id.empty()) throw Error(ErrorCode::kInvalidArgument, input.field + ": is required");
    kind.Validate(spec);
}

JobOutput RunJob(const v1::JobSpec& spec, const CloudLoader& load, const ProgressFn& progress,
                 const MemoryAdmit& admit) {
    ValidateSpec(spec);
    const JobKind& kind = KindOf(spec);
    Clouds clouds;
    std::map<std::string, std::shared_ptr<const PointCloud>> loaded;  // one load per distinct id
    for (const CloudInput& input : kind.Inputs(spec)) {
        auto& cloud = loaded[input.id];
        if (!cloud) cloud = load(input.id);
        SURFEL_CHECK(cloud != nullptr, "the cloud loader returned nothing for " << input.id);
        clouds.push_back(cloud);
    }
    // The estimate from the loaded clouds (the file's size taken as 0: it is freed by now).
    std::vector<CloudFacts> facts;
    for (const auto& cloud : clouds) facts.push_back(FactsOf(*cloud, 0));
    const std::uint64_t estimate = kind.EstimateMemory(spec, facts);
    if (admit) admit(estimate);
    JobOutput out = kind.Run(spec, clouds, progress);
    out.report["memory_estimate_bytes"] = estimate;
    return out;
}

// ---- Adapters shared by the kinds ---------------------------------------------------------------

v1::Vec3 ToProto(const Vec3d& v) {
    v1::Vec3 p;
    p.set_x(v.x());
    p.set_y(v.y());
    p.set_z(v.z());
    return p;
}

Vec3d FromProto(const v1::Vec3& v) { return {v.x(), v.y(), v.z()}; }

}  // namespace surfel::worker
