// bench_recognition_eval: precision and recall of place recognition (loop detection and map matching) on the
// simulator's missions against ground truth, per preset, with the transform errors and BoW scores; see
// test/server_cloud/recognition/recognition_eval.hpp for the protocol. SIMULATED figures.
//
//   bench_recognition_eval [--preset loop,overlap2,hall4,hall8,euroc-mh] [--seed 1] [--duration 60]
//                          [--vocabulary FILE] [--json OUT]
#include <cstdio>
#include <fstream>
#include <iostream>
#include <sstream>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include "common/features/vocabulary.hpp"
#include "test/bench/percentiles.hpp"
#include "test/server_cloud/recognition/recognition_eval.hpp"

namespace {

using cvislam::test::QueryStats;
using cvislam::test::RecognitionEvaluation;

double pct(const std::vector<double>& v, double p) {
  return cvislam::bench::percentile(v, p);
}

nlohmann::json toJson(const QueryStats& s) {
  nlohmann::json j;
  j["queries"] = s.queries;
  j["true_revisits"] = s.true_revisits;
  j["queries_with_candidates"] = s.with_candidates;
  j["candidates_verified"] = s.candidates;
  j["candidates_true"] = s.candidates_true;
  j["queries_bow_found_true"] = s.bow_found;
  j["accepted"] = s.accepted;
  j["accepted_false"] = s.accepted_false;
  j["accepted_correct_beyond_definition"] = s.accepted_not_revisit;
  j["found"] = s.found;
  j["recall"] = s.true_revisits > 0 ? static_cast<double>(s.found) / s.true_revisits : 0.0;
  j["precision"] = s.accepted > 0 ? 1.0 - static_cast<double>(s.accepted_false) / s.accepted : 1.0;
  j["translation_error_m"] = {{"p50", pct(s.translation_error_m, 0.5)},
                              {"p99", pct(s.translation_error_m, 0.99)},
                              {"max", pct(s.translation_error_m, 1.0)}};
  j["rotation_error_deg"] = {{"p50", pct(s.rotation_error_deg, 0.5)},
                             {"p99", pct(s.rotation_error_deg, 0.99)},
                             {"max", pct(s.rotation_error_deg, 1.0)}};
  j["candidate_search_ms"] = {{"p50", pct(s.query_ms, 0.5)}, {"p99", pct(s.query_ms, 0.99)}};
  j["verification_ms_per_candidate"] = {{"p50", pct(s.verification_ms, 0.5)}, {"p99", pct(s.verification_ms, 0.99)}};
  nlohmann::json rejections;
  for (std::size_t r = 0; r < s.rejections.size(); ++r) {
    rejections[std::string(cvislam::server::recognition::toString(
        static_cast<cvislam::server::recognition::Rejection>(r)))] = s.rejections[r];
  }
  j["verifications"] = rejections;
  return j;
}

void printRow(const char* kind, const RecognitionEvaluation& e, const QueryStats& s) {
  std::printf("%-9s %-5s %7d %8d %9d %8d %8d %6d %7d %6.1f%% %8.3f %8.3f %6.2f %6.2f\n", e.preset.c_str(), kind,
              s.queries, s.true_revisits, s.candidates, s.bow_found, s.accepted, s.accepted_false, s.found,
              s.true_revisits > 0 ? 100.0 * s.found / s.true_revisits : 0.0, pct(s.translation_error_m, 0.5),
              pct(s.translation_error_m, 1.0), pct(s.rotation_error_deg, 0.5), pct(s.rotation_error_deg, 1.0));
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "Place recognition on the simulator's missions: true revisits (ground truth), BoW candidates, "
      "verified matches and false ones, per preset. Figures are SIMULATED."};
  std::vector<std::string> presets{"loop", "overlap2", "hall4", "hall8", "euroc-mh"};
  std::uint64_t seed = 1;
  double duration_s = 60.0;
  double interval_s = 0.5;
  int threads = 2;
  std::string vocabulary_path = CVISLAM_VOCABULARY_FILE;
  std::string json_path;
  app.add_option("--preset", presets, "presets to run (comma-separated)")->delimiter(',');
  app.add_option("--seed", seed, "simulator seed (world, trajectories, drift)")->capture_default_str();
  app.add_option("--duration", duration_s, "seconds of flight per agent")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  app.add_option("--keyframe-interval", interval_s, "seconds between keyframes")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  app.add_option("--threads", threads, "rendering threads")->capture_default_str()->check(CLI::Range(1, 64));
  app.add_option("--vocabulary", vocabulary_path, "vocabulary file")->capture_default_str();
  app.add_option("--json", json_path, "write every figure as JSON here");
  CLI11_PARSE(app, argc, argv);

  auto vocabulary = cvislam::features::Vocabulary::load(vocabulary_path);
  if (!vocabulary) {
    std::cerr << "error: " << vocabulary.error().message() << "\n";
    return 1;
  }
  nlohmann::json all = nlohmann::json::array();
  std::vector<RecognitionEvaluation> results;
  for (const std::string& preset : presets) {
    cvislam::test::RecognitionEvalOptions options;
    options.preset = preset;
    options.seed = seed;
    options.duration_s = duration_s;
    options.keyframe_interval_s = interval_s;
    options.threads = threads;
    options.progress = [](const std::string& line) { std::cerr << line << "\n"; };
    auto e = cvislam::test::evaluateRecognition(options, *vocabulary);
    if (!e) {
      std::cerr << "error: " << preset << ": " << e.error().message() << "\n";
      return 1;
    }
    results.push_back(*e);
    nlohmann::json j;
    j["preset"] = preset;
    j["seed"] = seed;
    j["simulated"] = true;
    j["duration_s"] = duration_s;
    j["keyframe_interval_s"] = interval_s;
    j["agents"] = e->agents;
    j["keyframes"] = e->keyframes;
    j["loop"] = toJson(e->loop);
    j["map_match"] = toJson(e->match);
    j["bow_score_true_revisit"] = {
        {"p50", pct(e->revisit_scores, 0.5)}, {"p10", pct(e->revisit_scores, 0.1)}, {"n", e->revisit_scores.size()}};
    j["bow_score_far_apart"] = {{"p50", pct(e->different_scores, 0.5)},
                                {"p90", pct(e->different_scores, 0.9)},
                                {"p99", pct(e->different_scores, 0.99)},
                                {"n", e->different_scores.size()}};
    j["database_bytes_per_keyframe"] = e->keyframes > 0 ? static_cast<double>(e->database_bytes) / e->keyframes : 0.0;
    j["render_s"] = e->render_s;
    j["recognition_s"] = e->recognition_s;
    all.push_back(j);
  }

  std::printf(
      "== place recognition, SIMULATED (seed %llu, %.0f s per agent, a keyframe every %.2f s); "
      "trans/rot: error of the accepted correct matches, p50 and max\n",
      static_cast<unsigned long long>(seed), duration_s, interval_s);
  std::printf("%-9s %-5s %7s %8s %9s %8s %8s %6s %7s %7s %8s %8s %6s %6s\n", "preset", "kind", "queries", "revisits",
              "cands", "bow-true", "accepted", "false", "found", "recall", "t50[m]", "tmax[m]", "r50[d]", "rmax[d]");
  for (const RecognitionEvaluation& e : results) {
    printRow("loop", e, e.loop);
    printRow("match", e, e.match);
  }
  std::printf("\n%-9s %10s %10s %10s %10s %12s %14s\n", "preset", "KFs", "revisit50", "far50", "far99", "DB B/KF",
              "verify p50[ms]");
  for (const RecognitionEvaluation& e : results) {
    std::vector<double> verify = e.loop.verification_ms;
    verify.insert(verify.end(), e.match.verification_ms.begin(), e.match.verification_ms.end());
    std::printf("%-9s %10d %10.3f %10.3f %10.3f %12.0f %14.2f\n", e.preset.c_str(), e.keyframes,
                pct(e.revisit_scores, 0.5), pct(e.different_scores, 0.5), pct(e.different_scores, 0.99),
                e.keyframes > 0 ? static_cast<double>(e.database_bytes) / e.keyframes : 0.0, pct(verify, 0.5));
  }
  if (!json_path.empty()) {
    std::ofstream(json_path) << all.dump(2) << "\n";
    std::cerr << "wrote " << json_path << "\n";
  }
  return 0;
}
