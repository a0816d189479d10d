#include <gtest/gtest.h>

#include <chrono>
#include <condition_variable>
#include <filesystem>
#include <mutex>
#include <set>
#include <thread>

#include "surfel/base/error.h"
#include "surfel/base/shapes.h"
#include "surfel/io/image.h"
#include "surfel/io/ply.h"
#include "surfel/io/file_bytes.h"
#include "surfel/worker/job_kind.h"
#include "surfel/worker/job_manager.h"
#include "surfel/worker/status.h"
#include "surfel/worker/store.h"

namespace surfel::worker {
namespace {

namespace fs = std::filesystem;

TEST(Status, EveryErrorCodeMapsToItsGrpcCode) {
    const std::pair<ErrorCode, grpc::StatusCode> table[] = {
        {ErrorCode::kInvalidArgument, grpc::StatusCode::INVALID_ARGUMENT},
        {ErrorCode::kNotFound, grpc::StatusCode::NOT_FOUND},
        {ErrorCode::kResourceExhausted, grpc::StatusCode::RESOURCE_EXHAUSTED},
        {ErrorCode::kCancelled, grpc::StatusCode::CANCELLED},
        {ErrorCode::kDeadlineExceeded, grpc::StatusCode::DEADLINE_EXCEEDED},
        {ErrorCode::kUnavailable, grpc::StatusCode::UNAVAILABLE},
        {ErrorCode::kFailedPrecondition, grpc::StatusCode::FAILED_PRECONDITION},
        {ErrorCode::kInternal, grpc::StatusCode::INTERNAL},
        {ErrorCode::kDataLoss, grpc::StatusCode::DATA_LOSS},
        {ErrorCode::kUnauthenticated, grpc::StatusCode::UNAUTHENTICATED},
    };
    for (const auto& [code, grpc_code] : table) {
        EXPECT_EQ(ToStatusCode(code), grpc_code) << ErrorCodeName(code);
        const grpc::Status s = ToStatus(Error(code, "what went wrong"));
        EXPECT_EQ(s.error_code(), grpc_code);
        EXPECT_EQ(s.error_message(), "what went wrong");
    }
    const grpc::Status other = ToStatus(std::runtime_error("boom"));
    EXPECT_EQ(other.error_code(), grpc::StatusCode::INTERNAL);
    EXPECT_EQ(other.error_message(), "internal error: boom");
}

TEST(Sha256, KnownVectors) {
    EXPECT_EQ(Sha256Hex(""), "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
    EXPECT_EQ(Sha256Hex("abc"), "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
    Sha256 h;
    h.Update("a");
    h.Update("bc");
    EXPECT_EQ(h.FinishHex(), Sha256Hex("abc"));
}

TEST(JobManager, KeyIgnoresTheTimeoutOnly) {
    v1::JobSpec a;
    a.mutable_simplify()->set_cloud_id("c");
    a.mutable_simplify()->set_target(5);
    v1::JobSpec b = a;
    b.set_timeout_ms(1000);
    EXPECT_EQ(JobKey(a), JobKey(b));
    b.mutable_simplify()->set_target(6);
    EXPECT_NE(JobKey(a), JobKey(b));
}

// ---- JobManager on a real store in a temp directory.

class ManagerTest : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() / ("surfel-worker-test-" + std::to_string(::getpid()) + "-" +
                                            ::testing::UnitTest::GetInstance()->current_test_info()->name());
        fs::remove_all(dir_);
        store_ = std::make_unique<SqliteStore>(dir_.string());
        ShapeOptions o;
        o.points = 3000;
        const std::string bytes = FormatPly(SampleShape(Shape::kSphere, o));
        cloud_id_ = Sha256Hex(bytes);
        WriteFileBytes(store_->CloudPath(cloud_id_), bytes);
        v1::Cloud c;
        c.set_id(cloud_id_);
        c.set_points(3000);
        store_->PutCloud(c);
    }
    void TearDown() override {
        store_.reset();
        fs::remove_all(dir_);
    }
    v1::JobSpec Simplify(std::uint64_t target) const {
        v1::JobSpec spec;
        spec.mutable_simplify()->set_cloud_id(cloud_id_);
        spec.mutable_simplify()->set_target(target);
        spec.mutable_simplify()->set_no_error_report(true);
        return spec;
    }
    v1::Job WaitFinal(JobManager& m, const std::string& id) {
        for (int i = 0; i < 3000; ++i) {
            auto j = m.Get(id);
            if (j && (j->state() == v1::SUCCEEDED || j->state() == v1::FAILED || j->state() == v1::CANCELLED))
                return *j;
            std::this_thread::sleep_for(std::chrono::milliseconds(10));
        }
        ADD_FAILURE() << "job " << id << " did not finish";
        return {};
    }
    fs::path dir_;
    std::unique_ptr<Store> store_;
    std::string cloud_id_;
};

TEST_F(ManagerTest, RunsAJobAndStoresItsResult) {
    JobManager m(*store_, {});
    m.Start();
    const v1::Job job = m.Submit(Simplify(300));
    EXPECT_EQ(job.state(), v1::QUEUED);
    const v1::Job done = WaitFinal(m, job.id());
    ASSERT_EQ(done.state(), v1::SUCCEEDED) << done.status_message();
    EXPECT_EQ(done.result().points(), 300u);
    EXPECT_EQ(ParsePly(ReadFileBytes(store_->ResultPath(job.id())), "r").size(), 300u);
    // Its SHA-256 is recorded with it, for the check on download.
    EXPECT_EQ(done.result().sha256(), Sha256Hex(ReadFileBytes(store_->ResultPath(job.id()))));
    // An identical submission returns the finished job at once.
    const v1::Job again = m.Submit(Simplify(300));
    EXPECT_EQ(again.id(), job.id());
    EXPECT_TRUE(again.reused());
    EXPECT_EQ(again.state(), v1::SUCCEEDED);
}

TEST_F(ManagerTest, ProgressEventsCarryTheKindsStageAndCloudsAreShared) {
    JobManager m(*store_, {});  // subscribed before it starts: every event is seen
    const v1::Job job = m.Submit(Simplify(200));
    EXPECT_EQ(job.type(), "simplify");
    std::mutex mutex;
    std::set<std::string> stages;
    std::uint64_t token = 0;
    ASSERT_TRUE(m.Subscribe(
        job.id(),
        [&](const v1::JobEvent& e) {
            std::lock_guard lock(mutex);
            if (e.has_running()) stages.insert(e.running().stage());
        },
        &token));
    m.Start();
    ASSERT_EQ(WaitFinal(m, job.id()).state(), v1::SUCCEEDED);
    m.Unsubscribe(job.id(), token);
    std::lock_guard lock(mutex);
    EXPECT_TRUE(stages.count("loading"));
    EXPECT_TRUE(stages.count(std::string(KindOf(job.spec()).Stage()))) << "stage from the job-kind table";
    // The manager hands out its cached cloud itself, never a copy.
    EXPECT_EQ(m.LoadCloud(cloud_id_).get(), m.LoadCloud(cloud_id_).get());
}

TEST_F(ManagerTest, UnknownCloudIsNotFoundAndFullQueueIsResourceExhausted) {
    ManagerOptions o;
    o.max_queued = 2;
    JobManager m(*store_, o);  // not started: jobs stay queued
    v1::JobSpec missing = Simplify(10);
    missing.mutable_simplify()->set_cloud_id("nope");
    try {
        m.Submit(missing);
        FAIL();
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kNotFound);
        EXPECT_EQ(std::string(e.what()), "simplify.cloud_id: cloud nope not found (upload it first)");
    }
    m.Submit(Simplify(10));
    m.Submit(Simplify(11));
    try {
        m.Submit(Simplify(12));
        FAIL();
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kResourceExhausted);
    }
}

TEST_F(ManagerTest, CancelAQueuedJobAndWatchIt) {
    JobManager m(*store_, {});
    const v1::Job job = m.Submit(Simplify(10));
    std::vector<v1::JobEvent> events;
    std::uint64_t token = 0;
    ASSERT_TRUE(m.Subscribe(job.id(), [&](const v1::JobEvent& e) { events.push_back(e); }, &token));
    const v1::Job cancelled = m.Cancel(job.id());
    EXPECT_EQ(cancelled.state(), v1::CANCELLED);
    ASSERT_EQ(events.size(), 3u);  // state, queued(0), failed
    EXPECT_TRUE(events[0].has_state());
    EXPECT_EQ(events[1].queued().position(), 0u);
    EXPECT_EQ(events[2].failed().code(), grpc::StatusCode::CANCELLED);
    EXPECT_EQ(store_->FindJob(job.id())->state(), v1::CANCELLED);
}

TEST_F(ManagerTest, QueuedJobsSurviveARestart) {
    std::string id;
    {
        JobManager m(*store_, {});  // never started: the "crash" leaves it queued
        id = m.Submit(Simplify(50)).id();
    }
    JobManager again(*store_, {});
    again.Start();
    EXPECT_EQ(WaitFinal(again, id).state(), v1::SUCCEEDED);
}

TEST_F(ManagerTest, TimeoutGivesDeadlineExceeded) {
    ShapeOptions o;
    o.points = 60000;
    const std::string bytes = FormatPly(SampleShape(Shape::kTorus, o));
    const std::string big = Sha256Hex(bytes);
    WriteFileBytes(store_->CloudPath(big), bytes);
    v1::Cloud c;
    c.set_id(big);
    store_->PutCloud(c);
    JobManager m(*store_, {});
    m.Start();
    v1::JobSpec spec;
    spec.mutable_render()->set_cloud_id(big);
    spec.mutable_render()->set_width(1024);
    spec.mutable_render()->set_height(1024);
    spec.mutable_render()->set_samples_per_pixel(16);
    spec.set_timeout_ms(200);
    // The first render of a process opens the image plugin (dlopen, ~0.3 s of CPU, several
    // seconds on a loaded machine) before its deadline can be checked; open it first so that
    // the bound below measures how promptly a running render stops. (The job writes EXR: the
    // EXR plugin, or the OpenImageIO one where that is missing.)
    LoadImageCodec(ImageFormat::kExr);
    const v1::Job done = WaitFinal(m, m.Submit(spec).id());
    EXPECT_EQ(done.state(), v1::FAILED);
    EXPECT_EQ(done.status_code(), grpc::StatusCode::DEADLINE_EXCEEDED) << done.status_message();
    // Promptly: 2 s on a plain build; an instrumented one runs the render's set-up several
    // times slower (SURFEL_TEST_SLOWDOWN: cmake/SurfelHelpers.cmake, the same factor that
    // scales ctest's per-test limit).
    EXPECT_LT(done.finished_unix_ms() - done.started_unix_ms(), 2000 * SURFEL_TEST_SLOWDOWN);
}

}  // namespace
}  // namespace surfel::worker
