// The agent's own PNG decoder against OpenCV's (libpng), on PNGs written here with every row filter, on files
// libpng wrote, on the real EuRoC excerpt, and on broken and foreign files (which the agent's loader names and
// says how to convert; OpenCV's reader in image_codecs.hpp reads them for the tools).
#include "common/dataset/png_gray.hpp"

#include <libdeflate.h>

#include <cstdlib>
#include <fstream>
#include <random>
#include <string>
#include <utility>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "common/dataset/euroc.hpp"
#include "common/dataset/image.hpp"
#include "common/dataset/image_codecs.hpp"
#include "test/support/temp_dir.hpp"
#include "test/support/test_data.hpp"

namespace cvislam::dataset {
namespace {

using Bytes = std::vector<std::uint8_t>;

void putBigEndian32(Bytes& out, std::uint32_t v) {
  for (int shift = 24; shift >= 0; shift -= 8) out.push_back(static_cast<std::uint8_t>(v >> shift));
}

void putChunk(Bytes& out, const char* type, const Bytes& data) {
  putBigEndian32(out, static_cast<std::uint32_t>(data.size()));
  Bytes typed(type, type + 4);
  typed.insert(typed.end(), data.begin(), data.end());
  out.insert(out.end(), typed.begin(), typed.end());
  putBigEndian32(out, libdeflate_crc32(0, typed.data(), typed.size()));
}

int paeth(int a, int b, int c) {
  const int p = a + b - c;
  const int pa = std::abs(p - a);
  const int pb = std::abs(p - b);
  const int pc = std::abs(p - c);
  return (pa <= pb && pa <= pc) ? a : (pb <= pc ? b : c);
}

// An 8-bit grey PNG of `image`, row y filtered with filter_of_row(y) (0-4, or any byte to make a broken file),
// IDAT split into `idat_chunks` chunks.
template <typename FilterOfRow>
Bytes encodePng(const GrayImage& image, FilterOfRow filter_of_row, int idat_chunks = 1) {
  const auto w = static_cast<std::size_t>(image.width);
  Bytes filtered;
  for (int y = 0; y < image.height; ++y) {
    const int type = filter_of_row(y);
    filtered.push_back(static_cast<std::uint8_t>(type));
    for (std::size_t x = 0; x < w; ++x) {
      const int v = image.at(static_cast<int>(x), y);
      const int a = x > 0 ? image.at(static_cast<int>(x) - 1, y) : 0;
      const int b = y > 0 ? image.at(static_cast<int>(x), y - 1) : 0;
      const int c = x > 0 && y > 0 ? image.at(static_cast<int>(x) - 1, y - 1) : 0;
      const int predictor = type == 1 ? a : type == 2 ? b : type == 3 ? (a + b) / 2 : type == 4 ? paeth(a, b, c) : 0;
      filtered.push_back(static_cast<std::uint8_t>(v - predictor));
    }
  }
  libdeflate_compressor* deflater = libdeflate_alloc_compressor(6);
  Bytes deflated(libdeflate_zlib_compress_bound(deflater, filtered.size()));
  deflated.resize(
      libdeflate_zlib_compress(deflater, filtered.data(), filtered.size(), deflated.data(), deflated.size()));
  libdeflate_free_compressor(deflater);

  Bytes png = {137, 'P', 'N', 'G', '\r', '\n', 26, '\n'};
  Bytes header;
  putBigEndian32(header, static_cast<std::uint32_t>(image.width));
  putBigEndian32(header, static_cast<std::uint32_t>(image.height));
  header.insert(header.end(), {8, 0, 0, 0, 0});
  putChunk(png, "IHDR", header);
  putChunk(png, "tEXt", Bytes{'a', 0, 'b'});  // an ancillary chunk to skip
  const std::size_t step = deflated.size() / static_cast<std::size_t>(idat_chunks) + 1;
  for (std::size_t start = 0; start < deflated.size(); start += step) {
    putChunk(png, "IDAT",
             Bytes(deflated.begin() + static_cast<std::ptrdiff_t>(start),
                   deflated.begin() + static_cast<std::ptrdiff_t>(std::min(deflated.size(), start + step))));
  }
  putChunk(png, "IEND", {});
  return png;
}

GrayImage randomImage(int width, int height, unsigned seed) {
  std::mt19937 rng(seed);
  GrayImage image(width, height);
  for (auto& p : image.pixels) p = static_cast<std::uint8_t>(rng() & 0xff);
  return image;
}

// A smooth image with an edge: the filters' predictors matter, and Paeth takes each of its three branches.
GrayImage smoothImage(int width, int height) {
  GrayImage image(width, height);
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x)
      image.at(x, y) = static_cast<std::uint8_t>((x * 3 + y * 5 + (x > y ? 90 : 0)) & 0xff);
  }
  return image;
}

void writeBytes(const std::filesystem::path& path, const Bytes& bytes) {
  std::ofstream(path, std::ios::binary)
      .write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
}

// Writes `file` to `path` and decodes it with `png`: the pixels, or an empty vector (with a test failure) when the
// decoder refuses it or hands it back.
std::vector<std::uint8_t> writeAndDecode(GrayPngDecoder& png, const std::filesystem::path& path, const Bytes& file,
                                         int width, int height) {
  writeBytes(path, file);
  std::vector<std::uint8_t> pixels(static_cast<std::size_t>(width) * static_cast<std::size_t>(height), 0xAB);
  auto decoded = png.decodeInto(path, width, height, pixels);
  EXPECT_TRUE(decoded.ok()) << decoded.error().toString();
  if (!decoded.ok()) return {};
  EXPECT_TRUE(*decoded) << path << " was handed back undecoded";
  return *decoded ? pixels : std::vector<std::uint8_t>{};
}

TEST(GrayPngDecoder, UndoesEveryRowFilterExactlyAsLibpngDoes) {
  test::TempDir dir;
  GrayPngDecoder png;
  for (const GrayImage& image : {randomImage(61, 37, 7), smoothImage(64, 48)}) {
    for (int first_filter = 0; first_filter < 5; ++first_filter) {
      const Bytes file = encodePng(
          image, [&](int y) { return (y + first_filter) % 5; }, 3);
      const auto path = dir.path() / ("f" + std::to_string(first_filter) + ".png");
      EXPECT_EQ(writeAndDecode(png, path, file, image.width, image.height), image.pixels)
          << "first row filter " << first_filter;
      auto by_libpng = readImageAsGray(path);  // the test's encoder is right too
      ASSERT_TRUE(by_libpng.ok()) << by_libpng.error().toString();
      EXPECT_EQ(by_libpng->pixels, image.pixels);
    }
  }
}

// Rows are undone in pairs, with a loop for each pair of filter types: every one of the 25 pairs, the first row
// of the image in each, and an odd last row.
TEST(GrayPngDecoder, UndoesEveryPairOfRowFilters) {
  test::TempDir dir;
  GrayPngDecoder png;
  const GrayImage image = smoothImage(67, 2 * 25 + 1);
  for (int shift = 0; shift < 2; ++shift) {  // the pairs start on even rows; shifted, each pair also starts one
    const Bytes file = encodePng(image, [&](int y) {
      const int pair = (y + shift) / 2 % 25;
      return (y + shift) % 2 == 0 ? pair / 5 : pair % 5;
    });
    const auto path = dir.path() / ("pairs" + std::to_string(shift) + ".png");
    EXPECT_EQ(writeAndDecode(png, path, file, image.width, image.height), image.pixels) << "shift " << shift;
  }
  for (int type = 0; type < 5; ++type) {  // the first row alone (a one-row image) with each filter
    const GrayImage one_row = smoothImage(40, 1);
    const auto path = dir.path() / ("row" + std::to_string(type) + ".png");
    const Bytes file = encodePng(one_row, [&](int /*y*/) { return type; });
    EXPECT_EQ(writeAndDecode(png, path, file, one_row.width, one_row.height), one_row.pixels) << "filter " << type;
  }
}

TEST(GrayPngDecoder, ReadsWhatLibpngWroteByteForByte) {
  test::TempDir dir;
  GrayPngDecoder png;
  int n = 0;
  for (const GrayImage& image : {randomImage(40, 30, 11), smoothImage(752, 480), randomImage(1, 1, 3)}) {
    const auto path = dir.path() / ("w" + std::to_string(n++) + ".png");
    ASSERT_TRUE(writeGrayPng(path, image).ok());
    std::vector<std::uint8_t> pixels(image.pixels.size());
    auto decoded = png.decodeInto(path, image.width, image.height, pixels);
    ASSERT_TRUE(decoded.ok()) << decoded.error().toString();
    ASSERT_TRUE(*decoded);
    EXPECT_EQ(pixels, image.pixels);
  }
}

TEST(GrayPngDecoder, ReadsTheRealEurocImagesAsOpenCvDoes) {
  CVISLAM_REQUIRE_DATA(seq_path, "euroc-v101-excerpt");
  auto seq = EurocSequence::open(seq_path);
  ASSERT_TRUE(seq.ok()) << seq.error().toString();
  GrayPngDecoder png;
  for (int camera = 0; camera < seq->cameraCount(); ++camera) {
    const auto& cal = camera == 0 ? seq->cam0().calibration : seq->cam1()->calibration;
    const CameraStream& stream = camera == 0 ? seq->cam0() : *seq->cam1();
    std::vector<std::uint8_t> ours(static_cast<std::size_t>(cal.width) * static_cast<std::size_t>(cal.height));
    for (std::size_t frame = 0; frame < 10; ++frame) {
      ASSERT_TRUE(seq->loadImageInto(camera, frame, ours, png).ok());
      auto opencv = readImageAsGray(stream.imagePath(frame));
      ASSERT_TRUE(opencv.ok()) << opencv.error().toString();
      EXPECT_EQ(ours, opencv->pixels) << "camera " << camera << " frame " << frame;
      auto one_off = readGrayImage(stream.imagePath(frame));  // the loader without a kept decoder
      ASSERT_TRUE(one_off.ok()) << one_off.error().toString();
      EXPECT_EQ(one_off->pixels, opencv->pixels);
    }
  }
}

TEST(GrayPngDecoder, HandsOtherFormatsBackAndTheLoaderSaysWhatTheyAre) {
  test::TempDir dir;
  GrayPngDecoder png;
  cv::Mat deep(20, 30, CV_16UC1, cv::Scalar(1000));
  ASSERT_TRUE(cv::imwrite((dir.path() / "deep.png").string(), deep));
  cv::Mat colour(20, 30, CV_8UC3, cv::Scalar(10, 100, 200));
  ASSERT_TRUE(cv::imwrite((dir.path() / "colour.png").string(), colour));
  cv::Mat grey(20, 30, CV_8UC1, cv::Scalar(77));
  ASSERT_TRUE(cv::imwrite((dir.path() / "grey.jpg").string(), grey));
  std::vector<std::uint8_t> pixels(600);
  for (const char* name : {"deep.png", "colour.png", "grey.jpg"}) {
    auto decoded = png.decodeInto(dir.path() / name, 30, 20, pixels);
    ASSERT_TRUE(decoded.ok()) << name << ": " << decoded.error().toString();
    EXPECT_FALSE(*decoded) << name;
  }
  // The loader (no OpenCV) names the format and says how to convert it; both of its entry points.
  for (const auto& [name, what] : {std::pair{"grey.jpg", "a JPEG file"}, std::pair{"colour.png", "8-bit RGB"},
                                   std::pair{"deep.png", "16-bit grey"}}) {
    const Status into = readGrayImageInto(dir.path() / name, 30, 20, pixels, png);
    ASSERT_FALSE(into.ok()) << name;
    EXPECT_NE(into.error().message().find(what), std::string::npos) << into.error().message();
    EXPECT_NE(into.error().message().find("mogrify -format png"), std::string::npos) << into.error().message();
    auto whole = readGrayImage(dir.path() / name);
    ASSERT_FALSE(whole.ok()) << name;
    EXPECT_NE(whole.error().message().find(what), std::string::npos) << whole.error().message();
  }
  // OpenCV's reader, for the tools, reads them or names why not.
  auto jpeg = readImageAsGray(dir.path() / "grey.jpg");
  ASSERT_TRUE(jpeg.ok()) << jpeg.error().toString();
  EXPECT_NEAR(jpeg->pixels[0], 77, 2);
  ASSERT_TRUE(readImageAsGray(dir.path() / "colour.png").ok());
  auto deep_image = readImageAsGray(dir.path() / "deep.png");
  ASSERT_FALSE(deep_image.ok());
  EXPECT_NE(deep_image.error().message().find("16-bit"), std::string::npos) << deep_image.error().message();
}

TEST(GrayPngDecoder, NamesWhatIsWrongWithABrokenFileAndNeverReadsPastIt) {
  test::TempDir dir;
  GrayPngDecoder png;
  const GrayImage image = smoothImage(32, 24);
  const Bytes good = encodePng(image, [](int y) { return y % 5; });
  std::vector<std::uint8_t> pixels(image.pixels.size());
  const auto message = [&](const Bytes& bytes) {
    auto r = png.decodeInto(std::span<const std::uint8_t>(bytes), "x.png", 32, 24, pixels);
    return r.ok() ? std::string(*r ? "decoded" : "handed back") : r.error().message();
  };
  ASSERT_EQ(message(good), "decoded");

  auto missing = png.decodeInto(dir.path() / "none.png", 32, 24, pixels);
  ASSERT_FALSE(missing.ok());
  EXPECT_EQ(missing.error().code(), ErrorCode::kNotFound);
  writeBytes(dir.path() / "empty.png", {});
  auto empty = png.decodeInto(dir.path() / "empty.png", 32, 24, pixels);
  ASSERT_FALSE(empty.ok());
  EXPECT_NE(empty.error().message().find("empty"), std::string::npos);

  // Every truncation past the signature is an error, never a picture.
  for (std::size_t n = 8; n < good.size(); ++n) {
    const std::string m = message(Bytes(good.begin(), good.begin() + static_cast<std::ptrdiff_t>(n)));
    EXPECT_NE(m, "decoded") << n << " bytes";
    EXPECT_NE(m, "handed back") << n << " bytes";
  }
  EXPECT_NE(message(Bytes(good.begin(), good.end() - 12)).find("no end chunk"), std::string::npos);

  Bytes flipped = good;
  const std::size_t idat_data = good.size() - 12 - 4 - 10;  // inside the last IDAT's data
  flipped[idat_data] ^= 0x40;
  EXPECT_NE(message(flipped).find("IDAT fails its checksum"), std::string::npos) << message(flipped);

  const Bytes bad_filter = encodePng(image, [](int y) { return y == 5 ? 9 : 0; });
  EXPECT_NE(message(bad_filter).find("row 5 has an unknown filter type 9"), std::string::npos) << message(bad_filter);

  GrayImage taller(32, 25);
  EXPECT_NE(message(encodePng(taller, [](int) { return 0; })).find("32x25, the calibration says 32x24"),
            std::string::npos);

  // A header promising fewer rows than the data holds, with its checksum made right: the data is refused.
  GrayImage bigger(32, 30);
  Bytes more_data = encodePng(bigger, [](int) { return 0; });
  more_data[8 + 8 + 7] = 24;  // IHDR height's low byte: 30 -> 24
  const std::uint32_t crc = libdeflate_crc32(0, more_data.data() + 12, 17);
  for (int i = 0; i < 4; ++i)
    more_data[8 + 8 + 13 + static_cast<std::size_t>(i)] = static_cast<std::uint8_t>(crc >> (24 - 8 * i));
  EXPECT_NE(message(more_data).find("more than width x height"), std::string::npos) << message(more_data);

  Bytes huge_chunk = good;
  huge_chunk[33] = 0x7f;  // the chunk after IHDR claims ~2 GB
  EXPECT_NE(message(huge_chunk).find("runs past the file's end"), std::string::npos) << message(huge_chunk);
}

}  // namespace
}  // namespace cvislam::dataset
