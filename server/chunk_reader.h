#pragma once
/// \file
/// A job's result file sent as DataChunks, by Watch (include_result) and Download.

#include <cstdint>
#include <fstream>
#include <string>

#include "surfel/v1/surfel.pb.h"

namespace surfel::server {

/// Reads a file one chunk at a time, so that a reaction reads at most one chunk (a bounded read,
/// never the whole result).
class ChunkReader {
public:
    /// Opens `path` and notes its size; false when it cannot be opened.
    bool Open(const std::string& path);
    /// Fills the next chunk of at most `size` bytes (offset, total_size, data); false after the
    /// last. An empty file is one empty chunk. Throws Error(kInternal) when the file got shorter.
    bool Next(v1::DataChunk* chunk, std::size_t size);

private:
    std::string path_;
    std::ifstream in_;
    std::int64_t total_ = 0, offset_ = 0;
    bool sent_any_ = false;
};

}  // namespace surfel::server
