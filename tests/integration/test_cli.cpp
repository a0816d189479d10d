// The `surfel` CLI as a user runs it: every subcommand with a good call, an unknown flag, a
// missing input file and a malformed one, each with its exit code (0 ok, 2 usage, 1 failure)
// and the words its message must contain.
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <cstdio>
#include <filesystem>
#include <regex>

#include "surfel/base/shapes.h"
#include "surfel/io/file_bytes.h"
#include "surfel/io/ply.h"

namespace surfel {
namespace {

namespace fs = std::filesystem;

struct CliCase {
    std::string name;     ///< test name: <subcommand>_<situation>
    std::string args;     ///< after `surfel`; {dir} is the test folder
    int exit_code;
    std::string message;  ///< must appear in stdout + stderr ("" = anything)
};

std::ostream& operator<<(std::ostream& os, const CliCase& c) { return os << c.name; }

// A PLY whose second vertex lacks its z (line 9 of the file).
constexpr const char* kMalformedPly =
    "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
    "end_header\n0 0 0\n1 1\n";

const CliCase kCases[] = {
    // One good call, an unknown flag, a missing file, a malformed file, per subcommand.
    {"render_ok", "render {dir}/sphere.ply -o {dir}/r.exr --width 24 --height 16 --json", 0, "\"points\":"},
    {"render_unknown_flag", "render {dir}/sphere.ply -o {dir}/r.exr --nope", 2, "--nope"},
    {"render_missing_file", "render {dir}/none.ply -o {dir}/r.exr", 2, "none.ply"},
    {"render_malformed_file", "render {dir}/bad.ply -o {dir}/r.exr", 1, "bad.ply"},
    {"render_bad_value", "render {dir}/sphere.ply -o {dir}/r.exr --width 0", 2, "--width"},
    {"render_bad_extension", "render {dir}/sphere.ply -o {dir}/r.tiff", 2, "r.tiff"},
    {"render_png_ok", "render {dir}/sphere.ply -o {dir}/r.png --width 24 --height 16 --json", 0, "\"output\":"},
    {"render_preview_ok", "render {dir}/sphere.ply -o {dir}/r2.exr --png {dir}/r2.png --width 24 --height 16 --json", 0,
     "\"png\":"},
    {"render_quality_preview_ok", "render {dir}/sphere.ply -o {dir}/q.exr --quality preview --width 24 --height 16 --json", 0,
     "\"quality\":\"preview\""},
    {"render_quality_default_full", "render {dir}/sphere.ply -o {dir}/q2.exr --width 24 --height 16 --json", 0,
     "\"quality\":\"full\""},
    {"render_quality_unknown", "render {dir}/sphere.ply -o {dir}/q.exr --quality draft", 2, "--quality"},
    {"render_csg_ok", "render {dir}/sphere.ply --csg difference --with {dir}/sphere.ply --translate 0.5,0,0 -o {dir}/c.exr --width 24 --height 16 --json", 0,
     "\"csg_op\":\"difference\""},
    {"render_csg_unknown_flag", "render {dir}/sphere.ply --csg union --with {dir}/sphere.ply -o {dir}/c.exr --nope", 2, "--nope"},
    {"render_csg_missing_file", "render {dir}/sphere.ply --csg union --with {dir}/none.ply -o {dir}/c.exr", 2, "none.ply"},
    {"render_csg_malformed_file", "render {dir}/sphere.ply --csg union --with {dir}/bad.ply -o {dir}/c.exr", 1, "bad.ply"},
    {"render_csg_unknown_op", "render {dir}/sphere.ply --csg xor --with {dir}/sphere.ply -o {dir}/c.exr", 2, "xor"},
    {"render_csg_without_with", "render {dir}/sphere.ply --csg union -o {dir}/c.exr", 2, "--with"},
    {"render_with_without_csg", "render {dir}/sphere.ply --with {dir}/sphere.ply -o {dir}/c.exr", 2, "--csg"},
    {"render_placement_without_csg", "render {dir}/sphere.ply --translate 1,0,0 -o {dir}/c.exr", 2, "--with"},
    {"render_csg_bad_scale", "render {dir}/sphere.ply --csg union --with {dir}/sphere.ply --scale 0 -o {dir}/c.exr", 2, "--scale"},
    {"simplify_ok", "simplify {dir}/sphere.ply -o {dir}/s.ply --target 100 --json", 0, "\"points\":100"},
    {"simplify_unknown_flag", "simplify {dir}/sphere.ply -o {dir}/s.ply --nope", 2, "--nope"},
    {"simplify_missing_file", "simplify {dir}/none.ply -o {dir}/s.ply --target 10", 2, "none.ply"},
    {"simplify_malformed_file", "simplify {dir}/bad.ply -o {dir}/s.ply --target 1", 1, "bad.ply"},
    {"simplify_bad_extension", "simplify {dir}/sphere.ply -o {dir}/s.obj --target 10", 2, "s.obj"},
    {"simplify_no_bound", "simplify {dir}/sphere.ply -o {dir}/s.ply --method voxel", 2,
     "simplify.target: is required for this method"},
    {"simplify_member_ok", "simplify {dir}/sphere.ply -o {dir}/s.ply --target 100 --representative member --json", 0,
     "\"representative\":\"member\""},
    {"simplify_member_unknown", "simplify {dir}/sphere.ply -o {dir}/s.ply --target 100 --representative medoid", 2,
     "--representative"},
    {"simplify_member_of_particles",
     "simplify {dir}/sphere.ply -o {dir}/s.ply --method particle --target 100 --representative member", 2,
     "simplify.representative: particle simulation places its own points"},
    {"simplify_target_too_big", "simplify {dir}/sphere.ply -o {dir}/s.ply --target 100000", 1, "100000"},
    {"resample_ok", "resample {dir}/sphere.ply -o {dir}/rs.ply --target 3000 --iterations 5 --json", 0, "\"points\":3000"},
    {"resample_unknown_flag", "resample {dir}/sphere.ply -o {dir}/rs.ply --target 10 --nope", 2, "--nope"},
    {"resample_missing_file", "resample {dir}/none.ply -o {dir}/rs.ply --target 10", 2, "none.ply"},
    {"resample_malformed_file", "resample {dir}/bad.ply -o {dir}/rs.ply --target 10", 1, "bad.ply"},
    {"resample_no_count", "resample {dir}/sphere.ply -o {dir}/rs.ply", 2, "--target N or --spacing S"},
    {"resample_keep_input_too_few", "resample {dir}/sphere.ply -o {dir}/rs.ply --target 100 --keep-input", 1,
     "resample.target: with keep_input must exceed"},
    {"resample_mls_ok", "resample {dir}/sphere.ply -o {dir}/rm.ply --method mls --json", 0, "\"mls_h\":"},
    {"resample_mls_with_count", "resample {dir}/sphere.ply -o {dir}/rm.ply --method mls --target 10", 2,
     "give neither --target nor --spacing"},
    {"boolean_ok", "boolean {dir}/sphere.ply {dir}/sphere.ply --op union --translate 0.5,0,0 -o {dir}/b.ply --json", 0,
     "\"curve_samples\":"},
    {"boolean_unknown_flag", "boolean {dir}/sphere.ply {dir}/sphere.ply --op union -o {dir}/b.ply --nope", 2, "--nope"},
    {"boolean_missing_file", "boolean {dir}/sphere.ply {dir}/none.ply --op union -o {dir}/b.ply", 2, "none.ply"},
    {"boolean_malformed_file", "boolean {dir}/bad.ply {dir}/sphere.ply --op union -o {dir}/b.ply", 1, "bad.ply"},
    {"boolean_unknown_op", "boolean {dir}/sphere.ply {dir}/sphere.ply --op xor -o {dir}/b.ply", 2, "xor"},
    {"boolean_bad_rotation", "boolean {dir}/sphere.ply {dir}/sphere.ply --op union --rotate 0,0,0,30 -o {dir}/b.ply", 2,
     "--rotate: the axis must not be zero"},
    {"boolean_xyz_output", "boolean {dir}/sphere.ply {dir}/sphere.ply --op union -o {dir}/b.xyz", 2, "PLY"},
    {"normals_ok", "normals {dir}/sphere.ply -o {dir}/n.ply --json", 0, "\"points\":"},
    {"normals_unknown_flag", "normals {dir}/sphere.ply -o {dir}/n.ply --nope", 2, "--nope"},
    {"normals_missing_file", "normals {dir}/none.ply -o {dir}/n.ply", 2, "none.ply"},
    {"normals_malformed_file", "normals {dir}/bad.ply -o {dir}/n.ply", 1, "bad.ply"},
    {"project_ok", "project {dir}/sphere.ply -o {dir}/p.ply --json", 0, "\"points\":"},
    {"project_unknown_flag", "project {dir}/sphere.ply -o {dir}/p.ply --nope", 2, "--nope"},
    {"project_missing_file", "project {dir}/none.ply -o {dir}/p.ply", 2, "none.ply"},
    {"project_malformed_file", "project {dir}/bad.ply -o {dir}/p.ply", 1, "bad.ply"},
    {"error_ok", "error {dir}/sphere.ply {dir}/sphere.ply --json", 0, "\"max\":"},
    {"error_unknown_flag", "error {dir}/sphere.ply {dir}/sphere.ply --nope", 2, "--nope"},
    {"error_missing_file", "error {dir}/sphere.ply {dir}/none.ply", 2, "none.ply"},
    {"error_malformed_file", "error {dir}/sphere.ply {dir}/bad.ply", 1, "bad.ply"},
    {"info_ok", "info {dir}/sphere.ply --json", 0, "\"points\":2000"},
    {"info_unknown_flag", "info {dir}/sphere.ply --nope", 2, "--nope"},
    {"info_missing_file", "info {dir}/none.ply", 2, "none.ply"},
    {"info_malformed_file", "info {dir}/bad.ply", 1, "bad.ply"},
    {"convert_ok", "convert {dir}/sphere.ply -o {dir}/c.xyz --json", 0, ""},
    {"convert_unknown_flag", "convert {dir}/sphere.ply -o {dir}/c.xyz --nope", 2, "--nope"},
    {"convert_missing_file", "convert {dir}/none.ply -o {dir}/c.xyz", 2, "none.ply"},
    {"convert_malformed_file", "convert {dir}/bad.ply -o {dir}/c.xyz", 1, "bad.ply"},
    {"sample_ok", "sample torus -n 300 -o {dir}/t.ply --json", 0, "\"points\":300"},
    {"sample_unknown_flag", "sample torus -o {dir}/t.ply --nope", 2, "--nope"},
    {"sample_unknown_shape", "sample teapot -o {dir}/t.ply", 2, "teapot"},
    // Server commands without a server to talk to.
    {"upload_no_server", "upload {dir}/sphere.ply --server 127.0.0.1:1", 1, "127.0.0.1:1"},
    {"jobs_unknown_flag", "jobs --server 127.0.0.1:1 --nope", 2, "--nope"},
    {"render_detach_without_server", "render {dir}/sphere.ply -o {dir}/r.exr --detach", 2, "--detach needs --server"},
    // The tool itself.
    {"no_subcommand", "", 2, ""},
    {"unknown_subcommand", "frobnicate", 2, "unknown command 'frobnicate'"},
    {"help", "--help", 0, "Exit codes"},
};

class Cli : public ::testing::TestWithParam<CliCase> {
protected:
    static void SetUpTestSuite() {
        dir_ = fs::temp_directory_path() / ("surfel-cli-" + std::to_string(::getpid()));
        fs::create_directories(dir_);
        ShapeOptions o;
        o.points = 2000;
        o.normals = true;
        WritePly(SampleShape(Shape::kSphere, o), (dir_ / "sphere.ply").string());
        WriteFileBytes((dir_ / "bad.ply").string(), kMalformedPly);
    }
    static void TearDownTestSuite() { fs::remove_all(dir_); }
    static fs::path dir_;
};
fs::path Cli::dir_;

/// Runs `[env] surfel args` with SURFEL_SERVER, SURFEL_IMAGE_PLUGIN and SURFEL_EXR_PLUGIN unset (the
/// image plugins are found beside the binary, as a user's are); returns the exit code and stdout +
/// stderr.
int RunSurfel(const std::string& args, std::string* output, const std::string& env = "",
              const std::string& binary = std::string(SURFEL_BIN_DIR) + "/surfel") {
    const std::string command = "env -u SURFEL_SERVER -u SURFEL_IMAGE_PLUGIN -u SURFEL_EXR_PLUGIN " + env + " " + binary + " " + args + " 2>&1";
    FILE* pipe = popen(command.c_str(), "r");
    char buf[4096];
    while (std::size_t n = std::fread(buf, 1, sizeof buf, pipe)) output->append(buf, n);
    const int status = pclose(pipe);
    return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

TEST_P(Cli, ExitCodeAndMessage) {
    const CliCase& c = GetParam();
    const std::string args = std::regex_replace(c.args, std::regex("\\{dir\\}"), dir_.string());
    std::string output;
    EXPECT_EQ(RunSurfel(args, &output), c.exit_code) << "surfel " << args << "\n" << output;
    EXPECT_NE(output.find(c.message), std::string::npos) << "surfel " << args << "\n" << output;
    if (c.exit_code != 0) EXPECT_LT(output.size(), 4000u) << "an error is a message, not a dump";
}

// Issue 19.2: the image plugin (OpenImageIO) is opened only by a command that writes an image.
// LD_DEBUG=files makes the dynamic loader name every object it opens.
TEST_F(Cli, OnlyImageCommandsLoadTheImagePlugin) {
    const std::string sphere = (dir_ / "sphere.ply").string();
    for (const std::string& args : {std::string("--version"), "info " + sphere,
                                    "normals " + sphere + " -o " + (dir_ / "n2.ply").string()}) {
        std::string output;
        EXPECT_EQ(RunSurfel(args, &output, "LD_DEBUG=files"), 0) << args;
        EXPECT_EQ(output.find("surfel_image_oiio"), std::string::npos) << "surfel " << args << " opened the plugin";
        EXPECT_EQ(output.find("surfel_image_exr"), std::string::npos) << "surfel " << args << " opened the EXR plugin";
        EXPECT_EQ(output.find("libOpenImageIO"), std::string::npos) << "surfel " << args << " loaded OpenImageIO";
    }
    std::string output;
    EXPECT_EQ(RunSurfel("render " + sphere + " -o " + (dir_ / "l.png").string() + " --width 8 --height 8", &output,
                        "LD_DEBUG=files"),
              0);
    EXPECT_NE(output.find("surfel_image_oiio.so"), std::string::npos) << "the render must open the plugin";
    // Issue 19.1: an EXR render opens only the EXR plugin (OpenEXR), not OpenImageIO.
    output.clear();
    EXPECT_EQ(RunSurfel("render " + sphere + " -o " + (dir_ / "l.exr").string() + " --width 8 --height 8", &output,
                        "LD_DEBUG=files"),
              0);
    EXPECT_NE(output.find("surfel_image_exr.so"), std::string::npos) << "an EXR render must open the EXR plugin";
    EXPECT_EQ(output.find("libOpenImageIO"), std::string::npos) << "an EXR render loaded OpenImageIO";
}

// A missing plugin: exit 1 before any work, the message naming every path searched.
TEST_F(Cli, AMissingImagePluginIsAnErrorNamingThePathsSearched) {
    const std::string sphere = (dir_ / "sphere.ply").string();
    std::string output;
    // EXR needs the EXR plugin or, failing that, the OpenImageIO one: neither can be loaded.
    EXPECT_EQ(RunSurfel("render " + sphere + " -o " + (dir_ / "m.exr").string(), &output,
                        "SURFEL_IMAGE_PLUGIN=" + (dir_ / "nowhere" / "plugin.so").string() +
                            " SURFEL_EXR_PLUGIN=" + (dir_ / "nowhere" / "exr.so").string()),
              1);
    EXPECT_NE(output.find((dir_ / "nowhere" / "plugin.so").string()), std::string::npos) << output;
    EXPECT_NE(output.find((dir_ / "nowhere" / "exr.so").string()), std::string::npos) << output;
    EXPECT_NE(output.find("SURFEL_IMAGE_PLUGIN"), std::string::npos) << output;
    EXPECT_NE(output.find("SURFEL_EXR_PLUGIN"), std::string::npos) << output;
    EXPECT_FALSE(fs::exists(dir_ / "m.exr"));
    // Without the EXR plugin, EXR goes through the OpenImageIO plugin.
    output.clear();
    EXPECT_EQ(RunSurfel("render " + sphere + " -o " + (dir_ / "m.exr").string() + " --width 8 --height 8", &output,
                        "SURFEL_EXR_PLUGIN=" + (dir_ / "nowhere" / "exr.so").string()),
              0)
        << output;
    EXPECT_TRUE(fs::exists(dir_ / "m.exr"));

    // The binary alone in a folder (a hard link keeps /proc/self/exe there; a copy if /tmp is
    // another file system): the plugin is looked for beside it, then in the installed layout.
    const fs::path lone = dir_ / "lone";
    fs::create_directories(lone);
    std::error_code ec;
    fs::create_hard_link(fs::path(SURFEL_BIN_DIR) / "surfel", lone / "surfel", ec);
    if (ec) fs::copy_file(fs::path(SURFEL_BIN_DIR) / "surfel", lone / "surfel");
    output.clear();
    EXPECT_EQ(RunSurfel("render " + sphere + " -o " + (dir_ / "m.png").string() + " --png " +
                            (dir_ / "m2.png").string(),
                        &output, "", (lone / "surfel").string()),
              1);
    EXPECT_NE(output.find((lone / "surfel_image_oiio.so").string()), std::string::npos) << output;
    EXPECT_LT(output.size(), 4000u) << output;
    // The commands that write no image do not need it.
    output.clear();
    EXPECT_EQ(RunSurfel("info " + sphere, &output, "", (lone / "surfel").string()), 0) << output;
}

std::string CaseName(const ::testing::TestParamInfo<CliCase>& param) { return param.param.name; }

INSTANTIATE_TEST_SUITE_P(Subcommands, Cli, ::testing::ValuesIn(kCases), CaseName);

}  // namespace
}  // namespace surfel
