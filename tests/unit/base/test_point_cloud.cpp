#include <gtest/gtest.h>

#include "surfel/base/error.h"
#include "surfel/base/point_cloud.h"

namespace surfel {
namespace {

TEST(PointCloud, BoundsAndSubsetCarryEveryAttribute) {
    PointCloud c;
    c.positions = {{0, 0, 0}, {1, 2, 3}, {-1, 5, 0.5f}};
    c.normals = {{0, 0, 1}, {0, 1, 0}, {1, 0, 0}};
    c.colors = {{{1, 0, 0, 1}}, {{0, 1, 0, 1}}, {{0, 0, 1, 1}}};
    c.radii = {0.1f, 0.2f, 0.3f};
    c.extras.push_back({"intensity", ScalarType::kUInt16, {10, 20, 30}});
    const BoundingBox b = c.Bounds();
    EXPECT_EQ(b.min, Vec3f(-1, 0, 0));
    EXPECT_EQ(b.max, Vec3f(1, 5, 3));
    EXPECT_FLOAT_EQ(b.Diagonal(), std::sqrt(4.0f + 25.0f + 9.0f));
    const std::uint32_t idx[] = {2, 0};
    PointCloud s = c.Subset(idx);
    ASSERT_EQ(s.size(), 2u);
    EXPECT_EQ(s.positions[0], c.positions[2]);
    EXPECT_EQ(s.normals[1], c.normals[0]);
    EXPECT_EQ(s.colors[0], c.colors[2]);
    EXPECT_EQ(s.radii[1], 0.1f);
    EXPECT_EQ(s.extras[0].values, (std::vector<double>{30, 10}));
    EXPECT_EQ(s.extras[0].type, ScalarType::kUInt16);
}

TEST(PointCloud, EmptyBoxHasZeroDiagonal) {
    PointCloud c;
    EXPECT_TRUE(c.Bounds().empty());
    EXPECT_EQ(c.Bounds().Diagonal(), 0.0f);
}

TEST(Error, CarriesCodeAndName) {
    try {
        throw Error(ErrorCode::kNotFound, "x.ply: cannot open file");
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kNotFound);
        EXPECT_STREQ(e.what(), "x.ply: cannot open file");
    }
    EXPECT_EQ(ErrorCodeName(ErrorCode::kResourceExhausted), "ResourceExhausted");
}

}  // namespace
}  // namespace surfel
