// The store on both backends through one parameterised suite: SQLite in a temp directory and a
// real PostgreSQL 15 cluster that this test initialises in a temp directory and starts on its own
// free loopback port (skipped, with the reason, when Debian's postgresql binaries are absent).
#include <SQLiteCpp/SQLiteCpp.h>
#include <gtest/gtest.h>
#include <libpq-fe.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <pwd.h>
#include <sys/file.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <cctype>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "surfel/base/error.h"
#include "surfel/worker/status.h"
#include "surfel/worker/store.h"
#include "surfel/worker/store_migrations.h"
#include "surfel/worker/store_postgres.h"
#include "../../pg_cluster.h"

namespace surfel::worker {
namespace {
namespace fs = std::filesystem;

using testing_pg::Cluster;
using testing_pg::FreeLoopbackPort;

// ---- the suite, once per backend

std::string TestName() {
    return ::testing::UnitTest::GetInstance()->current_test_info()->name();
}

/// prefix + i (appended: GCC 12 reports a false -Wrestrict for a literal + std::to_string).
std::string Numbered(const char* prefix, int i) {
    std::string s = prefix;
    s += std::to_string(i);
    return s;
}

v1::Job MakeJob(const std::string& id, v1::JobState state, std::int64_t created) {
    v1::Job j;
    j.set_id(id);
    j.set_state(state);
    j.set_type("simplify");
    j.set_created_unix_ms(created);
    j.mutable_spec()->mutable_simplify()->set_cloud_id("c-" + id);
    j.mutable_spec()->mutable_simplify()->set_target(100);
    return j;
}

class StoreTest : public ::testing::TestWithParam<std::string> {
protected:
    void SetUp() override {
        std::string name = TestName();
        std::replace(name.begin(), name.end(), '/', '_');
        dir_ = fs::temp_directory_path() / ("surfel-store-test-" + std::to_string(::getpid()) +
                                            "-" + name);
        fs::remove_all(dir_);
        if (GetParam() == "postgres") {
            Cluster& c = Cluster::Get();
            if (!c.installed()) GTEST_SKIP() << "PostgreSQL not available: " << c.why_not();
            ASSERT_TRUE(c.ok()) << "PostgreSQL did not start: " << c.why_not();
            url_ = c.NewSchema(name);
        } else {
            url_ = "sqlite";
        }
        store_ = Open();
    }
    void TearDown() override {
        store_.reset();
        std::error_code ec;
        fs::remove_all(dir_, ec);
    }
    /// Another store on the same database (its own connection).
    std::unique_ptr<Store> Open() const { return OpenStore(url_, dir_.string()); }

    /// The number of rows of schema_migrations, read without the store.
    std::int64_t AppliedMigrations() const {
        if (GetParam() == "postgres")
            return std::stoll(Cluster::Exec(url_, "SELECT COUNT(*) FROM schema_migrations"));
        SQLite::Database db((dir_ / "surfel.db").string());
        return db.execAndGet("SELECT COUNT(*) FROM schema_migrations").getInt64();
    }
    void Sql(const std::string& sql) const {
        if (GetParam() == "postgres") {
            Cluster::Exec(url_, sql);
        } else {
            SQLite::Database db((dir_ / "surfel.db").string(), SQLite::OPEN_READWRITE);
            db.exec(sql);
        }
    }

    fs::path dir_;
    std::string url_;
    std::unique_ptr<Store> store_;
};

TEST_P(StoreTest, MigrationsAreIdempotent) {
    const auto n = static_cast<std::int64_t>(Migrations().size());
    EXPECT_EQ(AppliedMigrations(), n);
    store_->PutJob(MakeJob("a", v1::QUEUED, 1), "k");
    store_.reset();
    store_ = Open();  // open twice: nothing applied again, nothing lost
    auto other = Open();
    EXPECT_EQ(AppliedMigrations(), n);
    ASSERT_TRUE(other->FindJob("a"));
    EXPECT_EQ(other->FindJob("a")->spec().simplify().cloud_id(), "c-a");
}

TEST_P(StoreTest, MigrationsOpenedConcurrentlyApplyOnce) {
    store_.reset();
    if (GetParam() == "postgres") {
        url_ = Cluster::Get().NewSchema(TestName() + "_fresh");
    } else {
        fs::remove_all(dir_);
    }
    std::vector<std::thread> threads;
    std::mutex m;
    std::vector<std::string> errors;
    for (int i = 0; i < 4; ++i)
        threads.emplace_back([&] {
            try {
                Open();
            } catch (const std::exception& e) {
                std::lock_guard lock(m);
                errors.push_back(e.what());
            }
        });
    for (auto& t : threads) t.join();
    EXPECT_TRUE(errors.empty()) << errors.front();
    EXPECT_EQ(AppliedMigrations(), static_cast<std::int64_t>(Migrations().size()));
}

TEST_P(StoreTest, RefusesASchemaNewerThanItKnows) {
    Sql("INSERT INTO schema_migrations (version, name, applied_ms) VALUES (999, 'future', 0)");
    store_.reset();
    try {
        Open();
        ADD_FAILURE() << "opened a database migrated by a newer release";
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kFailedPrecondition);
        EXPECT_NE(std::string(e.what()).find("schema version 999"), std::string::npos) << e.what();
    }
}

TEST_P(StoreTest, CloudsPutFindDelete) {
    EXPECT_FALSE(store_->FindCloud("x"));
    v1::Cloud c;
    c.set_id("x");
    c.set_points(42);
    std::ofstream(store_->CloudPath("x")) << "bytes";
    store_->PutCloud(c);
    c.set_points(7);
    store_->PutCloud(c);  // no-op: the first record stays
    ASSERT_TRUE(store_->FindCloud("x"));
    EXPECT_EQ(store_->FindCloud("x")->points(), 42u);
    EXPECT_TRUE(store_->DeleteCloud("x"));
    EXPECT_FALSE(store_->FindCloud("x"));
    EXPECT_FALSE(fs::exists(store_->CloudPath("x")));
    EXPECT_FALSE(store_->DeleteCloud("x"));
}

TEST_P(StoreTest, JobsPutFindListUnfinishedReusable) {
    store_->PutJob(MakeJob("j1", v1::QUEUED, 10), "k1");
    store_->PutJob(MakeJob("j2", v1::RUNNING, 20), "k2");
    store_->PutJob(MakeJob("j3", v1::FAILED, 30), "k1");
    store_->PutJob(MakeJob("j4", v1::SUCCEEDED, 40), "k2");
    EXPECT_FALSE(store_->FindJob("nope"));
    ASSERT_TRUE(store_->FindJob("j2"));
    EXPECT_EQ(store_->FindJob("j2")->state(), v1::RUNNING);

    // A transition written with an empty key keeps the key and the order.
    v1::Job j1 = MakeJob("j1", v1::SUCCEEDED, 10);
    j1.set_finished_unix_ms(99);
    store_->PutJob(j1, "");
    EXPECT_EQ(store_->FindJob("j1")->state(), v1::SUCCEEDED);
    EXPECT_EQ(store_->FindJob("j1")->finished_unix_ms(), 99);

    auto ids = [](const std::vector<v1::Job>& jobs) {
        std::vector<std::string> out;
        for (const auto& j : jobs) out.push_back(j.id());
        return out;
    };
    using V = std::vector<std::string>;
    EXPECT_EQ(ids(store_->ListJobs(10, v1::JOB_STATE_UNSPECIFIED)), (V{"j4", "j3", "j2", "j1"}));
    EXPECT_EQ(ids(store_->ListJobs(2, v1::JOB_STATE_UNSPECIFIED)), (V{"j4", "j3"}));
    EXPECT_EQ(ids(store_->ListJobs(10, v1::SUCCEEDED)), (V{"j4", "j1"}));
    EXPECT_EQ(ids(store_->Unfinished()), (V{"j2"}));

    // Reusable: the newest queued, running or succeeded job with the key.
    ASSERT_TRUE(store_->FindReusable("k1"));
    EXPECT_EQ(store_->FindReusable("k1")->id(), "j1");  // j3 failed
    EXPECT_EQ(store_->FindReusable("k2")->id(), "j4");
    EXPECT_FALSE(store_->FindReusable("k3"));
    store_->PutJob(MakeJob("j1", v1::CANCELLED, 10), "");
    EXPECT_FALSE(store_->FindReusable("k1"));

    store_->PutJob(MakeJob("j5", v1::QUEUED, 50), "k5");
    EXPECT_EQ(ids(store_->Unfinished()), (V{"j2", "j5"}));
}

// Migration 4: cloud owners per tenant, jobs listed per tenant (docs/security.md).
TEST_P(StoreTest, TenantsOwnCloudsAndListTheirJobs) {
    v1::Cloud c;
    c.set_id("x");
    std::ofstream(store_->CloudPath("x")) << "bytes";
    store_->PutCloud(c);
    EXPECT_FALSE(store_->CloudOwned("alice", "x"));
    store_->AddCloudOwner("alice", "x");
    store_->AddCloudOwner("alice", "x");  // no-op
    store_->AddCloudOwner("bob", "x");
    EXPECT_TRUE(store_->CloudOwned("alice", "x"));
    EXPECT_FALSE(store_->CloudOwned("", "x"));
    std::size_t remaining = 9;
    EXPECT_FALSE(store_->RemoveCloudOwner("carol", "x", &remaining));
    EXPECT_EQ(remaining, 2u);
    EXPECT_TRUE(store_->RemoveCloudOwner("bob", "x", &remaining));
    EXPECT_EQ(remaining, 1u);
    EXPECT_FALSE(store_->CloudOwned("bob", "x"));
    EXPECT_TRUE(store_->DeleteCloud("x"));  // every owner goes with the record
    EXPECT_FALSE(store_->CloudOwned("alice", "x"));

    v1::Job a = MakeJob("ja", v1::QUEUED, 1), b = MakeJob("jb", v1::QUEUED, 2);
    a.set_tenant("alice");
    b.set_tenant("bob");
    store_->PutJob(a, "k");
    store_->PutJob(b, "k");
    a.set_state(v1::SUCCEEDED);
    store_->PutJob(a, "");  // a transition keeps the tenant
    const std::string alice = "alice", none;
    ASSERT_EQ(store_->ListJobs(10, v1::JOB_STATE_UNSPECIFIED, &alice).size(), 1u);
    EXPECT_EQ(store_->ListJobs(10, v1::JOB_STATE_UNSPECIFIED, &alice)[0].id(), "ja");
    EXPECT_EQ(store_->ListJobs(10, v1::SUCCEEDED, &alice).size(), 1u);
    EXPECT_EQ(store_->ListJobs(10, v1::QUEUED, &alice).size(), 0u);
    EXPECT_EQ(store_->ListJobs(10, v1::JOB_STATE_UNSPECIFIED, &none).size(), 0u);
    EXPECT_EQ(store_->ListJobs(10, v1::JOB_STATE_UNSPECIFIED).size(), 2u);
}

// ---- disk retention (migration 6): usage, tombstones, owners; the policy is test_retention.cpp

TEST_P(StoreTest, BlobUsageInLruOrderTombstonesPerTenantAndOwners) {
    store_->PutBlobUsage("clouds/b", 200, 20);
    store_->PutBlobUsage("results/j", 50, 10);
    store_->PutBlobUsage("clouds/a", 100, 20);
    store_->TouchBlobUsage("results/j", 30);
    store_->TouchBlobUsage("clouds/none", 40);  // no entry: nothing
    std::vector<BlobUsage> u = store_->ListBlobUsage();
    ASSERT_EQ(u.size(), 3u);
    EXPECT_EQ(u[0].key, "clouds/a");  // ties by key
    EXPECT_EQ(u[0].size, 100u);
    EXPECT_EQ(u[1].key, "clouds/b");
    EXPECT_EQ(u[2].key, "results/j");
    EXPECT_EQ(u[2].last_used_ms, 30);
    store_->PutBlobUsage("clouds/b", 250, 5);  // replaced
    u = store_->ListBlobUsage();
    EXPECT_EQ(u[0].key, "clouds/b");
    EXPECT_EQ(u[0].size, 250u);
    EXPECT_TRUE(store_->RemoveBlobUsage("clouds/b"));
    EXPECT_FALSE(store_->RemoveBlobUsage("clouds/b"));
    EXPECT_EQ(store_->ListBlobUsage().size(), 2u);

    const std::string alice = "alice", bob = "bob";
    store_->PutEviction("clouds/a", "alice", Eviction{"lru", 100});
    store_->PutEviction("clouds/a", "alice", Eviction{"ttl", 200});  // replaced
    EXPECT_EQ(store_->FindEviction("clouds/a", &alice)->reason, "ttl");
    EXPECT_EQ(store_->FindEviction("clouds/a", &alice)->evicted_ms, 200);
    EXPECT_FALSE(store_->FindEviction("clouds/a", &bob));
    EXPECT_EQ(store_->FindEviction("clouds/a", nullptr)->reason, "ttl");
    store_->PutBlobUsage("clouds/a", 100, 300);  // stored again: the tombstones go
    EXPECT_FALSE(store_->FindEviction("clouds/a", nullptr));

    v1::Cloud c;
    c.set_id("x");
    store_->PutCloud(c);
    store_->AddCloudOwner("bob", "x");
    store_->AddCloudOwner("alice", "x");
    EXPECT_EQ(store_->CloudOwners("x"), (std::vector<std::string>{"alice", "bob"}));
    EXPECT_TRUE(store_->CloudOwners("y").empty());
}

// ---- the queue

TEST_P(StoreTest, ClaimTakesTheOldestQueuedJobUnderALease) {
    EXPECT_FALSE(store_->ClaimNext("w1", 1000));
    store_->PutJob(MakeJob("running", v1::RUNNING, 1), "k");  // the JobManager's, no lease
    store_->PutJob(MakeJob("a", v1::QUEUED, 2), "k");
    store_->PutJob(MakeJob("b", v1::QUEUED, 3), "k");
    const std::int64_t before = NowUnixMs();
    auto first = store_->ClaimNext("w1", 5000);
    ASSERT_TRUE(first);
    EXPECT_EQ(first->job.id(), "a");
    EXPECT_EQ(first->job.state(), v1::RUNNING);
    EXPECT_GE(first->job.started_unix_ms(), before);
    EXPECT_EQ(first->owner, "w1");
    EXPECT_EQ(first->attempts, 0);
    EXPECT_GE(first->lease_expires_ms, before + 5000);
    ASSERT_TRUE(store_->FindJob("a"));
    EXPECT_EQ(store_->FindJob("a")->state(), v1::RUNNING);
    EXPECT_EQ(store_->FindJob("a")->started_unix_ms(), first->job.started_unix_ms());

    auto second = Open()->ClaimNext("w2", 5000);
    ASSERT_TRUE(second);
    EXPECT_EQ(second->job.id(), "b");
    EXPECT_FALSE(store_->ClaimNext("w1", 5000));
    EXPECT_THROW(store_->ClaimNext("", 5000), Error);
    EXPECT_THROW(store_->ClaimNext("w1", 0), Error);
}

TEST_P(StoreTest, HeartbeatKeepsTheLease) {
    store_->PutJob(MakeJob("a", v1::QUEUED, 1), "k");
    auto leased = store_->ClaimNext("w1", 1000);
    ASSERT_TRUE(leased);
    EXPECT_FALSE(store_->Heartbeat("a", "w2", 60'000));  // not the owner
    EXPECT_FALSE(store_->Heartbeat("b", "w1", 60'000));  // no such job
    ASSERT_TRUE(store_->Heartbeat("a", "w1", 60'000));
    // Past the first lease, within the renewed one: nothing is taken back.
    EXPECT_TRUE(store_->RequeueExpired(NowUnixMs() + 5'000, 3).empty());
    EXPECT_EQ(store_->FindJob("a")->state(), v1::RUNNING);
    EXPECT_TRUE(store_->Heartbeat("a", "w1", 60'000));
}

TEST_P(StoreTest, ExpiredLeaseIsRequeuedAndTheLeaseIsLost) {
    store_->PutJob(MakeJob("a", v1::QUEUED, 1), "k");
    auto leased = store_->ClaimNext("w1", 1000);
    ASSERT_TRUE(leased);
    const auto requeued = store_->RequeueExpired(leased->lease_expires_ms + 1, 3);
    ASSERT_EQ(requeued.size(), 1u);
    EXPECT_EQ(requeued[0].id(), "a");
    EXPECT_EQ(requeued[0].state(), v1::QUEUED);
    EXPECT_EQ(store_->FindJob("a")->state(), v1::QUEUED);
    EXPECT_EQ(store_->FindJob("a")->started_unix_ms(), 0);
    // The old owner has lost it: no heartbeat, no write.
    EXPECT_FALSE(store_->Heartbeat("a", "w1", 60'000));
    v1::Job late = leased->job;
    late.set_state(v1::SUCCEEDED);
    EXPECT_FALSE(store_->PutLeasedJob(late, "w1"));
    EXPECT_EQ(store_->FindJob("a")->state(), v1::QUEUED);
    // Claimed again with the attempt counted.
    auto again = store_->ClaimNext("w2", 1000);
    ASSERT_TRUE(again);
    EXPECT_EQ(again->job.id(), "a");
    EXPECT_EQ(again->attempts, 1);
}

TEST_P(StoreTest, FailsAJobPastMaxAttemptsNamingThem) {
    store_->PutJob(MakeJob("a", v1::QUEUED, 1), "k");
    for (int attempt = 1; attempt <= 2; ++attempt) {
        auto leased = store_->ClaimNext(Numbered("w", attempt), 1000);
        ASSERT_TRUE(leased) << "attempt " << attempt;
        EXPECT_EQ(leased->attempts, attempt - 1);
        const auto back = store_->RequeueExpired(leased->lease_expires_ms + 1, 2);
        ASSERT_EQ(back.size(), 1u);
        EXPECT_EQ(back[0].state(), attempt < 2 ? v1::QUEUED : v1::FAILED);
    }
    const auto job = store_->FindJob("a");
    ASSERT_TRUE(job);
    EXPECT_EQ(job->state(), v1::FAILED);
    EXPECT_EQ(job->status_code(), ToStatusCode(ErrorCode::kUnavailable));
    EXPECT_EQ(job->status_message(), LeaseExhaustedMessage(2, 2, "w2"));
    EXPECT_NE(job->status_message().find("attempt 2 of 2"), std::string::npos);
    EXPECT_GT(job->finished_unix_ms(), 0);
    EXPECT_FALSE(store_->ClaimNext("w3", 1000));
    EXPECT_TRUE(store_->RequeueExpired(NowUnixMs() + 1'000'000, 2).empty());
    EXPECT_THROW(store_->RequeueExpired(NowUnixMs(), 0), Error);
}

TEST_P(StoreTest, PutLeasedJobWritesOnlyUnderTheLease) {
    store_->PutJob(MakeJob("a", v1::QUEUED, 1), "k");
    auto leased = store_->ClaimNext("w1", 60'000);
    ASSERT_TRUE(leased);
    v1::Job job = leased->job;
    job.set_stage("simplify");
    job.set_fraction(0.5);
    EXPECT_FALSE(store_->PutLeasedJob(job, "w2"));
    EXPECT_TRUE(store_->PutLeasedJob(job, "w1"));
    EXPECT_DOUBLE_EQ(store_->FindJob("a")->fraction(), 0.5);
    job.set_state(v1::SUCCEEDED);
    job.set_fraction(1);
    EXPECT_TRUE(store_->PutLeasedJob(job, "w1"));  // the end releases the lease
    EXPECT_EQ(store_->FindJob("a")->state(), v1::SUCCEEDED);
    EXPECT_FALSE(store_->Heartbeat("a", "w1", 60'000));
    job.set_state(v1::FAILED);
    EXPECT_FALSE(store_->PutLeasedJob(job, "w1"));  // a second finisher changes nothing
    EXPECT_EQ(store_->FindJob("a")->state(), v1::SUCCEEDED);
    EXPECT_TRUE(store_->RequeueExpired(NowUnixMs() + 1'000'000, 3).empty());
}

TEST_P(StoreTest, ReleasingALeaseQueuesTheJobWithoutAnAttempt) {
    store_->PutJob(MakeJob("a", v1::QUEUED, 1), "k");
    auto leased = store_->ClaimNext("w1", 60'000);
    ASSERT_TRUE(leased);
    v1::Job job = leased->job;
    job.set_state(v1::QUEUED);  // SIGTERM: the worker gives it back
    EXPECT_TRUE(store_->PutLeasedJob(job, "w1"));
    EXPECT_FALSE(store_->Heartbeat("a", "w1", 60'000));
    auto again = store_->ClaimNext("w2", 60'000);
    ASSERT_TRUE(again);
    EXPECT_EQ(again->attempts, 0);
}

TEST_P(StoreTest, CancelRequestsQueuedAtOnceRunningByFlag) {
    store_->PutJob(MakeJob("q", v1::QUEUED, 1), "k1");
    store_->PutJob(MakeJob("r", v1::QUEUED, 2), "k2");
    store_->PutJob(MakeJob("s", v1::SUCCEEDED, 3), "k3");
    EXPECT_EQ(store_->CountQueued(), 2u);
    EXPECT_EQ(store_->QueuePosition("q"), 0u);
    EXPECT_EQ(store_->QueuePosition("r"), 1u);
    auto running = store_->ClaimNext("w1", 60'000);  // takes q, the oldest
    ASSERT_TRUE(running);
    EXPECT_EQ(running->job.id(), "q");
    EXPECT_EQ(store_->QueuePosition("r"), 0u);

    const auto queued = store_->RequestCancel("r");
    ASSERT_TRUE(queued);
    EXPECT_EQ(queued->state(), v1::CANCELLED);
    EXPECT_EQ(queued->status_code(), ToStatusCode(ErrorCode::kCancelled));
    EXPECT_EQ(store_->FindJob("r")->state(), v1::CANCELLED);
    EXPECT_FALSE(store_->ClaimNext("w2", 60'000));  // nothing left to claim

    EXPECT_FALSE(store_->CancelRequested("q"));
    const auto flagged = store_->RequestCancel("q");
    ASSERT_TRUE(flagged);
    EXPECT_EQ(flagged->state(), v1::RUNNING);  // its leaseholder stops it
    EXPECT_TRUE(Open()->CancelRequested("q"));  // seen through another connection
    EXPECT_EQ(store_->RequestCancel("s")->state(), v1::SUCCEEDED);  // final: unchanged
    EXPECT_FALSE(store_->CancelRequested("s"));
    EXPECT_FALSE(store_->RequestCancel("nope"));
    EXPECT_EQ(store_->CountQueued(), 0u);
}

TEST_P(StoreTest, HintsReachEveryListenerOnlyOnASharedStore) {
    std::mutex m;
    std::condition_variable cv;
    std::vector<std::string> got;
    auto sub = store_->Listen([&](const std::string& p) {
        std::lock_guard lock(m);
        got.push_back(p);
        cv.notify_all();
    });
    if (GetParam() == "sqlite") {
        EXPECT_FALSE(store_->shared());
        EXPECT_EQ(sub, nullptr);
        store_->Publish("n x j1");  // nothing to deliver to: a no-op
        return;
    }
    ASSERT_TRUE(store_->shared());
    ASSERT_NE(sub, nullptr);
    auto other = Open();
    // LISTEN starts on the listener's own thread: publish until the first hint arrives.
    std::unique_lock lock(m);
    for (int i = 0; i < 100 && got.empty(); ++i) {
        lock.unlock();
        other->Publish("p w1 j1 0.5 render");
        lock.lock();
        cv.wait_for(lock, std::chrono::milliseconds(50), [&] { return !got.empty(); });
    }
    ASSERT_FALSE(got.empty());
    EXPECT_EQ(got.front(), "p w1 j1 0.5 render");
}

TEST_P(StoreTest, ConcurrentClaimersNeverGetTheSameJob) {
    constexpr int kJobs = 60;
    constexpr int kClaimers = 4;
    for (int i = 0; i < kJobs; ++i) store_->PutJob(MakeJob(Numbered("j", i), v1::QUEUED, i), "k");
    std::vector<std::unique_ptr<Store>> stores;  // each claimer its own connection
    for (int t = 0; t < kClaimers; ++t) stores.push_back(Open());
    std::vector<std::vector<std::string>> claimed(kClaimers);
    std::vector<std::string> errors(kClaimers);
    std::vector<std::thread> threads;
    for (int t = 0; t < kClaimers; ++t)
        threads.emplace_back([&, t] {
            try {
                const std::string owner = Numbered("w", t);
                while (auto leased = stores[t]->ClaimNext(owner, 60'000))
                    claimed[t].push_back(leased->job.id());
            } catch (const std::exception& e) {
                errors[t] = e.what();
            }
        });
    for (auto& t : threads) t.join();
    std::multiset<std::string> all;
    for (int t = 0; t < kClaimers; ++t) {
        EXPECT_EQ(errors[t], "") << "claimer " << t;
        all.insert(claimed[t].begin(), claimed[t].end());
    }
    EXPECT_EQ(all.size(), static_cast<std::size_t>(kJobs));
    EXPECT_EQ(std::set<std::string>(all.begin(), all.end()).size(),
              static_cast<std::size_t>(kJobs));
    EXPECT_TRUE(store_->Unfinished().size() == static_cast<std::size_t>(kJobs));
    EXPECT_TRUE(store_->ListJobs(100, v1::QUEUED).empty());
}

TEST_P(StoreTest, RequeueLeavesJobsWithoutALeaseAlone) {
    store_->PutJob(MakeJob("a", v1::RUNNING, 1), "k");  // the single-node JobManager's
    EXPECT_TRUE(store_->RequeueExpired(NowUnixMs() + 1'000'000, 1).empty());
    EXPECT_EQ(store_->FindJob("a")->state(), v1::RUNNING);
}

INSTANTIATE_TEST_SUITE_P(Backends, StoreTest, ::testing::Values("sqlite", "postgres"),
                         [](const auto& backend) { return backend.param; });

// ---- backend-specific

TEST(SqliteStoreTest, AdoptsADatabaseFromBeforeMigrations) {
    const fs::path dir =
        fs::temp_directory_path() / ("surfel-store-legacy-" + std::to_string(::getpid()));
    fs::remove_all(dir);
    fs::create_directories(dir);
    const std::string record = MakeJob("old", v1::QUEUED, 5).SerializeAsString();
    {
        // The schema the store created before it had migrations.
        SQLite::Database db((dir / "surfel.db").string(),
                            SQLite::OPEN_READWRITE | SQLite::OPEN_CREATE);
        db.exec(
            "CREATE TABLE clouds (id TEXT PRIMARY KEY, record BLOB NOT NULL, created_ms INTEGER "
            "NOT NULL)");
        db.exec(
            "CREATE TABLE jobs (id TEXT PRIMARY KEY, key TEXT NOT NULL, state INTEGER NOT NULL, "
            "created_ms INTEGER NOT NULL, seq INTEGER NOT NULL, record BLOB NOT NULL)");
        SQLite::Statement q(db, "INSERT INTO jobs VALUES ('old', 'k', 1, 5, 1, ?)");
        q.bind(1, record.data(), static_cast<int>(record.size()));
        q.exec();
    }
    {
        SqliteStore store(dir.string());
        ASSERT_TRUE(store.FindJob("old"));
        EXPECT_EQ(store.Unfinished().size(), 1u);
        auto leased = store.ClaimNext("w", 1000);
        ASSERT_TRUE(leased);
        EXPECT_EQ(leased->job.id(), "old");
    }
    fs::remove_all(dir);
}

TEST(OpenStoreTest, ChoosesTheBackendByTheUrl) {
    const fs::path dir =
        fs::temp_directory_path() / ("surfel-store-open-" + std::to_string(::getpid()));
    fs::remove_all(dir);
    EXPECT_NE(dynamic_cast<SqliteStore*>(OpenStore("sqlite", (dir / "a").string()).get()), nullptr);
    EXPECT_TRUE(fs::exists(dir / "a" / "surfel.db"));
    EXPECT_TRUE(fs::is_directory(dir / "a" / "clouds"));
    OpenStore("sqlite:" + (dir / "db" / "x.db").string(), (dir / "blobs").string());
    EXPECT_TRUE(fs::exists(dir / "db" / "x.db"));
    EXPECT_TRUE(fs::is_directory(dir / "blobs" / "results"));
    OpenStore((dir / "c").string(), "");
    EXPECT_TRUE(fs::exists(dir / "c" / "surfel.db"));
    EXPECT_TRUE(fs::is_directory(dir / "c" / "uploads"));
    try {
        OpenStore("mysql://localhost/db", dir.string());
        ADD_FAILURE() << "accepted an unknown scheme";
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
        EXPECT_NE(std::string(e.what()).find("mysql://"), std::string::npos);
    }
    fs::remove_all(dir);
}

TEST(OpenStoreTest, UnreachablePostgresIsUnavailableWithThePasswordHidden) {
    const std::string url =
        "postgresql://u:secret@127.0.0.1:" + std::to_string(FreeLoopbackPort()) +
        "/db?connect_timeout=2";
    try {
        OpenStore(url, (fs::temp_directory_path() /
                        ("surfel-store-unreach-" + std::to_string(::getpid())))
                           .string());
        ADD_FAILURE() << "connected to a closed port";
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kUnavailable);
        EXPECT_EQ(std::string(e.what()).find("secret"), std::string::npos) << e.what();
    }
    fs::remove_all(fs::temp_directory_path() /
                   ("surfel-store-unreach-" + std::to_string(::getpid())));
    EXPECT_EQ(RedactDatabaseUrl("postgres://u:pw@h:5/d"), "postgres://u:***@h:5/d");
    EXPECT_EQ(RedactDatabaseUrl("postgres://u@h:5/d"), "postgres://u@h:5/d");
    EXPECT_EQ(RedactDatabaseUrl("postgres://h:5/d"), "postgres://h:5/d");
}

}  // namespace
}  // namespace surfel::worker
