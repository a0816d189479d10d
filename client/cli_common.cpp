#include "cli_common.h"

#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <iostream>
#include <sstream>

#include "surfel/io/cloud_io.h"

namespace surfel::cli {

void AddCommonFlags(CLI::App* sub, CommonFlags* flags) {
    sub->add_flag("--json", flags->json, "Print the report as one JSON object on stdout");
    sub->add_flag("-q,--quiet", flags->quiet, "No progress output on stderr");
}

void PrintReport(const nlohmann::json& report, const CommonFlags& flags) {
    if (flags.json) {
        std::cout << report.dump() << std::endl;
        return;
    }
    for (const auto& [key, value] : report.items()) {
        if (value.is_string()) std::cout << key << ": " << value.get<std::string>() << "\n";
        else std::cout << key << ": " << value.dump() << "\n";
    }
    std::cout.flush();
}

ProgressFn MakeProgressBar(const std::string& label, const CommonFlags& flags) {
    if (flags.quiet || flags.json || !isatty(STDERR_FILENO)) return {};
    return [label](double f) {
        const int width = 30, filled = static_cast<int>(std::lround(f * width));
        std::fprintf(stderr, "\r%-12s [%s%s] %3d%%", label.c_str(), std::string(filled, '#').c_str(),
                     std::string(width - filled, ' ').c_str(), static_cast<int>(std::lround(f * 100)));
        if (f >= 1.0) std::fprintf(stderr, "\n");
        std::fflush(stderr);
        return true;
    };
}

std::vector<double> ParseNumbers(const std::string& text, const std::string& flag, std::size_t count) {
    const std::string expected = std::to_string(count) + " comma-separated numbers";
    std::stringstream ss(text);
    std::string part;
    std::vector<double> v;
    while (std::getline(ss, part, ',')) {
        try {
            std::size_t used = 0;
            v.push_back(std::stod(part, &used));
            if (used != part.size()) throw std::invalid_argument(part);
        } catch (const std::exception&) {
            throw UsageError(flag + ": '" + text + "' is not " + expected);
        }
    }
    if (v.size() != count) throw UsageError(flag + ": '" + text + "' is not " + expected);
    return v;
}

Vec3d ParseVec3(const std::string& text, const std::string& flag) {
    const std::vector<double> v = ParseNumbers(text, flag, 3);
    return {v[0], v[1], v[2]};
}

nlohmann::json BoundsJson(const BoundingBox& box) {
    if (box.empty()) return nullptr;
    return {{"min", {box.min.x(), box.min.y(), box.min.z()}},
            {"max", {box.max.x(), box.max.y(), box.max.z()}},
            {"diagonal", box.Diagonal()}};
}

PointCloud LoadCloud(const std::string& path) { return ReadPointCloud(path); }

void SaveCloud(const PointCloud& cloud, const std::string& path, bool ascii) {
    WritePointCloud(cloud, path, ascii);
}

}  // namespace surfel::cli
