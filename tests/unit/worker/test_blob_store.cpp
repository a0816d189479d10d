// The blob store on both backends: a directory in a temp dir, and PostgreSQL large objects in a
// real PostgreSQL 15 cluster started by the test (tests/pg_cluster.h; skipped, with the reason,
// when Debian's postgresql binaries are absent). Then what only one backend has: the directory's
// files, and the large objects' 64-bit offsets (a sparse object past 2^31 bytes).
#include <gtest/gtest.h>
#include <libpq-fe.h>
#include <libpq/libpq-fs.h>
#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <memory>
#include <string>

#include "../../pg_cluster.h"
#include "surfel/base/error.h"
#include "surfel/worker/blob_store.h"
#include "surfel/worker/store.h"

namespace surfel::worker {
namespace {
namespace fs = std::filesystem;
using testing_pg::Cluster;

std::string TestName() {
    std::string name = ::testing::UnitTest::GetInstance()->current_test_info()->name();
    std::replace(name.begin(), name.end(), '/', '_');
    return name;
}

/// `n` bytes that differ from chunk to chunk (so a misplaced chunk changes the hash).
std::string Pattern(std::size_t n) {
    std::string s(n, '\0');
    for (std::size_t i = 0; i < n; ++i) s[i] = static_cast<char>((i * 131 + i / 977) & 0xff);
    return s;
}

/// Expects `f` to throw Error(kDataLoss) whose message contains `part`.
template <class F>
void ExpectDataLoss(F f, const std::string& part) {
    try {
        f();
        ADD_FAILURE() << "no DATA_LOSS";
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kDataLoss) << e.what();
        EXPECT_NE(std::string(e.what()).find(part), std::string::npos) << e.what();
    }
}

class BlobStoreTest : public ::testing::TestWithParam<std::string> {
protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() /
               ("surfel-blob-test-" + std::to_string(::getpid()) + "-" + TestName());
        fs::remove_all(dir_);
        if (GetParam() == "postgres") {
            Cluster& c = Cluster::Get();
            if (!c.installed()) GTEST_SKIP() << "PostgreSQL not available: " << c.why_not();
            ASSERT_TRUE(c.ok()) << "PostgreSQL did not start: " << c.why_not();
            url_ = c.NewSchema(TestName());
            // The store applies the migrations (table blobs); chunks of 1000 bytes, so that
            // every test crosses chunk boundaries.
            records_ = OpenStore(url_, dir_.string());
            blobs_ = OpenLargeObjectBlobStore(url_, 1000);
        } else {
            blobs_ = std::make_unique<DirBlobStore>(dir_.string());
        }
    }
    void TearDown() override {
        blobs_.reset();
        records_.reset();
        std::error_code ec;
        fs::remove_all(dir_, ec);
    }
    /// Changes one byte of a stored blob behind the store's back (the disk, or the database).
    void FlipByte(const std::string& key, std::uint64_t offset) {
        if (GetParam() == "postgres") {
            const std::string oid =
                Cluster::Exec(url_, "SELECT oid FROM blobs WHERE key = '" + key + "'");
            PGconn* c = PQconnectdb(url_.c_str());
            ASSERT_EQ(PQstatus(c), CONNECTION_OK);
            PQclear(PQexec(c, "BEGIN"));
            const int fd = lo_open(c, static_cast<Oid>(std::stoul(oid)), INV_READ | INV_WRITE);
            ASSERT_GE(fd, 0) << PQerrorMessage(c);
            char b = 0;
            ASSERT_EQ(lo_lseek64(c, fd, static_cast<pg_int64>(offset), SEEK_SET),
                      static_cast<pg_int64>(offset));
            ASSERT_EQ(lo_read(c, fd, &b, 1), 1);
            b ^= 0x01;
            lo_lseek64(c, fd, static_cast<pg_int64>(offset), SEEK_SET);
            ASSERT_EQ(lo_write(c, fd, &b, 1), 1);
            lo_close(c, fd);
            PQclear(PQexec(c, "COMMIT"));
            PQfinish(c);
        } else {
            std::fstream f(dir_ / key, std::ios::in | std::ios::out | std::ios::binary);
            f.seekg(static_cast<std::streamoff>(offset));
            char b = static_cast<char>(f.get());
            f.seekp(static_cast<std::streamoff>(offset));
            f.put(static_cast<char>(b ^ 0x01));
        }
    }

    fs::path dir_;
    std::string url_;
    std::unique_ptr<Store> records_;
    std::unique_ptr<BlobStore> blobs_;
};

INSTANTIATE_TEST_SUITE_P(Backends, BlobStoreTest, ::testing::Values("dir", "postgres"),
                         [](const auto& p) { return p.param; });

TEST_P(BlobStoreTest, PutBytesReadsBackVerifiedAndRemoves) {
    const std::string bytes = Pattern(3500);
    const std::string sha = Sha256Hex(bytes);
    const std::string key = CloudBlobKey(sha);
    EXPECT_FALSE(blobs_->Exists(key));
    EXPECT_EQ(blobs_->Open(key), nullptr);
    blobs_->PutBytes(key, bytes, sha);
    ASSERT_TRUE(blobs_->Size(key));
    EXPECT_EQ(*blobs_->Size(key), 3500u);
    EXPECT_EQ(ReadVerified(*blobs_, key, sha, "cloud " + sha), bytes);
    // A ranged read: Seek, then the tail.
    auto in = blobs_->Open(key);
    ASSERT_TRUE(in);
    in->Seek(3000);
    std::string tail(600, '\0');
    std::size_t got = 0;
    for (std::size_t n; (n = in->Read(tail.data() + got, tail.size() - got)) > 0;) got += n;
    EXPECT_EQ(tail.substr(0, got), bytes.substr(3000));
    in.reset();
    EXPECT_TRUE(blobs_->Remove(key));
    EXPECT_FALSE(blobs_->Remove(key));
    EXPECT_FALSE(blobs_->Exists(key));
    try {
        ReadVerified(*blobs_, key, sha, "cloud " + sha);
        ADD_FAILURE() << "read a removed blob";
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kNotFound) << e.what();
    }
}

TEST_P(BlobStoreTest, ListsEveryBlobWithItsSizeSortedByKey) {
    EXPECT_TRUE(blobs_->List().empty());
    blobs_->PutBytes(ResultBlobKey("j1"), Pattern(10), Sha256Hex(Pattern(10)));
    blobs_->PutBytes(CloudBlobKey("c1"), Pattern(20), Sha256Hex(Pattern(20)));
    using Entry = std::pair<std::string, std::uint64_t>;
    EXPECT_EQ(blobs_->List(), (std::vector<Entry>{{"clouds/c1", 20}, {"results/j1", 10}}));
    blobs_->Remove(CloudBlobKey("c1"));
    EXPECT_EQ(blobs_->List(), (std::vector<Entry>{{"results/j1", 10}}));
}

TEST_P(BlobStoreTest, PutFileConsumesTheFileAndReplacesAnOldBlob) {
    const std::string a = Pattern(2100), b = Pattern(10);
    fs::create_directories(dir_ / "uploads");
    const fs::path part = dir_ / "uploads" / "u.part";
    std::ofstream(part, std::ios::binary) << a;
    blobs_->PutFile(ResultBlobKey("j1"), part.string(), Sha256Hex(a));
    EXPECT_FALSE(fs::exists(part));
    EXPECT_EQ(ReadVerified(*blobs_, ResultBlobKey("j1"), Sha256Hex(a), "result of job j1"), a);
    const std::string old_oid =
        GetParam() == "postgres"
            ? Cluster::Exec(url_, "SELECT oid FROM blobs WHERE key = 'results/j1'")
            : "";
    blobs_->PutBytes(ResultBlobKey("j1"), b, Sha256Hex(b));  // a rerun of the job
    EXPECT_EQ(ReadVerified(*blobs_, ResultBlobKey("j1"), Sha256Hex(b), "result of job j1"), b);
    if (GetParam() == "postgres")  // the replaced large object was unlinked with it
        EXPECT_EQ(Cluster::Exec(url_, "SELECT COUNT(*) FROM pg_largeobject_metadata WHERE oid = " +
                                          old_oid),
                  "0");
}

TEST_P(BlobStoreTest, AFlippedByteIsDataLossNamingTheBlobAndItsOwner) {
    const std::string bytes = Pattern(2500);
    const std::string sha = Sha256Hex(bytes);
    blobs_->PutBytes(CloudBlobKey(sha), bytes, sha);
    FlipByte(CloudBlobKey(sha), 1234);
    ExpectDataLoss([&] { ReadVerified(*blobs_, CloudBlobKey(sha), sha, "cloud " + sha); },
                   "blob " + sha + " (cloud " + sha + ") is corrupt: sha256 ");
    // Streaming readers fail before handing out the last byte.
    VerifyingReader in(blobs_->Open(CloudBlobKey(sha)), sha, "cloud " + sha);
    std::string buf(1000, '\0');
    ExpectDataLoss(
        [&] {
            while (in.Read(buf.data(), buf.size()) > 0) {
            }
        },
        "is corrupt");
    EXPECT_FALSE(in.verified());
}

TEST_P(BlobStoreTest, AnEmptyBlobIsCheckedToo) {
    const std::string sha = Sha256Hex("");
    blobs_->PutBytes(ResultBlobKey("empty"), "", sha);
    EXPECT_EQ(ReadVerified(*blobs_, ResultBlobKey("empty"), sha, "result of job empty"), "");
    ExpectDataLoss(
        [&] { ReadVerified(*blobs_, ResultBlobKey("empty"), Sha256Hex("x"), "result of job e"); },
        "(result of job e) is corrupt");
}

// ---- the directory backend's files

TEST(DirBlobStore, KeepsTodaysLayoutAndLeavesNoTempFiles) {
    const fs::path dir = fs::temp_directory_path() / ("surfel-blob-dir-" + std::to_string(getpid()));
    fs::remove_all(dir);
    {
        DirBlobStore blobs(dir.string());
        blobs.PutBytes(ResultBlobKey("j9"), "abc", Sha256Hex("abc"));
        EXPECT_EQ(blobs.PathOf(ResultBlobKey("j9")), dir.string() + "/results/j9");
        std::ifstream in(dir / "results" / "j9");
        EXPECT_EQ(std::string(std::istreambuf_iterator<char>(in), {}), "abc");
        int entries = 0;
        for ([[maybe_unused]] const auto& e : fs::directory_iterator(dir / "results")) ++entries;
        EXPECT_EQ(entries, 1);
    }
    fs::remove_all(dir);
}

// ---- large objects: 64-bit offsets, recorded sizes, the flag

class LargeObjectTest : public ::testing::Test {
protected:
    void SetUp() override {
        Cluster& c = Cluster::Get();
        if (!c.installed()) GTEST_SKIP() << "PostgreSQL not available: " << c.why_not();
        ASSERT_TRUE(c.ok()) << "PostgreSQL did not start: " << c.why_not();
        url_ = c.NewSchema(TestName());
        dir_ = fs::temp_directory_path() / ("surfel-lo-test-" + std::to_string(getpid()));
        records_ = OpenStore(url_, dir_.string(), "postgres");
    }
    void TearDown() override {
        records_.reset();
        std::error_code ec;
        fs::remove_all(dir_, ec);
    }
    std::string url_;
    fs::path dir_;
    std::unique_ptr<Store> records_;
};

TEST_F(LargeObjectTest, ASparseObjectPast2GiBIsReadAtItsTailWith64BitOffsets) {
    // Written with libpq's lo_lseek64 past 2^31 (sparse: nothing before the tail is stored),
    // recorded in `blobs`, then opened and read through the store, whose Open measures the
    // object with lo_lseek64(SEEK_END) / lo_tell64 and whose Seek is lo_lseek64.
    constexpr std::uint64_t kOffset = (1ull << 31) + 5;
    const std::string tail = "tail past 2 GiB";
    PGconn* c = PQconnectdb(url_.c_str());
    ASSERT_EQ(PQstatus(c), CONNECTION_OK) << PQerrorMessage(c);
    PQclear(PQexec(c, "BEGIN"));
    const Oid oid = lo_creat(c, INV_READ | INV_WRITE);
    const int fd = lo_open(c, oid, INV_WRITE);
    ASSERT_GE(fd, 0);
    ASSERT_EQ(lo_lseek64(c, fd, static_cast<pg_int64>(kOffset), SEEK_SET),
              static_cast<pg_int64>(kOffset));
    ASSERT_EQ(lo_write(c, fd, tail.data(), tail.size()), static_cast<int>(tail.size()));
    EXPECT_EQ(lo_tell64(c, fd), static_cast<pg_int64>(kOffset + tail.size()));
    lo_close(c, fd);
    PQclear(PQexec(c, "COMMIT"));
    PQfinish(c);
    const std::uint64_t size = kOffset + tail.size();
    Cluster::Exec(url_, "INSERT INTO blobs (key, oid, size, sha256, created_ms) VALUES "
                        "('results/big', " + std::to_string(oid) + ", " + std::to_string(size) +
                        ", 'unknown', 0)");
    BlobStore& blobs = records_->blobs();
    ASSERT_EQ(blobs.Size("results/big"), size);
    auto in = blobs.Open("results/big");  // its length checked with lo_lseek64 / lo_tell64
    ASSERT_TRUE(in);
    EXPECT_EQ(in->size(), size);
    in->Seek(kOffset - 3);
    std::string got(64, '\0');
    std::size_t n = 0;
    for (std::size_t k; (k = in->Read(got.data() + n, got.size() - n)) > 0;) n += k;
    EXPECT_EQ(got.substr(0, n), std::string(3, '\0') + tail);  // a hole reads as zeros
    in.reset();
    // A recorded size that the object does not have is DATA_LOSS at open.
    Cluster::Exec(url_, "UPDATE blobs SET size = size + 1 WHERE key = 'results/big'");
    ExpectDataLoss([&] { blobs.Open("results/big"); }, "has " + std::to_string(size) + " bytes");
    EXPECT_TRUE(blobs.Remove("results/big"));
    EXPECT_EQ(Cluster::Exec(url_, "SELECT COUNT(*) FROM pg_largeobject_metadata WHERE oid = " +
                                      std::to_string(oid)),
              "0");
}

TEST_F(LargeObjectTest, DeleteCloudUnlinksItsLargeObject) {
    const std::string bytes = Pattern(5000);
    const std::string sha = Sha256Hex(bytes);
    records_->blobs().PutBytes(CloudBlobKey(sha), bytes, sha);
    v1::Cloud cloud;
    cloud.set_id(sha);
    records_->PutCloud(cloud);
    const std::string oid =
        Cluster::Exec(url_, "SELECT oid FROM blobs WHERE key = 'clouds/" + sha + "'");
    EXPECT_TRUE(records_->DeleteCloud(sha));
    EXPECT_FALSE(records_->blobs().Exists(CloudBlobKey(sha)));
    EXPECT_EQ(Cluster::Exec(url_, "SELECT COUNT(*) FROM pg_largeobject_metadata WHERE oid = " + oid),
              "0");
}

// The directory renames the file it was given (hashed while it was received); large objects copy
// it, and check the copy.
TEST_F(LargeObjectTest, PutFileWhoseBytesDoNotMatchTheirHashStoresNothing) {
    const fs::path part = dir_ / "bad.part";
    fs::create_directories(dir_);
    std::ofstream(part, std::ios::binary) << "not these bytes";
    const std::string claimed = Sha256Hex("other bytes");
    ExpectDataLoss([&] { records_->blobs().PutFile(CloudBlobKey(claimed), part.string(), claimed); },
                   "is corrupt");
    EXPECT_FALSE(records_->blobs().Exists(CloudBlobKey(claimed)));
}

TEST(BlobsFlag, PostgresNeedsAPostgresStoreAndDirNeedsAPath) {
    const fs::path dir = fs::temp_directory_path() / ("surfel-blob-flag-" + std::to_string(getpid()));
    try {
        OpenStore("sqlite", dir.string(), "postgres");
        ADD_FAILURE() << "opened large objects on SQLite";
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
        EXPECT_NE(std::string(e.what()).find("--blobs postgres: needs --store postgres://"),
                  std::string::npos)
            << e.what();
    }
    EXPECT_EQ(BlobDirFromFlag("dir:/x", "d"), "/x");
    EXPECT_EQ(BlobDirFromFlag("postgres", "d"), "d");
    EXPECT_EQ(BlobDirFromFlag("", "d"), "d");
    try {
        BlobDirFromFlag("s3://bucket", "d");
        ADD_FAILURE() << "accepted s3://";
    } catch (const Error& e) {
        EXPECT_NE(std::string(e.what()).find("--blobs s3://bucket: expected dir:PATH or postgres"),
                  std::string::npos)
            << e.what();
    }
    fs::remove_all(dir);
}

}  // namespace
}  // namespace surfel::worker
