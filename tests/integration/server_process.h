#pragma once
// Starts the real surfel-server binary on a free loopback port with a data directory, for
// integration tests.

#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

namespace surfel::testing {

class ServerProcess {
public:
    ServerProcess(const std::string& data_dir, std::vector<std::string> extra = {}) : data_dir_(data_dir) {
        Start(std::move(extra));
    }
    ~ServerProcess() { Kill(SIGKILL); }

    void Start(std::vector<std::string> extra = {}) {
        const std::string port_file = data_dir_ + ".port";
        std::filesystem::remove(port_file);
        std::vector<std::string> args = {std::string(SURFEL_BIN_DIR) + "/surfel-server", "--port", "0", "--data-dir",
                                         data_dir_, "--port-file", port_file, "--log-level", "warn"};
        args.insert(args.end(), extra.begin(), extra.end());
        const pid_t parent = getpid();
        pid_ = fork();
        if (pid_ == 0) {
            DieWithParent(parent);
            std::vector<char*> argv;
            for (auto& a : args) argv.push_back(a.data());
            argv.push_back(nullptr);
            execv(argv[0], argv.data());
            _exit(127);
        }
        for (int i = 0; i < 1000; ++i) {  // up to 10 s
            std::ifstream in(port_file);
            if (in >> port_ && port_ > 0) return;
            int status = 0;
            if (waitpid(pid_, &status, WNOHANG) == pid_) {
                pid_ = -1;
                throw std::runtime_error("surfel-server exited during start");
            }
            std::this_thread::sleep_for(std::chrono::milliseconds(10));
        }
        throw std::runtime_error("surfel-server did not start");
    }

    /// Sends `sig` and waits; returns the exit status (or 128 + signal).
    int Kill(int sig) {
        if (pid_ <= 0) return -1;
        ::kill(pid_, sig);
        int status = 0;
        waitpid(pid_, &status, 0);
        pid_ = -1;
        return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
    }

    /// In a forked child: ends it with SIGKILL when the test process ends, however it ends. A
    /// test that aborts (a failed ASSERT in a helper thread, a sanitizer report) would otherwise
    /// leave the server running and holding ctest's output pipe, and ctest would wait for it until
    /// the test's timeout. The signal follows the forking thread, so construct servers in the
    /// test's own thread (every test does).
    static void DieWithParent(pid_t parent) {
        ::prctl(PR_SET_PDEATHSIG, SIGKILL);
        if (getppid() != parent) _exit(127);  // the parent ended before prctl took effect
    }

    std::string target() const { return "127.0.0.1:" + std::to_string(port_); }
    int port() const { return port_; }
    pid_t pid() const { return pid_; }

private:
    std::string data_dir_;
    pid_t pid_ = -1;
    int port_ = 0;
};

}  // namespace surfel::testing
