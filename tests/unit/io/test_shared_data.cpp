// Loads every real model of ../shared/data when that folder exists (skipped otherwise).
#include <gtest/gtest.h>

#include <filesystem>

#include "surfel/io/ply.h"

namespace surfel {
namespace {

TEST(SharedData, EveryPlyLoads) {
    const std::filesystem::path dir = SURFEL_SHARED_DATA_DIR;
    if (!std::filesystem::is_directory(dir)) GTEST_SKIP() << dir << " not present";
    int files = 0;
    for (const auto& entry : std::filesystem::directory_iterator(dir)) {
        if (entry.path().extension() != ".ply") continue;
        PlyHeaderInfo info;
        const PointCloud c = ReadPly(entry.path().string(), {}, &info);
        EXPECT_GT(c.size(), 1000u) << entry.path();
        EXPECT_FALSE(c.Bounds().empty());
        const bool mesh = entry.path().stem().string().ends_with("_mesh");
        EXPECT_EQ(mesh, !c.triangles.empty()) << entry.path();
        if (entry.path().filename() == "bunny.ply") EXPECT_EQ(c.size(), 34834u);
        if (entry.path().filename() == "bunny_mesh.ply") EXPECT_EQ(c.triangles.size(), 69451u);
        if (entry.path().filename() == "bunny_normals.ply") EXPECT_TRUE(c.has_normals());
        ++files;
    }
    EXPECT_GE(files, 20);
}

}  // namespace
}  // namespace surfel
