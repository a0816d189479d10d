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

// ---- The upload check folded in while the file arrives (PlyPositionScan) ---------------------

// The bytes appended to a scan in pieces that end at `cuts` (offsets, ascending), then the check
// with the scan against the check of the whole file without one: the same summary to the bit,
// or the same code and message. Returns whether the scan covered every vertex record.
bool ExpectScanMatchesWholeFile(const std::string& bytes, const std::string& name, const std::vector<std::size_t>& cuts,
                                const PlyReadOptions& options = {}) {
    PlyPositionScan scan(options);
    std::size_t from = 0;
    for (const std::size_t cut : cuts) {
        const std::size_t to = std::min(cut, bytes.size());
        if (to > from) scan.Append(std::string_view(bytes).substr(from, to - from));
        from = std::max(from, to);
    }
    scan.Append(std::string_view(bytes).substr(from));
    EXPECT_EQ(scan.bytes(), bytes.size());
    std::optional<CloudFileSummary> whole;
    std::string whole_error;
    ErrorCode whole_code = ErrorCode::kInternal;
    try {
        whole = InspectCloudFile(bytes, name, options);
    } catch (const Error& e) {
        whole_error = e.what();
        whole_code = e.code();
    }
    try {
        const CloudFileSummary s = InspectCloudFile(bytes, name, options, &scan);
        EXPECT_TRUE(whole.has_value()) << "only the scanned check accepted it";
        if (whole) {
            EXPECT_EQ(s.points, whole->points);
            EXPECT_EQ(std::memcmp(s.bounds.min.data(), whole->bounds.min.data(), sizeof(Vec3f)), 0);
            EXPECT_EQ(std::memcmp(s.bounds.max.data(), whole->bounds.max.data(), sizeof(Vec3f)), 0);
            EXPECT_EQ(s.attributes, whole->attributes);
            EXPECT_EQ(s.format, whole->format);
        }
    } catch (const Error& e) {
        EXPECT_FALSE(whole.has_value()) << "only the scanned check refused it: " << e.what();
        EXPECT_EQ(e.code(), whole_code);
        EXPECT_EQ(std::string(e.what()), whole_error);
    }
    return scan.complete();
}

// FormatPly writes only the native byte order: big-endian by swapping every 4-byte value of a
// body of 4-byte values.
std::string AsBigEndian(std::string le) {
    const std::size_t body = le.find("end_header\n") + 11;
    le.replace(le.find("binary_little_endian"), 20, "binary_big_endian");
    for (std::size_t i = body - 3; i + 4 <= le.size(); i += 4) std::reverse(le.begin() + i, le.begin() + i + 4);
    return le;
}

// Every two-piece split (a cut at each byte: in the header, at its end, inside every record),
// one-byte pieces, and pieces of a record's size plus or minus one.
void ExpectScanMatchesAtEveryCut(const std::string& bytes, const std::string& name, bool expect_complete,
                                 const PlyReadOptions& options = {}) {
    SCOPED_TRACE(name);
    for (std::size_t cut = 0; cut <= bytes.size(); ++cut)
        EXPECT_EQ(ExpectScanMatchesWholeFile(bytes, name, {cut}, options), expect_complete) << "cut at " << cut;
    for (const std::size_t piece : {std::size_t{1}, std::size_t{23}, std::size_t{25}, std::size_t{4096 + 3}}) {
        std::vector<std::size_t> cuts;
        for (std::size_t c = piece; c < bytes.size(); c += piece) cuts.push_back(c);
        EXPECT_EQ(ExpectScanMatchesWholeFile(bytes, name, cuts, options), expect_complete) << "pieces of " << piece;
    }
}

TEST(PlyPositionScan, AgreesWithTheWholeFileCheckOnValidFilesOfEveryFormat) {
    ShapeOptions o;
    o.points = 40;  // 24-byte records (positions and normals)
    o.normals = true;
    const PointCloud cloud = SampleShape(Shape::kTorus, o);
    const std::string le = FormatPly(cloud);
    ExpectScanMatchesAtEveryCut(le, "le.ply", true);
    ExpectScanMatchesAtEveryCut(AsBigEndian(le), "be.ply", true);
    PlyWriteOptions ascii;
    ascii.format = PlyFormat::kAscii;
    const std::string ascii_ply = FormatPly(cloud, ascii);
    ExpectScanMatchesAtEveryCut(ascii_ply, "ascii.ply", true);
    // Ascii: CR LF, blank lines, signs, exponents, a double and a uchar, a list in the vertex
    // records and faces after them (read after the last byte); the last line without a newline.
    const std::string odd_ascii =
        "ply\r\nformat ascii 1.0\r\ncomment x\r\nelement vertex 3\r\nproperty uchar tag\r\nproperty double z\r\n"
        "property list uchar int ids\r\nproperty float x\r\nproperty float y\r\nelement face 1\r\n"
        "property list uchar int vertex_indices\r\nend_header\r\n"
        "7 -1.5 2 4 -5 2.25 0.5\r\n\r\n  \t\r\n14 1e-3 0 -3.5 -0\r\n\n+21 3 1 9 1e30 2\r\n3 0 1 2\r\n\r\n";
    ExpectScanMatchesAtEveryCut(odd_ascii, "odd-ascii.ply", true);
    ExpectScanMatchesAtEveryCut(ascii_ply.substr(0, ascii_ply.size() - 1), "no-newline.ply", false);
    // Doubles, an extra property before x and a header with CR LF, comments and end_header in one.
    std::string odd = "ply\r\nformat binary_little_endian 1.0\r\ncomment end_header is not here\r\n"
                      "element vertex 3\r\nproperty uchar tag\r\nproperty double z\r\nproperty double x\r\n"
                      "property float y\r\nend_header\r\n";
    for (int i = 0; i < 3; ++i) {
        const std::uint8_t tag = static_cast<std::uint8_t>(7 * i);
        const double z = -1.5 * i, x = 2.25 + i;
        const float y = i == 1 ? -0.0f : 0.5f * i;
        odd.append(reinterpret_cast<const char*>(&tag), 1);
        odd.append(reinterpret_cast<const char*>(&z), 8);
        odd.append(reinterpret_cast<const char*>(&x), 8);
        odd.append(reinterpret_cast<const char*>(&y), 4);
    }
    ExpectScanMatchesAtEveryCut(odd, "odd.ply", true);
    // Another element of fixed size before the vertices (their offset follows from the header),
    // and faces after them; faces (a list) before the vertices: read after the last byte.
    std::string before = "ply\nformat binary_little_endian 1.0\nelement camera 2\nproperty float f\n"
                         "element vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
    for (const float v : {9.0f, 8.0f, 1.0f, 2.0f, 3.0f, -4.0f, 5.0f, -6.0f}) before.append(reinterpret_cast<const char*>(&v), 4);
    ExpectScanMatchesAtEveryCut(before, "camera.ply", true);
    PointCloud mesh = cloud;
    mesh.triangles = {{0, 1, 2}, {3, 4, 39}};
    ExpectScanMatchesAtEveryCut(FormatPly(mesh), "mesh.ply", true);
    const std::string faces_first = "ply\nformat binary_little_endian 1.0\nelement face 1\n"
                                    "property list uchar int vertex_indices\nelement vertex 3\nproperty float x\n"
                                    "property float y\nproperty float z\nend_header\n";
    std::string ff = faces_first + std::string("\x03\0\0\0\0\x01\0\0\0\x02\0\0\0", 13);
    for (int i = 0; i < 9; ++i) {
        const float v = static_cast<float>(i);
        ff.append(reinterpret_cast<const char*>(&v), 4);
    }
    ExpectScanMatchesAtEveryCut(ff, "faces-first.ply", false);
    ExpectScanMatchesAtEveryCut("ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\n"
                                "element vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
                                "3 0 1 2\n0 0 0\n1 0 0\n0 1 0\n", "faces-first-ascii.ply", false);
    // Many blocks (64 KiB of records) in large pieces, cut inside records.
    ShapeOptions big = o;
    big.points = 66 * 2730 + 17;
    const std::string large = FormatPly(SampleShape(Shape::kSphere, big));
    std::vector<std::size_t> cuts;
    for (std::size_t c = 100; c < large.size(); c += (1u << 20) + 5) cuts.push_back(c);
    EXPECT_TRUE(ExpectScanMatchesWholeFile(large, "large.ply", cuts));
    EXPECT_TRUE(ExpectScanMatchesWholeFile(AsBigEndian(large), "large-be.ply", cuts));
    // Many ascii blocks (4096 records), in pieces of an upload's size cut inside lines.
    ShapeOptions many = o;
    many.points = 3 * 4096 + 17;
    const std::string large_ascii = FormatPly(SampleShape(Shape::kSphere, many), ascii);
    std::vector<std::size_t> ascii_cuts;
    for (std::size_t c = 100; c < large_ascii.size(); c += (256u << 10) + 5) ascii_cuts.push_back(c);
    EXPECT_TRUE(ExpectScanMatchesWholeFile(large_ascii, "large-ascii.ply", ascii_cuts));
}

TEST(PlyPositionScan, RefusesWhatTheWholeFileCheckRefusesWithTheSameMessage) {
    ShapeOptions o;
    o.points = 30;
    o.normals = true;
    const PointCloud cloud = SampleShape(Shape::kSphere, o);
    for (const bool big : {false, true}) {
        auto as = [big](const std::string& le) { return big ? AsBigEndian(le) : le; };
        for (const std::size_t bad : {std::size_t{0}, std::size_t{17}, std::size_t{29}}) {
            PointCloud c = cloud;
            c.positions[bad].y() = std::numeric_limits<float>::quiet_NaN();
            if (bad == 17) c.positions[20].x() = std::numeric_limits<float>::infinity();  // the first is named
            const std::string nan = as(FormatPly(c));
            ExpectScanMatchesAtEveryCut(nan, "nan.ply", true);
            ExpectScanMatchesAtEveryCut(nan + "junk", "nan-tail.ply", true);  // the tail is reported first
        }
        const std::string ok = as(FormatPly(cloud));
        ExpectScanMatchesAtEveryCut(ok.substr(0, ok.size() - 5), "cut.ply", false);  // truncated in a record
        ExpectScanMatchesAtEveryCut(ok + "xyz", "tail.ply", true);
        PointCloud mesh = cloud;
        mesh.triangles = {{0, 1, 30}};  // an index past the vertices
        ExpectScanMatchesAtEveryCut(FormatPly(mesh), "mesh-bad.ply", true);
    }
    PlyReadOptions limits;
    limits.max_points = 29;  // over the limit: kResourceExhausted from the header
    ExpectScanMatchesAtEveryCut(FormatPly(cloud), "many.ply", false, limits);
    const std::string header = "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n";
    ExpectScanMatchesAtEveryCut(header + "property float z\nend_header\n" + std::string(8, '\0'), "no-y.ply", false);
    ExpectScanMatchesAtEveryCut(header + "bogus line\nend_header\n" + std::string(4, '\0'), "bogus.ply", false);
    ExpectScanMatchesAtEveryCut(header + "property float y\nproperty float z\nend_header", "no-newline.ply", false);
    ExpectScanMatchesAtEveryCut("ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\n"
                                "property float y\nproperty float z\nend_header\n", "empty.ply", true);
    // Ascii: what a vertex line can get wrong turns the scan off and the whole-file check names
    // it; non-finite positions, a bad face index and trailing text are found after the scan.
    PlyWriteOptions ascii;
    ascii.format = PlyFormat::kAscii;
    for (const std::size_t bad : {std::size_t{0}, std::size_t{17}, std::size_t{29}}) {
        PointCloud c = cloud;
        c.positions[bad].y() = std::numeric_limits<float>::quiet_NaN();
        if (bad == 17) c.positions[20].x() = std::numeric_limits<float>::infinity();
        ExpectScanMatchesAtEveryCut(FormatPly(c, ascii), "nan-ascii.ply", true);
        ExpectScanMatchesAtEveryCut(FormatPly(c, ascii) + "\n \njunk", "nan-tail-ascii.ply", true);
    }
    const std::string ascii_header = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                                     "property float z\nproperty uchar c\nproperty list uchar int l\nend_header\n";
    for (const char* body : {"0 0 0 1 0\n1 x 0 1 0\n0 1 0 1 0\n", "0 0 0 1 0\n1 0 0 1\n0 1 0 1 0\n",
                             "0 0 0 1 0\n1 0 0 1 0 7\n0 1 0 1 0\n", "0 0 0 1 0\n1 0 0 300 0\n0 1 0 1 0\n",
                             "0 0 0 1 2 5\n", "0 0 0 1 -1\n", "0 0 0 1 0\n1 0 0 1 0\n", "0 0 0 1 0\n1 0 0 1e1 0\n"})
        ExpectScanMatchesAtEveryCut(ascii_header + body, "bad-ascii.ply", false);
    ExpectScanMatchesAtEveryCut(ascii_header + "0 0 0 1 0\n1 0 0 1 1 4\n0 1 0 1 0\n0 0 1 1 0\n", "extra-line.ply",
                                true);
    ExpectScanMatchesAtEveryCut(ascii_header + "0 0 0 1 0\n1 0 0 1 0\n0 1 0 1 0", "last-line.ply", false);
    PointCloud ascii_mesh = cloud;
    ascii_mesh.triangles = {{0, 1, 30}};
    ExpectScanMatchesAtEveryCut(FormatPly(ascii_mesh, ascii), "mesh-bad-ascii.ply", true);
    ExpectScanMatchesAtEveryCut(FormatPly(cloud, ascii), "many-ascii.ply", false, limits);
    // A vertex line over 64 KiB: the scan stops; the whole-file check reads it.
    EXPECT_FALSE(ExpectScanMatchesWholeFile(ascii_header + "0 0 0 1 0\n1" + std::string(70000, ' ') +
                                                " 0 0 1 0\n0 1 0 1 0\n",
                                            "long-line.ply", {100, 40000}));
    ExpectScanMatchesAtEveryCut("not a ply file\n", "junk.ply", false);
    ExpectScanMatchesAtEveryCut("1 2 3\n4 5 6\n", "points.xyz", false);
}

// Float positions in the machine's byte order are folded 16 bytes at a time (lane-wise minima and
// maxima): Extend's bits for records of 3 to 9 floats, a zero of either sign at a bound (the
// first one met is kept, so such a block goes the scalar way), and a non-finite coordinate named
// as the whole-file check names it, in whole periods of the pattern and in the records after.
TEST(PlyPositionScan, FoldsPlainFloatsToTheBitsOfExtend) {
    ShapeOptions o;
    o.points = 3 * 2730 + 5;
    PointCloud base = SampleShape(Shape::kTorus, o);
    for (Vec3f& p : base.positions) p = p.cwiseAbs() + Vec3f::Constant(1.0f);
    for (int extras = 0; extras <= 6; ++extras) {
        PointCloud cloud = base;
        for (int k = 0; k < extras; ++k)
            cloud.extras.push_back({std::string(1, static_cast<char>('a' + k)), ScalarType::kFloat32,
                                    std::vector<double>(cloud.size(), k == 0 ? std::nan("") : 0.5)});
        const std::string name = "plain" + std::to_string(extras) + ".ply";
        std::vector<std::size_t> cuts;
        for (std::size_t c = 333; c < cloud.size() * 40; c += 7777) cuts.push_back(c);
        EXPECT_TRUE(ExpectScanMatchesWholeFile(FormatPly(cloud), name, cuts));  // no zeros: the vector path
        PointCloud zeros = cloud;
        zeros.positions[10].x() = 0.0f;  // +0 first, then -0: the lower x bound is +0
        zeros.positions[20].x() = -0.0f;
        zeros.positions[3000].y() = -0.0f;  // -0 then +0 in a later block: the lower y bound is -0
        zeros.positions[4000].y() = 0.0f;
        zeros.positions[8194].z() = -0.0f;  // in the records after the last whole period
        EXPECT_TRUE(ExpectScanMatchesWholeFile(FormatPly(zeros), name, cuts));
        const BoundingBox b = zeros.Bounds();
        ASSERT_TRUE(std::signbit(b.min.y()) && !std::signbit(b.min.x()));
        for (const std::size_t bad : {std::size_t{7}, std::size_t{2731}, cloud.size() - 1}) {
            PointCloud c = cloud;
            c.positions[bad].z() = -std::numeric_limits<float>::infinity();
            EXPECT_TRUE(ExpectScanMatchesWholeFile(FormatPly(c), name, cuts));
        }
    }
}

// The scan's positions are what the check takes (it does not read them again): bytes of the same
// size and layout but other positions get the scanned bounds. Appending exactly the file's bytes
// is the caller's part (UploadSession appends each chunk it writes).
TEST(PlyPositionScan, IsTakenInsteadOfReadingThePositionsAgain) {
    PointCloud a = SmallCloud();
    PointCloud b = a;
    for (Vec3f& p : b.positions) p *= 2.0f;
    const std::string bytes_a = FormatPly(a), bytes_b = FormatPly(b);
    ASSERT_EQ(bytes_a.size(), bytes_b.size());
    PlyPositionScan scan;
    scan.Append(bytes_a);
    ASSERT_TRUE(scan.complete());
    const PlySummary s = InspectPly(bytes_b, "b.ply", {}, &scan);
    EXPECT_EQ(s.bounds.min, a.Bounds().min);
    EXPECT_EQ(s.bounds.max, a.Bounds().max);
    // A different size (one byte more at the end): the scan is not taken, the bytes are read.
    const PlySummary t = InspectPly(bytes_b + "\n", "b.ply", {}, &scan);
    EXPECT_EQ(t.bounds.min, b.Bounds().min);
    // Ascii: the lines of the vertex element are not read again either.
    const std::string header = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                               "property float z\nend_header\n";
    PlyPositionScan ascii_scan;
    ascii_scan.Append(header + "1 2 3\n4 5 6\n");
    ASSERT_TRUE(ascii_scan.complete());
    const PlySummary u = InspectPly(header + "7 8 9\n1 1 1\n", "c.ply", {}, &ascii_scan);
    EXPECT_EQ(u.bounds.min, Vec3f(1, 2, 3));
    EXPECT_EQ(u.bounds.max, Vec3f(4, 5, 6));
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
