// Every job kind of the table, through the real server and in-process: the same spec on the same
// bytes gives the same result bytes, and an empty spec is refused naming the kind's cloud id.
#include <gtest/gtest.h>

#include <cstdint>
#include <filesystem>
#include <string>

#include "exr_bytes.h"
#include "server_process.h"
#include "service_client.h"
#include "surfel/base/shapes.h"
#include "surfel/io/cloud_io.h"
#include "surfel/io/file_bytes.h"
#include "surfel/io/ply.h"
#include "surfel/worker/job_kind.h"

namespace surfel {
namespace {

namespace fs = std::filesystem;

class JobPaths : public ::testing::TestWithParam<const worker::JobKind*> {
protected:
    static void SetUpTestSuite() {
        dir_ = fs::temp_directory_path() / ("surfel-job-paths-" + std::to_string(::getpid()));
        fs::create_directories(dir_);
        ShapeOptions o;
        o.points = 3000;
        o.normals = true;
        WritePly(SampleShape(Shape::kSphere, o), (dir_ / "sphere.ply").string());
        server_ = std::make_unique<testing::ServerProcess>((dir_ / "data").string());
    }
    static void TearDownTestSuite() {
        server_.reset();
        fs::remove_all(dir_);
    }
    static fs::path dir_;
    static std::unique_ptr<testing::ServerProcess> server_;
};
fs::path JobPaths::dir_;
std::unique_ptr<testing::ServerProcess> JobPaths::server_;

std::string KindName(const ::testing::TestParamInfo<const worker::JobKind*>& info) {
    return std::string(info.param->Name());
}

INSTANTIATE_TEST_SUITE_P(JobKinds, JobPaths, ::testing::ValuesIn(worker::JobKinds().begin(), worker::JobKinds().end()),
                         KindName);

TEST_P(JobPaths, InProcessAndThroughTheServerGiveTheSameBytes) {
    const worker::JobKind& kind = *GetParam();
    const std::string path = (dir_ / "sphere.ply").string();

    // In-process, as the CLI runs it: each cloud id is the file's path.
    v1::JobSpec local = kind.Example();
    for (std::size_t i = 0; i < kind.InputCount(local); ++i) kind.SetInput(local, i, path);
    const worker::JobOutput here = worker::RunJob(
        local, [](const std::string& p) { return std::make_shared<const PointCloud>(ReadPointCloud(p)); });

    client::ServiceClient c(server_->target());
    v1::JobSpec remote = kind.Example();
    const std::string cloud_id = c.UploadFile(path).id();
    for (std::size_t i = 0; i < kind.InputCount(remote); ++i) kind.SetInput(remote, i, cloud_id);
    const v1::Job job = c.Submit(remote);
    EXPECT_EQ(job.type(), kind.Name());
    const client::WatchOutcome there = c.Watch(job.id(), /*include_result=*/true, /*cancel_on_disconnect=*/false);
    ASSERT_EQ(there.state, v1::SUCCEEDED) << there.status_message;

    EXPECT_EQ(there.result.media_type(), here.media_type);
    EXPECT_EQ(there.result.extension(), here.extension);
    EXPECT_EQ(there.result.points(), here.points);
    ASSERT_EQ(there.bytes.size(), here.bytes.size());
    EXPECT_TRUE(test::WithoutCaptureDate(there.bytes) == test::WithoutCaptureDate(here.bytes))
        << kind.Name() << ": result bytes differ";
}

// A CSG render reads two clouds (render.cloud_id and render.csg_cloud_id): in-process and through
// the server (both uploaded) it gives the same bytes.
class CsgRenderPaths : public JobPaths {};

TEST_F(CsgRenderPaths, InProcessAndThroughTheServerGiveTheSameBytes) {
    ShapeOptions o;
    o.points = 3000;
    o.normals = true;
    o.scale = 0.7;
    o.seed = 2;
    const std::string a = (dir_ / "sphere.ply").string(), b = (dir_ / "small.ply").string();
    WritePly(SampleShape(Shape::kSphere, o), b);
    const worker::JobKind& kind = *worker::FindJobKind("render");
    v1::JobSpec spec;
    v1::RenderJob& r = *spec.mutable_render();
    r.set_width(32);
    r.set_height(24);
    r.set_csg_op(v1::BooleanJob::DIFFERENCE);
    *r.mutable_csg_transform_b()->mutable_translation() = worker::ToProto(Vec3d(0.6, 0, 0.3));
    ASSERT_EQ(kind.InputCount(spec), 2u);
    v1::JobSpec local = spec;
    kind.SetInput(local, 0, a);
    kind.SetInput(local, 1, b);
    const worker::JobOutput here = worker::RunJob(
        local, [](const std::string& p) { return std::make_shared<const PointCloud>(ReadPointCloud(p)); });
    EXPECT_EQ(here.report.at("csg_op"), "difference");
    EXPECT_GT(here.report.at("classifications").get<std::uint64_t>(), 0u);

    client::ServiceClient c(server_->target());
    v1::JobSpec remote = spec;
    kind.SetInput(remote, 0, c.UploadFile(a).id());
    kind.SetInput(remote, 1, c.UploadFile(b).id());
    const v1::Job job = c.Submit(remote);
    const client::WatchOutcome there = c.Watch(job.id(), /*include_result=*/true, /*cancel_on_disconnect=*/false);
    ASSERT_EQ(there.state, v1::SUCCEEDED) << there.status_message;
    ASSERT_EQ(there.bytes.size(), here.bytes.size());
    EXPECT_TRUE(test::WithoutCaptureDate(there.bytes) == test::WithoutCaptureDate(here.bytes)) << "CSG render bytes differ";

    // Without its second cloud the spec is refused naming the field.
    v1::JobSpec missing = remote;
    missing.mutable_render()->clear_csg_cloud_id();
    try {
        c.Submit(missing);
        FAIL() << "submitted a CSG render without B";
    } catch (const client::RpcError& e) {
        EXPECT_NE(std::string(e.what()).find("render.csg_cloud_id: is required"), std::string::npos) << e.what();
    }
}

TEST_P(JobPaths, TheServerRefusesAnEmptySpecNamingTheCloudId) {
    const worker::JobKind& kind = *GetParam();
    v1::JobSpec spec = kind.Example();
    for (std::size_t i = 0; i < kind.InputCount(spec); ++i) kind.SetInput(spec, i, "");
    client::ServiceClient c(server_->target());
    try {
        c.Submit(spec);
        FAIL() << "submitted a spec without its cloud";
    } catch (const client::RpcError& e) {
        EXPECT_EQ(e.status().error_code(), grpc::StatusCode::INVALID_ARGUMENT);
        EXPECT_NE(std::string(e.what()).find(kind.Inputs(spec)[0].field + ": is required"), std::string::npos)
            << e.what();
    }
}

TEST_P(JobPaths, AnUnknownCloudIsNotFoundNamingTheField) {
    const worker::JobKind& kind = *GetParam();
    v1::JobSpec spec = kind.Example();
    for (std::size_t i = 0; i < kind.InputCount(spec); ++i) kind.SetInput(spec, i, std::string(64, 'a'));
    client::ServiceClient c(server_->target());
    try {
        c.Submit(spec);
        FAIL() << "submitted a spec on a cloud the server does not have";
    } catch (const client::RpcError& e) {
        EXPECT_EQ(e.status().error_code(), grpc::StatusCode::NOT_FOUND);
        EXPECT_NE(std::string(e.what()).find(kind.Inputs(spec)[0].field), std::string::npos) << e.what();
    }
}

}  // namespace
}  // namespace surfel
