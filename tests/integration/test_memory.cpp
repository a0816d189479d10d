// Memory before work (issue 18.2, 15.6): a real server with a tight --max-job-memory refuses
// oversized jobs at Submit with RESOURCE_EXHAUSTED naming the estimate and the limit, runs a
// small one, and stays alive; a resample target above --max-points is refused naming the field;
// --max-uploads caps the upload calls in progress. The estimates themselves: monotone and sane.
#include <gtest/gtest.h>
#include <sys/resource.h>

#include <chrono>
#include <filesystem>
#include <string>
#include <thread>

#include <grpcpp/grpcpp.h>

#include "server_process.h"
#include "service_client.h"
#include "surfel/base/shapes.h"
#include "surfel/io/ply.h"
#include "surfel/worker/job_kind.h"
#include "surfel/worker/memory.h"
#include "surfel/v1/surfel.grpc.pb.h"

namespace surfel {
namespace {

namespace fs = std::filesystem;

// ---- the estimates (no server) ----------------------------------------------------------------

worker::CloudFacts Facts(std::uint64_t points) {
    worker::CloudFacts f;
    f.points = points;
    f.attributes = {"normals"};
    f.file_bytes = points * 24 + 300;
    f.extent = Vec3d(1, 1, 1);
    return f;
}

std::uint64_t Estimate(const v1::JobSpec& spec, std::uint64_t points) {
    const worker::JobKind& kind = worker::KindOf(spec);
    std::vector<worker::CloudFacts> facts(kind.InputCount(spec), Facts(points));
    return worker::EstimateJobMemory(spec, facts);
}

TEST(MemoryEstimate, EveryKindGrowsWithItsInputAndExceedsTheLoadedCloud) {
    for (const worker::JobKind* kind : worker::JobKinds()) {
        const v1::JobSpec spec = kind->Example();
        const std::uint64_t small = Estimate(spec, 10'000), large = Estimate(spec, 1'000'000);
        EXPECT_GT(large, small) << kind->Name();
        EXPECT_GE(small, worker::LoadBytes(Facts(10'000))) << kind->Name();
        EXPECT_LT(large, 4ull << 30) << kind->Name() << ": a million points in under 4 GiB";
    }
}

TEST(MemoryEstimate, RenderGrowsWithPixelsAndA16kImageNeedsGigabytes) {
    v1::JobSpec spec;
    spec.mutable_render()->set_width(512);
    spec.mutable_render()->set_height(512);
    const std::uint64_t small = Estimate(spec, 35'000);
    spec.mutable_render()->set_width(16384);
    spec.mutable_render()->set_height(16384);
    const std::uint64_t huge = Estimate(spec, 35'000);
    EXPECT_GT(huge, 8ull << 30);  // 8 float channels of 2^28 pixels alone are 8 GiB
    EXPECT_LT(small, 256ull << 20);
    spec.mutable_render()->set_format(v1::RenderJob::PNG);
    EXPECT_LT(Estimate(spec, 35'000), huge);
}

TEST(MemoryEstimate, ResampleGrowsWithTargetAndWithFinerSpacing) {
    v1::JobSpec spec;
    spec.mutable_resample()->set_target(10'000);
    const std::uint64_t a = Estimate(spec, 50'000);
    spec.mutable_resample()->set_target(10'000'000);
    EXPECT_GT(Estimate(spec, 50'000), a + (1ull << 30));
    spec.mutable_resample()->set_target(0);
    spec.mutable_resample()->set_spacing(0.01);
    const std::uint64_t coarse = Estimate(spec, 50'000);
    spec.mutable_resample()->set_spacing(0.001);
    EXPECT_GT(Estimate(spec, 50'000), coarse);
}

TEST(MemoryEstimate, CheckNamesTheEstimateAndTheLimit) {
    v1::JobSpec spec;
    spec.mutable_render();
    try {
        worker::CheckJobMemory(spec, 300ull << 20, 100ull << 20, "--max-job-memory");
        FAIL() << "no throw";
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kResourceExhausted);
        EXPECT_EQ(std::string(e.what()), "render: job needs an estimated 300.0 MiB, above --max-job-memory 100.0 MiB");
    }
    try {
        worker::CheckJobMemory(spec, 60ull << 20, 100ull << 20, "--max-job-memory", 50ull << 20);
        FAIL() << "no throw";
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kResourceExhausted);
        EXPECT_NE(std::string(e.what()).find("above the 50.0 MiB that running jobs leave"), std::string::npos)
            << e.what();
    }
    EXPECT_NO_THROW(worker::CheckJobMemory(spec, 60ull << 20, 100ull << 20, "--max-job-memory", 40ull << 20));
    EXPECT_NO_THROW(worker::CheckJobMemory(spec, 1ull << 40, 0, "--max-job-memory"));  // 0 = no limit
    EXPECT_GT(worker::AvailableMemory(), 0u);
}

// ---- through a real server ----------------------------------------------------------------------

class MemoryServer : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() / ("surfel-memory-" + std::to_string(::getpid()));
        fs::remove_all(dir_);
        fs::create_directories(dir_);
        ShapeOptions o;
        o.points = 3000;
        o.normals = true;
        WritePly(SampleShape(Shape::kSphere, o), (dir_ / "sphere.ply").string());
    }
    void TearDown() override {
        server_.reset();
        fs::remove_all(dir_);
    }
    void Start(std::vector<std::string> flags) {
        server_ = std::make_unique<testing::ServerProcess>((dir_ / "data").string(), std::move(flags));
    }
    // Submit must fail with `code`; returns the message.
    std::string Refused(client::ServiceClient& c, const v1::JobSpec& spec, grpc::StatusCode code) {
        try {
            c.Submit(spec);
        } catch (const client::RpcError& e) {
            EXPECT_EQ(e.status().error_code(), code) << e.status().error_message();
            return e.status().error_message();
        }
        ADD_FAILURE() << "Submit succeeded";
        return "";
    }
    fs::path dir_;
    std::unique_ptr<testing::ServerProcess> server_;
};

TEST_F(MemoryServer, OversizedJobsAreRefusedAtSubmitAndASmallOneRuns) {
    Start({"--max-job-memory", "128", "--max-points", "1000000"});
    client::ServiceClient c(server_->target());
    const std::string id = c.UploadFile((dir_ / "sphere.ply").string()).id();

    v1::JobSpec render;
    render.mutable_render()->set_cloud_id(id);
    render.mutable_render()->set_width(16384);
    render.mutable_render()->set_height(16384);
    std::string m = Refused(c, render, grpc::StatusCode::RESOURCE_EXHAUSTED);
    EXPECT_NE(m.find("render: job needs an estimated"), std::string::npos) << m;
    EXPECT_NE(m.find("above --max-job-memory 128.0 MiB"), std::string::npos) << m;

    v1::JobSpec resample;
    resample.mutable_resample()->set_cloud_id(id);
    resample.mutable_resample()->set_target(990'000);  // under --max-points, over the memory
    m = Refused(c, resample, grpc::StatusCode::RESOURCE_EXHAUSTED);
    EXPECT_NE(m.find("resample: job needs an estimated"), std::string::npos) << m;

    // Issue 15.6: a target above the server's --max-points names the field.
    resample.mutable_resample()->set_target(2'000'000);
    m = Refused(c, resample, grpc::StatusCode::RESOURCE_EXHAUSTED);
    EXPECT_NE(m.find("resample.target"), std::string::npos) << m;
    EXPECT_NE(m.find("--max-points"), std::string::npos) << m;

    // A small job runs, and its report carries its estimate; the server is alive throughout.
    v1::JobSpec small = worker::KindOf(render).Example();
    small.mutable_render()->set_cloud_id(id);
    const v1::Job job = c.Submit(small);
    const client::WatchOutcome done = c.Watch(job.id(), false, false);
    ASSERT_EQ(done.state, v1::SUCCEEDED) << done.status_message;
    EXPECT_NE(done.result.report_json().find("memory_estimate_bytes"), std::string::npos);
    EXPECT_EQ(c.GetCloud(id).id(), id);
}

TEST_F(MemoryServer, UnderAHardAddressSpaceLimitOversizedJobsAreRefusedAndTheServerLives) {
    // The server's whole address space capped (RLIMIT_AS, inherited through fork/exec): a job
    // that started would fail its allocations; refused at Submit, none starts.
    struct rlimit old {};
    getrlimit(RLIMIT_AS, &old);
    struct rlimit tight = old;
    tight.rlim_cur = 3ull << 30;
    ASSERT_EQ(setrlimit(RLIMIT_AS, &tight), 0);
    Start({"--max-job-memory", "512", "--workers", "2"});
    setrlimit(RLIMIT_AS, &old);
    client::ServiceClient c(server_->target());
    const std::string id = c.UploadFile((dir_ / "sphere.ply").string()).id();
    for (int i = 0; i < 3; ++i) {
        v1::JobSpec render;
        render.mutable_render()->set_cloud_id(id);
        render.mutable_render()->set_width(16384 - i);
        render.mutable_render()->set_height(16384);
        Refused(c, render, grpc::StatusCode::RESOURCE_EXHAUSTED);
        v1::JobSpec simplify;
        simplify.mutable_simplify()->set_cloud_id(id);
        simplify.mutable_simplify()->set_target(100);
        EXPECT_NO_THROW(c.Watch(c.Submit(simplify).id(), false, false));
    }
    EXPECT_EQ(c.GetCloud(id).id(), id);
    EXPECT_EQ(server_->Kill(SIGTERM), 0);  // alive until asked to stop, and stops cleanly
}

TEST_F(MemoryServer, UploadsBeyondMaxUploadsAreRefused) {
    Start({"--max-uploads", "1"});
    client::ServiceClient c(server_->target());
    // One call holds its upload open (no finish_write); a second upload is refused meanwhile.
    grpc::ClientContext ctx;
    v1::Cloud response;
    auto channel = grpc::CreateChannel(server_->target(), grpc::InsecureChannelCredentials());
    auto stub = v1::Surfel::NewStub(channel);
    auto writer = stub->Upload(&ctx, &response);
    v1::UploadRequest first;
    first.set_upload_id("held-open");
    first.set_filename("x.ply");
    first.set_data("ply\n");
    ASSERT_TRUE(writer->Write(first));
    // The server claims the id when it reads the first message.
    for (int i = 0; i < 200; ++i) {
        v1::QueryUploadRequest q;
        q.set_upload_id("held-open");
        grpc::ClientContext qc;
        v1::QueryUploadResponse r;
        if (stub->QueryUpload(&qc, q, &r).ok() && r.committed_size() > 0) break;
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    try {
        c.UploadFile((dir_ / "sphere.ply").string());
        ADD_FAILURE() << "second upload accepted";
    } catch (const client::RpcError& e) {
        EXPECT_EQ(e.status().error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
        EXPECT_NE(e.status().error_message().find("--max-uploads"), std::string::npos) << e.status().error_message();
    }
    ctx.TryCancel();
    writer->Finish();
    // The slot is free again once that call ended.
    bool stored = false;
    for (int i = 0; i < 100 && !stored; ++i) {
        try {
            c.UploadFile((dir_ / "sphere.ply").string());
            stored = true;
        } catch (const client::RpcError&) {
            std::this_thread::sleep_for(std::chrono::milliseconds(20));
        }
    }
    EXPECT_TRUE(stored);
}

}  // namespace
}  // namespace surfel
