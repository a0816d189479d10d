// Upload ingestion off gRPC's threads: the server's Executor on its own, then the real server
// with several large uploads at once (one ingest thread, so they wait for it), cancelled uploads,
// and the unary calls that keep answering meanwhile. Completion and correctness only; no timing.
#include <gtest/gtest.h>

#include <atomic>
#include <filesystem>
#include <future>
#include <thread>
#include <vector>

#include "executor.h"
#include "server_process.h"
#include "service_client.h"
#include "surfel/base/shapes.h"
#include "surfel/io/file_bytes.h"
#include "surfel/io/ply.h"
#include "surfel/worker/sha256.h"

namespace surfel {
namespace {

namespace fs = std::filesystem;
using client::RpcError;
using client::ServiceClient;

// Uploads a file as a client that retries does: RESOURCE_EXHAUSTED (the ingest queue is full) and
// FAILED_PRECONDITION (an earlier call on this upload is still being ingested, or finished it
// between QueryUpload and Upload) are answered by trying again, which resumes at the committed
// size or finds the stored cloud.
v1::Cloud UploadRetrying(ServiceClient& c, const std::string& path) {
    for (int attempt = 0;; ++attempt) {
        try {
            return c.UploadFile(path);
        } catch (const RpcError& e) {
            const auto code = e.status().error_code();
            if (attempt == 200 ||
                (code != grpc::StatusCode::RESOURCE_EXHAUSTED && code != grpc::StatusCode::FAILED_PRECONDITION))
                throw;
            std::this_thread::sleep_for(std::chrono::milliseconds(50));
        }
    }
}

// ---- Executor ---------------------------------------------------------------------------------

TEST(Executor, RunsEveryTaskItAccepts) {
    std::atomic<int> ran{0};
    int accepted = 0;
    {
        server::Executor ex(3, 1000);
        EXPECT_EQ(ex.threads(), 3u);
        for (int i = 0; i < 500; ++i) accepted += ex.TrySubmit([&] { ran.fetch_add(1); }) ? 1 : 0;
    }  // the destructor runs what is queued
    EXPECT_EQ(accepted, 500);
    EXPECT_EQ(ran.load(), 500);
}

TEST(Executor, AFullQueueRefusesInsteadOfWaiting) {
    std::promise<void> started, release;
    std::shared_future<void> released = release.get_future().share();
    std::atomic<int> ran{0};
    {
        server::Executor ex(1, 2);
        ASSERT_TRUE(ex.TrySubmit([&] {
            started.set_value();
            released.wait();
            ran.fetch_add(1);
        }));
        started.get_future().wait();  // the only thread is busy; the queue is empty
        EXPECT_TRUE(ex.TrySubmit([&] { ran.fetch_add(1); }));
        EXPECT_TRUE(ex.TrySubmit([&] { ran.fetch_add(1); }));
        EXPECT_EQ(ex.Queued(), 2u);
        EXPECT_FALSE(ex.TrySubmit([&] { ran.fetch_add(100); }));  // refused, never run
        release.set_value();
    }
    EXPECT_EQ(ran.load(), 3);
}

TEST(Executor, ZeroSizesMeanOne) {
    server::Executor ex(0, 0);
    EXPECT_EQ(ex.threads(), 1u);
    std::promise<void> done;
    ASSERT_TRUE(ex.TrySubmit([&] { done.set_value(); }));
    done.get_future().wait();
}

// ---- The server -------------------------------------------------------------------------------

class UploadExecutorTest : public ::testing::Test {
protected:
    static constexpr int kClouds = 4;

    // Large ASCII clouds (slow to parse, tens of MB), distinct so that none deduplicates.
    static void SetUpTestSuite() {
        dir_ = fs::temp_directory_path() / ("surfel-ingest-" + std::to_string(::getpid()));
        fs::create_directories(dir_);
        PlyWriteOptions ascii;
        ascii.format = PlyFormat::kAscii;
        for (int i = 0; i < kClouds; ++i) {
            ShapeOptions o;
            o.points = 200'000 + 1000 * static_cast<std::size_t>(i);
            o.normals = true;
            o.seed = 7 + static_cast<std::uint64_t>(i);
            WritePly(SampleShape(Shape::kSphere, o), Path(i), ascii);
        }
        ShapeOptions small;
        small.points = 100;
        WritePly(SampleShape(Shape::kBox, small), (dir_ / "small.ply").string());
    }
    static void TearDownTestSuite() { fs::remove_all(dir_); }

    void SetUp() override {
        data_ = (dir_ / ::testing::UnitTest::GetInstance()->current_test_info()->name()).string();
        fs::remove_all(data_);
    }

    static std::string Path(int i) { return (dir_ / ("cloud" + std::to_string(i) + ".ply")).string(); }
    static std::size_t Points(int i) { return 200'000 + 1000 * static_cast<std::size_t>(i); }

    static fs::path dir_;
    std::string data_;
};
fs::path UploadExecutorTest::dir_;

TEST_F(UploadExecutorTest, ConcurrentLargeUploadsCompleteWhileUnaryCallsAnswer) {
    testing::ServerProcess server(data_, {"--ingest-threads", "1", "--ingest-queue", "16"});
    const v1::Cloud small = ServiceClient(server.target()).UploadFile((dir_ / "small.ply").string());

    std::vector<std::future<v1::Cloud>> uploads;
    for (int i = 0; i < kClouds; ++i)
        uploads.push_back(std::async(std::launch::async, [&, i] {
            ServiceClient c(server.target());
            return c.UploadFile(Path(i));
        }));
    // Unary calls go on while the uploads are sent and parsed; every one must answer correctly.
    std::atomic<bool> uploading{true};
    std::atomic<int> answered{0};
    std::thread unary([&] {
        ServiceClient c(server.target(), 60.0);
        do {
            EXPECT_EQ(c.GetCloud(small.id()).points(), 100u);
            EXPECT_TRUE(c.ListJobs(10).empty());
            answered.fetch_add(1);
        } while (uploading.load());
    });
    std::vector<v1::Cloud> clouds;
    for (auto& u : uploads) clouds.push_back(u.get());
    uploading = false;
    unary.join();
    EXPECT_GE(answered.load(), 1);

    for (int i = 0; i < kClouds; ++i) {
        SCOPED_TRACE(Path(i));
        const v1::Cloud& c = clouds[static_cast<std::size_t>(i)];
        EXPECT_EQ(c.points(), Points(i));
        EXPECT_EQ(c.id(), worker::Sha256Hex(ReadFileBytes(Path(i))));
        EXPECT_EQ(c.format(), "ply-ascii");
        EXPECT_FALSE(c.deduplicated());
        EXPECT_EQ(c.size_bytes(), fs::file_size(Path(i)));
        EXPECT_NEAR(c.bounds_max().x(), 1.0, 0.01);
        EXPECT_EQ(ServiceClient(server.target()).GetCloud(c.id()).points(), Points(i));
    }
}

// Cancelled right after the final message: whether the server saw the cancel before, during or
// after parsing, the call ends, nothing leaks or hangs, and the same upload then succeeds (resumed,
// parsed, or found stored).
TEST_F(UploadExecutorTest, UploadsCancelledDuringIngestionCanBeRepeated) {
    testing::ServerProcess server(data_, {"--ingest-threads", "1"});
    auto channel = grpc::CreateChannel(server.target(), grpc::InsecureChannelCredentials());
    auto stub = v1::Surfel::NewStub(channel);
    for (int i = 0; i < kClouds; ++i) {
        const std::string bytes = ReadFileBytes(Path(i));
        grpc::ClientContext ctx;
        v1::Cloud cloud;
        auto w = stub->Upload(&ctx, &cloud);
        v1::UploadRequest r;
        r.set_upload_id(worker::Sha256Hex(bytes));
        r.set_filename("cloud.ply");
        const std::size_t chunk = 1 << 20;
        for (std::size_t off = 0; off < bytes.size(); off += chunk) {
            r.set_write_offset(static_cast<std::int64_t>(off));
            r.set_data(bytes.substr(off, chunk));
            r.set_finish_write(off + chunk >= bytes.size());
            if (!w->Write(r)) break;
            r.clear_filename();
        }
        ctx.TryCancel();
        const grpc::Status s = w->Finish();
        if (!s.ok()) EXPECT_EQ(s.error_code(), grpc::StatusCode::CANCELLED) << s.error_message();
    }
    ServiceClient c(server.target());
    for (int i = 0; i < kClouds; ++i) EXPECT_EQ(UploadRetrying(c, Path(i)).points(), Points(i));
    EXPECT_EQ(c.ListJobs(10).size(), 0u);
}

// A full ingest queue answers RESOURCE_EXHAUSTED and keeps the bytes: the client's next attempt
// completes. Which uploads are refused depends on timing; every one ends up stored.
TEST_F(UploadExecutorTest, RefusedUploadsResumeLater) {
    testing::ServerProcess server(data_, {"--ingest-threads", "1", "--ingest-queue", "1"});
    std::vector<std::future<v1::Cloud>> uploads;
    for (int i = 0; i < kClouds; ++i)
        uploads.push_back(std::async(std::launch::async, [&, i] {
            ServiceClient c(server.target());
            return UploadRetrying(c, Path(i));
        }));
    for (int i = 0; i < kClouds; ++i) {
        const v1::Cloud c = uploads[static_cast<std::size_t>(i)].get();
        EXPECT_EQ(c.points(), Points(i));
        EXPECT_EQ(c.id(), worker::Sha256Hex(ReadFileBytes(Path(i))));
    }
}

}  // namespace
}  // namespace surfel
