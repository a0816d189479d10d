#pragma once
/// \file
/// Prometheus metrics of the server (prometheus-cpp): jobs by type and state, queue depth, job
/// durations, bytes in and out. Served on an HTTP port at /metrics when one is given.

#include <prometheus/counter.h>
#include <prometheus/exposer.h>
#include <prometheus/gauge.h>
#include <prometheus/histogram.h>
#include <prometheus/registry.h>

#include <memory>
#include <string>

#include "surfel/v1/surfel.pb.h"

namespace surfel::server {

class Metrics {
public:
    Metrics();
    /// Serves /metrics on `address` ("127.0.0.1:9464"); throws surfel::Error when it cannot bind.
    void Serve(const std::string& address);

    /// A job changed state (JobManager's transition hook).
    void OnTransition(const v1::Job& job, v1::JobState from);
    void SetQueueDepth(std::size_t depth);
    void AddBytesIn(std::uint64_t n);
    void AddBytesOut(std::uint64_t n);
    void CountUpload(bool ok);
    /// Disk retention (worker/retention.h): bytes of stored blobs, bytes reserved (upload part
    /// files, results being written), the quota (0 = none), upload bytes in flight.
    void SetDisk(std::uint64_t stored, std::uint64_t reserved, std::uint64_t quota,
                 std::uint64_t upload_inflight);
    /// One eviction: kind "cloud"/"result", cause "lru"/"ttl", bytes freed.
    void CountEviction(const std::string& kind, const std::string& cause, std::uint64_t bytes);

private:
    std::shared_ptr<prometheus::Registry> registry_;
    std::unique_ptr<prometheus::Exposer> exposer_;
    prometheus::Family<prometheus::Counter>* jobs_;
    prometheus::Family<prometheus::Gauge>* running_;
    prometheus::Family<prometheus::Histogram>* duration_;
    prometheus::Gauge* queue_depth_;
    prometheus::Counter* bytes_in_;
    prometheus::Counter* bytes_out_;
    prometheus::Family<prometheus::Counter>* uploads_;
    prometheus::Gauge* disk_stored_;
    prometheus::Gauge* disk_reserved_;
    prometheus::Gauge* disk_quota_;
    prometheus::Gauge* upload_inflight_;
    prometheus::Family<prometheus::Counter>* evictions_;
    prometheus::Family<prometheus::Counter>* evicted_bytes_;
};

}  // namespace surfel::server
