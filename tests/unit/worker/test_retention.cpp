// Disk quota and retention (issue 18.3, worker/retention.h): the LRU policy alone, durations,
// then Retention over a real SQLite store and blob directory: eviction order, clouds that
// queued jobs need are never evicted, a refusal evicts nothing, tombstones, time-to-lives per
// tenant, and the accounting at start.
#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>

#include "surfel/base/error.h"
#include "surfel/worker/blob_store.h"
#include "surfel/worker/retention.h"
#include "surfel/worker/sha256.h"
#include "surfel/worker/store.h"

namespace surfel::worker {
namespace {

namespace fs = std::filesystem;

// ---- the policy ---------------------------------------------------------------------------------

std::vector<std::string> Keys(const std::vector<BlobUsage>& v) {
    std::vector<std::string> out;
    for (const BlobUsage& b : v) out.push_back(b.key);
    return out;
}

TEST(ChooseVictims, TakesLeastRecentlyUsedFirstUntilEnoughSkippingPinned) {
    const std::vector<BlobUsage> lru = {
        {"clouds/a", 100, 1}, {"results/j1", 50, 2}, {"clouds/b", 200, 3}, {"results/j2", 10, 4}};
    EXPECT_EQ(Keys(ChooseVictims(lru, {}, 100)), (std::vector<std::string>{"clouds/a"}));
    EXPECT_EQ(Keys(ChooseVictims(lru, {}, 101)),
              (std::vector<std::string>{"clouds/a", "results/j1"}));
    EXPECT_EQ(Keys(ChooseVictims(lru, {"clouds/a"}, 100)),
              (std::vector<std::string>{"results/j1", "clouds/b"}));
    EXPECT_EQ(Keys(ChooseVictims(lru, {"clouds/a", "clouds/b"}, 60)),
              (std::vector<std::string>{"results/j1", "results/j2"}));
}

TEST(ChooseVictims, NothingWhenNothingIsNeededOrEvenAllUnpinnedAreTooFew) {
    const std::vector<BlobUsage> lru = {{"clouds/a", 100, 1}, {"clouds/b", 200, 2}};
    EXPECT_TRUE(ChooseVictims(lru, {}, 0).empty());
    EXPECT_TRUE(ChooseVictims(lru, {}, 301).empty());
    EXPECT_TRUE(ChooseVictims(lru, {"clouds/b"}, 101).empty());
    EXPECT_EQ(Keys(ChooseVictims(lru, {}, 300)),
              (std::vector<std::string>{"clouds/a", "clouds/b"}));
}

TEST(Durations, ParseFormatAndTheTtlFlag) {
    EXPECT_EQ(ParseDurationMs("0", "--ttl"), 0);
    EXPECT_EQ(ParseDurationMs("500ms", "--ttl"), 500);
    EXPECT_EQ(ParseDurationMs("90s", "--ttl"), 90'000);
    EXPECT_EQ(ParseDurationMs("15m", "--ttl"), 900'000);
    EXPECT_EQ(ParseDurationMs("12h", "--ttl"), 43'200'000);
    EXPECT_EQ(ParseDurationMs("7d", "--ttl"), 604'800'000);
    for (const char* bad : {"", "7", "d", "7w", "-1d", "1.5h", "7 d"}) {
        try {
            ParseDurationMs(bad, "--ttl");
            ADD_FAILURE() << "accepted '" << bad << "'";
        } catch (const Error& e) {
            EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
            EXPECT_NE(std::string(e.what()).find("--ttl: '" + std::string(bad) + "'"),
                      std::string::npos)
                << e.what();
        }
    }
    EXPECT_EQ(FormatDurationMs(604'800'000), "7d");
    EXPECT_EQ(FormatDurationMs(90'000), "90s");
    EXPECT_EQ(FormatDurationMs(1500), "1500ms");
    RetentionOptions o;
    ApplyTtlFlag("30d", &o);
    ApplyTtlFlag("alice=2h", &o);
    ApplyTtlFlag("bob=0", &o);
    EXPECT_EQ(o.default_ttl_ms, 30LL * 86'400'000);
    EXPECT_EQ(o.tenant_ttl_ms.at("alice"), 7'200'000);
    EXPECT_EQ(o.tenant_ttl_ms.at("bob"), 0);
    EXPECT_THROW(ApplyTtlFlag("=2h", &o), Error);
    EXPECT_THROW(ApplyTtlFlag("carol=soon", &o), Error);
}

// ---- Retention over a real store
// -----------------------------------------------------------------

class RetentionTest : public ::testing::Test {
  protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() /
               ("surfel-retention-" + std::to_string(::getpid()) + "-" +
                ::testing::UnitTest::GetInstance()->current_test_info()->name());
        fs::remove_all(dir_);
        store_ = std::make_unique<SqliteStore>(dir_.string());
    }
    void TearDown() override {
        store_.reset();
        fs::remove_all(dir_);
    }

    /// Stores a cloud of `size` bytes owned by `tenant`, last used at `used_ms`; returns its id.
    std::string AddCloud(Retention& r, std::size_t size, std::int64_t used_ms,
                         const std::string& tenant = "", char fill = 'x') {
        const std::string bytes(size, fill);
        const std::string id = Sha256Hex(bytes);
        r.Reserve(size, "test cloud");
        store_->blobs().PutBytes(CloudBlobKey(id), bytes, id);
        v1::Cloud c;
        c.set_id(id);
        c.set_size_bytes(size);
        store_->PutCloud(c);
        store_->AddCloudOwner(tenant, id);
        r.Stored(CloudBlobKey(id), size, size);
        store_->PutBlobUsage(CloudBlobKey(id), size, used_ms);  // a chosen "last used"
        return id;
    }
    /// Stores a SUCCEEDED job of `tenant` on `cloud` with a result of `size` bytes.
    std::string AddResult(Retention& r, const std::string& job_id, const std::string& cloud,
                          std::size_t size, std::int64_t used_ms, const std::string& tenant = "") {
        v1::Job job = Job(job_id, cloud, v1::SUCCEEDED, tenant);
        store_->PutJob(job, "key-" + job_id);
        const std::string bytes(size, 'r');
        r.Reserve(size, "test result");
        store_->blobs().PutBytes(ResultBlobKey(job_id), bytes, Sha256Hex(bytes));
        r.Stored(ResultBlobKey(job_id), size, size);
        store_->PutBlobUsage(ResultBlobKey(job_id), size, used_ms);
        return job_id;
    }
    static v1::Job Job(const std::string& id, const std::string& cloud, v1::JobState state,
                       const std::string& tenant = "") {
        v1::Job job;
        job.set_id(id);
        job.set_type("simplify");
        job.mutable_spec()->mutable_simplify()->set_cloud_id(cloud);
        job.mutable_spec()->mutable_simplify()->set_target(10);
        job.set_state(state);
        job.set_tenant(tenant);
        job.set_created_unix_ms(1);
        return job;
    }
    bool CloudStored(const std::string& id) const {
        return store_->FindCloud(id).has_value() && store_->blobs().Exists(CloudBlobKey(id));
    }

    fs::path dir_;
    std::unique_ptr<SqliteStore> store_;
};

TEST_F(RetentionTest, EvictsLeastRecentlyUsedFirstAndLeavesATombstonePerOwner) {
    RetentionOptions o;
    o.max_disk_bytes = 1000;
    std::vector<std::string> evicted;
    Retention r(*store_, o, [&](const std::string& kind, const std::string& cause, std::uint64_t) {
        evicted.push_back(kind + "/" + cause);
    });
    r.Load();
    const std::string a = AddCloud(r, 300, 1000, "alice", 'a');
    const std::string b = AddCloud(r, 300, 2000, "bob", 'b');
    AddResult(r, "j1", a, 200, 3000, "alice");
    store_->AddCloudOwner("carol", b);
    r.Touch(CloudBlobKey(a));  // a job read it: now the most recent
    EXPECT_EQ(r.stored_bytes(), 800u);

    // 300 more: 1100 > 1000 needs 100, the LRU blob is b (2000); a was just used.
    r.Reserve(300, "upload u1");
    EXPECT_EQ(evicted, (std::vector<std::string>{"cloud/lru"}));
    EXPECT_FALSE(CloudStored(b));
    EXPECT_FALSE(fs::exists(dir_ / "clouds" / b));
    EXPECT_TRUE(CloudStored(a));
    EXPECT_TRUE(store_->blobs().Exists(ResultBlobKey("j1")));
    EXPECT_EQ(r.stored_bytes(), 500u);
    EXPECT_EQ(r.reserved_bytes(), 300u);
    const std::string bob = "bob", carol = "carol", alice = "alice";
    for (const std::string* t : {&bob, &carol}) {
        const auto m = r.EvictedMessage(CloudBlobKey(b), "cloud " + b, t);
        ASSERT_TRUE(m) << *t;
        EXPECT_NE(m->find("cloud " + b + " was evicted at "), std::string::npos) << *m;
        EXPECT_NE(m->find("least recently used"), std::string::npos) << *m;
        EXPECT_NE(m->find("--max-disk-gb"), std::string::npos) << *m;
    }
    EXPECT_FALSE(r.EvictedMessage(CloudBlobKey(b), "cloud", &alice)) << "not alice's cloud";
    // The same bytes stored again: the tombstones go.
    r.Release(300);
    AddCloud(r, 300, 4000, "bob", 'b');
    EXPECT_FALSE(r.EvictedMessage(CloudBlobKey(b), "cloud", &bob));
}

TEST_F(RetentionTest, NeverEvictsACloudThatAQueuedOrRunningJobNeedsAndARefusalEvictsNothing) {
    RetentionOptions o;
    o.max_disk_bytes = 1000;
    Retention r(*store_, o);
    r.Load();
    const std::string a = AddCloud(r, 400, 1000, "", 'a');  // oldest, but needed
    const std::string b = AddCloud(r, 300, 2000, "", 'b');
    const std::string c = AddCloud(r, 200, 3000, "", 'c');
    store_->PutJob(Job("jq", a, v1::QUEUED), "kq");
    store_->PutJob(Job("jr", c, v1::RUNNING), "kr");
    store_->PutJob(Job("jf", b, v1::FAILED), "kf");  // a final job pins nothing

    // 900 stored; 400 more needs 300: a and c are pinned, b (300) suffices.
    r.Reserve(400, "upload u1");
    EXPECT_TRUE(CloudStored(a));
    EXPECT_FALSE(CloudStored(b));
    EXPECT_TRUE(CloudStored(c));
    // Now 600 stored + 400 reserved; 1 more byte cannot fit without a or c: refused, untouched.
    try {
        r.Reserve(1, "result of job jx");
        ADD_FAILURE() << "reserved past the quota";
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kResourceExhausted);
        const std::string m = e.what();
        EXPECT_NE(m.find("result of job jx: 1 more bytes do not fit under --max-disk-gb"),
                  std::string::npos)
            << m;
        EXPECT_NE(m.find("queued or running jobs need"), std::string::npos) << m;
    }
    EXPECT_TRUE(CloudStored(a));
    EXPECT_TRUE(CloudStored(c));
    EXPECT_EQ(r.stored_bytes(), 600u);
    EXPECT_EQ(r.reserved_bytes(), 400u);
    // Larger than the whole quota: refused at once, whatever could be evicted.
    try {
        r.Reserve(10, "upload big", 1001);
        ADD_FAILURE() << "reserved an object larger than the quota";
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kResourceExhausted);
        EXPECT_NE(std::string(e.what()).find("upload big: 1001 bytes are more than the whole"),
                  std::string::npos)
            << e.what();
    }
    // The queued job ends: a may go.
    store_->PutJob(Job("jq", a, v1::SUCCEEDED), "kq");
    r.Reserve(1, "result of job jx");
    EXPECT_FALSE(CloudStored(a));
    EXPECT_TRUE(CloudStored(c));
}

TEST_F(RetentionTest, WithoutAQuotaNothingIsEvicted) {
    Retention r(*store_, RetentionOptions{});
    r.Load();
    const std::string a = AddCloud(r, 400, 1000);
    r.Reserve(1ull << 40, "upload huge");
    EXPECT_TRUE(CloudStored(a));
    EXPECT_EQ(r.Sweep(NowUnixMs() + 1'000'000'000), 0u);
    EXPECT_TRUE(CloudStored(a));
}

TEST_F(RetentionTest, TimeToLivePerTenantEndsResultsAndOwnershipsNotNeededClouds) {
    RetentionOptions o;
    o.default_ttl_ms = 10'000;
    o.tenant_ttl_ms["keeper"] = 0;     // keeps forever
    o.tenant_ttl_ms["short"] = 1'000;  // one second
    std::vector<std::string> events;
    Retention r(*store_, o,
                [&](const std::string& kind, const std::string& cause, std::uint64_t n) {
                    events.push_back(kind + "/" + cause + "/" + std::to_string(n));
                });
    r.Load();
    const std::int64_t now = 100'000;
    // Shared by "short" (expired at 5 s unused) and "keeper": only short's ownership ends.
    const std::string shared = AddCloud(r, 100, now - 5'000, "short", 's');
    store_->AddCloudOwner("keeper", shared);
    // Only "short": the bytes go.
    const std::string lone = AddCloud(r, 100, now - 5'000, "short", 'l');
    // Default tenant, used 5 s ago: under the default 10 s.
    const std::string fresh = AddCloud(r, 100, now - 5'000, "", 'f');
    // Default tenant, 20 s unused, but a queued job needs it: kept.
    const std::string needed = AddCloud(r, 100, now - 20'000, "", 'n');
    store_->PutJob(Job("jq", needed, v1::QUEUED), "kq");
    AddResult(r, "jshort", fresh, 50, now - 2'000, "short");
    AddResult(r, "jdefault", fresh, 50, now - 2'000, "");

    EXPECT_EQ(r.Sweep(now), 3u);  // short's ownership of `shared`, `lone`, jshort's result
    EXPECT_TRUE(CloudStored(shared));
    EXPECT_FALSE(store_->CloudOwned("short", shared));
    EXPECT_TRUE(store_->CloudOwned("keeper", shared));
    EXPECT_FALSE(CloudStored(lone));
    EXPECT_TRUE(CloudStored(fresh));
    EXPECT_TRUE(CloudStored(needed));
    EXPECT_FALSE(store_->blobs().Exists(ResultBlobKey("jshort")));
    EXPECT_TRUE(store_->blobs().Exists(ResultBlobKey("jdefault")));
    const std::string short_tenant = "short";
    const auto m = r.EvictedMessage(ResultBlobKey("jshort"), "result of job jshort", &short_tenant);
    ASSERT_TRUE(m);
    EXPECT_NE(m->find("time-to-live 1s of tenant 'short'"), std::string::npos) << *m;
    EXPECT_TRUE(r.EvictedMessage(CloudBlobKey(shared), "cloud", &short_tenant));
    std::sort(events.begin(), events.end());
    EXPECT_EQ(events, (std::vector<std::string>{"cloud/ttl/0", "cloud/ttl/100", "result/ttl/50"}));
    EXPECT_EQ(r.stored_bytes(), 100u * 3 + 50u);
}

TEST_F(RetentionTest, LoadAdoptsBlobsWithoutEntriesDropsStaleOnesAndCountsPartFiles) {
    {
        Retention r(*store_, RetentionOptions{});
        r.Load();
        AddCloud(r, 300, 1000);
    }
    // Written behind retention's back (a store from before migration 6), and a stale entry.
    store_->blobs().PutBytes(ResultBlobKey("old"), std::string(200, 'o'), "");
    store_->PutBlobUsage(ResultBlobKey("gone"), 999, 5);
    std::ofstream(dir_ / "uploads" / "u1.part") << std::string(50, 'p');
    std::ofstream(dir_ / "results" / "x.tmp-0123456789abcdef") << "half";  // never counted

    Retention r(*store_, RetentionOptions{});
    r.Load();
    EXPECT_EQ(r.stored_bytes(), 500u);
    EXPECT_EQ(r.reserved_bytes(), 50u);
    const std::vector<BlobUsage> usage = store_->ListBlobUsage();
    ASSERT_EQ(usage.size(), 2u);
    EXPECT_EQ(usage[0].key.substr(0, 7), "clouds/");  // used at 1000, before "old" (now)
    EXPECT_EQ(usage[1].key, ResultBlobKey("old"));
}

}  // namespace
}  // namespace surfel::worker
