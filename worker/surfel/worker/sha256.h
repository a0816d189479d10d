#pragma once
/// \file
/// SHA-256 (OpenSSL behind our names): cloud ids on the server, upload ids in the client.

#include <string>
#include <string_view>

namespace surfel::worker {

/// Lower-case hex SHA-256 of bytes (OpenSSL), and an incremental hasher.
std::string Sha256Hex(std::string_view bytes);
class Sha256 {
public:
    Sha256();
    ~Sha256();
    Sha256(const Sha256&) = delete;
    Sha256& operator=(const Sha256&) = delete;
    void Update(std::string_view bytes);
    std::string FinishHex();

private:
    void* ctx_;
};

}  // namespace surfel::worker
