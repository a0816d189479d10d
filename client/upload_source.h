#pragma once
/// \file
/// The bytes of an upload as the client sends them: the file mapped read-only once; the hasher
/// reads the mapping, and each chunk goes to gRPC as a slice that refers to it (no read(2) into
/// a buffer, no copy into a protobuf message), so the sender's only copy is sendmsg's.

#include <grpcpp/support/byte_buffer.h>
#include <grpcpp/support/slice.h>

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <string>

namespace surfel::v1 {
class UploadRequest;
}
namespace surfel::worker {
class Sha256;
}

namespace surfel::client {

/// A read-only shared mapping of a whole regular file, counted: the owner and every slice of
/// it hold a reference; the last one unmaps. Slices outlive the upload call inside gRPC at
/// times (a transport frees them on its own thread), hence the count.
class FileMapping {
  public:
    /// Maps the file open on `fd` (`size` bytes, from its fstat). Null when it cannot be mapped
    /// (a pipe, a special file, an empty file, mmap refused, 64 mappings live): the caller reads
    /// instead. A page lost to truncation reads as zeros outside HashMappedBytes (no SIGBUS).
    static FileMapping* Map(int fd, std::uint64_t size);

    const char* data() const { return data_; }
    std::size_t size() const { return size_; }

    /// Bytes [offset, offset + n) as a gRPC slice that refers to the mapping (and holds it).
    grpc::Slice SliceOf(std::size_t offset, std::size_t n);

    /// Maps in the pages of bytes [offset, offset + n) now (one call instead of a fault per 16
    /// pages when they are read); a hint, without effect past the file's end.
    void Populate(std::size_t offset, std::size_t n) const;

    void Ref() { refs_.fetch_add(1, std::memory_order_relaxed); }
    void Unref();

  private:
    FileMapping(const char* data, std::size_t size) : data_(data), size_(size) {}
    ~FileMapping();
    static void ReleaseSlice(void* mapping);

    const char* data_;
    std::size_t size_;
    std::atomic<int> refs_{1};
};

/// Hashes `n` bytes of a mapping into `hash` (its pages faulted in ahead, a few MiB at a time).
/// Returns false, and `hash` holds garbage, when a page could not be read: the file was
/// truncated under the mapping (SIGBUS, caught on this thread for these addresses only; any
/// other SIGBUS goes to the handler installed before).
bool HashMappedBytes(worker::Sha256& hash, const char* data, std::size_t n);

/// One Upload message as gRPC sends it, with the chunk `data` as its own slice (no protobuf copy):
/// `fields` (everything but `data`, which must be empty there) serialized, then field 4, `data`,
/// length-delimited. Parsers take fields in any order, so the server reads the same
/// UploadRequest as from SerializeToString with `data` set.
grpc::ByteBuffer UploadMessage(const v1::UploadRequest& fields, grpc::Slice data);

}  // namespace surfel::client
