// Where tests find the real data of ../shared/data, and how they skip when it is absent.
#pragma once

#include <filesystem>
#include <string>

#include <gtest/gtest.h>

namespace cvislam::test {

// $CVISLAM_DATA_DIR if set, else the build's default (<repo>/../shared/data).
std::filesystem::path dataRoot();

// dataRoot() / relative if that exists, else an empty path.
std::filesystem::path findData(const std::string& relative);

}  // namespace cvislam::test

// Declares `var` = dataRoot()/relative, or skips the test, saying which data is missing and how to
// provide it. CTest reports the test as skipped, not as passed.
// NOLINTBEGIN(bugprone-macro-parentheses): `var` is the name the macro declares.
#define CVISLAM_REQUIRE_DATA(var, relative)                                                            \
  const std::filesystem::path var = ::cvislam::test::findData(relative);                               \
  if (var.empty()) {                                                                                   \
    GTEST_SKIP() << "test data '" << (relative) << "' not found under " << ::cvislam::test::dataRoot() \
                 << " (set CVISLAM_DATA_DIR to the folder holding the shared data)";                   \
  }
// NOLINTEND(bugprone-macro-parentheses)
