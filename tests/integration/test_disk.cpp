// Disk and retention (issue 18.3, docs/retention.md) through the real surfel-server:
//  - --max-disk-gb evicts the least recently used results and clouds, persisted across a
//    restart; an evicted blob answers NOT_FOUND saying "evicted"; an identical submission runs
//    again when its result was evicted; an upload larger than the quota is refused, evicting
//    nothing;
//  - --ttl: an unused cloud and result expire, saying so;
//  - DeleteCloud of a cloud a queued or running job needs: FAILED_PRECONDITION naming the job;
//  - a real full filesystem (a 1 MiB tmpfs): an upload that does not fit and a result write
//    that hits ENOSPC are RESOURCE_EXHAUSTED, no half-written file stays, the server keeps
//    serving, and what was acknowledged before is intact (SHA-256);
//  - --max-upload-inflight-mb: bytes received and not yet stored, over all upload calls;
//  - --upload-ttl: the part file of an abandoned upload goes, never one an upload call holds.
#include <fcntl.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <sys/mount.h>
#include <sys/statvfs.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>
#include <thread>
#include <tuple>

#include "server_process.h"
#include "service_client.h"
#include "surfel/base/shapes.h"
#include "surfel/io/file_bytes.h"
#include "surfel/io/ply.h"
#include "surfel/v1/surfel.grpc.pb.h"
#include "surfel/worker/sha256.h"

namespace surfel {
namespace {

namespace fs = std::filesystem;
using client::RpcError;
using client::ServiceClient;

v1::JobSpec Simplify(const std::string& cloud, int target) {
    v1::JobSpec spec;
    spec.mutable_simplify()->set_cloud_id(cloud);
    spec.mutable_simplify()->set_target(target);
    return spec;
}

/// The status of `fn`'s RpcError (OK when it did not throw).
template <typename Fn>
grpc::Status StatusOf(Fn&& fn) {
    try {
        fn();
    } catch (const RpcError& e) {
        return e.status();
    }
    return grpc::Status::OK;
}

/// Every file under `dir` whose name holds ".tmp-" or ends in ".part".
std::vector<std::string> LeftoverTemps(const fs::path& dir) {
    std::vector<std::string> out;
    std::error_code ec;
    for (fs::recursive_directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
        const std::string name = it->path().filename().string();
        if (name.find(".tmp-") != std::string::npos || name.ends_with(".part"))
            out.push_back(it->path().string());
    }
    return out;
}

class DiskTest : public ::testing::Test {
  protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() /
               ("surfel-disk-" + std::to_string(::getpid()) + "-" +
                ::testing::UnitTest::GetInstance()->current_test_info()->name());
        fs::remove_all(dir_);
        fs::create_directories(dir_);
    }
    void TearDown() override {
        if (mounted_) ::umount2(mnt_.c_str(), MNT_DETACH);
        fs::remove_all(dir_);
    }
    /// A sphere (or box) PLY of `points` points with normals; distinct seeds give distinct bytes.
    std::string Cloud(const std::string& name, std::size_t points, std::uint64_t seed,
                      Shape shape = Shape::kSphere) {
        ShapeOptions o;
        o.points = points;
        o.normals = true;
        o.seed = seed;
        const std::string path = (dir_ / name).string();
        WritePly(SampleShape(shape, o), path);
        return path;
    }
    /// Mounts a tmpfs of `bytes` at dir_/mnt; false (and why) when mount is not permitted.
    bool MountTmpfs(std::size_t bytes, std::string* why) {
        mnt_ = (dir_ / "mnt").string();
        fs::create_directories(mnt_);
        const std::string opts = "size=" + std::to_string(bytes);
        if (::mount("tmpfs", mnt_.c_str(), "tmpfs", 0, opts.c_str()) != 0) {
            *why =
                std::string("mount -t tmpfs -o ") + opts + " " + mnt_ + ": " + std::strerror(errno);
            return false;
        }
        mounted_ = true;
        return true;
    }
    fs::path dir_;
    std::string mnt_;
    bool mounted_ = false;
};

TEST_F(DiskTest, QuotaEvictsLeastRecentlyUsedFirstAndSaysSoAcrossARestart) {
    const std::string data = (dir_ / "data").string();
    const std::string a_path = Cloud("a.ply", 4000, 1), b_path = Cloud("b.ply", 4000, 2);
    const std::string c_path = Cloud("c.ply", 4000, 3);
    std::string a, b, j1, j2, r1_sha;
    std::uint64_t used = 0;
    {
        // Without a quota: A, job 1 on A, B, job 2 on A; so the least recently used are, in
        // order: job 1's result, B, A (read by job 2), job 2's result.
        testing::ServerProcess server(data);
        ServiceClient c(server.target());
        a = c.UploadFile(a_path).id();
        j1 = c.Submit(Simplify(a, 300)).id();
        ASSERT_EQ(c.Watch(j1, false, false).state, v1::SUCCEEDED);
        b = c.UploadFile(b_path).id();
        j2 = c.Submit(Simplify(a, 400)).id();
        ASSERT_EQ(c.Watch(j2, false, false).state, v1::SUCCEEDED);
        r1_sha = c.GetJob(j1).result().sha256();
        used = fs::file_size(a_path) + fs::file_size(b_path) + c.GetJob(j1).result().size_bytes() +
               c.GetJob(j2).result().size_bytes();
        server.Kill(SIGTERM);
    }
    // Restarted with a quota of what is stored plus 1000 bytes: C (as big as B) needs job 1's
    // result and B to go; the usage times were kept across the restart.
    char quota[32];
    std::snprintf(quota, sizeof quota, "%.9f", static_cast<double>(used + 1000) / 1e9);
    testing::ServerProcess server(data, {"--max-disk-gb", quota});
    ServiceClient c(server.target());
    const std::string cc = c.UploadFile(c_path).id();
    EXPECT_EQ(c.GetCloud(cc).id(), cc);
    EXPECT_EQ(c.GetCloud(a).id(), a);
    EXPECT_FALSE(c.Download(j2).empty());

    const grpc::Status gone_b = StatusOf([&] { c.GetCloud(b); });
    EXPECT_EQ(gone_b.error_code(), grpc::StatusCode::NOT_FOUND);
    EXPECT_NE(gone_b.error_message().find("cloud " + b + " was evicted at "), std::string::npos)
        << gone_b.error_message();
    EXPECT_NE(gone_b.error_message().find("least recently used"), std::string::npos)
        << gone_b.error_message();
    EXPECT_FALSE(fs::exists(fs::path(data) / "clouds" / b));
    const grpc::Status submit_b = StatusOf([&] { c.Submit(Simplify(b, 300)); });
    EXPECT_EQ(submit_b.error_code(), grpc::StatusCode::NOT_FOUND);
    EXPECT_NE(submit_b.error_message().find("was evicted"), std::string::npos)
        << submit_b.error_message();

    const grpc::Status gone_r1 = StatusOf([&] { c.Download(j1); });
    EXPECT_EQ(gone_r1.error_code(), grpc::StatusCode::NOT_FOUND);
    EXPECT_NE(gone_r1.error_message().find("result of job " + j1 + " was evicted at "),
              std::string::npos)
        << gone_r1.error_message();
    EXPECT_EQ(c.GetJob(j1).state(), v1::SUCCEEDED);  // the record stays; only the bytes went
    const auto watched = c.Watch(j1, true, false);   // Watch with the result says it too
    EXPECT_EQ(watched.status_code, grpc::StatusCode::NOT_FOUND);
    EXPECT_NE(watched.status_message.find("result of job " + j1 + " was evicted at "),
              std::string::npos)
        << watched.status_message;
    // An identical submission is not answered by the job whose result is gone: it runs again
    // and gives the same bytes.
    const v1::Job again = c.Submit(Simplify(a, 300));
    EXPECT_NE(again.id(), j1);
    EXPECT_FALSE(again.reused());
    const auto out = c.Watch(again.id(), true, false);
    ASSERT_EQ(out.state, v1::SUCCEEDED) << out.status_message;
    EXPECT_EQ(worker::Sha256Hex(out.bytes), r1_sha);

    // Larger than the whole quota: refused at its first chunk past it, nothing evicted, no
    // part file left.
    const std::string big = Cloud("big.ply", 30000, 9);
    const grpc::Status refused = StatusOf([&] { c.UploadFile(big); });
    EXPECT_EQ(refused.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
    EXPECT_NE(refused.error_message().find("--max-disk-gb"), std::string::npos)
        << refused.error_message();
    EXPECT_EQ(c.GetCloud(a).id(), a);
    EXPECT_EQ(c.GetCloud(cc).id(), cc);
    EXPECT_EQ(LeftoverTemps(data), std::vector<std::string>{});
}

TEST_F(DiskTest, TimeToLiveEndsUnusedResultsAndClouds) {
    const std::string data = (dir_ / "data").string();
    // The default tenant "" gets 1 s; the flag repeats (another tenant's entry).
    testing::ServerProcess server(
        data, {"--ttl", "1s", "--ttl", "nobody=7d", "--retention-sweep-s", "0.2"});
    ServiceClient c(server.target());
    const std::string a = c.UploadFile(Cloud("a.ply", 4000, 1)).id();
    const v1::Job job = c.Submit(Simplify(a, 300));
    ASSERT_EQ(c.Watch(job.id(), false, false).state, v1::SUCCEEDED);
    // 1 s of TTL plus a sweep every 0.2 s; the result was used after the cloud (the job read
    // the cloud first), so it may go a sweep later. Polled on disk: a download would use it.
    const fs::path result_file = fs::path(data) / "results" / job.id();
    for (int i = 0; i < 100 && fs::exists(result_file); ++i)
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
    const grpc::Status gone = StatusOf([&] { c.GetCloud(a); });
    const grpc::Status result = StatusOf([&] { c.Download(job.id()); });
    EXPECT_EQ(gone.error_code(), grpc::StatusCode::NOT_FOUND);
    EXPECT_NE(gone.error_message().find("time-to-live 1s of tenant ''"), std::string::npos)
        << gone.error_message();
    EXPECT_EQ(result.error_code(), grpc::StatusCode::NOT_FOUND);
    EXPECT_NE(result.error_message().find("was evicted"), std::string::npos)
        << result.error_message();
    EXPECT_FALSE(fs::exists(fs::path(data) / "clouds" / a));
    EXPECT_FALSE(fs::exists(fs::path(data) / "results" / job.id()));
}

TEST_F(DiskTest, DeleteCloudOfACloudInUseIsRefusedNamingTheJob) {
    const std::string data = (dir_ / "data").string();
    testing::ServerProcess server(data, {"--workers", "1"});
    ServiceClient c(server.target());
    const std::string a = c.UploadFile(Cloud("a.ply", 60000, 1)).id();
    std::vector<std::string> jobs;
    for (int target = 1000; target < 1008; ++target)
        jobs.push_back(c.Submit(Simplify(a, target)).id());
    // One worker, eight jobs of ~60k points each: the last ones are still queued now.
    const grpc::Status refused = StatusOf([&] { c.DeleteCloud(a); });
    EXPECT_EQ(refused.error_code(), grpc::StatusCode::FAILED_PRECONDITION)
        << refused.error_message();
    bool names_one = false;
    for (const std::string& j : jobs)
        names_one |= refused.error_message().find("input of job " + j + " (") != std::string::npos;
    EXPECT_TRUE(names_one) << refused.error_message();
    EXPECT_EQ(c.GetCloud(a).id(), a);
    for (const std::string& j : jobs) c.Cancel(j);
    for (const std::string& j : jobs) c.Watch(j, false, false);  // until each is final
    EXPECT_TRUE(c.DeleteCloud(a));
    const grpc::Status gone = StatusOf([&] { c.GetCloud(a); });
    EXPECT_EQ(gone.error_code(), grpc::StatusCode::NOT_FOUND);
    EXPECT_EQ(gone.error_message().find("evicted"), std::string::npos) << gone.error_message();
}

TEST_F(DiskTest, AFullFilesystemIsResourceExhaustedLeavesNoHalfFileAndLosesNothing) {
    std::string why;
    if (!MountTmpfs(1 << 20, &why)) GTEST_SKIP() << "cannot test a full disk: " << why;
    // Blobs and part files on the 1 MiB tmpfs; the database beside it (see docs/retention.md).
    const std::string data = mnt_;
    const std::string db = (dir_ / "db" / "surfel.db").string();
    testing::ServerProcess server(data, {"--store", "sqlite:" + db});
    ServiceClient c(server.target());
    const std::string s1 = c.UploadFile(Cloud("s1.ply", 4000, 1)).id();  // ~96 KB

    // ~2.4 MB: cannot fit in 1 MiB.
    const std::string big = Cloud("big.ply", 100000, 2);
    const grpc::Status full = StatusOf([&] { c.UploadFile(big); });
    EXPECT_EQ(full.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED) << full.error_message();
    EXPECT_NE(full.error_message().find("No space left on device"), std::string::npos)
        << full.error_message();
    EXPECT_EQ(LeftoverTemps(data), std::vector<std::string>{});
    EXPECT_EQ(fs::exists(fs::path(data) / "clouds" / worker::Sha256Hex(ReadFileBytes(big))), false);

    // Still serving: the discarded part file gave its space back.
    const std::string s2 = c.UploadFile(Cloud("s2.ply", 4000, 3, Shape::kBox)).id();
    const v1::Job j1 = c.Submit(Simplify(s1, 500));
    const auto out1 = c.Watch(j1.id(), true, false);
    ASSERT_EQ(out1.state, v1::SUCCEEDED) << out1.status_message;

    // Fill the filesystem, then give back 8 KiB: a result of ~48 KB hits ENOSPC.
    const std::string filler = (fs::path(data) / "filler").string();
    {
        const int fd = ::open(filler.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
        ASSERT_GE(fd, 0);
        const std::string block(4096, 'f');
        off_t size = 0;
        while (::write(fd, block.data(), block.size()) == static_cast<ssize_t>(block.size()))
            size += static_cast<off_t>(block.size());
        ASSERT_EQ(::ftruncate(fd, size - 8192), 0);
        ::close(fd);
    }
    const v1::Job j2 = c.Submit(Simplify(s2, 2000));
    const auto out2 = c.Watch(j2.id(), true, false);
    EXPECT_EQ(out2.state, v1::FAILED);
    EXPECT_EQ(out2.status_code, grpc::StatusCode::RESOURCE_EXHAUSTED) << out2.status_message;
    EXPECT_NE(out2.status_message.find("storing blob results/" + j2.id()), std::string::npos)
        << out2.status_message;
    EXPECT_NE(out2.status_message.find("No space left on device"), std::string::npos)
        << out2.status_message;
    EXPECT_EQ(LeftoverTemps(data), std::vector<std::string>{});
    EXPECT_FALSE(fs::exists(fs::path(data) / "results" / j2.id()));
    EXPECT_EQ(c.GetCloud(s1).id(), s1);  // serving

    // Space freed: the same job runs again (a failed job is not reused) and succeeds.
    fs::remove(filler);
    const v1::Job j3 = c.Submit(Simplify(s2, 2000));
    EXPECT_NE(j3.id(), j2.id());
    const auto out3 = c.Watch(j3.id(), true, false);
    ASSERT_EQ(out3.state, v1::SUCCEEDED) << out3.status_message;
    EXPECT_EQ(worker::Sha256Hex(out3.bytes), out3.result.sha256());

    // Nothing acknowledged was lost: the clouds' bytes hash to their ids, the first result to
    // its recorded SHA-256.
    for (const std::string& id : {s1, s2})
        EXPECT_EQ(worker::Sha256Hex(ReadFileBytes((fs::path(data) / "clouds" / id).string())), id);
    EXPECT_EQ(worker::Sha256Hex(c.Download(j1.id())), c.GetJob(j1.id()).result().sha256());
    server.Kill(SIGTERM);
}

// An Upload call left open after one chunk to upload id "held-open" (no finish_write): it holds
// that id, and its bytes count as in flight, until Close().
struct HeldUpload {
    grpc::ClientContext ctx;
    v1::Cloud response;
    std::unique_ptr<grpc::ClientWriter<v1::UploadRequest>> writer;
    // Opens the call and sends `bytes` bytes of `fill`; whether the chunk went out.
    bool Open(v1::Surfel::Stub& stub, std::size_t bytes, char fill) {
        writer = stub.Upload(&ctx, &response);
        v1::UploadRequest chunk;
        chunk.set_upload_id("held-open");
        chunk.set_filename("x.ply");
        chunk.set_data(std::string(bytes, fill));
        return writer->Write(chunk);
    }
    void Close() {
        ctx.TryCancel();
        writer->Finish();
    }
};

TEST_F(DiskTest, UploadBytesInFlightAreCappedAndTheHeldBytesKeptForAResume) {
    const std::string data = (dir_ / "data").string();
    // 0.25 MiB in flight at most; the sphere file is ~96 KB.
    testing::ServerProcess server(data, {"--max-upload-inflight-mb", "0.25"});
    ServiceClient c(server.target());
    const std::string sphere = Cloud("s.ply", 4000, 1);
    // One call holds 200 KB received and not stored (no finish_write).
    auto stub = v1::Surfel::NewStub(
        grpc::CreateChannel(server.target(), grpc::InsecureChannelCredentials()));
    HeldUpload held;
    ASSERT_TRUE(held.Open(*stub, 200 << 10, 'x'));
    std::int64_t committed = 0;
    // Polled until the whole chunk is on disk (the part file's size grows during the write).
    for (int i = 0; i < 300 && committed != (200 << 10); ++i) {
        v1::QueryUploadRequest q;
        q.set_upload_id("held-open");
        grpc::ClientContext qc;
        v1::QueryUploadResponse r;
        if (stub->QueryUpload(&qc, q, &r).ok()) committed = r.committed_size();
        if (committed != (200 << 10)) std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    ASSERT_EQ(committed, 200 << 10);
    // 200 KB + 96 KB > 256 KiB: refused, saying which limit.
    const grpc::Status refused = StatusOf([&] { c.UploadFile(sphere); });
    EXPECT_EQ(refused.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
    EXPECT_NE(refused.error_message().find("--max-upload-inflight-mb"), std::string::npos)
        << refused.error_message();
    held.Close();
    // The held call ended: its bytes stay on disk for a resume but are no longer in flight.
    bool stored = false;
    for (int i = 0; i < 100 && !stored; ++i) {
        stored = StatusOf([&] { c.UploadFile(sphere); }).ok();
        if (!stored) std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    EXPECT_TRUE(stored);
    v1::QueryUploadRequest q;
    q.set_upload_id("held-open");
    grpc::ClientContext qc;
    v1::QueryUploadResponse r;
    ASSERT_TRUE(stub->QueryUpload(&qc, q, &r).ok());
    EXPECT_EQ(r.committed_size(), 200 << 10);
}

/// The committed size the server reports for `upload_id` (QueryUpload).
std::int64_t Committed(v1::Surfel::Stub& stub, const std::string& upload_id) {
    v1::QueryUploadRequest q;
    q.set_upload_id(upload_id);
    grpc::ClientContext qc;
    v1::QueryUploadResponse r;
    const grpc::Status s = stub.QueryUpload(&qc, q, &r);
    EXPECT_TRUE(s.ok()) << s.error_message();
    return r.committed_size();
}

/// Opens an Upload call to `id` and sends `chunks` chunks of `chunk` bytes of `fill` from
/// `offset` on at once, without finish_write; the writer stays open.
std::unique_ptr<grpc::ClientWriter<v1::UploadRequest>> SendChunks(
    v1::Surfel::Stub& stub, grpc::ClientContext& ctx, v1::Cloud& response, const std::string& id,
    std::uint64_t offset, int chunks, std::size_t chunk, char fill) {
    auto writer = stub.Upload(&ctx, &response);
    for (int i = 0; i < chunks; ++i) {
        v1::UploadRequest r;
        r.set_upload_id(id);
        r.set_filename("x.ply");
        r.set_write_offset(static_cast<std::int64_t>(offset + i * chunk));
        r.set_data(std::string(chunk, fill));
        if (!writer->Write(r)) break;  // the server ended the call
    }
    return writer;
}

/// One upload call of `chunks` chunks of `chunk` bytes to a new id, ended without finish_write:
/// FAILED_PRECONDITION ("incomplete") when every chunk was taken, else why not.
grpc::Status Probe(v1::Surfel::Stub& stub, const std::string& id, int chunks, std::size_t chunk) {
    grpc::ClientContext ctx;
    v1::Cloud response;
    auto writer = SendChunks(stub, ctx, response, id, 0, chunks, chunk, 'p');
    writer->WritesDone();
    return writer->Finish();
}

// The gRPC reader runs up to 2 MiB ahead of the writer (--transfer-threads, bench/README.md
// "Session 14 (upload helper)"): those chunks are held in memory and count as in flight from the
// moment the reader takes them, not only once appended. The writer is held up long enough to look:
// a resumed upload's committed bytes (here a sparse 1.5 GiB part file, about a second of SHA-256)
// are hashed before its first chunk is appended, while the reader goes on reading. (A probe that
// raced the reader would take the room first and the read-ahead would be refused instead, so the
// probe waits 200 ms for the server to read 1 MiB on loopback.)
TEST_F(DiskTest, ChunksReadAheadOfTheWriterCountInFlightAndPastTheCapAreRefused) {
    const std::string data = (dir_ / "data").string();
    const fs::path uploads = fs::path(data) / "uploads";
    fs::create_directories(uploads);
    constexpr std::uint64_t kHeld = 1536ull << 20;
    constexpr std::size_t kChunk = 256 << 10;
    {
        std::ofstream(uploads / "big.part").close();
        fs::resize_file(uploads / "big.part", kHeld);  // a hole: no disk, hashed at CPU speed
    }
    // In flight at most the part file + 1.5 MiB.
    testing::ServerProcess server(data, {"--max-upload-inflight-mb", "1537.5", "--transfer-threads",
                                         "2", "--ingest-threads", "2"});
    auto stub = v1::Surfel::NewStub(
        grpc::CreateChannel(server.target(), grpc::InsecureChannelCredentials()));

    // 1 MiB more to "big" while its first 1.5 GiB are hashed: part file + 1 MiB in flight, so a
    // 768 KiB upload beside it does not fit, though none of the four chunks is appended yet.
    {
        grpc::ClientContext ctx;
        v1::Cloud response;
        auto big = SendChunks(*stub, ctx, response, "big", kHeld, 4, kChunk, 'b');
        std::this_thread::sleep_for(std::chrono::milliseconds(200));
        const grpc::Status probe = Probe(*stub, "probe", 1, 3 * kChunk);
        // Checked after the probe: the committed size only grows.
        const std::int64_t committed = Committed(*stub, "big");
        ASSERT_EQ(committed, static_cast<std::int64_t>(kHeld)) << "the hash ended before the probe";
        EXPECT_EQ(probe.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED)
            << "a 768 KiB upload was taken beside 1 MiB read ahead and not counted: "
            << probe.error_message();
        EXPECT_NE(probe.error_message().find("--max-upload-inflight-mb"), std::string::npos)
            << probe.error_message();
        // The four chunks are appended once the hash is done; nothing read ahead is lost.
        const auto appended = static_cast<std::int64_t>(kHeld + 4 * kChunk);
        for (int i = 0; i < 1000 && Committed(*stub, "big") != appended; ++i)
            std::this_thread::sleep_for(std::chrono::milliseconds(10));
        EXPECT_EQ(Committed(*stub, "big"), appended);
        big->WritesDone();
        EXPECT_EQ(big->Finish().error_code(), grpc::StatusCode::FAILED_PRECONDITION);
    }

    // Resumed with four more chunks read ahead of the hash: the third would pass the cap. The
    // call ends RESOURCE_EXHAUSTED naming the flag, with exactly the two chunks before it
    // committed, as when each chunk is appended before the next is read.
    {
        grpc::ClientContext ctx;
        v1::Cloud response;
        auto big = SendChunks(*stub, ctx, response, "big", kHeld + 4 * kChunk, 4, kChunk, 'c');
        big->WritesDone();
        const grpc::Status s = big->Finish();
        EXPECT_EQ(s.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED) << s.error_message();
        EXPECT_NE(s.error_message().find("--max-upload-inflight-mb"), std::string::npos)
            << s.error_message();
        EXPECT_EQ(Committed(*stub, "big"), static_cast<std::int64_t>(kHeld + 6 * kChunk));
    }

    // Every call has ended: nothing stays counted (the refused and unappended chunks released),
    // so 1.5 MiB fits again.
    const grpc::Status s = Probe(*stub, "after", 6, kChunk);
    EXPECT_EQ(s.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << s.error_message();
    EXPECT_EQ(Committed(*stub, "after"), static_cast<std::int64_t>(6 * kChunk));
}

// An upload that says its size (UploadRequest.total_size; `surfel upload` does) is refused at
// once when it could never be stored, before any of its bytes is written or any blob evicted.
// Without it the first chunk (256 KiB) fits only by evicting X, and the upload is refused at a
// later chunk, X gone for nothing (docs/retention.md, "Limits of this design", until session 17).
TEST_F(DiskTest, AnUploadThatSaysItsSizeIsRefusedAtOnceEvictingNothing) {
    const std::string data = (dir_ / "data").string();
    const std::string x_path = Cloud("x.ply", 12000, 1), big_path = Cloud("big.ply", 24000, 2);
    const std::uint64_t x_size = fs::file_size(x_path), big_size = fs::file_size(big_path);
    const std::uint64_t quota = 450000;
    ASSERT_GT(x_size + (256u << 10), quota);  // the first chunk needs X's room
    ASSERT_GT(big_size, quota);               // the whole file never fits
    ASSERT_LE(x_size, quota);
    char gb[32];
    std::snprintf(gb, sizeof gb, "%.9f", static_cast<double>(quota) / 1e9);
    testing::ServerProcess server(data, {"--max-disk-gb", gb, "--max-upload-mb", "1"});
    ServiceClient c(server.target());
    const std::string x = c.UploadFile(x_path).id();
    const grpc::Status refused = StatusOf([&] { c.UploadFile(big_path); });
    EXPECT_EQ(refused.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
    EXPECT_NE(refused.error_message().find(std::to_string(big_size) + " bytes are more than the whole --max-disk-gb"),
              std::string::npos)
        << refused.error_message();
    EXPECT_EQ(c.GetCloud(x).id(), x);  // nothing evicted
    EXPECT_EQ(LeftoverTemps(data), std::vector<std::string>{});

    auto stub = v1::Surfel::NewStub(grpc::CreateChannel(server.target(), grpc::InsecureChannelCredentials()));
    // Each message: the id, the offset, `bytes` bytes, the total size said, whether it is the last.
    auto call = [&](const std::string& id, std::vector<std::tuple<std::uint64_t, std::size_t, std::uint64_t, bool>> msgs) {
        grpc::ClientContext ctx;
        v1::Cloud response;
        auto writer = stub->Upload(&ctx, &response);
        for (const auto& [offset, bytes, total, last] : msgs) {
            v1::UploadRequest r;
            r.set_upload_id(id);
            r.set_filename("t.ply");
            r.set_write_offset(static_cast<std::int64_t>(offset));
            r.set_data(std::string(bytes, 'x'));
            r.set_total_size(total);
            r.set_finish_write(last);
            if (!writer->Write(r)) break;
        }
        writer->WritesDone();
        return writer->Finish();
    };
    // Past --max-upload-mb: refused at its first (small) chunk, which is not kept.
    const grpc::Status too_big = call("too-big", {{0, 1000, 2u << 20, false}});
    EXPECT_EQ(too_big.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED) << too_big.error_message();
    EXPECT_NE(too_big.error_message().find("exceeds the limit of 1048576 bytes"), std::string::npos)
        << too_big.error_message();
    EXPECT_EQ(Committed(*stub, "too-big"), 0);
    // Ending at another size than it said: INVALID_ARGUMENT, the bytes discarded.
    const grpc::Status short_end = call("short", {{0, 500, 1000, true}});
    EXPECT_EQ(short_end.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_NE(short_end.error_message().find("ended at 500 bytes, but its total_size said 1000"), std::string::npos)
        << short_end.error_message();
    EXPECT_EQ(Committed(*stub, "short"), 0);
    // Sending more than it said: refused at the chunk that passes it; the bytes before it kept.
    const grpc::Status long_end = call("long", {{0, 600, 1000, false}, {600, 600, 0, true}});
    EXPECT_EQ(long_end.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_NE(long_end.error_message().find("passes its total_size 1000 at byte 1200"), std::string::npos)
        << long_end.error_message();
    EXPECT_EQ(Committed(*stub, "long"), 600);
    // Another size in a later message of a call, and a size below what a resumed upload has
    // committed.
    const grpc::Status changed = call("long", {{600, 10, 1000, false}, {610, 10, 2000, false}});
    EXPECT_EQ(changed.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_NE(changed.error_message().find("total_size: 2000 after 1000"), std::string::npos) << changed.error_message();
    const grpc::Status below = call("long-2", {{0, 600, 0, false}});
    EXPECT_EQ(below.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << below.error_message();  // incomplete
    const grpc::Status less = call("long-2", {{600, 10, 300, false}});
    EXPECT_EQ(less.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_NE(less.error_message().find("total_size: 300 is less than the 600 bytes"), std::string::npos)
        << less.error_message();
    // A correct one is stored (the reserved space becomes the blob's: X still fits beside it).
    const std::string ok = c.UploadFile(Cloud("ok.ply", 1000, 3)).id();
    EXPECT_EQ(c.GetCloud(ok).id(), ok);
    EXPECT_EQ(c.GetCloud(x).id(), x);
}

TEST_F(DiskTest, AbandonedUploadPartFilesExpireButNotWhileAnUploadHoldsThem) {
    const std::string data = (dir_ / "data").string();
    const fs::path uploads = fs::path(data) / "uploads";
    fs::create_directories(uploads);
    // Left by uploads before this start: one abandoned two days ago, one written to just now.
    const fs::path abandoned = uploads / "abandoned.part";
    const fs::path fresh = uploads / "fresh.part";
    WriteFileBytes(abandoned.string(), std::string(1000, 'x'));
    WriteFileBytes(fresh.string(), std::string(700, 'y'));
    fs::last_write_time(abandoned, fs::last_write_time(abandoned) - std::chrono::hours(48));
    testing::ServerProcess server(data, {"--upload-ttl", "1h", "--retention-sweep-s", "0.1"});
    auto stub = v1::Surfel::NewStub(
        grpc::CreateChannel(server.target(), grpc::InsecureChannelCredentials()));
    for (int i = 0; i < 100 && fs::exists(abandoned); ++i)
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
    EXPECT_FALSE(fs::exists(abandoned));
    EXPECT_EQ(Committed(*stub, "abandoned"), 0);  // an upload of that id starts again
    EXPECT_EQ(Committed(*stub, "fresh"), 700);

    // A call in progress holds its upload id: its part file stays however old it looks.
    HeldUpload held;
    ASSERT_TRUE(held.Open(*stub, 4096, 'z'));
    const fs::path part = uploads / "held-open.part";
    for (int i = 0; i < 300 && Committed(*stub, "held-open") != 4096; ++i)
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
    ASSERT_EQ(Committed(*stub, "held-open"), 4096);
    fs::last_write_time(part, fs::last_write_time(part) - std::chrono::hours(48));
    std::this_thread::sleep_for(std::chrono::milliseconds(600));  // several sweeps
    EXPECT_TRUE(fs::exists(part));
    // Once the call has ended, the part file is abandoned like any other.
    held.Close();
    for (int i = 0; i < 100 && fs::exists(part); ++i)
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
    EXPECT_FALSE(fs::exists(part));
    EXPECT_TRUE(fs::exists(fresh));
}

}  // namespace
}  // namespace surfel
