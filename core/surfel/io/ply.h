#pragma once
/// \file
/// PLY point-cloud reader and writer (XYZ is in xyz.h, the choice of format in cloud_io.h).
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
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "surfel/base/point_cloud.h"

namespace surfel {

/// Encoding of a PLY body.
enum class PlyFormat { kAscii, kBinaryLittleEndian, kBinaryBigEndian };
/// The header keyword of a format: "ascii", "binary_little_endian" or "binary_big_endian".
const char* PlyFormatName(PlyFormat format);

/// Limits that protect a reader of untrusted files.
struct PlyReadOptions {
    std::uint64_t max_points = 200'000'000;     ///< Largest accepted vertex count.
    std::uint64_t max_faces = 400'000'000;      ///< Largest accepted face count.
    std::uint64_t max_elements = 1'000'000'000; ///< Largest count of any other element.
    std::size_t max_header_bytes = 64 * 1024;   ///< The header must end within this many bytes.
    /// Read and check the whole file as usual (the same errors), but keep only the positions
    /// (and faces): normals, colours, radii and extra properties are left out of the cloud and
    /// only named in PlyHeaderInfo::attributes. What an upload's check needs (InspectCloudFile).
    bool positions_only = false;
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
    /// PointCloud::AttributeNames() of the cloud the file holds, also when positions_only left
    /// the values out (every parser of the format table fills it).
    std::vector<std::string> attributes;
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

/// What an upload's check keeps of a PLY file (InspectPly).
struct PlySummary {
    std::uint64_t points = 0;             ///< Vertices.
    BoundingBox bounds;                   ///< Of the positions (all finite).
    std::vector<std::string> attributes;  ///< PointCloud::AttributeNames() of the full parse.
};

/// ParsePly with positions_only, summarised, with the same checks in the same order and the
/// same messages; the positions of a binary vertex element without lists are not kept at all
/// (read a block of about 64 KiB at a time: no array of every position to allocate and fault
/// in, issue 19.3). What InspectCloudFile runs for PLY uploads.
PlySummary InspectPly(std::string_view data, std::string_view name, const PlyReadOptions& options = {});

/// The positions part of InspectPly folded in while a file arrives in pieces (an upload's
/// chunks, issue 19.3: the check runs beside the transfer, on bytes still in the cache). Append
/// the file's bytes in order, from its first; the header is parsed once it has arrived, then
/// each piece's vertex records (a record split between pieces included) go into the same count,
/// bounds and first non-finite coordinate that InspectPly computes. InspectPly given a scan
/// then runs every other check as before (header, truncation, other elements, trailing bytes,
/// faces; the same errors in the same order) and takes the positions from the scan instead of
/// reading them again, but only when the scan covered the whole vertex element of exactly these
/// bytes with the layout its own header parse finds; otherwise (a binary vertex element with
/// lists or after one, an ascii vertex element that is not the first element or has an error or
/// a line over 64 KiB, an ascii file whose last vertex line has no newline, a header the scan
/// could not parse, bytes not appended from the start) it reads them as without one. An ascii
/// vertex element is read line by line as the whole-file check reads it (every field of every
/// record checked the same way); at its first error the scan stops and the whole-file check
/// finds and names it. Not thread-safe; a result, never an error, is what it changes: it throws
/// nothing.
class PlyPositionScan {
  public:
    explicit PlyPositionScan(const PlyReadOptions& options = {});
    ~PlyPositionScan();
    PlyPositionScan(const PlyPositionScan&) = delete;
    PlyPositionScan& operator=(const PlyPositionScan&) = delete;

    /// The next bytes of the file.
    void Append(std::string_view bytes) noexcept;
    /// Bytes appended so far.
    std::uint64_t bytes() const;
    /// True when every vertex record has been folded in (InspectPly can use the scan if the
    /// file is exactly bytes() long).
    bool complete() const;

    struct State;  ///< ply.cpp

  private:
    std::unique_ptr<State> state_;
    friend PlySummary InspectPly(std::string_view, std::string_view, const PlyReadOptions&, const PlyPositionScan*);
};

/// InspectPly with the positions of `scan` (see PlyPositionScan; nullptr: InspectPly above).
PlySummary InspectPly(std::string_view data, std::string_view name, const PlyReadOptions& options,
                      const PlyPositionScan* scan);

/// Reads a PLY file. Throws Error(kNotFound) when it cannot be opened.
PointCloud ReadPly(const std::string& path, const PlyReadOptions& options = {},
                   PlyHeaderInfo* info = nullptr);

/// Serialises a cloud as PLY. A cloud written and read back is identical, attribute for
/// attribute, bit for bit (positions, normals, radii as float; colours in their recorded type;
/// extras in their recorded type).
std::string FormatPly(const PointCloud& cloud, const PlyWriteOptions& options = {});

/// Writes a PLY file. Throws Error(kNotFound) when the file cannot be created.
void WritePly(const PointCloud& cloud, const std::string& path, const PlyWriteOptions& options = {});

/// True when `bytes` starts with the PLY magic line ("ply" then LF or CR LF).
bool HasPlyMagic(std::string_view bytes);

/// The encoding named by the header's `format` line, found without parsing the file (comment
/// and obj_info lines before it are skipped). kAscii when no such line comes before
/// `end_header` or within PlyReadOptions{}.max_header_bytes; for sniffing only: ParsePly
/// validates the header.
PlyFormat SniffPlyFormat(std::string_view bytes);

}  // namespace surfel
