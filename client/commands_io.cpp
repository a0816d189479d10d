// surfel info | sample | convert
#include <iostream>

#include "cli_common.h"
#include "surfel/base/shapes.h"
#include "surfel/io/file_bytes.h"
#include "surfel/io/ply.h"
#include "surfel/io/xyz.h"

namespace surfel::cli {
namespace {

struct InfoArgs {
    std::string input;
    CommonFlags flags;
};

void RunInfo(const InfoArgs& a) {
    PlyHeaderInfo header;
    Stopwatch watch;
    const std::string bytes = ReadFileBytes(a.input);
    const bool is_ply = HasPlyMagic(bytes);
    PointCloud cloud = is_ply ? ParsePly(bytes, a.input, {}, &header) : ParseXyz(bytes, a.input);
    nlohmann::json r;
    r["file"] = a.input;
    r["format"] = is_ply ? std::string("ply ") + PlyFormatName(header.format) : std::string("xyz");
    r["points"] = cloud.size();
    r["faces"] = is_ply ? header.face_count : 0;
    r["triangles"] = cloud.triangles.size();
    r["attributes"] = cloud.AttributeNames();
    r["bounds"] = BoundsJson(cloud.Bounds());
    if (is_ply) {
        nlohmann::json elements = nlohmann::json::array();
        for (const auto& e : header.elements)
            elements.push_back({{"name", e.name}, {"count", e.count}, {"properties", e.properties}});
        r["elements"] = elements;
        if (!header.comments.empty()) r["comments"] = header.comments;
    }
    r["time_ms"] = watch.ElapsedMs();
    PrintReport(r, a.flags);
}

struct SampleArgs {
    std::string shape;
    std::size_t points = 10000;
    double noise = 0.0;
    double scale = 1.0;
    bool normals = false;
    std::uint64_t seed = 1;
    std::string output;
    bool ascii = false;
    CommonFlags flags;
};

void RunSample(const SampleArgs& a) {
    ShapeOptions opt;
    opt.points = a.points;
    opt.noise = a.noise;
    opt.scale = a.scale;
    opt.normals = a.normals;
    opt.seed = a.seed;
    Stopwatch watch;
    PointCloud cloud = SampleShape(*ParseShape(a.shape), opt);
    const double ms = watch.ElapsedMs();
    SaveCloud(cloud, a.output, a.ascii);
    PrintReport({{"shape", a.shape}, {"points", cloud.size()}, {"output", a.output},
                 {"bounds", BoundsJson(cloud.Bounds())}, {"time_ms", ms}},
                a.flags);
}

struct ConvertArgs {
    std::string input, output;
    bool ascii = false;
    CommonFlags flags;
};

void RunConvert(const ConvertArgs& a) {
    PointCloud cloud = LoadCloud(a.input);
    SaveCloud(cloud, a.output, a.ascii);
    PrintReport({{"input", a.input}, {"output", a.output}, {"points", cloud.size()},
                 {"triangles", cloud.triangles.size()}, {"attributes", cloud.AttributeNames()}, {"time_ms", 0.0}},
                a.flags);
}

}  // namespace

void RegisterIoCommands(CLI::App& app) {
    {
        auto args = std::make_shared<InfoArgs>();
        auto* sub = app.add_subcommand("info", "Describe a point-cloud file: points, faces, attributes, bounds, format");
        sub->add_option("input", args->input, "PLY or XYZ file")->required()->check(CLI::ExistingFile);
        AddCommonFlags(sub, &args->flags);
        sub->footer("Example:\n  surfel info bunny.ply --json");
        sub->callback([args] { RunInfo(*args); });
    }
    {
        auto args = std::make_shared<SampleArgs>();
        std::vector<std::string> names;
        for (Shape s : AllShapes()) names.emplace_back(ShapeName(s));
        auto* sub = app.add_subcommand("sample", "Sample an analytic shape (uniform by area) into a point cloud");
        sub->add_option("shape", args->shape, "Shape to sample")->required()->check(CLI::IsMember(names));
        sub->add_option("-n,--points", args->points, "Number of points")->default_val(10000)->check(CLI::Range(1ul, 500'000'000ul));
        sub->add_option("--noise", args->noise, "Std. deviation of Gaussian noise along the normal (shape units; the shapes have unit size)")
            ->default_val(0.0)->check(CLI::NonNegativeNumber);
        sub->add_option("--scale", args->scale, "Size: sphere/cylinder radius, torus major radius, half side of plane and box")
            ->default_val(1.0)->check(CLI::PositiveNumber);
        sub->add_flag("--normals", args->normals, "Attach the exact outward unit normals");
        sub->add_option("--seed", args->seed, "Random seed (same seed, same cloud)")->default_val(1);
        sub->add_option("-o,--output", args->output, "Output file (.ply or .xyz)")->required();
        sub->add_flag("--ascii", args->ascii, "Write ASCII PLY instead of binary");
        AddCommonFlags(sub, &args->flags);
        sub->footer("Example:\n  surfel sample torus -n 50000 --noise 0.002 --normals -o torus.ply");
        sub->callback([args] { RunSample(*args); });
    }
    {
        auto args = std::make_shared<ConvertArgs>();
        auto* sub = app.add_subcommand("convert", "Convert between PLY (binary or ASCII) and XYZ, keeping every attribute PLY can hold");
        sub->add_option("input", args->input, "PLY or XYZ file")->required()->check(CLI::ExistingFile);
        sub->add_option("-o,--output", args->output, "Output file (.ply or .xyz)")->required();
        sub->add_flag("--ascii", args->ascii, "Write ASCII PLY instead of binary little endian");
        AddCommonFlags(sub, &args->flags);
        sub->footer("Example:\n  surfel convert scan.xyz -o scan.ply");
        sub->callback([args] { RunConvert(*args); });
    }
}

}  // namespace surfel::cli
