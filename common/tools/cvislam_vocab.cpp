// cvislam_vocab: train, inspect and try out the ORB vocabulary of the server's place recognition.
//
//   cvislam_vocab train --out FILE [--k K] [--levels L] [--seed S] [--threads N] [--stride N] [--max-features N]
//                       DATASET[@STRIDE]...
//   cvislam_vocab score --vocabulary FILE [--json OUT] [--direct-level N] IMAGE...
//   cvislam_vocab info --vocabulary FILE
//
// A DATASET is a EuRoC/ASL sequence (the folder holding mav0, or mav0 itself: cam0 and cam1 images, every
// --stride-th frame of each) or a folder of images (.png, .jpg, .jpeg, .pgm; all of them, in name order).
// DATASET@N takes every N-th image of that one dataset. The vocabulary file records how it was made (the command
// line, each dataset's image and descriptor counts, k, L, seed, tool version) and no date: the same command on
// the same data writes a byte-identical file.
//
// Exit status: 0 done, 1 the inputs could not be used (the message names the file and the problem), 2 bad command
// line.
#include <algorithm>
#include <cctype>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include "common/core/steady_clock.hpp"
#include "common/dataset/euroc.hpp"
#include "common/dataset/image.hpp"
#include "common/dataset/image_codecs.hpp"
#include "common/features/orb.hpp"
#include "common/features/vocabulary.hpp"

#ifndef CVISLAM_VOCAB_VERSION
#define CVISLAM_VOCAB_VERSION "cvislam_vocab (unversioned build)"
#endif

namespace {

namespace fs = std::filesystem;
using cvislam::Error;
using cvislam::ErrorCode;
using cvislam::Result;
using cvislam::secondsSince;
using cvislam::Status;
using cvislam::features::Descriptor;
using Clock = std::chrono::steady_clock;

std::string fixed(double value, int decimals) {
  char text[64];
  std::snprintf(text, sizeof(text), "%.*f", decimals, value);
  return text;
}

// The command line as a shell would take it back: arguments with anything but safe characters in single quotes.
std::string commandLine(int argc, char** argv) {
  std::string line;
  for (int i = 0; i < argc; ++i) {
    const std::string arg = argv[i];
    const bool safe = !arg.empty() && std::all_of(arg.begin(), arg.end(), [](char c) {
      return std::isalnum(static_cast<unsigned char>(c)) != 0 ||
             std::string_view("@%+=:,./_-").find(c) != std::string_view::npos;
    });
    if (i > 0) line += ' ';
    if (safe) {
      line += arg;
    } else {
      line += '\'';
      for (char c : arg) line += c == '\'' ? std::string("'\\''") : std::string(1, c);
      line += '\'';
    }
  }
  return line;
}

// ORB extraction on images of any size up to 4096 x 4096: the extractor is made again, larger, when an image does
// not fit the one there is.
class Extractor {
 public:
  explicit Extractor(int max_features) { options_.max_features = max_features; }

  Result<std::vector<Descriptor>> extract(const cvislam::dataset::GrayImage& image, const std::string& name) {
    if (!extractor_ || image.width > options_.max_width || image.height > options_.max_height) {
      cvislam::features::OrbOptions options = options_;
      options.max_width = std::max(options.max_width, image.width);
      options.max_height = std::max(options.max_height, image.height);
      auto created = cvislam::features::OrbExtractor::create(options);
      if (!created) {
        return Error{ErrorCode::kInvalidArgument, name + ": " + std::to_string(image.width) + "x" +
                                                      std::to_string(image.height) +
                                                      " pixels: " + created.error().message()};
      }
      options_ = options;
      extractor_.emplace(std::move(*created));
      keypoints_.resize(static_cast<std::size_t>(options_.max_features));
      descriptors_.resize(keypoints_.size());
    }
    const int n = extractor_->extract(image.pixels, image.width, image.height, keypoints_, descriptors_);
    return std::vector<Descriptor>(descriptors_.begin(), descriptors_.begin() + n);
  }

 private:
  cvislam::features::OrbOptions options_;
  std::optional<cvislam::features::OrbExtractor> extractor_;
  std::vector<cvislam::features::Keypoint> keypoints_;
  std::vector<Descriptor> descriptors_;
};

bool isImageFile(const fs::path& path) {
  std::string ext = path.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
  return ext == ".png" || ext == ".jpg" || ext == ".jpeg" || ext == ".pgm";
}

// ---------------------------------------------------------------------------------------------------------------
// train

struct DatasetArg {
  fs::path path;
  std::optional<int> stride;  // from PATH@N
};

// PATH@N, unless a file or folder by the whole name exists.
Result<DatasetArg> parseDatasetArg(const std::string& arg) {
  std::error_code ec;
  const std::size_t at = arg.rfind('@');
  if (at != std::string::npos && at + 1 < arg.size() && !fs::exists(arg, ec)) {
    const std::string digits = arg.substr(at + 1);
    if (std::all_of(digits.begin(), digits.end(), [](char c) { return c >= '0' && c <= '9'; })) {
      const int stride = digits.size() <= 6 ? std::stoi(digits) : 0;
      if (stride < 1) return Error{ErrorCode::kInvalidArgument, arg + ": the stride after '@' must be 1 to 999999"};
      return DatasetArg{arg.substr(0, at), stride};
    }
  }
  return DatasetArg{arg, std::nullopt};
}

struct DatasetImages {
  std::string description;                          // "EuRoC sequence, cam0 + cam1, every 5th frame"
  std::vector<std::string> names;                   // for messages
  std::vector<fs::path> files;                      // plain folders
  std::vector<std::pair<int, std::size_t>> frames;  // sequences: (camera, frame)
  std::optional<cvislam::dataset::EurocSequence> sequence;
};

// "every frame", "every 2nd frame", "every 11th frame".
std::string every(int n, const std::string& noun) {
  if (n == 1) return "every " + noun;
  const int tens = n % 100;
  const char* suffix = (tens >= 11 && tens <= 13) ? "th"
                       : n % 10 == 1              ? "st"
                       : n % 10 == 2              ? "nd"
                       : n % 10 == 3              ? "rd"
                                                  : "th";
  return "every " + std::to_string(n) + suffix + " " + noun;
}

Result<DatasetImages> listDataset(const DatasetArg& arg, int default_stride) {
  std::error_code ec;
  if (!fs::exists(arg.path, ec)) return Error{ErrorCode::kNotFound, arg.path.string() + ": no such dataset folder"};
  if (!fs::is_directory(arg.path, ec)) {
    return Error{ErrorCode::kInvalidArgument,
                 arg.path.string() + ": is a file; give a EuRoC/ASL sequence folder or a folder of images"};
  }
  DatasetImages out;
  const bool is_sequence = fs::is_directory(arg.path / "mav0" / "cam0", ec) || fs::is_directory(arg.path / "cam0", ec);
  if (is_sequence) {
    const int stride = arg.stride.value_or(default_stride);
    cvislam::dataset::EurocReaderOptions options;
    options.require_imu = false;
    auto sequence = cvislam::dataset::EurocSequence::open(arg.path, options);
    if (!sequence) return sequence.error();
    std::string cameras;
    for (int camera = 0; camera < std::min(2, sequence->cameraCount()); ++camera) {
      const auto& stream = sequence->camera(camera);
      for (std::size_t frame = 0; frame < stream.frames.size(); frame += static_cast<std::size_t>(stride)) {
        out.frames.emplace_back(camera, frame);
        out.names.push_back(stream.imagePath(frame).string());
      }
      cameras += (camera == 0 ? "cam0" : " + cam1");
    }
    if (!sequence->diagnostics().empty()) {
      std::cerr << arg.path.string() << ": " << sequence->diagnostics().warningCount() << " finding(s) reading it:\n";
      sequence->diagnostics().print(std::cerr, 3);
    }
    out.description = "EuRoC sequence, " + cameras + ", " + every(stride, "frame");
    out.sequence.emplace(std::move(*sequence));
    return out;
  }
  std::vector<fs::path> files;
  for (const fs::directory_entry& entry : fs::directory_iterator(arg.path, ec)) {
    if (entry.is_regular_file(ec) && isImageFile(entry.path())) files.push_back(entry.path());
  }
  if (ec) return Error{ErrorCode::kIoError, arg.path.string() + ": cannot list: " + ec.message()};
  if (files.empty()) {
    return Error{ErrorCode::kNotFound, arg.path.string() +
                                           ": neither a EuRoC/ASL sequence (no mav0/cam0) nor a folder of images "
                                           "(.png, .jpg, .jpeg, .pgm)"};
  }
  std::sort(files.begin(), files.end());
  const int stride = arg.stride.value_or(1);
  for (std::size_t i = 0; i < files.size(); i += static_cast<std::size_t>(stride)) {
    out.files.push_back(files[i]);
    out.names.push_back(files[i].string());
  }
  out.description = "folder of images, " + every(stride, "image");
  return out;
}

struct TrainArgs {
  std::string out;
  int k = 10;
  int levels = 5;
  std::uint64_t seed = 1;
  int threads = 2;
  int stride = 5;
  int max_features = 500;
  int max_iterations = 10;
  std::vector<std::string> datasets;
};

int runTrain(const TrainArgs& args, const std::string& command) {
  const Clock::time_point start = Clock::now();
  std::vector<DatasetArg> dataset_args;
  for (const std::string& text : args.datasets) {
    auto parsed = parseDatasetArg(text);
    if (!parsed) {
      std::cerr << "cvislam_vocab train: " << parsed.error().message() << "\n";
      return 2;
    }
    dataset_args.push_back(*parsed);
  }
  Extractor extractor(args.max_features);
  std::vector<std::vector<Descriptor>> images;
  std::string data_lines;
  std::size_t total_descriptors = 0;
  for (const DatasetArg& dataset : dataset_args) {
    auto listed = listDataset(dataset, args.stride);
    if (!listed) {
      std::cerr << "cvislam_vocab train: " << listed.error().message() << "\n";
      return 1;
    }
    std::size_t descriptors = 0;
    const std::size_t count = listed->names.size();
    for (std::size_t i = 0; i < count; ++i) {
      auto image = listed->sequence ? listed->sequence->loadImage(listed->frames[i].first, listed->frames[i].second)
                                    : cvislam::dataset::readImageAsGray(listed->files[i]);
      if (!image) {
        std::cerr << "cvislam_vocab train: " << image.error().message() << "\n";
        return 1;
      }
      auto extracted = extractor.extract(*image, listed->names[i]);
      if (!extracted) {
        std::cerr << "cvislam_vocab train: " << extracted.error().message() << "\n";
        return 1;
      }
      descriptors += extracted->size();
      images.push_back(std::move(*extracted));
      if ((i + 1) % 100 == 0) std::cout << "  " << (i + 1) << " of " << count << " images read\n" << std::flush;
    }
    const std::string line = dataset.path.string() + ": " + listed->description + ": " + std::to_string(count) +
                             " images, " + std::to_string(descriptors) + " descriptors";
    std::cout << line << " (" << fixed(secondsSince(start), 1) << " s)\n" << std::flush;
    data_lines += "  " + line + "\n";
    total_descriptors += descriptors;
  }

  std::string provenance;
  provenance += "made by: " CVISLAM_VOCAB_VERSION "\n";
  provenance += "command: " + command + "\n";
  provenance += "training: hierarchical Hamming k-means, k " + std::to_string(args.k) + ", L " +
                std::to_string(args.levels) + ", seed " + std::to_string(args.seed) + ", at most " +
                std::to_string(args.max_iterations) + " iterations per node; ORB: at most " +
                std::to_string(args.max_features) + " features per image, OrbOptions defaults otherwise\n";
  provenance += "data:\n" + data_lines;
  provenance +=
      "total: " + std::to_string(images.size()) + " images, " + std::to_string(total_descriptors) + " descriptors\n";

  cvislam::features::VocabularyTrainingOptions options;
  options.branching = args.k;
  options.levels = args.levels;
  options.seed = args.seed;
  options.threads = args.threads;
  options.max_iterations = args.max_iterations;
  options.progress = [](const std::string& line) { std::cout << "  " << line << "\n" << std::flush; };
  const Clock::time_point training_start = Clock::now();
  auto vocabulary = cvislam::features::Vocabulary::train(images, options, provenance);
  if (!vocabulary) {
    std::cerr << "cvislam_vocab train: " << vocabulary.error().message() << "\n";
    return 1;
  }
  const double training_s = secondsSince(training_start);
  if (Status st = vocabulary->save(args.out); !st) {
    std::cerr << "cvislam_vocab train: " << st.error().message() << "\n";
    return 1;
  }
  std::error_code ec;
  std::cout << "wrote " << args.out << ": " << vocabulary->nodeCount() << " nodes, " << vocabulary->wordCount()
            << " words, " << fs::file_size(args.out, ec) << " bytes; " << images.size() << " images, "
            << total_descriptors << " descriptors; training " << fixed(training_s, 1) << " s, all "
            << fixed(secondsSince(start), 1) << " s\n";
  return 0;
}

// ---------------------------------------------------------------------------------------------------------------
// score

Result<cvislam::features::Vocabulary> loadVocabulary(const std::string& path, double* load_ms = nullptr) {
  const Clock::time_point start = Clock::now();
  auto vocabulary = cvislam::features::Vocabulary::load(path);
  if (load_ms != nullptr) *load_ms = 1e3 * secondsSince(start);
  return vocabulary;
}

int runScore(const std::string& vocabulary_path, const std::string& json_path, int direct_level,
             const std::vector<std::string>& image_paths) {
  auto vocabulary = loadVocabulary(vocabulary_path);
  if (!vocabulary) {
    std::cerr << "cvislam_vocab score: cannot load the vocabulary: " << vocabulary.error().message() << "\n";
    return 1;
  }
  struct Scored {
    int width = 0;
    int height = 0;
    std::size_t features = 0;
    cvislam::features::BowVector bow;
    cvislam::features::FeatureVector direct;
  };
  Extractor extractor(500);
  std::vector<Scored> scored;
  for (const std::string& path : image_paths) {
    auto image = cvislam::dataset::readImageAsGray(path);
    if (!image) {
      std::cerr << "cvislam_vocab score: " << image.error().message() << "\n";
      return 1;
    }
    auto descriptors = extractor.extract(*image, path);
    if (!descriptors) {
      std::cerr << "cvislam_vocab score: " << descriptors.error().message() << "\n";
      return 1;
    }
    Scored s;
    s.width = image->width;
    s.height = image->height;
    s.features = descriptors->size();
    vocabulary->transform(*descriptors, s.bow, &s.direct, direct_level);
    scored.push_back(std::move(s));
  }
  const int level = std::clamp(direct_level, 0, vocabulary->levels());

  std::cout << "vocabulary: " << vocabulary_path << " (k " << vocabulary->branching() << ", L " << vocabulary->levels()
            << ", " << vocabulary->wordCount() << " words)\n";
  std::cout << "images:\n     #  features  words  file\n";
  for (std::size_t i = 0; i < scored.size(); ++i) {
    char row[64];
    std::snprintf(row, sizeof(row), "  %4zu  %8zu  %5zu  ", i, scored[i].features, scored[i].bow.size());
    std::cout << row << image_paths[i] << "\n";
  }
  std::cout << "pairs: BoW similarity in [0, 1] (1 - |a - b|_1 / 2); common words; direct index at level " << level
            << ": descriptor comparisons under shared nodes, of all pairs\n";
  std::cout << "     a     b   score  common  direct-index comparisons\n";
  nlohmann::json json;
  json["vocabulary"] = vocabulary_path;
  json["branching"] = vocabulary->branching();
  json["levels"] = vocabulary->levels();
  json["words"] = vocabulary->wordCount();
  json["direct_level"] = level;
  json["images"] = nlohmann::json::array();
  for (std::size_t i = 0; i < scored.size(); ++i) {
    json["images"].push_back({{"path", image_paths[i]},
                              {"width", scored[i].width},
                              {"height", scored[i].height},
                              {"features", scored[i].features},
                              {"words", scored[i].bow.size()}});
  }
  json["pairs"] = nlohmann::json::array();
  for (std::size_t a = 0; a < scored.size(); ++a) {
    for (std::size_t b = a + 1; b < scored.size(); ++b) {
      const double score = cvislam::features::bowScore(scored[a].bow, scored[b].bow);
      std::size_t common = 0;
      for (std::size_t i = 0, j = 0; i < scored[a].bow.size() && j < scored[b].bow.size();) {
        const auto wa = scored[a].bow[i].word;
        const auto wb = scored[b].bow[j].word;
        if (wa == wb) ++common;
        if (wa <= wb) ++i;
        if (wb <= wa) ++j;
      }
      // Feature vectors are sorted by node: count the pairs under each shared node.
      std::size_t comparisons = 0;
      const auto& fa = scored[a].direct;
      const auto& fb = scored[b].direct;
      for (std::size_t i = 0, j = 0; i < fa.size() && j < fb.size();) {
        if (fa[i].node < fb[j].node) {
          ++i;
        } else if (fb[j].node < fa[i].node) {
          ++j;
        } else {
          std::size_t i_end = i;
          std::size_t j_end = j;
          while (i_end < fa.size() && fa[i_end].node == fa[i].node) ++i_end;
          while (j_end < fb.size() && fb[j_end].node == fb[j].node) ++j_end;
          comparisons += (i_end - i) * (j_end - j);
          i = i_end;
          j = j_end;
        }
      }
      const std::size_t all = scored[a].features * scored[b].features;
      char row[128];
      std::snprintf(row, sizeof(row), "  %4zu  %4zu  %.4f  %6zu  %zu of %zu\n", a, b, score, common, comparisons, all);
      std::cout << row;
      json["pairs"].push_back({{"a", a},
                               {"b", b},
                               {"score", score},
                               {"common_words", common},
                               {"direct_index_comparisons", comparisons},
                               {"all_comparisons", all}});
    }
  }
  if (!json_path.empty()) {
    std::ofstream out(json_path, std::ios::binary);
    out << json.dump(2) << "\n";
    out.close();
    if (!out) {
      std::cerr << "cvislam_vocab score: " << json_path << ": cannot write\n";
      return 1;
    }
  }
  return 0;
}

// ---------------------------------------------------------------------------------------------------------------
// info

int runInfo(const std::string& vocabulary_path) {
  double load_ms = 0.0;
  auto vocabulary = loadVocabulary(vocabulary_path, &load_ms);
  if (!vocabulary) {
    std::cerr << "cvislam_vocab info: cannot load the vocabulary: " << vocabulary.error().message() << "\n";
    return 1;
  }
  std::error_code ec;
  std::vector<float> idf(vocabulary->wordCount());
  for (std::size_t w = 0; w < idf.size(); ++w) idf[w] = vocabulary->idf(static_cast<cvislam::features::WordId>(w));
  std::sort(idf.begin(), idf.end());
  const std::size_t zero = static_cast<std::size_t>(std::count(idf.begin(), idf.end(), 0.0F));
  std::cout << "file:       " << vocabulary_path << " (" << fs::file_size(vocabulary_path, ec) << " bytes)\n";
  std::cout << "k:          " << vocabulary->branching() << "\n";
  std::cout << "L:          " << vocabulary->levels() << "\n";
  std::cout << "nodes:      " << vocabulary->nodeCount() << "\n";
  std::cout << "words:      " << vocabulary->wordCount() << "\n";
  if (!idf.empty()) {
    std::cout << "idf:        min " << fixed(idf.front(), 3) << ", median " << fixed(idf[idf.size() / 2], 3) << ", max "
              << fixed(idf.back(), 3) << " (" << zero << " word(s) with idf 0)\n";
  }
  std::cout << "load time:  " << fixed(load_ms, 1) << " ms\n";
  std::cout << "provenance:\n";
  std::string line;
  for (char c : vocabulary->provenance()) {
    if (c == '\n') {
      std::cout << "  " << line << "\n";
      line.clear();
    } else {
      line += c;
    }
  }
  if (!line.empty()) std::cout << "  " << line << "\n";
  return 0;
}

}  // namespace

static int run(int argc, char** argv) {
  CLI::App app{
      "Train, inspect and try out the hierarchical ORB vocabulary (bag of binary words) of the server's "
      "place recognition.",
      "cvislam_vocab"};
  app.require_subcommand(1);
  app.set_version_flag("--version", CVISLAM_VOCAB_VERSION);

  TrainArgs train;
  CLI::App* train_cmd = app.add_subcommand(
      "train",
      "Extract ORB features from datasets and train a vocabulary. A DATASET is a EuRoC/ASL sequence (the folder "
      "holding mav0, or mav0 itself: cam0 and cam1 images, every --stride-th frame of each) or a folder of images "
      "(.png/.jpg/.jpeg/.pgm, all of them, colour converted to grey). DATASET@N takes every N-th image of that one "
      "dataset. The file records the command, the data, k, L, the seed and the tool version, and no date: the same "
      "command on the same data writes the same bytes.");
  train_cmd->add_option("--out", train.out, "The vocabulary file to write")->required();
  train_cmd->add_option("--k", train.k, "Branching factor: children per node")->check(CLI::Range(2, 1000));
  train_cmd->add_option("--levels", train.levels, "Levels below the root (L)")->check(CLI::Range(1, 32));
  train_cmd->add_option("--seed", train.seed, "Seed of the k-means++ seeding");
  train_cmd->add_option("--threads", train.threads, "Training threads; the result does not depend on them")
      ->check(CLI::Range(1, 256));
  train_cmd
      ->add_option("--stride", train.stride,
                   "Take every N-th frame of each camera of a EuRoC sequence (folders of images: every image)")
      ->check(CLI::Range(1, 1000000));
  train_cmd->add_option("--max-features", train.max_features, "ORB features per image")->check(CLI::Range(1, 65536));
  train_cmd->add_option("--max-iterations", train.max_iterations, "k-means iterations per node at most")
      ->check(CLI::Range(1, 1000));
  train_cmd
      ->add_option("DATASET", train.datasets, "EuRoC/ASL sequence folders or folders of images, each optionally @N")
      ->required();

  std::string vocabulary_path;
  std::string json_path;
  int direct_level = 2;
  std::vector<std::string> images;
  CLI::App* score_cmd = app.add_subcommand(
      "score",
      "Print the BoW similarity of every pair of images (any size, grey or colour; 500 ORB features each) and, per "
      "pair, how many descriptor comparisons the direct index at --direct-level leaves.");
  score_cmd->add_option("--vocabulary", vocabulary_path, "Vocabulary file")->required();
  score_cmd->add_option("--json", json_path, "Also write the results as JSON to this file");
  score_cmd->add_option("--direct-level", direct_level, "Direct-index level, 0 = root (clamped to L); default 2")
      ->check(CLI::Range(0, 64));
  score_cmd->add_option("IMAGE", images, "Two or more images")->required();

  std::string info_path;
  CLI::App* info_cmd =
      app.add_subcommand("info", "Print k, L, the node and word counts, idf figures, the load time and the provenance");
  info_cmd->add_option("--vocabulary", info_path, "Vocabulary file")->required();

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    // --help and --version exit 0; any other command-line error exits 2 after CLI11 prints it.
    return app.exit(e) == 0 ? 0 : 2;
  }
  if (train_cmd->parsed()) return runTrain(train, commandLine(argc, argv));
  if (score_cmd->parsed()) {
    if (images.size() < 2) {
      std::cerr << "cvislam_vocab score: give two or more images to compare\n";
      return 2;
    }
    return runScore(vocabulary_path, json_path, direct_level, images);
  }
  if (info_cmd->parsed()) return runInfo(info_path);
  return 2;
}

int main(int argc, char** argv) {
  try {
    return run(argc, argv);
  } catch (const std::exception& e) {  // a bug, or the system out of memory: say so instead of aborting
    std::cerr << "cvislam_vocab: internal error: " << e.what() << "\n";
    return 1;
  }
}
