// The blob interface's shared part (keys, checks, fsync) and the directory backend.
#include "surfel/worker/blob_store.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <algorithm>
#include <cstring>
#include <filesystem>
#include <random>

#include "surfel/base/error.h"

namespace surfel::worker {
namespace fs = std::filesystem;

BlobReader::~BlobReader() = default;
BlobStore::~BlobStore() = default;

std::string CloudBlobKey(const std::string& cloud_id) { return "clouds/" + cloud_id; }
std::string ResultBlobKey(const std::string& job_id) { return "results/" + job_id; }

std::string CorruptBlobMessage(const std::string& expected, const std::string& actual,
                               const std::string& what) {
    return "blob " + expected + " (" + what + ") is corrupt: sha256 " + actual + " != " + expected;
}

// ---- checks while reading

VerifyingReader::VerifyingReader(std::unique_ptr<BlobReader> inner, std::string expected,
                                 std::string what)
    : inner_(std::move(inner)), expected_(std::move(expected)), what_(std::move(what)) {
    checking_ = !expected_.empty();
}

std::size_t VerifyingReader::Read(char* buf, std::size_t n) {
    const std::size_t got = inner_->Read(buf, n);
    if (checking_) {
        hash_.Update(std::string_view(buf, got));
        position_ += got;
        if (position_ >= inner_->size()) {
            checking_ = false;
            const std::string actual = hash_.FinishHex();
            if (actual != expected_)
                throw Error(ErrorCode::kDataLoss, CorruptBlobMessage(expected_, actual, what_));
            verified_ = true;
        }
    } else {
        position_ += got;
    }
    return got;
}

void VerifyingReader::Seek(std::uint64_t offset) {
    if (offset != position_) checking_ = false;
    position_ = offset;
    inner_->Seek(offset);
}

std::string ReadVerified(const BlobStore& store, const std::string& key,
                         const std::string& expected, const std::string& what) {
    std::unique_ptr<BlobReader> raw = store.Open(key);
    if (!raw) throw Error(ErrorCode::kNotFound, what + ": blob " + key + " is missing");
    const std::uint64_t size = raw->size();
    VerifyingReader in(std::move(raw), expected, what);
    std::string bytes(static_cast<std::size_t>(size), '\0');
    std::size_t at = 0;
    constexpr std::size_t kChunk = 1 << 20;
    while (at < bytes.size()) {
        const std::size_t got = in.Read(bytes.data() + at, std::min(kChunk, bytes.size() - at));
        if (got == 0)
            throw Error(ErrorCode::kDataLoss, what + ": blob " + key + " ends at byte " +
                                                  std::to_string(at) + " of " +
                                                  std::to_string(size));
        at += got;
    }
    if (!expected.empty() && !in.verified()) {
        char probe;
        in.Read(&probe, 1);  // an empty blob: the check runs on the end
    }
    return bytes;
}

// ---- fsync

bool IsDiskFull(int err) { return err == ENOSPC || err == EDQUOT; }

int WriteAll(int fd, std::string_view bytes, std::size_t* written) {
    std::size_t at = 0;
    int err = 0;
    while (at < bytes.size()) {
        const ssize_t n = ::write(fd, bytes.data() + at, bytes.size() - at);
        if (n < 0 && errno == EINTR) continue;
        if (n < 0) {
            err = errno;
            break;
        }
        at += static_cast<std::size_t>(n);
    }
    if (written) *written = at;
    return err;
}

namespace {
ErrorCode WriteErrorCode(int err) {
    return IsDiskFull(err) ? ErrorCode::kResourceExhausted : ErrorCode::kInternal;
}
}  // namespace

void SyncFile(const std::string& path) {
    const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
    if (fd < 0)
        throw Error(ErrorCode::kInternal, "fsync " + path + ": " + std::strerror(errno));
    const int rc = ::fsync(fd);
    const int err = errno;
    ::close(fd);
    if (rc != 0) throw Error(WriteErrorCode(err), "fsync " + path + ": " + std::strerror(err));
}

void SyncDirectory(const std::string& dir) {
    const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    if (fd < 0)
        throw Error(ErrorCode::kInternal, "fsync " + dir + ": " + std::strerror(errno));
    const int rc = ::fsync(fd);
    const int err = errno;
    ::close(fd);
    // Some filesystems (certain FUSE and network mounts) refuse fsync on a directory; the
    // rename is then as durable as that filesystem makes it.
    if (rc != 0 && err != EINVAL && err != ENOTSUP)
        throw Error(ErrorCode::kInternal, "fsync " + dir + ": " + std::strerror(err));
}

// ---- the directory backend

namespace {

/// A file opened with open(2), read with read(2).
class FileReader final : public BlobReader {
public:
    FileReader(int fd, std::uint64_t size, std::string path)
        : fd_(fd), size_(size), path_(std::move(path)) {}
    ~FileReader() override { ::close(fd_); }
    std::uint64_t size() const override { return size_; }
    std::size_t Read(char* buf, std::size_t n) override {
        for (;;) {
            const ssize_t got = ::read(fd_, buf, n);
            if (got >= 0) return static_cast<std::size_t>(got);
            if (errno == EINTR) continue;
            throw Error(errno == EIO ? ErrorCode::kDataLoss : ErrorCode::kInternal,
                        "reading " + path_ + ": " + std::strerror(errno));
        }
    }
    void Seek(std::uint64_t offset) override {
        if (::lseek(fd_, static_cast<off_t>(offset), SEEK_SET) < 0)
            throw Error(ErrorCode::kInternal, "seeking " + path_ + ": " + std::strerror(errno));
    }

private:
    int fd_;
    std::uint64_t size_;
    std::string path_;
};

std::string TempSuffix() {
    static thread_local std::mt19937_64 rng(std::random_device{}());
    char buf[24];
    std::snprintf(buf, sizeof buf, ".tmp-%016llx", static_cast<unsigned long long>(rng()));
    return buf;
}

}  // namespace

DirBlobStore::DirBlobStore(std::string dir) : dir_(std::move(dir)) {
    std::error_code ec;
    for (const char* sub : {"", "/clouds", "/results"}) {
        fs::create_directories(dir_ + sub, ec);
        if (ec)
            throw Error(ErrorCode::kInvalidArgument, "blob dir " + dir_ + sub + ": " + ec.message());
    }
}

void DirBlobStore::PutFile(const std::string& key, const std::string& path,
                           const std::string& /*sha256: the name is the check*/) {
    const std::string target = PathOf(key);
    SyncFile(path);
    std::error_code ec;
    fs::rename(path, target, ec);
    if (ec)
        throw Error(WriteErrorCode(ec.value()), "storing blob " + key + ": " + ec.message());
    SyncDirectory(fs::path(target).parent_path().string());
}

void DirBlobStore::PutBytes(const std::string& key, std::string_view bytes,
                            const std::string& sha256) {
    const std::string tmp = PathOf(key) + TempSuffix();
    const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
    if (fd < 0) {
        const int err = errno;
        throw Error(WriteErrorCode(err),
                    "storing blob " + key + ": " + tmp + ": " + std::strerror(err));
    }
    std::size_t at = 0;
    int err = WriteAll(fd, bytes, &at);
    if (err == 0 && ::fsync(fd) != 0) err = errno;
    ::close(fd);
    if (err != 0) {
        // The temp name is all a half-written blob ever had; it goes, and with it the space.
        std::error_code ec;
        fs::remove(tmp, ec);
        throw Error(WriteErrorCode(err), "storing blob " + key + " (" + std::to_string(at) +
                                             " of " + std::to_string(bytes.size()) +
                                             " bytes written): " + std::strerror(err));
    }
    try {
        PutFile(key, tmp, sha256);  // the fsync of the file again is cheap: nothing is dirty
    } catch (...) {
        std::error_code ec;
        fs::remove(tmp, ec);
        throw;
    }
}

std::unique_ptr<BlobReader> DirBlobStore::Open(const std::string& key) const {
    const std::string path = PathOf(key);
    const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
    if (fd < 0) {
        if (errno == ENOENT) return nullptr;
        throw Error(ErrorCode::kUnavailable, "opening blob " + path + ": " + std::strerror(errno));
    }
    struct stat st {};
    if (::fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {
        ::close(fd);
        throw Error(ErrorCode::kInternal, "blob " + path + " is not a regular file");
    }
    return std::make_unique<FileReader>(fd, static_cast<std::uint64_t>(st.st_size), path);
}

std::optional<std::uint64_t> DirBlobStore::Size(const std::string& key) const {
    std::error_code ec;
    const auto size = fs::file_size(PathOf(key), ec);
    if (ec) return std::nullopt;
    return size;
}

std::vector<std::pair<std::string, std::uint64_t>> DirBlobStore::List() const {
    std::vector<std::pair<std::string, std::uint64_t>> out;
    for (const char* sub : {"clouds", "results"}) {
        std::error_code ec;
        for (fs::directory_iterator it(dir_ + "/" + sub, ec), end; !ec && it != end;
             it.increment(ec)) {
            const std::string name = it->path().filename().string();
            if (name.find(".tmp-") != std::string::npos) continue;  // a put in progress
            std::error_code sec;
            if (!it->is_regular_file(sec)) continue;
            const auto size = it->file_size(sec);
            if (!sec) out.emplace_back(std::string(sub) + "/" + name, size);
        }
    }
    std::sort(out.begin(), out.end());
    return out;
}

bool DirBlobStore::Remove(const std::string& key) {
    std::error_code ec;
    // Only a blob's file, never a folder a malformed key names ("clouds/").
    if (!fs::is_regular_file(PathOf(key), ec)) return false;
    return fs::remove(PathOf(key), ec);
}

}  // namespace surfel::worker
