#include "common/core/text.hpp"

#include <gmock/gmock.h>
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

TEST(IsPrintableToken, AcceptsPrintableAsciiWithoutSpacesOnly) {
  EXPECT_TRUE(isPrintableToken("4f1c0a57-c2a0_4b2e~!"));
  EXPECT_FALSE(isPrintableToken(""));
  EXPECT_FALSE(isPrintableToken("with space"));
  EXPECT_FALSE(isPrintableToken("tab\there"));
  EXPECT_FALSE(isPrintableToken("line\n"));
  EXPECT_FALSE(isPrintableToken("caf\xc3\xa9"));
  EXPECT_FALSE(isPrintableToken(std::string_view("nul\0x", 5)));
}

TEST(ReadFiles, WholeFilesPemChecksAndErrorsThatNameTheFile) {
  cvislam::test::TempDir dir;
  std::ofstream(dir.path() / "ca.pem") << "-----BEGIN CERTIFICATE-----\nAAAA\n-----END CERTIFICATE-----\n";
  std::ofstream(dir.path() / "notes.txt") << "line 1\nline 2";
  const auto pem = readPemFile(dir.path() / "ca.pem", "CA file");
  const auto text = readTextFile(dir.path() / "notes.txt", "notes");
  const auto not_pem = readPemFile(dir.path() / "notes.txt", "CA file");
  const auto missing = readTextFile(dir.path() / "absent", "tokens file");

  ASSERT_TRUE(pem.ok());
  EXPECT_THAT(*pem, ::testing::StartsWith("-----BEGIN CERTIFICATE-----"));
  ASSERT_TRUE(text.ok());
  EXPECT_EQ(*text, "line 1\nline 2");
  ASSERT_FALSE(not_pem.ok());
  EXPECT_EQ(not_pem.error().code(), ErrorCode::kParseError);
  EXPECT_THAT(not_pem.error().message(),
              ::testing::HasSubstr("the CA file " + (dir.path() / "notes.txt").string() + " is not a PEM file"));
  ASSERT_FALSE(missing.ok());
  EXPECT_EQ(missing.error().code(), ErrorCode::kNotFound);
  EXPECT_THAT(missing.error().message(), ::testing::HasSubstr("cannot read the tokens file"));
}

}  // namespace
}  // namespace cvislam::text
