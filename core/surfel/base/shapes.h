#pragma once
/// \file
/// Analytic test shapes sampled uniformly by area: the ground truth for tests, benchmarks and
/// the demo. Every shape is centred at the origin; sizes are in the same units as `scale`.

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "surfel/base/point_cloud.h"

namespace surfel {

enum class Shape {
    kSphere,    ///< radius = scale.
    kPlane,     ///< square [-scale, scale]^2 in z = 0, normal +z.
    kBox,       ///< cube [-scale, scale]^3 (closed).
    kCylinder,  ///< radius = scale, z in [-scale, scale], with caps (closed).
    kTorus,     ///< major radius = scale, minor radius = 0.35 * scale, around the z axis.
};

/// "sphere", "plane", "box", "cylinder", "torus".
const char* ShapeName(Shape shape);
/// Parses a shape name; nullopt when unknown.
std::optional<Shape> ParseShape(const std::string& name);
/// All shapes, for loops in tests and help texts.
std::vector<Shape> AllShapes();

struct ShapeOptions {
    std::size_t points = 10000;  ///< Number of samples.
    double scale = 1.0;          ///< Size parameter (see Shape).
    double noise = 0.0;          ///< Std. deviation of Gaussian displacement along the normal (absolute units).
    bool normals = false;        ///< Attach the exact outward unit normals (of the noise-free surface).
    std::uint64_t seed = 1;      ///< Same seed, same cloud, on every platform.
};

/// Samples `shape` uniformly by area. Deterministic for a given seed (a portable generator).
PointCloud SampleShape(Shape shape, const ShapeOptions& options = {});

/// Exact outward normal of the noise-free `shape` at the closest surface point to `p`.
Vec3d ShapeNormal(Shape shape, const Vec3d& p, double scale = 1.0);

/// Exact unsigned distance from `p` to the surface of `shape`.
double ShapeDistance(Shape shape, const Vec3d& p, double scale = 1.0);

/// Minor radius of the torus relative to its scale.
inline constexpr double kTorusMinorRatio = 0.35;

}  // namespace surfel
