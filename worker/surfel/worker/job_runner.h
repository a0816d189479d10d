#pragma once
/// \file
/// Runs one job (a surfel.v1.JobSpec) on the core library: the proto <-> core adapters shared
/// by the server's worker pool and the CLI's in-process mode.

#include <functional>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "surfel/base/point_cloud.h"
#include "surfel/base/progress.h"
#include "surfel/render/renderer.h"
#include "surfel/simplify/simplify.h"
#include "surfel/v1/surfel.pb.h"

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

/// Gives the cloud a job names (by id). Throws Error(kNotFound) for an unknown id.
using CloudLoader = std::function<PointCloud(const std::string& cloud_id)>;

/// A point or direction as the proto's Vec3, and back.
v1::Vec3 ToProto(const Vec3d& v);
Vec3d FromProto(const v1::Vec3& v);

/// "render" or "simplify"; throws Error(kInvalidArgument) for an empty spec.
std::string JobType(const v1::JobSpec& spec);
/// The cloud ids a job reads.
std::vector<std::string> JobCloudIds(const v1::JobSpec& spec);
/// Checks every option's range; throws Error(kInvalidArgument) naming the field
/// ("render.width: must lie in 1..16384, got 0").
void ValidateSpec(const v1::JobSpec& spec);

/// Core options of a render job for `cloud` (the default camera frames its bounding box).
RenderOptions ToRenderOptions(const v1::RenderJob& job, const PointCloud& cloud);
/// Core options of a simplify job.
SimplifyOptions ToSimplifyOptions(const v1::SimplifyJob& job);

/// The JSON reports (also the service's JobResult.report_json).
nlohmann::json RenderReportJson(const RenderStats& stats, std::size_t points, int width, int height);
nlohmann::json SimplifyReportJson(const SimplifyReport& report);

/// Validates and runs `spec`. Errors are surfel::Error (kInvalidArgument for bad options or
/// input, kCancelled when `progress` asks to stop).
JobOutput RunJob(const v1::JobSpec& spec, const CloudLoader& load, const ProgressFn& progress = {});

}  // namespace surfel::worker
