#include "job_exec.h"

#include "service_client.h"
#include "surfel/base/error.h"
#include "surfel/io/file_bytes.h"
#include "surfel/worker/job_kind.h"
#include "surfel/worker/status.h"

namespace surfel::cli {
client::ByteProgress ByteProgressBar(const std::string& label, const CommonFlags& flags) {
    const ProgressFn bar = MakeProgressBar(label, flags);
    if (!bar) return {};
    return [bar](std::uint64_t done, std::uint64_t total) { bar(total ? double(done) / double(total) : 1.0); };
}

void AddConnectFlags(CLI::App* sub, ConnectFlags* flags) {
    sub->add_option("--token", flags->options.token,
                    "Bearer token for a server started with --auth-tokens")
        ->envname("SURFEL_TOKEN");
    sub->add_option("--ca", flags->options.ca_file,
                    "Connect with TLS, trusting the CA in this PEM file (the server's --tls-cert issuer)")
        ->check(CLI::ExistingFile);
    sub->add_flag("--tls", flags->options.tls, "Connect with TLS, trusting the system's root certificates");
    sub->add_option("--cert", flags->options.cert_file, "Mutual TLS: this client's certificate (PEM)")
        ->check(CLI::ExistingFile);
    sub->add_option("--key", flags->options.key_file, "Mutual TLS: the key of --cert (PEM)")
        ->check(CLI::ExistingFile);
}

void AddJobFlags(CLI::App* sub, JobFlags* flags) {
    AddConnectFlags(sub, &flags->connect);
    sub->add_option("--server", flags->server, "Run on a surfel-server at host:port instead of in-process")
        ->envname("SURFEL_SERVER");
    sub->add_option("--timeout", flags->timeout_s, "Fail the job with DEADLINE_EXCEEDED after this many seconds")
        ->check(CLI::NonNegativeNumber);
    sub->add_flag("--detach", flags->detach, "With --server: submit, print the job id and return");
}

nlohmann::json ExecuteJob(v1::JobSpec spec, const std::vector<std::string>& inputs, const std::string& output,
                          const CommonFlags& flags, const JobFlags& job_flags) {
    const worker::JobKind& kind = worker::KindOf(spec);
    SURFEL_CHECK(inputs.size() == kind.InputCount(spec), kind.Name() << " takes " << kind.InputCount(spec) << " inputs");
    const std::string label(kind.Name());
    if (job_flags.timeout_s > 0) spec.set_timeout_ms(static_cast<std::int64_t>(job_flags.timeout_s * 1000));
    // Options first, before any work: a bad value is a usage error. In-process, a cloud's id is
    // its file's path.
    for (std::size_t i = 0; i < inputs.size(); ++i) kind.SetInput(spec, i, inputs[i]);
    try {
        worker::ValidateSpec(spec);
    } catch (const Error& e) {
        throw UsageError(e.what());
    }
    if (job_flags.detach && job_flags.server.empty()) throw UsageError("--detach needs --server");

    if (job_flags.server.empty()) {
        const worker::JobOutput out = worker::RunJob(
            spec, [](const std::string& path) { return std::make_shared<const PointCloud>(LoadCloud(path)); },
            MakeProgressBar(label, flags), [&](std::uint64_t estimate) {
                // In-process the limit is what the machine has now (docs/memory.md).
                worker::CheckJobMemory(spec, estimate, worker::AvailableMemory(), "the memory available");
            });
        WriteFileBytes(output, out.bytes);
        nlohmann::json report = out.report;
        report["output"] = output;
        return report;
    }

    client::ServiceClient client(job_flags.server, 30.0, job_flags.connect.options);
    std::vector<std::string> cloud_ids;
    for (std::size_t i = 0; i < inputs.size(); ++i) {
        cloud_ids.push_back(client.UploadFile(inputs[i], ByteProgressBar("upload", flags)).id());
        kind.SetInput(spec, i, cloud_ids.back());
    }
    // One input: "cloud_id" as before; several: "cloud_ids" in the kind's order.
    const nlohmann::json cloud_json = cloud_ids.size() == 1 ? nlohmann::json(cloud_ids[0]) : nlohmann::json(cloud_ids);
    const char* cloud_key = cloud_ids.size() == 1 ? "cloud_id" : "cloud_ids";
    const v1::Job job = client.Submit(spec);
    if (job_flags.detach)
        return {{"job_id", job.id()}, {"state", v1::JobState_Name(job.state())}, {"reused", job.reused()},
                {cloud_key, cloud_json}, {"server", job_flags.server}};
    const ProgressFn bar = MakeProgressBar(label, flags);
    const client::WatchOutcome done = client.Watch(
        job.id(), /*include_result=*/true, /*cancel_on_disconnect=*/true,
        [&](const std::string&, double f) {
            if (bar) bar(f);
        },
        {}, ByteProgressBar("download", flags));
    if (done.state != v1::SUCCEEDED) {
        throw Error(worker::FromStatusCode(done.status_code), "job " + job.id() + " " + v1::JobState_Name(done.state) + ": " + done.status_message);
    }
    WriteFileBytes(output, done.bytes);
    nlohmann::json report = nlohmann::json::parse(done.result.report_json());
    report["output"] = output;
    report["job_id"] = job.id();
    report[cloud_key] = cloud_json;
    report["reused"] = job.reused();
    report["server"] = job_flags.server;
    return report;
}

}  // namespace surfel::cli
