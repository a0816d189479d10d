// Integrity (issue 18.4) through the real surfel-server on the directory backend: a byte flipped
// on disk in an uploaded cloud fails the next job with DATA_LOSS naming the blob, never a wrong
// result; a byte flipped in a result fails its download (gRPC Download and Watch with the result)
// with DATA_LOSS, and the HTTP GET stops short of its Content-Length.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>

#include "server_process.h"
#include "service_client.h"
#include "surfel/base/shapes.h"
#include "surfel/io/ply.h"
#include "surfel/worker/sha256.h"

namespace surfel {
namespace {

namespace fs = std::filesystem;
using client::RpcError;
using client::ServiceClient;

/// Flips the lowest bit of the byte at `offset` of `path`.
void FlipByte(const fs::path& path, std::streamoff offset) {
    std::fstream f(path, std::ios::in | std::ios::out | std::ios::binary);
    ASSERT_TRUE(f) << path;
    f.seekg(offset);
    const char b = static_cast<char>(f.get());
    f.seekp(offset);
    f.put(static_cast<char>(b ^ 0x01));
}

class IntegrityTest : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() /
               ("surfel-integrity-" + std::to_string(::getpid()) + "-" +
                ::testing::UnitTest::GetInstance()->current_test_info()->name());
        fs::remove_all(dir_);
        fs::create_directories(dir_);
        ShapeOptions o;
        o.points = 4000;
        o.normals = true;
        WritePly(SampleShape(Shape::kSphere, o), (dir_ / "sphere.ply").string());
    }
    void TearDown() override { fs::remove_all(dir_); }
    static v1::JobSpec Simplify(const std::string& cloud, int target) {
        v1::JobSpec spec;
        spec.mutable_simplify()->set_cloud_id(cloud);
        spec.mutable_simplify()->set_target(target);
        return spec;
    }
    fs::path dir_;
};

TEST_F(IntegrityTest, AFlippedByteInACloudFailsTheJobWithDataLossNamingTheBlob) {
    const std::string data = (dir_ / "data").string();
    testing::ServerProcess server(data);
    ServiceClient c(server.target());
    const std::string cloud = c.UploadFile((dir_ / "sphere.ply").string()).id();
    // Flipped in the point data (past the header), where a parser would not notice.
    const fs::path blob = fs::path(data) / "clouds" / cloud;
    FlipByte(blob, static_cast<std::streamoff>(fs::file_size(blob) - 7));
    const auto out = c.Watch(c.Submit(Simplify(cloud, 500)).id(), true, false);
    EXPECT_EQ(out.state, v1::FAILED);
    EXPECT_EQ(out.status_code, grpc::StatusCode::DATA_LOSS) << out.status_message;
    EXPECT_NE(out.status_message.find("blob " + cloud + " (cloud " + cloud + ") is corrupt: sha256 "),
              std::string::npos)
        << out.status_message;
    EXPECT_TRUE(out.bytes.empty());
}

TEST_F(IntegrityTest, AResultRecordsItsSha256AndAFlippedByteFailsItsDownload) {
    const std::string data = (dir_ / "data").string();
    testing::ServerProcess server(data);
    ServiceClient c(server.target());
    const std::string cloud = c.UploadFile((dir_ / "sphere.ply").string()).id();
    const v1::Job job = c.Submit(Simplify(cloud, 500));
    const auto out = c.Watch(job.id(), true, false);
    ASSERT_EQ(out.state, v1::SUCCEEDED) << out.status_message;
    EXPECT_EQ(out.result.sha256(), worker::Sha256Hex(out.bytes));
    EXPECT_EQ(c.GetJob(job.id()).result().sha256(), out.result.sha256());
    EXPECT_EQ(c.Download(job.id()), out.bytes);
    // Into a file, chunk by chunk (surfel download): the same bytes, no temporary left.
    const fs::path good = dir_ / "good.ply";
    EXPECT_EQ(c.DownloadToFile(job.id(), good.string()), out.bytes.size());
    {
        std::ifstream in(good, std::ios::binary);
        EXPECT_EQ(std::string(std::istreambuf_iterator<char>(in), {}), out.bytes);
    }
    EXPECT_FALSE(fs::exists(good.string() + ".tmp-surfel"));

    FlipByte(fs::path(data) / "results" / job.id(), 3);
    // A corrupt result never reaches the file: neither the output nor its temporary is left,
    // and an earlier file of that name keeps its bytes.
    for (const fs::path& target : {dir_ / "bad.ply", good}) {
        try {
            c.DownloadToFile(job.id(), target.string());
            ADD_FAILURE() << "a corrupt result was written to " << target;
        } catch (const RpcError& e) {
            EXPECT_EQ(e.status().error_code(), grpc::StatusCode::DATA_LOSS) << e.what();
        }
        EXPECT_FALSE(fs::exists(target.string() + ".tmp-surfel"));
    }
    EXPECT_FALSE(fs::exists(dir_ / "bad.ply"));
    EXPECT_EQ(fs::file_size(good), out.bytes.size());
    try {
        c.Download(job.id());
        ADD_FAILURE() << "a corrupt result was downloaded";
    } catch (const RpcError& e) {
        EXPECT_EQ(e.status().error_code(), grpc::StatusCode::DATA_LOSS) << e.what();
        EXPECT_NE(e.status().error_message().find("(result of job " + job.id() + ") is corrupt"),
                  std::string::npos)
            << e.status().error_message();
    }
    // Watch of the finished job with its result: the same check.
    try {
        const auto again = c.Watch(job.id(), true, false);
        ADD_FAILURE() << "a corrupt result was streamed: " << again.bytes.size() << " bytes";
    } catch (const RpcError& e) {
        EXPECT_EQ(e.status().error_code(), grpc::StatusCode::DATA_LOSS) << e.what();
    }
}

// The server reads and hashes the next chunk of a download while the last is sent (on its
// transfer threads; --transfer-threads 0: one chunk at a time on gRPC's): the same chunks either
// way, and on a corrupt result every chunk but the last arrives, then DATA_LOSS.
TEST_F(IntegrityTest, ADownloadReadAheadSendsTheSameChunksAndHoldsTheLastBackOnDataLoss) {
    ShapeOptions o;
    o.points = 60000;
    o.normals = true;
    WritePly(SampleShape(Shape::kTorus, o), (dir_ / "torus.ply").string());
    for (const char* threads : {"0", "2"}) {
        SCOPED_TRACE(std::string("--transfer-threads ") + threads);
        const std::string data = (dir_ / ("data-" + std::string(threads))).string();
        testing::ServerProcess server(data, {"--transfer-threads", threads});
        ServiceClient c(server.target());
        const std::string cloud = c.UploadFile((dir_ / "torus.ply").string()).id();
        const v1::Job job = c.Submit(Simplify(cloud, 50000));
        const auto out = c.Watch(job.id(), true, false);
        ASSERT_EQ(out.state, v1::SUCCEEDED) << out.status_message;
        const std::size_t chunk = 256 << 10;  // the server's download_chunk_bytes
        ASSERT_GT(out.bytes.size(), 3 * chunk);
        auto stub = v1::Surfel::NewStub(grpc::CreateChannel(server.target(), grpc::InsecureChannelCredentials()));
        // Every chunk in order, each at its offset, and the status at the end.
        const auto download = [&](std::string* bytes) {
            grpc::ClientContext ctx;
            v1::DownloadRequest req;
            req.set_job_id(job.id());
            auto reader = stub->Download(&ctx, req);
            v1::DataChunk d;
            while (reader->Read(&d)) {
                EXPECT_EQ(d.offset(), static_cast<std::int64_t>(bytes->size()));
                EXPECT_EQ(d.total_size(), static_cast<std::int64_t>(out.bytes.size()));
                EXPECT_LE(d.data().size(), chunk);
                bytes->append(d.data());
            }
            return reader->Finish();
        };
        std::string bytes;
        const grpc::Status ok = download(&bytes);
        ASSERT_TRUE(ok.ok()) << ok.error_message();
        EXPECT_EQ(bytes, out.bytes);
        FlipByte(fs::path(data) / "results" / job.id(), static_cast<std::streamoff>(chunk + 5));
        std::string cut;
        const grpc::Status lost = download(&cut);
        EXPECT_EQ(lost.error_code(), grpc::StatusCode::DATA_LOSS) << lost.error_message();
        const std::size_t last = out.bytes.size() % chunk ? out.bytes.size() % chunk : chunk;
        EXPECT_EQ(cut.size(), out.bytes.size() - last);
    }
}

}  // namespace
}  // namespace surfel
