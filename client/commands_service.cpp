// surfel upload | jobs | job | cancel | download: talking to a surfel-server.
#include <ctime>

#include "cli_common.h"
#include "job_exec.h"
#include "service_client.h"
#include "surfel/io/file_bytes.h"

namespace surfel::cli {
namespace {

struct ServerArgs {
    std::string server;
    ConnectFlags connect;
    CommonFlags flags;
};

void AddServer(CLI::App* sub, ServerArgs* a) {
    sub->add_option("--server", a->server, "surfel-server at host:port")->envname("SURFEL_SERVER")->required();
    AddConnectFlags(sub, &a->connect);
    AddCommonFlags(sub, &a->flags);
}

nlohmann::json JobJson(const v1::Job& j) {
    nlohmann::json out = {{"id", j.id()},
                          {"type", j.type()},
                          {"state", v1::JobState_Name(j.state())},
                          {"created_unix_ms", j.created_unix_ms()}};
    if (j.state() == v1::RUNNING) {
        out["stage"] = j.stage();
        out["fraction"] = j.fraction();
    }
    if (j.finished_unix_ms() && j.started_unix_ms())
        out["run_ms"] = j.finished_unix_ms() - j.started_unix_ms();
    if (j.state() == v1::SUCCEEDED) {
        out["result"] = {{"media_type", j.result().media_type()},
                         {"size_bytes", j.result().size_bytes()},
                         {"points", j.result().points()},
                         {"time_ms", j.result().time_ms()},
                         {"sha256", j.result().sha256()}};
        if (!j.result().report_json().empty()) out["report"] = nlohmann::json::parse(j.result().report_json());
    }
    if (j.state() == v1::FAILED || j.state() == v1::CANCELLED) {
        out["status_code"] = j.status_code();
        out["status_message"] = j.status_message();
    }
    if (j.reused()) out["reused"] = true;
    return out;
}

std::string Clock(std::int64_t unix_ms) {
    const std::time_t t = static_cast<std::time_t>(unix_ms / 1000);
    char buf[32];
    std::strftime(buf, sizeof buf, "%Y-%m-%d %H:%M:%S", std::gmtime(&t));
    return buf;
}

}  // namespace

void RegisterServiceCommands(CLI::App& app) {
    {
        struct Args : ServerArgs {
            std::string input;
        };
        auto a = std::make_shared<Args>();
        auto* sub = app.add_subcommand("upload", "Upload a PLY/XYZ file to a server; prints the cloud id");
        sub->add_option("input", a->input, "PLY or XYZ file")->required()->check(CLI::ExistingFile);
        AddServer(sub, a.get());
        sub->footer("Uploads are content-addressed (SHA-256) and resumable: running it again after a broken\n"
                    "connection continues where the server stopped; a file it already has is not sent.\n"
                    "Example:\n  surfel upload bunny.ply --server localhost:50051 --json");
        sub->callback([a] {
            client::ServiceClient c(a->server, 30.0, a->connect.options);
            Stopwatch watch;
            const v1::Cloud cloud = c.UploadFile(a->input, ByteProgressBar("upload", a->flags));
            const double ms = watch.ElapsedMs();
            PrintReport({{"cloud_id", cloud.id()},
                         {"points", cloud.points()},
                         {"size_bytes", cloud.size_bytes()},
                         {"format", cloud.format()},
                         {"attributes", std::vector<std::string>(cloud.attributes().begin(), cloud.attributes().end())},
                         {"deduplicated", cloud.deduplicated()},
                         {"mb_per_s", ms > 0 ? double(cloud.size_bytes()) / (1 << 20) / (ms / 1000.0) : 0.0},
                         {"time_ms", ms}},
                        a->flags);
        });
    }
    {
        struct Args : ServerArgs {
            std::uint32_t limit = 20;
            std::string state;
        };
        auto a = std::make_shared<Args>();
        auto* sub = app.add_subcommand("jobs", "List a server's jobs, newest first");
        sub->add_option("--limit", a->limit, "At most this many")->default_val(20)->check(CLI::Range(1, 10000));
        sub->add_option("--state", a->state, "Only jobs in this state")
            ->check(CLI::IsMember({"queued", "running", "succeeded", "failed", "cancelled"}));
        AddServer(sub, a.get());
        sub->footer("Example:\n  surfel jobs --server localhost:50051 --state running");
        sub->callback([a] {
            client::ServiceClient c(a->server, 30.0, a->connect.options);
            const v1::JobState state = a->state.empty() ? v1::JOB_STATE_UNSPECIFIED
                                                        : ParseProtoEnum("--state", a->state, &v1::JobState_Parse);
            const auto jobs = c.ListJobs(a->limit, state);
            if (a->flags.json) {
                nlohmann::json arr = nlohmann::json::array();
                for (const auto& j : jobs) arr.push_back(JobJson(j));
                PrintReport({{"jobs", arr}, {"count", jobs.size()}}, a->flags);
                return;
            }
            std::printf("%-18s %-9s %-10s %-19s %s\n", "ID", "TYPE", "STATE", "CREATED (UTC)", "DETAIL");
            for (const auto& j : jobs) {
                std::string detail;
                if (j.state() == v1::RUNNING) detail = j.stage() + " " + std::to_string(int(j.fraction() * 100)) + "%";
                if (j.state() == v1::SUCCEEDED)
                    detail = std::to_string(j.result().size_bytes()) + " bytes " + j.result().media_type();
                if (j.state() == v1::FAILED || j.state() == v1::CANCELLED) detail = j.status_message();
                std::printf("%-18s %-9s %-10s %-19s %s\n", j.id().c_str(), j.type().c_str(),
                            v1::JobState_Name(j.state()).c_str(), Clock(j.created_unix_ms()).c_str(), detail.c_str());
            }
        });
    }
    {
        struct Args : ServerArgs {
            std::string id;
        };
        auto a = std::make_shared<Args>();
        auto* sub = app.add_subcommand("job", "Show one job of a server (state, progress, report)");
        sub->add_option("id", a->id, "Job id")->required();
        AddServer(sub, a.get());
        sub->callback([a] {
            client::ServiceClient c(a->server, 30.0, a->connect.options);
            PrintReport(JobJson(c.GetJob(a->id)), a->flags);
        });
    }
    {
        struct Args : ServerArgs {
            std::string id;
        };
        auto a = std::make_shared<Args>();
        auto* sub = app.add_subcommand("cancel", "Cancel a queued or running job of a server");
        sub->add_option("id", a->id, "Job id")->required();
        AddServer(sub, a.get());
        sub->footer("A running job stops within 100 ms and ends CANCELLED.\nExample:\n"
                    "  surfel cancel j0123456789abcdef --server localhost:50051");
        sub->callback([a] {
            client::ServiceClient c(a->server, 30.0, a->connect.options);
            PrintReport(JobJson(c.Cancel(a->id)), a->flags);
        });
    }
    {
        struct Args : ServerArgs {
            std::string id, output;
        };
        auto a = std::make_shared<Args>();
        auto* sub = app.add_subcommand("download", "Write the result of a succeeded job to a file");
        sub->add_option("id", a->id, "Job id")->required();
        sub->add_option("-o,--output", a->output, "Output file")->required();
        AddServer(sub, a.get());
        sub->callback([a] {
            client::ServiceClient c(a->server, 30.0, a->connect.options);
            const std::uint64_t size = c.DownloadToFile(a->id, a->output, ByteProgressBar("download", a->flags));
            PrintReport({{"job_id", a->id}, {"output", a->output}, {"size_bytes", size}}, a->flags);
        });
    }
}

}  // namespace surfel::cli
