#include "common/features/orb.hpp"

#include <algorithm>
#include <bit>
#include <cstring>
#include <limits>
#include <string>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/features2d.hpp>

namespace cvislam::features {

Status OrbOptions::validate() const {
  const auto bad = [](const std::string& what) { return Error{ErrorCode::kInvalidArgument, "ORB options: " + what}; };
  if (max_features < 1) return bad("max_features must be >= 1");
  if (grid_columns < 1 || grid_rows < 1 || grid_columns * grid_rows > 4096) {
    return bad("grid_columns x grid_rows must be between 1 and 4096 cells");
  }
  if (pyramid_levels < 1 || pyramid_levels > 16) return bad("pyramid_levels must be 1 to 16");
  if (!(scale_factor > 1.0F) || scale_factor > 2.0F) return bad("scale_factor must be in (1, 2]");
  if (fast_threshold < 1 || fast_threshold > 255) return bad("fast_threshold must be 1 to 255");
  if (edge_threshold < 16) return bad("edge_threshold must be >= 16 (the descriptor patch)");
  if (candidates_per_feature < 1) return bad("candidates_per_feature must be >= 1");
  return Status::Ok();
}

struct OrbExtractor::Impl {
  OrbOptions options;
  cv::Ptr<cv::ORB> orb;
  std::vector<cv::KeyPoint> candidates;
  std::vector<cv::KeyPoint> selected;
  std::vector<char> taken;
  std::vector<int> per_cell;
  cv::Mat descriptors;
};

OrbExtractor::OrbExtractor(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
OrbExtractor::OrbExtractor(OrbExtractor&&) noexcept = default;
OrbExtractor& OrbExtractor::operator=(OrbExtractor&&) noexcept = default;
OrbExtractor::~OrbExtractor() = default;

const OrbOptions& OrbExtractor::options() const {
  return impl_->options;
}

Result<OrbExtractor> OrbExtractor::create(const OrbOptions& options) {
  if (Status status = options.validate(); !status.ok()) return status.error();
  auto impl = std::make_unique<Impl>();
  impl->options = options;
  const int candidates = options.max_features * options.candidates_per_feature;
  impl->orb = cv::ORB::create(candidates, options.scale_factor, options.pyramid_levels, options.edge_threshold, 0, 2,
                              cv::ORB::FAST_SCORE, 31, options.fast_threshold);
  // Sized once; OpenCV's own buffers are outside our control (see the header).
  impl->candidates.reserve(static_cast<std::size_t>(candidates));
  impl->selected.reserve(static_cast<std::size_t>(options.max_features));
  impl->taken.reserve(static_cast<std::size_t>(candidates));
  impl->per_cell.resize(static_cast<std::size_t>(options.grid_columns) * static_cast<std::size_t>(options.grid_rows));
  return OrbExtractor(std::move(impl));
}

int OrbExtractor::extract(std::span<const std::uint8_t> pixels, int width, int height, std::span<Keypoint> keypoints,
                          std::span<Descriptor> descriptors) {
  Impl& m = *impl_;
  const OrbOptions& o = m.options;
  if (width <= 0 || height <= 0 || pixels.size() < static_cast<std::size_t>(width) * static_cast<std::size_t>(height)) {
    return 0;
  }
  // A view of the caller's pixels; OpenCV only reads it.
  const cv::Mat view(height, width, CV_8UC1, const_cast<std::uint8_t*>(pixels.data()));  // NOLINT: read-only use
  m.candidates.clear();
  m.orb->detect(view, m.candidates);
  std::sort(m.candidates.begin(), m.candidates.end(),
            [](const cv::KeyPoint& a, const cv::KeyPoint& b) { return a.response > b.response; });

  // Grid selection: the strongest corners of each cell up to an equal quota, then the strongest of the rest.
  const int cells = o.grid_columns * o.grid_rows;
  const int quota = std::max(1, o.max_features / cells);
  std::fill(m.per_cell.begin(), m.per_cell.end(), 0);
  m.taken.assign(m.candidates.size(), 0);
  m.selected.clear();
  const int wanted = std::min<int>(o.max_features, static_cast<int>(std::min(keypoints.size(), descriptors.size())));
  for (std::size_t i = 0; i < m.candidates.size() && static_cast<int>(m.selected.size()) < wanted; ++i) {
    const cv::Point2f& p = m.candidates[i].pt;
    const int cx = std::clamp(static_cast<int>(p.x * static_cast<float>(o.grid_columns) / static_cast<float>(width)), 0,
                              o.grid_columns - 1);
    const int cy = std::clamp(static_cast<int>(p.y * static_cast<float>(o.grid_rows) / static_cast<float>(height)), 0,
                              o.grid_rows - 1);
    int& count = m.per_cell[static_cast<std::size_t>(cy) * static_cast<std::size_t>(o.grid_columns) +
                            static_cast<std::size_t>(cx)];
    if (count < quota) {
      ++count;
      m.taken[i] = 1;
      m.selected.push_back(m.candidates[i]);
    }
  }
  for (std::size_t i = 0; i < m.candidates.size() && static_cast<int>(m.selected.size()) < wanted; ++i) {
    if (m.taken[i] == 0) m.selected.push_back(m.candidates[i]);
  }

  m.orb->compute(view, m.selected, m.descriptors);  // may drop keypoints whose patch leaves the image
  const int n = std::min(static_cast<int>(m.selected.size()), m.descriptors.rows);
  for (int i = 0; i < n; ++i) {
    const cv::KeyPoint& k = m.selected[static_cast<std::size_t>(i)];
    Keypoint& out = keypoints[static_cast<std::size_t>(i)];
    out.px = Eigen::Vector2f(k.pt.x, k.pt.y);
    out.response = k.response;
    out.angle_deg = k.angle;
    out.octave = static_cast<std::uint8_t>(k.octave);
    std::memcpy(descriptors[static_cast<std::size_t>(i)].data(), m.descriptors.ptr(i), sizeof(Descriptor));
  }
  return n;
}

int hammingDistance(const Descriptor& a, const Descriptor& b) {
  int bits = 0;
  for (std::size_t i = 0; i < a.size(); i += 8) {
    std::uint64_t x = 0;
    std::uint64_t y = 0;
    std::memcpy(&x, a.data() + i, 8);
    std::memcpy(&y, b.data() + i, 8);
    bits += std::popcount(x ^ y);
  }
  return bits;
}

int matchDescriptors(std::span<const Descriptor> query, std::span<const Descriptor> train, const MatchOptions& options,
                     std::span<DescriptorMatch> matches) {
  int count = 0;
  for (std::size_t q = 0; q < query.size() && static_cast<std::size_t>(count) < matches.size(); ++q) {
    int best = std::numeric_limits<int>::max();
    int second = std::numeric_limits<int>::max();
    std::size_t best_train = 0;
    for (std::size_t t = 0; t < train.size(); ++t) {
      const int d = hammingDistance(query[q], train[t]);
      if (d < best) {
        second = best;
        best = d;
        best_train = t;
      } else if (d < second) {
        second = d;
      }
    }
    if (best > options.max_distance) continue;
    if (second != std::numeric_limits<int>::max() &&
        static_cast<float>(best) > options.ratio * static_cast<float>(second)) {
      continue;
    }
    if (options.mutual) {
      bool is_mutual = true;
      for (std::size_t other = 0; other < query.size() && is_mutual; ++other) {
        if (other != q && hammingDistance(query[other], train[best_train]) < best) is_mutual = false;
      }
      if (!is_mutual) continue;
    }
    matches[static_cast<std::size_t>(count++)] = {static_cast<int>(q), static_cast<int>(best_train), best};
  }
  return count;
}

}  // namespace cvislam::features
