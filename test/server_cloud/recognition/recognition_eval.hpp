// Precision and recall of place recognition on a simulated mission, against ground truth.
//
// Every agent of the preset gets a keyframe every keyframe_interval_s of its flight: a rendered cam0 view made
// into its own server map (synthetic_keyframes.hpp), in its own gravity-aligned frame (a random yaw and shift)
// and with VIO-like drift (a random walk in yaw and position that grows with the distance flown). Keyframes
// arrive in mission-time order, as on the server; after each, the recogniser runs a loop query (its own map)
// and a map-match query (the other maps), on the database of everything that arrived before.
//
// Ground truth. A true revisit of query q is an earlier keyframe c in the query's scope (for loops: the same
// map, not covisible with q, at least loop_min_interval_s earlier) whose camera is within max_revisit_distance_m and
// max_revisit_angle_deg of q's and that sees a common surface patch: at least min_shared_spots of q's keypoints'
// surface points are in c's image, in front of it and not hidden. An accepted match is false when the query camera's
// pose it gives in the candidate map is off the truth by more than false_translation_m or false_rotation_deg. Recall
// counts the queries that have a true revisit and got a correct match.
#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <string>
#include <vector>

#include "common/core/result.hpp"
#include "common/features/vocabulary.hpp"
#include "server_cloud/recognition/place_recognition.hpp"

namespace cvislam::test {

struct RecognitionEvalOptions {
  std::string preset = "loop";
  std::uint64_t seed = 1;
  double duration_s = 60.0;
  double keyframe_interval_s = 0.5;
  int threads = 2;  // rendering
  // Drift of each agent's map, per square root of metre flown (1 sigma).
  double drift_yaw_deg_per_sqrt_m = 0.3;
  double drift_xy_m_per_sqrt_m = 0.02;
  double drift_z_m_per_sqrt_m = 0.005;
  // Ground truth.
  double max_revisit_distance_m = 1.5;
  double max_revisit_angle_deg = 30.0;
  int min_shared_spots = 50;
  double false_translation_m = 0.5;
  double false_rotation_deg = 5.0;
  server::recognition::RecognitionOptions recognition;
  std::function<void(const std::string&)> progress;
};

struct QueryStats {
  int queries = 0;
  int true_revisits = 0;                    // queries with at least one true revisit
  int with_candidates = 0;                  // queries BoW gave candidates for
  int candidates = 0;                       // candidates verified, all queries
  int candidates_true = 0;                  // of those, true revisits
  int bow_found = 0;                        // queries with a true revisit among their candidates
  int accepted = 0;                         // queries with an accepted match
  int accepted_false = 0;                   // accepted, but the pose is wrong
  int accepted_not_revisit = 0;             // accepted and correct, but beyond the revisit definition
  int found = 0;                            // true revisits with a correct accepted match
  std::vector<double> translation_error_m;  // of the accepted correct matches
  std::vector<double> rotation_error_deg;
  std::vector<double> query_ms;         // candidate search, per query
  std::vector<double> verification_ms;  // per candidate
  std::vector<double> rejections;       // count per Rejection value
};

struct RecognitionEvaluation {
  std::string preset;
  std::uint64_t seed = 0;
  int agents = 0;
  int keyframes = 0;
  QueryStats loop;
  QueryStats match;
  std::vector<double> revisit_scores;    // BoW score of true revisit pairs
  std::vector<double> different_scores;  // BoW score of pairs more than 5 m apart (a sample)
  double render_s = 0.0;
  double recognition_s = 0.0;
  std::size_t database_bytes = 0;
};

Result<RecognitionEvaluation> evaluateRecognition(const RecognitionEvalOptions& options,
                                                  const features::Vocabulary& vocabulary);

}  // namespace cvislam::test
