#pragma once
/// \file
/// Bearer-token authentication and tenants (docs/security.md). A token file names one tenant
/// per line; only SHA-256 hashes of the tokens are kept in memory and compared in constant time.
/// The gRPC handlers and the HTTP routes turn an `authorization: Bearer <token>` into a Caller,
/// and Operations scopes every lookup to the caller's tenant.

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace surfel::server {

/// Who is calling. Without auth every caller is the default tenant "", unscoped (today's
/// behaviour: every cloud and job is visible).
struct Caller {
    std::string tenant;   ///< the token's name; "" = the default tenant
    bool scoped = false;  ///< true with auth: only the tenant's own clouds and jobs exist for it
};

/// "sha256:<64 lowercase hex>" of a token: the hashed form a token file may hold.
std::string HashToken(std::string_view token);

/// The tokens of a token file, hashed.
///
/// File format: one `NAME TOKEN` or `NAME sha256:HEX` per line (separated by spaces or tabs),
/// blank lines and lines starting with `#` ignored. NAME matches [A-Za-z0-9_.-]{1,64} and is the
/// tenant; a plaintext TOKEN is 16 to 4096 printable non-space ASCII characters; HEX is the
/// SHA-256 of the token (`surfel-server --hash-token` prints it). Names and tokens are unique.
class TokenSet {
  public:
    /// Reads and parses `path`. Throws Error(kInvalidArgument) naming the file and the line.
    static TokenSet Load(const std::string& path);
    /// Parses a token file's text; `where` names it in errors.
    static TokenSet Parse(std::string_view text, const std::string& where);

    std::size_t size() const { return entries_.size(); }
    /// The tenant whose token this is; nullopt when none. Hashes `token` once, then compares
    /// with every entry without stopping early (the time does not tell which entry matched).
    std::optional<std::string> Find(std::string_view token) const;

  private:
    struct Entry {
        std::string name;
        std::string hash_hex;  ///< 64 lowercase hex digits
    };
    std::vector<Entry> entries_;
};

/// Authentication of calls: off (every call is Caller{}) unless built with a TokenSet.
class Authenticator {
  public:
    Authenticator() = default;
    explicit Authenticator(TokenSet tokens) : tokens_(std::move(tokens)), enabled_(true) {}

    bool enabled() const { return enabled_; }
    /// The caller of a request whose `authorization` header (or gRPC metadata) is
    /// `authorization` ("" when absent). Throws Error(kUnauthenticated) with auth on when it is
    /// missing, not a Bearer token, or an unknown token.
    Caller Authenticate(std::string_view authorization) const;

  private:
    TokenSet tokens_;
    bool enabled_ = false;
};

/// Short-lived signed URLs for the browser's event stream (EventSource cannot send headers):
/// HMAC-SHA256 under a random key of this process over the job id, the owning tenant and the
/// expiry. docs/security.md says why a signed URL rather than a cookie.
class UrlSigner {
  public:
    /// A fresh random 32-byte key.
    UrlSigner();
    /// The signature (64 hex) of (job_id, tenant, expires_unix_ms).
    std::string Sign(const std::string& job_id, const std::string& tenant,
                     std::int64_t expires_unix_ms) const;
    /// True when `signature` is Sign(job_id, tenant, expires) and `now_unix_ms` <= expires.
    bool Verify(const std::string& job_id, const std::string& tenant, std::int64_t expires_unix_ms,
                const std::string& signature, std::int64_t now_unix_ms) const;

  private:
    std::string key_;
};

/// Constant-time equality of two strings of the same length (false at once when lengths
/// differ: lengths are not secret here).
bool ConstantTimeEquals(std::string_view a, std::string_view b);

}  // namespace surfel::server
