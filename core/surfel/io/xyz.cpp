#include "surfel/io/xyz.h"

#include <charconv>
#include <cmath>

#include "surfel/base/error.h"
#include "surfel/io/text_internal.h"

namespace surfel {

using io_internal::AppendFloatAscii;
using io_internal::Fail;
using io_internal::Quote;
using io_internal::Tokenize;

PointCloud ParseXyz(std::string_view data, std::string_view file, std::uint64_t max_points) {
    if (io_internal::IsBlank(data))
        Fail(file, data.empty() ? "empty file (0 bytes): not a point cloud"
                                : "only whitespace (" + std::to_string(data.size()) + " bytes): not a point cloud");
    PointCloud cloud;
    std::size_t pos = 0;
    int line_no = 0;
    int columns = 0;
    while (pos < data.size()) {
        std::size_t end = data.find('\n', pos);
        if (end == std::string_view::npos) end = data.size();
        std::string_view line = data.substr(pos, end - pos);
        pos = end + 1;
        ++line_no;
        if (auto hash = line.find('#'); hash != std::string_view::npos) line = line.substr(0, hash);
        auto tok = Tokenize(line);
        if (tok.empty()) continue;
        const std::string where = "line " + std::to_string(line_no) + ": ";
        if (tok.size() != 3 && tok.size() != 6)
            Fail(file, where + "expected 3 values (x y z) or 6 (x y z nx ny nz), found " +
                           std::to_string(tok.size()));
        if (columns == 0) columns = static_cast<int>(tok.size());
        if (static_cast<int>(tok.size()) != columns)
            Fail(file, where + "has " + std::to_string(tok.size()) + " values but earlier lines have " +
                           std::to_string(columns));
        if (cloud.size() >= max_points)
            throw Error(ErrorCode::kResourceExhausted,
                        std::string(file) + ": " + where + "more than " + std::to_string(max_points) + " points");
        float v[6];
        static const char* kNames[] = {"x", "y", "z", "nx", "ny", "nz"};
        for (std::size_t k = 0; k < tok.size(); ++k) {
            auto [p, ec] = std::from_chars(tok[k].data(), tok[k].data() + tok[k].size(), v[k]);
            if (ec != std::errc() || p != tok[k].data() + tok[k].size())
                Fail(file, where + "field '" + kNames[k] + "': " + Quote(tok[k]) + " is not a number");
            if (!std::isfinite(v[k])) Fail(file, where + "field '" + kNames[k] + "': value is not finite");
        }
        cloud.positions.emplace_back(v[0], v[1], v[2]);
        if (columns == 6) cloud.normals.emplace_back(v[3], v[4], v[5]);
    }
    return cloud;
}

std::string FormatXyz(const PointCloud& cloud) {
    // XYZ has no header: an empty cloud is one comment line, which reads back as 0 points
    // (an empty file does not).
    if (cloud.empty()) return "# 0 points\n";
    std::string out;
    out.reserve(cloud.size() * 40);
    for (std::size_t i = 0; i < cloud.size(); ++i) {
        for (int k = 0; k < 3; ++k) {
            if (k) out += ' ';
            AppendFloatAscii(out, cloud.positions[i][k]);
        }
        if (cloud.has_normals())
            for (int k = 0; k < 3; ++k) { out += ' '; AppendFloatAscii(out, cloud.normals[i][k]); }
        out += '\n';
    }
    return out;
}

}  // namespace surfel
