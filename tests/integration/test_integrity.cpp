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

}  // namespace
}  // namespace surfel
