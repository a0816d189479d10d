// The render job: a ray-traced image of the Adamson-Alexa surface (core/surfel/render).

#include <algorithm>

#include "surfel/base/error.h"
#include "surfel/base/validate.h"
#include "surfel/io/image.h"
#include "surfel/render/csg_render.h"
#include "surfel/render/renderer.h"
#include "surfel/worker/jobs/jobs.h"

namespace surfel::worker {
namespace {

// ---- Memory estimate constants (docs/memory.md; checked by bench/memory_estimates.py) --------
/// Per point: the Adamson-Alexa surface's neighbour data, the packed balls and Embree's BVH.
constexpr std::uint64_t kRenderBytesPerPoint = 140;
/// Embree's and TBB's arenas and the EXR plugin (OpenEXR alone, opened by the first render).
constexpr std::uint64_t kRenderFixedBytes = 6ull << 20;
constexpr std::uint64_t kImageBytesPerPixel = 32;    ///< 8 float channels
constexpr std::uint64_t kExrFloatBytesPerPixel = 8;  ///< the codec's line buffers; it reads our channels
constexpr std::uint64_t kExrHalfBytesPerPixel = 16;  ///< the channels converted to half
constexpr std::uint64_t kPngBytesPerPixel = 6;       ///< 8-bit RGB buffer + the PNG file
/// Per point of a cloud without normals under normal-aware weights (the default): the estimate
/// of its normals in the set-up (neighbour table, covariances, the orientation's tree), a peak
/// before the image is allocated.
constexpr std::uint64_t kRenderNormalEstimateBytesPerPoint = 264;
/// PNG goes through the OpenImageIO plugin, whose ~260 libraries a first PNG loads.
constexpr std::uint64_t kPngFixedBytes = 96ull << 20;
// Fitted to peak RSS (bench/memory_estimates.py -> bench/results-memory.md): bunny 512^2 and
// 2048^2, person_scan 256^2 and 1024^2, lucy 1024^2, dragon 4096^2 PNG.

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
    if (!v1::RenderJob::Quality_IsValid(job.quality())) Bad("quality", "unknown quality " + std::to_string(job.quality()));
    for (int i = 0; i < job.lights_size(); ++i)
        if (!v1::Light::Kind_IsValid(job.lights(i).kind()))
            Bad("lights[" + std::to_string(i) + "].kind", "unknown kind " + std::to_string(job.lights(i).kind()));
    CheckFinite("render.view", FromProto(job.view()));
    if (job.csg_op() == v1::BooleanJob::OP_UNSPECIFIED) {
        if (!job.csg_cloud_id().empty()) Bad("csg_op", "is required with csg_cloud_id (UNION, INTERSECTION, DIFFERENCE or REVERSE_DIFFERENCE)");
        if (job.has_csg_transform_b()) Bad("csg_transform_b", "needs csg_op (a CSG render)");
    } else {
        BooleanOpFromProto(job.csg_op(), "render.csg_op");
    }
}

bool IsCsg(const v1::RenderJob& job) { return job.csg_op() != v1::BooleanJob::OP_UNSPECIFIED; }

/// The boolean's options of a CSG render: B's placement (BooleanJob's defaults otherwise).
BooleanOptions ToCsgOptions(const v1::RenderJob& job) {
    BooleanOptions o;
    if (job.has_csg_transform_b()) o.transform = SimilarityFromProto(job.csg_transform_b(), "render.csg_transform_b");
    return o;
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
    // The preset first: the explicit fields below (weights, bandwidth, precision) override it.
    switch (job.quality()) {
        case v1::RenderJob::QUALITY_UNSPECIFIED: break;
        case v1::RenderJob::FULL: ApplyRenderQuality(RenderQuality::kFull, &o); break;
        case v1::RenderJob::PREVIEW: ApplyRenderQuality(RenderQuality::kPreview, &o); break;
        default: break;  // CheckProtoOnly refused it
    }
    o.shadows = !job.no_shadows();
    if (job.samples_per_pixel()) o.samples_per_pixel = job.samples_per_pixel();
    o.background = FromProto(job.background());
    o.creases = !job.no_creases();
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
    std::size_t InputCount(const v1::JobSpec& spec) const override { return IsCsg(spec.render()) ? 2 : 1; }

    std::vector<CloudInput> Inputs(const v1::JobSpec& spec) const override {
        if (IsCsg(spec.render()))
            return {{"render.cloud_id", spec.render().cloud_id()}, {"render.csg_cloud_id", spec.render().csg_cloud_id()}};
        return {{"render.cloud_id", spec.render().cloud_id()}};
    }
    void SetInput(v1::JobSpec& spec, std::size_t index, const std::string& cloud_id) const override {
        SURFEL_CHECK(index < InputCount(spec), index);
        if (index == 0) spec.mutable_render()->set_cloud_id(cloud_id);
        else spec.mutable_render()->set_csg_cloud_id(cloud_id);
    }

    void Validate(const v1::JobSpec& spec) const override {
        CheckProtoOnly(spec.render());
        if (IsCsg(spec.render())) {
            const BooleanOptions csg = ToCsgOptions(spec.render());
            WithFieldPrefix("render", [&] { csg.Validate(); });
        }
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
        const bool csg = IsCsg(job);
        const BooleanOptions csg_options = csg ? ToCsgOptions(job) : BooleanOptions{};
        // The default camera frames what the CSG render can show: A ∪ B for a union, A for
        // A − B, B (placed) for B − A, the overlap of the two boxes for an intersection (both
        // boxes when they do not overlap: the image is then empty anyway).
        BoundingBox bounds = cloud.Bounds();
        if (csg && !clouds.at(1)->empty()) {
            const BoundingBox bb = clouds.at(1)->Bounds();
            const Similarity& T = csg_options.transform;
            BoundingBox placed_b;
            for (int c = 0; c < 8; ++c) {
                const Vec3d corner((c & 1) ? bb.max.x() : bb.min.x(), (c & 2) ? bb.max.y() : bb.min.y(),
                                   (c & 4) ? bb.max.z() : bb.min.z());
                placed_b.Extend((T.scale * (T.rotation * corner) + T.translation).cast<float>());
            }
            BoundingBox both = bounds;
            both.Extend(placed_b.min);
            both.Extend(placed_b.max);
            switch (BooleanOpFromProto(job.csg_op(), "render.csg_op")) {
                case BooleanOp::kUnion: bounds = both; break;
                case BooleanOp::kDifference: break;  // inside A
                case BooleanOp::kReverseDifference: bounds = placed_b; break;
                case BooleanOp::kIntersection: {
                    BoundingBox overlap;
                    overlap.min = bounds.min.cwiseMax(placed_b.min);
                    overlap.max = bounds.max.cwiseMin(placed_b.max);
                    bounds = overlap.empty() ? both : overlap;
                    break;
                }
            }
        }
        const RenderOptions options = ToRenderOptions(job, bounds);
        WithFieldPrefix("render", [&] { options.Validate(); });
        // A missing image plugin fails here, before the render's work. The first render of a
        // process opens it (dlopen, not cancellable: ~0.3 s of CPU); a job cancelled or past its
        // deadline meanwhile stops right after, before the render's setup. EXR needs only the EXR
        // plugin (OpenEXR: a few ms), PNG the OpenImageIO one.
        LoadImageCodec(job.format() == v1::RenderJob::PNG ? ImageFormat::kPng : ImageFormat::kExr);
        if (progress && !progress(0.0)) throw Error(ErrorCode::kCancelled, "render: cancelled while loading the image plugin");
        RenderResult r;
        CsgRenderReport csg_report;
        if (csg) {
            // Core names B's placement "transform"; the spec calls it "csg_transform_b".
            try {
                CsgRenderResult c =
                    RenderCsg(cloud, *clouds.at(1), BooleanOpFromProto(job.csg_op(), "render.csg_op"), options,
                              csg_options, progress);
                r = std::move(c.render);
                csg_report = c.report;
            } catch (const Error& e) {
                std::string what = e.what();
                if (e.code() != ErrorCode::kInvalidArgument) throw;
                if (what.rfind("transform.", 0) == 0) what = "csg_transform_b." + what.substr(10);
                else if (what.rfind("b: ", 0) == 0) what = "csg_cloud_id: " + what.substr(3);
                else if (what.rfind("a: ", 0) == 0) what = "cloud_id: " + what.substr(3);
                throw Error(e.code(), "render." + what);
            }
        } else {
            WithFieldPrefix("render", [&] { r = Render(cloud, options, progress); });
        }
        ImageWriteOptions w;
        w.half = job.format() == v1::RenderJob::EXR_HALF;
        JobOutput out;
        std::tie(out.media_type, out.extension) = ResultType(spec);
        out.bytes = EncodeImage(r.image, out.extension == ".png" ? ImageFormat::kPng : ImageFormat::kExr, w);
        out.report = RenderReportJson(r.stats, cloud.size(), options.camera.width, options.camera.height);
        out.report["quality"] = job.quality() == v1::RenderJob::PREVIEW ? "preview" : "full";
        if (csg) {
            out.report["csg_op"] = BooleanOpName(BooleanOpFromProto(job.csg_op(), "render.csg_op"));
            out.report["points_b"] = clouds.at(1)->size();
            out.report["classifications"] = csg_report.classifications;
            out.report["queries_saved"] = csg_report.queries_saved;
            out.report["normals_estimated_a"] = csg_report.normals_estimated_a;
            out.report["normals_estimated_b"] = csg_report.normals_estimated_b;
        } else {
            out.report["creases"] = options.creases && HasSurfelPairs(cloud);
        }
        out.points = cloud.size();
        out.time_ms = r.stats.time_ms;
        return out;
    }

    /// The cloud; per point the surface's neighbour data and the BVH over its balls
    /// (kRenderBytesPerPoint); the image, 8 float channels a pixel; the encoded file (EXR: up to
    /// the raw channels plus the codec's copy; PNG: the 8-bit RGB buffer and the file).
    std::uint64_t EstimateMemory(const v1::JobSpec& spec, std::span<const CloudFacts> inputs) const override {
        const v1::RenderJob& job = spec.render();
        const RenderOptions defaults;
        const std::uint64_t w = job.width() ? job.width() : defaults.camera.width;
        const std::uint64_t h = job.height() ? job.height() : defaults.camera.height;
        const std::uint64_t pixels = w * h;
        std::uint64_t encode_per_pixel = kExrFloatBytesPerPixel;
        if (job.format() == v1::RenderJob::EXR_HALF) encode_per_pixel = kExrHalfBytesPerPixel;
        if (job.format() == v1::RenderJob::PNG) encode_per_pixel = kPngBytesPerPixel;
        const CloudFacts& in = inputs[0];
        // The set-up's normal estimate (a cloud without normals, normal-aware weights) ends before
        // the image is allocated: the larger of the two counts.
        const bool estimates_normals =
            std::find(in.attributes.begin(), in.attributes.end(), "normals") == in.attributes.end() &&
            ToRenderOptions(job, StandInBounds(job)).surface.normal_sigma > 0;
        const std::uint64_t image = pixels * (kImageBytesPerPixel + encode_per_pixel);
        const std::uint64_t normals = estimates_normals ? kRenderNormalEstimateBytesPerPoint * in.points : 0;
        const std::uint64_t work = kRenderFixedBytes + (job.format() == v1::RenderJob::PNG ? kPngFixedBytes : 0) +
                                   kRenderBytesPerPoint * in.points + std::max(image, normals);
        return CloudBytes(in) + std::max(in.file_bytes, work);
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
