// The malformed-input table: each case gives the input and the exact message it must produce.
#include <gtest/gtest.h>

#include <cstring>

#include "surfel/base/error.h"
#include "surfel/io/ply.h"
#include "surfel/io/xyz.h"

namespace surfel {
namespace {

const std::string kXyzHeader = "property float x\nproperty float y\nproperty float z\n";

std::string Ascii(const std::string& elements, const std::string& body) {
    return "ply\nformat ascii 1.0\n" + elements + "end_header\n" + body;
}

std::string BinaryVertices(int declared, int present) {
    std::string s = "ply\nformat binary_little_endian 1.0\nelement vertex " + std::to_string(declared) + "\n" + kXyzHeader + "end_header\n";
    for (int i = 0; i < present * 3; ++i) {
        float v = float(i);
        s.append(reinterpret_cast<const char*>(&v), 4);
    }
    return s;
}

struct Case {
    const char* name;
    std::string input;
    ErrorCode code;
    std::string message;
};

std::vector<Case> Cases() {
    const std::string v2 = "element vertex 2\n" + kXyzHeader;
    return {
        {"not_ply", "PLY\nformat ascii 1.0\n", ErrorCode::kInvalidArgument, "bad.ply: not a PLY file (the first line must be 'ply')"},
        {"empty", "", ErrorCode::kInvalidArgument, "bad.ply: not a PLY file (the first line must be 'ply')"},
        {"unknown_format", "ply\nformat binary_middle_endian 1.0\n", ErrorCode::kInvalidArgument,
         "bad.ply: header line 2: unknown format 'binary_middle_endian' (expected ascii, binary_little_endian or binary_big_endian)"},
        {"bad_version", "ply\nformat ascii 2.0\n", ErrorCode::kInvalidArgument, "bad.ply: header line 2: unsupported PLY version '2.0' (expected 1.0)"},
        {"no_format", "ply\nelement vertex 1\n", ErrorCode::kInvalidArgument, "bad.ply: header line 2: 'element' before the 'format' line"},
        {"unknown_type", "ply\nformat ascii 1.0\nelement vertex 1\nproperty float3 x\n", ErrorCode::kInvalidArgument,
         "bad.ply: header line 4: unknown type 'float3' for property 'x'"},
        {"unknown_list_type", "ply\nformat ascii 1.0\nelement face 1\nproperty list uchar integer vertex_indices\n", ErrorCode::kInvalidArgument,
         "bad.ply: header line 4: unknown type 'integer' for the items of list 'vertex_indices'"},
        {"stray_header_line", "ply\nformat ascii 1.0\nelement vertex 1\n" + kXyzHeader + "texture_file skin.png\nend_header\n", ErrorCode::kInvalidArgument,
         "bad.ply: header line 7: unknown keyword 'texture_file' (expected comment, obj_info, format, element, property or end_header)"},
        {"property_before_element", "ply\nformat ascii 1.0\nproperty float x\n", ErrorCode::kInvalidArgument,
         "bad.ply: header line 3: 'property' before any 'element'"},
        {"bad_count", "ply\nformat ascii 1.0\nelement vertex -3\n", ErrorCode::kInvalidArgument,
         "bad.ply: header line 3: element 'vertex' has an invalid count '-3'"},
        {"duplicate_property", "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float x\n", ErrorCode::kInvalidArgument,
         "bad.ply: header line 5: property 'x' declared twice in element 'vertex'"},
        {"no_end_header", "ply\nformat ascii 1.0\nelement vertex 1\n" + kXyzHeader, ErrorCode::kInvalidArgument,
         "bad.ply: header ends without 'end_header' (after line 6)"},
        {"header_too_large", "ply\nformat ascii 1.0\n" + std::string(70000, 'c'), ErrorCode::kInvalidArgument,
         "bad.ply: header is larger than 65536 bytes (no end_header within the limit)"},
        {"missing_z", Ascii("element vertex 1\nproperty float x\nproperty float y\n", "1 2\n"), ErrorCode::kInvalidArgument,
         "bad.ply: header line 3: element 'vertex' has no property 'z'"},
        {"no_vertex_element", Ascii("element face 0\nproperty list uchar int vertex_indices\n", ""), ErrorCode::kInvalidArgument,
         "bad.ply: no 'vertex' element in the header"},
        {"too_many_points", "ply\nformat ascii 1.0\nelement vertex 300000000\n", ErrorCode::kResourceExhausted,
         "bad.ply: header line 3: element 'vertex' has 300000000 records, over the limit of 200000000"},
        {"ascii_too_few_values", Ascii(v2, "1 2 3\n4 5\n"), ErrorCode::kInvalidArgument,
         "bad.ply: line 9: vertex 1, field 'z': missing value (the line has 2 values)"},
        {"ascii_too_many_values", Ascii(v2, "1 2 3\n4 5 6 7\n"), ErrorCode::kInvalidArgument,
         "bad.ply: line 9: vertex 1 has 4 values, expected 3"},
        {"ascii_not_a_number", Ascii(v2, "1 2 3\n4 five 6\n"), ErrorCode::kInvalidArgument,
         "bad.ply: line 9: vertex 1, field 'y': 'five' is not a valid float"},
        {"ascii_uchar_out_of_range", Ascii("element vertex 1\n" + kXyzHeader + "property uchar red\nproperty uchar green\nproperty uchar blue\n", "1 2 3 256 0 0\n"),
         ErrorCode::kInvalidArgument, "bad.ply: line 11: vertex 0, field 'red': '256' is not a valid uchar"},
        {"ascii_truncated", Ascii(v2, "1 2 3\n"), ErrorCode::kInvalidArgument,
         "bad.ply: line 9: unexpected end of file: element 'vertex' declares 2 records, found 1"},
        {"ascii_extra_data", Ascii(v2, "1 2 3\n4 5 6\n7 8 9\n"), ErrorCode::kInvalidArgument,
         "bad.ply: line 10: unexpected data after the last element (the header's counts do not match the data)"},
        {"nan_coordinate", Ascii(v2, "1 2 3\n4 nan 6\n"), ErrorCode::kInvalidArgument,
         "bad.ply: vertex 1, field 'y': coordinate is not finite (nan)"},
        {"inf_coordinate", Ascii(v2, "1 2 inf\n4 5 6\n"), ErrorCode::kInvalidArgument,
         "bad.ply: vertex 0, field 'z': coordinate is not finite (inf)"},
        {"face_index_out_of_range", Ascii(v2 + "element face 1\nproperty list uchar int vertex_indices\n", "0 0 0\n1 0 0\n3 0 1 2\n"),
         ErrorCode::kInvalidArgument, "bad.ply: face triangle 0: vertex index 2 is not below the vertex count 2"},
        {"face_too_few_vertices", Ascii(v2 + "element face 1\nproperty list uchar int vertex_indices\n", "0 0 0\n1 0 0\n2 0 1\n"),
         ErrorCode::kInvalidArgument, "bad.ply: element 'face' 0: a face needs at least 3 vertices, has 2"},
        {"list_longer_than_line", Ascii(v2 + "element face 1\nproperty list uchar int vertex_indices\n", "0 0 0\n1 0 0\n4 0 1\n"),
         ErrorCode::kInvalidArgument, "bad.ply: line 12: face 0, field 'vertex_indices': list declares 4 items but the line has 2"},
        {"binary_truncated", BinaryVertices(10, 4), ErrorCode::kInvalidArgument,
         "bad.ply: truncated data: element 'vertex' declares 10 records but the file ends in record 4 (byte offset 164)"},
        // Found by the fuzzer: a record with a list, cut off after its first fields.
        {"binary_list_record_cut", std::string("ply\nformat binary_little_endian 1.0\nelement vertex 2\n") + kXyzHeader +
                                       "property list uchar int ids\nend_header\n" + std::string(13, '\0') + std::string(8, '\0'),
         ErrorCode::kInvalidArgument, "bad.ply: truncated data: element 'vertex' declares 2 records but the file ends in record 1 (byte offset 164)"},
        {"binary_extra_data", BinaryVertices(2, 3), ErrorCode::kInvalidArgument,
         "bad.ply: 12 bytes of unexpected data after the last element (byte offset 139; the header's counts do not match the data)"},
    };
}

void PrintTo(const Case& c, std::ostream* os) { *os << c.name; }

class Malformed : public ::testing::TestWithParam<Case> {};

TEST_P(Malformed, ThrowsTheExactMessage) {
    const Case& c = GetParam();
    try {
        ParsePly(c.input, "bad.ply");
        FAIL() << "no error for " << c.name;
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), c.code) << ErrorCodeName(e.code());
        EXPECT_EQ(std::string(e.what()), c.message);
    }
}

INSTANTIATE_TEST_SUITE_P(Ply, Malformed, ::testing::ValuesIn(Cases()),
                         [](const ::testing::TestParamInfo<Case>& i) { return std::string(i.param.name); });

TEST(PlyLimits, ConfigurableCountLimit) {
    PlyReadOptions o;
    o.max_points = 1;
    try {
        ParsePly(Ascii("element vertex 2\n" + kXyzHeader, "1 2 3\n4 5 6\n"), "small.ply", o);
        FAIL();
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kResourceExhausted);
        EXPECT_STREQ(e.what(), "small.ply: header line 3: element 'vertex' has 2 records, over the limit of 1");
    }
}

TEST(XyzMalformed, NamesTheLineAndField) {
    try {
        ParseXyz("1 2 3\n4 5 x\n", "pts.xyz");
        FAIL();
    } catch (const Error& e) {
        EXPECT_STREQ(e.what(), "pts.xyz: line 2: field 'z': 'x' is not a number");
    }
    try {
        ParseXyz("1 2 3\n4 5 6 0 0 1\n", "pts.xyz");
        FAIL();
    } catch (const Error& e) {
        EXPECT_STREQ(e.what(), "pts.xyz: line 2: has 6 values but earlier lines have 3");
    }
}

}  // namespace
}  // namespace surfel
