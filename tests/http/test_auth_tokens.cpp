// The token file, the bearer check and the signed event URLs (server/auth.h), table-driven.
#include <gtest/gtest.h>

#include <functional>

#include "auth.h"
#include "surfel/base/error.h"

namespace surfel::server {
namespace {

constexpr const char* kAlice = "alice-0123456789abcdef";

ErrorCode CodeOf(const std::function<void()>& fn, std::string* message) {
    try {
        fn();
    } catch (const Error& e) {
        *message = e.what();
        return e.code();
    }
    return ErrorCode::kInternal;
}

TEST(TokenSet, ParsesPlainAndHashedTokensAndComments) {
    const std::string text = std::string("# tenants\n\n  alice ") + kAlice + "  \nbob\t" +
                             HashToken("bob-fedcba9876543210") + "\n";
    const TokenSet set = TokenSet::Parse(text, "tokens");
    EXPECT_EQ(set.size(), 2u);
    EXPECT_EQ(set.Find(kAlice), "alice");
    EXPECT_EQ(set.Find("bob-fedcba9876543210"), "bob");
    EXPECT_FALSE(set.Find("bob-fedcba987654321"));
    EXPECT_FALSE(set.Find(""));
}

TEST(TokenSet, MalformedLinesNameFileAndLine) {
    const std::pair<std::string, std::string> cases[] = {
        {"alice\n", "tokens:1: expected NAME TOKEN"},
        {"# c\nalice a b c\n", "tokens:2: expected NAME TOKEN, got more"},
        {"al/ice 0123456789abcdef0\n", "tokens:1: name 'al/ice'"},
        {"alice short\n", "tokens:1: tenant alice: a token has 16 to 4096"},
        {"alice sha256:abc\n", "tokens:1: tenant alice: sha256: must be followed by 64"},
        {std::string("alice ") + kAlice + "\nalice other-0123456789abc\n", "tokens:2: tenant alice is listed twice"},
        {std::string("alice ") + kAlice + "\nbob " + kAlice + "\n", "tokens:2: tenant bob: its token"},
        {"# nothing\n", "tokens: no tokens"},
    };
    for (const auto& [text, expected] : cases) {
        std::string message;
        EXPECT_EQ(CodeOf([&] { TokenSet::Parse(text, "tokens"); }, &message), ErrorCode::kInvalidArgument)
            << text;
        EXPECT_NE(message.find(expected), std::string::npos) << message;
    }
}

TEST(Authenticator, OffLetsEveryoneInAsTheDefaultTenant) {
    const Caller c = Authenticator().Authenticate("");
    EXPECT_EQ(c.tenant, "");
    EXPECT_FALSE(c.scoped);
}

TEST(Authenticator, BearerTokensOnlyOtherwiseUnauthenticated) {
    const Authenticator auth(TokenSet::Parse(std::string("alice ") + kAlice, "t"));
    const Caller c = auth.Authenticate(std::string("Bearer ") + kAlice);
    EXPECT_EQ(c.tenant, "alice");
    EXPECT_TRUE(c.scoped);
    EXPECT_EQ(auth.Authenticate(std::string("bearer ") + kAlice).tenant, "alice");
    for (const std::string& bad : {std::string(), std::string("Bearer"), std::string("Bearer wrong-0123456789abc"),
                                  std::string("Basic ") + kAlice, std::string(kAlice)}) {
        std::string message;
        EXPECT_EQ(CodeOf([&] { auth.Authenticate(bad); }, &message), ErrorCode::kUnauthenticated) << bad;
    }
}

TEST(UrlSigner, SignedUrlsBindJobTenantAndExpiry) {
    const UrlSigner s;
    const std::string sig = s.Sign("j1", "alice", 1000);
    EXPECT_EQ(sig.size(), 64u);
    EXPECT_TRUE(s.Verify("j1", "alice", 1000, sig, 999));
    EXPECT_TRUE(s.Verify("j1", "alice", 1000, sig, 1000));
    EXPECT_FALSE(s.Verify("j1", "alice", 1000, sig, 1001));  // expired
    EXPECT_FALSE(s.Verify("j2", "alice", 1000, sig, 0));
    EXPECT_FALSE(s.Verify("j1", "bob", 1000, sig, 0));
    EXPECT_FALSE(s.Verify("j1", "alice", 2000, sig, 0));
    EXPECT_FALSE(UrlSigner().Verify("j1", "alice", 1000, sig, 0));  // another process's key
}

}  // namespace
}  // namespace surfel::server
