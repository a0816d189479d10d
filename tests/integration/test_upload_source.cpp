// The client's upload source (client/upload_source.h): the file mapped once, hashed from the
// mapping (a file truncated meanwhile is an error, not SIGBUS), and each Upload message built
// around a slice of it, which the server must read as the same UploadRequest.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdint>
#include <filesystem>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include "surfel/v1/surfel.pb.h"
#include "surfel/worker/sha256.h"
#include "upload_source.h"

namespace surfel {
namespace {

namespace fs = std::filesystem;
using client::FileMapping;
using client::HashMappedBytes;
using client::UploadMessage;

std::string RandomBytes(std::size_t n, unsigned seed) {
    std::mt19937 rng(seed);
    std::string s(n, '\0');
    for (char& c : s) c = static_cast<char>(rng());
    return s;
}

std::string Flatten(const grpc::ByteBuffer& buffer) {
    std::vector<grpc::Slice> slices;
    EXPECT_TRUE(buffer.Dump(&slices).ok());
    std::string out;
    for (const grpc::Slice& s : slices)
        out.append(reinterpret_cast<const char*>(s.begin()), s.size());
    return out;
}

class UploadSource : public ::testing::Test {
  protected:
    void SetUp() override {
        path_ = fs::temp_directory_path() /
                ("surfel-upload-source-" + std::to_string(::getpid()) + "-" +
                 ::testing::UnitTest::GetInstance()->current_test_info()->name());
    }
    void TearDown() override {
        if (fd_ >= 0) ::close(fd_);
        fs::remove(path_);
    }
    // Writes `bytes` to the test's file and opens it for reading.
    int Open(const std::string& bytes) {
        std::ofstream(path_, std::ios::binary)
            .write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
        fd_ = ::open(path_.c_str(), O_RDONLY | O_CLOEXEC);
        EXPECT_GE(fd_, 0);
        return fd_;
    }
    fs::path path_;
    int fd_ = -1;
};

TEST_F(UploadSource, TheMessageParsesAsTheRequestSerializedWithItsData) {
    // Lengths at the varint's byte boundaries, and the client's 256 KiB and the server's 1 MiB.
    for (const std::size_t n :
         {std::size_t{0}, std::size_t{1}, std::size_t{127}, std::size_t{128}, std::size_t{16383},
          std::size_t{16384}, std::size_t{256} << 10, std::size_t{1} << 20}) {
        for (const bool first : {true, false}) {
            SCOPED_TRACE("n=" + std::to_string(n) + (first ? " first" : " later"));
            v1::UploadRequest fields;
            fields.set_upload_id("fabc_-09");
            if (first) {
                fields.set_filename("big.ply");
                fields.set_total_size(96000201);
            }
            fields.set_write_offset(first ? 0 : 5 * 262144);
            fields.set_finish_write(n == 127);
            const std::string data = RandomBytes(n, static_cast<unsigned>(n));
            v1::UploadRequest expected = fields;
            expected.set_data(data);

            const std::string wire = Flatten(UploadMessage(fields, grpc::Slice(data)));
            v1::UploadRequest parsed;
            ASSERT_TRUE(parsed.ParseFromString(wire));
            EXPECT_EQ(parsed.SerializeAsString(), expected.SerializeAsString());
            EXPECT_EQ(wire.size(), expected.ByteSizeLong());  // the same bytes, in another order
        }
    }
}

TEST_F(UploadSource, TheHashOfTheMappingIsTheFilesSha256) {
    const std::string bytes = RandomBytes((9u << 20) + 123, 7);  // more than two 4 MiB blocks
    FileMapping* mapping = FileMapping::Map(Open(bytes), bytes.size());
    ASSERT_NE(mapping, nullptr);
    ASSERT_EQ(mapping->size(), bytes.size());
    worker::Sha256 hash;
    EXPECT_TRUE(HashMappedBytes(hash, mapping->data(), mapping->size()));
    EXPECT_EQ(hash.FinishHex(), worker::Sha256Hex(bytes));
    mapping->Unref();
}

TEST_F(UploadSource, AnEmptyFileIsNotMapped) { EXPECT_EQ(FileMapping::Map(Open(""), 0), nullptr); }

TEST_F(UploadSource, AFileTruncatedUnderTheMappingIsReportedNotABusError) {
    const std::string bytes = RandomBytes(9u << 20, 8);
    FileMapping* mapping = FileMapping::Map(Open(bytes), bytes.size());
    ASSERT_NE(mapping, nullptr);
    ASSERT_EQ(::truncate(path_.c_str(), (1 << 20) + 5), 0);
    for (int round = 0; round < 2; ++round) {  // the handler stays in place after a first catch
        worker::Sha256 hash;
        EXPECT_FALSE(HashMappedBytes(hash, mapping->data(), mapping->size()));
    }
    // Outside the hasher's guard a lost page reads as zeros (gRPC's TLS reading a slice).
    EXPECT_EQ(mapping->data()[(4 << 20) + 17], 0);
    // What is left of the file still hashes.
    worker::Sha256 head;
    EXPECT_TRUE(HashMappedBytes(head, mapping->data(), 1 << 20));
    EXPECT_EQ(head.FinishHex(), worker::Sha256Hex(std::string_view(bytes).substr(0, 1 << 20)));
    mapping->Unref();
}

TEST_F(UploadSource, ASliceKeepsTheMappingAfterItsOwnerLetsGo) {
    const std::string bytes = RandomBytes(3u << 20, 9);
    FileMapping* mapping = FileMapping::Map(Open(bytes), bytes.size());
    ASSERT_NE(mapping, nullptr);
    mapping->Populate(1 << 20, 1 << 20);
    grpc::Slice s = mapping->SliceOf(1 << 20, 300000);
    mapping->Unref();  // the slice holds the last reference now
    ::close(fd_);
    fd_ = -1;
    fs::remove(path_);
    ASSERT_EQ(s.size(), 300000u);
    EXPECT_EQ(std::string(reinterpret_cast<const char*>(s.begin()), s.size()),
              bytes.substr(1 << 20, 300000));
}

}  // namespace
}  // namespace surfel
