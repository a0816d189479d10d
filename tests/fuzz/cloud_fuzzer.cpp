// Fuzzes the upload path's check of a file (InspectCloudFile, which UploadSession::Finish runs
// before it stores a cloud): format sniffing, the PLY and XYZ readers under the server's point
// limit, and the summary the service records. Any input is refused with surfel::Error or gives a
// summary that agrees with the cloud it describes: at least one point, finite bounds that hold
// every point, and the format that ParsePointCloud chose.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "surfel/base/error.h"
#include "surfel/io/cloud_io.h"
#include "surfel/io/ply.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const std::string_view bytes(reinterpret_cast<const char*>(data), size);
    surfel::PlyReadOptions limits;  // tighter than the server's, so that inputs stay fast
    limits.max_points = 100'000;
    limits.max_faces = 100'000;
    limits.max_elements = 1'000'000;
    try {
        const surfel::CloudFileSummary s = surfel::InspectCloudFile(bytes, "upload.ply", limits);
        if (s.points == 0 || s.points > limits.max_points) __builtin_trap();
        if (!s.bounds.min.allFinite() || !s.bounds.max.allFinite()) __builtin_trap();
        if ((s.bounds.min.array() > s.bounds.max.array()).any()) __builtin_trap();
        if (surfel::HasPlyMagic(bytes) != s.format.starts_with("ply-")) __builtin_trap();
        const surfel::PointCloud cloud = surfel::ParsePointCloud(bytes, "upload.ply", limits);
        if (cloud.size() != s.points || cloud.AttributeNames() != s.attributes) __builtin_trap();
        for (const auto& p : cloud.positions)
            if ((p.array() < s.bounds.min.array()).any() || (p.array() > s.bounds.max.array()).any()) __builtin_trap();
    } catch (const surfel::Error&) {
    }
    return 0;
}
