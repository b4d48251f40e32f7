#include "common/core/text.hpp"

#include <gtest/gtest.h>

#include "test/support/temp_dir.hpp"

namespace cvislam::text {
namespace {

TEST(ParseSecondsAsNs, IsExactWhereADoubleIsNot) {
  // 1.403636579763555527e+09 s as a double is 1403636579763555584 ns: 57 ns off.
  EXPECT_EQ(parseSecondsAsNs("1.403636579763555527e+09"), 1403636579763555527LL);
  EXPECT_EQ(parseSecondsAsNs("1403715273.262142976"), 1403715273262142976LL);
  EXPECT_EQ(parseSecondsAsNs("1305031102.160407"), 1305031102160407000LL);
  EXPECT_EQ(parseSecondsAsNs("0.000000001"), 1);
  EXPECT_EQ(parseSecondsAsNs("-1.5"), -1500000000LL);
  EXPECT_EQ(parseSecondsAsNs("1e-9"), 1);
  EXPECT_EQ(parseSecondsAsNs("12"), 12000000000LL);
  EXPECT_EQ(parseSecondsAsNs(".5"), 500000000LL);
}

TEST(ParseSecondsAsNs, RoundsBeyondNanoseconds) {
  EXPECT_EQ(parseSecondsAsNs("0.0000000014"), 1);
  EXPECT_EQ(parseSecondsAsNs("0.0000000015"), 2);
  EXPECT_EQ(parseSecondsAsNs("1.4036365797635555279e+09"), 1403636579763555528LL);
}

TEST(ParseSecondsAsNs, RejectsJunkAndOverflow) {
  for (const char* bad : {"", "abc", "1.2.3", "1e", "1e+", "12x", "-", ".", "1e400", "9.3e9", "nan", "inf"}) {
    EXPECT_FALSE(parseSecondsAsNs(bad).has_value()) << bad;
  }
}

TEST(FormatNsAsSeconds, RoundTrips) {
  for (std::int64_t t : {0LL, 1LL, 1403715273262142976LL, -1500000000LL, 999999999LL}) {
    EXPECT_EQ(parseSecondsAsNs(formatNsAsSeconds(t)), t) << formatNsAsSeconds(t);
  }
  EXPECT_EQ(formatNsAsSeconds(1403715273262142976LL), "1403715273.262142976");
}

TEST(ParseNumbers, RejectNonNumericAndNonFinite) {
  EXPECT_EQ(parseInt64(" 42 "), 42);
  EXPECT_EQ(parseInt64("+7"), 7);
  EXPECT_FALSE(parseInt64("4.2").has_value());
  EXPECT_FALSE(parseInt64("").has_value());
  EXPECT_EQ(parseDouble("-1.7e-05"), -1.7e-05);
  EXPECT_FALSE(parseDouble("nan").has_value());
  EXPECT_FALSE(parseDouble("inf").has_value());
  EXPECT_FALSE(parseDouble("0.5x").has_value());
  EXPECT_FALSE(parseDouble("").has_value());
}

TEST(SplitFields, CommaAndWhitespace) {
  std::vector<std::string_view> f;
  splitFields("1, 2 ,3,", true, f);
  ASSERT_EQ(f.size(), 4u);
  EXPECT_EQ(f[1], "2");
  EXPECT_EQ(f[3], "");
  splitFields("  a\tb   c ", false, f);
  ASSERT_EQ(f.size(), 3u);
  EXPECT_EQ(f[2], "c");
}

TEST(LineReader, StripsCarriageReturnsAndCountsLines) {
  test::TempDir dir;
  test::writeTextFile(dir / "f.csv", "a\r\nb\n\nc");
  auto reader = LineReader::open(dir / "f.csv");
  ASSERT_TRUE(reader.ok());
  std::string_view line;
  std::vector<std::string> lines;
  while (reader->next(line)) lines.emplace_back(line);
  EXPECT_EQ(lines, (std::vector<std::string>{"a", "b", "", "c"}));
  EXPECT_EQ(reader->lineNumber(), 4);
}

TEST(LineReader, MissingFileAndFolderGiveClearErrors) {
  test::TempDir dir;
  auto missing = LineReader::open(dir / "nope.csv");
  ASSERT_FALSE(missing.ok());
  EXPECT_EQ(missing.error().code(), ErrorCode::kNotFound);
  EXPECT_NE(missing.error().message().find("nope.csv"), std::string::npos);
  auto folder = LineReader::open(dir.path());
  ASSERT_FALSE(folder.ok());
  EXPECT_NE(folder.error().message().find("folder"), std::string::npos);
}

}  // namespace
}  // namespace cvislam::text
