// The format table: lookup by extension, by content, and the bytes-on-disk helpers.
#include <gtest/gtest.h>

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <limits>
#include <optional>

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

// ---- The upload check (InspectCloudFile: positions only, the full parse's checks) ---------------

// The summary of the positions-only parse against the full parse of the same bytes: count,
// bounds and attribute names equal, or both refuse the bytes with the same code and message.
void ExpectSummaryMatchesFullParse(const std::string& bytes, const std::string& name) {
    SCOPED_TRACE(name);
    std::optional<PointCloud> full;
    std::string full_error;
    ErrorCode full_code = ErrorCode::kInternal;
    try {
        full = ParsePointCloud(bytes, name);
        if (full->empty()) throw Error(ErrorCode::kInvalidArgument, name + ": the cloud has no points");
    } catch (const Error& e) {
        full.reset();
        full_error = e.what();
        full_code = e.code();
    }
    try {
        const CloudFileSummary s = InspectCloudFile(bytes, name);
        ASSERT_TRUE(full.has_value()) << "the full parse refused it: " << full_error;
        EXPECT_EQ(s.points, full->size());
        EXPECT_EQ(s.bounds.min, full->Bounds().min);
        EXPECT_EQ(s.bounds.max, full->Bounds().max);
        EXPECT_EQ(s.attributes, full->AttributeNames());
    } catch (const Error& e) {
        ASSERT_FALSE(full.has_value()) << "only the summary refused it: " << e.what();
        EXPECT_EQ(e.code(), full_code);
        EXPECT_EQ(std::string(e.what()), full_error);
    }
}

TEST(InspectCloudFile, AgreesWithTheFullParseOnEveryAttributeLayout) {
    const std::string head = "ply\nformat ascii 1.0\nelement vertex 3\n";
    const std::vector<std::pair<std::string, std::string>> layouts = {
        {"property float x\nproperty float y\nproperty float z\n", "1 2 3\n-1 0 5\n4 4 -2\n"},
        // normals, rgba colours, a radius and an extra property, in an unusual order
        {"property uchar red\nproperty float x\nproperty uchar green\nproperty float nx\nproperty float y\n"
         "property float ny\nproperty uchar blue\nproperty float z\nproperty float nz\nproperty uchar alpha\n"
         "property float radius\nproperty double intensity\n",
         "1 0 2 0 0 1 3 0 1 4 0.5 7\n5 1 6 1 0 0 7 2 0 8 0.25 -1\n9 -3 10 0 1 0 11 1 0 12 1 0.5\n"},
        // colours of mixed types are not colours: three extra properties
        {"property float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty float green\n"
         "property uchar blue\n", "0 0 0 1 0.5 3\n1 1 1 4 0.25 6\n2 0 1 7 1 9\n"},
        // float rgb without alpha
        {"property double x\nproperty double y\nproperty double z\nproperty float red\nproperty float green\n"
         "property float blue\n", "0 0 0 1 0.5 0\n1 1 1 0 0.25 1\n2 0 1 0 1 1\n"},
    };
    for (const auto& [props, body] : layouts) {
        const std::string ascii = head + props + "end_header\n" + body;
        ExpectSummaryMatchesFullParse(ascii, "layout.ply");
        const PointCloud c = ParsePointCloud(ascii, "layout.ply");
        ExpectSummaryMatchesFullParse(FormatPly(c), "layout.ply");  // binary little-endian
        ExpectSummaryMatchesFullParse(FormatXyz(c), "layout.xyz");
    }
    // Many records: the binary reader's blocks (64 KiB of records) and their last, short one.
    ShapeOptions big;
    big.points = 10'007;
    big.normals = true;
    ExpectSummaryMatchesFullParse(FormatPly(SampleShape(Shape::kTorus, big)), "torus.ply");
    // Faces before the vertices, and their indices checked against the vertex count.
    const std::string faces = "ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\n"
                              "element vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                              "property float nx\nend_header\n";
    ExpectSummaryMatchesFullParse(faces + "3 0 1 2\n0 0 0 1\n1 0 0 1\n0 1 0 1\n", "faces.ply");
    ExpectSummaryMatchesFullParse(faces + "3 0 1 3\n0 0 0 1\n1 0 0 1\n0 1 0 1\n", "faces.ply");
}

TEST(InspectCloudFile, RefusesWhatTheFullParseRefusesWithTheSameMessage) {
    const std::string head = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                             "property float z\nproperty float nx\nend_header\n";
    ExpectSummaryMatchesFullParse(head + "0 0 0 1\n0 nan 0 1\n", "nan.ply");         // not finite
    ExpectSummaryMatchesFullParse(head + "0 0 0 1\n0 0 0 oops\n", "word.ply");       // an attribute's value
    ExpectSummaryMatchesFullParse(head + "0 0 0 1\n", "short.ply");                   // too few records
    ExpectSummaryMatchesFullParse("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                                  "property float z\nproperty float nx\nend_header\n", "empty.ply");
    ShapeOptions o;
    o.points = 100;
    o.normals = true;
    const std::string binary = FormatPly(SampleShape(Shape::kSphere, o));
    ExpectSummaryMatchesFullParse(binary.substr(0, binary.size() - 7), "cut.ply");  // truncated
    ExpectSummaryMatchesFullParse(binary + "xyz", "tail.ply");                       // bytes after the end
}

// The binary positions are streamed a block at a time (InspectPly, never all in memory): a
// coordinate that is not finite in a later block, with a later error that the full parse reports
// first, faces checked against the streamed count, both byte orders, a file of whole blocks.
TEST(InspectCloudFile, StreamedBinaryPositionsAgreeWithTheFullParse) {
    ShapeOptions o;
    o.points = 3 * 2730;  // 2,730 records of 24 bytes (positions + normals) fill a 64 KiB block
    o.normals = true;
    const PointCloud cloud = SampleShape(Shape::kTorus, o);
    // FormatPly writes only the native byte order: big-endian by swapping every 4-byte value.
    auto as = [](bool big, std::string le) {
        if (!big) return le;
        const std::size_t body = le.find("end_header\n") + 11;
        le.replace(le.find("binary_little_endian"), 20, "binary_big_endian");
        for (std::size_t i = body - 3; i + 4 <= le.size(); i += 4) std::reverse(le.begin() + i, le.begin() + i + 4);
        return le;
    };
    for (const bool big : {false, true}) {
        const std::string bytes = as(big, FormatPly(cloud));
        ASSERT_EQ(ParsePointCloud(bytes, "whole.ply").positions, cloud.positions);  // a valid file
        ExpectSummaryMatchesFullParse(bytes, "whole.ply");
        for (const std::uint64_t bad : {std::uint64_t{0}, std::uint64_t{2729}, std::uint64_t{2730}, std::uint64_t{8000}}) {
            PointCloud c = cloud;
            c.positions[bad].y() = std::numeric_limits<float>::quiet_NaN();
            if (bad == 8000) c.positions[bad + 1].x() = std::numeric_limits<float>::infinity();  // the first is named
            const std::string nan = as(big, FormatPly(c));
            ExpectSummaryMatchesFullParse(nan, "nan.ply");
            ExpectSummaryMatchesFullParse(nan + "junk", "nan-tail.ply");  // the tail is reported first
            ExpectSummaryMatchesFullParse(nan.substr(0, nan.size() - 5), "nan-cut.ply");
        }
    }
    // Faces (a list element after the fixed-size vertices): indices checked against the count.
    PointCloud mesh = cloud;
    mesh.triangles = {{0, 1, 2}, {3, 4, static_cast<std::uint32_t>(cloud.size() - 1)}};
    ExpectSummaryMatchesFullParse(FormatPly(mesh), "mesh.ply");
    mesh.triangles.push_back({0, 1, static_cast<std::uint32_t>(cloud.size())});
    ExpectSummaryMatchesFullParse(FormatPly(mesh), "mesh-bad.ply");
    // InspectPly itself: the count, exact bounds and the attributes of the full parse.
    const PlySummary s = InspectPly(FormatPly(cloud), "torus.ply");
    EXPECT_EQ(s.points, cloud.size());
    EXPECT_EQ(s.bounds.min, cloud.Bounds().min);
    EXPECT_EQ(s.bounds.max, cloud.Bounds().max);
    EXPECT_EQ(s.attributes, std::vector<std::string>{"normals"});
}

// At 64 blocks and more the streamed positions are read in two halves, the second on another
// thread: the same answers as one pass, to the bit (the sign of a zero at the bounds included),
// and a non-finite coordinate in either half, or in both, named as the full parse names it.
TEST(InspectCloudFile, StreamedHalvesAgreeWithOnePassToTheBit) {
    ShapeOptions o;
    o.points = 66 * 2730 + 17;  // 66 blocks of 24-byte records and a short one; the second half from 32 * 2730
    o.normals = true;
    PointCloud cloud = SampleShape(Shape::kTorus, o);
    const std::uint64_t mid = 33 * 2730;
    // Zeros of both signs tie at the lower x bound, one in each half: a pass keeps the first.
    for (Vec3f& p : cloud.positions) p.x() = std::abs(p.x()) + 1.0f;
    cloud.positions[100].x() = 0.0f;
    cloud.positions[mid + 5].x() = -0.0f;
    const std::string bytes = FormatPly(cloud);
    ExpectSummaryMatchesFullParse(bytes, "halves.ply");
    const PlySummary s = InspectPly(bytes, "halves.ply");
    const BoundingBox b = cloud.Bounds();
    EXPECT_EQ(s.points, cloud.size());
    EXPECT_EQ(std::memcmp(s.bounds.min.data(), b.min.data(), sizeof(Vec3f)), 0);
    EXPECT_EQ(std::memcmp(s.bounds.max.data(), b.max.data(), sizeof(Vec3f)), 0);
    for (const std::uint64_t bad : {std::uint64_t{0}, mid - 1, mid, mid + 2730, cloud.size() - 1}) {
        PointCloud c = cloud;
        c.positions[bad].z() = std::numeric_limits<float>::infinity();
        if (bad < mid) c.positions[mid + 1].y() = std::numeric_limits<float>::quiet_NaN();  // the first is named
        ExpectSummaryMatchesFullParse(FormatPly(c), "halves-bad.ply");
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
