#pragma once
/// \file
/// The table of job kinds. Each kind (render, simplify, ...) lives in one file under jobs/ and
/// says everything the CLI, the server, the job manager and the metrics need to know about it:
/// its name, its stage label, the clouds it reads, how to validate its spec (proto -> core
/// Options -> Options::Validate()), how to run it and what its result is. The one `switch` over
/// `JobSpec::job_case()` is FindJobKind (job_kind.cpp), so `-Wswitch -Werror` stops the build
/// when a kind in the proto has no entry. docs/extending.md lists the files a new kind touches.

#include <cstdint>
#include <functional>
#include <memory>
#include <nlohmann/json.hpp>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "surfel/base/point_cloud.h"
#include "surfel/base/progress.h"
#include "surfel/base/validate.h"  // WithFieldPrefix, used by every kind
#include "surfel/v1/surfel.pb.h"
#include "surfel/worker/memory.h"

namespace surfel::worker {

/// A job's result: the bytes of one file and its report.
struct JobOutput {
    std::string bytes;
    std::string media_type;  ///< "application/ply", "image/x-exr", "image/png"
    std::string extension;   ///< ".ply", ".exr", ".png"
    nlohmann::json report;   ///< What `surfel <job> --json` prints (without "output").
    std::uint64_t points = 0;
    double time_ms = 0.0;    ///< The algorithm alone.
};

/// One cloud a job reads: the spec's field that names it ("render.cloud_id") and its id.
struct CloudInput {
    std::string field;
    std::string id;
};

/// The clouds of a job, loaded, in the order of JobKind::Inputs. Shared, never copied per job.
using Clouds = std::vector<std::shared_ptr<const PointCloud>>;

/// Gives the cloud a job names (by id; in-process, the id is the file's path). Throws
/// Error(kNotFound) for an unknown id.
using CloudLoader = std::function<std::shared_ptr<const PointCloud>(const std::string& cloud_id)>;

/// One kind of job. Implementations are stateless singletons (jobs/*.cpp).
class JobKind {
public:
    virtual ~JobKind() = default;

    /// The oneof case of JobSpec this kind handles.
    virtual v1::JobSpec::JobCase Case() const = 0;
    /// "render", "simplify": Job.type, the CLI subcommand and the metrics label.
    virtual std::string_view Name() const = 0;
    /// What a running job of this kind is doing ("rendering"), for progress events.
    virtual std::string_view Stage() const = 0;
    /// Number of input clouds `spec` reads (1 for render and simplify, 2 for a boolean and for a
    /// CSG render, whose spec sets render.csg_op).
    virtual std::size_t InputCount(const v1::JobSpec& spec) const = 0;
    /// The clouds `spec` reads, InputCount(spec) of them, with their field paths.
    virtual std::vector<CloudInput> Inputs(const v1::JobSpec& spec) const = 0;
    /// Sets input `index` (0 <= index < InputCount(spec)) of `spec` to `cloud_id`.
    virtual void SetInput(v1::JobSpec& spec, std::size_t index, const std::string& cloud_id) const = 0;
    /// Checks every option: proto -> core Options -> Options::Validate(), with the field path
    /// prefixed ("render.width: must lie in 1..16384, got 0"). Throws Error(kInvalidArgument).
    /// Cloud ids are checked by ValidateSpec, their existence by whoever loads them.
    virtual void Validate(const v1::JobSpec& spec) const = 0;
    /// Media type and extension of the result `spec` asks for.
    virtual std::pair<std::string, std::string> ResultType(const v1::JobSpec& spec) const = 0;
    /// Runs a validated `spec` on its clouds (in Inputs order).
    virtual JobOutput Run(const v1::JobSpec& spec, const Clouds& clouds, const ProgressFn& progress) const = 0;
    /// Peak memory (bytes, beyond the process's baseline) a run of the validated `spec` on clouds
    /// with these facts (InputCount(spec) of them, in Inputs order) needs: loading, the algorithm's
    /// data structures and the encoded result. Derived from the data structures the kind's core
    /// code allocates; docs/memory.md lists the terms and the measured check.
    virtual std::uint64_t EstimateMemory(const v1::JobSpec& spec, std::span<const CloudFacts> inputs) const = 0;
    /// A small valid spec of this kind with empty cloud ids, quick to run on a few thousand points
    /// (the parameterised tests run it for every kind).
    virtual v1::JobSpec Example() const = 0;
};

/// The kind of `spec`; throws Error(kInvalidArgument) "spec: no job given (render, simplify)"
/// when its oneof is empty.
const JobKind& KindOf(const v1::JobSpec& spec);
/// The kind handling `job_case`; nullptr for JOB_NOT_SET. The only switch over JobCase.
const JobKind* FindJobKind(v1::JobSpec::JobCase job_case);
/// The kind named `name` ("render"); nullptr when there is none.
const JobKind* FindJobKind(std::string_view name);
/// Every kind, in the order of the proto's oneof.
std::span<const JobKind* const> JobKinds();
/// "render, simplify": the kinds' names, for messages and help texts.
std::string JobKindNames();

/// Checks `spec` whole: one kind given, timeout_ms >= 0, every cloud id present, the kind's
/// options. Throws Error(kInvalidArgument) naming the field.
void ValidateSpec(const v1::JobSpec& spec);

/// Called by RunJob with the job's memory estimate once its clouds are loaded, before the work;
/// throws (Error(kResourceExhausted), see CheckJobMemory) to refuse the job.
using MemoryAdmit = std::function<void(std::uint64_t estimate)>;

/// Validates `spec`, loads its clouds through `load`, asks `admit` (when given) about its memory
/// estimate and runs it; the report gets "memory_estimate_bytes". Errors are surfel::Error
/// (kInvalidArgument for bad options or input, kNotFound for an unknown cloud, kCancelled when
/// `progress` asks to stop, what `admit` throws).
JobOutput RunJob(const v1::JobSpec& spec, const CloudLoader& load, const ProgressFn& progress = {},
                 const MemoryAdmit& admit = {});

/// A point or direction as the proto's Vec3, and back.
v1::Vec3 ToProto(const Vec3d& v);
Vec3d FromProto(const v1::Vec3& v);

}  // namespace surfel::worker
