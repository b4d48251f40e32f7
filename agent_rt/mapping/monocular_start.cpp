#include "agent_rt/mapping/monocular_start.hpp"

#include <algorithm>
#include <cmath>
#include <numeric>
#include <optional>
#include <string>
#include <vector>

#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>

#include "agent_rt/mapping/two_view_initialiser.hpp"
#include "common/features/best_two.hpp"

namespace cvislam::agent {

namespace {

using Eigen::Vector2d;
using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;

using MonocularStart = Mapper::State::MonocularStart;

// The pose of a keyframe between the two views is found from at least this many of the map's points.
constexpr int kMinRegisteredPoints = 20;

// A reference's tracks: its own keypoints, each found at itself.
std::vector<std::int32_t> ownKeypoints(std::size_t count) {
  std::vector<std::int32_t> own(count);
  std::iota(own.begin(), own.end(), 0);
  return own;
}

// The reference is this keyframe from now on; the keyframes before it go (they carry no points).
void startOver(Mapper::State& s, PoolHandle handle) {
  std::vector<PoolHandle> others;
  s.map.keyframes().forEach([&](PoolHandle h, const KeyframeData&) {
    if (!(h == handle)) others.push_back(h);
  });
  for (PoolHandle h : others) (void)s.map.removeKeyframe(h);
  MonocularStart& start = s.mono_start;
  start.clear();
  start.views.push_back(handle);
  start.R_c_c0.emplace_back();
  const KeyframeData& kf = *s.map.keyframes().get(handle);
  start.followed.push_back(ownKeypoints(kf.keypoint_count));
}

// The start's `count` oldest views go, with their keyframes.
void dropOldestViews(Mapper::State& s, std::size_t count) {
  MonocularStart& start = s.mono_start;
  for (std::size_t v = 0; v < count; ++v) (void)s.map.removeKeyframe(start.views[v]);
  const auto drop = [&](auto& v) { v.erase(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(count)); };
  drop(start.views);
  drop(start.followed);
  drop(start.R_c_c0);
  start.reference -= std::min(start.reference, count);
}

// The newest view, which follow() has just appended, is the reference from now on: its keypoints are the tracks.
// The views before it keep the tracks they share with it (the old reference's keypoints found in both), so that
// once the map starts they can be placed on its points, and their IMU links stay in the chain the IMU
// initialisation aligns: a start that lost sight of its reference would otherwise also lose the motion seen so
// far. A view sharing fewer than kMinRegisteredPoints could not be placed; it goes, with every view before it.
// Returns how many views were kept before the new reference.
std::size_t startOverKeepingShared(Mapper::State& s) {
  MonocularStart& start = s.mono_start;
  const std::size_t newest = start.views.size() - 1;
  const std::vector<std::int32_t> in_newest = start.followed[newest];  // old track -> the newest view's keypoint
  const std::size_t tracks = s.map.keyframes().get(start.views[newest])->keypoint_count;
  std::size_t first_kept = newest;
  for (std::size_t v = newest; v-- > 0;) {
    std::vector<std::int32_t> shared(tracks, -1);
    int count = 0;
    for (std::size_t track = 0; track < in_newest.size(); ++track) {
      if (in_newest[track] < 0 || start.followed[v][track] < 0) continue;
      shared[static_cast<std::size_t>(in_newest[track])] = start.followed[v][track];
      ++count;
    }
    if (count < kMinRegisteredPoints) break;
    start.followed[v] = std::move(shared);
    first_kept = v;
  }
  start.followed[newest] = ownKeypoints(tracks);
  dropOldestViews(s, first_kept);
  start.reference = start.views.size() - 1;
  return start.reference;
}

// The camera's rotation from `previous` to `kf` by the gyro, when kf's IMU link starts at `previous` (identity
// otherwise: the search window then has to hold the rotation). Before the IMU initialisation the link is
// integrated at the bias tracking assumed, which the window absorbs.
SO3d gyroRotation(const Mapper::State& s, const KeyframeData& previous, const KeyframeData& kf) {
  if (!kf.has_preintegration || kf.preintegration_incomplete || !(kf.preintegration_from == previous.id)) return {};
  const SO3d R_s_c = s.T_s_c.so3();
  return (R_s_c.inverse() * kf.preintegration.deltaR() * R_s_c).inverse();  // R_c1_c0
}

// The newest view before `views` (the count so far) in which the track was found: its index, or -1 when it was
// not found in any of the last kMaxUnseenViews.
constexpr std::size_t kMaxUnseenViews = 3;
int lastSeen(const MonocularStart& start, std::size_t views, std::size_t track) {
  for (std::size_t back = 1; back <= std::min(kMaxUnseenViews, views); ++back) {
    if (start.followed[views - back][track] >= 0) return static_cast<int>(views - back);
  }
  return -1;
}

// Where each of the reference's keypoints is in `handle`'s keyframe: searched for from the newest view that found
// it (a corner is not detected again in every image), in a window around its position there turned by the gyro's
// rotation since. The nearest descriptor at a neighbouring pyramid level, clear of the second nearest (Lowe's
// test), and no keypoint taken by two. Appends the view; returns how many it found.
int follow(Mapper::State& s, PoolHandle handle) {
  MonocularStart& start = s.mono_start;
  const std::size_t views = start.views.size();
  const KeyframeData& kf = *s.map.keyframes().get(handle);
  const SO3d R_c_c0 = gyroRotation(s, *s.map.keyframes().get(start.views.back()), kf) * start.R_c_c0.back();
  s.grid.build(std::span(kf.keypoints.data(), kf.keypoint_count), s.left.width(), s.left.height());
  const std::size_t tracks = start.followed.front().size();
  std::vector<std::int32_t> next(tracks, -1);
  std::vector<std::int32_t> owner(kf.keypoint_count, -1);
  std::vector<int> owner_distance(kf.keypoint_count, 0);
  const int max_distance = s.options.mono_init_max_distance;
  for (std::size_t track = 0; track < tracks; ++track) {
    const int seen = lastSeen(start, views, track);
    if (seen < 0) continue;
    const KeyframeData& there = *s.map.keyframes().get(start.views[static_cast<std::size_t>(seen)]);
    const auto k0 = static_cast<std::size_t>(start.followed[static_cast<std::size_t>(seen)][track]);
    const features::Keypoint& from = there.keypoints[k0];
    const SO3d R_c1_cseen = R_c_c0 * start.R_c_c0[static_cast<std::size_t>(seen)].inverse();
    Vector2d predicted = from.px.cast<double>();
    if (auto px = s.left.project(R_c1_cseen * s.left.unproject(predicted))) predicted = *px;
    features::BestTwo<int> nearest(max_distance + 1, -1);
    s.grid.forEachWithin(predicted, s.options.mono_init_search_radius_px, [&](int k) {
      if (std::abs(static_cast<int>(kf.keypoints[static_cast<std::size_t>(k)].octave) - from.octave) > 1) return;
      nearest.offer(features::hammingDistance(there.descriptors[k0], kf.descriptors[static_cast<std::size_t>(k)]), k);
    });
    if (nearest.candidate < 0) continue;
    if (nearest.hasSecond() && static_cast<double>(nearest.best) > s.options.mono_init_ratio * nearest.second) continue;
    const auto k1 = static_cast<std::size_t>(nearest.candidate);
    if (owner[k1] >= 0) {
      if (owner_distance[k1] <= nearest.best) continue;
      next[static_cast<std::size_t>(owner[k1])] = -1;
    }
    owner[k1] = static_cast<std::int32_t>(track);
    owner_distance[k1] = nearest.best;
    next[track] = nearest.candidate;
  }
  start.views.push_back(handle);
  start.R_c_c0.push_back(R_c_c0);
  start.followed.push_back(std::move(next));
  const std::vector<std::int32_t>& found = start.followed.back();
  return static_cast<int>(std::count_if(found.begin(), found.end(), [](std::int32_t k) { return k >= 0; }));
}

// A keyframe between the two views placed on the new map's points (PnP with RANSAC), its inlier keypoints made
// observations. False, with nothing changed, when too few points agree.
bool registerView(Mapper::State& s, PoolHandle handle, const std::vector<std::int32_t>& followed,
                  const std::vector<std::optional<PoolHandle>>& point_of_track,
                  const std::vector<Vector3d>& p_c0_of_track, const SE3d& T_w_c0) {
  const KeyframeData& kf = *s.map.keyframes().get(handle);
  std::vector<cv::Point3d> object;
  std::vector<cv::Point2d> image;
  std::vector<std::size_t> track_of;
  for (std::size_t track = 0; track < followed.size(); ++track) {
    if (followed[track] < 0 || !point_of_track[track]) continue;
    const Vector3d b = s.left.unproject(kf.keypoints[static_cast<std::size_t>(followed[track])].px.cast<double>());
    if (b.z() <= 1e-6) continue;
    const Vector3d& p = p_c0_of_track[track];
    object.emplace_back(p.x(), p.y(), p.z());
    image.emplace_back(b.x() / b.z(), b.y() / b.z());
    track_of.push_back(track);
  }
  if (static_cast<int>(object.size()) < kMinRegisteredPoints) return false;
  cv::Mat rvec;
  cv::Mat tvec;
  std::vector<int> inliers;
  const double threshold = 2.0 / s.left.calibration().fx;
  try {
    if (!cv::solvePnPRansac(object, image, cv::Mat::eye(3, 3, CV_64F), cv::noArray(), rvec, tvec, false, 100, threshold,
                            0.99, inliers)) {
      return false;
    }
  } catch (const cv::Exception&) {
    return false;  // a degenerate configuration: the keyframe is left out like one with too few inliers
  }
  if (static_cast<int>(inliers.size()) < kMinRegisteredPoints) return false;
  const SE3d T_c_c0(SO3d::exp(Vector3d(rvec.at<double>(0), rvec.at<double>(1), rvec.at<double>(2))),
                    Vector3d(tvec.at<double>(0), tvec.at<double>(1), tvec.at<double>(2)));
  KeyframeData& view = *s.map.keyframes().get(handle);
  view.T_w_s = T_w_c0 * T_c_c0.inverse() * s.T_s_c.inverse();
  for (int i : inliers) {
    const std::size_t track = track_of[static_cast<std::size_t>(i)];
    (void)s.map.addObservation(handle, static_cast<std::uint16_t>(followed[track]), *point_of_track[track]);
  }
  return true;
}

// Each keyframe's velocity from its neighbours' positions: a start for the IMU initialisation, which sets them.
void velocitiesFromPositions(Mapper::State& s, const std::vector<PoolHandle>& views) {
  for (std::size_t i = 0; i < views.size(); ++i) {
    const KeyframeData& a = *s.map.keyframes().get(views[i == 0 ? 0 : i - 1]);
    const KeyframeData& b = *s.map.keyframes().get(views[std::min(i + 1, views.size() - 1)]);
    const double dt = static_cast<double>(b.t_ns - a.t_ns) * 1e-9;
    KeyframeData& kf = *s.map.keyframes().get(views[i]);
    kf.v_w = dt > 0 ? Vector3d((b.T_w_s.translation() - a.T_w_s.translation()) / dt) : Vector3d::Zero();
  }
}

// The first map from the view `first` (the reference, or a keyframe after it) and the newest keyframe, when their
// followed keypoints show enough parallax, and the other waiting keyframes placed on it.
Status initialiseFromTwoViews(Mapper::State& s, std::size_t first, MapperReport& report) {
  MonocularStart& start = s.mono_start;
  const PoolHandle reference = start.views[first];
  const PoolHandle newest = start.views.back();
  const KeyframeData& kf0 = *s.map.keyframes().get(reference);
  const KeyframeData& kf1 = *s.map.keyframes().get(newest);
  const std::vector<std::int32_t>& in_first = start.followed[first];
  const std::vector<std::int32_t>& last = start.followed.back();
  std::vector<Vector3d> b0;
  std::vector<Vector3d> b1;
  std::vector<std::size_t> tracks;
  for (std::size_t track = 0; track < last.size(); ++track) {
    if (in_first[track] < 0 || last[track] < 0) continue;
    b0.push_back(s.left.unproject(kf0.keypoints[static_cast<std::size_t>(in_first[track])].px.cast<double>()));
    b1.push_back(s.left.unproject(kf1.keypoints[static_cast<std::size_t>(last[track])].px.cast<double>()));
    tracks.push_back(track);
  }
  TwoViewOptions two_view;
  two_view.focal_px = s.left.calibration().fx;
  two_view.min_inliers = s.options.mono_init_min_matches;
  two_view.min_median_parallax_deg = s.options.mono_init_min_parallax_deg;
  auto geometry = initialiseTwoView(b0, b1, two_view);
  if (!geometry) return geometry.error();
  // Median depth 2 (arbitrary units until the IMU gives the scale).
  std::vector<double> depths;
  for (std::size_t i = 0; i < geometry->inlier.size(); ++i) {
    if (geometry->inlier[i] != 0) depths.push_back(geometry->p_c0[i].norm());
  }
  std::nth_element(depths.begin(), depths.begin() + static_cast<std::ptrdiff_t>(depths.size() / 2), depths.end());
  const double scale = 2.0 / depths[depths.size() / 2];
  const SE3d T_w_c0 = s.cameraPose(kf0);
  SE3d T_c0_c1 = geometry->T_c0_c1;
  T_c0_c1.translation() *= scale;
  s.map.keyframes().get(newest)->T_w_s = T_w_c0 * T_c0_c1 * s.T_s_c.inverse();

  std::vector<std::optional<PoolHandle>> point_of_track(last.size());
  std::vector<Vector3d> p_c0_of_track(last.size(), Vector3d::Zero());
  int created = 0;
  for (std::size_t i = 0; i < geometry->inlier.size(); ++i) {
    if (geometry->inlier[i] == 0) continue;
    const std::size_t track = tracks[i];
    const Vector3d p_c0 = geometry->p_c0[i] * scale;
    auto point = s.map.createMapPoint(reference, static_cast<std::uint16_t>(in_first[track]), p_c0.normalized(),
                                      p_c0.norm(), s.point_ids.next());
    if (!point) continue;
    (void)s.map.addObservation(newest, static_cast<std::uint16_t>(last[track]), *point);
    point_of_track[track] = *point;
    p_c0_of_track[track] = p_c0;
    ++created;
  }
  std::vector<PoolHandle> placed;
  int dropped = 0;
  for (std::size_t v = 0; v + 1 < start.views.size(); ++v) {
    if (v == first || registerView(s, start.views[v], start.followed[v], point_of_track, p_c0_of_track, T_w_c0)) {
      placed.push_back(start.views[v]);
    } else {
      // Its IMU link goes with it: the chain the IMU initialisation aligns starts after it.
      (void)s.map.removeKeyframe(start.views[v]);
      ++dropped;
    }
  }
  placed.push_back(newest);
  velocitiesFromPositions(s, placed);
  s.mono_initialised = true;
  report.mono_initialised_now = true;
  report.triangulated += created;
  const std::size_t after_reference = first - start.reference;
  report.note =
      "monocular map from two views " + std::to_string(start.views.size() - 1 - first) + " keyframes apart" +
      (after_reference > 0 ? " (the first " + std::to_string(after_reference) + " after the reference)" : "") + ": " +
      std::to_string(created) + " points, median parallax " + std::to_string(geometry->median_parallax_deg) + " deg, " +
      std::to_string(placed.size() - 2) + " other keyframes placed" +
      (dropped > 0 ? " (" + std::to_string(dropped) + " left out)" : "");
  start.clear();
  return Status::Ok();
}

}  // namespace

void tryMonocularStart(Mapper::State& s, PoolHandle handle, MapperReport& report) {
  MonocularStart& start = s.mono_start;
  const bool all_there = std::all_of(start.views.begin(), start.views.end(),
                                     [&](PoolHandle h) { return s.map.keyframes().get(h) != nullptr; });
  if (start.views.empty() || !all_there) {
    startOver(s, handle);
    return;
  }
  const int followed = follow(s, handle);
  if (followed < s.options.mono_init_min_matches) {
    const std::size_t kept = startOverKeepingShared(s);
    report.note = "monocular start: " + std::to_string(followed) +
                  " of the reference's keypoints followed, fewer than " +
                  std::to_string(s.options.mono_init_min_matches) + ": this keyframe is the reference now, " +
                  std::to_string(kept) + " keyframes before it kept";
    return;
  }
  // The reference first. A start that moves back and forth can bring the camera back near the reference while a
  // keyframe between saw the scene from far enough away: then that one makes the map with the newest.
  // The views kept from before the reference share fewer tracks with it than a start needs.
  const Status st = initialiseFromTwoViews(s, start.reference, report);
  if (st.ok()) return;
  for (std::size_t first = start.reference + 1; first + 1 < start.views.size(); ++first) {
    if (initialiseFromTwoViews(s, first, report).ok()) return;
  }
  report.note = st.error().message();
  // The waiting keyframes stay in the map: leave room for the ones that come after the start. The views kept from
  // before the reference go first.
  const auto waiting = [&] { return static_cast<int>(start.views.size()); };
  if (waiting() >= s.options.max_keyframes / 2 && start.reference > 0) {
    const auto count = std::min(start.reference, static_cast<std::size_t>(waiting() - s.options.max_keyframes / 2 + 1));
    dropOldestViews(s, count);
    report.note += "; the " + std::to_string(count) + " oldest keyframes kept from before the reference go";
  }
  if (waiting() >= s.options.max_keyframes / 2) {
    report.note += "; after " + std::to_string(start.views.size() - 1) + " keyframes this one is the reference now";
    startOver(s, handle);
  }
}

}  // namespace cvislam::agent
