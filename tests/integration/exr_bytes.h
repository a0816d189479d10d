#pragma once
// Comparing rendered EXR files byte for byte in the integration tests.

#include <cstddef>
#include <cstdint>
#include <string>

namespace surfel::test {

/// The bytes with the value of an EXR header's `capDate` attribute blanked (same length): the
/// OpenImageIO plugin and the EXR plugin both stamp the local time of the encode, to the second,
/// so two renders of one spec differ there whenever their encodes straddle a second, and nowhere
/// else. Files that are not EXR come back unchanged.
inline std::string WithoutCaptureDate(std::string bytes) {
    static const std::string kKey("capDate\0string\0", 15);
    if (bytes.rfind("\x76\x2f\x31\x01", 0) != 0) return bytes;  // not an EXR
    const std::size_t at = bytes.find(kKey);
    if (at == std::string::npos || at + kKey.size() + 4 > bytes.size()) return bytes;
    const std::size_t value = at + kKey.size() + 4;
    std::uint32_t size = 0;  // little-endian int32 before the value
    for (int i = 3; i >= 0; --i) size = size << 8 | static_cast<unsigned char>(bytes[at + kKey.size() + i]);
    if (value + size <= bytes.size()) bytes.replace(value, size, std::string(size, '0'));
    return bytes;
}

}  // namespace surfel::test
