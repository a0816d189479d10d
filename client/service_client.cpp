#include "service_client.h"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <optional>
#include <sstream>
#include <thread>

#include "surfel/base/error.h"
#include "surfel/worker/sha256.h"
#include "upload_source.h"

namespace surfel::client {
namespace {

const char* CodeName(grpc::StatusCode code) {
    switch (code) {
        case grpc::StatusCode::OK: return "OK";
        case grpc::StatusCode::CANCELLED: return "CANCELLED";
        case grpc::StatusCode::UNKNOWN: return "UNKNOWN";
        case grpc::StatusCode::INVALID_ARGUMENT: return "INVALID_ARGUMENT";
        case grpc::StatusCode::DEADLINE_EXCEEDED: return "DEADLINE_EXCEEDED";
        case grpc::StatusCode::NOT_FOUND: return "NOT_FOUND";
        case grpc::StatusCode::ALREADY_EXISTS: return "ALREADY_EXISTS";
        case grpc::StatusCode::PERMISSION_DENIED: return "PERMISSION_DENIED";
        case grpc::StatusCode::RESOURCE_EXHAUSTED: return "RESOURCE_EXHAUSTED";
        case grpc::StatusCode::FAILED_PRECONDITION: return "FAILED_PRECONDITION";
        case grpc::StatusCode::ABORTED: return "ABORTED";
        case grpc::StatusCode::OUT_OF_RANGE: return "OUT_OF_RANGE";
        case grpc::StatusCode::UNIMPLEMENTED: return "UNIMPLEMENTED";
        case grpc::StatusCode::INTERNAL: return "INTERNAL";
        case grpc::StatusCode::UNAVAILABLE: return "UNAVAILABLE";
        case grpc::StatusCode::DATA_LOSS: return "DATA_LOSS";
        case grpc::StatusCode::UNAUTHENTICATED: return "UNAUTHENTICATED";
        default: return "?";
    }
}

void Check(const grpc::Status& status, const std::string& call) {
    if (!status.ok()) throw RpcError(status, call);
}

std::string FileSha256(const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    if (!in) throw std::runtime_error(path + ": cannot open");
    worker::Sha256 hash;
    std::string buf(1 << 20, '\0');
    while (in) {
        in.read(buf.data(), static_cast<std::streamsize>(buf.size()));
        hash.Update(std::string_view(buf.data(), static_cast<std::size_t>(in.gcount())));
    }
    return hash.FinishHex();
}

// One unary call with the client's deadline: the status, and the response in *resp.
template <typename Req, typename Resp, typename Method>
grpc::Status CallUnary(v1::Surfel::Stub* stub, Method method, const Req& req, Resp* resp, double timeout_s,
                       const std::string& token) {
    grpc::ClientContext ctx;
    if (!token.empty()) ctx.AddMetadata("authorization", "Bearer " + token);
    ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::milliseconds(static_cast<std::int64_t>(timeout_s * 1000)));
    return (stub->*method)(&ctx, req, resp);
}

}  // namespace

void ServiceClient::Authorize(grpc::ClientContext& ctx) const {
    if (!token_.empty()) ctx.AddMetadata("authorization", "Bearer " + token_);
}

RpcError::RpcError(const grpc::Status& status, const std::string& what)
    : std::runtime_error(what + ": " + CodeName(status.error_code()) + ": " + status.error_message()), status_(status) {}

static std::string ReadPemFile(const std::string& path, const char* what) {
    std::ifstream in(path, std::ios::binary);
    if (!in) throw std::runtime_error(std::string(what) + ": cannot read " + path);
    std::stringstream s;
    s << in.rdbuf();
    return s.str();
}

ServiceClient::ServiceClient(const std::string& target, double timeout_s, const ConnectOptions& options)
    : target_(target), timeout_s_(timeout_s), token_(options.token) {
    grpc::ChannelArguments args;
    args.SetMaxReceiveMessageSize(16 << 20);
    std::shared_ptr<grpc::ChannelCredentials> credentials = grpc::InsecureChannelCredentials();
    if (options.tls || !options.ca_file.empty() || !options.cert_file.empty() || !options.key_file.empty()) {
        if (options.cert_file.empty() != options.key_file.empty())
            throw std::runtime_error("--cert and --key go together");
        grpc::SslCredentialsOptions ssl;
        if (!options.ca_file.empty()) ssl.pem_root_certs = ReadPemFile(options.ca_file, "--ca");
        if (!options.cert_file.empty()) {
            ssl.pem_cert_chain = ReadPemFile(options.cert_file, "--cert");
            ssl.pem_private_key = ReadPemFile(options.key_file, "--key");
        }
        credentials = grpc::SslCredentials(ssl);
    }
    channel_ = grpc::CreateCustomChannel(target, credentials, args);
    stub_ = v1::Surfel::NewStub(channel_);
}

v1::Cloud ServiceClient::GetCloud(const std::string& id) {
    v1::GetCloudRequest req;
    req.set_cloud_id(id);
    v1::Cloud c;
    Check(CallUnary(stub_.get(), &v1::Surfel::Stub::GetCloud, req, &c, timeout_s_, token_), "GetCloud");
    return c;
}

// The upload id of a file: a fingerprint of its identity (size, modification time, first and last
// MiB), known at once, so that sending need not wait for the whole file's SHA-256. The same file,
// unchanged, gets the same id, so a broken upload resumes; the cloud's id (the server's SHA-256)
// is checked against the file's own at the end, which catches a file that changed meanwhile.
// `mapped`: the file's mapping when there is one (the same bytes, not read again).
std::string UploadFingerprint(const std::string& path, std::uint64_t size,
                              const FileMapping* mapped) {
    std::error_code ec;
    const auto mtime = std::filesystem::last_write_time(path, ec).time_since_epoch().count();
    worker::Sha256 h;
    const std::string head = std::to_string(size) + ":" + std::to_string(ec ? 0 : mtime) + ":";
    h.Update(head);
    const std::size_t part = static_cast<std::size_t>(std::min<std::uint64_t>(size, 1 << 20));
    if (mapped) {
        const bool whole =
            HashMappedBytes(h, mapped->data(), part) &&
            (size <= part || HashMappedBytes(h, mapped->data() + (size - part), part));
        if (!whole) throw std::runtime_error(path + ": shorter than its size while uploading");
        return "f" + h.FinishHex().substr(0, 48);
    }
    std::ifstream in(path, std::ios::binary);
    std::string buf(part, '\0');
    in.read(buf.data(), static_cast<std::streamsize>(buf.size()));
    h.Update(std::string_view(buf.data(), static_cast<std::size_t>(in.gcount())));
    if (size > buf.size()) {
        in.clear();
        in.seekg(static_cast<std::streamoff>(size - buf.size()));
        in.read(buf.data(), static_cast<std::streamsize>(buf.size()));
        h.Update(std::string_view(buf.data(), static_cast<std::size_t>(in.gcount())));
    }
    return "f" + h.FinishHex().substr(0, 48);
}

namespace {

// A chunk read from a file that could not be mapped: one copy, into the slice gRPC sends.
grpc::Slice ReadSlice(int fd, std::uint64_t offset, std::size_t n, const std::string& path) {
    grpc::Slice s(n);
    auto* p = const_cast<std::uint8_t*>(s.begin());
    std::size_t got = 0;
    while (got < n) {
        const ssize_t r = ::pread(fd, p + got, n - got, static_cast<off_t>(offset + got));
        if (r < 0 && errno == EINTR) continue;
        if (r < 0) throw std::runtime_error(path + ": read failed (" + std::strerror(errno) + ")");
        if (r == 0) throw std::runtime_error(path + ": shorter than its size while uploading");
        got += static_cast<std::size_t>(r);
    }
    return s;
}

}  // namespace

v1::Cloud ServiceClient::UploadFile(const std::string& path, const ByteProgress& progress, std::size_t chunk) {
    channel_->GetState(true);  // connect while the file is opened and fingerprinted
    const std::uint64_t total = std::filesystem::file_size(path);
    const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
    if (fd < 0) throw std::runtime_error(path + ": cannot open");
    // The file mapped once (hasher and sender read it; nothing is read(2) or copied by us), or
    // read chunk by chunk when it cannot be mapped. Slices of the mapping may outlive this call
    // inside gRPC: each holds a reference.
    struct Held {
        int fd;
        FileMapping* mapping;
        ~Held() {
            if (mapping) mapping->Unref();
            ::close(fd);
        }
    } held{fd, FileMapping::Map(fd, total)};
    FileMapping* const mapping = held.mapping;
    const std::string upload_id = UploadFingerprint(path, total, mapping);
    std::uint64_t offset = 0;
    {
        v1::QueryUploadRequest req;
        req.set_upload_id(upload_id);
        v1::QueryUploadResponse resp;
        Check(CallUnary(stub_.get(), &v1::Surfel::Stub::QueryUpload, req, &resp, timeout_s_, token_), "QueryUpload");
        offset = static_cast<std::uint64_t>(resp.committed_size());
        if (offset > total) offset = 0;  // cannot happen for an unchanged file
    }
    grpc::ClientContext ctx;  // no deadline: large files take their time
    Authorize(ctx);

    // The file's SHA-256 on a second thread, beside the sending: when it is ready, a server that
    // already has the cloud is asked, and while less than half of the file has been sent the
    // upload is cancelled (on a slow link most of the file is then never sent; the part file
    // stays on the server, and the next upload of the file resumes it and is deduplicated). Past
    // half (loopback, fast links) the upload runs to its end and the server deduplicates it,
    // leaving no part file. Hashing at ~1.8 GB/s, it finishes before the sending does.
    std::string sha, hash_error;
    std::optional<v1::Cloud> stored;
    std::atomic<std::uint64_t> sent{offset};
    std::thread hasher([&] {
        try {
            if (mapping) {
                worker::Sha256 h;
                if (!HashMappedBytes(h, mapping->data(), mapping->size()))
                    throw std::runtime_error(path + ": shorter than its size while uploading");
                sha = h.FinishHex();
            } else {
                sha = FileSha256(path);
            }
            v1::GetCloudRequest req;
            req.set_cloud_id(sha);
            v1::Cloud c;
            if (sent.load() < total / 2 &&
                CallUnary(stub_.get(), &v1::Surfel::Stub::GetCloud, req, &c, timeout_s_, token_).ok()) {
                stored = std::move(c);
                ctx.TryCancel();
            }
        } catch (const std::exception& e) {
            hash_error = e.what();
            ctx.TryCancel();  // the file changed: stop sending it
        }
    });
    struct Join {
        std::thread& t;
        ~Join() {
            if (t.joinable()) t.join();
        }
    } join{hasher};

    // The generated stub's Upload with raw messages (UploadMessage): the same RPC on the wire.
    static const std::string method_name =
        "/" + std::string(v1::Surfel::service_full_name()) + "/Upload";
    const grpc::internal::RpcMethod method(method_name.c_str(),
                                           grpc::internal::RpcMethod::CLIENT_STREAMING);
    grpc::ByteBuffer answer;
    std::unique_ptr<grpc::ClientWriter<grpc::ByteBuffer>> writer(
        grpc::internal::ClientWriterFactory<grpc::ByteBuffer>::Create(channel_.get(), method, &ctx,
                                                                      &answer));
    v1::UploadRequest fields;  // all but `data`
    fields.set_upload_id(upload_id);
    fields.set_filename(std::filesystem::path(path).filename().string());
    fields.set_total_size(total);  // the server refuses at once what could never be stored
    bool open = true;
    constexpr std::uint64_t kPopulateBytes = 4u << 20;
    std::uint64_t populated = 0;  // the sender's pages are mapped in up to here
    do {
        const auto n = static_cast<std::size_t>(std::min<std::uint64_t>(chunk, total - offset));
        // The sender maps its pages in 4 MiB at a time (the hasher maps its own; whichever is
        // first does the work): sendmsg then copies without a page fault per 16 pages.
        if (mapping && offset + n > populated) {
            populated = std::max(populated, offset);
            mapping->Populate(static_cast<std::size_t>(populated), kPopulateBytes);
            populated += kPopulateBytes;
        }
        grpc::Slice data = mapping ? mapping->SliceOf(static_cast<std::size_t>(offset), n)
                                   : ReadSlice(fd, offset, n, path);
        fields.set_write_offset(static_cast<std::int64_t>(offset));
        offset += n;
        fields.set_finish_write(offset >= total);
        sent.store(offset);
        if (!writer->Write(UploadMessage(fields, std::move(data)))) {
            open = false;
            break;
        }
        fields.clear_filename();
        fields.clear_total_size();
        if (progress) progress(offset, total);
    } while (offset < total);
    if (open) writer->WritesDone();
    const grpc::Status status = writer->Finish();
    v1::Cloud cloud;
    if (status.ok() && !grpc::SerializationTraits<v1::Cloud>::Deserialize(&answer, &cloud).ok())
        throw std::runtime_error("Upload " + path + ": the server's answer is not a Cloud");
    hasher.join();
    if (!hash_error.empty()) throw std::runtime_error(hash_error);
    if (stored && !(status.ok() && cloud.id() == sha)) {  // cancelled: the server had it already
        stored->set_deduplicated(true);
        if (progress) progress(total, total);
        return *stored;
    }
    Check(status, "Upload " + path);
    if (cloud.id() != sha)
        throw std::runtime_error("Upload " + path + ": the server stored cloud " + cloud.id() +
                                 " but the file's SHA-256 is " + sha +
                                 " (did the file change while it was uploaded? upload it again)");
    return cloud;
}

v1::Job ServiceClient::Submit(const v1::JobSpec& spec) {
    v1::SubmitRequest req;
    *req.mutable_spec() = spec;
    v1::Job job;
    Check(CallUnary(stub_.get(), &v1::Surfel::Stub::Submit, req, &job, timeout_s_, token_), "Submit");
    return job;
}

WatchOutcome ServiceClient::Watch(const std::string& job_id, bool include_result, bool cancel_on_disconnect,
                                  const std::function<void(const std::string&, double)>& on_running,
                                  const std::function<void(std::uint32_t)>& on_queued, const ByteProgress& on_bytes) {
    grpc::ClientContext ctx;
    Authorize(ctx);
    v1::WatchRequest req;
    req.set_job_id(job_id);
    req.set_include_result(include_result);
    req.set_cancel_on_disconnect(cancel_on_disconnect);
    auto reader = stub_->Watch(&ctx, req);
    WatchOutcome out;
    v1::JobEvent e;
    while (reader->Read(&e)) {
        switch (e.event_case()) {
            case v1::JobEvent::kState: out.state = e.state().state(); break;
            case v1::JobEvent::kQueued:
                if (on_queued) on_queued(e.queued().position());
                break;
            case v1::JobEvent::kRunning:
                out.state = v1::RUNNING;
                if (on_running) on_running(e.running().stage(), e.running().fraction());
                break;
            case v1::JobEvent::kFinished:
                out.state = v1::SUCCEEDED;
                out.result = e.finished();
                break;
            case v1::JobEvent::kFailed:
                out.state = e.failed().code() == grpc::StatusCode::CANCELLED ? v1::CANCELLED : v1::FAILED;
                out.status_code = e.failed().code();
                out.status_message = e.failed().message();
                break;
            case v1::JobEvent::kResultChunk:
                out.bytes += e.result_chunk().data();
                if (on_bytes) on_bytes(out.bytes.size(), static_cast<std::uint64_t>(e.result_chunk().total_size()));
                break;
            case v1::JobEvent::EVENT_NOT_SET: break;
        }
    }
    Check(reader->Finish(), "Watch " + job_id);
    return out;
}

std::string ServiceClient::Download(const std::string& job_id, const ByteProgress& progress) {
    grpc::ClientContext ctx;
    Authorize(ctx);
    v1::DownloadRequest req;
    req.set_job_id(job_id);
    auto reader = stub_->Download(&ctx, req);
    std::string bytes;
    v1::DataChunk chunk;
    while (reader->Read(&chunk)) {
        if (bytes.empty() && chunk.total_size() > 0 && chunk.total_size() < (std::int64_t{1} << 40))
            bytes.reserve(static_cast<std::size_t>(chunk.total_size()));  // one buffer, no regrowth
        bytes += chunk.data();
        if (progress) progress(bytes.size(), static_cast<std::uint64_t>(chunk.total_size()));
    }
    Check(reader->Finish(), "Download " + job_id);
    return bytes;
}

std::uint64_t ServiceClient::DownloadToFile(const std::string& job_id, const std::string& path,
                                            const ByteProgress& progress) {
    const std::string tmp = path + ".tmp-surfel";  // as WriteFileBytes
    std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
    if (!out) throw Error(ErrorCode::kNotFound, path + ": cannot create file (" + std::strerror(errno) + ")");
    struct RemoveUnlessKept {
        const std::string& tmp;
        bool keep = false;
        ~RemoveUnlessKept() {
            std::error_code ec;
            if (!keep) std::filesystem::remove(tmp, ec);
        }
    } guard{tmp};
    grpc::ClientContext ctx;
    Authorize(ctx);
    v1::DownloadRequest req;
    req.set_job_id(job_id);
    auto reader = stub_->Download(&ctx, req);
    std::uint64_t size = 0;
    v1::DataChunk chunk;
    // Each chunk (the server's 256 KiB) is written while it is in the cache; one write of a
    // whole result held in memory costs several times the CPU (bench/README.md, session 11).
    while (reader->Read(&chunk)) {
        out.write(chunk.data().data(), static_cast<std::streamsize>(chunk.data().size()));
        size += chunk.data().size();
        if (!out) {
            ctx.TryCancel();
            reader->Finish();
            throw Error(ErrorCode::kInternal, path + ": write failed (" + std::strerror(errno) + ")");
        }
        if (progress) progress(size, static_cast<std::uint64_t>(chunk.total_size()));
    }
    Check(reader->Finish(), "Download " + job_id);
    out.close();
    if (!out) throw Error(ErrorCode::kInternal, path + ": write failed (" + std::strerror(errno) + ")");
    std::error_code ec;
    std::filesystem::rename(tmp, path, ec);
    if (ec) throw Error(ErrorCode::kNotFound, path + ": cannot create file (" + ec.message() + ")");
    guard.keep = true;
    return size;
}

v1::Job ServiceClient::Cancel(const std::string& job_id) {
    v1::CancelRequest req;
    req.set_job_id(job_id);
    v1::Job job;
    Check(CallUnary(stub_.get(), &v1::Surfel::Stub::Cancel, req, &job, timeout_s_, token_), "Cancel");
    return job;
}

v1::Job ServiceClient::GetJob(const std::string& job_id) {
    v1::GetJobRequest req;
    req.set_job_id(job_id);
    v1::Job job;
    Check(CallUnary(stub_.get(), &v1::Surfel::Stub::GetJob, req, &job, timeout_s_, token_), "GetJob");
    return job;
}

std::vector<v1::Job> ServiceClient::ListJobs(std::uint32_t limit, v1::JobState state) {
    v1::ListJobsRequest req;
    req.set_limit(limit);
    req.set_state(state);
    v1::ListJobsResponse resp;
    Check(CallUnary(stub_.get(), &v1::Surfel::Stub::ListJobs, req, &resp, timeout_s_, token_), "ListJobs");
    return {resp.jobs().begin(), resp.jobs().end()};
}

bool ServiceClient::DeleteCloud(const std::string& id) {
    v1::DeleteCloudRequest req;
    req.set_cloud_id(id);
    v1::DeleteCloudResponse resp;
    Check(CallUnary(stub_.get(), &v1::Surfel::Stub::DeleteCloud, req, &resp, timeout_s_, token_), "DeleteCloud");
    return resp.deleted();
}

}  // namespace surfel::client
