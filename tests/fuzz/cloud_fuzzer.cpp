// Fuzzes the upload path's check of a file (InspectCloudFile, which UploadSession::Finish runs
// before it stores a cloud): format sniffing, the PLY and XYZ readers under the server's point
// limit, and the summary the service records. Any input is refused with surfel::Error or gives a
// summary that agrees with the cloud it describes: at least one point, finite bounds that hold
// every point, and the format that ParsePointCloud chose. The same bytes appended in pieces to a
// PlyPositionScan (as the server does with an upload's chunks) get the same answer.
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <string_view>

#include "surfel/base/error.h"
#include "surfel/io/cloud_io.h"
#include "surfel/io/ply.h"

namespace {

// The check with a PlyPositionScan of the bytes appended in pieces (as an upload's chunks, of a
// size the input's length picks): the same summary to the bit, or the same error.
void CheckScanAgrees(std::string_view bytes, const surfel::PlyReadOptions& limits,
                     const surfel::CloudFileSummary* whole, const surfel::Error* whole_error) {
    surfel::PlyPositionScan scan(limits);
    const std::size_t piece = 1 + bytes.size() % 97;
    for (std::size_t at = 0; at < bytes.size(); at += piece) scan.Append(bytes.substr(at, piece));
    try {
        const surfel::CloudFileSummary s = surfel::InspectCloudFile(bytes, "upload.ply", limits, &scan);
        if (!whole || s.points != whole->points || s.attributes != whole->attributes || s.format != whole->format)
            __builtin_trap();
        if (std::memcmp(&s.bounds, &whole->bounds, sizeof(s.bounds)) != 0) __builtin_trap();
    } catch (const surfel::Error& e) {
        if (!whole_error || e.code() != whole_error->code() || std::string_view(e.what()) != whole_error->what())
            __builtin_trap();
    }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const std::string_view bytes(reinterpret_cast<const char*>(data), size);
    surfel::PlyReadOptions limits;  // tighter than the server's, so that inputs stay fast
    limits.max_points = 100'000;
    limits.max_faces = 100'000;
    limits.max_elements = 1'000'000;
    try {
        const surfel::CloudFileSummary s = surfel::InspectCloudFile(bytes, "upload.ply", limits);
        CheckScanAgrees(bytes, limits, &s, nullptr);
        if (s.points == 0 || s.points > limits.max_points) __builtin_trap();
        if (!s.bounds.min.allFinite() || !s.bounds.max.allFinite()) __builtin_trap();
        if ((s.bounds.min.array() > s.bounds.max.array()).any()) __builtin_trap();
        if (surfel::HasPlyMagic(bytes) != s.format.starts_with("ply-")) __builtin_trap();
        const surfel::PointCloud cloud = surfel::ParsePointCloud(bytes, "upload.ply", limits);
        if (cloud.size() != s.points || cloud.AttributeNames() != s.attributes) __builtin_trap();
        for (const auto& p : cloud.positions)
            if ((p.array() < s.bounds.min.array()).any() || (p.array() > s.bounds.max.array()).any()) __builtin_trap();
    } catch (const surfel::Error& e) {
        CheckScanAgrees(bytes, limits, nullptr, &e);
    }
    return 0;
}
