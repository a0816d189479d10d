#pragma once
/// \file
/// Shared pieces of the `surfel` command-line tool: the command registry, reports, exit codes.

#include <CLI/CLI.hpp>
#include <cctype>
#include <functional>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "surfel/base/error.h"
#include "surfel/base/point_cloud.h"
#include "surfel/base/progress.h"

namespace surfel::cli {

/// Exit codes of every subcommand (documented in `surfel --help` and the README).
inline constexpr int kExitOk = 0;
inline constexpr int kExitFailure = 1;
inline constexpr int kExitUsage = 2;

/// A usage mistake found after parsing (a value that is valid syntax but not meaningful): exit 2.
struct UsageError : std::runtime_error {
    using std::runtime_error::runtime_error;
};

/// Runs `fn` (which checks a flag's value, e.g. a file extension) and turns an
/// Error(kInvalidArgument) from it into a UsageError naming `flag`: exit 2, not 1.
template <typename Fn>
auto UsageOnBadValue(const std::string& flag, Fn&& fn) -> decltype(fn()) {
    try {
        return fn();
    } catch (const Error& e) {
        if (e.code() != ErrorCode::kInvalidArgument) throw;
        throw UsageError(flag + ": " + e.what());
    }
}

/// The proto enum value a flag's name stands for: "reverse-difference" -> REVERSE_DIFFERENCE, by
/// the enum's generated `Parse` (e.g. v1::SimplifyJob::Method_Parse). UsageError naming the flag
/// when there is none.
template <typename Enum>
Enum ParseProtoEnum(const std::string& flag, const std::string& name, bool (*parse)(const std::string&, Enum*)) {
    std::string upper = name;
    for (char& c : upper) c = c == '-' ? '_' : static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
    Enum value{};
    if (!parse(upper, &value)) throw UsageError(flag + ": unknown value '" + name + "'");
    return value;
}

/// Options every job subcommand shares.
struct CommonFlags {
    bool json = false;   ///< Print the report as one JSON object on stdout.
    bool quiet = false;  ///< No progress on stderr.
};

/// Adds --json and --quiet to a job subcommand.
void AddCommonFlags(CLI::App* sub, CommonFlags* flags);

/// Prints a report: one JSON object when flags.json, else "key: value" lines.
void PrintReport(const nlohmann::json& report, const CommonFlags& flags);

/// A progress hook that draws a one-line bar on stderr when it is a terminal (and not quiet).
ProgressFn MakeProgressBar(const std::string& label, const CommonFlags& flags);

/// Parses `count` comma-separated numbers ("1,0,-2.5") given to `flag`; UsageError naming the
/// flag otherwise.
std::vector<double> ParseNumbers(const std::string& text, const std::string& flag, std::size_t count);
/// Three comma-separated numbers x,y,z.
Vec3d ParseVec3(const std::string& text, const std::string& flag);

/// JSON for a bounding box: {"min": [..], "max": [..], "diagonal": d}.
nlohmann::json BoundsJson(const BoundingBox& box);

/// Reads a point-cloud file named on the command line.
PointCloud LoadCloud(const std::string& path);
/// Writes a point-cloud file (PLY or XYZ by extension; binary PLY unless ascii).
void SaveCloud(const PointCloud& cloud, const std::string& path, bool ascii = false);

/// Each module of the CLI registers its subcommands here.
void RegisterIoCommands(CLI::App& app);
void RegisterSurfaceCommands(CLI::App& app);
void RegisterRenderCommands(CLI::App& app);
void RegisterSimplifyCommands(CLI::App& app);
void RegisterResampleCommands(CLI::App& app);
void RegisterBooleanCommands(CLI::App& app);
void RegisterServiceCommands(CLI::App& app);

}  // namespace surfel::cli
