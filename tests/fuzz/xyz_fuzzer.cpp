// Fuzzes the XYZ reader and writer: any input must either parse into a consistent cloud of
// finite values or throw surfel::Error; what was read must write and read back bit for bit
// (shortest round-trip decimals), and the format table must pick XYZ for it.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "surfel/base/error.h"
#include "surfel/io/cloud_io.h"
#include "surfel/io/ply.h"
#include "surfel/io/xyz.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const std::string_view bytes(reinterpret_cast<const char*>(data), size);
    try {
        const surfel::PointCloud cloud = surfel::ParseXyz(bytes, "fuzz.xyz", 1'000'000);
        cloud.CheckConsistent();
        for (std::size_t i = 0; i < cloud.size(); ++i) {
            if (!cloud.positions[i].allFinite()) __builtin_trap();
            if (cloud.has_normals() && !cloud.normals[i].allFinite()) __builtin_trap();
        }
        const surfel::PointCloud again = surfel::ParseXyz(surfel::FormatXyz(cloud), "again.xyz");
        if (again.positions != cloud.positions || again.normals != cloud.normals) __builtin_trap();
        // Without the PLY magic the table reads the same bytes as XYZ, to the same cloud.
        if (!surfel::HasPlyMagic(bytes)) {
            if (surfel::SniffCloudFormat(bytes) != "xyz") __builtin_trap();
            if (surfel::ParsePointCloud(bytes, "fuzz.xyz").positions != cloud.positions) __builtin_trap();
        }
    } catch (const surfel::Error&) {
    }
    return 0;
}
