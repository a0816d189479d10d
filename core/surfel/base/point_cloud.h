#pragma once
/// \file
/// PointCloud: the struct-of-arrays point set every module works on, and bounding boxes.

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <cstdint>
#include <limits>
#include <span>
#include <string>
#include <vector>

namespace surfel {

using Vec3f = Eigen::Vector3f;
using Vec3d = Eigen::Vector3d;

/// The scalar types of the PLY format; remembered per attribute so that a round trip through
/// our reader and writer reproduces the file's types and values bit for bit.
enum class ScalarType : std::uint8_t { kInt8, kUInt8, kInt16, kUInt16, kInt32, kUInt32, kFloat32, kFloat64 };

/// Size in bytes of one value of `type`.
int ScalarSize(ScalarType type);
/// The canonical PLY name ("char", "uchar", ..., "float", "double").
const char* ScalarTypeName(ScalarType type);

/// A per-point scalar attribute the library does not interpret (e.g. "intensity", "confidence").
/// Values are held as double, which represents every PLY scalar type exactly.
struct ExtraAttribute {
    std::string name;
    ScalarType type = ScalarType::kFloat32;  ///< Type written back to files.
    std::vector<double> values;              ///< One value per point.
};

/// Axis-aligned bounding box; empty (min > max) until a point is added.
struct BoundingBox {
    Vec3f min = Vec3f::Constant(std::numeric_limits<float>::infinity());
    Vec3f max = Vec3f::Constant(-std::numeric_limits<float>::infinity());

    bool empty() const { return !(min.array() <= max.array()).all(); }
    void Extend(const Vec3f& p) {
        min = min.cwiseMin(p);
        max = max.cwiseMax(p);
    }
    Vec3f Center() const { return 0.5f * (min + max); }
    Vec3f Extent() const { return empty() ? Vec3f::Zero() : Vec3f(max - min); }
    /// Length of the diagonal; 0 for an empty box. The reference length for relative errors.
    float Diagonal() const { return Extent().norm(); }
};

/// A point set as a struct of arrays. Every optional array is either empty or has size() entries.
///
/// Positions are float (metres, or whatever unit the input used). Colours are RGBA in [0, 1]
/// when read from uchar (exactly v/255, so they write back bit-exact) or the file's float values.
/// Triangles are kept when the input was a mesh, so a mesh file serves both as a cloud and as
/// ground truth.
struct PointCloud {
    std::vector<Vec3f> positions;
    std::vector<Vec3f> normals;                   ///< Unit normals, or empty.
    std::vector<std::array<float, 4>> colors;     ///< RGBA, or empty.
    ScalarType color_type = ScalarType::kUInt8;   ///< How colours are stored in files.
    bool color_has_alpha = false;                 ///< Whether files carry an alpha channel.
    std::vector<float> radii;                     ///< Splat radius per point, or empty.
    std::vector<ExtraAttribute> extras;           ///< Uninterpreted scalar attributes.
    std::vector<std::array<std::uint32_t, 3>> triangles;  ///< Mesh faces (indices), or empty.

    std::size_t size() const { return positions.size(); }
    bool empty() const { return positions.empty(); }
    bool has_normals() const { return !normals.empty(); }
    bool has_colors() const { return !colors.empty(); }
    bool has_radii() const { return !radii.empty(); }

    /// Finds an extra attribute by name; nullptr when absent.
    const ExtraAttribute* FindExtra(const std::string& name) const;

    /// Bounding box of the positions.
    BoundingBox Bounds() const;

    /// A new cloud holding the points `indices` (in that order) with every per-point attribute;
    /// triangles are dropped. Indices must be < size().
    PointCloud Subset(std::span<const std::uint32_t> indices) const;

    /// Aborts (SURFEL_CHECK) when an optional array has the wrong length.
    void CheckConsistent() const;

    /// Names of the per-point attributes present, e.g. {"normals", "colors", "radius", "intensity"}.
    std::vector<std::string> AttributeNames() const;
};

}  // namespace surfel
