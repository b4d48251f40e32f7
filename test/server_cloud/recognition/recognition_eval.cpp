#include "test/server_cloud/recognition/recognition_eval.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <map>
#include <memory>
#include <numbers>
#include <thread>
#include <unordered_set>

#include "common/dataset/euroc_calibration.hpp"
#include "common/geometry/alignment.hpp"
#include "test/server_cloud/recognition/synthetic_keyframes.hpp"
#include "test/sim/presets.hpp"
#include "test/sim/random.hpp"

namespace cvislam::test {
namespace {

using server::MapContent;
using server::MapId;
namespace rec = server::recognition;
using Clock = std::chrono::steady_clock;

constexpr double kDeg = std::numbers::pi / 180.0;
constexpr std::uint64_t kFrameStream = 0x5eed0001;
constexpr std::uint64_t kDriftStream = 0x5eed0002;
constexpr std::uint64_t kSampleStream = 0x5eed0003;

double ms(Clock::duration d) {
  return std::chrono::duration<double, std::milli>(d).count();
}

struct Keyframe {
  std::size_t agent = 0;
  std::size_t index = 0;
  double t_s = 0.0;
  SyntheticView view;
  geometry::SE3d T_w_c;    // true camera pose
  geometry::SE3d E_map_w;  // the agent's map frame and drift at this keyframe
  KeyframeId id;
};

// Whether c's camera sees at least `needed` of q's surface points (in its image, in front, not hidden).
bool sharesSurface(const sim::World& world, const camera::CameraModel& camera, const Keyframe& q, const Keyframe& c,
                   int needed) {
  const geometry::SE3d T_c_w = c.T_w_c.inverse();
  const Eigen::Vector3d o_w = c.T_w_c.translation();
  int seen = 0;
  for (std::size_t i = 0; i < q.view.p_w.size(); ++i) {
    if (q.view.face[i] < 0) continue;
    const Eigen::Vector3d p_c = T_c_w * q.view.p_w[i];
    const std::optional<Eigen::Vector2d> px = camera.project(p_c);
    if (!px || px->x() < 0.0 || px->y() < 0.0 || px->x() >= camera.width() || px->y() >= camera.height()) continue;
    const Eigen::Vector3d d = q.view.p_w[i] - o_w;
    const double distance = d.norm();
    const sim::RayHit hit = world.cast(o_w, d / distance);
    if (hit.face < 0 || hit.t_m < distance - 0.03) continue;
    if (++seen >= needed) return true;
  }
  return false;
}

double angleBetweenAxesDeg(const geometry::SE3d& a, const geometry::SE3d& b) {
  const Eigen::Vector3d za = a.rotationMatrix().col(2);
  const Eigen::Vector3d zb = b.rotationMatrix().col(2);
  return std::acos(std::clamp(za.dot(zb), -1.0, 1.0)) / kDeg;
}

}  // namespace

Result<RecognitionEvaluation> evaluateRecognition(const RecognitionEvalOptions& options,
                                                  const features::Vocabulary& vocabulary) {
  if (Status s = options.recognition.validate(); !s) return s.error();
  if (options.keyframe_interval_s <= 0.0 || options.duration_s <= 0.0) {
    return Error(ErrorCode::kInvalidArgument, "keyframe interval and duration must be positive");
  }
  const auto say = [&](const std::string& text) {
    if (options.progress) options.progress(text);
  };
  Result<sim::MissionPlan> plan = sim::planPreset(options.preset, options.seed, options.duration_s);
  if (!plan) return plan.error().withContext("planning " + options.preset);
  sim::WorldOptions world_options;
  world_options.seed = options.seed;
  const sim::World world(plan->layout, world_options);
  const dataset::CameraCalibration cam0 = dataset::eurocCam0();

  RecognitionEvaluation out;
  out.preset = options.preset;
  out.seed = options.seed;
  out.agents = static_cast<int>(plan->agents.size());

  // 1. Views, rendered on `threads` threads (agents split between them).
  const Clock::time_point render_start = Clock::now();
  std::vector<std::vector<Keyframe>> per_agent(plan->agents.size());
  {
    std::vector<std::thread> workers;
    std::vector<Status> status(static_cast<std::size_t>(std::max(1, options.threads)));
    const std::size_t thread_count = status.size();
    for (std::size_t w = 0; w < thread_count; ++w) {
      workers.emplace_back([&, w] {
        Result<ViewMaker> maker = ViewMaker::create(cam0);
        if (!maker) {
          status[w] = maker.error();
          return;
        }
        for (std::size_t a = w; a < plan->agents.size(); a += thread_count) {
          const sim::BodyTrajectory& trajectory = plan->agents[a].trajectory;
          const double end_s = std::min(plan->duration_s, trajectory.duration());
          for (std::size_t k = 0;; ++k) {
            const double t_s = static_cast<double>(k) * options.keyframe_interval_s;
            if (t_s > end_s) break;
            Keyframe kf;
            kf.agent = a;
            kf.index = k;
            kf.t_s = t_s;
            kf.view = maker->render(world, trajectory.state(t_s).T_w_b);
            kf.T_w_c = kf.view.T_w_s * cam0.T_b_c;
            per_agent[a].push_back(std::move(kf));
          }
        }
      });
    }
    for (std::thread& t : workers) t.join();
    for (const Status& s : status) {
      if (!s) return s.error();
    }
  }
  out.render_s = std::chrono::duration<double>(Clock::now() - render_start).count();
  say(options.preset + ": rendered " + std::to_string(plan->agents.size()) + " agents' keyframes in " +
      std::to_string(static_cast<int>(out.render_s)) + " s");

  // 2. Each agent's map frame and drift.
  for (std::size_t a = 0; a < per_agent.size(); ++a) {
    sim::Rng rng(sim::deriveSeed(options.seed, kDriftStream, a));
    const geometry::SE3d frame(geometry::rotationAboutZ(rng.uniform(-std::numbers::pi, std::numbers::pi)),
                               Eigen::Vector3d(rng.uniform(-5.0, 5.0), rng.uniform(-5.0, 5.0), rng.uniform(-0.5, 0.5)));
    geometry::SE3d drift;
    Eigen::Vector3d last = per_agent[a].empty() ? Eigen::Vector3d::Zero() : per_agent[a][0].T_w_c.translation();
    for (Keyframe& kf : per_agent[a]) {
      const Eigen::Vector3d p = kf.T_w_c.translation();
      const double root = std::sqrt((p - last).norm());
      last = p;
      // A turn about the vertical through the current position, and a shift.
      const geometry::SO3d R = geometry::rotationAboutZ(options.drift_yaw_deg_per_sqrt_m * kDeg * root * rng.normal());
      const Eigen::Vector3d shift(options.drift_xy_m_per_sqrt_m * root * rng.normal(),
                                  options.drift_xy_m_per_sqrt_m * root * rng.normal(),
                                  options.drift_z_m_per_sqrt_m * root * rng.normal());
      drift = drift * geometry::SE3d(R, p - (R * p) + shift);
      kf.E_map_w = frame * drift;
    }
  }

  // 3. Keyframes in mission-time order: into the maps and the database, then the two queries each.
  std::vector<Keyframe*> order;
  for (auto& agent : per_agent) {
    for (Keyframe& kf : agent) order.push_back(&kf);
  }
  std::stable_sort(order.begin(), order.end(), [](const Keyframe* a, const Keyframe* b) {
    return a->t_s != b->t_s ? a->t_s < b->t_s : a->agent < b->agent;
  });
  std::vector<std::unique_ptr<MapContent>> maps;
  std::vector<std::unique_ptr<SyntheticMap>> builders;
  for (std::size_t a = 0; a < per_agent.size(); ++a) {
    maps.push_back(std::make_unique<MapContent>(static_cast<MapId>(a)));
    SyntheticMapOptions map_options;
    map_options.seed = sim::deriveSeed(options.seed, kFrameStream, a);
    builders.push_back(std::make_unique<SyntheticMap>(*maps.back(), world, static_cast<AgentId>(a), map_options));
  }
  Result<camera::CameraModel> camera = camera::CameraModel::create(cam0);
  if (!camera) return camera.error();
  const rec::AgentCamera agent_camera{*camera, cam0.T_b_c};
  const rec::CameraLookup cameras = [&](AgentId) { return &agent_camera; };
  const rec::MapLookup map_of = [&](MapId id) -> const MapContent* {
    return id < maps.size() ? maps[id].get() : nullptr;
  };
  rec::KeyframeDatabase database(vocabulary.wordCount());
  std::map<KeyframeId, const Keyframe*> by_id;
  std::vector<const Keyframe*> arrived;
  sim::Rng sample_rng(sim::deriveSeed(options.seed, kSampleStream));
  out.loop.rejections.assign(7, 0.0);
  out.match.rejections.assign(7, 0.0);

  const Clock::time_point recognition_start = Clock::now();
  std::size_t done = 0;
  for (Keyframe* kf : order) {
    Result<KeyframeId> id =
        builders[kf->agent]->add(kf->view, kf->E_map_w, static_cast<std::int64_t>(std::llround(kf->t_s * 1e9)));
    if (!id) return id.error();
    kf->id = *id;
    by_id.emplace(*id, kf);
    const MapContent& map = *maps[kf->agent];
    features::BowVector bow;
    features::FeatureVector fv;
    vocabulary.transform(map.keyframe(*id)->descriptors, bow, &fv, options.recognition.direct_level);
    if (Status s = database.add(*id, static_cast<MapId>(kf->agent), std::move(bow), std::move(fv)); !s) {
      return s.error();
    }
    ++out.keyframes;
    const features::BowVector& query_bow = database.find(*id)->bow;

    for (const rec::QueryKind kind : {rec::QueryKind::kLoop, rec::QueryKind::kMapMatch}) {
      QueryStats& stats = kind == rec::QueryKind::kLoop ? out.loop : out.match;
      ++stats.queries;
      // Ground truth: the true revisits among the keyframes that arrived before.
      std::unordered_set<KeyframeId> excluded{*id};
      for (const auto& [n, shared] : map.covisible(*id)) excluded.insert(n);
      std::unordered_set<KeyframeId> revisits;
      for (const Keyframe* c : arrived) {
        const bool same = c->agent == kf->agent;
        if (same != (kind == rec::QueryKind::kLoop) || excluded.contains(c->id)) continue;
        // A loop is a revisit at least loop_min_interval_s later; sooner, it is tracking's.
        if (same && kf->t_s - c->t_s < options.recognition.loop_min_interval_s) continue;
        const double distance = (c->T_w_c.translation() - kf->T_w_c.translation()).norm();
        if (distance > 5.0 && sample_rng.uniform() < 0.02) {
          out.different_scores.push_back(features::bowScore(query_bow, database.find(c->id)->bow));
        }
        if (distance > options.max_revisit_distance_m ||
            angleBetweenAxesDeg(c->T_w_c, kf->T_w_c) > options.max_revisit_angle_deg) {
          continue;
        }
        if (sharesSurface(world, *camera, *kf, *c, options.min_shared_spots)) {
          revisits.insert(c->id);
          out.revisit_scores.push_back(features::bowScore(query_bow, database.find(c->id)->bow));
        }
      }
      if (!revisits.empty()) ++stats.true_revisits;

      // The recogniser.
      const Clock::time_point t0 = Clock::now();
      Result<rec::CandidateSearch> search = rec::findCandidates(database, map, *id, kind, map_of, options.recognition);
      stats.query_ms.push_back(ms(Clock::now() - t0));
      if (!search) return search.error();
      if (!search->candidates.empty()) ++stats.with_candidates;
      bool bow_found = false;
      std::optional<rec::VerifiedMatch> best;
      for (const rec::Candidate& c : search->candidates) {
        ++stats.candidates;
        if (revisits.contains(c.keyframe)) {
          ++stats.candidates_true;
          bow_found = true;
        }
        const Clock::time_point v0 = Clock::now();
        const rec::Verification v =
            rec::verifyCandidate(database, map, *id, *maps[c.map], c.keyframe, c.score, cameras, options.recognition);
        stats.verification_ms.push_back(ms(Clock::now() - v0));
        stats.rejections[static_cast<std::size_t>(v.rejection)] += 1.0;
        if (v.accepted() && (!best || v.match->inliers > best->inliers)) best = v.match;
      }
      if (bow_found) ++stats.bow_found;
      if (best) {
        ++stats.accepted;
        // The query camera's true pose in the candidate's map: the candidate keyframe's drift applied to truth.
        const Keyframe& c = *by_id.at(best->candidate);
        const geometry::SE3d truth = c.E_map_w * kf->T_w_c;
        const geometry::SE3d error = truth.inverse() * best->T_cmap_cq;
        const double translation = (truth.translation() - best->T_cmap_cq.translation()).norm();
        const double rotation = error.so3().log().norm() / kDeg;
        const bool correct = translation <= options.false_translation_m && rotation <= options.false_rotation_deg;
        if (!correct) {
          ++stats.accepted_false;
          say("  FALSE " + std::string(rec::toString(kind)) + " " + id->toString() + " -> " +
              best->candidate.toString() + ": " + std::to_string(translation) + " m, " + std::to_string(rotation) +
              " deg, " + std::to_string(best->inliers) + " inliers");
        } else {
          stats.translation_error_m.push_back(translation);
          stats.rotation_error_deg.push_back(rotation);
          if (!revisits.empty()) {
            ++stats.found;
          } else {
            ++stats.accepted_not_revisit;
          }
        }
      }
    }
    arrived.push_back(kf);
    if (++done % 100 == 0) {
      say(options.preset + ": " + std::to_string(done) + " / " + std::to_string(order.size()) + " keyframes");
    }
  }
  out.recognition_s = std::chrono::duration<double>(Clock::now() - recognition_start).count();
  out.database_bytes = database.memoryBytes();
  return out;
}

}  // namespace cvislam::test
