// Degenerate clouds through every job (issue 18, item 5): 0, 1 and 2 points, identical points, a
// plane, collinear points, coordinates near 1e30 and 1e-30 -- through every job kind and each of
// its methods (the table below, checked against the proto's enums), in-process as the CLI runs it
// and through the real server, plus the CLI's normals and project commands. Each run must end in
// a clear error (INVALID_ARGUMENT or FAILED_PRECONDITION whose message names the job) or in a
// result that reads back with finite values; never a crash, an INTERNAL, or a hang. The server
// gives the same outcome as the in-process run: the same code and message, or the same bytes.
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <google/protobuf/descriptor.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <functional>
#include <set>

#include "exr_bytes.h"
#include "server_process.h"
#include "service_client.h"
#include "surfel/base/error.h"
#include "surfel/base/shapes.h"
#include "surfel/io/cloud_io.h"
#include "surfel/io/file_bytes.h"
#include "surfel/io/image.h"
#include "surfel/io/ply.h"
#include "surfel/worker/job_kind.h"
#include "surfel/worker/status.h"

namespace surfel {
namespace {

namespace fs = std::filesystem;

// ---- The degenerate clouds --------------------------------------------------------------------

struct DegenerateCloud {
    std::string name;
    PointCloud cloud;
};

void PrintTo(const DegenerateCloud& c, std::ostream* os) { *os << c.name; }

PointCloud FromPoints(std::vector<Vec3f> points) {
    PointCloud c;
    c.positions = std::move(points);
    return c;
}

PointCloud ScaledSphere(double scale) {
    ShapeOptions o;
    o.points = 400;
    o.scale = scale;
    return SampleShape(Shape::kSphere, o);
}

const std::vector<DegenerateCloud>& DegenerateClouds() {
    static const std::vector<DegenerateCloud> clouds = [] {
        std::vector<DegenerateCloud> all;
        all.push_back({"empty", PointCloud{}});
        all.push_back({"one_point", FromPoints({{0.5f, 0.25f, -1.0f}})});
        all.push_back({"two_points", FromPoints({{0, 0, 0}, {1, 0.5f, 0.25f}})});
        all.push_back({"identical", FromPoints(std::vector<Vec3f>(64, Vec3f(0.3f, -0.2f, 0.7f)))});
        ShapeOptions plane;
        plane.points = 400;
        all.push_back({"plane", SampleShape(Shape::kPlane, plane)});
        std::vector<Vec3f> line;
        for (int i = 0; i < 64; ++i) line.emplace_back(0.1f * i, 0.05f * i, -0.02f * i);
        all.push_back({"collinear", FromPoints(line)});
        all.push_back({"huge_1e30", ScaledSphere(1e30)});
        all.push_back({"tiny_1e-30", ScaledSphere(1e-30)});
        return all;
    }();
    return clouds;
}

// ---- The job variants: every kind, every method or operation ------------------------------------

/// One job to run on a cloud of `points` points with bounding-box diagonal `diagonal`: its spec
/// (cloud ids unset), built from the cloud so that counts and offsets fit it.
struct JobVariant {
    std::string name;  ///< <kind>_<method>
    std::function<v1::JobSpec(std::size_t points, double diagonal)> spec;
};

void PrintTo(const JobVariant& v, std::ostream* os) { *os << v.name; }

std::size_t Half(std::size_t n) { return std::max<std::size_t>(1, n / 2); }

const std::vector<JobVariant>& JobVariants() {
    static const std::vector<JobVariant> variants = [] {
        std::vector<JobVariant> all;
        all.push_back({"render", [](std::size_t, double) {
                           v1::JobSpec s;
                           s.mutable_render()->set_width(24);
                           s.mutable_render()->set_height(16);
                           return s;
                       }});
        const google::protobuf::EnumDescriptor* simplify = v1::SimplifyJob::Method_descriptor();
        for (int i = 0; i < simplify->value_count(); ++i) {
            const auto method = static_cast<v1::SimplifyJob::Method>(simplify->value(i)->number());
            if (method == v1::SimplifyJob::METHOD_UNSPECIFIED) continue;
            all.push_back({"simplify_" + simplify->value(i)->name(), [method](std::size_t n, double) {
                               v1::JobSpec s;
                               s.mutable_simplify()->set_method(method);
                               s.mutable_simplify()->set_target(Half(n));
                               return s;
                           }});
        }
        all.push_back({"simplify_HIERARCHICAL_error", [](std::size_t, double) {
                           v1::JobSpec s;
                           s.mutable_simplify()->set_method(v1::SimplifyJob::HIERARCHICAL);
                           s.mutable_simplify()->set_error(0.01);
                           return s;
                       }});
        const google::protobuf::EnumDescriptor* resample = v1::ResampleJob::Method_descriptor();
        for (int i = 0; i < resample->value_count(); ++i) {
            const auto method = static_cast<v1::ResampleJob::Method>(resample->value(i)->number());
            if (method == v1::ResampleJob::METHOD_UNSPECIFIED) continue;
            all.push_back({"resample_" + resample->value(i)->name(), [method](std::size_t n, double) {
                               v1::JobSpec s;
                               v1::ResampleJob& r = *s.mutable_resample();
                               r.set_method(method);
                               r.set_iterations(4);
                               // mls takes no count; particle and split a target above the input.
                               if (method != v1::ResampleJob::MLS) r.set_target(2 * n + 2);
                               return s;
                           }});
        }
        const google::protobuf::EnumDescriptor* op = v1::BooleanJob::Op_descriptor();
        for (int i = 0; i < op->value_count(); ++i) {
            const auto value = static_cast<v1::BooleanJob::Op>(op->value(i)->number());
            if (value == v1::BooleanJob::OP_UNSPECIFIED) continue;
            all.push_back({"boolean_" + op->value(i)->name(), [value](std::size_t, double diagonal) {
                               v1::JobSpec s;
                               s.mutable_boolean()->set_op(value);
                               // B is A moved by a third of its diagonal: the two overlap.
                               const double shift = diagonal > 0 && std::isfinite(diagonal) ? diagonal / 3 : 0.5;
                               *s.mutable_boolean()->mutable_transform_b()->mutable_translation() =
                                   worker::ToProto(Vec3d(shift, 0, 0));
                               return s;
                           }});
        }
        return all;
    }();
    return variants;
}

// Every kind of the table has a variant, so a new kind must be added here the day it lands.
TEST(DegenerateInputTable, CoversEveryJobKind) {
    std::set<std::string> kinds;
    for (const JobVariant& v : JobVariants()) kinds.insert(std::string(worker::KindOf(v.spec(10, 1.0)).Name()));
    for (const worker::JobKind* kind : worker::JobKinds())
        EXPECT_TRUE(kinds.count(std::string(kind->Name()))) << kind->Name() << " has no degenerate-input variant";
}

// ---- Outcomes ----------------------------------------------------------------------------------

/// How a job ended: a result's bytes, or an error code (as gRPC's) with its message.
struct Outcome {
    bool ok = false;
    grpc::StatusCode code = grpc::StatusCode::OK;
    std::string message;
    std::string bytes;
    std::string extension;
    std::uint64_t points = 0;
};

double Diagonal(const PointCloud& c) {
    if (c.empty()) return 0;
    const BoundingBox b = c.Bounds();
    return (b.max.cast<double>() - b.min.cast<double>()).norm();
}

constexpr auto kHangLimit = std::chrono::seconds(60);

/// Runs `variant` in-process on `cloud` (both inputs of a boolean are the cloud).
Outcome RunHere(const JobVariant& variant, const PointCloud& cloud) {
    v1::JobSpec spec = variant.spec(cloud.size(), Diagonal(cloud));
    const worker::JobKind& kind = worker::KindOf(spec);
    for (std::size_t i = 0; i < kind.InputCount(spec); ++i) kind.SetInput(spec, i, "cloud");
    const auto shared = std::make_shared<const PointCloud>(cloud);
    const auto start = std::chrono::steady_clock::now();
    bool hung = false;
    Outcome o;
    try {
        worker::JobOutput out = worker::RunJob(
            spec, [&](const std::string&) { return shared; },
            [&](double) {
                hung = std::chrono::steady_clock::now() - start > kHangLimit;
                return !hung;
            });
        o.ok = true;
        o.bytes = std::move(out.bytes);
        o.extension = out.extension;
        o.points = out.points;
    } catch (const Error& e) {
        o.code = worker::ToStatusCode(e.code());
        o.message = e.what();
    }
    EXPECT_FALSE(hung) << "ran longer than " << kHangLimit.count() << " s";
    return o;
}

/// A result must read back, with finite positions and normals (PLY) or finite colours (images).
void CheckResult(const Outcome& o) {
    if (o.extension == ".ply") {
        const PointCloud r = ParsePly(o.bytes, "result.ply");
        r.CheckConsistent();
        EXPECT_EQ(r.size(), o.points);
        for (std::size_t i = 0; i < r.size(); ++i) {
            ASSERT_TRUE(r.positions[i].allFinite()) << "point " << i << " is not finite";
            if (r.has_normals()) ASSERT_TRUE(r.normals[i].allFinite()) << "normal " << i << " is not finite";
        }
        return;
    }
    const fs::path path = fs::temp_directory_path() / ("surfel-degenerate-" + std::to_string(::getpid()) + o.extension);
    WriteFileBytes(path.string(), o.bytes);
    const Image image = ReadImage(path.string());
    fs::remove(path);
    ASSERT_GT(image.width, 0);
    for (const char* channel : {"R", "G", "B", "A"}) {
        const int c = image.ChannelIndex(channel);
        ASSERT_GE(c, 0) << channel;
        for (int y = 0; y < image.height; ++y)
            for (int x = 0; x < image.width; ++x)
                ASSERT_TRUE(std::isfinite(image.At(x, y, c))) << channel << " at " << x << "," << y;
    }
}

/// An error must be one the client can act on, and name the job it belongs to.
void CheckError(const Outcome& o, const std::string& kind) {
    EXPECT_TRUE(o.code == grpc::StatusCode::INVALID_ARGUMENT || o.code == grpc::StatusCode::FAILED_PRECONDITION)
        << "status " << o.code << ": " << o.message;
    EXPECT_NE(o.message.find(kind), std::string::npos) << "the message does not name the job: " << o.message;
    EXPECT_LT(o.message.size(), 1000u) << o.message;
}

std::string KindName(const JobVariant& v) { return std::string(worker::KindOf(v.spec(10, 1.0)).Name()); }

// ---- In-process --------------------------------------------------------------------------------

// One test per job variant, over every cloud (a process per test under ctest: 14, not 112).
class InProcess : public ::testing::TestWithParam<JobVariant> {};

TEST_P(InProcess, ClearErrorOrFiniteResult) {
    const JobVariant& variant = GetParam();
    for (const DegenerateCloud& input : DegenerateClouds()) {
        SCOPED_TRACE(input.name);
        const Outcome o = RunHere(variant, input.cloud);
        if (o.ok) CheckResult(o);
        else CheckError(o, KindName(variant));
    }
}

std::string VariantName(const ::testing::TestParamInfo<JobVariant>& info) { return info.param.name; }

INSTANTIATE_TEST_SUITE_P(Degenerate, InProcess, ::testing::ValuesIn(JobVariants()), VariantName);

// ---- Through the server ------------------------------------------------------------------------

// One test per job variant, over every cloud: one server start for each (ctest runs each test in
// a process of its own).
class ThroughTheServer : public ::testing::TestWithParam<JobVariant> {
protected:
    static void SetUpTestSuite() {
        dir_ = fs::temp_directory_path() / ("surfel-degenerate-" + std::to_string(::getpid()));
        fs::create_directories(dir_);
        server_ = std::make_unique<testing::ServerProcess>((dir_ / "data").string());
    }
    static void TearDownTestSuite() {
        server_.reset();
        fs::remove_all(dir_);
    }
    /// The cloud's id on the server; "" with the upload's error in `refused` otherwise.
    static std::string Upload(const DegenerateCloud& input, grpc::Status* refused) {
        const std::string path = (dir_ / (input.name + ".ply")).string();
        WritePly(input.cloud, path);
        client::ServiceClient c(server_->target());
        try {
            return c.UploadFile(path).id();
        } catch (const client::RpcError& e) {
            *refused = e.status();
            return "";
        }
    }
    static fs::path dir_;
    static std::unique_ptr<testing::ServerProcess> server_;
};
fs::path ThroughTheServer::dir_;
std::unique_ptr<testing::ServerProcess> ThroughTheServer::server_;

TEST_P(ThroughTheServer, SameOutcomeAsInProcess) {
    const JobVariant& variant = GetParam();
    for (const DegenerateCloud& input : DegenerateClouds()) {
        SCOPED_TRACE(input.name);
        grpc::Status refused;
        const std::string id = Upload(input, &refused);
        if (id.empty()) {
            // The server takes no cloud without points: refused at upload, naming the file.
            EXPECT_EQ(input.cloud.size(), 0u) << refused.error_message();
            EXPECT_EQ(refused.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << refused.error_message();
            EXPECT_NE(refused.error_message().find("no points"), std::string::npos) << refused.error_message();
            continue;
        }
        v1::JobSpec spec = variant.spec(input.cloud.size(), Diagonal(input.cloud));
        const worker::JobKind& kind = worker::KindOf(spec);
        for (std::size_t i = 0; i < kind.InputCount(spec); ++i) kind.SetInput(spec, i, id);

        Outcome there;
        client::ServiceClient c(server_->target(), /*timeout_s=*/60);
        try {
            const v1::Job job = c.Submit(spec);
            const client::WatchOutcome w = c.Watch(job.id(), /*include_result=*/true, /*cancel_on_disconnect=*/true);
            there.ok = w.state == v1::SUCCEEDED;
            ASSERT_TRUE(there.ok || w.state == v1::FAILED) << v1::JobState_Name(w.state) << ": " << w.status_message;
            there.code = static_cast<grpc::StatusCode>(w.status_code);
            there.message = w.status_message;
            there.bytes = w.bytes;
            there.extension = w.result.extension();
            there.points = w.result.points();
        } catch (const client::RpcError& e) {  // refused at Submit
            there.code = e.status().error_code();
            there.message = e.status().error_message();
        }
        if (there.ok) CheckResult(there);
        else CheckError(there, std::string(kind.Name()));

        const Outcome here = RunHere(variant, input.cloud);
        EXPECT_EQ(there.ok, here.ok) << "server: " << there.message << "\nin-process: " << here.message;
        EXPECT_EQ(there.code, here.code);
        EXPECT_EQ(there.message, here.message);
        EXPECT_TRUE(test::WithoutCaptureDate(there.bytes) == test::WithoutCaptureDate(here.bytes)) << "result bytes differ";
        ASSERT_NO_THROW(c.ListJobs(1)) << "the server stopped serving";
    }
}

INSTANTIATE_TEST_SUITE_P(Degenerate, ThroughTheServer, ::testing::ValuesIn(JobVariants()), VariantName);

// ---- The CLI's surface commands (normals, project) and info -------------------------------------

/// Runs `surfel args`; returns the exit code (-signal when killed) and stdout + stderr.
int RunSurfel(const std::string& args, std::string* output) {
    const std::string command = "env -u SURFEL_SERVER " + std::string(SURFEL_BIN_DIR) + "/surfel " + args + " 2>&1";
    FILE* pipe = popen(command.c_str(), "r");
    char buf[4096];
    while (std::size_t n = std::fread(buf, 1, sizeof buf, pipe)) output->append(buf, n);
    const int status = pclose(pipe);
    if (WIFSIGNALED(status)) return -WTERMSIG(status);
    return WIFEXITED(status) ? WEXITSTATUS(status) : -1000;
}

class Cli : public ::testing::TestWithParam<std::tuple<std::string, DegenerateCloud>> {};

TEST_P(Cli, ExitsCleanlyWithAResultOrAMessage) {
    const auto& [command, input] = GetParam();
    const fs::path dir = fs::temp_directory_path() / ("surfel-degenerate-cli-" + std::to_string(::getpid()));
    fs::create_directories(dir);
    const std::string in = (dir / (input.name + ".ply")).string();
    const std::string out = (dir / (input.name + "-" + command + ".ply")).string();
    WritePly(input.cloud, in);
    std::string output;
    const int code = RunSurfel(command + " " + in + " -o " + out + " --json", &output);
    ASSERT_TRUE(code == 0 || code == 1) << "surfel " << command << " exited " << code << "\n" << output;
    if (code == 1) {
        EXPECT_LT(output.size(), 1000u) << output;
        EXPECT_NE(output.find("error"), std::string::npos) << output;
    } else {
        const PointCloud r = ReadPointCloud(out);
        EXPECT_EQ(r.size(), input.cloud.size());
        for (std::size_t i = 0; i < r.size(); ++i) {
            ASSERT_TRUE(r.positions[i].allFinite()) << "point " << i;
            if (r.has_normals()) ASSERT_TRUE(r.normals[i].allFinite()) << "normal " << i;
        }
    }
    fs::remove_all(dir);
}

std::string CliName(const ::testing::TestParamInfo<std::tuple<std::string, DegenerateCloud>>& info) {
    std::string name = std::get<0>(info.param) + "_" + std::get<1>(info.param).name;
    for (char& ch : name)
        if (!std::isalnum(static_cast<unsigned char>(ch))) ch = '_';
    return name;
}

INSTANTIATE_TEST_SUITE_P(Degenerate, Cli,
                         ::testing::Combine(::testing::Values("normals", "project"),
                                            ::testing::ValuesIn(DegenerateClouds())),
                         CliName);

// An empty file is no point cloud, whatever its extension (it used to read as an empty XYZ).
TEST(EmptyFile, IsRefusedByInfoAndEveryReader) {
    const fs::path dir = fs::temp_directory_path() / ("surfel-empty-" + std::to_string(::getpid()));
    fs::create_directories(dir);
    for (const char* name : {"empty.ply", "empty.xyz", "blank.txt"}) {
        const std::string path = (dir / name).string();
        WriteFileBytes(path, std::string_view(name).starts_with("blank") ? " \n\t\r\n" : "");
        try {
            ReadPointCloud(path);
            ADD_FAILURE() << name << " read as a cloud";
        } catch (const Error& e) {
            EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
            EXPECT_NE(std::string(e.what()).find(path + ": "), std::string::npos) << e.what();
            EXPECT_NE(std::string(e.what()).find("not a point cloud"), std::string::npos) << e.what();
        }
        std::string output;
        EXPECT_EQ(RunSurfel("info " + path, &output), 1) << output;
        EXPECT_NE(output.find("not a point cloud"), std::string::npos) << output;
    }
    fs::remove_all(dir);
}

}  // namespace
}  // namespace surfel
