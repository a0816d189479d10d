#include "surfel/base/shapes.h"

#include <cmath>
#include <numbers>
#include <random>

#include "surfel/base/error.h"

namespace surfel {
namespace {

// Portable uniform and normal variates (the standard distributions differ between libraries).
class Rng {
public:
    explicit Rng(std::uint64_t seed) : engine_(seed) {}
    double Uniform() { return static_cast<double>(engine_() >> 11) * 0x1.0p-53; }
    double Normal() {
        if (has_spare_) {
            has_spare_ = false;
            return spare_;
        }
        double u, v, s;
        do {
            u = 2.0 * Uniform() - 1.0;
            v = 2.0 * Uniform() - 1.0;
            s = u * u + v * v;
        } while (s >= 1.0 || s == 0.0);
        const double m = std::sqrt(-2.0 * std::log(s) / s);
        spare_ = v * m;
        has_spare_ = true;
        return u * m;
    }

private:
    std::mt19937_64 engine_;
    double spare_ = 0.0;
    bool has_spare_ = false;
};

constexpr double kPi = std::numbers::pi;

struct Sample {
    Vec3d p, n;
};

Sample SampleOne(Shape shape, Rng& rng) {
    switch (shape) {
        case Shape::kSphere: {
            const double z = 2.0 * rng.Uniform() - 1.0, phi = 2.0 * kPi * rng.Uniform();
            const double r = std::sqrt(std::max(0.0, 1.0 - z * z));
            Vec3d p(r * std::cos(phi), r * std::sin(phi), z);
            return {p, p};
        }
        case Shape::kPlane:
            return {Vec3d(2.0 * rng.Uniform() - 1.0, 2.0 * rng.Uniform() - 1.0, 0.0), Vec3d(0, 0, 1)};
        case Shape::kBox: {
            const int face = std::min(5, static_cast<int>(rng.Uniform() * 6.0));
            const int axis = face / 2;
            const double sign = (face % 2) ? -1.0 : 1.0;
            Vec3d p(2.0 * rng.Uniform() - 1.0, 2.0 * rng.Uniform() - 1.0, 2.0 * rng.Uniform() - 1.0);
            p[axis] = sign;
            Vec3d n = Vec3d::Zero();
            n[axis] = sign;
            return {p, n};
        }
        case Shape::kCylinder: {
            // Lateral area 2*pi*r*h = 4*pi, caps 2*pi: choose by area.
            const double u = rng.Uniform() * 6.0 * kPi;
            if (u < 4.0 * kPi) {
                const double phi = 2.0 * kPi * rng.Uniform(), z = 2.0 * rng.Uniform() - 1.0;
                return {Vec3d(std::cos(phi), std::sin(phi), z), Vec3d(std::cos(phi), std::sin(phi), 0)};
            }
            const double sign = u < 5.0 * kPi ? 1.0 : -1.0;
            const double r = std::sqrt(rng.Uniform()), phi = 2.0 * kPi * rng.Uniform();
            return {Vec3d(r * std::cos(phi), r * std::sin(phi), sign), Vec3d(0, 0, sign)};
        }
        case Shape::kTorus: {
            const double R = 1.0, r = kTorusMinorRatio;
            for (;;) {  // rejection sampling: area element is r (R + r cos v) du dv
                const double u = 2.0 * kPi * rng.Uniform(), v = 2.0 * kPi * rng.Uniform();
                if (rng.Uniform() * (R + r) > R + r * std::cos(v)) continue;
                Vec3d n(std::cos(v) * std::cos(u), std::cos(v) * std::sin(u), std::sin(v));
                Vec3d p((R + r * std::cos(v)) * std::cos(u), (R + r * std::cos(v)) * std::sin(u), r * std::sin(v));
                return {p, n};
            }
        }
    }
    SURFEL_CHECK(false, "unknown shape");
    return {};
}

}  // namespace

const char* ShapeName(Shape shape) {
    switch (shape) {
        case Shape::kSphere: return "sphere";
        case Shape::kPlane: return "plane";
        case Shape::kBox: return "box";
        case Shape::kCylinder: return "cylinder";
        case Shape::kTorus: return "torus";
    }
    return "?";
}

std::optional<Shape> ParseShape(const std::string& name) {
    for (Shape s : AllShapes())
        if (name == ShapeName(s)) return s;
    return std::nullopt;
}

std::vector<Shape> AllShapes() {
    return {Shape::kSphere, Shape::kPlane, Shape::kBox, Shape::kCylinder, Shape::kTorus};
}

PointCloud SampleShape(Shape shape, const ShapeOptions& options) {
    if (!(options.scale > 0.0) || !std::isfinite(options.scale))
        throw Error(ErrorCode::kInvalidArgument, "shape scale must be positive, got " + std::to_string(options.scale));
    if (!(options.noise >= 0.0) || !std::isfinite(options.noise))
        throw Error(ErrorCode::kInvalidArgument, "noise must be >= 0, got " + std::to_string(options.noise));
    Rng rng(options.seed);
    PointCloud cloud;
    cloud.positions.reserve(options.points);
    if (options.normals) cloud.normals.reserve(options.points);
    for (std::size_t i = 0; i < options.points; ++i) {
        Sample s = SampleOne(shape, rng);
        Vec3d p = s.p * options.scale;
        if (options.noise > 0.0) p += s.n * (options.noise * rng.Normal());
        cloud.positions.push_back(p.cast<float>());
        if (options.normals) cloud.normals.push_back(s.n.normalized().cast<float>());
    }
    return cloud;
}

Vec3d ShapeNormal(Shape shape, const Vec3d& q, double scale) {
    const Vec3d p = q / scale;
    switch (shape) {
        case Shape::kSphere: return p.normalized();
        case Shape::kPlane: return Vec3d(0, 0, 1);
        case Shape::kBox: {
            int axis;
            p.cwiseAbs().maxCoeff(&axis);
            Vec3d n = Vec3d::Zero();
            n[axis] = p[axis] >= 0 ? 1.0 : -1.0;
            return n;
        }
        case Shape::kCylinder: {
            const double rho = std::hypot(p.x(), p.y());
            if (std::abs(p.z()) - 1.0 > rho - 1.0) return Vec3d(0, 0, p.z() >= 0 ? 1.0 : -1.0);
            return Vec3d(p.x(), p.y(), 0).normalized();
        }
        case Shape::kTorus: {
            const Vec3d ring = Vec3d(p.x(), p.y(), 0).normalized();
            return (p - ring).normalized();
        }
    }
    return Vec3d::UnitZ();
}

double ShapeDistance(Shape shape, const Vec3d& q, double scale) {
    const Vec3d p = q / scale;
    double d = 0.0;
    switch (shape) {
        case Shape::kSphere: d = std::abs(p.norm() - 1.0); break;
        case Shape::kPlane: {
            const double dx = std::max(std::abs(p.x()) - 1.0, 0.0), dy = std::max(std::abs(p.y()) - 1.0, 0.0);
            d = std::sqrt(dx * dx + dy * dy + p.z() * p.z());
            break;
        }
        case Shape::kBox: {
            const Vec3d a = p.cwiseAbs() - Vec3d::Ones();
            const double outside = a.cwiseMax(0.0).norm();
            d = outside > 0 ? outside : -a.maxCoeff();
            break;
        }
        case Shape::kCylinder: {
            const double rho = std::hypot(p.x(), p.y());
            const double dr = rho - 1.0, dz = std::abs(p.z()) - 1.0;
            if (dr > 0 || dz > 0) d = std::hypot(std::max(dr, 0.0), std::max(dz, 0.0));
            else d = std::min(-dr, -dz);
            break;
        }
        case Shape::kTorus: {
            const double rho = std::hypot(p.x(), p.y());
            d = std::abs(std::hypot(rho - 1.0, p.z()) - kTorusMinorRatio);
            break;
        }
    }
    return d * scale;
}

}  // namespace surfel
