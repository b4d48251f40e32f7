#include "agent_rt/link/anchor_decoder.hpp"

#include <algorithm>
#include <cmath>
#include <functional>
#include <limits>
#include <string>
#include <vector>

#include "agent_rt/messages/conversions.hpp"
#include "cvislam/v1/agent_link.pb.h"
#include "proto/wire/wire.hpp"

namespace cvislam::agent {
namespace {

constexpr std::uint32_t kPyramidLevels = wire::kMaxOctave + 1;
static_assert(kMaxAnchorKeyframesPerMessage == wire::kMaxCovisibleKeyframesPerMessage);
static_assert(kMaxAnchorPointsPerMessage == wire::kMaxCovisiblePointsPerMessage);

Status refused(const std::string& what) {
  return Error{ErrorCode::kInvalidArgument, "downlink covisible map: " + what};
}

Result<PoseMsg> pose(const v1::Pose& in, const std::string& what) {
  Result<geometry::SE3d> T = wire::fromProto(in, what);
  if (!T) return T.error();
  return toMsg(*T);
}

bool agentId(std::uint32_t value) {
  return value <= std::numeric_limits<AgentId>::max();
}

// More than `capacity` of `what` in one message is refused.
Status checkCapacity(int count, std::size_t capacity, const std::string& what) {
  if (static_cast<std::size_t>(count) <= capacity) return Status::Ok();
  return refused(std::to_string(count) + " " + what + ", over the capacity of " + std::to_string(capacity));
}

Status checkPosition(const google::protobuf::RepeatedField<float>& values, int first, const std::string& what) {
  for (int i = first; i < first + 3; ++i) {
    if (!std::isfinite(values.Get(i))) return refused(what + " is not finite");
  }
  return Status::Ok();
}

Status decode(const v1::CovisibleMap& in, AnchorMessage& out) {
  out.agent_map = in.agent_map();
  // The server's selection, best first.
  if (in.selected_agent_size() != in.selected_counter_size())
    return refused("selected_agent and selected_counter differ in length");
  if (Status s = checkCapacity(in.selected_counter_size(), kMaxAnchorKeyframesPerMessage, "selected keyframes");
      !s.ok()) {
    return s;
  }
  for (int i = 0; i < in.selected_counter_size(); ++i) {
    if (!agentId(in.selected_agent(i)))
      return refused("selected keyframe " + std::to_string(i) + ": agent id over 16 bits");
    out.selected[out.selected_count++] = KeyframeId{static_cast<AgentId>(in.selected_agent(i)), in.selected_counter(i)};
  }
  // Points in full.
  if (Status s = checkCapacity(in.points_size(), kMaxAnchorPointsPerMessage, "points"); !s.ok()) return s;
  for (const v1::CovisiblePoint& p : in.points()) {
    const std::string what = "point " + std::to_string(p.agent()) + ":" + std::to_string(p.counter());
    if (!agentId(p.agent())) return refused(what + ": agent id over 16 bits");
    if (p.p_w_size() != 3) return refused(what + ": p_w needs 3 values, has " + std::to_string(p.p_w_size()));
    if (Status s = checkPosition(p.p_w(), 0, what + " p_w"); !s.ok()) return s;
    if (p.orb_size() != 4) return refused(what + ": orb needs 4 words, has " + std::to_string(p.orb_size()));
    if (p.octave() >= kPyramidLevels)
      return refused(what + ": octave " + std::to_string(p.octave()) + " beyond the pyramid");
    AnchorPointMsg& point = out.points[out.point_count++];
    point.id = MapPointId{static_cast<AgentId>(p.agent()), p.counter()};
    point.p_w = {p.p_w(0), p.p_w(1), p.p_w(2)};
    wire::unpackDescriptor(p.orb().data(), point.descriptor.data());
    point.octave = static_cast<std::uint8_t>(p.octave());
  }
  // Keyframes in full.
  if (Status s = checkCapacity(in.keyframes_size(), kMaxAnchorKeyframesPerMessage, "keyframes"); !s.ok()) return s;
  for (const v1::CovisibleKeyframe& k : in.keyframes()) {
    const std::string what = "keyframe " + std::to_string(k.agent()) + ":" + std::to_string(k.counter());
    if (!agentId(k.agent())) return refused(what + ": agent id over 16 bits");
    if (!k.has_t_w_c()) return refused(what + ": no T_w_c");
    Result<PoseMsg> T_w_c = pose(k.t_w_c(), what + " T_w_c");
    if (!T_w_c) return refused(T_w_c.error().message());
    const int n = k.point_counter_size();
    if (k.point_agent_size() != n || k.xy_size() != 2 * n || static_cast<int>(k.octave().size()) != n) {
      return refused(what + ": xy, point_agent, point_counter and octave differ in length");
    }
    if (Status s = checkCapacity(n, kMaxKeypointsPerKeyframe, what + " observations"); !s.ok()) return s;
    AnchorKeyframeMsg& keyframe = out.keyframes[out.keyframe_count++];
    keyframe.id = KeyframeId{static_cast<AgentId>(k.agent()), k.counter()};
    keyframe.t_ns = k.t_ns();
    keyframe.T_w_c = *T_w_c;
    keyframe.observation_count = 0;
    for (int i = 0; i < n; ++i) {
      const float x = k.xy(2 * i);
      const float y = k.xy(2 * i + 1);
      // Normalised coordinates: a point in front of the camera, within 89.4 degrees of its axis (fisheye lenses
      // see beyond 80).
      if (!std::isfinite(x) || !std::isfinite(y) || std::abs(x) > 100.0F || std::abs(y) > 100.0F) {
        return refused(what + ": observation " + std::to_string(i) + " is not a finite normalised coordinate");
      }
      const auto octave = static_cast<std::uint8_t>(k.octave()[static_cast<std::size_t>(i)]);
      if (octave >= kPyramidLevels)
        return refused(what + ": observation " + std::to_string(i) + " octave beyond the pyramid");
      if (!agentId(k.point_agent(i)))
        return refused(what + ": observation " + std::to_string(i) + " agent id over 16 bits");
      keyframe.observations[keyframe.observation_count++] =
          AnchorObservationMsg{x, y, MapPointId{static_cast<AgentId>(k.point_agent(i)), k.point_counter(i)}, octave};
    }
  }
  // Updates.
  if (Status s = checkCapacity(in.keyframe_updates_size(), kMaxAnchorKeyframesPerMessage, "keyframe updates");
      !s.ok()) {
    return s;
  }
  for (const v1::CovisiblePose& u : in.keyframe_updates()) {
    const std::string what = "keyframe update " + std::to_string(u.agent()) + ":" + std::to_string(u.counter());
    if (!agentId(u.agent())) return refused(what + ": agent id over 16 bits");
    if (!u.has_t_w_c()) return refused(what + ": no T_w_c");
    Result<PoseMsg> T_w_c = pose(u.t_w_c(), what + " T_w_c");
    if (!T_w_c) return refused(T_w_c.error().message());
    out.keyframe_updates[out.keyframe_update_count++] =
        AnchorPoseUpdateMsg{KeyframeId{static_cast<AgentId>(u.agent()), u.counter()}, *T_w_c};
  }
  const int updates = in.point_update_counter_size();
  if (in.point_update_agent_size() != updates || in.point_update_p_w_size() != 3 * updates) {
    return refused("point_update_agent, point_update_counter and point_update_p_w differ in length");
  }
  if (Status s = checkCapacity(updates, kMaxAnchorPointsPerMessage, "point updates"); !s.ok()) return s;
  for (int i = 0; i < updates; ++i) {
    const std::string what = "point update " + std::to_string(i);
    if (!agentId(in.point_update_agent(i))) return refused(what + ": agent id over 16 bits");
    if (Status s = checkPosition(in.point_update_p_w(), 3 * i, what + " p_w"); !s.ok()) return s;
    out.point_updates[out.point_update_count++] = AnchorPointUpdateMsg{
        MapPointId{static_cast<AgentId>(in.point_update_agent(i)), in.point_update_counter(i)},
        {in.point_update_p_w(3 * i), in.point_update_p_w(3 * i + 1), in.point_update_p_w(3 * i + 2)}};
  }
  return Status::Ok();
}

void clearCounts(AnchorMessage& out) {
  out.selected_count = 0;
  out.keyframe_count = 0;
  out.point_count = 0;
  out.keyframe_update_count = 0;
  out.point_update_count = 0;
}

}  // namespace

Status decodeCovisibleMap(const v1::CovisibleMap& in, std::uint64_t sequence, AnchorMessage& out) {
  clearCounts(out);
  out.sequence = sequence;
  Status s = decode(in, out);
  if (!s.ok()) clearCounts(out);
  return s;
}

Status decodeCorrections(const google::protobuf::RepeatedPtrField<v1::KeyframeState>& in, AgentId agent,
                         AnchorMessage& out) {
  out.correction_count = 0;
  // The newest keyframes are the ones mapping still holds: when there are more than the capacity, the
  // highest counters are kept.
  std::uint32_t lowest_kept = 0;
  if (static_cast<std::size_t>(in.size()) > kMaxAnchorCorrectionsPerMessage) {
    std::vector<std::uint32_t> counters;
    counters.reserve(static_cast<std::size_t>(in.size()));
    for (const v1::KeyframeState& c : in) counters.push_back(c.counter());
    std::nth_element(counters.begin(), counters.begin() + kMaxAnchorCorrectionsPerMessage - 1, counters.end(),
                     std::greater<>());
    lowest_kept = counters[kMaxAnchorCorrectionsPerMessage - 1];
  }
  for (const v1::KeyframeState& c : in) {
    if (c.counter() < lowest_kept || out.correction_count >= kMaxAnchorCorrectionsPerMessage) continue;
    const std::string what =
        "downlink correction of keyframe " + std::to_string(agent) + ":" + std::to_string(c.counter());
    auto state = wire::fromProto(c, what);
    if (!state) {
      out.correction_count = 0;
      return Error{ErrorCode::kInvalidArgument, state.error().message()};
    }
    KeyframeStateMsg& m = out.corrections[out.correction_count++];
    m.id = KeyframeId{agent, c.counter()};
    m.T_w_s = toMsg(state->T_w_s);
    m.v_w = toArray(state->v_w);
    m.bias = toMsg(state->bias);
  }
  return Status::Ok();
}

}  // namespace cvislam::agent
