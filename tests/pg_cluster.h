#pragma once
// A throwaway PostgreSQL 15 cluster for tests: initialised (once per machine, as a template in
// /dev/shm) by Debian's initdb as the `postgres` user when run as root, copied into a temp dir
// and started on a free loopback port. Used by the store's unit tests and the scale-out
// integration tests (which also stop and restart it on the same port).
#include <fcntl.h>
#include <gtest/gtest.h>
#include <libpq-fe.h>
#include <netinet/in.h>
#include <pwd.h>
#include <sys/file.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cctype>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>

namespace surfel::testing_pg {
namespace fs = std::filesystem;

/// Quotes a string for /bin/sh.
inline std::string Sh(const std::string& s) {
    std::string out = "'";
    for (char c : s) out += c == '\'' ? std::string("'\\''") : std::string(1, c);
    return out + "'";
}

/// A port on 127.0.0.1 that was free a moment ago.
inline int FreeLoopbackPort() {
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
inline std::string ScratchDir() {
    std::error_code ec;
    if (fs::is_directory("/dev/shm", ec) && ::access("/dev/shm", W_OK) == 0) return "/dev/shm";
    return fs::temp_directory_path().string();
}

/// The newest /usr/lib/postgresql/<version>/bin holding initdb and pg_ctl, or "".
inline std::string PostgresBinDir() {
    std::string best;
    std::error_code ec;
    for (const auto& e : fs::directory_iterator("/usr/lib/postgresql", ec)) {
        const fs::path bin = e.path() / "bin";
        if (fs::exists(bin / "initdb") && fs::exists(bin / "pg_ctl") && bin.string() > best)
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
            why_not_ =
                "PostgreSQL server binaries not found under /usr/lib/postgresql "
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
        start_ = start;
        started_ = true;
        port_ = std::to_string(port);
    }

  public:
    /// The cluster's port ("" when it did not start).
    const std::string& port() const { return port_; }
    /// Stops the server (`pg_ctl stop -m fast`: sessions are terminated); true on success.
    bool Stop() {
        const std::string stop = pg_ctl_ + " -m fast -w stop > /dev/null 2>&1";
        const bool ok = std::system(stop.c_str()) == 0;
        if (ok) started_ = false;
        return ok;
    }
    /// Starts it again on the same port and data; true on success.
    bool Restart() {
        const bool ok = std::system(start_.c_str()) == 0;
        if (ok) started_ = true;
        return ok;
    }

  private:
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
        const std::string root =
            ScratchDir() + "/surfel-pg-template-" + version + "-uid" + std::to_string(::geteuid());
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

    std::string dir_, pg_ctl_, port_, why_not_, start_;
    uid_t uid_ = 0;
    gid_t gid_ = 0;
    bool installed_ = false;
    bool started_ = false;
};

}  // namespace surfel::testing_pg
