#include "surfel/worker/job_runner.h"

#include <cmath>
#include <sstream>
#include <string>

#include "surfel/base/error.h"
#include "surfel/io/image.h"
#include "surfel/io/ply.h"

namespace surfel::worker {
namespace {

[[noreturn]] void Bad(const std::string& field, const std::string& what) {
    throw Error(ErrorCode::kInvalidArgument, field + ": " + what);
}

void CheckRange(const std::string& field, double value, double lo, double hi) {
    if (std::isfinite(value) && value >= lo && value <= hi) return;
    std::ostringstream msg;
    msg << "must lie in " << lo << ".." << hi << ", got " << value;
    Bad(field, msg.str());
}

void CheckFinite(const std::string& field, const v1::Vec3& v) {
    if (!std::isfinite(v.x()) || !std::isfinite(v.y()) || !std::isfinite(v.z())) Bad(field, "must be finite");
}

void CheckCloudId(const std::string& field, const std::string& id) {
    if (id.empty()) Bad(field, "is required");
}

}  // namespace

v1::Vec3 ToProto(const Vec3d& v) {
    v1::Vec3 p;
    p.set_x(v.x());
    p.set_y(v.y());
    p.set_z(v.z());
    return p;
}

Vec3d FromProto(const v1::Vec3& v) { return {v.x(), v.y(), v.z()}; }

std::string JobType(const v1::JobSpec& spec) {
    switch (spec.job_case()) {
        case v1::JobSpec::kRender: return "render";
        case v1::JobSpec::kSimplify: return "simplify";
        case v1::JobSpec::JOB_NOT_SET: break;
    }
    Bad("spec", "no job given (render or simplify)");
}

std::vector<std::string> JobCloudIds(const v1::JobSpec& spec) {
    switch (spec.job_case()) {
        case v1::JobSpec::kRender: return {spec.render().cloud_id()};
        case v1::JobSpec::kSimplify: return {spec.simplify().cloud_id()};
        case v1::JobSpec::JOB_NOT_SET: break;
    }
    return {};
}

void ValidateSpec(const v1::JobSpec& spec) {
    JobType(spec);
    if (spec.timeout_ms() < 0) Bad("timeout_ms", "must be >= 0");
    if (spec.has_render()) {
        const v1::RenderJob& r = spec.render();
        CheckCloudId("render.cloud_id", r.cloud_id());
        if (r.width() != 0) CheckRange("render.width", r.width(), 1, 16384);
        if (r.height() != 0) CheckRange("render.height", r.height(), 1, 16384);
        if (r.samples_per_pixel() != 0) CheckRange("render.samples_per_pixel", r.samples_per_pixel(), 1, 1024);
        CheckRange("render.h", r.h(), 0, 1e30);
        CheckRange("render.precision", r.precision(), 0, 1e30);
        if (!v1::RenderJob::Degree_IsValid(r.degree())) Bad("render.degree", "unknown degree");
        CheckRange("render.max_iterations", r.max_iterations(), 0, 1000);
        CheckFinite("render.view", r.view());
        CheckFinite("render.background", r.background());
        if (r.has_camera()) {
            CheckFinite("render.camera.eye", r.camera().eye());
            CheckFinite("render.camera.target", r.camera().target());
            CheckFinite("render.camera.up", r.camera().up());
            if (r.camera().fovy_deg() != 0) CheckRange("render.camera.fovy_deg", r.camera().fovy_deg(), 1, 179);
            if (r.camera().has_eye() && r.camera().has_target() &&
                FromProto(r.camera().eye()) == FromProto(r.camera().target()))
                Bad("render.camera", "eye and target must differ");
        }
        if (r.lights_size() > 64) Bad("render.lights", "at most 64 lights");
        for (int i = 0; i < r.lights_size(); ++i) {
            const std::string f = "render.lights[" + std::to_string(i) + "]";
            CheckFinite(f + ".vector", r.lights(i).vector());
            CheckFinite(f + ".color", r.lights(i).color());
            CheckRange(f + ".intensity", r.lights(i).intensity(), 0, 1e6);
            if (r.lights(i).kind() == v1::Light::DIRECTIONAL && FromProto(r.lights(i).vector()).norm() == 0)
                Bad(f + ".vector", "a directional light needs a non-zero direction");
        }
        if (!v1::RenderJob::Format_IsValid(r.format())) Bad("render.format", "unknown format");
    } else {
        const v1::SimplifyJob& s = spec.simplify();
        CheckCloudId("simplify.cloud_id", s.cloud_id());
        if (!v1::SimplifyJob::Method_IsValid(s.method())) Bad("simplify.method", "unknown method");
        CheckRange("simplify.error", s.error(), 0, 1e30);
        if (s.target() > 0 && s.error() > 0) Bad("simplify", "give target or error, not both");
        if (s.max_variation() != 0) CheckRange("simplify.max_variation", s.max_variation(), 1e-12, 1.0 / 3.0);
        const auto method = s.method();
        const bool own_bound = method == v1::SimplifyJob::HIERARCHICAL || method == v1::SimplifyJob::INCREMENTAL;
        const bool error_bound = method == v1::SimplifyJob::HIERARCHICAL || method == v1::SimplifyJob::ITERATIVE;
        if (s.error() > 0 && !error_bound) Bad("simplify.error", "this method takes a target, not an error bound");
        if (s.target() == 0 && s.error() == 0 && !own_bound) Bad("simplify.target", "is required for this method");
    }
}

RenderOptions ToRenderOptions(const v1::RenderJob& job, const PointCloud& cloud) {
    RenderOptions o;
    const int width = job.width() ? job.width() : 512, height = job.height() ? job.height() : 512;
    Vec3d view = FromProto(job.view());
    if (view.norm() == 0) view = Vec3d(0, 0, 1);
    const double fovy = job.has_camera() && job.camera().fovy_deg() != 0 ? job.camera().fovy_deg() : 40.0;
    o.camera = Camera::Framing(cloud.Bounds(), width, height, view, fovy);
    if (job.has_camera()) {
        const v1::Camera& c = job.camera();
        if (c.has_eye()) o.camera.eye = FromProto(c.eye());
        if (c.has_target()) o.camera.target = FromProto(c.target());
        if (c.has_up()) o.camera.up = FromProto(c.up());
    }
    for (const v1::Light& l : job.lights()) {
        Light L;
        L.kind = l.kind() == v1::Light::POINT ? Light::Kind::kPoint : Light::Kind::kDirectional;
        L.vector = FromProto(l.vector());
        if (l.has_color()) L.color = FromProto(l.color());
        if (l.intensity() != 0) L.intensity = l.intensity();
        o.lights.push_back(L);
    }
    o.shadows = !job.no_shadows();
    o.samples_per_pixel = job.samples_per_pixel() ? job.samples_per_pixel() : 1;
    o.background = FromProto(job.background());
    o.surface.h = static_cast<float>(job.h());
    o.surface.precision = static_cast<float>(job.precision());
    if (job.degree() != v1::RenderJob::DEGREE_UNSPECIFIED) o.surface.degree = static_cast<int>(job.degree()) - 1;
    if (job.max_iterations()) o.surface.max_iterations = job.max_iterations();
    return o;
}

SimplifyOptions ToSimplifyOptions(const v1::SimplifyJob& job) {
    SimplifyOptions o;
    switch (job.method()) {
        case v1::SimplifyJob::INCREMENTAL: o.method = SimplifyMethod::kIncremental; break;
        case v1::SimplifyJob::ITERATIVE: o.method = SimplifyMethod::kIterative; break;
        case v1::SimplifyJob::PARTICLE: o.method = SimplifyMethod::kParticle; break;
        case v1::SimplifyJob::VOXEL: o.method = SimplifyMethod::kVoxel; break;
        default: o.method = SimplifyMethod::kHierarchical; break;
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

nlohmann::json RenderReportJson(const RenderStats& s, std::size_t points, int width, int height) {
    return {{"points", points},
            {"width", width},
            {"height", height},
            {"rays", s.primary_rays},
            {"shadow_rays", s.shadow_rays},
            {"hits", s.hits},
            {"average_iterations", s.AverageIterations()},
            {"evaluations", s.surface.evaluations},
            {"cache_hits", s.surface.cache_hits},
            {"h", s.h},
            {"precision", s.precision},
            {"rays_per_second", s.time_ms > 0 ? 1000.0 * double(s.primary_rays + s.shadow_rays) / s.time_ms : 0.0},
            {"setup_ms", s.setup_ms},
            {"time_ms", s.time_ms}};
}

nlohmann::json SimplifyReportJson(const SimplifyReport& r) {
    nlohmann::json j = {{"points", r.output_points},
                        {"input_points", r.input_points},
                        {"method", r.method},
                        {"adaptive", r.adaptive},
                        {"time_ms", r.time_ms},
                        {"peak_rss_mb", r.peak_rss_mb},
                        {"normals_estimated", r.normals_estimated}};
    if (r.error) {
        j["error"] = {{"max", r.error->max},
                      {"avg", r.error->avg},
                      {"max_relative", r.error->max_relative()},
                      {"avg_relative", r.error->avg_relative()},
                      {"avg_per_sample_relative", r.error->avg_per_sample_relative()},
                      {"samples", r.error->samples},
                      {"failed", r.error->failed},
                      {"time_ms", r.error_time_ms}};
    }
    return j;
}

JobOutput RunJob(const v1::JobSpec& spec, const CloudLoader& load, const ProgressFn& progress) {
    ValidateSpec(spec);
    JobOutput out;
    if (spec.has_render()) {
        const v1::RenderJob& job = spec.render();
        const PointCloud cloud = load(job.cloud_id());
        if (cloud.empty()) throw Error(ErrorCode::kInvalidArgument, "render: the cloud has no points");
        const RenderOptions options = ToRenderOptions(job, cloud);
        const RenderResult r = Render(cloud, options, progress);
        ImageWriteOptions w;
        w.half = job.format() == v1::RenderJob::EXR_HALF;
        const bool png = job.format() == v1::RenderJob::PNG;
        out.bytes = EncodeImage(r.image, png ? ImageFormat::kPng : ImageFormat::kExr, w);
        out.media_type = png ? "image/png" : "image/x-exr";
        out.extension = png ? ".png" : ".exr";
        out.report = RenderReportJson(r.stats, cloud.size(), options.camera.width, options.camera.height);
        out.points = cloud.size();
        out.time_ms = r.stats.time_ms;
    } else {
        const v1::SimplifyJob& job = spec.simplify();
        const PointCloud cloud = load(job.cloud_id());
        const SimplifyResult r = Simplify(cloud, ToSimplifyOptions(job), progress);
        PlyWriteOptions w;
        w.format = job.ascii() ? PlyFormat::kAscii : PlyFormat::kBinaryLittleEndian;
        w.comments.push_back(std::string("surfel simplify ") + r.report.method);
        out.bytes = FormatPly(r.cloud, w);
        out.media_type = "application/ply";
        out.extension = ".ply";
        out.report = SimplifyReportJson(r.report);
        out.points = r.cloud.size();
        out.time_ms = r.report.time_ms;
    }
    return out;
}

}  // namespace surfel::worker
