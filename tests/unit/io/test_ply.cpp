#include <gtest/gtest.h>

#include <bit>
#include <cstring>
#include <filesystem>

#include "surfel/base/error.h"
#include "surfel/base/shapes.h"
#include "surfel/io/cloud_io.h"
#include "surfel/io/ply.h"
#include "surfel/io/xyz.h"

namespace surfel {
namespace {

PointCloud RichCloud() {
    ShapeOptions o;
    o.points = 257;
    o.normals = true;
    o.noise = 0.01;
    PointCloud c = SampleShape(Shape::kTorus, o);
    for (std::size_t i = 0; i < c.size(); ++i) {
        c.colors.push_back({float(i % 256) / 255.0f, float((i * 7) % 256) / 255.0f, float((i * 13) % 256) / 255.0f, 1.0f});
        c.radii.push_back(0.001f * float(i) + 1e-7f);
    }
    c.color_type = ScalarType::kUInt8;
    ExtraAttribute a{"confidence", ScalarType::kFloat64, {}}, b{"label", ScalarType::kInt32, {}}, d{"tiny", ScalarType::kInt8, {}};
    for (std::size_t i = 0; i < c.size(); ++i) {
        a.values.push_back(1.0 / (1.0 + double(i)));
        b.values.push_back(-1000000 + double(i) * 7919);
        d.values.push_back(double(int(i % 256) - 128));
    }
    c.extras = {a, b, d};
    c.triangles = {{0, 1, 2}, {2, 3, 4}, {256, 255, 0}};
    return c;
}

void ExpectBitExact(const PointCloud& a, const PointCloud& b) {
    ASSERT_EQ(a.size(), b.size());
    EXPECT_EQ(0, std::memcmp(a.positions.data(), b.positions.data(), a.size() * sizeof(Vec3f)));
    ASSERT_EQ(a.normals.size(), b.normals.size());
    EXPECT_EQ(0, std::memcmp(a.normals.data(), b.normals.data(), a.normals.size() * sizeof(Vec3f)));
    ASSERT_EQ(a.colors.size(), b.colors.size());
    for (std::size_t i = 0; i < a.colors.size(); ++i)
        for (int k = 0; k < 3; ++k) EXPECT_EQ(std::bit_cast<std::uint32_t>(a.colors[i][k]), std::bit_cast<std::uint32_t>(b.colors[i][k]));
    EXPECT_EQ(a.radii, b.radii);
    ASSERT_EQ(a.extras.size(), b.extras.size());
    for (std::size_t k = 0; k < a.extras.size(); ++k) {
        EXPECT_EQ(a.extras[k].name, b.extras[k].name);
        EXPECT_EQ(a.extras[k].type, b.extras[k].type);
        EXPECT_EQ(a.extras[k].values, b.extras[k].values);
    }
    EXPECT_EQ(a.triangles, b.triangles);
}

TEST(Ply, BinaryRoundTripIsBitExact) {
    const PointCloud c = RichCloud();
    const PointCloud r = ParsePly(FormatPly(c), "mem.ply");
    ExpectBitExact(c, r);
    // And a second generation is byte-identical.
    EXPECT_EQ(FormatPly(r), FormatPly(c));
}

TEST(Ply, AsciiRoundTripIsBitExact) {
    const PointCloud c = RichCloud();
    PlyWriteOptions w;
    w.format = PlyFormat::kAscii;
    const std::string text = FormatPly(c, w);
    ExpectBitExact(c, ParsePly(text, "mem.ply"));
    // CRLF line ends read the same.
    std::string crlf;
    for (char ch : text) {
        if (ch == '\n') crlf += '\r';
        crlf += ch;
    }
    ExpectBitExact(c, ParsePly(crlf, "crlf.ply"));
}

TEST(Ply, FloatColoursKeepTheirValues) {
    PointCloud c;
    c.positions = {{1, 2, 3}};
    c.colors = {{{0.123456789f, 2.5f, -1.0f, 0.5f}}};
    c.color_type = ScalarType::kFloat32;
    c.color_has_alpha = true;
    const PointCloud r = ParsePly(FormatPly(c), "m.ply");
    EXPECT_EQ(r.colors, c.colors);
    EXPECT_TRUE(r.color_has_alpha);
    EXPECT_EQ(r.color_type, ScalarType::kFloat32);
}

// A big-endian file with every scalar type and alias, a list inside the vertex element, and an
// extra element, built byte by byte.
TEST(Ply, BigEndianEveryTypeListsAndExtraElements) {
    std::string h =
        "ply\nformat binary_big_endian 1.0\ncomment hand made\nobj_info generator test\n"
        "element vertex 2\nproperty double x\nproperty float32 y\nproperty int z\n"
        "property list uchar int ignored_list\nproperty char c\nproperty int8 c8\nproperty uchar uc\n"
        "property uint8 u8\nproperty short s\nproperty int16 s16\nproperty ushort us\nproperty uint16 u16\n"
        "property int32 i32\nproperty uint ui\nproperty uint32 u32\nproperty float64 f64\n"
        "element camera 1\nproperty float fov\nproperty list uchar float params\n"
        "element face 1\nproperty list uchar uint vertex_indices\nproperty uchar flags\nend_header\n";
    auto be = [&](auto v) {
        char b[sizeof v];
        std::memcpy(b, &v, sizeof v);
        std::reverse(b, b + sizeof v);
        h.append(b, sizeof v);
    };
    for (int i = 0; i < 2; ++i) {
        be(double(1.5 + i));
        be(float(-2.25f));
        be(std::int32_t(7 - i));
        be(std::uint8_t(2));
        be(std::int32_t(11));
        be(std::int32_t(12));
        be(std::int8_t(-5));
        be(std::int8_t(5));
        be(std::uint8_t(250));
        be(std::uint8_t(3));
        be(std::int16_t(-30000));
        be(std::int16_t(300));
        be(std::uint16_t(65535));
        be(std::uint16_t(1));
        be(std::int32_t(-2000000000));
        be(std::uint32_t(4000000000u));
        be(std::uint32_t(17));
        be(double(3.141592653589793));
    }
    be(float(60.0f));
    be(std::uint8_t(3));
    be(1.0f);
    be(2.0f);
    be(3.0f);
    be(std::uint8_t(3));
    be(std::uint32_t(0));
    be(std::uint32_t(1));
    be(std::uint32_t(0));
    be(std::uint8_t(9));
    PlyHeaderInfo info;
    const PointCloud c = ParsePly(h, "be.ply", {}, &info);
    ASSERT_EQ(c.size(), 2u);
    EXPECT_EQ(c.positions[1], Vec3f(2.5f, -2.25f, 6.0f));
    EXPECT_EQ(info.format, PlyFormat::kBinaryBigEndian);
    EXPECT_EQ(info.comments, (std::vector<std::string>{"hand made", "generator test"}));
    ASSERT_EQ(c.extras.size(), 12u);  // every scalar but x, y, z
    auto val = [&](const char* n) { return c.FindExtra(n)->values[0]; };
    EXPECT_EQ(val("c"), -5);
    EXPECT_EQ(val("uc"), 250);
    EXPECT_EQ(val("s"), -30000);
    EXPECT_EQ(val("us"), 65535);
    EXPECT_EQ(val("i32"), -2000000000);
    EXPECT_EQ(val("ui"), 4000000000.0);
    EXPECT_EQ(val("f64"), 3.141592653589793);
    EXPECT_EQ(c.FindExtra("ui")->type, ScalarType::kUInt32);
    EXPECT_EQ(c.triangles, (std::vector<std::array<std::uint32_t, 3>>{{0, 1, 0}}));
    EXPECT_EQ(info.face_count, 1u);
    // Written back (little endian) and read again: same values and types.
    const PointCloud r = ParsePly(FormatPly(c), "le.ply");
    EXPECT_EQ(r.positions, c.positions);
    for (std::size_t k = 0; k < c.extras.size(); ++k) {
        EXPECT_EQ(r.extras[k].values, c.extras[k].values) << c.extras[k].name;
        EXPECT_EQ(r.extras[k].type, c.extras[k].type);
    }
}

TEST(Ply, PolygonsAreFanTriangulated) {
    const std::string s =
        "ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 2\nproperty list uchar int vertex_index\nend_header\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n0.5 2 0\n4 0 1 2 3\n3 2 4 3\n";
    const PointCloud c = ParsePly(s, "quad.ply");
    EXPECT_EQ(c.triangles, (std::vector<std::array<std::uint32_t, 3>>{{0, 1, 2}, {0, 2, 3}, {2, 4, 3}}));
}

TEST(Xyz, RoundTripAndComments) {
    ShapeOptions o;
    o.points = 100;
    o.normals = true;
    const PointCloud c = SampleShape(Shape::kSphere, o);
    const std::string text = "# exported\n\n" + FormatXyz(c) + "# end\n";
    const PointCloud r = ParseXyz(text, "s.xyz");
    EXPECT_EQ(r.positions, c.positions);
    EXPECT_EQ(r.normals, c.normals);
}

// An empty or blank file is not a point cloud (XYZ has no header, so it used to read as 0 points);
// an empty cloud written as XYZ is one comment line and reads back.
TEST(Xyz, EmptyFileIsNotACloudButAnEmptyCloudRoundTrips) {
    for (const std::string& bytes : {std::string(), std::string(" \n\r\n\t")}) {
        for (auto parse : {+[](std::string_view b) { return ParseXyz(b, "e.xyz"); },
                           +[](std::string_view b) { return ParsePointCloud(b, "e.xyz"); }}) {
            try {
                parse(bytes);
                ADD_FAILURE() << "a blank file of " << bytes.size() << " bytes parsed";
            } catch (const Error& e) {
                EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
                EXPECT_EQ(std::string(e.what()),
                          bytes.empty() ? "e.xyz: empty file (0 bytes): not a point cloud"
                                        : "e.xyz: only whitespace (5 bytes): not a point cloud");
            }
        }
    }
    EXPECT_EQ(FormatXyz(PointCloud{}), "# 0 points\n");
    EXPECT_EQ(ParsePointCloud(FormatXyz(PointCloud{}), "e.xyz").size(), 0u);
}

TEST(Files, WriteThenReadByExtensionAndMissingFile) {
    const auto dir = std::filesystem::temp_directory_path() / ("surfel_io_" + std::to_string(::getpid()));
    std::filesystem::create_directories(dir);
    const PointCloud c = RichCloud();
    WritePointCloud(c, (dir / "a.ply").string());
    WritePointCloud(c, (dir / "b.ply").string(), /*ascii=*/true);
    WritePointCloud(c, (dir / "c.xyz").string());
    ExpectBitExact(c, ReadPointCloud((dir / "a.ply").string()));
    ExpectBitExact(c, ReadPointCloud((dir / "b.ply").string()));
    EXPECT_EQ(ReadPointCloud((dir / "c.xyz").string()).positions, c.positions);
    try {
        ReadPointCloud((dir / "missing.ply").string());
        FAIL();
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kNotFound);
        EXPECT_NE(std::string(e.what()).find("missing.ply: cannot open file"), std::string::npos);
    }
    EXPECT_THROW(WritePointCloud(c, (dir / "x.obj").string()), Error);
    std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace surfel
