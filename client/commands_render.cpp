// surfel render
#include <sstream>

#include "cli_common.h"
#include "job_exec.h"
#include "placement.h"
#include "surfel/boolean/boolean.h"
#include "surfel/worker/job_kind.h"
#include "surfel/base/error.h"
#include "surfel/io/image.h"
#include "surfel/render/renderer.h"

namespace surfel::cli {
namespace {

Light ParseLight(const std::string& text) {
    const auto colon = text.find(':');
    if (colon == std::string::npos)
        throw UsageError("--light: '" + text + "' must be dir:x,y,z[:intensity] or point:x,y,z[:intensity]");
    const std::string kind = text.substr(0, colon);
    std::string rest = text.substr(colon + 1);
    Light L;
    if (kind == "dir") L.kind = Light::Kind::kDirectional;
    else if (kind == "point") L.kind = Light::Kind::kPoint;
    else throw UsageError("--light: unknown kind '" + kind + "' (dir or point)");
    if (const auto c2 = rest.find(':'); c2 != std::string::npos) {
        try {
            L.intensity = std::stod(rest.substr(c2 + 1));
        } catch (const std::exception&) {
            throw UsageError("--light: bad intensity in '" + text + "'");
        }
        rest = rest.substr(0, c2);
    }
    L.vector = ParseVec3(rest, "--light");
    if (L.kind == Light::Kind::kDirectional && L.vector.norm() == 0) throw UsageError("--light: direction must not be zero");
    return L;
}

// Defaults come from a default-constructed RenderOptions, ranges from core's named limits.
struct RenderArgs {
    RenderOptions defaults;
    std::string input, output, png;
    int width = defaults.camera.width, height = defaults.camera.height;
    std::string eye, target, up, view = "0,0,1", background = "0,0,0";
    double fovy = defaults.camera.fovy_deg;
    std::vector<std::string> lights;
    bool no_shadows = !defaults.shadows, half = false;
    int spp = defaults.samples_per_pixel, degree = defaults.surface.degree,
        max_iterations = defaults.surface.max_iterations;
    float h = defaults.surface.h, precision = defaults.surface.precision;
    std::string csg, with;  // --csg OP --with B
    PlacementFlags place;
    bool no_creases = !defaults.creases;
    std::string bandwidth = defaults.surface.bandwidth == AaBandwidth::kAdaptive ? "adaptive" : "fixed";
    std::string weights = defaults.surface.normal_sigma > 0 ? "normal" : "plain";
    std::string quality = "full";
    bool bandwidth_given = false, weights_given = false;  // else the job leaves them to --quality
    CommonFlags flags;
    JobFlags job;
};

void RunRender(RenderArgs& a) {
    // A bad extension is a usage error, found before any work.
    const ImageFormat format = UsageOnBadValue("--output", [&] { return ImageFormatFromPath(a.output); });
    if (!a.png.empty()) UsageOnBadValue("--png", [&] { return ImageFormatFromPath(a.png); });
    // The preview is encoded here even with --server: a missing image plugin fails before any
    // work (in-process, the render job checks it before rendering).
    if (!a.png.empty()) LoadImageCodec();
    v1::JobSpec spec;
    v1::RenderJob& r = *spec.mutable_render();
    r.set_width(a.width);
    r.set_height(a.height);
    *r.mutable_view() = worker::ToProto(ParseVec3(a.view, "--view"));
    v1::Camera& cam = *r.mutable_camera();
    cam.set_fovy_deg(a.fovy);
    if (!a.eye.empty()) *cam.mutable_eye() = worker::ToProto(ParseVec3(a.eye, "--eye"));
    if (!a.target.empty()) *cam.mutable_target() = worker::ToProto(ParseVec3(a.target, "--target"));
    if (!a.up.empty()) *cam.mutable_up() = worker::ToProto(ParseVec3(a.up, "--up"));
    for (const auto& text : a.lights) {
        const Light L = ParseLight(text);
        v1::Light& l = *r.add_lights();
        l.set_kind(L.kind == Light::Kind::kPoint ? v1::Light::POINT : v1::Light::DIRECTIONAL);
        *l.mutable_vector() = worker::ToProto(L.vector);
        l.set_intensity(L.intensity);
    }
    r.set_no_shadows(a.no_shadows);
    r.set_samples_per_pixel(a.spp);
    *r.mutable_background() = worker::ToProto(ParseVec3(a.background, "--background"));
    r.set_h(a.h);
    r.set_precision(a.precision);
    r.set_degree(static_cast<v1::RenderJob::Degree>(a.degree + 1));  // --degree 0..2
    r.set_max_iterations(a.max_iterations);
    r.set_quality(a.quality == "preview" ? v1::RenderJob::PREVIEW : v1::RenderJob::FULL);
    if (a.bandwidth_given) r.set_bandwidth(a.bandwidth == "adaptive" ? v1::RenderJob::ADAPTIVE : v1::RenderJob::FIXED);
    if (a.weights_given) r.set_weights(a.weights == "normal" ? v1::RenderJob::NORMAL_AWARE : v1::RenderJob::PLAIN);
    r.set_format(format == ImageFormat::kPng ? v1::RenderJob::PNG
                 : a.half                    ? v1::RenderJob::EXR_HALF
                                             : v1::RenderJob::EXR);
    r.set_no_creases(a.no_creases);
    std::vector<std::string> inputs{a.input};
    if (!a.csg.empty()) {
        if (a.with.empty()) throw UsageError("--csg: needs --with B (the second solid)");
        r.set_csg_op(ParseProtoEnum("--csg", a.csg, &v1::BooleanJob::Op_Parse));
        *r.mutable_csg_transform_b() = PlacementToProto(a.place);
        inputs.push_back(a.with);
    } else if (!a.with.empty()) {
        throw UsageError("--with: needs --csg OP (union, intersection, difference, reverse-difference)");
    } else if (!a.place.translate.empty() || !a.place.rotate.empty() || a.place.scale != 1.0) {
        throw UsageError("--translate/--rotate/--scale: place the --with solid of a --csg render");
    }
    nlohmann::json report = ExecuteJob(spec, inputs, a.output, a.flags, a.job);
    if (!a.png.empty() && report.contains("output")) {  // the preview, from the written image
        WriteImage(ReadImage(a.output), a.png);
        report["png"] = a.png;
    }
    PrintReport(report, a.flags);
}

}  // namespace

void RegisterRenderCommands(CLI::App& app) {
    auto a = std::make_shared<RenderArgs>();
    auto* sub = app.add_subcommand("render", "Ray-trace the cloud's point-set surface (Adamson & Alexa 2003) to EXR/PNG");
    sub->add_option("input", a->input, "PLY or XYZ file")->required()->check(CLI::ExistingFile);
    sub->add_option("-o,--output", a->output, "EXR (R,G,B,A,Z,N.X,N.Y,N.Z) or PNG file")->required();
    sub->add_option("--png", a->png, "Also write an 8-bit sRGB PNG preview");
    sub->add_option("--width", a->width, "Image width in pixels")->capture_default_str()->check(CLI::Range(1, kMaxImageSide));
    sub->add_option("--height", a->height, "Image height in pixels")->capture_default_str()->check(CLI::Range(1, kMaxImageSide));
    sub->add_option("--eye", a->eye, "Camera position x,y,z (default: frames the bounding box)");
    sub->add_option("--target", a->target, "Point looked at x,y,z (default: the bounding box centre)");
    sub->add_option("--up", a->up, "Up direction x,y,z")->default_str("0,1,0");
    sub->add_option("--view", a->view, "Direction from the target to the default eye")->default_val("0,0,1");
    sub->add_option("--fovy", a->fovy, "Vertical field of view in degrees")->capture_default_str()->check(CLI::Range(kMinFovyDeg, kMaxFovyDeg));
    sub->add_option("--light", a->lights, "dir:x,y,z[:intensity] (direction the light travels) or point:x,y,z[:intensity]; repeatable");
    sub->add_flag("--no-shadows", a->no_shadows, "Skip shadow rays");
    sub->add_option("--spp", a->spp, "Stratified samples per pixel")->capture_default_str()->check(CLI::Range(1, kMaxSamplesPerPixel));
    sub->add_option("--background", a->background, "Background colour r,g,b (linear)")->default_val("0,0,0");
    sub->add_option("--h", a->h, "Gaussian scale h (0 = 1.4 x median sample spacing; with --bandwidth adaptive, the scale where the spacing is the median)")->capture_default_str()->check(CLI::NonNegativeNumber);
    sub->add_option("--precision", a->precision, "Convergence |c| < precision (0 = 1e-3 h; 0.03 h with --quality preview)")->capture_default_str()->check(CLI::NonNegativeNumber);
    sub->add_option("--degree", a->degree, "Local polynomial degree (0, 1, 2)")->capture_default_str()->check(CLI::Range(0, 2));
    sub->add_option("--max-iterations", a->max_iterations, "Iterations per ball")->capture_default_str()->check(CLI::Range(1, kMaxSurfaceIterations));
    sub->add_option("--bandwidth", a->bandwidth, "Gaussian scale: fixed (one h) or adaptive (a smooth h per point from the sampling density); overrides --quality's choice")->capture_default_str()->check(CLI::IsMember({"fixed", "adaptive"}))
        ->each([a](const std::string&) { a->bandwidth_given = true; });
    sub->add_option("--weights", a->weights, "Neighbour weights: plain (the paper's) or normal (also by normal agreement: thin parts stay two sheets; estimates normals when the cloud has none); overrides --quality's choice")->capture_default_str()->check(CLI::IsMember({"plain", "normal"}))
        ->each([a](const std::string&) { a->weights_given = true; });
    sub->add_option("--quality", a->quality,
                    "full: the notes' method (normal-aware weights, adaptive bandwidth, |c| < 1e-3 h, both shadow stages). "
                    "preview: about twice as fast: the paper's surface (plain weights, fixed h, so no normal estimation), "
                    "|c| < 0.03 h, shadow rays only through balls they pass near the centre; "
                    "thin parts, fine detail (hits stop up to ~0.2 h earlier) and shadow outlines differ (figures: bench/README.md, session 18). "
                    "--weights, --bandwidth and --precision override its choices")
        ->capture_default_str()->check(CLI::IsMember({"full", "preview"}));
    sub->add_flag("--half", a->half, "Write EXR channels as 16-bit half floats");
    std::vector<std::string> ops;
    for (const BooleanOp op : kBooleanOps) ops.emplace_back(BooleanOpName(op));
    sub->add_option("--csg", a->csg, "Ray-trace the boolean of INPUT and --with directly (notes 3.1): union | intersection | difference (INPUT - B) | reverse-difference")
        ->check(CLI::IsMember(ops));
    sub->add_option("--with", a->with, "The second solid B of --csg (PLY or XYZ), placed by --translate/--rotate/--scale")
        ->check(CLI::ExistingFile);
    AddPlacementFlags(sub, &a->place);
    sub->add_flag("--no-creases", a->no_creases, "Render a boolean result's surfel pairs as one smooth surface");
    AddCommonFlags(sub, &a->flags);
    AddJobFlags(sub, &a->job);
    sub->footer("Runs in-process, or on a server with --server host:port (the cloud is uploaded once).\nExample:\n  surfel render bunny.ply -o bunny.exr --png bunny.png --width 400 --height 200 \\\n"
                "      --light dir:-1,-1,-1 --spp 4 --json\n"
                "  surfel render sphere.ply --csg difference --with box.ply --translate 0,0,1.4 -o carved.exr\n"
                "A boolean result (surfel boolean) renders with sharp creases at its surfel pairs.");
    sub->callback([a] { RunRender(*a); });
}

}  // namespace surfel::cli
