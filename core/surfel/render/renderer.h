#pragma once
/// \file
/// Ray tracing of the Adamson-Alexa point-set surface (paper, sections 4-6) with Embree:
/// a ball per point (radius enclosing its 6 nearest neighbours) as user geometry, the
/// section-4 iteration inside each ball, Lambert + Blinn-Phong shading with hard shadows.

#include <optional>
#include <vector>

#include "surfel/base/point_cloud.h"
#include "surfel/base/progress.h"
#include "surfel/io/image.h"
#include "surfel/surface/aa_surface.h"

namespace surfel {

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

struct RenderOptions {
    Camera camera;
    std::vector<Light> lights;            ///< Empty = one directional light over the camera's left shoulder.
    bool shadows = true;                  ///< Hard shadows by occlusion rays.
    int samples_per_pixel = 1;            ///< Stratified; 1 = the pixel centre.
    Vec3d background{0, 0, 0};
    Vec3d albedo{0.8, 0.8, 0.8};          ///< Surface colour when the cloud has none.
    double ambient = 0.1, specular = 0.25, shininess = 32.0;
    AaOptions surface;                    ///< h, precision, degree, iterations.
    int tile = 16;                        ///< Tile size for parallel rendering.
};

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
/// depend on the thread count. The progress hook is called per tile; returning false throws
/// Error(kCancelled).
RenderResult Render(const PointCloud& cloud, const RenderOptions& options, const ProgressFn& progress = {});

}  // namespace surfel
