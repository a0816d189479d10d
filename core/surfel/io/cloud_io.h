#pragma once
/// \file
/// Point-cloud files in any known format: the format chosen by the file name's extension (for
/// writing) or by the content (for reading).
///
/// The formats are one table in cloud_io.cpp (name, extensions, content magic, parse, format),
/// after Open3D's extension -> reader map (Open3D, io/PointCloudIO.cpp): a new format is one
/// entry there plus its own reader/writer file.

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "surfel/base/point_cloud.h"
#include "surfel/io/ply.h"

namespace surfel {

/// File formats known to ReadPointCloud/WritePointCloud.
enum class CloudFileFormat { kPly, kXyz };

/// The table name of a format: "ply" or "xyz".
std::string_view CloudFormatName(CloudFileFormat format);

/// Chooses a format from the file name's extension, case-insensitively (.ply; .xyz, .txt, .pts).
/// Throws Error(kInvalidArgument) naming the path, the extension and the known ones otherwise.
CloudFileFormat FormatFromPath(const std::string& path);

/// Names the encoding of a cloud held in memory, as the format that ParsePointCloud would choose
/// for it: "ply-binary-le", "ply-binary-be" or "ply-ascii" (from the PLY header's format line,
/// see SniffPlyFormat), otherwise "xyz". Does not validate the bytes.
std::string_view SniffCloudFormat(std::string_view bytes);

/// Parses a cloud held in memory in the format its content shows (the PLY magic line, otherwise
/// XYZ). `name` is used in error messages; `options` limits the counts (XYZ: max_points only).
PointCloud ParsePointCloud(std::string_view data, std::string_view name,
                           const PlyReadOptions& options = {});

/// What the service records about an uploaded cloud file (surfel.v1.Cloud without its id).
struct CloudFileSummary {
    std::uint64_t points = 0;
    BoundingBox bounds;                   ///< Of the positions (all finite).
    std::vector<std::string> attributes;  ///< PointCloud::AttributeNames()
    std::string_view format;              ///< SniffCloudFormat: "ply-binary-le", "ply-ascii", "xyz", ...
};

/// Checks an uploaded file as the service does before it stores it, and summarises it: parsed
/// as ParsePointCloud (the parsers' messages, `options`' limits), and refused with
/// Error(kInvalidArgument) "<name>: the cloud has no points" when it holds none (a PLY with
/// `element vertex 0`, an XYZ of comments). The libFuzzer target cloud_fuzzer runs it.
/// `scan`, when given, is a PlyPositionScan the bytes were appended to as they arrived: a PLY
/// file's positions are then taken from it where it covered them (InspectPly), the same result.
CloudFileSummary InspectCloudFile(std::string_view data, std::string_view name, const PlyReadOptions& options = {},
                                  const PlyPositionScan* scan = nullptr);

/// Reads a cloud file in the format its content shows, as ParsePointCloud. `info`, when given,
/// receives the header of a PLY file (left untouched for other formats).
PointCloud ReadPointCloud(const std::string& path, const PlyReadOptions& options = {},
                          PlyHeaderInfo* info = nullptr);

/// Writes a cloud file (atomically) in the format of the file name's extension: PLY binary
/// little-endian, or ascii when `ascii`; XYZ positions and normals (`ascii` is moot).
void WritePointCloud(const PointCloud& cloud, const std::string& path, bool ascii = false);

}  // namespace surfel
