// CVISLAM_CHECK stays on in every build: the default preset defines NDEBUG, and these death tests run there too.
#include "common/core/check.hpp"

#include <gtest/gtest.h>

#include "common/core/result.hpp"

namespace cvislam {
namespace {

TEST(CheckDeathTest, AFailedCheckAbortsNamingTheFileTheConditionAndTheMessage) {
  const int capacity = 3;
  EXPECT_DEATH(CVISLAM_CHECK(capacity > 4, "the pool is too small"),
               "check_test.cpp:[0-9]+: check failed: capacity > 4 \\(the pool is too small\\)");
}

TEST(CheckDeathTest, APassingCheckDoesNothing) {
  int evaluated = 0;
  CVISLAM_CHECK(++evaluated == 1, "evaluated once");
  EXPECT_EQ(evaluated, 1);
}

TEST(CheckDeathTest, TheValueOfAFailedResultStopsTheProgramEvenWithNdebug) {
  const Result<int> failed = Error{ErrorCode::kNotFound, "nothing"};
  EXPECT_DEATH((void)failed.value(), "Result::value\\(\\) on an error");
  EXPECT_DEATH((void)Status::Ok().error(), "Status::error\\(\\) on OK");
}

}  // namespace
}  // namespace cvislam
