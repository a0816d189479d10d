#include "http_events.h"

#include <algorithm>

#include "operations.h"
#include "surfel/worker/job_state.h"

namespace surfel::server {

// ---- JobEventLog ------------------------------------------------------------------------------

void JobEventLog::Append(const v1::JobEvent& event) {
    {
        std::lock_guard lock(mutex_);
        if (final_) return;
        const bool progress = event.has_queued() || event.has_running();
        const bool coalesce =
            progress && !events_.empty() && events_.back().event.event_case() == event.event_case();
        if (coalesce)
            events_.back() = NumberedEvent{next_id_++, event};
        else
            events_.push_back(NumberedEvent{next_id_++, event});
        final_ = event.has_finished() || event.has_failed();
    }
    changed_.notify_all();
}

JobEventLog::Wait JobEventLog::WaitAfter(std::uint64_t after, std::chrono::milliseconds timeout,
                                         std::vector<NumberedEvent>* out) {
    std::unique_lock lock(mutex_);
    const auto ready = [&] { return stopped_ || (!events_.empty() && events_.back().id > after); };
    if (!changed_.wait_for(lock, timeout, ready)) return Wait::kTimeout;
    if (stopped_) return Wait::kStopped;
    auto first =
        std::upper_bound(events_.begin(), events_.end(), after,
                         [](std::uint64_t id, const NumberedEvent& e) { return id < e.id; });
    out->assign(first, events_.end());
    return Wait::kEvents;
}

std::uint64_t JobEventLog::LastId() const {
    std::lock_guard lock(mutex_);
    return events_.empty() ? 0 : events_.back().id;
}

bool JobEventLog::Final() const {
    std::lock_guard lock(mutex_);
    return final_;
}

void JobEventLog::Stop() {
    {
        std::lock_guard lock(mutex_);
        stopped_ = true;
    }
    changed_.notify_all();
}

// ---- JobEventLogs -----------------------------------------------------------------------------

JobEventLogs::JobEventLogs(worker::JobManager& jobs, std::size_t keep_final)
    : jobs_(jobs), keep_final_(keep_final) {}

JobEventLogs::~JobEventLogs() {
    Stop();
    std::lock_guard lock(mutex_);
    for (auto& [id, e] : logs_)
        if (e.subscribed) jobs_.Unsubscribe(id, e.token);
}

std::shared_ptr<JobEventLog> JobEventLogs::Open(const std::string& job_id) {
    std::lock_guard lock(mutex_);
    if (auto it = logs_.find(job_id); it != logs_.end()) return it->second.log;
    Entry e;
    e.log = std::make_shared<JobEventLog>();
    if (stopped_) e.log->Stop();
    std::weak_ptr<JobEventLog> weak = e.log;
    // The manager delivers the job's state (and queue position) to the listener inside
    // Subscribe, under its lock, so nothing comes before them.
    std::optional<v1::Job> job = jobs_.Subscribe(
        job_id,
        [weak](const v1::JobEvent& event) {
            if (auto log = weak.lock()) log->Append(event);
        },
        &e.token);
    if (!job) return nullptr;
    e.subscribed = !worker::IsFinal(job->state());
    if (!e.subscribed)
        for (const v1::JobEvent& event : Operations::FinalEvents(*job)) e.log->Append(event);
    e.opened = opened_++;
    auto log = e.log;
    logs_.emplace(job_id, std::move(e));
    DropOldFinal();
    return log;
}

void JobEventLogs::DropOldFinal() {
    std::vector<std::map<std::string, Entry>::iterator> unread;
    for (auto it = logs_.begin(); it != logs_.end(); ++it)
        if (it->second.log.use_count() == 1 && it->second.log->Final()) unread.push_back(it);
    if (unread.size() <= keep_final_) return;
    std::sort(unread.begin(), unread.end(),
              [](auto a, auto b) { return a->second.opened < b->second.opened; });
    for (std::size_t i = 0; i + keep_final_ < unread.size(); ++i) {
        if (unread[i]->second.subscribed)
            jobs_.Unsubscribe(unread[i]->first, unread[i]->second.token);
        logs_.erase(unread[i]);
    }
}

void JobEventLogs::Stop() {
    std::lock_guard lock(mutex_);
    stopped_ = true;
    for (auto& [id, e] : logs_) e.log->Stop();
}

}  // namespace surfel::server
