#include "upload_session.h"

#include <fcntl.h>
#include <spdlog/spdlog.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <sys/uio.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <climits>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <optional>
#include <system_error>
#include <thread>

#include "surfel/base/error.h"
#include "surfel/io/cloud_io.h"
#include "surfel/worker/blob_store.h"
#include "surfel/worker/job_kind.h"
#include "surfel/worker/retention.h"

namespace surfel::server {
namespace fs = std::filesystem;

namespace {

// Writeback of the part file is started every this many bytes (when the store adopts the file):
// large enough that the disk sees big writes, small enough that the fsync at the end has at most
// this much (plus what the disk has not finished) left to write. With the upload check done while
// the chunks arrive, that fsync is most of the wait after the last byte: 2 MiB instead of 8 took
// its median from 8.2 to 3.3 ms on a 91.6 MiB upload (bench/README.md, Session 15).
constexpr std::uint64_t kWritebackBytes = 2u << 20;

// A whole file mapped read-only: the parser reads the page cache directly, no copy.
class MappedFile {
  public:
    // `populate`: map every page at once (when the parser will read them all).
    explicit MappedFile(const std::string& path, bool populate = true) {
        const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
        if (fd < 0) throw Error(ErrorCode::kInternal, "cannot open " + path + ": " + std::strerror(errno));
        struct stat st {};
        if (::fstat(fd, &st) != 0) {
            const int err = errno;
            ::close(fd);
            throw Error(ErrorCode::kInternal, "cannot stat " + path + ": " + std::strerror(err));
        }
        size_ = static_cast<std::size_t>(st.st_size);
        if (size_ > 0) {
            void* p = ::mmap(nullptr, size_, PROT_READ, MAP_PRIVATE, fd, 0);
            if (p == MAP_FAILED) {
                const int err = errno;
                ::close(fd);
                throw Error(ErrorCode::kInternal, "cannot map " + path + ": " + std::strerror(err));
            }
            data_ = static_cast<const char*>(p);
            if (populate) Populate();
        }
        ::close(fd);  // the mapping keeps the file
    }
    ~MappedFile() {
        if (data_) ::munmap(const_cast<char*>(data_), size_);
    }
    MappedFile(const MappedFile&) = delete;
    MappedFile& operator=(const MappedFile&) = delete;
    std::string_view view() const { return {data_ ? data_ : "", size_}; }

  private:
    // The pages are in the page cache (just written): mapping them all at once is cheaper than a
    // fault per 64 KiB, and a large file's two halves are mapped on two threads (the check after
    // the last byte reads them in two halves too, ply.cpp). A hint: what it leaves out faults in.
    void Populate() {
#ifdef MADV_POPULATE_READ
        char* base = const_cast<char*>(data_);
        const std::size_t page = static_cast<std::size_t>(::sysconf(_SC_PAGESIZE));
        const std::size_t half = size_ >= kSplitBytes ? size_ / 2 / page * page : size_;
        std::thread second;
        if (half < size_) {
            try {
                second = std::thread([base, half, this] { ::madvise(base + half, size_ - half, MADV_POPULATE_READ); });
            } catch (const std::system_error&) {
            }
        }
        ::madvise(base, second.joinable() ? half : size_, MADV_POPULATE_READ);
        if (second.joinable()) second.join();
#endif
    }
    static constexpr std::size_t kSplitBytes = 8u << 20;

    const char* data_ = nullptr;
    std::size_t size_ = 0;
};

// Writes every piece, in order (writev, up to IOV_MAX at a time; short writes continued).
// Returns 0 or the errno of the write that failed.
int WriteAllPieces(int fd, const std::vector<std::string_view>& pieces) {
    std::vector<iovec> iov;
    iov.reserve(pieces.size());
    for (const std::string_view piece : pieces)
        if (!piece.empty()) iov.push_back({const_cast<char*>(piece.data()), piece.size()});
    std::size_t first = 0;
    while (first < iov.size()) {
        const int count = static_cast<int>(std::min<std::size_t>(iov.size() - first, IOV_MAX));
        const ssize_t n = ::writev(fd, iov.data() + first, count);
        if (n < 0 && errno == EINTR) continue;
        if (n < 0) return errno;
        auto done = static_cast<std::size_t>(n);
        while (first < iov.size() && done >= iov[first].iov_len) done -= iov[first++].iov_len;
        if (done > 0) {  // a piece written in part: the rest of it next
            iov[first].iov_base = static_cast<char*>(iov[first].iov_base) + done;
            iov[first].iov_len -= done;
        }
    }
    return 0;
}

// Joins a thread on every way out of a scope (a joinable std::thread must never be destroyed).
struct Joiner {
    std::thread thread;
    ~Joiner() {
        if (thread.joinable()) thread.join();
    }
};

}  // namespace

void CheckUploadId(const std::string& id) {
    const bool ok =
        !id.empty() && id.size() <= 128 && std::all_of(id.begin(), id.end(), [](char c) {
            return std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '-';
        });
    if (!ok) throw Error(ErrorCode::kInvalidArgument, "upload_id: must match [A-Za-z0-9_-]{1,128}");
}

UploadSession::UploadSession(Operations& ops, const Caller& caller, std::string upload_id,
                             const std::string& filename)
    : ops_(ops), caller_(caller), id_(std::move(upload_id)) {
    CheckUploadId(id_);
    if (!ops_.ClaimUpload(Operations::ScopedUploadId(caller_, id_)))
        throw Error(ErrorCode::kFailedPrecondition,
                    "upload " + id_ + " is in progress on another call");
    claimed_ = true;
    filename_ = filename.empty() ? id_ : fs::path(filename).filename().string();
    if (filename_.empty()) filename_ = id_;
    path_ = ops_.store().UploadPath(Operations::ScopedUploadId(caller_, id_));
    committed_ = static_cast<std::uint64_t>(ops_.CommittedUploadBytes(caller_, id_));
    hashed_ = committed_ == 0;
    writeback_from_ = committed_;
    adopt_ = ops_.store().blobs().AdoptsFiles();
    if (committed_ == 0) scan_ = std::make_unique<PlyPositionScan>(ReadLimits());
    try {
        fd_ = ::open(path_.c_str(), O_WRONLY | O_CREAT | O_APPEND | O_CLOEXEC, 0644);
        if (fd_ < 0) {
            const int err = errno;
            throw Error(worker::IsDiskFull(err) ? ErrorCode::kResourceExhausted : ErrorCode::kInternal,
                        "cannot open " + path_ + ": " + std::strerror(err));
        }
        // A resumed upload's committed bytes are in flight again until stored.
        ops_.ReserveInflight(committed_, id_);
        inflight_ = committed_;
    } catch (...) {  // the destructor does not run for a constructor that throws
        CloseFile();
        ops_.ReleaseUpload(Operations::ScopedUploadId(caller_, id_));
        throw;
    }
}

UploadSession::~UploadSession() {
    CloseFile();
    ops_.ReleaseInflight(inflight_);
    // The part file's committed bytes stay counted (a resume); the space for the rest goes back.
    if (prereserved_ && ops_.retention()) ops_.retention()->Release(prereserved_);
    if (claimed_) ops_.ReleaseUpload(Operations::ScopedUploadId(caller_, id_));
}

void UploadSession::CloseFile() {
    if (fd_ >= 0) ::close(fd_);
    fd_ = -1;
}

PlyReadOptions UploadSession::ReadLimits() const {
    PlyReadOptions read_limits;
    read_limits.max_points = ops_.limits().max_points;
    return read_limits;
}

std::string UploadSession::ResumeHint() const {
    return std::to_string(committed_) + " bytes committed; resume at write_offset " +
           std::to_string(committed_) + " and end with finish_write";
}

void UploadSession::CheckFits(std::uint64_t more) {
    const std::uint64_t limit = ops_.limits().max_upload_bytes;
    if (committed_ + more > limit) {
        Discard();
        throw Error(ErrorCode::kResourceExhausted,
                    "upload " + id_ + " exceeds the limit of " + std::to_string(limit) + " bytes");
    }
}

void UploadSession::ExpectSize(std::uint64_t total) {
    if (total_ != 0) {
        if (total != total_)
            throw Error(ErrorCode::kInvalidArgument, "total_size: " + std::to_string(total) + " after " +
                                                         std::to_string(total_) + " within one upload");
        return;
    }
    if (total < committed_)
        throw Error(ErrorCode::kInvalidArgument, "total_size: " + std::to_string(total) + " is less than the " +
                                                     std::to_string(committed_) + " bytes upload " + id_ +
                                                     " has committed");
    CheckFits(total - committed_);
    // What can never be stored goes, as Append's refusals do: the part file and its bytes.
    auto refuse = [&](const std::string& why) {
        const std::uint64_t had = committed_;
        Discard();
        throw Error(ErrorCode::kResourceExhausted,
                    why + (had ? "; the upload's " + std::to_string(had) + " committed bytes were discarded" : ""));
    };
    const std::uint64_t cap = ops_.limits().max_upload_inflight_bytes;
    if (cap != 0 && total > cap)
        refuse("upload " + id_ + ": its " + std::to_string(total) +
               " bytes are more than the whole --max-upload-inflight-mb (" + std::to_string(cap) + " bytes)");
    if (worker::Retention* retention = ops_.retention()) {
        try {
            retention->Reserve(total - committed_, "upload " + id_, total);
        } catch (const Error& e) {
            if (e.code() != ErrorCode::kResourceExhausted) throw;
            refuse(e.what());
        }
    }
    prereserved_ = total - committed_;
    total_ = total;
}

void UploadSession::HashCommitted() {
    std::ifstream in(path_, std::ios::binary);
    if (!in) throw Error(ErrorCode::kInternal, "cannot read " + path_);
    std::string buf(1 << 20, '\0');
    std::uint64_t hashed = 0;
    while (in) {
        in.read(buf.data(), static_cast<std::streamsize>(buf.size()));
        const auto n = static_cast<std::size_t>(in.gcount());
        hash_.Update(std::string_view(buf.data(), n));
        hashed += n;
    }
    if (hashed != committed_)
        throw Error(ErrorCode::kInternal, "reading " + path_ + ": " + std::to_string(hashed) +
                                              " of " + std::to_string(committed_) + " bytes");
    hashed_ = true;
}

void UploadSession::Append(std::string_view data) { Append(std::vector<std::string_view>{data}); }

void UploadSession::Append(const std::vector<std::string_view>& pieces) {
    std::size_t size = 0;
    for (const std::string_view piece : pieces) size += piece.size();
    inflight_ += size;  // the transport's count, ours now
    SURFEL_CHECK(hashed_, "Append before HashCommitted on upload " << id_);
    CheckFits(size);
    SURFEL_CHECK(fd_ >= 0, "Append after Finish or Discard on upload " << id_);
    if (size == 0) return;
    if (total_ != 0 && committed_ + size > total_)
        throw Error(ErrorCode::kInvalidArgument, "data: upload " + id_ + " passes its total_size " +
                                                     std::to_string(total_) + " at byte " +
                                                     std::to_string(committed_ + size));
    worker::Retention* retention = ops_.retention();
    if (retention && prereserved_ >= size) {
        prereserved_ -= size;  // ExpectSize reserved it
    } else if (retention) {
        try {
            retention->Reserve(size, "upload " + id_, committed_ + size);
        } catch (const Error& e) {
            const std::uint64_t had = committed_;
            Discard();
            throw Error(e.code(), std::string(e.what()) + "; the upload's " + std::to_string(had) +
                                      " committed bytes were discarded: upload it again");
        }
    }
    const int err = WriteAllPieces(fd_, pieces);
    if (err != 0) {
        // Nothing of this chunk stays; on a full disk the whole part file goes, and its space.
        if (::ftruncate(fd_, static_cast<off_t>(committed_)) != 0) {
        }
        if (retention) retention->Release(size);
        const std::uint64_t had = committed_;
        const bool full = worker::IsDiskFull(err);
        if (full) Discard();
        throw Error(full ? ErrorCode::kResourceExhausted : ErrorCode::kInternal,
                    "upload " + id_ + ": writing " + path_ + ": " + std::strerror(err) +
                        (full ? "; the upload's " + std::to_string(had) +
                                    " committed bytes were discarded to free the space: upload "
                                    "it again"
                              : std::string()));
    }
    for (const std::string_view piece : pieces) {
        hash_.Update(piece);
        if (scan_) scan_->Append(piece);  // while the bytes are in the cache
    }
    committed_ += size;
    ops_.metrics().AddBytesIn(size);
#ifdef __linux__
    if (adopt_ && committed_ - writeback_from_ >= kWritebackBytes) {
        // Starts writeback of what has been written since the last call and returns: a hint
        // (an error here shows again at the fsync that decides).
        ::sync_file_range(fd_, static_cast<off_t>(writeback_from_),
                          static_cast<off_t>(committed_ - writeback_from_), SYNC_FILE_RANGE_WRITE);
        writeback_from_ = committed_;
    }
#endif
}

v1::Cloud UploadSession::Finish() {
    SURFEL_CHECK(hashed_, "Finish before HashCommitted on upload " << id_);
    if (total_ != 0 && committed_ != total_) {
        const std::uint64_t had = committed_;
        Discard();
        ops_.metrics().CountUpload(false);
        throw Error(ErrorCode::kInvalidArgument, "upload " + id_ + " ended at " + std::to_string(had) +
                                                     " bytes, but its total_size said " + std::to_string(total_) +
                                                     "; the bytes were discarded: upload it again");
    }
    const std::string id = hash_.FinishHex();
    worker::Retention* retention = ops_.retention();
    // No eviction of the cloud between finding it here and recording this owner.
    std::unique_lock<std::recursive_mutex> hold;
    if (retention) hold = retention->Lock();
    // Deduplication answers only from the caller's own clouds: a tenant learns nothing about
    // another's files (docs/security.md). Unscoped callers (no auth) see every cloud.
    const bool own = !caller_.scoped || ops_.store().CloudOwned(caller_.tenant, id);
    std::optional<v1::Cloud> existing = own ? ops_.store().FindCloud(id) : std::nullopt;
    if (existing) {
        ops_.store().AddCloudOwner(caller_.tenant, id);
        const std::uint64_t size = committed_;
        Discard();
        existing->set_deduplicated(true);
        spdlog::info("upload {}: {} bytes, already stored as cloud {}", id_, size, id);
        ops_.metrics().CountUpload(true);
        if (retention) retention->Touch(worker::CloudBlobKey(id));
        return *existing;
    }
    const std::uint64_t size = committed_;
    if (hold) hold.unlock();  // parsing takes long; evictions may run meanwhile
    CloudFileSummary cloud;
    int sync_error = 0;
    try {
        Joiner syncer;
        // The fsync that PutFile needs runs beside the parse: the disk works while the CPU
        // parses, and PutFile's own fsync then finds nothing dirty. Only for a store that adopts
        // the file (a copying store, PostgreSQL, never reads the part file from disk again).
        if (adopt_)
            syncer.thread = std::thread([this, &sync_error] {
                if (::fsync(fd_) != 0) sync_error = errno;
            });
        // With a scan of every byte the check reads only the header and what follows the
        // vertex records: no need to map in the rest.
        const PlyPositionScan* scan = scan_ && scan_->bytes() == committed_ ? scan_.get() : nullptr;
        const MappedFile file(path_, !(scan && scan->complete()));
        cloud = InspectCloudFile(file.view(), filename_, ReadLimits(), scan);  // what cloud_fuzzer fuzzes
    } catch (...) {
        Discard();
        ops_.metrics().CountUpload(false);
        throw;
    }
    CloseFile();
    if (sync_error != 0) {
        Discard();
        ops_.metrics().CountUpload(false);
        throw Error(worker::IsDiskFull(sync_error) ? ErrorCode::kResourceExhausted : ErrorCode::kInternal,
                    "fsync " + path_ + ": " + std::strerror(sync_error));
    }
    // Durable before it is recorded and acknowledged: dir backend fsync + rename + fsync of the
    // directory; large objects one committed transaction (docs/durability.md).
    if (retention) hold.lock();
    try {
        if (caller_.scoped && ops_.store().blobs().Size(worker::CloudBlobKey(id))) {
            Discard();  // another tenant's identical bytes are already stored: keep one copy
            if (retention) retention->Touch(worker::CloudBlobKey(id));
        } else {
            ops_.store().blobs().PutFile(worker::CloudBlobKey(id), path_, id);
            if (retention) retention->Stored(worker::CloudBlobKey(id), committed_, committed_);
        }
    } catch (...) {
        Discard();
        ops_.metrics().CountUpload(false);
        throw;
    }
    committed_ = 0;
    v1::Cloud c;
    c.set_id(id);
    c.set_points(cloud.points);
    *c.mutable_bounds_min() = worker::ToProto(cloud.bounds.min.cast<double>());
    *c.mutable_bounds_max() = worker::ToProto(cloud.bounds.max.cast<double>());
    for (const std::string& a : cloud.attributes) c.add_attributes(a);
    c.set_size_bytes(size);
    c.set_format(std::string(cloud.format));
    ops_.store().PutCloud(c);
    ops_.store().AddCloudOwner(caller_.tenant, id);
    ops_.metrics().CountUpload(true);
    spdlog::info("upload {}: stored cloud {} ({} points, {} bytes)", id_, id, cloud.points, size);
    return c;
}

void UploadSession::Discard() {
    CloseFile();
    std::error_code ec;
    const bool removed = fs::remove(path_, ec);
    // The part file's bytes were counted by retention (Load, or chunk by chunk), and so was the
    // space ExpectSize reserved for the rest.
    if (ops_.retention()) ops_.retention()->Release((removed ? committed_ : 0) + prereserved_);
    committed_ = 0;
    prereserved_ = 0;
}

}  // namespace surfel::server
