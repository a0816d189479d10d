// Fuzzes the PLY and XYZ readers: any input must either parse into a consistent cloud or throw
// surfel::Error; never crash, leak, hang or allocate without bound.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "surfel/base/error.h"
#include "surfel/io/cloud_io.h"
#include "surfel/io/ply.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const std::string_view bytes(reinterpret_cast<const char*>(data), size);
    surfel::PlyReadOptions limits;
    limits.max_points = 1'000'000;
    limits.max_faces = 1'000'000;
    try {
        surfel::PointCloud cloud = surfel::ParsePointCloud(bytes, "fuzz.ply", limits);
        cloud.CheckConsistent();
        // What was read must write and read back.
        const std::string out = surfel::FormatPly(cloud);
        const surfel::PointCloud again = surfel::ParsePly(out, "again.ply");
        if (again.size() != cloud.size()) __builtin_trap();
    } catch (const surfel::Error&) {
    }
    return 0;
}
