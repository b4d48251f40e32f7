// The agent's check of the server's covisible map (agent_rt/link/anchor_decoder.hpp): a well-formed message is
// decoded field for field; each kind of malformed or hostile message is refused whole, naming what is wrong, and
// leaves nothing behind.
#include "agent_rt/link/anchor_decoder.hpp"

#include <cmath>
#include <functional>
#include <memory>
#include <string>

#include <gtest/gtest.h>

#include "cvislam/v1/agent_link.pb.h"

namespace cvislam::agent {
namespace {

void setPose(v1::Pose* pose, double x) {
  pose->set_px(x);
  pose->set_py(2.0);
  pose->set_pz(-1.0);
  const double half = 0.2;  // 0.4 rad about z
  pose->set_qx(0.0F);
  pose->set_qy(0.0F);
  pose->set_qz(static_cast<float>(std::sin(half)));
  pose->set_qw(static_cast<float>(std::cos(half)));
}

// Two points of agent 2, one keyframe of agent 2 observing both, a pose update and a point update.
v1::CovisibleMap validMap() {
  v1::CovisibleMap m;
  m.set_agent_map(3);
  m.add_selected_agent(2);
  m.add_selected_counter(40);
  for (std::uint32_t c : {7U, 8U}) {
    v1::CovisiblePoint* p = m.add_points();
    p->set_agent(2);
    p->set_counter(c);
    for (float v : {1.0F * c, 2.0F, 5.0F}) p->add_p_w(v);
    for (std::uint64_t w = 0; w < 4; ++w) p->add_orb(0x0102030405060708ULL + w);
    p->set_octave(c - 6);
  }
  v1::CovisibleKeyframe* k = m.add_keyframes();
  k->set_agent(2);
  k->set_counter(40);
  k->set_t_ns(123456789);
  setPose(k->mutable_t_w_c(), 0.5);
  for (std::uint32_t c : {7U, 8U}) {
    k->add_xy(0.1F * static_cast<float>(c));
    k->add_xy(-0.2F);
    k->add_point_agent(2);
    k->add_point_counter(c);
  }
  k->set_octave(std::string("\x01\x02", 2));
  v1::CovisiblePose* u = m.add_keyframe_updates();
  u->set_agent(1);
  u->set_counter(3);
  setPose(u->mutable_t_w_c(), -0.5);
  m.add_point_update_agent(1);
  m.add_point_update_counter(11);
  for (float v : {0.5F, 0.25F, 4.0F}) m.add_point_update_p_w(v);
  return m;
}

TEST(AnchorDecoder, AWellFormedCovisibleMapIsDecodedFieldForField) {
  auto out = std::make_unique<AnchorMessage>();
  const Status s = decodeCovisibleMap(validMap(), 17, *out);

  ASSERT_TRUE(s.ok()) << s.error().toString();
  EXPECT_EQ(out->sequence, 17U);
  EXPECT_EQ(out->agent_map, 3U);
  ASSERT_EQ(out->selected_count, 1U);
  EXPECT_EQ(out->selected[0], (KeyframeId{2, 40}));
  ASSERT_EQ(out->point_count, 2U);
  EXPECT_EQ(out->points[1].id, (MapPointId{2, 8}));
  EXPECT_DOUBLE_EQ(out->points[1].p_w[0], 8.0);
  EXPECT_EQ(out->points[1].octave, 2U);
  EXPECT_EQ(out->points[0].descriptor[0], 0x08U) << "byte 0 is the low byte of word 0";
  ASSERT_EQ(out->keyframe_count, 1U);
  const AnchorKeyframeMsg& kf = out->keyframes[0];
  EXPECT_EQ(kf.id, (KeyframeId{2, 40}));
  EXPECT_EQ(kf.t_ns, 123456789);
  EXPECT_DOUBLE_EQ(kf.T_w_c.p[0], 0.5);
  EXPECT_NEAR(kf.T_w_c.q[2], std::sin(0.2), 1e-6);
  ASSERT_EQ(kf.observation_count, 2U);
  EXPECT_FLOAT_EQ(kf.observations[1].x, 0.8F);
  EXPECT_EQ(kf.observations[1].point, (MapPointId{2, 8}));
  EXPECT_EQ(kf.observations[1].octave, 2U);
  ASSERT_EQ(out->keyframe_update_count, 1U);
  EXPECT_EQ(out->keyframe_updates[0].id, (KeyframeId{1, 3}));
  ASSERT_EQ(out->point_update_count, 1U);
  EXPECT_DOUBLE_EQ(out->point_updates[0].p_w[2], 4.0);
}

struct Hostile {
  const char* name;
  std::function<void(v1::CovisibleMap&)> spoil;
  const char* named;  // what the error must name
};

TEST(AnchorDecoder, EachMalformedOrHostileMessageIsRefusedWholeNamingTheProblem) {
  const float nan = std::nanf("");
  const std::vector<Hostile> cases = {
      {"NaN point position", [&](v1::CovisibleMap& m) { m.mutable_points(1)->set_p_w(2, nan); }, "p_w"},
      {"two-value position", [](v1::CovisibleMap& m) { m.mutable_points(0)->mutable_p_w()->RemoveLast(); }, "p_w"},
      {"short descriptor", [](v1::CovisibleMap& m) { m.mutable_points(0)->mutable_orb()->RemoveLast(); }, "orb"},
      {"octave beyond the pyramid", [](v1::CovisibleMap& m) { m.mutable_points(0)->set_octave(200); }, "octave"},
      {"agent id over 16 bits", [](v1::CovisibleMap& m) { m.mutable_points(0)->set_agent(70000); }, "agent id"},
      {"not a rotation", [](v1::CovisibleMap& m) { m.mutable_keyframes(0)->mutable_t_w_c()->set_qw(3.0F); }, "T_w_c"},
      {"NaN keyframe position", [&](v1::CovisibleMap& m) { m.mutable_keyframes(0)->mutable_t_w_c()->set_px(nan); },
       "T_w_c"},
      {"no keyframe pose", [](v1::CovisibleMap& m) { m.mutable_keyframes(0)->clear_t_w_c(); }, "T_w_c"},
      {"NaN observation", [&](v1::CovisibleMap& m) { m.mutable_keyframes(0)->set_xy(1, nan); }, "observation 0"},
      {"observation behind the camera's view", [](v1::CovisibleMap& m) { m.mutable_keyframes(0)->set_xy(2, 1e6F); },
       "observation 1"},
      {"columns of different lengths", [](v1::CovisibleMap& m) { m.mutable_keyframes(0)->add_point_counter(9); },
       "differ in length"},
      {"observation octave beyond the pyramid",
       [](v1::CovisibleMap& m) { m.mutable_keyframes(0)->set_octave(std::string("\x01\x28", 2)); }, "octave"},
      {"selection columns of different lengths", [](v1::CovisibleMap& m) { m.add_selected_agent(1); },
       "selected_agent"},
      {"over the keyframe capacity",
       [](v1::CovisibleMap& m) {
         for (std::size_t i = 0; i < kMaxAnchorKeyframesPerMessage; ++i) *m.add_keyframes() = m.keyframes(0);
       },
       "capacity"},
      {"over the point capacity",
       [](v1::CovisibleMap& m) {
         for (std::size_t i = 0; i < kMaxAnchorPointsPerMessage; ++i) *m.add_points() = m.points(0);
       },
       "capacity"},
      {"point update of two values", [](v1::CovisibleMap& m) { m.mutable_point_update_p_w()->RemoveLast(); },
       "point_update"},
      {"NaN point update", [&](v1::CovisibleMap& m) { m.set_point_update_p_w(0, nan); }, "point update 0"},
      {"keyframe update that is not a rotation",
       [](v1::CovisibleMap& m) { m.mutable_keyframe_updates(0)->mutable_t_w_c()->set_qx(0.9F); }, "keyframe update"},
  };
  auto out = std::make_unique<AnchorMessage>();
  for (const Hostile& c : cases) {
    v1::CovisibleMap m = validMap();
    c.spoil(m);
    const Status s = decodeCovisibleMap(m, 5, *out);
    ASSERT_FALSE(s.ok()) << c.name << " was accepted";
    EXPECT_NE(s.error().message().find(c.named), std::string::npos) << c.name << ": " << s.error().message();
    EXPECT_EQ(out->keyframe_count + out->point_count + out->selected_count + out->keyframe_update_count +
                  out->point_update_count,
              0U)
        << c.name << " left something behind";
    // The next good message is taken as if nothing had happened.
    ASSERT_TRUE(decodeCovisibleMap(validMap(), 6, *out).ok()) << "after " << c.name;
    EXPECT_EQ(out->point_count, 2U);
  }
}

}  // namespace
}  // namespace cvislam::agent
