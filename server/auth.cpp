#include "auth.h"

#include <openssl/crypto.h>
#include <openssl/evp.h>
#include <openssl/hmac.h>
#include <openssl/rand.h>

#include <algorithm>
#include <cctype>
#include <fstream>
#include <set>
#include <sstream>

#include "surfel/base/error.h"
#include "surfel/worker/sha256.h"

namespace surfel::server {
namespace {

constexpr std::string_view kSha256Prefix = "sha256:";

bool ValidName(std::string_view name) {
    return !name.empty() && name.size() <= 64 && std::all_of(name.begin(), name.end(), [](char c) {
        return std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '.' || c == '-';
    });
}

bool ValidToken(std::string_view token) {
    return std::all_of(token.begin(), token.end(), [](char c) { return c > ' ' && c < 0x7f; });
}

bool LowerHex(std::string_view s) {
    return std::all_of(s.begin(), s.end(),
                       [](char c) { return (c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'); });
}

std::string Trim(std::string_view s) {
    std::size_t b = 0, e = s.size();
    while (b < e && std::isspace(static_cast<unsigned char>(s[b]))) ++b;
    while (e > b && std::isspace(static_cast<unsigned char>(s[e - 1]))) --e;
    return std::string(s.substr(b, e - b));
}

}  // namespace

bool ConstantTimeEquals(std::string_view a, std::string_view b) {
    if (a.size() != b.size()) return false;
    return CRYPTO_memcmp(a.data(), b.data(), a.size()) == 0;
}

std::string HashToken(std::string_view token) {
    return std::string(kSha256Prefix) + worker::Sha256Hex(token);
}

// ---- token file ---------------------------------------------------------------------------------

TokenSet TokenSet::Load(const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    if (!in) throw Error(ErrorCode::kInvalidArgument, "--auth-tokens: cannot read " + path);
    std::stringstream text;
    text << in.rdbuf();
    return Parse(text.str(), path);
}

TokenSet TokenSet::Parse(std::string_view text, const std::string& where) {
    TokenSet set;
    std::set<std::string> names, hashes;
    std::size_t line_no = 0;
    std::istringstream lines{std::string(text)};
    for (std::string raw; std::getline(lines, raw);) {
        ++line_no;
        const std::string line = Trim(raw);
        if (line.empty() || line[0] == '#') continue;
        const auto fail = [&](const std::string& what) {
            throw Error(ErrorCode::kInvalidArgument,
                        where + ":" + std::to_string(line_no) + ": " + what);
        };
        std::istringstream fields(line);
        std::string name, token, extra;
        fields >> name >> token;
        if (token.empty()) fail("expected NAME TOKEN (or NAME sha256:HEX), got one field");
        if (fields >> extra) fail("expected NAME TOKEN, got more than two fields");
        if (!ValidName(name)) fail("name '" + name + "' must match [A-Za-z0-9_.-]{1,64}");
        Entry e;
        e.name = name;
        if (token.rfind(kSha256Prefix, 0) == 0) {
            e.hash_hex = token.substr(kSha256Prefix.size());
            if (e.hash_hex.size() != 64 || !LowerHex(e.hash_hex))
                fail("tenant " + name + ": sha256: must be followed by 64 lowercase hex digits");
        } else {
            if (!ValidToken(token)) fail("tenant " + name + ": the token has a non-printable character");
            if (token.size() < 16 || token.size() > 4096)
                fail("tenant " + name + ": a token has 16 to 4096 characters (got " +
                     std::to_string(token.size()) + ")");
            e.hash_hex = worker::Sha256Hex(token);
        }
        if (!names.insert(name).second) fail("tenant " + name + " is listed twice");
        if (!hashes.insert(e.hash_hex).second) fail("tenant " + name + ": its token is another tenant's too");
        set.entries_.push_back(std::move(e));
    }
    if (set.entries_.empty())
        throw Error(ErrorCode::kInvalidArgument, where + ": no tokens (expected NAME TOKEN lines)");
    return set;
}

std::optional<std::string> TokenSet::Find(std::string_view token) const {
    const std::string hash = worker::Sha256Hex(token);
    const Entry* found = nullptr;
    for (const Entry& e : entries_)  // every entry, whichever matches
        if (ConstantTimeEquals(hash, e.hash_hex)) found = &e;
    if (!found) return std::nullopt;
    return found->name;
}

// ---- Authenticator ------------------------------------------------------------------------------

Caller Authenticator::Authenticate(std::string_view authorization) const {
    if (!enabled_) return {};
    if (authorization.empty())
        throw Error(ErrorCode::kUnauthenticated,
                    "missing credentials: send 'authorization: Bearer <token>'");
    constexpr std::string_view kBearer = "bearer ";
    std::string scheme(authorization.substr(0, std::min(authorization.size(), kBearer.size())));
    std::transform(scheme.begin(), scheme.end(), scheme.begin(),
                   [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
    if (scheme != kBearer)
        throw Error(ErrorCode::kUnauthenticated,
                    "unsupported authorization scheme: expected 'Bearer <token>'");
    const std::string token = Trim(authorization.substr(kBearer.size()));
    auto tenant = tokens_.Find(token);
    if (!tenant) throw Error(ErrorCode::kUnauthenticated, "invalid token");
    return Caller{*tenant, true};
}

// ---- UrlSigner ----------------------------------------------------------------------------------

UrlSigner::UrlSigner() : key_(32, '\0') {
    if (RAND_bytes(reinterpret_cast<unsigned char*>(key_.data()), static_cast<int>(key_.size())) != 1)
        throw Error(ErrorCode::kInternal, "RAND_bytes failed: no key for signed event URLs");
}

std::string UrlSigner::Sign(const std::string& job_id, const std::string& tenant,
                            std::int64_t expires_unix_ms) const {
    const std::string message = job_id + '\n' + tenant + '\n' + std::to_string(expires_unix_ms);
    unsigned char mac[EVP_MAX_MD_SIZE];
    unsigned int len = 0;
    HMAC(EVP_sha256(), key_.data(), static_cast<int>(key_.size()),
         reinterpret_cast<const unsigned char*>(message.data()), message.size(), mac, &len);
    static const char* kHex = "0123456789abcdef";
    std::string hex;
    for (unsigned int i = 0; i < len; ++i) {
        hex += kHex[mac[i] >> 4];
        hex += kHex[mac[i] & 15];
    }
    return hex;
}

bool UrlSigner::Verify(const std::string& job_id, const std::string& tenant,
                       std::int64_t expires_unix_ms, const std::string& signature,
                       std::int64_t now_unix_ms) const {
    const bool match = ConstantTimeEquals(Sign(job_id, tenant, expires_unix_ms), signature);
    return match && now_unix_ms <= expires_unix_ms;
}

}  // namespace surfel::server
