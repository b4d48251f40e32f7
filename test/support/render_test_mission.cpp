// cvislam_render_test_mission: renders one simulated mission for the tests of a CTest run (a fixture set-up
// test; see test/support/rendered_mission.hpp).
//
//   cvislam_render_test_mission ROOT PRESET SEED DURATION_S stereo|mono THREADS
#include <cstdio>
#include <cstdlib>
#include <string>

#include "test/support/rendered_mission.hpp"

int main(int argc, char** argv) {
  if (argc != 7) {
    std::fprintf(stderr, "usage: %s ROOT PRESET SEED DURATION_S stereo|mono THREADS\n", argv[0]);
    return 2;
  }
  cvislam::test::MissionSpec spec;
  spec.preset = argv[2];
  spec.seed = std::strtoull(argv[3], nullptr, 10);
  spec.duration_s = std::strtod(argv[4], nullptr);
  const std::string camera = argv[5];
  if (camera != "stereo" && camera != "mono") {
    std::fprintf(stderr, "%s: the fifth argument is stereo or mono, not '%s'\n", argv[0], argv[5]);
    return 2;
  }
  spec.stereo = camera == "stereo";
  spec.threads = std::atoi(argv[6]);
  if (const cvislam::Status s = cvislam::test::renderSharedMission(spec, argv[1]); !s.ok()) {
    std::fprintf(stderr, "%s: %s\n", argv[0], s.error().toString().c_str());
    return 1;
  }
  std::printf("rendered %s under %s\n", spec.name().c_str(), argv[1]);
  return 0;
}
