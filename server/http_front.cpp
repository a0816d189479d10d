#include "http_front.h"

#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <httplib.h>
#include <spdlog/spdlog.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <exception>
#include <fstream>
#include <future>
#include <random>
#include <sstream>
#include <thread>
#include <vector>

#include "http_events.h"
#include "surfel/base/error.h"
#include "surfel/worker/status.h"
#include "upload_session.h"

namespace surfel::server {

// ---- Status mapping (google/rpc/code.proto) ---------------------------------------------------

int HttpStatusFromCode(int grpc_code) {
    switch (static_cast<grpc::StatusCode>(grpc_code)) {
        case grpc::StatusCode::OK:
            return 200;
        case grpc::StatusCode::CANCELLED:
            return 499;
        case grpc::StatusCode::UNKNOWN:
            return 500;
        case grpc::StatusCode::INVALID_ARGUMENT:
            return 400;
        case grpc::StatusCode::DEADLINE_EXCEEDED:
            return 504;
        case grpc::StatusCode::NOT_FOUND:
            return 404;
        case grpc::StatusCode::ALREADY_EXISTS:
            return 409;
        case grpc::StatusCode::PERMISSION_DENIED:
            return 403;
        case grpc::StatusCode::UNAUTHENTICATED:
            return 401;
        case grpc::StatusCode::RESOURCE_EXHAUSTED:
            return 429;
        case grpc::StatusCode::FAILED_PRECONDITION:
            return 400;
        case grpc::StatusCode::ABORTED:
            return 409;
        case grpc::StatusCode::OUT_OF_RANGE:
            return 400;
        case grpc::StatusCode::UNIMPLEMENTED:
            return 501;
        case grpc::StatusCode::INTERNAL:
            return 500;
        case grpc::StatusCode::UNAVAILABLE:
            return 503;
        case grpc::StatusCode::DATA_LOSS:
            return 500;
        case grpc::StatusCode::DO_NOT_USE:
            break;
    }
    return 500;
}

namespace {

namespace pbu = google::protobuf::util;
using httplib::ContentReader;
using httplib::DataSink;
using httplib::Request;
using httplib::Response;

constexpr const char* kJson = "application/json";
constexpr std::size_t kUploadBlock = 256 * 1024;  // bytes gathered per UploadSession::Append

// ---- JSON in and out (protobuf's proto3 JSON mapping; no hand-written JSON) -----------------

std::string ToJson(const google::protobuf::Message& m) {
    pbu::JsonPrintOptions options;
    options.always_print_primitive_fields = true;
    std::string out;
    const auto status = pbu::MessageToJsonString(m, &out, options);
    if (!status.ok())
        throw Error(ErrorCode::kInternal, "printing " + m.GetTypeName() + ": " + status.ToString());
    return out;
}

void SendMessage(Response& res, const google::protobuf::Message& m) {
    res.status = 200;
    res.set_content(ToJson(m), kJson);
}

// A google.rpc.Status-shaped body {code, message, details: []}, built as a google.protobuf.Struct
// (google/rpc/status.proto is not in Debian's libprotobuf-dev).
void SendStatus(Response& res, grpc::StatusCode code, const std::string& message,
                int http_status = 0) {
    google::protobuf::Struct body;
    auto& fields = *body.mutable_fields();
    fields["code"].set_number_value(static_cast<int>(code));
    fields["message"].set_string_value(message);
    fields["details"].mutable_list_value();
    res.status = http_status ? http_status : HttpStatusFromCode(static_cast<int>(code));
    if (code == grpc::StatusCode::UNAUTHENTICATED)
        res.set_header("WWW-Authenticate", "Bearer realm=\"surfel\"");  // RFC 6750
    pbu::JsonPrintOptions options;
    std::string out;
    (void)pbu::MessageToJsonString(body, &out, options);
    res.set_content(out, kJson);
}

// Runs a route and answers what it throws with the mapped status; nothing escapes uncaught.
template <typename Fn>
void Guard(const Request& req, Response& res, Fn&& fn) {
    try {
        fn();
    } catch (...) {
        const grpc::Status s = worker::CurrentExceptionStatus();
        spdlog::debug("HTTP {} {}: {}", req.method, req.path, s.error_message());
        SendStatus(res, s.error_code(), s.error_message());
    }
}

template <typename M>
M ParseJson(const std::string& body, const std::string& what) {
    M m;
    pbu::JsonParseOptions options;
    options.ignore_unknown_fields = false;
    if (body.empty())
        throw Error(ErrorCode::kInvalidArgument,
                    what + ": the request body is empty (a JSON object)");
    const auto status = pbu::JsonStringToMessage(body, &m, options);
    if (!status.ok())
        throw Error(ErrorCode::kInvalidArgument, what + ": " + std::string(status.message()));
    return m;
}

// Reads a small body through the content reader, refusing more than `max` bytes.
std::string ReadSmallBody(const ContentReader& reader, std::size_t max, const std::string& what) {
    std::string body;
    bool too_big = false;
    reader([&](const char* data, std::size_t n) {
        if (body.size() + n > max) {
            too_big = true;
            return false;
        }
        body.append(data, n);
        return true;
    });
    if (too_big)
        throw Error(ErrorCode::kInvalidArgument,
                    what + ": the body exceeds " + std::to_string(max) + " bytes");
    return body;
}

std::string RandomUploadId() {
    std::random_device rd;
    std::ostringstream s;
    s << "http-" << std::hex;
    for (int i = 0; i < 4; ++i) s << rd();
    return s.str();
}

std::uint64_t ParseUint(const std::string& text, const std::string& field) {
    try {
        std::size_t used = 0;
        const unsigned long long v = std::stoull(text, &used);
        if (used == text.size() && !text.empty() && text[0] != '-') return v;
    } catch (const std::exception&) {
    }
    throw Error(ErrorCode::kInvalidArgument,
                field + ": '" + text + "' is not a non-negative integer");
}

// ---- Range (RFC 9110 §14): cpp-httplib 0.11 answers a malformed Range with 416 and cuts the
// ranges it parsed itself, but serves a range past the end as if the bytes were there (a wrong
// Content-Length). This drops the unsatisfiable ranges of a body of `size` bytes and clamps the
// rest to it; false when none is left (416).
bool FitRanges(httplib::Ranges& ranges, std::uint64_t size) {
    const auto n = static_cast<ssize_t>(size);
    std::erase_if(ranges, [n](const httplib::Range& r) {
        if (r.first < 0) return r.second <= 0 || n == 0;  // "-k": the last k bytes
        return r.first >= n || (r.second >= 0 && r.second < r.first);
    });
    for (httplib::Range& r : ranges)
        if (r.second >= n) r.second = n - 1;
    return !ranges.empty();
}

std::string SseFrame(const NumberedEvent& e) {
    return "id: " + std::to_string(e.id) + "\ndata: " + ToJson(e.event) + "\n\n";
}

}  // namespace

// ---- HttpFront --------------------------------------------------------------------------------
//
// Threads. cpp-httplib runs each connection on one thread of a fixed pool (options.threads) for
// the connection's whole life. Routes do what the gRPC unary handlers do (indexed SQLite work)
// inline; an upload body is streamed to the part file chunk by chunk as the ContentReader
// delivers it (never buffered whole), and the session's Finish (parse, validate, store) runs on
// the shared ingest Executor while the connection thread waits — a full ingest queue is 429,
// as in gRPC. An event stream blocks its thread in JobEventLog::WaitAfter, at most
// sse_keepalive_ms at a time, and returns false once the sink is no longer writable (so a
// client that leaves never makes 0.11's chunked writer spin: yhirose/cpp-httplib#1475).
struct HttpFront::Impl {
    Impl(Operations& o, HttpOptions opt) : ops(o), options(std::move(opt)), logs(o.jobs()) {}

    Operations& ops;
    HttpOptions options;
    JobEventLogs logs;
    std::unique_ptr<httplib::Server> server_ptr = MakeServer(options);
    httplib::Server& server = *server_ptr;

    // HTTPS when a certificate is given; mutual TLS with a client CA (cpp-httplib then sets
    // SSL_VERIFY_PEER | SSL_VERIFY_FAIL_IF_NO_PEER_CERT).
    static std::unique_ptr<httplib::Server> MakeServer(const HttpOptions& o) {
        if (o.tls_cert.empty() != o.tls_key.empty())
            throw Error(ErrorCode::kInvalidArgument, "--tls-cert and --tls-key go together");
        if (o.tls_cert.empty()) {
            if (!o.tls_client_ca.empty())
                throw Error(ErrorCode::kInvalidArgument, "--tls-client-ca needs --tls-cert and --tls-key");
            return std::make_unique<httplib::Server>();
        }
        auto s = std::make_unique<httplib::SSLServer>(
            o.tls_cert.c_str(), o.tls_key.c_str(),
            o.tls_client_ca.empty() ? nullptr : o.tls_client_ca.c_str());
        if (!s->is_valid())
            throw Error(ErrorCode::kInvalidArgument,
                        "HTTP TLS: cannot load certificate " + o.tls_cert + " / key " + o.tls_key +
                            (o.tls_client_ca.empty() ? "" : " / client CA " + o.tls_client_ca));
        return s;
    }

    // The caller of an API request (its Authorization header); throws kUnauthenticated.
    Caller Who(const Request& req) const {
        return ops.auth().Authenticate(req.get_header_value("Authorization"));
    }

    // The caller of an event stream: the Authorization header, or a signed URL
    // (?exp=UNIX_MS&sig=HEX from POST /v1/jobs/{id}:eventsUrl) since EventSource sends no headers.
    Caller EventsCaller(const Request& req, const std::string& job_id) const {
        if (!ops.auth().enabled() || !req.has_param("sig")) return Who(req);
        const auto refuse = [] {
            return Error(ErrorCode::kUnauthenticated,
                         "the signed events URL is invalid or expired: sign a new one "
                         "(POST /v1/jobs/{id}:eventsUrl)");
        };
        std::int64_t exp = 0;
        try {
            exp = std::stoll(req.get_param_value("exp"));
        } catch (const std::exception&) {
            throw refuse();
        }
        const std::optional<v1::Job> job = ops.jobs().Get(job_id);
        if (!job || !ops.url_signer().Verify(job_id, job->tenant(), exp, req.get_param_value("sig"),
                                             worker::NowUnixMs()))
            throw refuse();
        return Caller{job->tenant(), true};
    }
    std::thread listener;
    int port = 0;
    std::atomic<bool> stopped{false};

    bool OriginAllowed(const std::string& origin) const {
        for (const std::string& o : options.cors_origins)
            if (o == "*" || o == origin) return true;
        return false;
    }

    // CORS on every response to an allowed origin; preflights answered here.
    httplib::Server::HandlerResponse PreRouting(const Request& req, Response& res) {
        const std::string origin = req.get_header_value("Origin");
        const bool allowed = !origin.empty() && OriginAllowed(origin);
        if (allowed) {
            res.set_header("Access-Control-Allow-Origin", origin);
            res.set_header("Vary", "Origin");
            res.set_header("Access-Control-Expose-Headers",
                           "Content-Disposition, Content-Range, Content-Length");
        }
        if (req.method != "OPTIONS") return httplib::Server::HandlerResponse::Unhandled;
        if (!allowed) {
            SendStatus(res, grpc::StatusCode::PERMISSION_DENIED,
                       origin.empty()
                           ? std::string(
                                 "OPTIONS: only CORS preflights (with an Origin header) are served")
                           : "origin " + origin + " is not allowed (--http-cors-origins)");
            return httplib::Server::HandlerResponse::Handled;
        }
        res.status = 204;
        res.set_header("Access-Control-Allow-Methods", "GET, POST, DELETE, OPTIONS");
        const std::string asked = req.get_header_value("Access-Control-Request-Headers");
        res.set_header("Access-Control-Allow-Headers",
                       asked.empty() ? "Content-Type, Range, Last-Event-ID, Authorization" : asked);
        res.set_header("Access-Control-Max-Age", "600");
        return httplib::Server::HandlerResponse::Handled;
    }

    // POST /v1/clouds?filename=NAME — the file as the raw body.
    void Upload(const Request& req, Response& res, const ContentReader& reader) {
        UploadSession session(ops, Who(req), RandomUploadId(), req.get_param_value("filename"));
        bool done = false;
        // The bytes of `block` counted in the in-flight total, each piece before it is copied
        // in (over the limit: RESOURCE_EXHAUSTED naming it); Append takes the count over.
        std::uint64_t counted = 0;
        try {
            if (req.has_header("Content-Length")) {
                session.ExpectSize(ParseUint(req.get_header_value("Content-Length"), "Content-Length"));
                res.set_header("Connection",
                               "close");  // in case of an error before the body is read
            }
            // httplib hands the body over in 4 KiB reads; the session writes (and flushes) each
            // Append, so pieces are gathered into kUploadBlock before they go to the part file.
            std::exception_ptr error;
            std::string block;
            block.reserve(kUploadBlock);
            const bool complete = reader([&](const char* data, std::size_t n) {
                try {
                    ops.ReserveInflight(n, session.id());
                    counted += n;
                    block.append(data, n);
                    if (block.size() >= kUploadBlock) {
                        counted = 0;
                        session.Append(block);
                        block.clear();
                    }
                    return true;
                } catch (...) {
                    error = std::current_exception();
                    return false;
                }
            });
            if (error) std::rethrow_exception(error);
            if (!complete) throw Error(ErrorCode::kInvalidArgument, "the upload body ended early");
            if (!block.empty()) {
                counted = 0;
                session.Append(block);
            }
            res.headers.erase("Connection");
            auto promise = std::make_shared<std::promise<v1::Cloud>>();
            auto future = promise->get_future();
            const bool queued = ops.ingest().TrySubmit([&session, promise] {
                try {
                    promise->set_value(session.Finish());
                } catch (...) {
                    promise->set_exception(std::current_exception());
                }
            });
            if (!queued)
                throw Error(ErrorCode::kResourceExhausted,
                            "the server is busy ingesting other uploads, try again");
            done = true;  // Finish removes the part file, whatever the outcome
            SendMessage(res, future.get());
        } catch (...) {
            ops.ReleaseInflight(counted);
            if (!done) session.Discard();
            throw;
        }
    }

    // GET /v1/jobs/{id}/events — Server-Sent Events.
    void Events(const Request& req, Response& res, const std::string& job_id) {
        const Caller caller = EventsCaller(req, job_id);
        if (caller.scoped) ops.GetJob(caller, job_id);  // NOT_FOUND for another tenant's job
        std::shared_ptr<JobEventLog> log = logs.Open(job_id);
        if (!log) throw Error(ErrorCode::kNotFound, "job " + job_id + " not found");
        std::uint64_t after = 0;
        if (req.has_header("Last-Event-ID")) {
            after = ParseUint(req.get_header_value("Last-Event-ID"), "Last-Event-ID");
            if (after > log->LastId())
                after = 0;  // not one of ours (a restarted server): from the start
            if (log->Final() && after == log->LastId()) {
                res.status =
                    204;  // the client has seen the final event; 204 stops EventSource reconnecting
                return;
            }
        }
        res.set_header("Cache-Control", "no-cache");
        res.set_header("X-Accel-Buffering", "no");
        const auto keepalive = std::chrono::milliseconds(options.sse_keepalive_ms);
        auto cursor = std::make_shared<std::uint64_t>(after);
        res.set_chunked_content_provider(
            "text/event-stream", [log, cursor, keepalive](std::size_t, DataSink& sink) {
                if (!sink.is_writable()) return false;
                std::vector<NumberedEvent> batch;
                switch (log->WaitAfter(*cursor, keepalive, &batch)) {
                    case JobEventLog::Wait::kStopped:
                        sink.done();
                        return true;
                    case JobEventLog::Wait::kTimeout:
                        return sink.write(": keep-alive\n\n", 14);
                    case JobEventLog::Wait::kEvents:
                        break;
                }
                for (const NumberedEvent& e : batch) {
                    const std::string frame = SseFrame(e);
                    if (!sink.write(frame.data(), frame.size())) return false;
                    *cursor = e.id;
                    if (e.event.has_finished() || e.event.has_failed()) {
                        sink.done();
                        return true;
                    }
                }
                return true;
            });
    }

    // POST /v1/jobs/{id}:eventsUrl -> {"url": "/v1/jobs/{id}/events?exp=..&sig=..", "expiresUnixMs"}
    void EventsUrl(const Request& req, Response& res, const std::string& job_id) {
        const Caller caller = Who(req);
        const v1::Job job = ops.GetJob(caller, job_id);
        std::string url = "/v1/jobs/" + job_id + "/events";
        const std::int64_t exp = worker::NowUnixMs() + options.events_url_ttl_ms;
        if (ops.auth().enabled())
            url += "?exp=" + std::to_string(exp) +
                   "&sig=" + ops.url_signer().Sign(job_id, job.tenant(), exp);
        google::protobuf::Struct body;
        (*body.mutable_fields())["url"].set_string_value(url);
        (*body.mutable_fields())["expiresUnixMs"].set_string_value(std::to_string(exp));
        SendMessage(res, body);
    }

    // GET /v1/jobs/{id}/result — the bytes, with Range.
    void Result(const Request& req, Response& res, const std::string& job_id) {
        const ResultFile r = ops.Result(Who(req), job_id);
        // The Request is httplib's own, mutable object; only its parsed ranges are fitted.
        auto& ranges = const_cast<Request&>(req).ranges;
        if (!ranges.empty() && !FitRanges(ranges, r.size)) {
            res.set_header("Content-Range", "bytes */" + std::to_string(r.size));
            SendStatus(res, grpc::StatusCode::OUT_OF_RANGE,
                       "Range " + req.get_header_value("Range") + ": the result of job " + job_id +
                           " has " + std::to_string(r.size) + " bytes",
                       416);
            return;
        }
        const std::string type = r.job.result().media_type().empty() ? "application/octet-stream"
                                                                     : r.job.result().media_type();
        const bool inline_image = type == "image/png";
        res.set_header("Content-Disposition", std::string(inline_image ? "inline" : "attachment") +
                                                  "; filename=\"" + r.filename + "\"");
        res.set_header("Accept-Ranges", "bytes");
        // The blob, read in chunks; a whole-body GET is checked against the result's SHA-256
        // (VerifyingReader): on a mismatch the last chunk is never sent and the connection is
        // closed short of Content-Length, so a client never takes a corrupt body as complete.
        std::unique_ptr<worker::BlobReader> raw = ops.store().blobs().Open(r.key);
        if (!raw) throw Error(ErrorCode::kNotFound, "result of job " + job_id + " is gone");
        auto in = std::make_shared<worker::VerifyingReader>(std::move(raw), r.job.result().sha256(),
                                                            "result of job " + job_id);
        const std::size_t chunk = ops.limits().download_chunk_bytes;
        Metrics* metrics = &ops.metrics();
        auto position = std::make_shared<std::uint64_t>(0);
        res.set_content_provider(
            r.size, type,
            [in, chunk, metrics, position, job_id](std::size_t offset, std::size_t length,
                                                   DataSink& sink) {
                if (!sink.is_writable()) return false;
                std::string buf(std::min(length, chunk), '\0');
                std::size_t n = 0;
                try {
                    if (offset != *position) in->Seek(offset);
                    while (n < buf.size()) {
                        const std::size_t got = in->Read(buf.data() + n, buf.size() - n);
                        if (got == 0) break;
                        n += got;
                    }
                } catch (const std::exception& e) {
                    spdlog::error("HTTP GET result of job {}: {}", job_id, e.what());
                    return false;
                }
                *position = offset + n;
                if (n == 0) return false;  // the blob got shorter
                metrics->AddBytesOut(n);
                return sink.write(buf.data(), n);
            });
    }

    void Routes() {
        auto& s = server;
        s.set_pre_routing_handler(
            [this](const Request& req, Response& res) { return PreRouting(req, res); });

        s.Post("/v1/clouds",
               [this](const Request& req, Response& res, const ContentReader& reader) {
                   Guard(req, res, [&] { Upload(req, res, reader); });
               });
        s.Get(R"(/v1/clouds/([^/]+))", [this](const Request& req, Response& res) {
            Guard(req, res, [&] { SendMessage(res, ops.GetCloud(Who(req), req.matches[1])); });
        });
        s.Delete(R"(/v1/clouds/([^/]+))", [this](const Request& req, Response& res) {
            Guard(req, res, [&] {
                ops.DeleteCloud(Who(req), req.matches[1]);
                v1::DeleteCloudResponse r;
                r.set_deleted(true);
                SendMessage(res, r);
            });
        });
        s.Post("/v1/jobs", [this](const Request& req, Response& res, const ContentReader& reader) {
            Guard(req, res, [&] {
                const Caller caller = Who(req);
                const auto spec = ParseJson<v1::JobSpec>(
                    ReadSmallBody(reader, options.max_spec_bytes, "JobSpec"), "JobSpec");
                SendMessage(res, ops.Submit(caller, spec));
            });
        });
        s.Get("/v1/jobs", [this](const Request& req, Response& res) {
            Guard(req, res, [&] {
                const Caller caller = Who(req);
                std::uint32_t limit = 0;
                if (req.has_param("limit")) {
                    const std::uint64_t l = ParseUint(req.get_param_value("limit"), "limit");
                    limit = static_cast<std::uint32_t>(std::min<std::uint64_t>(l, 1u << 30));
                }
                v1::JobState state = v1::JOB_STATE_UNSPECIFIED;
                if (req.has_param("state") &&
                    !v1::JobState_Parse(req.get_param_value("state"), &state))
                    throw Error(ErrorCode::kInvalidArgument,
                                "state: '" + req.get_param_value("state") +
                                    "' is not a JobState (QUEUED, RUNNING, ...)");
                v1::ListJobsResponse r;
                for (v1::Job& j : ops.ListJobs(caller, limit, state)) *r.add_jobs() = std::move(j);
                SendMessage(res, r);
            });
        });
        s.Get(R"(/v1/jobs/([^/:]+))", [this](const Request& req, Response& res) {
            Guard(req, res, [&] { SendMessage(res, ops.GetJob(Who(req), req.matches[1])); });
        });
        s.Post(R"(/v1/jobs/([^/:]+):cancel)", [this](const Request& req, Response& res) {
            Guard(req, res, [&] { SendMessage(res, ops.Cancel(Who(req), req.matches[1])); });
        });
        // A short-lived URL of the job's event stream for EventSource, which cannot send an
        // Authorization header (docs/security.md). Without auth the plain path is returned.
        s.Post(R"(/v1/jobs/([^/:]+):eventsUrl)", [this](const Request& req, Response& res) {
            Guard(req, res, [&] { EventsUrl(req, res, req.matches[1]); });
        });
        s.Get(R"(/v1/jobs/([^/:]+)/events)", [this](const Request& req, Response& res) {
            Guard(req, res, [&] { Events(req, res, req.matches[1]); });
        });
        s.Get(R"(/v1/jobs/([^/:]+)/result)", [this](const Request& req, Response& res) {
            Guard(req, res, [&] { Result(req, res, req.matches[1]); });
        });

        // The page, and Debian's three.js beside it.
        if (!options.web_root.empty() && !s.set_mount_point("/", options.web_root))
            spdlog::warn("HTTP: no web page: {} is not a directory (--web-root)", options.web_root);
        if (!options.three_root.empty() && !s.set_mount_point("/three", options.three_root))
            spdlog::warn("HTTP: no 3D preview: {} is not a directory (install libjs-three)",
                         options.three_root);

        // Whatever no route answered (an unknown path or method) gets a Status body too.
        s.set_error_handler([](const Request& req, Response& res) {
            if (!res.body.empty() || res.status == 204) return;
            if (res.status == 404)
                SendStatus(res, grpc::StatusCode::NOT_FOUND,
                           req.method + " " + req.path + ": no such route");
            else if (res.status == 416)
                SendStatus(res, grpc::StatusCode::OUT_OF_RANGE,
                           "Range " + req.get_header_value("Range") + ": malformed", 416);
            else if (res.status == 413)
                SendStatus(res, grpc::StatusCode::RESOURCE_EXHAUSTED,
                           "the request body is too large", 413);
            else
                SendStatus(res, grpc::StatusCode::INVALID_ARGUMENT,
                           req.method + " " + req.path + ": bad request", res.status);
        });
        s.set_exception_handler([](const Request&, Response& res, std::exception_ptr ep) {
            try {
                std::rethrow_exception(ep);
            } catch (...) {
                const grpc::Status st = worker::CurrentExceptionStatus();
                SendStatus(res, st.error_code(), st.error_message());
            }
        });
        s.set_logger([](const Request& req, const Response& res) {
            spdlog::debug("HTTP {} {} -> {}", req.method, req.path, res.status);
        });
    }
};

HttpFront::HttpFront(Operations& ops, HttpOptions options)
    : impl_(std::make_unique<Impl>(ops, std::move(options))) {
    const std::size_t threads = std::max<std::size_t>(impl_->options.threads, 2);
    impl_->server.new_task_queue = [threads] { return new httplib::ThreadPool(threads); };
    impl_->server.set_keep_alive_timeout(5);
    impl_->server.set_read_timeout(30);
    impl_->server.set_write_timeout(30);
    impl_->Routes();
}

HttpFront::~HttpFront() { Stop(); }

void HttpFront::Start() {
    auto& s = impl_->server;
    const std::string& host = impl_->options.host;
    if (impl_->options.port == 0) {
        impl_->port = s.bind_to_any_port(host);
    } else if (s.bind_to_port(host, impl_->options.port)) {
        impl_->port = impl_->options.port;
    }
    if (impl_->port <= 0)
        throw Error(ErrorCode::kUnavailable,
                    "HTTP: cannot listen on " + host + ":" + std::to_string(impl_->options.port));
    impl_->listener = std::thread([this] { impl_->server.listen_after_bind(); });
}

int HttpFront::port() const { return impl_->port; }

void HttpFront::Stop() {
    if (impl_->stopped.exchange(true)) return;
    impl_->logs.Stop();
    impl_->server.stop();
    if (impl_->listener.joinable()) impl_->listener.join();
}

}  // namespace surfel::server
