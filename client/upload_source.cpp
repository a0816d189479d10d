#include "upload_source.h"

#include <setjmp.h>
#include <signal.h>
#include <sys/mman.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <mutex>
#include <string_view>

#include "surfel/v1/surfel.pb.h"
#include "surfel/worker/sha256.h"

namespace surfel::client {
namespace {

// ---- SIGBUS of a truncated mapping -----------------------------------------------------------
//
// A mapped file cut shorter than the mapping raises SIGBUS on a read past its new end (sendmsg's
// copy in the kernel gets EFAULT instead, and the stream breaks). The hasher reads under a guard:
// its thread's address range and a jump back into HashMappedBytes, which then reports the file as
// changed. A read of a live mapping elsewhere (gRPC encrypting a slice for TLS) gets a page of
// zeros in place of the lost one and goes on: the hashes then differ and the client reports the
// file as changed, as for any file changed while it is sent. Any other SIGBUS goes to the
// disposition that was there before, as if this handler were not installed. The live mappings
// are a fixed table of atomics (what a signal handler may read); a full table maps nothing more
// (the client reads the file instead).
struct BusGuard {
    const char* begin;
    const char* end;
    sigjmp_buf env;
};
thread_local BusGuard* t_guard = nullptr;
struct sigaction g_previous {};
constexpr int kMaxMappings = 64;
std::atomic<const char*> g_begin[kMaxMappings];
std::atomic<const char*> g_end[kMaxMappings];

bool Register(const char* begin, const char* end) {
    for (int i = 0; i < kMaxMappings; ++i) {
        const char* none = nullptr;
        if (g_end[i].compare_exchange_strong(none, end)) {
            g_begin[i].store(begin);  // valid from here
            return true;
        }
    }
    return false;
}

void Unregister(const char* begin) {
    for (int i = 0; i < kMaxMappings; ++i) {
        if (g_begin[i].load() == begin) {
            g_begin[i].store(nullptr);
            g_end[i].store(nullptr);
            return;
        }
    }
}

void OnSigbus(int sig, siginfo_t* info, void* context) {
    const char* at = static_cast<const char*>(info->si_addr);
    if (BusGuard* g = t_guard; g && at >= g->begin && at < g->end) siglongjmp(g->env, 1);
    for (int i = 0; i < kMaxMappings; ++i) {
        const char* begin = g_begin[i].load();
        if (begin && at >= begin && at < g_end[i].load()) {
            const auto page = static_cast<std::uintptr_t>(::sysconf(_SC_PAGESIZE));
            void* lost =
                reinterpret_cast<void*>(reinterpret_cast<std::uintptr_t>(at) / page * page);
            if (::mmap(lost, page, PROT_READ, MAP_PRIVATE | MAP_ANONYMOUS | MAP_FIXED, -1, 0) !=
                MAP_FAILED)
                return;
        }
    }
    if (g_previous.sa_flags & SA_SIGINFO) {
        g_previous.sa_sigaction(sig, info, context);
    } else if (g_previous.sa_handler != SIG_DFL && g_previous.sa_handler != SIG_IGN) {
        g_previous.sa_handler(sig);
    } else {
        // The default action: the faulting access runs again after return and kills the process.
        ::sigaction(SIGBUS, &g_previous, nullptr);
    }
}

void InstallSigbusHandler() {
    static std::once_flag once;
    std::call_once(once, [] {
        struct sigaction sa {};
        sa.sa_sigaction = OnSigbus;
        sa.sa_flags = SA_SIGINFO;
        sigemptyset(&sa.sa_mask);
        ::sigaction(SIGBUS, &sa, &g_previous);
    });
}

}  // namespace

FileMapping* FileMapping::Map(int fd, std::uint64_t size) {
    if (size == 0 || size > SIZE_MAX) return nullptr;
    void* p = ::mmap(nullptr, static_cast<std::size_t>(size), PROT_READ, MAP_SHARED, fd, 0);
    if (p == MAP_FAILED) return nullptr;
    const char* data = static_cast<const char*>(p);
    InstallSigbusHandler();
    if (!Register(data, data + size)) {
        ::munmap(p, static_cast<std::size_t>(size));
        return nullptr;
    }
    // Read once, front to back: the kernel may read ahead further and drop pages behind.
    ::madvise(p, static_cast<std::size_t>(size), MADV_SEQUENTIAL);
    return new FileMapping(data, static_cast<std::size_t>(size));
}

FileMapping::~FileMapping() {
    Unregister(data_);
    ::munmap(const_cast<char*>(data_), size_);
}

void FileMapping::Unref() {
    if (refs_.fetch_sub(1, std::memory_order_acq_rel) == 1) delete this;
}

void FileMapping::ReleaseSlice(void* mapping) { static_cast<FileMapping*>(mapping)->Unref(); }

grpc::Slice FileMapping::SliceOf(std::size_t offset, std::size_t n) {
    Ref();
    // gRPC never writes to an outgoing slice; the cast only fits its signature.
    return grpc::Slice(const_cast<char*>(data_ + offset), n, &FileMapping::ReleaseSlice, this);
}

// One UploadRequest as gRPC sends it, without a protobuf copy of the chunk: the other fields
// serialized, then field 4 (`data`, length-delimited) whose bytes are the chunk's own slice. A
// parser takes fields in any order, so the server reads the same message as from
// UploadRequest::SerializeToString with `data` set (test_upload_source).
grpc::ByteBuffer UploadMessage(const v1::UploadRequest& fields, grpc::Slice data) {
    std::string head = fields.SerializeAsString();
    const std::size_t n = data.size();
    grpc::Slice parts[2];
    if (n > 0) {
        head.push_back(static_cast<char>((4 << 3) | 2));  // field 4, wire type 2
        for (std::uint64_t v = n;; v >>= 7) {             // its length, a varint
            if (v < 0x80) {
                head.push_back(static_cast<char>(v));
                break;
            }
            head.push_back(static_cast<char>((v & 0x7f) | 0x80));
        }
        parts[1] = std::move(data);
    }
    parts[0] = grpc::Slice(head);
    return grpc::ByteBuffer(parts, n > 0 ? 2 : 1);
}

void FileMapping::Populate(std::size_t offset, std::size_t n) const {
#ifdef MADV_POPULATE_READ
    static const std::size_t page = static_cast<std::size_t>(::sysconf(_SC_PAGESIZE));
    if (offset >= size_) return;
    const std::size_t begin = offset / page * page;
    ::madvise(const_cast<char*>(data_ + begin), std::min(size_, offset + n) - begin,
              MADV_POPULATE_READ);
#else
    (void)offset;
    (void)n;
#endif
}

bool HashMappedBytes(worker::Sha256& hash, const char* data, std::size_t n) {
    // Pages are mapped in ahead of the hash a block at a time (one call instead of a fault per
    // 16 pages); the sender, behind the hasher, then finds them mapped too. The hash takes a
    // page at a time and the cache lines 16 KiB ahead are prefetched: SHA-256 alone does not
    // keep enough loads in flight (hashing 91.6 MiB from the mapping: ~71 ms of CPU without
    // the prefetch, ~61 with it, ~64 by read(2) into a buffer, ~50 from the cache; Session 18).
    constexpr std::size_t kBlock = 4u << 20;
    constexpr std::size_t kStep = 4096;
    constexpr std::size_t kAhead = 16u << 10;
    BusGuard guard{data, data + n, {}};
    if (sigsetjmp(guard.env, 1) != 0) {
        t_guard = nullptr;
        return false;
    }
    t_guard = &guard;
    for (std::size_t at = 0; at < n; at += kBlock) {
        const std::size_t end = std::min(n, at + kBlock);
#ifdef MADV_POPULATE_READ
        // Page-aligned start (the mapping's base is); an error (past a new end) shows as SIGBUS.
        ::madvise(const_cast<char*>(data + at), end - at, MADV_POPULATE_READ);
#endif
        for (std::size_t page = at; page < end; page += kStep) {
            const std::size_t ahead_end = std::min(n, page + kAhead + kStep);
            for (std::size_t line = page + kAhead; line < ahead_end; line += 64)
                __builtin_prefetch(data + line);
            hash.Update(std::string_view(data + page, std::min(kStep, end - page)));
        }
    }
    t_guard = nullptr;
    return true;
}

}  // namespace surfel::client
