// Integration tests: the real surfel-server on a free loopback port, driven by the client library
// and by the real `surfel` CLI.
#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <thread>

#include "server_process.h"
#include "service_client.h"
#include "surfel/base/error.h"
#include "surfel/base/shapes.h"
#include "surfel/io/cloud_io.h"
#include "surfel/io/file_bytes.h"
#include "surfel/io/image.h"
#include "surfel/io/ply.h"
#include "surfel/worker/sha256.h"

namespace surfel {
namespace {

namespace fs = std::filesystem;
using client::RpcError;
using client::ServiceClient;
using Clock = std::chrono::steady_clock;

class ServiceTest : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        dir_ = fs::temp_directory_path() / ("surfel-it-" + std::to_string(::getpid()));
        fs::create_directories(dir_);
        ShapeOptions o;
        o.points = 5000;
        o.normals = true;
        WritePly(SampleShape(Shape::kSphere, o), (dir_ / "sphere.ply").string());
        o.points = 40000;
        WritePly(SampleShape(Shape::kTorus, o), (dir_ / "torus.ply").string());
        WriteFileBytes((dir_ / "bad.ply").string(), "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n"
                                                    "property float y\nproperty float z\nend_header\n0 0 0\n1 1\n");
    }
    static void TearDownTestSuite() { fs::remove_all(dir_); }

    void SetUp() override {
        data_ = (dir_ / ::testing::UnitTest::GetInstance()->current_test_info()->name()).string();
        fs::remove_all(data_);
    }
    std::string Path(const std::string& name) const { return (dir_ / name).string(); }

    static v1::JobSpec Render(const std::string& cloud, int w, int h, int spp = 1) {
        v1::JobSpec spec;
        auto* r = spec.mutable_render();
        r->set_cloud_id(cloud);
        r->set_width(w);
        r->set_height(h);
        r->set_samples_per_pixel(spp);
        return spec;
    }

    static fs::path dir_;
    std::string data_;
};
fs::path ServiceTest::dir_;

// A test process that dies without running destructors (an abort, a sanitizer's report) takes
// its server with it: otherwise the orphan keeps ctest's output pipe open and ctest hangs until
// the test's timeout instead of reporting the failure.
TEST_F(ServiceTest, TheServerEndsWithTheTestProcessThatStartedIt) {
    int pipe_fds[2];
    ASSERT_EQ(::pipe(pipe_fds), 0);
    const pid_t test_process = ::fork();
    ASSERT_GE(test_process, 0);
    if (test_process == 0) {
        ::close(pipe_fds[0]);
        testing::ServerProcess server(data_);
        const int ids[2] = {server.port(), static_cast<int>(server.pid())};
        if (::write(pipe_fds[1], ids, sizeof ids) != sizeof ids) ::_exit(2);
        ::_exit(0);  // no destructor: the server is not killed by ServerProcess
    }
    ::close(pipe_fds[1]);
    int ids[2] = {0, 0};
    const bool got_port = ::read(pipe_fds[0], ids, sizeof ids) == sizeof ids;
    const int port = ids[0];
    ::close(pipe_fds[0]);
    int status = 0;
    ASSERT_EQ(::waitpid(test_process, &status, 0), test_process);
    ASSERT_TRUE(got_port);
    ASSERT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0);

    const auto accepts = [port] {
        const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
        sockaddr_in addr{};
        addr.sin_family = AF_INET;
        addr.sin_port = htons(static_cast<uint16_t>(port));
        addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
        const bool ok = ::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) == 0;
        ::close(fd);
        return ok;
    };
    const auto deadline = Clock::now() + std::chrono::seconds(10);
    while (accepts() && Clock::now() < deadline) std::this_thread::sleep_for(std::chrono::milliseconds(20));
    if (accepts()) {
        ::kill(ids[1], SIGKILL);  // an orphan (pid ids[1], the test process's child) is ours to end
        ADD_FAILURE() << "surfel-server on port " << port << " outlived the process that started it";
    }
}

TEST_F(ServiceTest, UploadRenderAndDecodeTheExr) {
    testing::ServerProcess server(data_);
    ServiceClient c(server.target());
    const v1::Cloud cloud = c.UploadFile(Path("sphere.ply"));
    EXPECT_EQ(cloud.points(), 5000u);
    EXPECT_EQ(cloud.id().size(), 64u);
    EXPECT_EQ(cloud.format(), "ply-binary-le");
    EXPECT_EQ(std::vector<std::string>(cloud.attributes().begin(), cloud.attributes().end()),
              std::vector<std::string>{"normals"});
    EXPECT_NEAR(cloud.bounds_max().x(), 1.0, 0.01);

    const v1::Job job = c.Submit(Render(cloud.id(), 64, 48));
    const auto out = c.Watch(job.id(), true, false);
    ASSERT_EQ(out.state, v1::SUCCEEDED) << out.status_message;
    EXPECT_EQ(out.result.media_type(), "image/x-exr");
    EXPECT_EQ(out.bytes.size(), out.result.size_bytes());
    WriteFileBytes(Path("render.exr"), out.bytes);
    const Image img = ReadImage(Path("render.exr"));
    ASSERT_EQ(img.width, 64);
    ASSERT_EQ(img.height, 48);
    ASSERT_EQ(img.channels, (std::vector<std::string>{"R", "G", "B", "A", "Z", "N.X", "N.Y", "N.Z"}));
    auto px = [&](int x, int y, int ch) { return img.At(x, y, ch); };
    EXPECT_EQ(px(32, 24, 3), 1.0f);                  // the sphere covers the centre
    EXPECT_TRUE(std::isfinite(px(32, 24, 4)));       // with a finite depth
    EXPECT_NEAR(px(32, 24, 7), 1.0f, 0.05f);         // facing the camera (+z)
    EXPECT_EQ(px(0, 0, 3), 0.0f);                    // and misses the corner
    EXPECT_TRUE(std::isinf(px(0, 0, 4)));
    // The report came along.
    EXPECT_NE(out.result.report_json().find("\"rays\":3072"), std::string::npos) << out.result.report_json();
    // Download gives the same bytes.
    EXPECT_EQ(c.Download(job.id()), out.bytes);
}

TEST_F(ServiceTest, UploadSimplifyAndCountThePly) {
    testing::ServerProcess server(data_);
    ServiceClient c(server.target());
    const v1::Cloud cloud = c.UploadFile(Path("sphere.ply"));
    v1::JobSpec spec;
    spec.mutable_simplify()->set_cloud_id(cloud.id());
    spec.mutable_simplify()->set_target(500);
    spec.mutable_simplify()->set_method(v1::SimplifyJob::ITERATIVE);
    const v1::Job job = c.Submit(spec);
    const auto out = c.Watch(job.id(), true, false);
    ASSERT_EQ(out.state, v1::SUCCEEDED) << out.status_message;
    const PointCloud result = ParsePly(out.bytes, "result");
    EXPECT_EQ(result.size(), 500u);
    EXPECT_TRUE(result.has_normals());
    EXPECT_TRUE(result.has_radii());
    // The same job again is answered from the store.
    const v1::Job again = c.Submit(spec);
    EXPECT_TRUE(again.reused());
    EXPECT_EQ(again.id(), job.id());
    EXPECT_EQ(again.state(), v1::SUCCEEDED);
}

TEST_F(ServiceTest, SameBytesAreStoredOnce) {
    testing::ServerProcess server(data_);
    ServiceClient c(server.target());
    const v1::Cloud a = c.UploadFile(Path("sphere.ply"));
    const v1::Cloud b = c.UploadFile(Path("sphere.ply"));
    EXPECT_EQ(a.id(), b.id());
    EXPECT_FALSE(a.deduplicated());
    EXPECT_TRUE(b.deduplicated());
    std::size_t files = 0;
    for ([[maybe_unused]] const auto& e : fs::directory_iterator(data_ + "/clouds")) ++files;
    EXPECT_EQ(files, 1u);
}

// The client sends from a mapping of the file (client/upload_source.h): a file cut shorter while
// it is sent ends the upload with an error (the hasher's, or the broken stream's), never SIGBUS,
// and nothing is stored; the server still serves.
TEST_F(ServiceTest, AFileTruncatedWhileUploadedIsAnErrorNotACrash) {
    testing::ServerProcess server(data_);
    ServiceClient c(server.target());
    const std::string path = (fs::path(data_ + "-file") / "big.ply").string();
    fs::create_directories(fs::path(path).parent_path());
    {
        const std::string torus = ReadFileBytes(Path("torus.ply"));
        std::ofstream out(path, std::ios::binary);
        for (int i = 0; i < 24; ++i)
            out.write(torus.data(), static_cast<std::streamsize>(torus.size()));
    }
    bool cut = false;
    EXPECT_THROW(c.UploadFile(path,
                              [&](std::uint64_t, std::uint64_t) {
                                  if (!cut) fs::resize_file(path, 100000);
                                  cut = true;
                              }),
                 std::exception);
    EXPECT_TRUE(cut);
    EXPECT_FALSE(fs::exists(data_ + "/clouds") && !fs::is_empty(data_ + "/clouds"));
    EXPECT_EQ(c.UploadFile(Path("sphere.ply")).points(), 5000u);
    fs::remove_all(fs::path(path).parent_path());
}

TEST_F(ServiceTest, MalformedUploadIsInvalidArgumentAndTheServerStillServes) {
    testing::ServerProcess server(data_);
    ServiceClient c(server.target());
    try {
        c.UploadFile(Path("bad.ply"));
        FAIL() << "accepted a malformed file";
    } catch (const RpcError& e) {
        EXPECT_EQ(e.status().error_code(), grpc::StatusCode::INVALID_ARGUMENT);
        EXPECT_NE(e.status().error_message().find("bad.ply"), std::string::npos) << e.status().error_message();
    }
    EXPECT_EQ(c.UploadFile(Path("sphere.ply")).points(), 5000u);
    EXPECT_TRUE(fs::is_empty(data_ + "/uploads"));  // the rejected bytes are gone
}

TEST_F(ServiceTest, UnknownIdsAreNotFound) {
    testing::ServerProcess server(data_);
    ServiceClient c(server.target());
    auto code = [](auto&& fn) {
        try {
            fn();
        } catch (const RpcError& e) {
            return e.status().error_code();
        }
        return grpc::StatusCode::OK;
    };
    EXPECT_EQ(code([&] { c.GetJob("j0"); }), grpc::StatusCode::NOT_FOUND);
    EXPECT_EQ(code([&] { c.Cancel("j0"); }), grpc::StatusCode::NOT_FOUND);
    EXPECT_EQ(code([&] { c.Watch("j0", false, false); }), grpc::StatusCode::NOT_FOUND);
    EXPECT_EQ(code([&] { c.Download("j0"); }), grpc::StatusCode::NOT_FOUND);
    EXPECT_EQ(code([&] { c.GetCloud("c0"); }), grpc::StatusCode::NOT_FOUND);
    EXPECT_EQ(code([&] { c.Submit(Render("c0", 8, 8)); }), grpc::StatusCode::NOT_FOUND);
    EXPECT_EQ(code([&] { c.Submit(Render("c0", 0x7fffffff, 8)); }), grpc::StatusCode::INVALID_ARGUMENT);
}

TEST_F(ServiceTest, UploadResumesAtTheCommittedSize) {
    testing::ServerProcess server(data_);
    const std::string bytes = ReadFileBytes(Path("sphere.ply"));
    auto channel = grpc::CreateChannel(server.target(), grpc::InsecureChannelCredentials());
    auto stub = v1::Surfel::NewStub(channel);
    const std::size_t half = bytes.size() / 2;
    {  // the first half, then the connection "breaks" (the stream ends without finish_write)
        grpc::ClientContext ctx;
        v1::Cloud cloud;
        auto w = stub->Upload(&ctx, &cloud);
        v1::UploadRequest r;
        r.set_upload_id("resume-test");
        r.set_filename("sphere.ply");
        r.set_data(bytes.substr(0, half));
        ASSERT_TRUE(w->Write(r));
        w->WritesDone();
        EXPECT_EQ(w->Finish().error_code(), grpc::StatusCode::FAILED_PRECONDITION);
    }
    grpc::ClientContext qctx;
    v1::QueryUploadRequest q;
    q.set_upload_id("resume-test");
    v1::QueryUploadResponse qr;
    ASSERT_TRUE(stub->QueryUpload(&qctx, q, &qr).ok());
    EXPECT_EQ(qr.committed_size(), static_cast<std::int64_t>(half));
    {  // a wrong offset is refused
        grpc::ClientContext ctx;
        v1::Cloud cloud;
        auto w = stub->Upload(&ctx, &cloud);
        v1::UploadRequest r;
        r.set_upload_id("resume-test");
        r.set_write_offset(1);
        r.set_data("x");
        w->Write(r);
        w->WritesDone();
        EXPECT_EQ(w->Finish().error_code(), grpc::StatusCode::FAILED_PRECONDITION);
    }
    grpc::ClientContext ctx;
    v1::Cloud cloud;
    auto w = stub->Upload(&ctx, &cloud);
    v1::UploadRequest r;
    r.set_upload_id("resume-test");
    r.set_filename("sphere.ply");
    r.set_write_offset(static_cast<std::int64_t>(half));
    r.set_data(bytes.substr(half));
    r.set_finish_write(true);
    ASSERT_TRUE(w->Write(r));
    w->WritesDone();
    const grpc::Status s = w->Finish();
    ASSERT_TRUE(s.ok()) << s.error_message();
    EXPECT_EQ(cloud.points(), 5000u);
    ServiceClient c(server.target());
    EXPECT_EQ(c.UploadFile(Path("sphere.ply")).id(), cloud.id());  // the whole file's hash
}

// The upload check runs while the chunks arrive (PlyPositionScan, fed by UploadSession::Append):
// chunks cut inside the header and inside records, good and bad binary and ascii files, answered as the
// check of the whole file answers (the same Cloud, or the same code and message); a resumed
// upload (its first bytes were not seen by this call) is checked after the last byte, the same.
TEST_F(ServiceTest, UploadsCheckedWhileReceivedAnswerAsTheWholeFileCheck) {
    testing::ServerProcess server(data_);
    auto channel = grpc::CreateChannel(server.target(), grpc::InsecureChannelCredentials());
    auto stub = v1::Surfel::NewStub(channel);
    const std::string ok = ReadFileBytes(Path("sphere.ply"));
    PointCloud nan_cloud = ReadPly(Path("sphere.ply"));
    nan_cloud.positions[4000].y() = std::numeric_limits<float>::quiet_NaN();
    const std::string nan = FormatPly(nan_cloud);
    PlyWriteOptions ascii;
    ascii.format = PlyFormat::kAscii;
    const std::string ok_ascii = FormatPly(ReadPly(Path("sphere.ply")), ascii);
    std::string bad_ascii = ok_ascii;  // a coordinate that is not a number, far into the records
    bad_ascii.insert(bad_ascii.find('\n', bad_ascii.size() / 2) + 1, "0.5 0.x5 ");
    const std::vector<std::pair<std::string, std::string>> files = {
        {"ok.ply", ok}, {"nan.ply", nan}, {"nan-tail.ply", nan + "junk"}, {"cut.ply", ok.substr(0, ok.size() - 5)},
        {"ok-ascii.ply", ok_ascii}, {"nan-ascii.ply", FormatPly(nan_cloud, ascii) + "junk\n"},
        {"bad-ascii.ply", bad_ascii}, {"cut-ascii.ply", ok_ascii.substr(0, ok_ascii.size() - 5)}};
    int n = 0;
    for (const auto& [name, bytes] : files) {
        for (const bool resumed : {false, true}) {
            SCOPED_TRACE(name + (resumed ? " resumed" : ""));
            const std::string id = "scan-" + std::to_string(n++);
            std::size_t offset = 0;
            if (resumed) {  // the first 3,000 bytes (the header and some records), then the call breaks off
                grpc::ClientContext ctx;
                v1::Cloud cloud;
                auto w = stub->Upload(&ctx, &cloud);
                v1::UploadRequest r;
                r.set_upload_id(id);
                r.set_filename(name);
                r.set_data(bytes.substr(0, 3000));
                ASSERT_TRUE(w->Write(r));
                w->WritesDone();
                EXPECT_EQ(w->Finish().error_code(), grpc::StatusCode::FAILED_PRECONDITION);
                offset = 3000;
            }
            grpc::ClientContext ctx;
            v1::Cloud cloud;
            auto w = stub->Upload(&ctx, &cloud);
            for (std::size_t piece = 100; offset < bytes.size(); piece = 7777) {  // 100: inside the header
                v1::UploadRequest r;
                r.set_upload_id(id);
                r.set_filename(name);
                r.set_write_offset(static_cast<std::int64_t>(offset));
                r.set_data(bytes.substr(offset, piece));
                offset = std::min(bytes.size(), offset + piece);
                r.set_finish_write(offset == bytes.size());
                ASSERT_TRUE(w->Write(r));
            }
            w->WritesDone();
            const grpc::Status s = w->Finish();
            try {
                const CloudFileSummary want = InspectCloudFile(bytes, name);
                ASSERT_TRUE(s.ok()) << s.error_message();
                EXPECT_EQ(cloud.points(), want.points);
                EXPECT_EQ(cloud.bounds_min().x(), static_cast<double>(want.bounds.min.x()));
                EXPECT_EQ(cloud.bounds_min().y(), static_cast<double>(want.bounds.min.y()));
                EXPECT_EQ(cloud.bounds_min().z(), static_cast<double>(want.bounds.min.z()));
                EXPECT_EQ(cloud.bounds_max().x(), static_cast<double>(want.bounds.max.x()));
                EXPECT_EQ(cloud.bounds_max().y(), static_cast<double>(want.bounds.max.y()));
                EXPECT_EQ(cloud.bounds_max().z(), static_cast<double>(want.bounds.max.z()));
                EXPECT_EQ(cloud.format(), want.format);
            } catch (const Error& e) {
                ASSERT_EQ(e.code(), ErrorCode::kInvalidArgument) << e.what();
                EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
                EXPECT_EQ(s.error_message(), e.what());
            }
        }
    }
    EXPECT_TRUE(fs::is_empty(data_ + "/uploads"));
}

// The server reads ahead of its writer (upload_reactor.cpp): messages received after one that
// ends the call are dropped, and those before a broken stream's end are all appended. The
// committed sizes must be those of a server that appends each chunk before reading the next
// (--transfer-threads 0), whatever the client sends after the failing message.
TEST_F(ServiceTest, ChunksReadAheadAreCommittedExactlyUpToTheFailingMessage) {
    const std::string bytes = ReadFileBytes(Path("torus.ply"));
    constexpr std::size_t kChunk = 4096;
    ASSERT_GT(bytes.size(), 60 * kChunk);
    for (const char* threads : {"0", "2"}) {
        SCOPED_TRACE(std::string("--transfer-threads ") + threads);
        testing::ServerProcess server(data_ + "-" + threads, {"--transfer-threads", threads});
        auto stub = v1::Surfel::NewStub(grpc::CreateChannel(server.target(), grpc::InsecureChannelCredentials()));
        const auto committed = [&](const std::string& id) {
            grpc::ClientContext ctx;
            v1::QueryUploadRequest q;
            q.set_upload_id(id);
            v1::QueryUploadResponse r;
            EXPECT_TRUE(stub->QueryUpload(&ctx, q, &r).ok());
            return r.committed_size();
        };
        // Sends chunks [from, to) of `bytes` at once (no waiting between them), the chunk at
        // `bad` with a wrong write_offset; then ends the stream without finish_write.
        const auto send = [&](const std::string& id, std::size_t from, std::size_t to, std::size_t bad) {
            grpc::ClientContext ctx;
            v1::Cloud cloud;
            auto w = stub->Upload(&ctx, &cloud);
            for (std::size_t i = from; i < to; ++i) {
                v1::UploadRequest r;
                r.set_upload_id(id);
                r.set_filename("torus.ply");
                r.set_write_offset(static_cast<std::int64_t>(i == bad ? i * kChunk + 1 : i * kChunk));
                r.set_data(bytes.substr(i * kChunk, kChunk));
                if (!w->Write(r)) break;  // the server ended the call
            }
            w->WritesDone();
            return w->Finish();
        };
        const grpc::Status broken = send("ahead-broken", 0, 40, SIZE_MAX);
        EXPECT_EQ(broken.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << broken.error_message();
        EXPECT_NE(broken.error_message().find("resume at write_offset " + std::to_string(40 * kChunk)),
                  std::string::npos)
            << broken.error_message();
        EXPECT_EQ(committed("ahead-broken"), static_cast<std::int64_t>(40 * kChunk));

        const grpc::Status refused = send("ahead-refused", 0, 60, 25);
        EXPECT_EQ(refused.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << refused.error_message();
        EXPECT_NE(refused.error_message().find("write_offset " + std::to_string(25 * kChunk + 1)),
                  std::string::npos)
            << refused.error_message();
        EXPECT_EQ(committed("ahead-refused"), static_cast<std::int64_t>(25 * kChunk));

        // The broken upload resumes where it stopped and is stored under the file's SHA-256.
        grpc::ClientContext ctx;
        v1::Cloud cloud;
        auto w = stub->Upload(&ctx, &cloud);
        for (std::size_t off = 40 * kChunk; off < bytes.size(); off += kChunk) {
            v1::UploadRequest r;
            r.set_upload_id("ahead-broken");
            r.set_write_offset(static_cast<std::int64_t>(off));
            r.set_data(bytes.substr(off, kChunk));
            r.set_finish_write(off + kChunk >= bytes.size());
            ASSERT_TRUE(w->Write(r));
        }
        w->WritesDone();
        const grpc::Status s = w->Finish();
        ASSERT_TRUE(s.ok()) << s.error_message();
        EXPECT_EQ(cloud.id(), worker::Sha256Hex(bytes));
        EXPECT_EQ(cloud.points(), 40000u);
        EXPECT_EQ(committed("ahead-broken"), 0);
    }
}

TEST_F(ServiceTest, LimitsGiveResourceExhausted) {
    testing::ServerProcess server(data_, {"--max-points", "1000", "--max-queued", "1", "--workers", "1"});
    ServiceClient c(server.target());
    try {
        c.UploadFile(Path("sphere.ply"));
        FAIL();
    } catch (const RpcError& e) {
        EXPECT_EQ(e.status().error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED) << e.what();
    }
    testing::ServerProcess small(data_ + "-small", {"--max-upload-mb", "0.01"});
    ServiceClient s(small.target());
    try {
        s.UploadFile(Path("sphere.ply"));
        FAIL();
    } catch (const RpcError& e) {
        EXPECT_EQ(e.status().error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED) << e.what();
    }
}

TEST_F(ServiceTest, FullQueueGivesResourceExhausted) {
    testing::ServerProcess server(data_, {"--max-queued", "1", "--workers", "1"});
    ServiceClient c(server.target());
    const std::string id = c.UploadFile(Path("torus.ply")).id();
    const v1::Job running = c.Submit(Render(id, 512, 512, 8));
    for (int i = 0; i < 500 && c.GetJob(running.id()).state() != v1::RUNNING; ++i)
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
    const v1::Job queued = c.Submit(Render(id, 512, 512, 7));
    try {
        c.Submit(Render(id, 512, 512, 6));
        FAIL() << "a third job fit a queue of one";
    } catch (const RpcError& e) {
        EXPECT_EQ(e.status().error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
    }
    c.Cancel(queued.id());
    c.Cancel(running.id());
}

TEST_F(ServiceTest, CancelMidRenderStopsQuickly) {
    testing::ServerProcess server(data_);
    ServiceClient c(server.target());
    const std::string id = c.UploadFile(Path("torus.ply")).id();
    const v1::Job job = c.Submit(Render(id, 1024, 1024, 16));  // tens of seconds uncancelled
    std::atomic<bool> running{false};
    Clock::time_point cancelled_at{};
    client::WatchOutcome outcome;
    std::thread watcher([&] {
        outcome = c.Watch(job.id(), false, false, [&](const std::string&, double f) {
            if (f > 0) running = true;
        });
    });
    for (int i = 0; i < 1000 && !running; ++i) std::this_thread::sleep_for(std::chrono::milliseconds(10));
    ASSERT_TRUE(running);
    cancelled_at = Clock::now();
    c.Cancel(job.id());
    watcher.join();
    const double ms = std::chrono::duration<double, std::milli>(Clock::now() - cancelled_at).count();
    EXPECT_EQ(outcome.state, v1::CANCELLED);
    EXPECT_EQ(outcome.status_code, grpc::StatusCode::CANCELLED);
    EXPECT_LT(ms, 1000.0);  // the goal is 100 ms; the figure is recorded below
    std::printf("cancel -> CANCELLED event: %.1f ms\n", ms);
    EXPECT_EQ(c.GetJob(job.id()).state(), v1::CANCELLED);
}

TEST_F(ServiceTest, WatcherDisconnectCancelsWhenAsked) {
    testing::ServerProcess server(data_);
    ServiceClient c(server.target());
    const std::string id = c.UploadFile(Path("torus.ply")).id();
    const v1::Job job = c.Submit(Render(id, 1024, 1024, 15));
    {
        auto channel = grpc::CreateChannel(server.target(), grpc::InsecureChannelCredentials());
        auto stub = v1::Surfel::NewStub(channel);
        grpc::ClientContext ctx;
        ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::milliseconds(500));
        v1::WatchRequest req;
        req.set_job_id(job.id());
        req.set_cancel_on_disconnect(true);
        auto reader = stub->Watch(&ctx, req);
        v1::JobEvent e;
        while (reader->Read(&e)) {
        }
        EXPECT_EQ(reader->Finish().error_code(), grpc::StatusCode::DEADLINE_EXCEEDED);
    }
    v1::JobState state = v1::RUNNING;
    for (int i = 0; i < 200 && state != v1::CANCELLED; ++i) {
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
        state = c.GetJob(job.id()).state();
    }
    EXPECT_EQ(state, v1::CANCELLED);
}

TEST_F(ServiceTest, TwentyConcurrentClients) {
    testing::ServerProcess server(data_);
    const std::string id = ServiceClient(server.target()).UploadFile(Path("sphere.ply")).id();
    std::atomic<int> ok{0};
    std::vector<std::thread> clients;
    for (int i = 0; i < 20; ++i) {
        clients.emplace_back([&, i] {
            ServiceClient c(server.target());
            v1::JobSpec spec = Render(id, 40, 40);
            spec.mutable_render()->mutable_background()->set_x(i / 20.0);  // 20 different jobs
            const auto out = c.Watch(c.Submit(spec).id(), true, false);
            if (out.state == v1::SUCCEEDED && out.bytes.size() == out.result.size_bytes() && !out.bytes.empty()) ++ok;
        });
    }
    for (auto& t : clients) t.join();
    EXPECT_EQ(ok, 20);
    EXPECT_EQ(ServiceClient(server.target()).ListJobs(100).size(), 20u);
}

TEST_F(ServiceTest, KilledMidJobTheJobCompletesAfterRestart) {
    std::string job_id;
    {
        testing::ServerProcess server(data_, {"--workers", "1"});
        ServiceClient c(server.target());
        const std::string id = c.UploadFile(Path("torus.ply")).id();
        job_id = c.Submit(Render(id, 256, 256, 2)).id();
        for (int i = 0; i < 1000 && c.GetJob(job_id).state() != v1::RUNNING; ++i)
            std::this_thread::sleep_for(std::chrono::milliseconds(5));
        ASSERT_EQ(c.GetJob(job_id).state(), v1::RUNNING);
        EXPECT_EQ(server.Kill(SIGKILL), 128 + SIGKILL);
    }
    testing::ServerProcess again(data_, {"--workers", "1"});
    ServiceClient c(again.target());
    const auto out = c.Watch(job_id, true, false);
    ASSERT_EQ(out.state, v1::SUCCEEDED) << out.status_message;
    EXPECT_EQ(out.bytes.size(), out.result.size_bytes());
}

TEST_F(ServiceTest, SigtermShutsDownCleanly) {
    testing::ServerProcess server(data_);
    ServiceClient(server.target()).UploadFile(Path("sphere.ply"));
    EXPECT_EQ(server.Kill(SIGTERM), 0);
}

// ---- The real CLI against the real server.

int Shell(const std::string& command, std::string* out = nullptr) {
    FILE* pipe = popen((command + " 2>/dev/null").c_str(), "r");
    std::string text;
    char buf[4096];
    while (std::size_t n = std::fread(buf, 1, sizeof buf, pipe)) text.append(buf, n);
    const int status = pclose(pipe);
    if (out) *out = text;
    return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

TEST_F(ServiceTest, CliRendersAndSimplifiesThroughTheServer) {
    testing::ServerProcess server(data_);
    const std::string surfel = std::string(SURFEL_BIN_DIR) + "/surfel";
    const std::string at = " --server " + server.target();
    std::string out;
    ASSERT_EQ(Shell(surfel + " render " + Path("sphere.ply") + " -o " + Path("cli.exr") + " --png " + Path("cli.png") +
                      " --width 32 --height 32 --json" + at,
                  &out),
              0);
    EXPECT_NE(out.find("\"job_id\""), std::string::npos) << out;
    EXPECT_EQ(ReadImage(Path("cli.exr")).channels.size(), 8u);
    EXPECT_TRUE(fs::exists(Path("cli.png")));
    ASSERT_EQ(Shell(surfel + " simplify " + Path("sphere.ply") + " -o " + Path("cli.ply") +
                      " --method particle --target 300 --json" + at,
                  &out),
              0);
    EXPECT_EQ(ReadPly(Path("cli.ply")).size(), 300u);
    ASSERT_EQ(Shell(surfel + " jobs --json" + at, &out), 0);
    EXPECT_NE(out.find("\"count\":2"), std::string::npos) << out;
    EXPECT_EQ(Shell(surfel + " cancel j0" + at), 1);                                         // NOT_FOUND
    EXPECT_EQ(Shell(surfel + " render " + Path("bad.ply") + " -o " + Path("x.exr") + at), 1);  // INVALID_ARGUMENT
    EXPECT_EQ(Shell(surfel + " simplify " + Path("sphere.ply") + " -o " + Path("x.ply") + " --method voxel" + at), 2);
}

}  // namespace
}  // namespace surfel
