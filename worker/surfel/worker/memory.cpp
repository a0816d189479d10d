#include "surfel/worker/memory.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <sstream>

#include "surfel/base/error.h"
#include "surfel/worker/job_kind.h"

namespace surfel::worker {

CloudFacts FactsOf(const v1::Cloud& cloud) {
    CloudFacts f;
    f.points = cloud.points();
    f.attributes.assign(cloud.attributes().begin(), cloud.attributes().end());
    f.file_bytes = cloud.size_bytes();
    f.extent = (FromProto(cloud.bounds_max()) - FromProto(cloud.bounds_min())).cwiseMax(0.0);
    return f;
}

CloudFacts FactsOf(const PointCloud& cloud, std::uint64_t file_bytes) {
    CloudFacts f;
    f.points = cloud.size();
    f.attributes = cloud.AttributeNames();
    f.file_bytes = file_bytes;
    f.extent = cloud.Bounds().Extent().cast<double>();
    return f;
}

std::uint64_t PointBytes(const std::vector<std::string>& attributes) {
    std::uint64_t b = 12;  // positions (Vec3f)
    for (const std::string& a : attributes) {
        if (a == "normals") b += 12;
        else if (a.rfind("colors", 0) == 0) b += 16;  // std::array<float, 4>
        else if (a == "radius") b += 4;
        else b += 8;  // ExtraAttribute::values, double
    }
    return b;
}

std::uint64_t CloudBytes(const CloudFacts& facts) { return facts.points * PointBytes(facts.attributes); }

std::uint64_t LoadBytes(const CloudFacts& facts) { return CloudBytes(facts) + facts.file_bytes; }

std::uint64_t PointsAtSpacing(const Vec3d& extent, double spacing) {
    const double area = 2.0 * (extent.x() * extent.y() + extent.y() * extent.z() + extent.z() * extent.x());
    if (!(spacing > 0) || !std::isfinite(area)) return 1;
    const double n = area / (0.8660254037844386 * spacing * spacing);
    return n >= 1e15 ? std::uint64_t(1e15) : std::max<std::uint64_t>(1, std::uint64_t(n));
}

std::uint64_t EstimateJobMemory(const v1::JobSpec& spec, std::span<const CloudFacts> inputs) {
    const JobKind& kind = KindOf(spec);
    SURFEL_CHECK(inputs.size() == kind.InputCount(spec), kind.Name() << ": " << inputs.size() << " inputs");
    return kind.EstimateMemory(spec, inputs);
}

namespace {

/// A number from a one-line file ("max" and unreadable files give 0).
std::uint64_t ReadNumber(const std::string& path) {
    std::ifstream in(path);
    std::string s;
    if (!(in >> s) || s == "max") return 0;
    try {
        return std::stoull(s);
    } catch (const std::exception&) {
        return 0;
    }
}

/// This process's cgroup v2 directory, "" when there is none.
std::string CgroupDir() {
    std::ifstream in("/proc/self/cgroup");
    for (std::string line; std::getline(in, line);)
        if (line.rfind("0::", 0) == 0) return "/sys/fs/cgroup" + line.substr(3);
    return "";
}

}  // namespace

std::uint64_t AvailableMemory() {
    std::uint64_t available = 0;
    std::ifstream in("/proc/meminfo");
    for (std::string line; std::getline(in, line);) {
        unsigned long long kib = 0;
        if (std::sscanf(line.c_str(), "MemAvailable: %llu kB", &kib) == 1) {
            available = kib * 1024;
            break;
        }
    }
    const std::string cg = CgroupDir();
    if (!cg.empty()) {
        const std::uint64_t max = ReadNumber(cg + "/memory.max");
        const std::uint64_t current = ReadNumber(cg + "/memory.current");
        if (max > 0) {
            const std::uint64_t left = max > current ? max - current : 0;
            available = available == 0 ? left : std::min(available, left);
        }
    }
    return available;
}

std::uint64_t DefaultMaxJobMemory() { return AvailableMemory() / 4 * 3; }

std::string MiB(std::uint64_t bytes) {
    char buf[64];
    std::snprintf(buf, sizeof buf, "%.1f MiB", double(bytes) / (1024.0 * 1024.0));
    return buf;
}

void CheckJobMemory(const v1::JobSpec& spec, std::uint64_t estimate, std::uint64_t limit,
                    const std::string& limit_name, std::uint64_t in_use) {
    if (limit == 0) return;
    const std::string kind(KindOf(spec).Name());
    if (estimate > limit)
        throw Error(ErrorCode::kResourceExhausted, kind + ": job needs an estimated " + MiB(estimate) +
                                                       ", above " + limit_name + " " + MiB(limit));
    const std::uint64_t left = limit > in_use ? limit - in_use : 0;
    if (estimate > left)
        throw Error(ErrorCode::kResourceExhausted,
                    kind + ": job needs an estimated " + MiB(estimate) + ", above the " + MiB(left) +
                        " that running jobs leave of " + limit_name + " " + MiB(limit) + "; retry later");
}

void CheckOutputPoints(const v1::JobSpec& spec, std::uint64_t max_points) {
    if (max_points == 0 || !spec.has_resample() || spec.resample().target() <= max_points) return;
    throw Error(ErrorCode::kResourceExhausted, "resample.target: " + std::to_string(spec.resample().target()) +
                                                   " points exceed the server's --max-points " +
                                                   std::to_string(max_points));
}

}  // namespace surfel::worker
