#include "surfel/base/point_cloud.h"

#include "surfel/base/error.h"

namespace surfel {

int ScalarSize(ScalarType type) {
    switch (type) {
        case ScalarType::kInt8:
        case ScalarType::kUInt8: return 1;
        case ScalarType::kInt16:
        case ScalarType::kUInt16: return 2;
        case ScalarType::kInt32:
        case ScalarType::kUInt32:
        case ScalarType::kFloat32: return 4;
        case ScalarType::kFloat64: return 8;
    }
    return 0;
}

const char* ScalarTypeName(ScalarType type) {
    switch (type) {
        case ScalarType::kInt8: return "char";
        case ScalarType::kUInt8: return "uchar";
        case ScalarType::kInt16: return "short";
        case ScalarType::kUInt16: return "ushort";
        case ScalarType::kInt32: return "int";
        case ScalarType::kUInt32: return "uint";
        case ScalarType::kFloat32: return "float";
        case ScalarType::kFloat64: return "double";
    }
    return "?";
}

const ExtraAttribute* PointCloud::FindExtra(const std::string& name) const {
    for (const auto& e : extras)
        if (e.name == name) return &e;
    return nullptr;
}

BoundingBox PointCloud::Bounds() const {
    BoundingBox box;
    for (const auto& p : positions) box.Extend(p);
    return box;
}

PointCloud PointCloud::Subset(std::span<const std::uint32_t> indices) const {
    PointCloud out;
    out.color_type = color_type;
    out.color_has_alpha = color_has_alpha;
    out.positions.reserve(indices.size());
    for (auto i : indices) {
        SURFEL_CHECK(i < size(), "index " << i << " of " << size());
        out.positions.push_back(positions[i]);
    }
    if (has_normals())
        for (auto i : indices) out.normals.push_back(normals[i]);
    if (has_colors())
        for (auto i : indices) out.colors.push_back(colors[i]);
    if (has_radii())
        for (auto i : indices) out.radii.push_back(radii[i]);
    for (const auto& e : extras) {
        ExtraAttribute sub{e.name, e.type, {}};
        sub.values.reserve(indices.size());
        for (auto i : indices) sub.values.push_back(e.values[i]);
        out.extras.push_back(std::move(sub));
    }
    return out;
}

void PointCloud::CheckConsistent() const {
    const std::size_t n = size();
    SURFEL_CHECK(normals.empty() || normals.size() == n, normals.size() << " normals for " << n);
    SURFEL_CHECK(colors.empty() || colors.size() == n, colors.size() << " colors for " << n);
    SURFEL_CHECK(radii.empty() || radii.size() == n, radii.size() << " radii for " << n);
    for (const auto& e : extras)
        SURFEL_CHECK(e.values.size() == n, e.name << ": " << e.values.size() << " for " << n);
}

std::vector<std::string> PointCloud::AttributeNames() const {
    std::vector<std::string> names;
    if (has_normals()) names.emplace_back("normals");
    if (has_colors()) names.emplace_back(color_has_alpha ? "colors(rgba)" : "colors(rgb)");
    if (has_radii()) names.emplace_back("radius");
    for (const auto& e : extras) names.push_back(e.name);
    return names;
}

}  // namespace surfel
