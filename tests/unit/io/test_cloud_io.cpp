// The format table: lookup by extension, by content, and the bytes-on-disk helpers.
#include <gtest/gtest.h>

#include <unistd.h>

#include <filesystem>

#include "surfel/base/error.h"
#include "surfel/base/shapes.h"
#include "surfel/io/cloud_io.h"
#include "surfel/io/file_bytes.h"
#include "surfel/io/ply.h"
#include "surfel/io/xyz.h"

namespace surfel {
namespace {

PointCloud SmallCloud() {
    ShapeOptions o;
    o.points = 50;
    o.normals = true;
    return SampleShape(Shape::kSphere, o);
}

// ---- Lookup by extension ----------------------------------------------------------------------

TEST(CloudFormatTable, ExtensionsMapToTheirFormat) {
    EXPECT_EQ(FormatFromPath("a.ply"), CloudFileFormat::kPly);
    EXPECT_EQ(FormatFromPath("dir.d/A.PLY"), CloudFileFormat::kPly);
    EXPECT_EQ(FormatFromPath("a.xyz"), CloudFileFormat::kXyz);
    EXPECT_EQ(FormatFromPath("a.TXT"), CloudFileFormat::kXyz);
    EXPECT_EQ(FormatFromPath("/tmp/a.pts"), CloudFileFormat::kXyz);
    EXPECT_EQ(CloudFormatName(CloudFileFormat::kPly), "ply");
    EXPECT_EQ(CloudFormatName(CloudFileFormat::kXyz), "xyz");
}

TEST(CloudFormatTable, UnknownExtensionNamesTheKnownOnes) {
    for (const auto& [path, ext] : {std::pair<std::string, std::string>{"mesh.obj", ".obj"}, {"noext", ""}}) {
        try {
            FormatFromPath(path);
            FAIL() << path;
        } catch (const Error& e) {
            EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
            EXPECT_EQ(std::string(e.what()), path + ": unknown point-cloud file extension '" + ext +
                                                 "' (expected .ply, .xyz, .txt or .pts)");
        }
    }
}

// ---- Lookup by content ------------------------------------------------------------------------

TEST(CloudFormatTable, SniffNamesTheEncoding) {
    const PointCloud c = SmallCloud();
    PlyWriteOptions ascii;
    ascii.format = PlyFormat::kAscii;
    EXPECT_EQ(SniffCloudFormat(FormatPly(c)), "ply-binary-le");
    EXPECT_EQ(SniffCloudFormat(FormatPly(c, ascii)), "ply-ascii");
    EXPECT_EQ(SniffCloudFormat("ply\nformat binary_big_endian 1.0\nelement vertex 0\nend_header\n"),
              "ply-binary-be");
    EXPECT_EQ(SniffCloudFormat("ply\r\nformat binary_little_endian 1.0\r\n"), "ply-binary-le");
    EXPECT_EQ(SniffCloudFormat(FormatXyz(c)), "xyz");
    EXPECT_EQ(SniffCloudFormat(""), "xyz");
}

TEST(CloudFormatTable, SniffReadsTheFormatLineNotComments) {
    // A long comment before the format line, and one that names another encoding.
    const std::string comment = "comment " + std::string(200, 'c') + " binary_big_endian\n";
    EXPECT_EQ(SniffCloudFormat("ply\n" + comment + "format binary_little_endian 1.0\nend_header\n"), "ply-binary-le");
    EXPECT_EQ(SniffCloudFormat("ply\n" + comment + "format ascii 1.0\nend_header\n"), "ply-ascii");
    EXPECT_EQ(SniffCloudFormat("ply\nend_header\nformat binary_little_endian 1.0\n"), "ply-ascii");
}

TEST(CloudFormatTable, ParseFollowsTheSniffedFormat) {
    const PointCloud c = SmallCloud();
    EXPECT_EQ(ParsePointCloud(FormatPly(c), "c.ply").positions, c.positions);
    EXPECT_EQ(ParsePointCloud(FormatXyz(c), "c.xyz").normals, c.normals);
    // No PLY magic line ("ply" then a newline): read as XYZ, and its message says so.
    try {
        ParsePointCloud("ply 1 2\n", "odd.txt");
        FAIL();
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
        EXPECT_STREQ(e.what(), "odd.txt: line 1: field 'x': 'ply' is not a number");
    }
    EXPECT_EQ(SniffCloudFormat("ply 1 2\n"), "xyz");
    // The limits reach the XYZ reader too.
    PlyReadOptions limits;
    limits.max_points = 10;
    try {
        ParsePointCloud(FormatXyz(c), "c.xyz", limits);
        FAIL();
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kResourceExhausted);
        EXPECT_STREQ(e.what(), "c.xyz: line 11: more than 10 points");
    }
}

// ---- Files ------------------------------------------------------------------------------------

TEST(FileBytes, WriteIsAtomicAndReadsBack) {
    const auto dir = std::filesystem::temp_directory_path() / ("surfel_bytes_" + std::to_string(::getpid()));
    std::filesystem::create_directories(dir);
    const std::string path = (dir / "blob.bin").string();
    const std::string bytes("a\0b\nc", 5);
    WriteFileBytes(path, bytes);
    EXPECT_EQ(ReadFileBytes(path), bytes);
    WriteFileBytes(path, "shorter");
    EXPECT_EQ(ReadFileBytes(path), "shorter");
    EXPECT_FALSE(std::filesystem::exists(path + ".tmp-surfel"));
    try {
        ReadFileBytes(dir.string());
        FAIL();
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
        EXPECT_EQ(std::string(e.what()), dir.string() + ": is a directory, not a file");
    }
    EXPECT_THROW(WriteFileBytes((dir / "no" / "such" / "dir.bin").string(), "x"), Error);
    // PLY info comes back through the table for PLY files only.
    const PointCloud c = SmallCloud();
    WritePointCloud(c, (dir / "c.ply").string(), /*ascii=*/true);
    PlyHeaderInfo info;
    EXPECT_EQ(ReadPointCloud((dir / "c.ply").string(), {}, &info).size(), c.size());
    EXPECT_EQ(info.format, PlyFormat::kAscii);
    ASSERT_EQ(info.elements.size(), 1u);
    EXPECT_EQ(info.elements[0].count, c.size());
    WritePointCloud(c, (dir / "c.xyz").string());
    PlyHeaderInfo untouched;
    EXPECT_EQ(ReadPointCloud((dir / "c.xyz").string(), {}, &untouched).normals, c.normals);
    EXPECT_TRUE(untouched.elements.empty());
    std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace surfel
