// Simulated missions for tests, rendered once per CTest run and shared by every test that reads them.
//
// Rendering a mission costs far more than most tests that read it (a 20 s stereo sequence takes about a minute
// on one core), and CTest runs each test case in its own process, so a suite that rendered in its set-up did so
// once per case. CTest now renders each shared mission once, in a fixture set-up test
// (cvislam_render_test_mission), and gives the tests that declare it the folder in CVISLAM_TEST_MISSIONS. Run
// directly (no CVISLAM_TEST_MISSIONS), a test renders into its own folder as before. Tests must treat a shared
// mission as read-only: copy (or hard-link and replace) what they change.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>

#include "common/core/result.hpp"

namespace cvislam::test {

struct MissionSpec {
  std::string preset;
  std::uint64_t seed = 0;
  double duration_s = 0.0;
  bool stereo = false;
  int threads = 1;  // agents rendered at once (the files do not depend on it)

  // Folder name, e.g. "loop-seed5-20s-stereo".
  [[nodiscard]] std::string name() const;
};

// The mission's folder (agents in agentN/): the shared one under $CVISLAM_TEST_MISSIONS, rendered now if it is
// not there yet (under a file lock, so that concurrent tests render it once), else rendered into `private_dir`.
Result<std::filesystem::path> renderedMission(const MissionSpec& spec, const std::filesystem::path& private_dir);

// Renders the mission under `root` afresh, replacing what a previous run left (the set-up test's job, so that a
// changed simulator is never read from an old rendering).
Status renderSharedMission(const MissionSpec& spec, const std::filesystem::path& root);

// A copy of the folder tree with its files hard-linked where the file system allows, copied where it does not.
// Replace a file in the copy (remove, then write) rather than write through it.
void linkedCopy(const std::filesystem::path& source, const std::filesystem::path& target);

}  // namespace cvislam::test
