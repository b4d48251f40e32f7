#include "common/features/orb.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <limits>
#include <span>
#include <string>
#include <vector>

#include "common/features/byte_vectors.hpp"
#include "common/features/fast_corners.hpp"
#include "common/features/pyramid_filters.hpp"

namespace cvislam::features {

namespace {

using detail::CornerScan;
using detail::F32x4;
using detail::I32x4;
using detail::keyLevel;
using detail::keyScore;
using detail::keyX;
using detail::keyY;
using detail::kMaxImageSide;

// ---------------------------------------------------------------------------------------------------------------
// Constants and the test pattern.

constexpr int kMaxLevels = 16;
constexpr int kPatchRadius = 15;  // orientation disc and descriptor test points

struct TestPair {
  std::int8_t x1 = 0;
  std::int8_t y1 = 0;
  std::int8_t x2 = 0;
  std::int8_t y2 = 0;
};

// SplitMix64: small, constexpr, and the same sequence everywhere (unlike std:: distributions).
class SplitMix64 {
 public:
  constexpr explicit SplitMix64(std::uint64_t seed) : state_(seed) {}
  constexpr std::uint64_t next() {
    state_ += 0x9E3779B97F4A7C15ULL;
    std::uint64_t z = state_;
    z = (z ^ (z >> 30U)) * 0xBF58476D1CE4E5B9ULL;
    z = (z ^ (z >> 27U)) * 0x94D049BB133111EBULL;
    return z ^ (z >> 31U);
  }
  // Uniform in [0, 1).
  constexpr double uniform() { return static_cast<double>(next() >> 11U) * 0x1.0p-53; }
  // Standard normal, approximately: the Irwin-Hall sum of 12 uniforms (constexpr, unlike Box-Muller).
  constexpr double normal() {
    double sum = 0.0;
    for (int i = 0; i < 12; ++i) sum += uniform();
    return sum - 6.0;
  }

 private:
  std::uint64_t state_;
};

// Rounds half away from zero (std::lround is not constexpr).
constexpr int roundToInt(double v) {
  const int whole = static_cast<int>(v);  // towards zero
  const double fraction = v - whole;
  return fraction >= 0.5 ? whole + 1 : fraction <= -0.5 ? whole - 1 : whole;
}

// BRIEF's sampling rule G II (Calonder et al., ECCV 2010): both points of a test drawn independently from an
// isotropic Gaussian of sigma S/5 for a patch of side S = 31, here kept inside the disc of radius 15 so that the
// points stay in the patch at any rotation. A test is drawn again when it is within 4 px (in the 4-D space of its
// two points, either way round) of one already chosen: such near-twins give strongly correlated bits. Without
// this, stereo matches on EuRoC V1_01 were 90.8 % inliers (mean over four seeds) instead of 91.8 %.
constexpr int kMinTestSeparation2 = 4 * 4;
std::array<TestPair, 256> makeTestPattern() {
  SplitMix64 rng(0x0DB1EF5EEDULL);
  constexpr double kSigma = 31.0 / 5.0;
  const auto draw = [&rng](int& x, int& y) {
    for (;;) {
      x = roundToInt(kSigma * rng.normal());
      y = roundToInt(kSigma * rng.normal());
      if (x * x + y * y <= kPatchRadius * kPatchRadius) return;
    }
  };
  // Each test gets at most kMaxRedraws redraws for nearness, so that the loop ends whatever the constants (with a
  // separation of 6 px it would not); with these, no test needs more than 24.
  constexpr int kMaxRedraws = 100000;
  int redraws = 0;
  std::array<TestPair, 256> pattern{};
  for (std::size_t i = 0; i < pattern.size();) {
    int x1 = 0;
    int y1 = 0;
    int x2 = 0;
    int y2 = 0;
    draw(x1, y1);
    draw(x2, y2);
    if (x1 == x2 && y1 == y2) continue;
    bool repeated = false;
    for (std::size_t j = 0; j < i && !repeated && redraws < kMaxRedraws; ++j) {
      const TestPair& p = pattern[j];
      const auto sq = [](int a) { return a * a; };
      repeated = sq(p.x1 - x1) + sq(p.y1 - y1) + sq(p.x2 - x2) + sq(p.y2 - y2) < kMinTestSeparation2 ||
                 sq(p.x1 - x2) + sq(p.y1 - y2) + sq(p.x2 - x1) + sq(p.y2 - y1) < kMinTestSeparation2;
    }
    if (repeated) {
      ++redraws;
      continue;
    }
    redraws = 0;
    pattern[i++] = {static_cast<std::int8_t>(x1), static_cast<std::int8_t>(y1), static_cast<std::int8_t>(x2),
                    static_cast<std::int8_t>(y2)};
  }
  return pattern;
}

// The pattern's points as floats, both points of test i at 2i and 2i + 1, for rotating four at a time. Computed
// once, at the first OrbExtractor::create (a static without heap storage); too long a computation for constexpr.
struct PatternPoints {
  std::array<float, 512> x{};
  std::array<float, 512> y{};
};
const PatternPoints& patternPoints() {
  static const PatternPoints points = [] {
    const std::array<TestPair, 256> pattern = makeTestPattern();
    PatternPoints p;
    for (std::size_t i = 0; i < pattern.size(); ++i) {
      p.x[2 * i] = pattern[i].x1;
      p.y[2 * i] = pattern[i].y1;
      p.x[2 * i + 1] = pattern[i].x2;
      p.y[2 * i + 1] = pattern[i].y2;
    }
    return p;
  }();
  return points;
}

// Half-width of the disc of radius 15 at each row offset: |dx| <= kDiscHalfWidth[|dy|].
constexpr std::array<int, kPatchRadius + 1> makeDiscHalfWidths() {
  std::array<int, kPatchRadius + 1> half{};
  for (int dy = 0; dy <= kPatchRadius; ++dy) {
    int dx = 0;
    while ((dx + 1) * (dx + 1) + dy * dy <= kPatchRadius * kPatchRadius) ++dx;
    half[static_cast<std::size_t>(dy)] = dx;
  }
  return half;
}
constexpr std::array<int, kPatchRadius + 1> kDiscHalfWidths = makeDiscHalfWidths();

struct LevelSize {
  int width = 0;
  int height = 0;
};

// Sizes of the pyramid levels of a width x height image.
void pyramidSizes(int width, int height, int levels, float scale_factor, std::array<LevelSize, kMaxLevels>& sizes) {
  double scale = 1.0;
  for (int l = 0; l < levels; ++l) {
    sizes[static_cast<std::size_t>(l)] = {std::max(1, static_cast<int>(std::lround(width / scale))),
                                          std::max(1, static_cast<int>(std::lround(height / scale)))};
    scale *= static_cast<double>(scale_factor);
  }
}

// Source index and 8-bit weight of the right/lower neighbour for bilinear sampling of pixel centres.
void bilinearTaps(int src_size, int dst_size, std::int32_t* index, std::int32_t* weight) {
  const double ratio = static_cast<double>(src_size) / static_cast<double>(dst_size);
  for (int d = 0; d < dst_size; ++d) {
    const double s = std::clamp((d + 0.5) * ratio - 0.5, 0.0, static_cast<double>(src_size - 1));
    int i = static_cast<int>(s);
    if (i >= src_size - 1) i = std::max(0, src_size - 2);
    index[d] = i;
    weight[d] = src_size < 2 ? 0 : std::clamp(static_cast<int>(std::lround((s - i) * 256.0)), 0, 256);
  }
}

}  // namespace

Status OrbOptions::validate() const {
  const auto bad = [](const std::string& what) { return Error{ErrorCode::kInvalidArgument, "ORB options: " + what}; };
  if (max_features < 1) return bad("max_features must be >= 1");
  if (grid_columns < 1 || grid_rows < 1 || grid_columns * grid_rows > 4096) {
    return bad("grid_columns x grid_rows must be between 1 and 4096 cells");
  }
  if (pyramid_levels < 1 || pyramid_levels > kMaxLevels) return bad("pyramid_levels must be 1 to 16");
  if (!(scale_factor > 1.0F) || scale_factor > 2.0F) return bad("scale_factor must be in (1, 2]");
  if (fast_threshold < 1 || fast_threshold > 254) return bad("fast_threshold must be 1 to 254");
  if (edge_threshold < kPatchRadius + 1) return bad("edge_threshold must be >= 16 (the descriptor patch)");
  if (candidates_per_feature < 1) return bad("candidates_per_feature must be >= 1");
  if (max_width < 1 || max_width > kMaxImageSide || max_height < 1 || max_height > kMaxImageSide) {
    return bad("max_width and max_height must be 1 to 4096");
  }
  if (static_cast<long long>(max_features) * candidates_per_feature > (1LL << 24)) {
    return bad("max_features x candidates_per_feature must be <= 2^24");
  }
  return Status::Ok();
}

struct OrbExtractor::Impl {
  OrbOptions options;
  int candidate_budget = 0;  // max_features x candidates_per_feature
  std::array<int, kMaxLevels> level_budget{};

  // Geometry of the current image size; recomputed (without allocating) when the size changes.
  int width = 0;
  int height = 0;
  std::array<LevelSize, kMaxLevels> size{};
  std::array<std::size_t, kMaxLevels> x_tap_offset{};  // into x_index / x_weight, per level (from level 1)
  std::vector<std::int32_t> x_index;
  std::vector<std::int32_t> x_weight;

  // Level images: level 0 is the caller's pixels; levels >= 1 live in `pyramid` (from level_offset[l] -
  // level_offset[1]), the smoothed levels in `smoothed` (from level_offset[l]). Both are laid out for the maximum
  // image size, every level with its width as row stride.
  std::array<std::size_t, kMaxLevels> level_offset{};
  std::vector<std::uint8_t> pyramid;
  std::vector<std::uint8_t> smoothed;
  std::array<const std::uint8_t*, kMaxLevels> image{};

  // Scratch rows.
  std::vector<std::uint16_t> blur_row;                  // a row blended or blurred vertically
  std::array<std::vector<std::uint8_t>, 3> score_rows;  // FAST scores of three consecutive rows
  bool wide_vectors = false;  // AVX2: 32-lane corners, 16-lane pyramid filters (wideVectorsAvailable)

  // Corners of the level being detected, then the candidates kept from all levels, then the selection.
  std::vector<std::uint64_t> level_corners;
  std::vector<std::uint64_t> candidates;
  std::vector<char> taken;
  std::vector<int> per_cell;
  std::vector<std::uint64_t> cell_best;  // strongest corner of each cell that its level's budget left out
  // Grid column of each pixel column and row of each pixel row, per level (from cell_x_offset / cell_y_offset): the
  // cell of a corner is two lookups, since every corner a level's budget leaves out is binned.
  std::array<std::size_t, kMaxLevels> cell_x_offset{};
  std::array<std::size_t, kMaxLevels> cell_y_offset{};
  std::vector<std::uint16_t> cell_x;
  std::vector<std::uint16_t> cell_y;
  std::vector<std::uint64_t> selected;
  std::array<int, kMaxLevels> selected_min_y{};
  std::array<int, kMaxLevels> selected_max_y{};

  [[nodiscard]] std::size_t cellOf(std::uint64_t key) const;
  void setImageSize(int w, int h);
  // The level's `found` corners (in level_corners): its `keep` strongest go to candidates from `candidate_count` on
  // (in no particular order); the others are binned into cell_best. Returns the new candidate count.
  std::size_t keepStrongest(int found, int keep, std::size_t candidate_count);
  void buildLevel(int level);
  int detectLevel(int level);  // FAST corners and their suppression
  void smoothRows(int level, int y_begin, int y_end);
  void describe(std::uint64_t key, Keypoint& keypoint, Descriptor& descriptor) const;
};

OrbExtractor::OrbExtractor(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
OrbExtractor::OrbExtractor(OrbExtractor&&) noexcept = default;
OrbExtractor& OrbExtractor::operator=(OrbExtractor&&) noexcept = default;
OrbExtractor::~OrbExtractor() = default;

const OrbOptions& OrbExtractor::options() const {
  return impl_->options;
}

int OrbExtractor::cornerLanes() const {
  return impl_->wide_vectors ? 32 : 16;
}

Status OrbExtractor::checkImageSize(int width, int height) const {
  const OrbOptions& o = impl_->options;
  if (width < 1 || height < 1 || width > o.max_width || height > o.max_height) {
    return Error{ErrorCode::kInvalidArgument, "ORB: image of " + std::to_string(width) + "x" + std::to_string(height) +
                                                  " px is outside 1x1 to " + std::to_string(o.max_width) + "x" +
                                                  std::to_string(o.max_height) + " (OrbOptions::max_width/height)"};
  }
  return Status::Ok();
}

Result<OrbExtractor> OrbExtractor::create(const OrbOptions& options) {
  if (Status status = options.validate(); !status.ok()) return status.error();
  (void)patternPoints();  // generated here rather than in the first extract
  auto impl = std::make_unique<Impl>();
  Impl& m = *impl;
  m.options = options;
  m.wide_vectors = detail::wideVectorsAvailable();
  const int levels = options.pyramid_levels;

  // Budget of candidates per level, in proportion to 1/scale_factor^level (ORB's share-out).
  m.candidate_budget = options.max_features * options.candidates_per_feature;
  {
    const double f = 1.0 / static_cast<double>(options.scale_factor);
    double share = m.candidate_budget * (1.0 - f) / (1.0 - std::pow(f, levels));
    int given = 0;
    for (int l = 0; l < levels - 1; ++l) {  // never more than the total, which sizes `candidates`
      m.level_budget[static_cast<std::size_t>(l)] =
          std::min(static_cast<int>(std::lround(share)), m.candidate_budget - given);
      given += m.level_budget[static_cast<std::size_t>(l)];
      share *= f;
    }
    m.level_budget[static_cast<std::size_t>(levels - 1)] = std::max(0, m.candidate_budget - given);
  }

  std::array<LevelSize, kMaxLevels> max_size{};
  pyramidSizes(options.max_width, options.max_height, levels, options.scale_factor, max_size);
  std::size_t pixels = 0;
  std::size_t taps = 0;
  std::size_t largest_corner_count = 0;
  for (int l = 0; l < levels; ++l) {
    const LevelSize s = max_size[static_cast<std::size_t>(l)];
    m.level_offset[static_cast<std::size_t>(l)] = pixels;
    pixels += static_cast<std::size_t>(s.width) * static_cast<std::size_t>(s.height);
    taps += static_cast<std::size_t>(s.width);
    // Non-maximum suppression leaves no two corners 8-adjacent: at most one per 2x2 block.
    largest_corner_count = std::max(largest_corner_count, static_cast<std::size_t>((s.width + 1) / 2) *
                                                              static_cast<std::size_t>((s.height + 1) / 2));
  }
  constexpr std::size_t kPad = 32;  // vector loads may run up to 16 bytes past a row's last pixel
  m.pyramid.resize(pixels - m.level_offset[std::min(1, levels - 1)] + kPad);  // level 0 is the caller's
  m.smoothed.resize(pixels + kPad);
  m.x_index.resize(taps);
  m.x_weight.resize(taps);
  const auto row = static_cast<std::size_t>(options.max_width) + kPad;
  m.blur_row.resize(row);
  for (auto& r : m.score_rows) r.resize(row);
  m.level_corners.resize(largest_corner_count);
  const std::size_t cells =
      static_cast<std::size_t>(options.grid_columns) * static_cast<std::size_t>(options.grid_rows);
  m.candidates.resize(static_cast<std::size_t>(m.candidate_budget) + cells);
  m.taken.resize(m.candidates.size());
  m.per_cell.resize(cells);
  m.cell_best.resize(cells);
  std::size_t columns = 0;
  std::size_t rows = 0;
  for (int l = 0; l < levels; ++l) {
    columns += static_cast<std::size_t>(max_size[static_cast<std::size_t>(l)].width);
    rows += static_cast<std::size_t>(max_size[static_cast<std::size_t>(l)].height);
  }
  m.cell_x.resize(columns);
  m.cell_y.resize(rows);
  m.selected.resize(static_cast<std::size_t>(options.max_features));
  return OrbExtractor(std::move(impl));
}

// Grid cell of a corner's level-0 position (its pixel centre scaled up), from the tables setImageSize fills.
std::size_t OrbExtractor::Impl::cellOf(std::uint64_t key) const {
  const auto L = static_cast<std::size_t>(keyLevel(key));
  const std::size_t cx = cell_x[cell_x_offset[L] + static_cast<std::size_t>(keyX(key))];
  const std::size_t cy = cell_y[cell_y_offset[L] + static_cast<std::size_t>(keyY(key))];
  return cy * static_cast<std::size_t>(options.grid_columns) + cx;
}

void OrbExtractor::Impl::setImageSize(int w, int h) {
  if (w == width && h == height) return;
  width = w;
  height = h;
  pyramidSizes(w, h, options.pyramid_levels, options.scale_factor, size);
  // A pixel's cell: its centre's share of the level's side, times the cells along it (the last cell closed).
  const auto cell = [](int pixel, int side, int cells) {
    const float share = (static_cast<float>(pixel) + 0.5F) / static_cast<float>(side);  // in [0, 1)
    return static_cast<std::uint16_t>(std::min(static_cast<int>(share * static_cast<float>(cells)), cells - 1));
  };
  std::size_t columns = 0;
  std::size_t rows = 0;
  for (int l = 0; l < options.pyramid_levels; ++l) {
    const auto L = static_cast<std::size_t>(l);
    cell_x_offset[L] = columns;
    cell_y_offset[L] = rows;
    for (int x = 0; x < size[L].width; ++x) cell_x[columns++] = cell(x, size[L].width, options.grid_columns);
    for (int y = 0; y < size[L].height; ++y) cell_y[rows++] = cell(y, size[L].height, options.grid_rows);
  }
  std::size_t taps = 0;
  for (int l = 1; l < options.pyramid_levels; ++l) {
    const auto L = static_cast<std::size_t>(l);
    x_tap_offset[L] = taps;
    bilinearTaps(size[L - 1].width, size[L].width, x_index.data() + taps, x_weight.data() + taps);
    taps += static_cast<std::size_t>(size[L].width);
  }
}

// Bilinear downsampling of the previous level: the two source rows are blended vertically, then the blended row is
// sampled horizontally (pyramid_filters.hpp).
void OrbExtractor::Impl::buildLevel(int level) {
  const auto L = static_cast<std::size_t>(level);
  const LevelSize src_size = size[L - 1];
  const LevelSize dst_size = size[L];
  const std::uint8_t* src = image[L - 1];
  std::uint8_t* dst = pyramid.data() + (level_offset[L] - level_offset[1]);
  image[L] = dst;
  const std::int32_t* xi = x_index.data() + x_tap_offset[L];
  const std::int32_t* xw = x_weight.data() + x_tap_offset[L];
  const int step = src_size.width > 1 ? 1 : 0;
  std::uint16_t* blended = blur_row.data();
  const double ratio = static_cast<double>(src_size.height) / static_cast<double>(dst_size.height);
  for (int y = 0; y < dst_size.height; ++y) {
    const double s = std::clamp((y + 0.5) * ratio - 0.5, 0.0, static_cast<double>(src_size.height - 1));
    int y0 = static_cast<int>(s);
    if (y0 >= src_size.height - 1) y0 = std::max(0, src_size.height - 2);
    const int y1 = std::min(y0 + 1, src_size.height - 1);
    const auto wy = static_cast<std::uint16_t>(
        src_size.height < 2 ? 0 : std::clamp(static_cast<int>(std::lround((s - y0) * 256.0)), 0, 256));
    const auto wy0 = static_cast<std::uint16_t>(256 - wy);
    const std::uint8_t* r0 = src + static_cast<std::ptrdiff_t>(y0) * src_size.width;
    const std::uint8_t* r1 = src + static_cast<std::ptrdiff_t>(y1) * src_size.width;
    if (wide_vectors) {
      detail::blendRowsWide(r0, r1, wy0, wy, src_size.width, blended);
    } else {
      detail::blendRowsNarrow(r0, r1, wy0, wy, src_size.width, blended);
    }
    std::uint8_t* d = dst + static_cast<std::ptrdiff_t>(y) * dst_size.width;
    if (wide_vectors) {
      detail::resampleRowWide(blended, xi, xw, step, dst_size.width, d);
    } else {
      detail::resampleRowNarrow(blended, xi, xw, step, dst_size.width, d);
    }
  }
}

// FAST-9 corners of one level with 3x3 non-maximum suppression, at least edge_threshold pixels from the border,
// into level_corners; returns their number.
int OrbExtractor::Impl::detectLevel(int level) {
  const auto L = static_cast<std::size_t>(level);
  CornerScan scan;
  scan.image = image[L];
  scan.width = size[L].width;
  scan.height = size[L].height;
  scan.edge = options.edge_threshold;
  scan.threshold = static_cast<std::uint8_t>(options.fast_threshold);
  scan.level = level;
  for (std::size_t r = 0; r < score_rows.size(); ++r) scan.score_rows[r] = score_rows[r].data();
  const std::span<std::uint64_t> corners(level_corners);
  if (wide_vectors && scan.width - 2 * scan.edge >= 32) return detail::detectCornersWide(scan, corners);
  return detail::detectCornersNarrow(scan, corners);
}

// Rows [y_begin, y_end) of the level smoothed by the separable 7-tap Gaussian; the border is replicated.
void OrbExtractor::Impl::smoothRows(int level, int y_begin, int y_end) {
  const auto L = static_cast<std::size_t>(level);
  std::uint8_t* out = smoothed.data() + level_offset[L];
  if (wide_vectors) {
    detail::blurRowsWide(image[L], size[L].width, size[L].height, y_begin, y_end, out, blur_row.data());
  } else {
    detail::blurRowsNarrow(image[L], size[L].width, size[L].height, y_begin, y_end, out, blur_row.data());
  }
}

std::size_t OrbExtractor::Impl::keepStrongest(int found, int keep, std::size_t candidate_count) {
  const auto bin = [this](std::uint64_t key) {
    std::uint64_t& best = cell_best[cellOf(key)];
    best = std::max(best, key);
  };
  const auto n = static_cast<std::size_t>(found);
  if (keep >= found) {
    std::copy_n(level_corners.begin(), n, candidates.begin() + static_cast<std::ptrdiff_t>(candidate_count));
    return candidate_count + n;
  }
  // Keys order by score first (their top byte), and a level has thousands of corners for a budget of a few hundred:
  // the score at the cut comes from a histogram, every corner above it is kept, and only the corners at the cut
  // score are ordered (by the rest of their key) to fill the budget. The same corners as ordering them all.
  std::array<int, 256> per_score{};
  for (std::size_t i = 0; i < n; ++i) ++per_score[static_cast<std::size_t>(keyScore(level_corners[i]))];
  int cut = 255;
  int above = 0;  // corners scoring more than `cut`
  while (above + per_score[static_cast<std::size_t>(cut)] < keep) above += per_score[static_cast<std::size_t>(cut--)];
  std::size_t at_cut = 0;  // moved to the front of level_corners
  for (std::size_t i = 0; i < n; ++i) {
    const std::uint64_t key = level_corners[i];
    const int score = keyScore(key);
    if (score > cut) {
      candidates[candidate_count++] = key;
    } else if (score == cut) {
      level_corners[at_cut++] = key;
    } else {
      bin(key);
    }
  }
  const auto wanted = static_cast<std::size_t>(keep - above);
  const auto first = level_corners.begin();
  std::nth_element(first, first + static_cast<std::ptrdiff_t>(wanted), first + static_cast<std::ptrdiff_t>(at_cut),
                   std::greater<>());
  std::copy_n(first, wanted, candidates.begin() + static_cast<std::ptrdiff_t>(candidate_count));
  for (std::size_t i = wanted; i < at_cut; ++i) bin(level_corners[i]);
  return candidate_count + wanted;
}

// Orientation (intensity centroid) and steered BRIEF of one selected corner.
void OrbExtractor::Impl::describe(std::uint64_t key, Keypoint& keypoint, Descriptor& descriptor) const {
  const int level = keyLevel(key);
  const auto L = static_cast<std::size_t>(level);
  const int x = keyX(key);
  const int y = keyY(key);
  const int w = size[L].width;
  const std::uint8_t* centre = image[L] + static_cast<std::ptrdiff_t>(y) * w + x;
  int m10 = 0;
  int m01 = 0;
  for (int dy = -kPatchRadius; dy <= kPatchRadius; ++dy) {
    const int half = kDiscHalfWidths[static_cast<std::size_t>(std::abs(dy))];
    const std::uint8_t* r = centre + static_cast<std::ptrdiff_t>(dy) * w;
    int sum = 0;
    int weighted = 0;
    for (int dx = -half; dx <= half; ++dx) {
      sum += r[dx];
      weighted += dx * r[dx];
    }
    m10 += weighted;
    m01 += dy * sum;
  }
  const float norm = std::hypot(static_cast<float>(m10), static_cast<float>(m01));
  float c = 1.0F;
  float s = 0.0F;
  float angle = 0.0F;
  if (norm > 0.0F) {
    c = static_cast<float>(m10) / norm;
    s = static_cast<float>(m01) / norm;
    angle = std::atan2(static_cast<float>(m01), static_cast<float>(m10)) * (180.0F / 3.14159265358979F);
    if (angle < 0.0F) angle += 360.0F;
    if (angle >= 360.0F) angle = 0.0F;
  }

  const std::uint8_t* blurred = smoothed.data() + level_offset[L] + static_cast<std::ptrdiff_t>(y) * w + x;
  // Offsets of the rotated test points, rounded half away from zero, four at a time.
  std::array<std::int32_t, 512> offsets;  // NOLINT(cppcoreguidelines-pro-type-member-init): filled below
  const PatternPoints& pattern = patternPoints();
  const F32x4 cos4 = F32x4{} + c;
  const F32x4 sin4 = F32x4{} + s;
  const F32x4 half4 = F32x4{} + 0.5F;
  const I32x4 stride4 = I32x4{} + w;
  for (std::size_t i = 0; i < offsets.size(); i += 4) {
    F32x4 px;
    F32x4 py;
    std::memcpy(&px, pattern.x.data() + i, sizeof(px));
    std::memcpy(&py, pattern.y.data() + i, sizeof(py));
    const F32x4 rx = cos4 * px - sin4 * py;
    const F32x4 ry = sin4 * px + cos4 * py;
    const I32x4 ix = __builtin_convertvector(rx + (rx >= 0.0F ? half4 : -half4), I32x4);  // truncates
    const I32x4 iy = __builtin_convertvector(ry + (ry >= 0.0F ? half4 : -half4), I32x4);
    const I32x4 offset = iy * stride4 + ix;
    std::memcpy(offsets.data() + i, &offset, sizeof(offset));
  }
  for (std::size_t byte = 0; byte < descriptor.size(); ++byte) {
    unsigned bits = 0;
    const std::int32_t* o = offsets.data() + byte * 16;
    for (std::size_t bit = 0; bit < 8; ++bit) {
      bits |= (blurred[o[2 * bit]] < blurred[o[2 * bit + 1]] ? 1U : 0U) << bit;
    }
    descriptor[byte] = static_cast<std::uint8_t>(bits);
  }

  // Level-0 position of the pixel centre.
  const float sx = static_cast<float>(width) / static_cast<float>(w);
  const float sy = static_cast<float>(height) / static_cast<float>(size[L].height);
  keypoint.px = Eigen::Vector2f((static_cast<float>(x) + 0.5F) * sx - 0.5F, (static_cast<float>(y) + 0.5F) * sy - 0.5F);
  keypoint.response = static_cast<float>(keyScore(key));
  keypoint.angle_deg = angle;
  keypoint.octave = static_cast<std::uint8_t>(level);
}

int OrbExtractor::extract(std::span<const std::uint8_t> pixels, int width, int height, std::span<Keypoint> keypoints,
                          std::span<Descriptor> descriptors) {
  Impl& m = *impl_;
  const OrbOptions& o = m.options;
  // checkImageSize's test, without building its message (which would allocate).
  if (width < 1 || height < 1 || width > o.max_width || height > o.max_height) return 0;
  if (pixels.size() < static_cast<std::size_t>(width) * static_cast<std::size_t>(height)) return 0;
  m.setImageSize(width, height);

  // Pyramid and corners, level by level; each level keeps its strongest corners up to its budget, and each grid
  // cell remembers the strongest corner left out.
  m.image[0] = pixels.data();
  std::fill(m.cell_best.begin(), m.cell_best.end(), 0);
  std::size_t candidate_count = 0;
  for (int l = 0; l < o.pyramid_levels; ++l) {
    if (l > 0) m.buildLevel(l);
    const int found = m.detectLevel(l);
    candidate_count =
        m.keepStrongest(found, std::min(found, m.level_budget[static_cast<std::size_t>(l)]), candidate_count);
  }
  // A cell without candidates (the budgets go to the strongest corners, which texture-rich regions have) gets
  // the strongest corner it has, so that the grid can cover dark and weakly textured regions too; only one per
  // cell, since weak corners match worse.
  std::fill(m.per_cell.begin(), m.per_cell.end(), 0);
  for (std::size_t i = 0; i < candidate_count; ++i) ++m.per_cell[m.cellOf(m.candidates[i])];
  for (std::size_t c = 0; c < m.cell_best.size(); ++c) {
    if (m.per_cell[c] == 0 && m.cell_best[c] != 0) m.candidates[candidate_count++] = m.cell_best[c];
  }
  const auto candidates_end = m.candidates.begin() + static_cast<std::ptrdiff_t>(candidate_count);
  std::sort(m.candidates.begin(), candidates_end, std::greater<>());

  // Grid selection: the strongest corners of each cell up to an equal quota, then the strongest of the rest.
  const int cells = o.grid_columns * o.grid_rows;
  const int quota = std::max(1, o.max_features / cells);
  std::fill(m.per_cell.begin(), m.per_cell.end(), 0);
  std::fill(m.taken.begin(), m.taken.begin() + static_cast<std::ptrdiff_t>(candidate_count), 0);
  const int wanted = std::min<int>(o.max_features, static_cast<int>(std::min(keypoints.size(), descriptors.size())));
  int n = 0;
  for (std::size_t i = 0; i < candidate_count && n < wanted; ++i) {
    const std::uint64_t key = m.candidates[i];
    int& count = m.per_cell[m.cellOf(key)];
    if (count < quota) {
      ++count;
      m.taken[i] = 1;
      m.selected[static_cast<std::size_t>(n++)] = key;
    }
  }
  for (std::size_t i = 0; i < candidate_count && n < wanted; ++i) {
    if (m.taken[i] == 0) m.selected[static_cast<std::size_t>(n++)] = m.candidates[i];
  }
  // Strongest first, whichever pass selected them.
  std::sort(m.selected.begin(), m.selected.begin() + n, std::greater<>());

  // Smooth only the rows of each level that selected corners' patches reach, then describe.
  m.selected_min_y.fill(std::numeric_limits<int>::max());
  m.selected_max_y.fill(-1);
  for (int i = 0; i < n; ++i) {
    const std::uint64_t key = m.selected[static_cast<std::size_t>(i)];
    const auto L = static_cast<std::size_t>(keyLevel(key));
    m.selected_min_y[L] = std::min(m.selected_min_y[L], keyY(key));
    m.selected_max_y[L] = std::max(m.selected_max_y[L], keyY(key));
  }
  for (int l = 0; l < o.pyramid_levels; ++l) {
    const auto L = static_cast<std::size_t>(l);
    if (m.selected_max_y[L] < 0) continue;
    m.smoothRows(l, m.selected_min_y[L] - kPatchRadius, m.selected_max_y[L] + kPatchRadius + 1);
  }
  for (int i = 0; i < n; ++i) {
    m.describe(m.selected[static_cast<std::size_t>(i)], keypoints[static_cast<std::size_t>(i)],
               descriptors[static_cast<std::size_t>(i)]);
  }
  return n;
}

}  // namespace cvislam::features
