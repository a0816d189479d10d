#include <gtest/gtest.h>

#include "surfel/base/error.h"
#include "surfel/base/progress.h"

namespace surfel {
namespace {

TEST(ProgressTracker, ReportsMonotoneFractionsEndingAtOne) {
    std::vector<double> seen;
    ProgressTracker t([&](double f) { seen.push_back(f); return true; }, 1000, "test");
    for (int i = 0; i < 1000; ++i) t.Advance();
    ASSERT_FALSE(seen.empty());
    EXPECT_DOUBLE_EQ(seen.back(), 1.0);
    for (std::size_t i = 1; i < seen.size(); ++i) EXPECT_GT(seen[i], seen[i - 1]);
    EXPECT_LE(seen.size(), 101u);
}

TEST(ProgressTracker, CancelThrowsCancelledNamingTheStage) {
    ProgressTracker t([](double f) { return f < 0.5; }, 100, "normal estimation");
    try {
        for (int i = 0; i < 100; ++i) t.Advance();
        FAIL() << "not cancelled";
    } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kCancelled);
        EXPECT_STREQ(e.what(), "cancelled during normal estimation");
    }
    EXPECT_TRUE(t.cancelled());
}

}  // namespace
}  // namespace surfel
