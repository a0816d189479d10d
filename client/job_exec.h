#pragma once
/// \file
/// One path for every job subcommand: run a surfel.v1.JobSpec in-process through the worker's
/// job-kind table (the embedded default), or through a server with --server host:port (upload if
/// needed, submit, watch with progress, receive the result). Both write the result file and
/// return the job's JSON report.

#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "cli_common.h"
#include "service_client.h"
#include "surfel/v1/surfel.pb.h"

namespace surfel::cli {

/// How to reach a server with auth or TLS (docs/security.md): --token (or SURFEL_TOKEN),
/// --ca FILE (TLS, this CA), --tls (TLS, system roots), --cert/--key (mutual TLS).
struct ConnectFlags {
    client::ConnectOptions options;
};

/// Adds --token, --ca, --tls, --cert and --key.
void AddConnectFlags(CLI::App* sub, ConnectFlags* flags);

/// Options every job subcommand shares beyond --json/--quiet.
struct JobFlags {
    std::string server;     ///< host:port; empty = in-process
    ConnectFlags connect;   ///< --token, --ca, ... for --server
    double timeout_s = 0;   ///< > 0: the job fails with DEADLINE_EXCEEDED past it
    bool detach = false;    ///< --server only: submit and print the job id without waiting
};

/// A progress bar for byte transfers (upload, download); empty when quiet or not a terminal.
client::ByteProgress ByteProgressBar(const std::string& label, const CommonFlags& flags);

/// Adds --server, --timeout and --detach.
void AddJobFlags(CLI::App* sub, JobFlags* flags);

/// Runs `spec` on the clouds in `inputs` (one file per input of its kind, in the kind's order;
/// their cloud ids are filled in here: in-process each id is the file's path, with --server the
/// id of its upload), writes the result to `output` and returns the report (with "output", and
/// "job_id"/"server" when remote). Invalid options throw UsageError; other failures
/// surfel::Error or client::RpcError.
nlohmann::json ExecuteJob(v1::JobSpec spec, const std::vector<std::string>& inputs, const std::string& output,
                          const CommonFlags& flags, const JobFlags& job_flags);

}  // namespace surfel::cli
