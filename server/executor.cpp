#include "executor.h"

#include <algorithm>
#include <utility>

namespace surfel::server {
namespace {

// A task that throws would leave its reactor unfinished and the server's shutdown waiting for
// it forever; noexcept turns that bug into a visible std::terminate.
void RunTask(const std::function<void()>& task) noexcept { task(); }

}  // namespace

Executor::Executor(std::size_t threads, std::size_t max_queued) : max_queued_(std::max<std::size_t>(max_queued, 1)) {
    threads = std::max<std::size_t>(threads, 1);
    threads_.reserve(threads);
    for (std::size_t i = 0; i < threads; ++i) threads_.emplace_back([this] { Loop(); });
}

Executor::~Executor() { Stop(); }

void Executor::Stop() {
    {
        std::lock_guard lock(mutex_);
        stopping_ = true;
    }
    wake_.notify_all();
    for (std::thread& t : threads_)
        if (t.joinable()) t.join();
}

bool Executor::TrySubmit(std::function<void()> task) {
    {
        std::lock_guard lock(mutex_);
        if (stopping_ || queue_.size() >= max_queued_) return false;
        queue_.push_back(std::move(task));
    }
    wake_.notify_one();
    return true;
}

std::size_t Executor::Queued() const {
    std::lock_guard lock(mutex_);
    return queue_.size();
}

void Executor::Loop() {
    for (;;) {
        std::function<void()> task;
        {
            std::unique_lock lock(mutex_);
            wake_.wait(lock, [this] { return stopping_ || !queue_.empty(); });
            if (queue_.empty()) return;  // stopping, and everything queued has run
            task = std::move(queue_.front());
            queue_.pop_front();
        }
        RunTask(task);
    }
}

}  // namespace surfel::server
