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
};

}  // namespace surfel::server
