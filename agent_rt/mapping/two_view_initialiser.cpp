#include "agent_rt/mapping/two_view_initialiser.hpp"

#include <algorithm>
#include <cmath>
#include <string>

#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>

#include "common/geometry/triangulation.hpp"

namespace cvislam::agent {

Result<TwoViewResult> initialiseTwoView(std::span<const Eigen::Vector3d> bearings0,
                                        std::span<const Eigen::Vector3d> bearings1, const TwoViewOptions& options) {
  if (bearings0.size() != bearings1.size()) {
    return Error{ErrorCode::kInvalidArgument, "two-view initialisation: bearing lists differ in length"};
  }
  if (static_cast<int>(bearings0.size()) < options.min_inliers) {
    return Error{ErrorCode::kDegenerate, "two-view initialisation: " + std::to_string(bearings0.size()) +
                                             " matches, fewer than " + std::to_string(options.min_inliers)};
  }
  std::vector<cv::Point2d> x0;
  std::vector<cv::Point2d> x1;
  std::vector<std::size_t> index;
  for (std::size_t i = 0; i < bearings0.size(); ++i) {
    if (bearings0[i].z() <= 1e-6 || bearings1[i].z() <= 1e-6) continue;
    x0.emplace_back(bearings0[i].x() / bearings0[i].z(), bearings0[i].y() / bearings0[i].z());
    x1.emplace_back(bearings1[i].x() / bearings1[i].z(), bearings1[i].y() / bearings1[i].z());
    index.push_back(i);
  }
  cv::Mat mask;
  const cv::Mat E = cv::findEssentialMat(x0, x1, cv::Mat::eye(3, 3, CV_64F), cv::RANSAC, options.confidence,
                                         options.ransac_threshold_px / options.focal_px, mask);
  if (E.rows != 3 || E.cols != 3) {
    return Error{ErrorCode::kDegenerate, "two-view initialisation: no essential matrix found"};
  }
  cv::Mat R;
  cv::Mat t;
  // recoverPose picks the decomposition of E that puts the most points in front of both cameras, counting only
  // points nearer than 50 baselines (a parallax above about 1.1 deg): farther ones are in front under every
  // decomposition within their noise, and counting them picks a wrong one with a short baseline. But it also
  // drops them from its mask, which would leave the median parallax test below only points that pass it: the
  // points kept are the essential matrix's inliers that the checks below pass.
  const cv::Mat essential_inliers = mask.clone();
  cv::recoverPose(E, x0, x1, cv::Mat::eye(3, 3, CV_64F), R, t, mask);
  mask = essential_inliers;
  Eigen::Matrix3d R_c1_c0;
  Eigen::Vector3d t_c1_c0;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) R_c1_c0(r, c) = R.at<double>(r, c);
    t_c1_c0(r) = t.at<double>(r);
  }
  const geometry::SE3d T_c1_c0(Eigen::Quaterniond(R_c1_c0).normalized(), t_c1_c0.normalized());
  TwoViewResult result;
  result.T_c0_c1 = T_c1_c0.inverse();
  result.inlier.assign(bearings0.size(), 0);
  result.p_c0.assign(bearings0.size(), Eigen::Vector3d::Zero());
  std::vector<double> parallax;
  const Eigen::Vector3d c1_c0 = result.T_c0_c1.translation();
  for (std::size_t j = 0; j < index.size(); ++j) {
    if (mask.at<std::uint8_t>(static_cast<int>(j)) == 0) continue;
    const std::size_t i = index[j];
    auto p = geometry::triangulateMidpoint(geometry::SE3d(), bearings0[i].normalized(), result.T_c0_c1,
                                           bearings1[i].normalized());
    if (!p) continue;
    const double angle = geometry::parallaxAngle(*p, Eigen::Vector3d::Zero(), c1_c0);
    // Both rays must agree with the point to within about two pixels.
    const Eigen::Vector3d p_c1 = T_c1_c0 * *p;
    const double tolerance = 2.0 / options.focal_px;
    if (p->z() <= 0.0 || p_c1.z() <= 0.0) continue;
    if (geometry::rayAngle(*p, bearings0[i]) > tolerance || geometry::rayAngle(p_c1, bearings1[i]) > tolerance)
      continue;
    parallax.push_back(angle);
    if (angle < 0.5 * options.min_median_parallax_deg * M_PI / 180.0) continue;  // too far to place
    result.inlier[i] = 1;
    result.p_c0[i] = *p;
    ++result.inliers;
  }
  if (parallax.empty()) return Error{ErrorCode::kDegenerate, "two-view initialisation: no point triangulated"};
  std::nth_element(parallax.begin(), parallax.begin() + static_cast<std::ptrdiff_t>(parallax.size() / 2),
                   parallax.end());
  result.median_parallax_deg = parallax[parallax.size() / 2] * 180.0 / M_PI;
  if (result.median_parallax_deg < options.min_median_parallax_deg) {
    return Error{ErrorCode::kDegenerate, "two-view initialisation: median parallax " +
                                             std::to_string(result.median_parallax_deg) + " deg, below " +
                                             std::to_string(options.min_median_parallax_deg)};
  }
  if (result.inliers < options.min_inliers) {
    return Error{ErrorCode::kDegenerate, "two-view initialisation: " + std::to_string(result.inliers) +
                                             " good points, fewer than " + std::to_string(options.min_inliers)};
  }
  return result;
}

}  // namespace cvislam::agent
