#pragma once
/// \file
/// Ray tracing of the Adamson-Alexa point-set surface (paper, sections 4-6) with Embree:
/// a ball per point (radius enclosing its 6 nearest neighbours) as user geometry, the
/// section-4 iteration inside each ball, Lambert + Blinn-Phong shading with hard shadows.

#include <functional>
#include <optional>
#include <vector>

#include "surfel/base/point_cloud.h"
#include "surfel/base/progress.h"
#include "surfel/io/image.h"
#include "surfel/surface/aa_surface.h"

namespace surfel {

/// Limits of RenderOptions, checked by RenderOptions::Validate() (the worker and the CLI read them
/// from here).
inline constexpr int kMaxImageSide = 16384;        ///< Pixels per side (Camera::width, height).
inline constexpr int kMaxSamplesPerPixel = 1024;   ///< RenderOptions::samples_per_pixel.
inline constexpr int kMaxLights = 64;              ///< RenderOptions::lights.size().
inline constexpr double kMinFovyDeg = 1.0;         ///< Camera::fovy_deg, degrees.
inline constexpr double kMaxFovyDeg = 179.0;       ///< Camera::fovy_deg, degrees.
inline constexpr double kMaxLightIntensity = 1e6;  ///< Light::intensity (0 is allowed: a light that is off).

/// Pinhole camera. The ray of pixel (i, j) passes through its centre (i + 0.5, j + 0.5); row 0 is
/// the top of the image.
struct Camera {
    Vec3d eye{0, 0, 3}, target{0, 0, 0}, up{0, 1, 0};
    double fovy_deg = 40.0;  ///< Vertical field of view in degrees.
    int width = 512, height = 512;

    /// The camera's orthonormal frame and image-plane scale, computed once per render.
    struct Frame {
        Vec3d u, v, w;          ///< right, true up, forward (unit)
        double sx, sy;          ///< half extents of the image plane at distance 1
        double width, height;
        /// Unit direction through image position (x, y) in pixels (x right, y down).
        Vec3d Direction(double x, double y) const {
            return (w + (2.0 * x / width - 1.0) * sx * u + (1.0 - 2.0 * y / height) * sy * v).normalized();
        }
    };
    Frame MakeFrame() const;

    /// Unit direction through image position (x, y) in pixels (x right, y down).
    Vec3d Direction(double x, double y) const { return MakeFrame().Direction(x, y); }
    /// A camera that frames `box` from direction `from` (eye - target), up +y.
    static Camera Framing(const BoundingBox& box, int width, int height, const Vec3d& from = Vec3d(0, 0, 1),
                          double fovy_deg = 40.0);
};

struct Light {
    enum class Kind { kDirectional, kPoint } kind = Kind::kDirectional;
    Vec3d vector{-0.4, -0.5, -1.0};  ///< Direction the light travels (directional) or position (point).
    Vec3d color{1, 1, 1};
    double intensity = 1.0;
};

/// The render's seam for a CSG render (the boolean issue): called with every converged hit of
/// every ray, primary and shadow, before the ray accepts it; returning false rejects the hit, and
/// the ray goes on through the scene as if that part of the surface were absent (a later ball on
/// the ray can still give a hit). For A - B, a CSG render would keep a hit on A only where B's
/// AaSurface::Evaluate(hit.position).f < 0 (outside B). Called concurrently from the render's
/// threads, from inside Embree's callbacks: what it throws is caught there and rethrown by
/// Render() to its caller (the first exception of the ray; the render stops).
using HitFilter = std::function<bool(const AaHit& hit)>;

struct RenderOptions {
    Camera camera;
    std::vector<Light> lights;            ///< Empty = one directional light over the camera's left shoulder.
    bool shadows = true;                  ///< Hard shadows by occlusion rays.
    /// Shadow rays in the paper's two stages (section 5): first the balls the ray passes within
    /// half the radius of the centre (gamma >= 0.5), then, when none of them blocked it, the
    /// others. false (RenderQuality::kPreview) = the first stage alone: only a converged hit in a
    /// ball the ray passes near the centre blocks it, which a ray through a densely sampled sheet
    /// nearly always finds; the shadow's outline can move by about half a sample spacing.
    bool shadow_second_stage = true;
    int samples_per_pixel = 1;            ///< Stratified; 1 = the pixel centre.
    Vec3d background{0, 0, 0};
    Vec3d albedo{0.8, 0.8, 0.8};          ///< Surface colour when the cloud has none.
    double ambient = 0.1, specular = 0.25, shininess = 32.0;
    AaOptions surface;                    ///< h, precision, degree, iterations.
    int tile = 16;                        ///< Tile size for parallel rendering.
    HitFilter hit_filter;                 ///< Empty = accept every hit (see HitFilter).
    /// A cloud with surfel pairs (a boolean result, surfel/boolean/boolean.h) renders with sharp
    /// creases (csg_render.h, RenderWithCreases); false = as one smooth surface.
    bool creases = true;

    /// Throws Error(kInvalidArgument, "<field>: <what>") for the first bad field. The fields are
    /// named as in the render job spec (proto RenderJob), which the worker prefixes with "render.":
    /// - "width", "height" (camera.width, camera.height): 1..kMaxImageSide, e.g.
    ///   "width: must lie in 1..16384, got 0";
    /// - "camera.fovy_deg": kMinFovyDeg..kMaxFovyDeg;
    /// - "camera.eye", "camera.target", "camera.up": "must be finite"; "camera: eye and target must
    ///   differ"; "camera.up: must be non-zero and not parallel to the view direction";
    /// - "samples_per_pixel": 1..kMaxSamplesPerPixel;
    /// - "lights: at most 64 lights" (kMaxLights); per light i, "lights[i].vector: must be finite",
    ///   "lights[i].vector: a directional light needs a non-zero direction",
    ///   "lights[i].color: must be finite", "lights[i].intensity": 0..kMaxLightIntensity;
    /// - "background: must be finite";
    /// - not in the job spec: "albedo: must be finite", "ambient", "specular", "shininess"
    ///   (finite, >= 0);
    /// - surface: AaOptions::Validate() ("h", "precision", "degree", "max_iterations", ...);
    /// - "tile": 1..kMaxImageSide.
    /// Range messages are CheckRange's (surfel/base/validate.h). Default-constructed options are valid.
    void Validate() const;
};

/// A render's speed against fidelity to the notes' method (ApplyRenderQuality). The CLI's
/// `--quality`, the job's RenderJob.quality.
enum class RenderQuality {
    /// The defaults of RenderOptions and AaOptions: normal-aware weights (normals estimated for a
    /// cloud without them), adaptive bandwidth, |c| < 1e-3 h, both shadow stages.
    kFull,
    /// 0.58x the instructions of kFull at the paper's framing, time_ms 72 against 146 ms
    /// (bench/README.md, session 18): the paper's surface (plain Gaussian weights and one fixed
    /// h, as `--weights plain --bandwidth fixed`: no normal estimation and no adaptive scales in
    /// the set-up; the notes' boundary stays on), the iteration accepted at |c| <
    /// kPreviewRelativePrecision x h (1.15 iterations a hit instead of 2.1), and shadow rays in
    /// the first stage alone (RenderOptions::shadow_second_stage false). The image differs from
    /// kFull's as the paper's surface does (thin parts, uneven sampling; on the bunny 15 % of the
    /// pixels by more than 1e-3), and from the paper's surface where the iteration stops earlier
    /// (0.75 % of the bunny's pixels by more than 1e-3; 1.6-1.9 % of the dragon's and buddha's)
    /// and in a few shadow-outline pixels.
    kPreview,
};

/// RenderQuality::kPreview's acceptance |c| < kPreviewRelativePrecision x h (AaOptions::relative_precision):
/// 0.03 h = 0.04 median spacings. It bounds the last fit's offset, not the distance to where the
/// paper's 1e-3 h would have stopped: that is 0.011 h at p99 on the bunny (a pixel there is
/// 0.4 h), 0.04 h on the dragon and 0.18 h on the buddha (bench/README.md, session 18). 0.01 h
/// (`--precision`) about halves those for 7 % more instructions.
inline constexpr float kPreviewRelativePrecision = 3e-2f;

/// Sets the fields of `options` that `quality` chooses (kFull: the defaults of each; kPreview: see
/// RenderQuality) and leaves the others as they are; a caller that takes explicit settings as well
/// (the worker: RenderJob's weights, bandwidth, precision) applies them after this.
void ApplyRenderQuality(RenderQuality quality, RenderOptions* options);

/// What a render did (the paper's section 6 figures).
struct RenderStats {
    std::uint64_t primary_rays = 0, shadow_rays = 0, hits = 0;
    AaCounters surface;
    double time_ms = 0;   ///< The whole render.
    double setup_ms = 0;  ///< Of which: the surface (neighbour search, ball radii) and the BVH build.
    double h = 0, precision = 0;
    double AverageIterations() const { return surface.converged ? double(surface.iterations) / double(surface.converged) : 0.0; }
};

/// Image channels R, G, B (background composited, linear), A (coverage), Z (distance from the eye
/// along the unit ray; +inf on a miss), N.X, N.Y, N.Z (world-space unit normal; 0 on a miss).
struct RenderResult {
    Image image;
    RenderStats stats;
};

/// Renders `cloud` (kept by reference during the call). Parallel over tiles; the image does not
/// depend on the thread count. Calls options.Validate() first. The progress hook is called per
/// tile; returning false throws Error(kCancelled). An exception raised while tracing (in the
/// surface or the hit filter, inside Embree's callbacks) reaches the caller unchanged.
RenderResult Render(const PointCloud& cloud, const RenderOptions& options, const ProgressFn& progress = {});

}  // namespace surfel
