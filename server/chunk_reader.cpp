#include "chunk_reader.h"

#include <algorithm>
#include <utility>

#include "surfel/base/error.h"

namespace surfel::server {

bool ChunkReader::Open(const std::string& path) {
    path_ = path;
    in_.open(path, std::ios::binary);
    if (!in_) return false;
    in_.seekg(0, std::ios::end);
    total_ = static_cast<std::int64_t>(in_.tellg());
    in_.seekg(0);
    return in_.good() && total_ >= 0;
}

bool ChunkReader::Next(v1::DataChunk* chunk, std::size_t size) {
    if (sent_any_ && offset_ >= total_) return false;
    std::string data(static_cast<std::size_t>(std::min<std::int64_t>(static_cast<std::int64_t>(size), total_ - offset_)),
                     '\0');
    in_.read(data.data(), static_cast<std::streamsize>(data.size()));
    if (static_cast<std::size_t>(in_.gcount()) != data.size())
        throw Error(ErrorCode::kInternal, "reading " + path_ + ": short read at offset " + std::to_string(offset_) +
                                              " of " + std::to_string(total_) + " bytes");
    chunk->set_offset(offset_);
    chunk->set_total_size(total_);
    chunk->set_data(std::move(data));
    offset_ += static_cast<std::int64_t>(chunk->data().size());
    sent_any_ = true;
    return true;
}

}  // namespace surfel::server
