#include "agent_rt/mapping/imu_initialisation.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <string>
#include <vector>

#include "agent_rt/messages/conversions.hpp"

namespace cvislam::agent {

using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;

namespace {

// How far before the first kept IMU sample a keyframe may be moved, with the IMU held at that sample: a recording
// whose IMU starts just as early as the first image was taken.
constexpr std::int64_t kMaxImuHeldBeforeNs = 5'000'000;

// 80 s of IMU at 200 Hz, 16 s at 1 kHz: far longer than an initialisation's chain of keyframes takes, and far
// more than one keyframe interval.
constexpr std::size_t kImuHistorySamples = 16384;

// Applies a similarity to the whole map: camera positions and orientations, velocities and point depths.
void transformMap(Mapper::State& s, double scale, const SO3d& R_w_v) {
  s.map.keyframes().forEach([&](PoolHandle, KeyframeData& kf) {
    const SE3d T_w_c = kf.T_w_s * s.T_s_c;
    const SE3d T_w_c_new(R_w_v * T_w_c.so3(), scale * (R_w_v * T_w_c.translation()));
    kf.T_w_s = T_w_c_new * s.T_s_c.inverse();
    kf.v_w = scale * (R_w_v * kf.v_w);
  });
  s.map.mapPoints().forEach([&](PoolHandle, MapPointData& p) { p.inverse_depth /= scale; });
  s.epoch_scale = scale;
  s.epoch_transform = SE3d(R_w_v, Vector3d::Zero());
  ++s.epoch;
}

// The trailing run of own keyframes, each IMU-linked to the one before it, oldest first.
std::vector<PoolHandle> imuLinkedChain(const Mapper::State& s) {
  const std::vector<PoolHandle> order = s.keyframesBySequence();
  std::vector<PoolHandle> chain;
  for (auto it = order.rbegin(); it != order.rend(); ++it) {
    chain.insert(chain.begin(), *it);
    const KeyframeData& kf = *s.map.keyframes().get(*it);
    if (std::next(it) == order.rend()) break;
    const KeyframeData& previous = *s.map.keyframes().get(*std::next(it));
    if (!kf.has_preintegration || !(kf.preintegration_from == previous.id)) break;
  }
  return chain;
}

Result<imu::VisualInertialAlignment> alignChain(const Mapper::State& s, const std::vector<PoolHandle>& chain,
                                                const imu::VisualInertialAlignmentOptions& options) {
  std::vector<imu::VisualKeyframe> visual;
  std::vector<imu::Preintegration> preintegrations;
  for (std::size_t i = 0; i < chain.size(); ++i) {
    const KeyframeData& kf = *s.map.keyframes().get(chain[i]);
    visual.push_back({s.cameraPose(kf), kf.gyro_s, static_cast<double>(kf.time_correction_ns) * 1e-9});
    if (i > 0) preintegrations.push_back(kf.preintegration);
  }
  return imu::alignVisualInertial(visual, preintegrations, s.T_s_c, options);
}

// The gyro at t_ns, interpolated between the samples around it; `samples` covers t_ns.
Vector3d gyroAt(const std::vector<dataset::ImuSample>& samples, std::int64_t t_ns) {
  auto after = std::lower_bound(samples.begin(), samples.end(), t_ns,
                                [](const dataset::ImuSample& a, std::int64_t t) { return a.t_ns < t; });
  if (after == samples.end()) return samples.back().gyro_s;
  if (after == samples.begin() || after->t_ns == t_ns) return after->gyro_s;
  const auto before = std::prev(after);
  const double a = static_cast<double>(t_ns - before->t_ns) / static_cast<double>(after->t_ns - before->t_ns);
  return before->gyro_s + a * (after->gyro_s - before->gyro_s);
}

// The first sample held back to t_ns, when t_ns lies before it.
void holdFirstSampleBackTo(std::vector<dataset::ImuSample>& imu, std::int64_t t_ns) {
  if (t_ns >= imu.front().t_ns) return;
  dataset::ImuSample held = imu.front();
  held.t_ns = t_ns;
  imu.insert(imu.begin(), held);
}

// What re-timing changes in a keyframe, to be put back when it cannot be done or the alignment then refuses.
struct KeyframeTiming {
  std::int64_t t_ns = 0;
  std::int64_t time_correction_ns = 0;
  Vector3d gyro_s;
  imu::Preintegration preintegration;
  bool has_preintegration = false;
  bool preintegration_incomplete = false;
};

std::vector<KeyframeTiming> timingsOf(const Mapper::State& s, const std::vector<PoolHandle>& keyframes) {
  std::vector<KeyframeTiming> out;
  for (PoolHandle h : keyframes) {
    const KeyframeData& kf = *s.map.keyframes().get(h);
    out.push_back({kf.t_ns, kf.time_correction_ns, kf.gyro_s, kf.preintegration, kf.has_preintegration,
                   kf.preintegration_incomplete});
  }
  return out;
}

void restoreTimings(Mapper::State& s, const std::vector<PoolHandle>& keyframes,
                    const std::vector<KeyframeTiming>& saved) {
  for (std::size_t i = 0; i < keyframes.size(); ++i) {
    KeyframeData& kf = *s.map.keyframes().get(keyframes[i]);
    kf.t_ns = saved[i].t_ns;
    kf.time_correction_ns = saved[i].time_correction_ns;
    kf.gyro_s = saved[i].gyro_s;
    kf.preintegration = saved[i].preintegration;
    kf.has_preintegration = saved[i].has_preintegration;
    kf.preintegration_incomplete = saved[i].preintegration_incomplete;
  }
}

// Moves the own keyframes to the times their images were taken by the estimate `correction_ns` and integrates
// the IMU between them again, making the links that the IMU did not cover before (a first keyframe stamped before
// the first sample). The newest keyframe's new time may lie up to the offset past the newest sample: the IMU is
// extrapolated over the gap (a few tens of ms of the keyframe's preintegration), and the link is marked incomplete,
// to be integrated again when the next keyframe brings the samples (completeImuLinks). A keyframe more than
// kMaxImuHeldBeforeNs older than the kept IMU keeps its time. False, with nothing changed, when a link of the
// initialisation's chain cannot be integrated again.
bool retimeKeyframes(Mapper::State& s, const std::vector<PoolHandle>& chain, std::int64_t correction_ns) {
  const std::vector<PoolHandle> order = s.keyframesBySequence();
  const std::vector<KeyframeTiming> saved = timingsOf(s, order);
  std::vector<dataset::ImuSample> imu = s.imu_history;
  if (imu.empty()) return false;
  for (PoolHandle h : order) {
    KeyframeData& kf = *s.map.keyframes().get(h);
    const std::int64_t t_ns = kf.t_ns + correction_ns - kf.time_correction_ns;
    if (t_ns < imu.front().t_ns - kMaxImuHeldBeforeNs) continue;
    holdFirstSampleBackTo(imu, t_ns);
    kf.t_ns = t_ns;
    kf.time_correction_ns = correction_ns;
    if (t_ns > imu.back().t_ns) {
      // Holding the newest sample over the gap instead left the keyframe's velocity 4 cm/s off in a 4 m/s^2 turn on
      // the simulated loop, and tracking leans on that velocity until the next keyframe, up to a second later.
      imu.push_back(imu::extrapolateImu(imu, t_ns));
    }
    kf.gyro_s = gyroAt(imu, t_ns);
  }
  bool chain_ok = true;
  for (std::size_t i = 1; i < order.size(); ++i) {
    KeyframeData& kf = *s.map.keyframes().get(order[i]);
    const KeyframeData& previous = *s.map.keyframes().get(order[i - 1]);
    if (!(kf.preintegration_from == previous.id) || !(kf.has_preintegration || kf.preintegration_incomplete)) {
      continue;
    }
    const bool had_link = kf.has_preintegration;
    kf.has_preintegration = integrateImuLink(s, previous, imu, kf);
    kf.preintegration_incomplete = !kf.has_preintegration || kf.t_ns > s.imu_history.back().t_ns;
    if (had_link && !kf.has_preintegration && std::find(chain.begin(), chain.end(), order[i]) != chain.end()) {
      chain_ok = false;
    }
  }
  if (!chain_ok) restoreTimings(s, order, saved);
  return chain_ok;
}

}  // namespace

bool integrateImuLink(const Mapper::State& s, const KeyframeData& previous, std::span<const dataset::ImuSample> samples,
                      KeyframeData& kf) {
  imu::Preintegration link(previous.bias, s.options.ba.noise);
  if (!link.integrateInterval(samples, previous.t_ns, kf.t_ns).ok()) return false;
  kf.preintegration = link;
  return true;
}

bool linkFromBeforeFirstSample(const Mapper::State& s, const KeyframeData& previous, KeyframeData& kf) {
  const std::vector<dataset::ImuSample>& kept = s.imu_history;
  const auto bound_ns = static_cast<std::int64_t>(s.options.ba.max_time_offset_s * 1e9);
  if (kept.empty() || previous.t_ns >= kept.front().t_ns || kept.front().t_ns - previous.t_ns > bound_ns) return false;
  std::vector<dataset::ImuSample> imu = kept;
  holdFirstSampleBackTo(imu, previous.t_ns);
  return integrateImuLink(s, previous, imu, kf);
}

void completeImuLinks(Mapper::State& s, const std::vector<PoolHandle>& order) {
  if (s.imu_history.empty()) return;
  for (std::size_t i = 1; i < order.size(); ++i) {
    KeyframeData& kf = *s.map.keyframes().get(order[i]);
    if (!kf.preintegration_incomplete || s.imu_history.back().t_ns < kf.t_ns) continue;
    const KeyframeData& previous = *s.map.keyframes().get(order[i - 1]);
    if (!(kf.preintegration_from == previous.id)) {
      kf.preintegration_incomplete = false;  // the keyframe it would link to is gone
      continue;
    }
    // Left as it is while the history does not reach back to the previous keyframe (a gap, or it has gone).
    if (!integrateImuLink(s, previous, s.imu_history, kf)) continue;
    kf.has_preintegration = true;
    kf.preintegration_incomplete = false;
    kf.gyro_s = gyroAt(s.imu_history, kf.t_ns);
  }
}

void keepImuHistory(Mapper::State& s, const KeyframeMessage& msg) {
  if (!s.options.use_imu || !s.options.ba.estimate_time_offset) return;
  std::vector<dataset::ImuSample>& kept = s.imu_history;
  if (kept.capacity() < kImuHistorySamples) kept.reserve(kImuHistorySamples);
  const std::uint32_t count = std::min<std::uint32_t>(msg.imu_count, kMaxImuSamplesPerKeyframe);
  for (std::uint32_t i = 0; i < count; ++i) {
    const dataset::ImuSample sample = fromMsg(msg.imu[i]);
    // Consecutive keyframes' samples overlap (each message holds the first sample after its keyframe).
    if (!kept.empty() && sample.t_ns <= kept.back().t_ns) continue;
    if (kept.size() == kImuHistorySamples) {
      kept.erase(kept.begin(), kept.begin() + static_cast<std::ptrdiff_t>(kImuHistorySamples / 4));
    }
    kept.push_back(sample);
  }
}

namespace {
// A keyframe's mapper note may already say something (the monocular start, a return to a place).
void addNote(MapperReport& report, const std::string& note) {
  report.note = report.note.empty() ? note : report.note + "; " + note;
}

std::string scaleOrNone(double scale) {
  return std::isnan(scale) ? std::string("none") : std::to_string(scale);
}

// True when `scale` lies within imu_init_scale_agreement of each of the last early attempts' scales; otherwise it
// joins them, the oldest leaving. The attempts follow keyframe by keyframe, so a scale that agrees with the ones
// before it no longer moves with the motion the new keyframes add. Slots without an attempt yet are NaN, which
// agrees with nothing.
bool scaleHasSettled(Mapper::State& s, double scale) {
  const double tolerance = s.options.imu_init_scale_agreement * scale;
  const bool settled = std::all_of(s.early_scales.begin(), s.early_scales.end(),
                                   [&](double earlier) { return std::abs(earlier - scale) <= tolerance; });
  if (!settled) {
    std::rotate(s.early_scales.begin(), s.early_scales.begin() + 1, s.early_scales.end());
    s.early_scales.back() = scale;
  }
  return settled;
}
}  // namespace

Status initialiseImu(Mapper::State& s, MapperReport& report) {
  const std::vector<PoolHandle> chain = imuLinkedChain(s);
  const int count = static_cast<int>(chain.size());
  // A stereo map's scale is known: only a monocular one tries earlier, on the scale it has observed.
  const int first_try =
      s.right ? s.options.imu_init_keyframes : std::min(s.options.imu_init_min_keyframes, s.options.imu_init_keyframes);
  if (count < first_try) return Error{ErrorCode::kNotFound, std::to_string(count) + " IMU-linked keyframes"};
  const bool early = count < s.options.imu_init_keyframes;
  imu::VisualInertialAlignmentOptions alignment = s.options.alignment;
  if (s.right) alignment.known_scale = 1.0;  // the stereo map is metric already
  alignment.estimate_time_offset = s.options.ba.estimate_time_offset;
  alignment.max_time_offset_s = s.options.ba.max_time_offset_s;
  auto aligned = alignChain(s, chain, alignment);
  // Before imu_init_keyframes a refusal is not a failure: the attempt at imu_init_keyframes is the first that counts.
  if (!aligned) {
    s.forgetEarlyScales();
    if (!early) return aligned.error();
    addNote(report, "IMU initialisation over " + std::to_string(count) + " keyframes refused (" +
                        aligned.error().message() + "), tried again at the next keyframe");
    return Error{ErrorCode::kNotFound, aligned.error().message()};
  }
  if (early) {
    const std::array<double, 2> earlier = s.early_scales;
    if (!scaleHasSettled(s, aligned->scale)) {
      addNote(report, "IMU initialisation over " + std::to_string(count) + " keyframes waits: scale " +
                          std::to_string(aligned->scale) + " (+-" +
                          std::to_string(aligned->scale_sigma_relative * 100.0) + " %), the two attempts before " +
                          scaleOrNone(earlier[0]) + " and " + scaleOrNone(earlier[1]) + ", not all within " +
                          std::to_string(s.options.imu_init_scale_agreement * 100.0) + " %");
      return Error{ErrorCode::kNotFound, std::to_string(count) + " IMU-linked keyframes: the scale has not settled"};
    }
  }
  int retimings = 0;
  if (alignment.estimate_time_offset) {
    // Aligned again over the re-timed keyframes: the velocities, the scale and the offset then come from IMU
    // intervals between the images' true times instead of from a first-order shift of each keyframe. Twice at
    // most: the second round starts from an offset whose first-order error the first round has removed.
    const std::vector<PoolHandle> order = s.keyframesBySequence();
    for (int round = 0; round < 2; ++round) {
      const std::vector<KeyframeTiming> saved = timingsOf(s, order);
      if (!retimeKeyframes(s, chain, std::llround(aligned->time_correction_s * 1e9))) break;
      auto again = alignChain(s, chain, alignment);
      if (!again) {
        restoreTimings(s, order, saved);
        break;
      }
      aligned = std::move(again);
      ++retimings;
    }
  }
  const double scale = aligned->scale;  // 1 for stereo (known)
  transformMap(s, scale, aligned->R_w_v);
  for (std::size_t i = 0; i < chain.size(); ++i) {
    KeyframeData& kf = *s.map.keyframes().get(chain[i]);
    kf.v_w = aligned->v_w[i];
  }
  s.map.keyframes().forEach([&](PoolHandle, KeyframeData& kf) { kf.bias.gyro = aligned->gyro_bias; });
  if (alignment.estimate_time_offset) s.map.setTimeCorrectionS(aligned->time_correction_s);
  s.imu_initialised = true;
  // Monocular: the next local BAs take the whole local map. Its scale came from the few seconds before, and the
  // keyframes a window holds fixed would hold that scale too. (A stereo map's scale is the baseline's; there the
  // whole map was measured to do worse than the window.)
  s.whole_map_bas_left = s.right.has_value() ? 0 : s.options.imu_init_full_window_keyframes;
  report.imu_initialised_now = true;
  report.note = "IMU initialised over " + std::to_string(chain.size()) + " keyframes: scale " +
                std::to_string(aligned->scale) + " (+-" + std::to_string(aligned->scale_sigma_relative * 100.0) +
                " %), gyro bias " + std::to_string(aligned->gyro_bias.norm()) + " rad/s";
  if (alignment.estimate_time_offset) {
    report.note += ", time offset correction " + std::to_string(aligned->time_correction_s * 1e3) + " ms" +
                   (retimings > 0 ? " (the keyframes re-timed to it)" : "");
  }
  return Status::Ok();
}

}  // namespace cvislam::agent
