#pragma once
/// \file
/// PLY and XYZ point-cloud readers and writers.
///
/// PLY: ascii, binary_little_endian and binary_big_endian; every scalar type and alias
/// (char/int8, uchar/uint8, short/int16, ushort/uint16, int/int32, uint/uint32, float/float32,
/// double/float64). Vertex properties x, y, z (required), nx, ny, nz, red, green, blue (alpha)
/// as uchar or float/double, radius; every other vertex scalar property is kept as an
/// ExtraAttribute; list properties of the vertex element and all other elements are skipped;
/// `element face` (list property vertex_indices or vertex_index) is read and fan-triangulated.
/// Malformed input throws Error(kInvalidArgument) whose message names the file and the header
/// line, element index, or data line, and the field; counts over the limits in PlyReadOptions
/// throw Error(kResourceExhausted).

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "surfel/base/point_cloud.h"

namespace surfel {

/// Encoding of a PLY body.
enum class PlyFormat { kAscii, kBinaryLittleEndian, kBinaryBigEndian };
const char* PlyFormatName(PlyFormat format);

/// Limits that protect a reader of untrusted files.
struct PlyReadOptions {
    std::uint64_t max_points = 200'000'000;     ///< Largest accepted vertex count.
    std::uint64_t max_faces = 400'000'000;      ///< Largest accepted face count.
    std::uint64_t max_elements = 1'000'000'000; ///< Largest count of any other element.
    std::size_t max_header_bytes = 64 * 1024;   ///< The header must end within this many bytes.
};

/// What a file's header said, for `surfel info`.
struct PlyHeaderInfo {
    PlyFormat format = PlyFormat::kBinaryLittleEndian;
    struct Element {
        std::string name;
        std::uint64_t count = 0;
        std::vector<std::string> properties;  ///< "float x", "list uchar int vertex_indices", ...
    };
    std::vector<Element> elements;
    std::vector<std::string> comments;  ///< comment and obj_info lines, without the keyword.
    std::uint64_t face_count = 0;       ///< Polygons in `element face` (before triangulation).
};

/// How to write a PLY file.
struct PlyWriteOptions {
    PlyFormat format = PlyFormat::kBinaryLittleEndian;
    bool write_faces = true;  ///< Write `element face` when the cloud has triangles.
    std::vector<std::string> comments;
};

/// Parses a PLY file held in memory. `name` is used in error messages (usually the path).
PointCloud ParsePly(std::string_view data, std::string_view name, const PlyReadOptions& options = {},
                    PlyHeaderInfo* info = nullptr);

/// Reads a PLY file. Throws Error(kNotFound) when it cannot be opened.
PointCloud ReadPly(const std::string& path, const PlyReadOptions& options = {},
                   PlyHeaderInfo* info = nullptr);

/// Serialises a cloud as PLY. A cloud written and read back is identical, attribute for
/// attribute, bit for bit (positions, normals, radii as float; colours in their recorded type;
/// extras in their recorded type).
std::string FormatPly(const PointCloud& cloud, const PlyWriteOptions& options = {});

/// Writes a PLY file. Throws Error(kNotFound) when the file cannot be created.
void WritePly(const PointCloud& cloud, const std::string& path, const PlyWriteOptions& options = {});

/// Parses XYZ text: one point per line as `x y z` or `x y z nx ny nz` (the same count on every
/// line), `#` starts a comment, blank lines are ignored.
PointCloud ParseXyz(std::string_view data, std::string_view name, std::uint64_t max_points = 200'000'000);
/// Serialises positions (and normals when present) as XYZ text, shortest round-trip decimals.
std::string FormatXyz(const PointCloud& cloud);

/// File formats known to ReadPointCloud/WritePointCloud.
enum class CloudFileFormat { kPly, kXyz };

/// Chooses a format from the file name's extension (.ply, .xyz, .txt, .pts); otherwise, for
/// reading, from the content ("ply" magic). Throws Error(kInvalidArgument) for unknown ones.
CloudFileFormat FormatFromPath(const std::string& path);

/// Parses PLY or XYZ from memory, sniffing the "ply" magic.
PointCloud ParsePointCloud(std::string_view data, std::string_view name,
                           const PlyReadOptions& options = {});

/// Reads a PLY or XYZ file, by its content.
PointCloud ReadPointCloud(const std::string& path, const PlyReadOptions& options = {},
                          PlyHeaderInfo* info = nullptr);

/// Writes PLY (binary unless `ascii`) or XYZ, chosen by the file name's extension.
void WritePointCloud(const PointCloud& cloud, const std::string& path, bool ascii = false);

/// Reads a whole file into memory. Throws Error(kNotFound) when it cannot be read.
std::string ReadFileBytes(const std::string& path);
/// Writes bytes to a file (atomically: a temporary file renamed into place).
void WriteFileBytes(const std::string& path, std::string_view bytes);

}  // namespace surfel
