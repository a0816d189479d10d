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

namespace surfel::worker {
namespace {
namespace fs = std::filesystem;

// ---- a throwaway PostgreSQL cluster

/// Quotes a string for /bin/sh.
std::string Sh(const std::string& s) {
    std::string out = "'";
    for (char c : s) out += c == '\'' ? std::string("'\\''") : std::string(1, c);
    return out + "'";
}

/// A port on 127.0.0.1 that was free a moment ago.
int FreeLoopbackPort() {
    const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    a.sin_port = 0;
    socklen_t len = sizeof a;
    if (fd < 0 || ::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0 ||
        ::getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len) != 0) {
        if (fd >= 0) ::close(fd);
        return 0;
    }
    ::close(fd);
    return ntohs(a.sin_port);
}

/// Where the clusters live: /dev/shm (memory; copying a cluster there takes a tenth of the time)
/// when it is a directory, else the temp directory.
std::string ScratchDir() {
    std::error_code ec;
    if (fs::is_directory("/dev/shm", ec) && ::access("/dev/shm", W_OK) == 0) return "/dev/shm";
    return fs::temp_directory_path().string();
}

/// The newest /usr/lib/postgresql/<version>/bin holding initdb and pg_ctl, or "".
std::string PostgresBinDir() {
    std::string best;
    std::error_code ec;
    for (const auto& e : fs::directory_iterator("/usr/lib/postgresql", ec)) {
        const fs::path bin = e.path() / "bin";
        if (fs::exists(bin / "initdb") && fs::exists(bin / "pg_ctl") &&
            bin.string() > best)
            best = bin.string();
    }
    return best;
}

/// One cluster per test process, started on first use and stopped at exit: initdb as the
/// `postgres` user (postgres refuses to run as root; see Template), trust authentication,
/// copied into a temp dir, fsync off (a throwaway), its socket in that dir and TCP on a free
/// loopback port.
class Cluster {
public:
    static Cluster& Get() {
        static Cluster cluster;
        return cluster;
    }
    /// False when this machine has no PostgreSQL to start (the tests skip).
    bool installed() const { return installed_; }
    /// True when the cluster runs; else why_not() says what failed (the tests fail).
    bool ok() const { return !port_.empty(); }
    const std::string& why_not() const { return why_not_; }

    /// The URL of a new, empty schema (each test its own; a schema costs a millisecond, a
    /// database a second): the connection's search_path is set to it.
    std::string NewSchema(const std::string& name) {
        std::string schema = "t_";
        for (char c : name)
            schema += std::isalnum(static_cast<unsigned char>(c)) ? std::tolower(c) : '_';
        schema = schema.substr(0, 60);
        const std::string postgres = "postgresql://surfel@127.0.0.1:" + port_ + "/postgres";
        Exec(postgres, "DROP SCHEMA IF EXISTS " + schema + " CASCADE");
        Exec(postgres, "CREATE SCHEMA " + schema);
        return postgres + "?options=-c%20search_path%3D" + schema;
    }
    /// Runs one statement (without parameters) at `url`; returns the first value of the first
    /// row as text ("" when none). Fails the test on an error.
    static std::string Exec(const std::string& url, const std::string& sql) {
        PGconn* c = PQconnectdb(url.c_str());
        std::string value;
        if (PQstatus(c) != CONNECTION_OK) {
            ADD_FAILURE() << "connect " << url << ": " << PQerrorMessage(c);
        } else {
            PQsetNoticeProcessor(
                c, [](void*, const char*) {}, nullptr);  // "does not exist, skipping"
            PGresult* r = PQexec(c, sql.c_str());
            const ExecStatusType st = PQresultStatus(r);
            if (st != PGRES_COMMAND_OK && st != PGRES_TUPLES_OK)
                ADD_FAILURE() << sql << ": " << PQresultErrorMessage(r);
            else if (st == PGRES_TUPLES_OK && PQntuples(r) > 0)
                value = PQgetvalue(r, 0, 0);
            PQclear(r);
        }
        PQfinish(c);
        return value;
    }

private:
    Cluster() {
        const std::string bin = PostgresBinDir();
        if (bin.empty()) {
            why_not_ = "PostgreSQL server binaries not found under /usr/lib/postgresql "
                       "(apt-get install postgresql)";
            return;
        }
        installed_ = true;
        std::string as_user;  // the prefix that runs a command as the cluster's owner
        if (::geteuid() == 0) {
            const passwd* pw = ::getpwnam("postgres");
            if (!pw) {
                why_not_ = "running as root and there is no `postgres` user to run PostgreSQL";
                installed_ = false;
                return;
            }
            uid_ = pw->pw_uid;
            gid_ = pw->pw_gid;
            as_user = "runuser -u postgres -- ";
        }
        std::string tmpl = ScratchDir() + "/surfel-pg-XXXXXX";
        if (!::mkdtemp(tmpl.data())) {
            why_not_ = "mkdtemp failed";
            return;
        }
        dir_ = tmpl;
        if (::geteuid() == 0 && ::chown(dir_.c_str(), uid_, gid_) != 0) {
            why_not_ = "chown " + dir_ + " failed";
            return;
        }
        const int port = FreeLoopbackPort();
        if (port == 0) {
            why_not_ = "no free loopback port";
            return;
        }
        const std::string data = dir_ + "/data";
        pg_ctl_ = as_user + Sh(bin + "/pg_ctl") + " -D " + Sh(data);
        const std::string tmpl_data = Template(bin, as_user);
        if (tmpl_data.empty()) return;
        const std::string copy = "cp -a " + Sh(tmpl_data) + " " + Sh(data);
        if (std::system(copy.c_str()) != 0) {
            why_not_ = "copying the initdb template failed: " + copy;
            return;
        }
        const std::string start =
            pg_ctl_ + " -l " + Sh(dir_ + "/server.log") + " -w -t 30 -o " +
            Sh("-p " + std::to_string(port) + " -k " + dir_ +
               " -c listen_addresses=127.0.0.1 -c fsync=off -c synchronous_commit=off "
               "-c full_page_writes=off -c max_connections=40") +
            " start > " + Sh(dir_ + "/pg_ctl.log") + " 2>&1";
        if (std::system(start.c_str()) != 0) {
            why_not_ = "pg_ctl start failed: " + ReadLog("/server.log");
            return;
        }
        started_ = true;
        port_ = std::to_string(port);
    }
    ~Cluster() {
        if (started_) {
            const std::string stop = pg_ctl_ + " -m immediate -w stop > /dev/null 2>&1";
            if (std::system(stop.c_str()) != 0) std::fprintf(stderr, "pg_ctl stop failed\n");
        }
        std::error_code ec;
        if (!dir_.empty()) fs::remove_all(dir_, ec);
    }
    /// The data directory of a cluster fresh from initdb, made once per PostgreSQL version and
    /// user and copied by each test process (initdb takes seconds; a copy a fraction of one).
    /// Made under an exclusive lock so test processes running in parallel make it once.
    std::string Template(const std::string& bin, const std::string& as_user) {
        const std::string version = fs::path(bin).parent_path().filename().string();
        const std::string root = ScratchDir() + "/surfel-pg-template-" + version + "-uid" +
                                 std::to_string(::geteuid());
        const int lock = ::open((root + ".lock").c_str(), O_CREAT | O_RDWR, 0600);
        if (lock < 0 || ::flock(lock, LOCK_EX) != 0) {
            why_not_ = "cannot lock " + root + ".lock";
            if (lock >= 0) ::close(lock);
            return "";
        }
        std::string result = root + "/data";
        if (!fs::exists(result + "/PG_VERSION")) {
            const std::string tmp = root + ".tmp";
            std::error_code ec;
            fs::remove_all(tmp, ec);
            fs::create_directories(tmp, ec);
            const std::string initdb =
                as_user + Sh(bin + "/initdb") + " -D " + Sh(tmp + "/data") +
                " -A trust -U surfel -E UTF8 --locale=C --no-sync --wal-segsize=1 > " +
                Sh(dir_ + "/initdb.log") + " 2>&1";
            if (ec || (::geteuid() == 0 && ::chown(tmp.c_str(), uid_, gid_) != 0) ||
                std::system(initdb.c_str()) != 0) {
                why_not_ = "initdb failed: " + ReadLog("/initdb.log");
                result.clear();
            } else {
                fs::remove_all(root, ec);
                fs::rename(tmp, root, ec);
                if (ec) {
                    why_not_ = "rename " + tmp + ": " + ec.message();
                    result.clear();
                }
            }
        }
        ::flock(lock, LOCK_UN);
        ::close(lock);
        return result;
    }
    std::string ReadLog(const std::string& name) const {
        std::ifstream in(dir_ + name);
        return std::string(std::istreambuf_iterator<char>(in), {});
    }

    std::string dir_, pg_ctl_, port_, why_not_;
    uid_t uid_ = 0;
    gid_t gid_ = 0;
    bool installed_ = false;
    bool started_ = false;
};

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
