// cvislam_vocab as a user runs it: exit codes, messages naming the problem, byte-identical training, info and score.
#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "test/support/run_command.hpp"
#include "test/support/temp_dir.hpp"
#include "test/support/test_data.hpp"

namespace {

using ::testing::HasSubstr;

using cvislam::test::CommandResult;

CommandResult runVocab(const std::string& args) {
  return cvislam::test::runCommand(CVISLAM_VOCAB_BINARY, args);
}

std::string readBytes(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

TEST(CvislamVocabCli, UsageErrorsExitWithTwoAndHelpDescribesTheInterface) {
  EXPECT_EQ(runVocab("").exit_code, 2);                                // no subcommand
  EXPECT_EQ(runVocab("fly").exit_code, 2);                             // no such subcommand
  EXPECT_EQ(runVocab("train some/dataset").exit_code, 2);              // --out is required
  EXPECT_EQ(runVocab("train --out v.cvvoc").exit_code, 2);             // no dataset
  EXPECT_EQ(runVocab("train --out v.cvvoc --k 1 data").exit_code, 2);  // k below 2
  EXPECT_EQ(runVocab("train --out v.cvvoc --stride 0 data").exit_code, 2);
  EXPECT_EQ(runVocab("score --vocabulary v.cvvoc").exit_code, 2);  // no images
  const CommandResult one_image = runVocab("score --vocabulary v.cvvoc a.png");
  EXPECT_EQ(one_image.exit_code, 2);
  EXPECT_THAT(one_image.output, HasSubstr("two or more images"));
  EXPECT_EQ(runVocab("info").exit_code, 2);  // --vocabulary is required
  EXPECT_EQ(runVocab("info --vocabulary v.cvvoc --frobnicate").exit_code, 2);

  const CommandResult help = runVocab("--help");
  EXPECT_EQ(help.exit_code, 0);
  for (const char* word : {"train", "score", "info"}) EXPECT_THAT(help.output, HasSubstr(word));
  const CommandResult train_help = runVocab("train --help");
  EXPECT_EQ(train_help.exit_code, 0);
  for (const char* flag : {"--out", "--k", "--levels", "--seed", "--threads", "--stride", "--max-features"}) {
    EXPECT_THAT(train_help.output, HasSubstr(flag));
  }
}

TEST(CvislamVocabCli, MissingInputsExitWithOneNamingTheFile) {
  cvislam::test::TempDir dir;
  const std::string absent = (dir / "absent.cvvoc").string();
  const CommandResult info = runVocab("info --vocabulary " + absent);
  EXPECT_EQ(info.exit_code, 1);
  EXPECT_THAT(info.output, HasSubstr(absent));
  EXPECT_THAT(info.output, HasSubstr("no such vocabulary file"));
  const CommandResult score = runVocab("score --vocabulary " + absent + " a.png b.png");
  EXPECT_EQ(score.exit_code, 1);
  EXPECT_THAT(score.output, HasSubstr(absent));

  const CommandResult no_data = runVocab("train --out " + (dir / "v.cvvoc").string() + " " + (dir / "nope").string());
  EXPECT_EQ(no_data.exit_code, 1);
  EXPECT_THAT(no_data.output, HasSubstr((dir / "nope").string()));
  std::filesystem::create_directories(dir / "empty");
  const CommandResult empty = runVocab("train --out " + (dir / "v.cvvoc").string() + " " + (dir / "empty").string());
  EXPECT_EQ(empty.exit_code, 1);
  EXPECT_THAT(empty.output, HasSubstr("neither a EuRoC/ASL sequence"));
  EXPECT_FALSE(std::filesystem::exists(dir / "v.cvvoc"));

  cvislam::test::writeTextFile(dir / "garbage.cvvoc", "not a vocabulary at all");
  const CommandResult garbage = runVocab("info --vocabulary " + (dir / "garbage.cvvoc").string());
  EXPECT_EQ(garbage.exit_code, 1);
  EXPECT_THAT(garbage.output, HasSubstr("not a cvislam vocabulary"));
}

TEST(CvislamVocabCli, TrainingTwiceWritesTheSameBytesAndInfoAndScoreReadThem) {
  CVISLAM_REQUIRE_DATA(seq, "euroc-v101-excerpt");
  CVISLAM_REQUIRE_DATA(frames, "euroc-single-frames/vicon_room_stereo_loop_closure");
  cvislam::test::TempDir dir;
  const std::string out = (dir / "v.cvvoc").string();
  const std::string train =
      "train --out " + out + " --k 8 --levels 4 --seed 3 --stride 12 " + seq.string() + " " + frames.string() + "@2";
  const CommandResult first = runVocab(train + " --threads 1");
  ASSERT_EQ(first.exit_code, 0) << first.output;
  EXPECT_THAT(first.output, HasSubstr("every 12th frame: 16 images, 8000 descriptors"));  // 8 cam0 + 8 cam1
  EXPECT_THAT(first.output, HasSubstr("folder of images, every 2nd image: 4 images"));
  const std::string bytes = readBytes(out);
  ASSERT_GT(bytes.size(), 1000u);
  std::filesystem::remove(out);
  const CommandResult second = runVocab(train + " --threads 1");
  ASSERT_EQ(second.exit_code, 0) << second.output;
  EXPECT_EQ(readBytes(out), bytes);

  const CommandResult info = runVocab("info --vocabulary " + out);
  ASSERT_EQ(info.exit_code, 0) << info.output;
  for (const char* text : {"k:          8", "L:          4", "load time:", "seed 3", "command: ", "--stride 12",
                           "cvislam_vocab 0.", "16 images, 8000 descriptors", "total: 20 images"}) {
    EXPECT_THAT(info.output, HasSubstr(text));
  }

  const std::string json = (dir / "s.json").string();
  const CommandResult score = runVocab(
      "score --vocabulary " + out + " --json " + json + " --direct-level 1 " + (frames / "left_img_0.png").string() +
      " " + (frames / "left_img_1.png").string() + " " + (frames / "left_img_2.png").string());
  ASSERT_EQ(score.exit_code, 0) << score.output;
  EXPECT_THAT(score.output, HasSubstr("left_img_2.png"));
  const auto parsed = nlohmann::json::parse(cvislam::test::readTextFile(json));
  EXPECT_EQ(parsed["direct_level"], 1);
  ASSERT_EQ(parsed["images"].size(), 3u);
  ASSERT_EQ(parsed["pairs"].size(), 3u);  // 0-1, 0-2, 1-2
  for (const auto& pair : parsed["pairs"]) {
    EXPECT_GE(pair["score"].get<double>(), 0.0);
    EXPECT_LE(pair["score"].get<double>(), 1.0);
    EXPECT_LE(pair["direct_index_comparisons"].get<std::size_t>(), pair["all_comparisons"].get<std::size_t>());
  }
  // Pair 0-1 views one place from nearby poses; 0-2 another place.
  EXPECT_GT(parsed["pairs"][0]["score"].get<double>(), parsed["pairs"][1]["score"].get<double>());
}

}  // namespace
