#pragma once
/// \file
/// A small fixed pool of threads with a bounded queue, for the work that a gRPC reaction must
/// not do itself (grpc/grpc#36609): parsing and hashing uploaded files.

#include <condition_variable>
#include <cstddef>
#include <deque>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

namespace surfel::server {

class Executor {
public:
    /// Starts `threads` threads (at least 1); at most `max_queued` tasks wait for one (at least 1).
    Executor(std::size_t threads, std::size_t max_queued);
    /// Stop(): runs every task still queued, then joins the threads.
    ~Executor();
    /// Refuses new tasks, runs every task still queued, then joins the threads (idempotent). No
    /// accepted task is dropped: each one ends an upload call, and a call never ended would never
    /// reach OnDone. The server calls it after grpc::Server::Shutdown and before the objects its
    /// tasks use (Operations, the store) are destroyed: a task may still be returning from the
    /// call's Finish when Shutdown returns.
    void Stop();
    Executor(const Executor&) = delete;
    Executor& operator=(const Executor&) = delete;

    /// Queues `task` to run on one of the threads. Returns false, without running it, when
    /// `max_queued` tasks wait already: the caller answers RESOURCE_EXHAUSTED rather than wait.
    /// A task must not throw (one that does terminates the process: it is a bug).
    bool TrySubmit(std::function<void()> task);

    /// Tasks waiting for a thread (not counting those running).
    std::size_t Queued() const;
    std::size_t threads() const { return threads_.size(); }

private:
    void Loop();

    const std::size_t max_queued_;
    mutable std::mutex mutex_;
    std::condition_variable wake_;
    std::deque<std::function<void()>> queue_;
    bool stopping_ = false;
    std::vector<std::thread> threads_;
};

}  // namespace surfel::server
