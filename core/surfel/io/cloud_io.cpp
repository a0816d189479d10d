#include "surfel/io/cloud_io.h"

#include <algorithm>
#include <cctype>
#include <filesystem>
#include <span>
#include <vector>

#include "surfel/base/error.h"
#include "surfel/io/file_bytes.h"
#include "surfel/io/xyz.h"

namespace surfel {
namespace {

// ---- The format table -------------------------------------------------------------------------

// One known format. `magic` recognises its content (nullptr: the fallback when no magic
// matches), `encoding` names the content's variant for SniffCloudFormat, `parse` reads it
// (`info` is PLY's header; the others fill only its `attributes`) and `format` writes it.
struct CloudFormatEntry {
    CloudFileFormat format;
    std::string_view name;
    std::span<const std::string_view> extensions;  // lower case, with the dot
    bool (*magic)(std::string_view bytes);
    std::string_view (*encoding)(std::string_view bytes);
    PointCloud (*parse)(std::string_view data, std::string_view name, const PlyReadOptions& options,
                        PlyHeaderInfo* info);
    std::string (*format_cloud)(const PointCloud& cloud, bool ascii);
};

// ---- PLY ----

constexpr std::string_view kPlyExtensions[] = {".ply"};

std::string_view PlyEncoding(std::string_view bytes) {
    switch (SniffPlyFormat(bytes)) {
        case PlyFormat::kAscii: return "ply-ascii";
        case PlyFormat::kBinaryLittleEndian: return "ply-binary-le";
        case PlyFormat::kBinaryBigEndian: return "ply-binary-be";
    }
    return "ply-ascii";
}

PointCloud ParsePlyEntry(std::string_view data, std::string_view name, const PlyReadOptions& options,
                         PlyHeaderInfo* info) {
    return ParsePly(data, name, options, info);
}

std::string FormatPlyEntry(const PointCloud& cloud, bool ascii) {
    PlyWriteOptions opt;
    opt.format = ascii ? PlyFormat::kAscii : PlyFormat::kBinaryLittleEndian;
    return FormatPly(cloud, opt);
}

// ---- XYZ ----

constexpr std::string_view kXyzExtensions[] = {".xyz", ".txt", ".pts"};

std::string_view XyzEncoding(std::string_view) { return "xyz"; }

PointCloud ParseXyzEntry(std::string_view data, std::string_view name, const PlyReadOptions& options,
                         PlyHeaderInfo* info) {
    PointCloud cloud = ParseXyz(data, name, options.max_points);
    if (info) info->attributes = cloud.AttributeNames();
    return cloud;
}

std::string FormatXyzEntry(const PointCloud& cloud, bool) { return FormatXyz(cloud); }

// ---- The table and its lookups ----

constexpr CloudFormatEntry kFormats[] = {
    {CloudFileFormat::kPly, "ply", kPlyExtensions, HasPlyMagic, PlyEncoding, ParsePlyEntry, FormatPlyEntry},
    {CloudFileFormat::kXyz, "xyz", kXyzExtensions, nullptr, XyzEncoding, ParseXyzEntry, FormatXyzEntry},
};

const CloudFormatEntry& Entry(CloudFileFormat format) {
    for (const auto& e : kFormats)
        if (e.format == format) return e;
    SURFEL_CHECK(false, "CloudFileFormat missing from the format table");
    return kFormats[0];
}

// The format whose magic the content shows; the one without magic otherwise.
const CloudFormatEntry& EntryForContent(std::string_view bytes) {
    const CloudFormatEntry* fallback = nullptr;
    for (const auto& e : kFormats) {
        if (!e.magic) fallback = &e;
        else if (e.magic(bytes)) return e;
    }
    SURFEL_CHECK(fallback != nullptr, "the format table has no fallback format");
    return *fallback;
}

// ".ply, .xyz, .txt or .pts"
std::string KnownExtensions() {
    std::vector<std::string_view> all;
    for (const auto& e : kFormats) all.insert(all.end(), e.extensions.begin(), e.extensions.end());
    std::string out;
    for (std::size_t i = 0; i < all.size(); ++i) {
        if (i > 0) out += i + 1 == all.size() ? " or " : ", ";
        out += all[i];
    }
    return out;
}

}  // namespace

// ---- Public entry points ------------------------------------------------------------------------

std::string_view CloudFormatName(CloudFileFormat format) { return Entry(format).name; }

CloudFileFormat FormatFromPath(const std::string& path) {
    std::string ext = std::filesystem::path(path).extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
    for (const auto& e : kFormats)
        if (std::find(e.extensions.begin(), e.extensions.end(), ext) != e.extensions.end()) return e.format;
    throw Error(ErrorCode::kInvalidArgument,
                path + ": unknown point-cloud file extension '" + ext + "' (expected " + KnownExtensions() + ")");
}

std::string_view SniffCloudFormat(std::string_view bytes) { return EntryForContent(bytes).encoding(bytes); }

PointCloud ParsePointCloud(std::string_view data, std::string_view name, const PlyReadOptions& options) {
    return EntryForContent(data).parse(data, name, options, nullptr);
}

CloudFileSummary InspectCloudFile(std::string_view data, std::string_view name, const PlyReadOptions& options,
                                  const PlyPositionScan* scan) {
    const CloudFormatEntry& entry = EntryForContent(data);
    if (entry.format == CloudFileFormat::kPly) {  // the positions streamed, never all in memory
        PlySummary ply = InspectPly(data, name, options, scan);
        if (ply.points == 0) throw Error(ErrorCode::kInvalidArgument, std::string(name) + ": the cloud has no points");
        CloudFileSummary s;
        s.points = ply.points;
        s.bounds = ply.bounds;
        s.attributes = std::move(ply.attributes);
        s.format = entry.encoding(data);
        return s;
    }
    // Only the positions are kept (bounds, the count); the parse and its checks are the full ones.
    PlyReadOptions positions = options;
    positions.positions_only = true;
    PlyHeaderInfo info;
    const PointCloud cloud = entry.parse(data, name, positions, &info);
    if (cloud.empty()) throw Error(ErrorCode::kInvalidArgument, std::string(name) + ": the cloud has no points");
    CloudFileSummary s;
    s.points = cloud.size();
    s.bounds = cloud.Bounds();
    s.attributes = std::move(info.attributes);
    s.format = SniffCloudFormat(data);
    return s;
}

PointCloud ReadPointCloud(const std::string& path, const PlyReadOptions& options, PlyHeaderInfo* info) {
    const std::string bytes = ReadFileBytes(path);
    return EntryForContent(bytes).parse(bytes, path, options, info);
}

void WritePointCloud(const PointCloud& cloud, const std::string& path, bool ascii) {
    WriteFileBytes(path, Entry(FormatFromPath(path)).format_cloud(cloud, ascii));
}

}  // namespace surfel
