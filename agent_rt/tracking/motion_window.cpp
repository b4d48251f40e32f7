#include "agent_rt/tracking/motion_window.hpp"

#include <algorithm>

#include "agent_rt/messages/conversions.hpp"

namespace cvislam::agent {

void MotionWindowBuilder::addLink(const KeyframeId& from, const KeyframeId& to,
                                  const imu::Preintegration& preintegration) {
  ImuLink& link = links_[links_next_];
  link.from = from;
  link.to = to;
  link.preintegration = preintegration;
  link.valid = true;
  links_next_ = (links_next_ + 1) % links_.size();
}

const MotionWindowBuilder::ImuLink* MotionWindowBuilder::findLink(const KeyframeId& from, const KeyframeId& to) const {
  for (const ImuLink& l : links_) {
    if (l.valid && l.from == from && l.to == to) return &l;
  }
  return nullptr;
}

std::span<MotionWindowKeyframe> MotionWindowBuilder::build(const MapSnapshotMessage* map, int n,
                                                           const NewestPublishedKeyframe& newest,
                                                           const imu::Preintegration& to_frame) {
  if (n <= 1 || map == nullptr || map->window_count == 0) return {};
  const KeyframeId& newest_mapped = map->keyframes[map->window[map->window_count - 1].keyframe].id;
  const bool unmapped = !(newest_mapped == newest.id);
  const auto wanted = std::min<std::size_t>(static_cast<std::size_t>(n) - (unmapped ? 1 : 0), map->window_count);
  if (wanted == 0) return {};
  const std::size_t first = map->window_count - wanted;
  // Walk back from the newest window keyframe while the IMU links chain.
  std::size_t start = map->window_count - 1;
  while (start > first) {
    const KeyframeId& older = map->keyframes[map->window[start - 1].keyframe].id;
    const KeyframeId& newer = map->keyframes[map->window[start].keyframe].id;
    if (findLink(older, newer) == nullptr) break;
    --start;
  }
  const ImuLink* to_unmapped = nullptr;
  if (unmapped) {
    to_unmapped = findLink(newest_mapped, newest.id);
    if (to_unmapped == nullptr) return {};
  }
  std::size_t count = 0;
  for (std::size_t w = start; w < map->window_count; ++w) {
    const WindowKeyframeMsg& wk = map->window[w];
    const KeyframeStateMsg& state = map->keyframes[wk.keyframe];
    std::array<PoseObservation, kMaxKeypointsPerKeyframe>& obs = observations_[count];
    // The first keyframe is held: its observations would not be used.
    const std::uint16_t observation_count = w == start ? 0 : wk.observation_count;
    for (std::uint16_t i = 0; i < observation_count; ++i) {
      const KeyframeObservationMsg& m = wk.observations[i];
      const MapPointMsg& p = map->points[m.point];
      obs[i].p_w = Eigen::Vector3d(p.p_w[0], p.p_w[1], p.p_w[2]);
      obs[i].keypoint_px = Eigen::Vector2d(m.u, m.v);
      obs[i].sigma_px = m.sigma_px;
    }
    MotionWindowKeyframe& k = window_[count];
    k.T_w_s = fromMsg(state.T_w_s);
    k.v_w = toVector3(state.v_w);
    k.bias = biasFromMsg(state.bias);
    k.observations = std::span<const PoseObservation>(obs.data(), observation_count);
    k.is_outlier = std::span(outliers_[count].data(), observation_count);
    if (w + 1 < map->window_count) {
      k.to_next = &findLink(state.id, map->keyframes[map->window[w + 1].keyframe].id)->preintegration;
    } else {
      k.to_next = to_unmapped != nullptr ? &to_unmapped->preintegration : &to_frame;
    }
    ++count;
  }
  if (to_unmapped != nullptr) {
    MotionWindowKeyframe& k = window_[count++];
    k.T_w_s = newest.T_w_s;
    k.v_w = newest.v_w;
    k.bias = newest.bias;
    k.observations = {};
    k.is_outlier = {};
    k.to_next = &to_frame;
  }
  return std::span(window_.data(), count);
}

}  // namespace cvislam::agent
