#include "metrics.h"

#include "surfel/base/error.h"
#include "surfel/worker/job_kind.h"
#include "surfel/worker/job_state.h"

namespace surfel::server {

Metrics::Metrics() : registry_(std::make_shared<prometheus::Registry>()) {
    jobs_ = &prometheus::BuildCounter()
                 .Name("surfel_jobs_total")
                 .Help("Jobs that entered a state, by type and state")
                 .Register(*registry_);
    running_ = &prometheus::BuildGauge().Name("surfel_jobs_running").Help("Jobs running now, by type").Register(*registry_);
    duration_ = &prometheus::BuildHistogram()
                     .Name("surfel_job_duration_seconds")
                     .Help("Wall time of finished jobs (running to final state), by type and state")
                     .Register(*registry_);
    queue_depth_ = &prometheus::BuildGauge()
                        .Name("surfel_queue_depth")
                        .Help("Jobs waiting for a worker")
                        .Register(*registry_)
                        .Add({});
    auto& bytes = prometheus::BuildCounter().Name("surfel_bytes_total").Help("Payload bytes by direction").Register(*registry_);
    bytes_in_ = &bytes.Add({{"direction", "in"}});
    bytes_out_ = &bytes.Add({{"direction", "out"}});
    uploads_ = &prometheus::BuildCounter().Name("surfel_uploads_total").Help("Finished uploads by outcome").Register(*registry_);
    auto& disk = prometheus::BuildGauge()
                     .Name("surfel_disk_bytes")
                     .Help("Blob bytes counted toward --max-disk-gb: stored blobs, reserved (upload part "
                           "files and results being written), and the quota (0 = none)")
                     .Register(*registry_);
    disk_stored_ = &disk.Add({{"what", "stored"}});
    disk_reserved_ = &disk.Add({{"what", "reserved"}});
    disk_quota_ = &disk.Add({{"what", "quota"}});
    upload_inflight_ = &prometheus::BuildGauge()
                            .Name("surfel_upload_inflight_bytes")
                            .Help("Bytes received by uploads in progress and not yet stored")
                            .Register(*registry_)
                            .Add({});
    evictions_ = &prometheus::BuildCounter()
                      .Name("surfel_evictions_total")
                      .Help("Blobs evicted (or tenants' ownerships ended), by kind and cause (lru, ttl)")
                      .Register(*registry_);
    evicted_bytes_ = &prometheus::BuildCounter()
                          .Name("surfel_evicted_bytes_total")
                          .Help("Bytes freed by evictions, by kind and cause")
                          .Register(*registry_);
    for (const char* kind : {"cloud", "result"})
        for (const char* cause : {"lru", "ttl"}) {
            evictions_->Add({{"kind", kind}, {"cause", cause}});
            evicted_bytes_->Add({{"kind", kind}, {"cause", cause}});
        }
    // Every kind of the job table has its series from the start (0 until it runs), so a
    // dashboard sees a kind that never ran and a rate() has a starting point.
    for (const worker::JobKind* kind : worker::JobKinds()) running_->Add({{"type", std::string(kind->Name())}});
}

void Metrics::Serve(const std::string& address) {
    try {
        exposer_ = std::make_unique<prometheus::Exposer>(address);
        exposer_->RegisterCollectable(registry_);
    } catch (const std::exception& e) {
        throw Error(ErrorCode::kInvalidArgument, "metrics on " + address + ": " + e.what());
    }
}

void Metrics::OnTransition(const v1::Job& job, v1::JobState from) {
    const std::string state = v1::JobState_Name(job.state());
    jobs_->Add({{"type", job.type()}, {"state", state}}).Increment();
    auto& running = running_->Add({{"type", job.type()}});
    if (job.state() == v1::RUNNING) running.Increment();
    if (from == v1::RUNNING) running.Decrement();
    if (worker::IsFinal(job.state()) && job.started_unix_ms() > 0) {
        static const prometheus::Histogram::BucketBoundaries kBuckets{0.01, 0.03, 0.1, 0.3, 1, 3, 10, 30, 100, 300};
        duration_->Add({{"type", job.type()}, {"state", state}}, kBuckets)
            .Observe(static_cast<double>(job.finished_unix_ms() - job.started_unix_ms()) / 1000.0);
    }
}

void Metrics::SetQueueDepth(std::size_t depth) { queue_depth_->Set(static_cast<double>(depth)); }
void Metrics::AddBytesIn(std::uint64_t n) { bytes_in_->Increment(static_cast<double>(n)); }
void Metrics::AddBytesOut(std::uint64_t n) { bytes_out_->Increment(static_cast<double>(n)); }
void Metrics::SetDisk(std::uint64_t stored, std::uint64_t reserved, std::uint64_t quota,
                      std::uint64_t upload_inflight) {
    disk_stored_->Set(static_cast<double>(stored));
    disk_reserved_->Set(static_cast<double>(reserved));
    disk_quota_->Set(static_cast<double>(quota));
    upload_inflight_->Set(static_cast<double>(upload_inflight));
}
void Metrics::CountEviction(const std::string& kind, const std::string& cause, std::uint64_t bytes) {
    evictions_->Add({{"kind", kind}, {"cause", cause}}).Increment();
    evicted_bytes_->Add({{"kind", kind}, {"cause", cause}}).Increment(static_cast<double>(bytes));
}
void Metrics::CountUpload(bool ok) { uploads_->Add({{"outcome", ok ? "stored" : "rejected"}}).Increment(); }

}  // namespace surfel::server
