#include "surfel/render/renderer.h"

#include <embree3/rtcore.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <array>
#include <atomic>
#include <cmath>
#include <deque>
#include <exception>
#include <limits>
#include <mutex>
#include <numbers>

#include "surfel/base/error.h"
#include "surfel/base/validate.h"
#include "surfel/render/csg_render.h"
#include "surfel/render/surface_layers.h"

namespace surfel {

Camera::Frame Camera::MakeFrame() const {
    Frame f;
    f.w = (target - eye).normalized();
    f.u = f.w.cross(up).normalized();
    f.v = f.u.cross(f.w);
    f.sy = std::tan(0.5 * fovy_deg * std::numbers::pi / 180.0);
    f.sx = f.sy * double(width) / height;
    f.width = width;
    f.height = height;
    return f;
}

Camera Camera::Framing(const BoundingBox& box, int width, int height, const Vec3d& from, double fovy_deg) {
    Camera c;
    c.width = width;
    c.height = height;
    c.fovy_deg = fovy_deg;
    c.target = box.Center().cast<double>();
    const double radius = std::max(0.5 * box.Diagonal(), 1e-9);
    const double half = 0.5 * fovy_deg * std::numbers::pi / 180.0;
    const double fit = std::min(half, std::atan(std::tan(half) * double(width) / height));
    c.eye = c.target + from.normalized() * (1.05 * radius / std::sin(fit));
    c.up = std::abs(from.normalized().y()) > 0.99 ? Vec3d(0, 0, -1) : Vec3d(0, 1, 0);
    return c;
}

namespace {

// ---- Validation -----------------------------------------------------------------------------

void ValidateCamera(const Camera& cam) {
    CheckRange("width", cam.width, 1, kMaxImageSide);
    CheckRange("height", cam.height, 1, kMaxImageSide);
    CheckRange("camera.fovy_deg", cam.fovy_deg, kMinFovyDeg, kMaxFovyDeg);
    CheckFinite("camera.eye", cam.eye);
    CheckFinite("camera.target", cam.target);
    CheckFinite("camera.up", cam.up);
    if ((cam.target - cam.eye).norm() == 0) InvalidField("camera", "eye and target must differ");
    if ((cam.target - cam.eye).normalized().cross(cam.up).norm() < 1e-9)
        InvalidField("camera.up", "must be non-zero and not parallel to the view direction");
}

void ValidateLights(const std::vector<Light>& lights) {
    if (lights.size() > std::size_t(kMaxLights))
        InvalidField("lights", "at most " + std::to_string(kMaxLights) + " lights");
    for (std::size_t i = 0; i < lights.size(); ++i) {
        const Light& L = lights[i];
        const std::string f = "lights[" + std::to_string(i) + "]";
        CheckFinite(f + ".vector", L.vector);
        if (L.kind == Light::Kind::kDirectional && L.vector.norm() == 0)
            InvalidField(f + ".vector", "a directional light needs a non-zero direction");
        CheckFinite(f + ".color", L.color);
        CheckRange(f + ".intensity", L.intensity, 0, kMaxLightIntensity);
    }
}

}  // namespace

void RenderOptions::Validate() const {
    ValidateCamera(camera);
    CheckRange("samples_per_pixel", samples_per_pixel, 1, kMaxSamplesPerPixel);
    ValidateLights(lights);
    CheckFinite("background", background);
    CheckFinite("albedo", albedo);
    CheckAtLeast("ambient", ambient, 0);
    CheckAtLeast("specular", specular, 0);
    CheckAtLeast("shininess", shininess, 0);
    surface.Validate();
    CheckRange("tile", tile, 1, kMaxImageSide);
}

void ApplyRenderQuality(RenderQuality quality, RenderOptions* options) {
    const RenderOptions full;
    AaOptions& s = options->surface;
    switch (quality) {
        case RenderQuality::kFull:
            s.normal_sigma = full.surface.normal_sigma;
            s.bandwidth = full.surface.bandwidth;
            s.relative_precision = full.surface.relative_precision;
            options->shadow_second_stage = full.shadow_second_stage;
            return;
        case RenderQuality::kPreview:
            s.normal_sigma = 0.0f;
            s.bandwidth = AaBandwidth::kFixed;
            s.relative_precision = kPreviewRelativePrecision;
            options->shadow_second_stage = false;
            return;
    }
    InvalidField("quality", "unknown quality " + std::to_string(static_cast<int>(quality)));
}

namespace {

// ---- Embree callbacks ------------------------------------------------------------------------
// Callbacks from C never throw (conventions, "Errors"): each one runs its body in Guarded, which
// keeps the first exception in the context and skips the work of later callbacks of the same
// ray; Intersect() and Occluded() rethrow it once Embree has returned.

// Per-ray context: Embree hands it to the callbacks (the documented way to pass ray data). The
// Embree part must come first: the callbacks cast the RTCIntersectContext* back to it.
struct RayContext {
    RTCIntersectContext embree;
    std::optional<AaHit> hit;
    unsigned hit_layer = 0;                    // the layer (geometry) of `hit`
    AaCounters counters;
    // Shadow rays: balls with gamma < kGammaFirst are not tried during the traversal but kept
    // here, in traversal order, for the second stage (see InShadow): (layer, ball).
    std::vector<std::pair<unsigned, unsigned>>* deferred = nullptr;
    const HitFilter* filter = nullptr;         // RenderOptions::hit_filter; null = accept every hit
    std::exception_ptr error;                  // the first exception a callback caught
};

struct SceneData {
    const AaSurface* surface;
    const PointCloud* cloud;
    unsigned layer = 0;               // index into the layers (= Embree geometry id)
    const HitFilter* keep = nullptr;  // SurfaceLayer::keep; null or empty = every hit
    bool flip = false;                // SurfaceLayer::flip_normals
    // Ball i as (centre x, y, z, radius rho_i), the values of cloud->positions[i] and
    // surface->BallRadius(i) side by side: the ray-ball test of every candidate the traversal
    // reports (BallInterval: 8 % of a render's CPU by perf) reads one 16-byte entry instead of two
    // arrays, one of them behind a call into the surface.
    std::vector<std::array<float, 4>> balls;
    // The first exception of a bounds callback (those run on Embree's build threads).
    std::mutex build_mutex;
    std::exception_ptr build_error;
};

// Runs body(); an exception is kept in *error (the first only) instead of leaving the callback.
template <typename Body>
void Guarded(std::exception_ptr* error, Body&& body) noexcept {
    try {
        body();
    } catch (...) {
        if (!*error) *error = std::current_exception();
    }
}

// Whether the layer's filter and the render's hit filter (if any) let the ray accept `hit`.
bool Accepts(const RayContext& ctx, const SceneData& s, const AaHit& hit) {
    return (!s.keep || !*s.keep || (*s.keep)(hit)) && (!ctx.filter || !*ctx.filter || (*ctx.filter)(hit));
}

void BoundsFn(const RTCBoundsFunctionArguments* args) {
    auto* s = static_cast<SceneData*>(args->geometryUserPtr);
    RTCBounds* b = args->bounds_o;
    try {
        const Vec3f& c = s->cloud->positions[args->primID];
        const float r = s->surface->BallRadius(args->primID);
        b->lower_x = c.x() - r;
        b->lower_y = c.y() - r;
        b->lower_z = c.z() - r;
        b->upper_x = c.x() + r;
        b->upper_y = c.y() + r;
        b->upper_z = c.z() + r;
    } catch (...) {
        // An empty box (lower > upper): the builder leaves the primitive out; the build is
        // abandoned anyway once rtcCommitScene returns.
        b->lower_x = b->lower_y = b->lower_z = std::numeric_limits<float>::infinity();
        b->upper_x = b->upper_y = b->upper_z = -std::numeric_limits<float>::infinity();
        std::lock_guard lock(s->build_mutex);
        if (!s->build_error) s->build_error = std::current_exception();
    }
}

// Ray against ball i: [t0, t1] within [tnear, tfar], and (when `gamma` is given: shadow rays
// only) the priority gamma = (rho - d) / rho. Inline, and its second square root and division
// only where gamma is read: it runs for every candidate the traversal reports (~10 % of the
// tiles' CPU by perf), most of them balls the ray then leaves at the centre polynomial.
inline bool BallInterval(const SceneData& s, unsigned prim, const Vec3d& o, const Vec3d& d, double tnear, double tfar,
                  double* t0, double* t1, double* gamma) {
    const std::array<float, 4>& b = s.balls[prim];
    const Vec3d c(b[0], b[1], b[2]);
    const double rho = b[3];
    const double tc = (c - o).dot(d);
    const double d2 = (o + tc * d - c).squaredNorm();
    if (d2 > rho * rho) return false;
    const double half = std::sqrt(rho * rho - d2);
    *t0 = std::max(tnear, tc - half);
    *t1 = std::min(tfar, tc + half);
    if (gamma) *gamma = (rho - std::sqrt(d2)) / rho;
    return *t0 <= *t1;
}

// Nearest hit: the section-4 iteration in ball primID; a converged hit nearer than the ray's
// current one, and accepted by the hit filter, becomes the ray's hit.
void IntersectFn(const RTCIntersectFunctionNArguments* args) {
    if (!args->valid[0]) return;
    auto* ctx = reinterpret_cast<RayContext*>(args->context);
    if (ctx->error) return;
    Guarded(&ctx->error, [&] {
        const auto* s = static_cast<const SceneData*>(args->geometryUserPtr);
        RTCRayHit* rh = reinterpret_cast<RTCRayHit*>(args->rayhit);  // N == 1 with rtcIntersect1
        const Vec3d o(rh->ray.org_x, rh->ray.org_y, rh->ray.org_z), d(rh->ray.dir_x, rh->ray.dir_y, rh->ray.dir_z);
        double t0, t1;
        if (!BallInterval(*s, args->primID, o, d, rh->ray.tnear, rh->ray.tfar, &t0, &t1, nullptr)) return;
        // The same-sheet shortcut only against a hit of the same surface (another layer's sheet
        // may lie just behind this one, as at a crease).
        const bool same = ctx->hit && ctx->hit_layer == s->layer;
        auto hit = s->surface->IntersectInBall(args->primID, o, d, t0, t1, &ctx->counters,
                                               same ? ctx->hit->t : std::numeric_limits<double>::infinity());
        if (!hit || hit->t >= rh->ray.tfar) return;
        if (s->flip) hit->normal = -hit->normal;
        if (!Accepts(*ctx, *s, *hit)) return;
        rh->ray.tfar = static_cast<float>(hit->t);
        rh->hit.Ng_x = static_cast<float>(hit->normal.x());
        rh->hit.Ng_y = static_cast<float>(hit->normal.y());
        rh->hit.Ng_z = static_cast<float>(hit->normal.z());
        rh->hit.u = rh->hit.v = 0.0f;
        rh->hit.primID = args->primID;
        rh->hit.geomID = args->geomID;
        rh->hit.instID[0] = args->context->instID[0];
        ctx->hit = hit;
        ctx->hit_layer = s->layer;
    });
}

// Shadow rays try the balls the ray passes near the centre first (paper, section 5).
constexpr double kGammaFirst = 0.5;

// Any hit: the ray is blocked (tfar = -inf) by a converged, accepted hit in a ball with gamma >=
// kGammaFirst; a ball with a smaller gamma is deferred (ctx->deferred), or passed over when the
// render has no second stage (RenderOptions::shadow_second_stage false: ctx->deferred is null). A
// caught exception also ends the traversal.
void OccludedFn(const RTCOccludedFunctionNArguments* args) {
    if (!args->valid[0]) return;
    auto* ctx = reinterpret_cast<RayContext*>(args->context);
    RTCRay* ray = reinterpret_cast<RTCRay*>(args->ray);
    if (ctx->error) return;
    Guarded(&ctx->error, [&] {
        const auto* s = static_cast<const SceneData*>(args->geometryUserPtr);
        const Vec3d o(ray->org_x, ray->org_y, ray->org_z), d(ray->dir_x, ray->dir_y, ray->dir_z);
        double t0, t1, gamma;
        if (!BallInterval(*s, args->primID, o, d, ray->tnear, ray->tfar, &t0, &t1, &gamma)) return;
        if (gamma < kGammaFirst) {
            if (ctx->deferred) ctx->deferred->emplace_back(s->layer, args->primID);  // null: no second stage
            return;
        }
        auto hit = s->surface->IntersectInBall(args->primID, o, d, t0, t1, &ctx->counters);
        if (hit && s->flip) hit->normal = -hit->normal;
        if (hit && Accepts(*ctx, *s, *hit)) ray->tfar = -std::numeric_limits<float>::infinity();
    });
    if (ctx->error) ray->tfar = -std::numeric_limits<float>::infinity();
}

// Deterministic per-pixel jitter (a hash, so the image is the same whatever the thread count).
double Jitter(std::uint64_t x) {
    x += 0x9e3779b97f4a7c15ULL;
    x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ULL;
    x = (x ^ (x >> 27)) * 0x94d049bb133111ebULL;
    x ^= x >> 31;
    return double(x >> 11) * 0x1.0p-53;
}

class EmbreeScene {
public:
    /// Builds the BVH over the balls of every layer (one user geometry each, geometry id = layer);
    /// rethrows what a bounds callback caught.
    explicit EmbreeScene(std::deque<SceneData>* layers) : layers_(layers) {
        device_ = rtcNewDevice(nullptr);
        if (!device_) throw Error(ErrorCode::kInternal, "Embree device creation failed");
        scene_ = rtcNewScene(device_);
        // LOW: the Morton builder. On the bunny it builds in 8 ms against 11-14 ms for HIGH (SAH)
        // and renders no slower (single-core 158 against 162 ms; the image differs only in which
        // ball a ray meets first).
        rtcSetSceneBuildQuality(scene_, RTC_BUILD_QUALITY_LOW);
        for (SceneData& data : *layers) {
            RTCGeometry g = rtcNewGeometry(device_, RTC_GEOMETRY_TYPE_USER);
            rtcSetGeometryUserPrimitiveCount(g, static_cast<unsigned>(data.cloud->size()));
            rtcSetGeometryUserData(g, &data);
            rtcSetGeometryBoundsFunction(g, BoundsFn, nullptr);
            rtcSetGeometryIntersectFunction(g, IntersectFn);
            rtcSetGeometryOccludedFunction(g, OccludedFn);
            rtcCommitGeometry(g);
            rtcAttachGeometryByID(scene_, g, data.layer);
            rtcReleaseGeometry(g);
        }
        rtcCommitScene(scene_);
        std::exception_ptr build_error;
        for (SceneData& data : *layers)
            if (!build_error) build_error = data.build_error;
        if (build_error || rtcGetDeviceError(device_) != RTC_ERROR_NONE) {
            rtcReleaseScene(scene_);
            rtcReleaseDevice(device_);
            if (build_error) std::rethrow_exception(build_error);
            throw Error(ErrorCode::kInternal, "Embree scene build failed");
        }
    }
    ~EmbreeScene() {
        rtcReleaseScene(scene_);
        rtcReleaseDevice(device_);
    }
    RTCScene scene() const { return scene_; }
    const SceneData& layer(unsigned i) const { return (*layers_)[i]; }

private:
    const std::deque<SceneData>* layers_;
    RTCDevice device_ = nullptr;
    RTCScene scene_ = nullptr;
};

RTCRayHit MakeRay(const Vec3d& o, const Vec3d& d, double tnear, double tfar) {
    RTCRayHit rh{};
    rh.ray.org_x = float(o.x());
    rh.ray.org_y = float(o.y());
    rh.ray.org_z = float(o.z());
    rh.ray.dir_x = float(d.x());
    rh.ray.dir_y = float(d.y());
    rh.ray.dir_z = float(d.z());
    rh.ray.tnear = float(tnear);
    rh.ray.tfar = float(tfar);
    rh.ray.mask = ~0u;
    rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
    rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
    return rh;
}

// Traces the nearest hit (ctx->hit); rethrows what a callback caught.
void Intersect(const EmbreeScene& scene, RayContext* ctx, RTCRayHit* rh) {
    rtcIntersect1(scene.scene(), &ctx->embree, rh);
    if (ctx->error) std::rethrow_exception(ctx->error);
}

// Traces an any-hit ray; true when it is blocked. Rethrows what a callback caught.
bool Occluded(const EmbreeScene& scene, RayContext* ctx, RTCRay* ray) {
    rtcOccluded1(scene.scene(), &ctx->embree, ray);
    if (ctx->error) std::rethrow_exception(ctx->error);
    return ray->tfar < 0;
}

// ---- The render, in layers -------------------------------------------------------------------
// RenderTile -> RenderPixel -> EvaluatePixelSample -> Shade -> InShadow (after pbrt-v4's
// ImageTileIntegrator::Render -> EvaluatePixelSample -> Li). Each layer sums its work into the
// caller's RenderStats; only RenderTile's caller merges across threads.

// What every layer of one render reads.
struct Integrator {
    const RenderOptions& opt;
    const EmbreeScene& scene;
    Camera::Frame frame;
    std::vector<Light> lights;  // opt.lights, or the default light
    int strata;                 // ceil(sqrt(samples per pixel)): the jitter grid per side
};

// The samples of one pixel, summed.
struct PixelSum {
    Vec3d rgb = Vec3d::Zero();
    Vec3d nearest_n = Vec3d::Zero();  // normal of the nearest hit
    double coverage = 0;
    double zmin = std::numeric_limits<double>::infinity();
};

// Occlusion: whether the shadow ray from `hit` (normal `n`, towards the camera) to a light in
// direction `ldir` at distance `ldist` is blocked. It starts half an h off the surface so that it
// does not find its own origin, and runs as the paper's section 5 says: first the balls the ray
// passes near the centre (gamma >= kGammaFirst), then the rest; each ball is tried once. One
// traversal: the rest are the balls it deferred, tried in its order once it found no block (the
// balls and the order a second traversal restricted to gamma < kGammaFirst would give).
bool InShadow(const Integrator& I, const AaHit& hit, double h, const Vec3d& n, const Vec3d& ldir, double ldist,
              RenderStats* stats) {
    thread_local std::vector<std::pair<unsigned, unsigned>> deferred;
    const Vec3d so = hit.position + 0.5 * h * n;
    RayContext sctx;
    rtcInitIntersectContext(&sctx.embree);
    sctx.filter = &I.opt.hit_filter;
    deferred.clear();
    sctx.deferred = I.opt.shadow_second_stage ? &deferred : nullptr;
    RTCRayHit sr = MakeRay(so, ldir, 0.0, ldist - 0.5 * h);
    const float tnear = sr.ray.tnear, tfar = sr.ray.tfar;
    const Vec3d o(sr.ray.org_x, sr.ray.org_y, sr.ray.org_z), d(sr.ray.dir_x, sr.ray.dir_y, sr.ray.dir_z);
    ++stats->shadow_rays;
    bool blocked = Occluded(I.scene, &sctx, &sr.ray);
    for (std::size_t k = 0; k < deferred.size() && !blocked; ++k) {
        const SceneData& data = I.scene.layer(deferred[k].first);
        const unsigned ball = deferred[k].second;
        double t0, t1;
        if (!BallInterval(data, ball, o, d, tnear, tfar, &t0, &t1, nullptr)) continue;
        auto sh = data.surface->IntersectInBall(ball, o, d, t0, t1, &sctx.counters);
        if (sh && data.flip) sh->normal = -sh->normal;
        blocked = sh && Accepts(sctx, data, *sh);
    }
    stats->surface.Add(sctx.counters);
    return blocked;
}

// Shade: the radiance towards the eye from `hit` on the ray with unit direction `d`: ambient plus,
// per unshadowed light, Lambert and Blinn-Phong terms. The side facing the camera is shaded.
Vec3d Shade(const Integrator& I, const AaHit& hit, unsigned layer, const Vec3d& d, RenderStats* stats) {
    const RenderOptions& opt = I.opt;
    const SceneData& data = I.scene.layer(layer);
    Vec3d n = hit.normal;
    if (n.dot(d) > 0) n = -n;
    const Vec3d albedo = data.cloud->has_colors() ? Vec3d(hit.color[0], hit.color[1], hit.color[2]) : opt.albedo;
    Vec3d c = opt.ambient * albedo;
    for (const Light& L : I.lights) {
        Vec3d ldir;
        double ldist = std::numeric_limits<float>::infinity();
        if (L.kind == Light::Kind::kDirectional) {
            ldir = -L.vector.normalized();
        } else {
            ldir = L.vector - hit.position;
            ldist = ldir.norm();
            ldir /= ldist;
        }
        const double ndl = n.dot(ldir);
        if (ndl <= 0) continue;
        if (opt.shadows && InShadow(I, hit, data.surface->h(), n, ldir, ldist, stats)) continue;
        const Vec3d hv = (ldir - d).normalized();
        const Vec3d lc = L.color * L.intensity;
        c += lc.cwiseProduct(albedo) * ndl + lc * (opt.specular * std::pow(std::max(0.0, n.dot(hv)), opt.shininess));
    }
    return c;
}

// Pixel sample s of pixel (x, y): the pixel centre with one sample, else a jittered stratum of the
// strata x strata grid. Traces the primary ray and adds its colour, coverage, depth and normal.
void EvaluatePixelSample(const Integrator& I, int x, int y, int s, PixelSum* sum, RenderStats* stats) {
    const int spp = I.opt.samples_per_pixel, strata = I.strata;
    double px = x + 0.5, py = y + 0.5;
    if (spp > 1) {
        const std::uint64_t key = (std::uint64_t(y) * I.opt.camera.width + x) * 1024 + s;
        px = x + ((s % strata) + Jitter(key * 2)) / strata;
        py = y + ((s / strata) % strata + Jitter(key * 2 + 1)) / strata;
    }
    const Vec3d d = I.frame.Direction(px, py);
    RayContext ctx;
    rtcInitIntersectContext(&ctx.embree);
    ctx.filter = &I.opt.hit_filter;
    RTCRayHit rh = MakeRay(I.opt.camera.eye, d, 0.0, std::numeric_limits<float>::infinity());
    Intersect(I.scene, &ctx, &rh);
    ++stats->primary_rays;
    stats->surface.Add(ctx.counters);
    if (!ctx.hit) {
        sum->rgb += I.opt.background;
        return;
    }
    ++stats->hits;
    const AaHit& hit = *ctx.hit;
    sum->coverage += 1.0;
    if (hit.t < sum->zmin) {
        sum->zmin = hit.t;
        sum->nearest_n = hit.normal;
    }
    sum->rgb += Shade(I, hit, ctx.hit_layer, d, stats);
}

// Pixel (x, y): the mean of its samples into the image's channels (see RenderResult).
void RenderPixel(const Integrator& I, int x, int y, Image* img, RenderStats* stats) {
    const int spp = I.opt.samples_per_pixel;
    PixelSum sum;
    for (int s = 0; s < spp; ++s) EvaluatePixelSample(I, x, y, s, &sum, stats);
    const Vec3d rgb = sum.rgb / spp;
    img->At(x, y, 0) = float(rgb.x());
    img->At(x, y, 1) = float(rgb.y());
    img->At(x, y, 2) = float(rgb.z());
    img->At(x, y, 3) = float(sum.coverage / spp);
    img->At(x, y, 4) = std::isinf(sum.zmin) ? std::numeric_limits<float>::infinity() : float(sum.zmin);
    img->At(x, y, 5) = float(sum.nearest_n.x());
    img->At(x, y, 6) = float(sum.nearest_n.y());
    img->At(x, y, 7) = float(sum.nearest_n.z());
}

// Tile `tile` (row-major over tiles_x tiles per row of tile x tile pixels, clipped to the image).
void RenderTile(const Integrator& I, int tile, int tiles_x, Image* img, RenderStats* stats) {
    const Camera& cam = I.opt.camera;
    const int x0 = (tile % tiles_x) * I.opt.tile, y0 = (tile / tiles_x) * I.opt.tile;
    for (int y = y0; y < std::min(y0 + I.opt.tile, cam.height); ++y)
        for (int x = x0; x < std::min(x0 + I.opt.tile, cam.width); ++x) RenderPixel(I, x, y, img, stats);
}

}  // namespace

RenderResult RenderLayers(std::span<const SurfaceLayer> layers, const RenderOptions& opt, const ProgressFn& progress) {
    opt.Validate();
    SURFEL_CHECK(!layers.empty(), layers.size());
    const Camera& cam = opt.camera;

    // Setup: the BVH over the balls of every layer (the surfaces are the caller's).
    Stopwatch watch;
    std::deque<SceneData> data;
    for (std::size_t i = 0; i < layers.size(); ++i) {
        SceneData& d = data.emplace_back();
        d.surface = layers[i].surface;
        d.cloud = &layers[i].surface->cloud();
        d.layer = static_cast<unsigned>(i);
        d.keep = &layers[i].keep;
        d.flip = layers[i].flip_normals;
        d.balls.resize(d.cloud->size());
        for (std::size_t j = 0; j < d.balls.size(); ++j) {
            const Vec3f& p = d.cloud->positions[j];
            d.balls[j] = {p.x(), p.y(), p.z(), d.surface->BallRadius(static_cast<std::uint32_t>(j))};
        }
    }
    const EmbreeScene scene(&data);
    const double setup_ms = watch.ElapsedMs();

    // The camera frame, the lights (default: one over the camera's left shoulder), the image.
    const Camera::Frame frame = cam.MakeFrame();
    std::vector<Light> lights = opt.lights;
    if (lights.empty())
        lights.push_back(
            {Light::Kind::kDirectional, (frame.w - 0.6 * frame.v + 0.5 * frame.u).normalized(), {1, 1, 1}, 1.0});
    const Integrator integrator{opt, scene, frame, std::move(lights),
                                static_cast<int>(std::ceil(std::sqrt(double(opt.samples_per_pixel))))};
    RenderResult result;
    Image& img = result.image;
    img.width = cam.width;
    img.height = cam.height;
    img.channels = {"R", "G", "B", "A", "Z", "N.X", "N.Y", "N.Z"};
    img.pixels.assign(std::size_t(img.width) * img.height * img.channels.size(), 0.0f);

    // The surfaces' weight normals (estimated on their own thread since the AaSurface constructor,
    // beside the BVH build above) are awaited here, outside the tiles: a tile's first fit would
    // wait for them inside a TBB task, which keeps that TBB thread from joining the estimation's
    // parallel loops (on 2 cores the per-point normals then ran on one thread while the other
    // waited); waiting here leaves every TBB worker free to help.
    for (const SurfaceLayer& layer : layers) layer.surface->WeightNormals();

    // The tiles, in parallel; each thread sums its stats and merges them once.
    const int tiles_x = (cam.width + opt.tile - 1) / opt.tile, tiles_y = (cam.height + opt.tile - 1) / opt.tile;
    ProgressTracker tracker(progress, double(tiles_x) * tiles_y, "render");
    std::mutex stats_mutex;
    RenderStats& st = result.stats;
    tbb::parallel_for(tbb::blocked_range<int>(0, tiles_x * tiles_y, 1), [&](const tbb::blocked_range<int>& range) {
        RenderStats local;
        for (int tile = range.begin(); tile != range.end(); ++tile) {
            tracker.Check();
            for (const SurfaceLayer& layer : layers)
                if (layer.on_tile) layer.on_tile();
            RenderTile(integrator, tile, tiles_x, &img, &local);
            tracker.Advance(1.0);
        }
        std::lock_guard lock(stats_mutex);
        st.primary_rays += local.primary_rays;
        st.shadow_rays += local.shadow_rays;
        st.hits += local.hits;
        st.surface.Add(local.surface);
    });
    st.time_ms = watch.ElapsedMs();
    st.setup_ms = setup_ms;
    st.h = layers[0].surface->h();
    st.precision = layers[0].surface->precision();
    return result;
}

RenderResult Render(const PointCloud& cloud, const RenderOptions& opt, const ProgressFn& progress) {
    opt.Validate();
    if (opt.creases && HasSurfelPairs(cloud)) return RenderWithCreases(cloud, opt, progress);
    // Setup: the surface (neighbour search, ball radii); RenderLayers adds the BVH build.
    Stopwatch watch;
    const AaSurface surface(cloud, opt.surface, progress);
    const double surface_ms = watch.ElapsedMs();
    SurfaceLayer layer;
    layer.surface = &surface;
    RenderResult result = RenderLayers({&layer, 1}, opt, progress);
    result.stats.setup_ms += surface_ms;
    result.stats.time_ms += surface_ms;
    return result;
}

}  // namespace surfel
