// The render job: a ray-traced image of the Adamson-Alexa surface (core/surfel/render).

#include "surfel/base/error.h"
#include "surfel/base/validate.h"
#include "surfel/io/image.h"
#include "surfel/render/renderer.h"
#include "surfel/worker/jobs/jobs.h"

namespace surfel::worker {
namespace {

[[noreturn]] void Bad(const std::string& field, const std::string& what) { InvalidField("render." + field, what); }

// ---- proto -> RenderOptions ------------------------------------------------------------------
// Proto3's "0 / unset means the default" is resolved here; every default and limit is core's.

/// The fields of the proto that core does not see: enum values outside their enum, the view.
void CheckProtoOnly(const v1::RenderJob& job) {
    if (!v1::RenderJob::Degree_IsValid(job.degree())) Bad("degree", "unknown degree " + std::to_string(job.degree()));
    if (!v1::RenderJob::Format_IsValid(job.format())) Bad("format", "unknown format " + std::to_string(job.format()));
    if (!v1::RenderJob::Bandwidth_IsValid(job.bandwidth()))
        Bad("bandwidth", "unknown bandwidth " + std::to_string(job.bandwidth()));
    if (!v1::RenderJob::Weights_IsValid(job.weights())) Bad("weights", "unknown weights " + std::to_string(job.weights()));
    for (int i = 0; i < job.lights_size(); ++i)
        if (!v1::Light::Kind_IsValid(job.lights(i).kind()))
            Bad("lights[" + std::to_string(i) + "].kind", "unknown kind " + std::to_string(job.lights(i).kind()));
    CheckFinite("render.view", FromProto(job.view()));
}

/// Core options of `job` for a cloud with bounding box `bounds` (the default camera frames it).
RenderOptions ToRenderOptions(const v1::RenderJob& job, const BoundingBox& bounds) {
    const RenderOptions defaults;
    RenderOptions o;
    const int width = job.width() ? job.width() : defaults.camera.width;
    const int height = job.height() ? job.height() : defaults.camera.height;
    Vec3d view = FromProto(job.view());
    if (view.norm() == 0) view = Vec3d(0, 0, 1);
    const double fovy =
        job.has_camera() && job.camera().fovy_deg() != 0 ? job.camera().fovy_deg() : defaults.camera.fovy_deg;
    o.camera = Camera::Framing(bounds, width, height, view, fovy);
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
    if (job.samples_per_pixel()) o.samples_per_pixel = job.samples_per_pixel();
    o.background = FromProto(job.background());
    o.surface.h = static_cast<float>(job.h());
    o.surface.precision = static_cast<float>(job.precision());
    if (job.degree() != v1::RenderJob::DEGREE_UNSPECIFIED) o.surface.degree = static_cast<int>(job.degree()) - 1;
    if (job.max_iterations()) o.surface.max_iterations = job.max_iterations();
    switch (job.bandwidth()) {
        case v1::RenderJob::BANDWIDTH_UNSPECIFIED: break;
        case v1::RenderJob::FIXED: o.surface.bandwidth = AaBandwidth::kFixed; break;
        case v1::RenderJob::ADAPTIVE: o.surface.bandwidth = AaBandwidth::kAdaptive; break;
        default: break;  // CheckProtoOnly refused it
    }
    switch (job.weights()) {
        case v1::RenderJob::WEIGHTS_UNSPECIFIED: break;
        case v1::RenderJob::PLAIN: o.surface.normal_sigma = 0.0f; break;
        case v1::RenderJob::NORMAL_AWARE: o.surface.normal_sigma = kNormalAwareSigma; break;
        default: break;  // CheckProtoOnly refused it
    }
    return o;
}

/// Before the cloud is loaded the framing is not known; a stand-in box serves. It is centred
/// away from a given eye, so that "eye and target must differ" fires only when the spec gives
/// both and they coincide.
BoundingBox StandInBounds(const v1::RenderJob& job) {
    Vec3d centre = Vec3d::Zero();
    if (job.has_camera() && job.camera().has_target()) centre = FromProto(job.camera().target());
    else if (job.has_camera() && job.camera().has_eye()) centre = FromProto(job.camera().eye()) - Vec3d(0, 0, 3);
    BoundingBox box;
    if (!centre.allFinite()) centre = Vec3d::Zero();  // the camera's own check names the field
    box.Extend((centre - Vec3d::Constant(0.5)).cast<float>());
    box.Extend((centre + Vec3d::Constant(0.5)).cast<float>());
    return box;
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

// ---- The kind ---------------------------------------------------------------------------------

class RenderJobKind final : public JobKind {
public:
    v1::JobSpec::JobCase Case() const override { return v1::JobSpec::kRender; }
    std::string_view Name() const override { return "render"; }
    std::string_view Stage() const override { return "rendering"; }
    std::size_t InputCount() const override { return 1; }

    std::vector<CloudInput> Inputs(const v1::JobSpec& spec) const override {
        return {{"render.cloud_id", spec.render().cloud_id()}};
    }
    void SetInput(v1::JobSpec& spec, std::size_t index, const std::string& cloud_id) const override {
        SURFEL_CHECK(index == 0, index);
        spec.mutable_render()->set_cloud_id(cloud_id);
    }

    void Validate(const v1::JobSpec& spec) const override {
        CheckProtoOnly(spec.render());
        const RenderOptions options = ToRenderOptions(spec.render(), StandInBounds(spec.render()));
        WithFieldPrefix("render", [&] { options.Validate(); });
    }

    std::pair<std::string, std::string> ResultType(const v1::JobSpec& spec) const override {
        if (spec.render().format() == v1::RenderJob::PNG) return {"image/png", ".png"};
        return {"image/x-exr", ".exr"};
    }

    JobOutput Run(const v1::JobSpec& spec, const Clouds& clouds, const ProgressFn& progress) const override {
        const v1::RenderJob& job = spec.render();
        const PointCloud& cloud = *clouds.at(0);
        if (cloud.empty()) throw Error(ErrorCode::kInvalidArgument, "render: the cloud has no points");
        const RenderOptions options = ToRenderOptions(job, cloud.Bounds());
        WithFieldPrefix("render", [&] { options.Validate(); });
        // A missing image plugin fails here, before the render's work. The first render of a
        // process opens it (dlopen, not cancellable: ~0.3 s of CPU); a job cancelled or past its
        // deadline meanwhile stops right after, before the render's setup.
        LoadImageCodec();
        if (progress && !progress(0.0)) throw Error(ErrorCode::kCancelled, "render: cancelled while loading the image plugin");
        RenderResult r;
        WithFieldPrefix("render", [&] { r = Render(cloud, options, progress); });
        ImageWriteOptions w;
        w.half = job.format() == v1::RenderJob::EXR_HALF;
        JobOutput out;
        std::tie(out.media_type, out.extension) = ResultType(spec);
        out.bytes = EncodeImage(r.image, out.extension == ".png" ? ImageFormat::kPng : ImageFormat::kExr, w);
        out.report = RenderReportJson(r.stats, cloud.size(), options.camera.width, options.camera.height);
        out.points = cloud.size();
        out.time_ms = r.stats.time_ms;
        return out;
    }

    v1::JobSpec Example() const override {
        v1::JobSpec spec;
        v1::RenderJob& r = *spec.mutable_render();
        r.set_width(48);
        r.set_height(32);
        r.set_samples_per_pixel(2);
        return spec;
    }
};

}  // namespace

const JobKind& RenderKind() {
    static const RenderJobKind kind;
    return kind;
}

}  // namespace surfel::worker
