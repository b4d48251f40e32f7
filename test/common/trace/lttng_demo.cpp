// Records what the LTTng test expects (common/trace/lttng_test.sh): ten spans "orb" with their frame, and one
// instant "keyframe_sent", with no trace session of its own, so that only LTTng can see them.
#include "common/trace/trace.hpp"

int main() {
  for (int frame = 0; frame < 10; ++frame) {
    const cvislam::trace::Span span("orb", {{"frame", frame}});
  }
  cvislam::trace::instant("keyframe_sent", {{"keyframe", 7}, {"batch", 3}});
  return 0;
}
