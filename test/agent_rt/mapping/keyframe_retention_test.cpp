// keyframeToEvict: the newest keyframes always stay, the oldest goes while age is all there is to go by, and
// beyond that the keyframe whose place an older one covers goes, the newer of two at one place.
#include "agent_rt/mapping/keyframe_retention.hpp"

#include <memory>
#include <vector>

#include <gtest/gtest.h>

namespace cvislam::agent {
namespace {

using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;

class KeyframeRetentionTest : public ::testing::Test {
 protected:
  KeyframeRetentionTest() : map_(std::make_unique<LocalMap>(SE3d())) {}

  // A keyframe whose camera (here the body's frame) is at p_w, turned by turn_rad about the world y axis: its
  // optical axis, z, turns with it.
  PoolHandle add(const Vector3d& p_w, double turn_rad = 0.0) {
    auto kf = std::make_unique<KeyframeData>();
    kf->id = ids_.next();
    kf->T_w_s = SE3d(SO3d::exp(Vector3d(0.0, turn_rad, 0.0)), p_w);
    auto handle = map_->insertKeyframe(*kf);
    EXPECT_TRUE(handle.ok());
    own_.push_back(*handle);
    return *handle;
  }

  std::unique_ptr<LocalMap> map_;
  std::vector<PoolHandle> own_;  // oldest first
  IdCounter<KeyframeId> ids_{0};
};

TEST_F(KeyframeRetentionTest, WithoutPlaceKeyframesTheOldestGoes) {
  for (int i = 0; i < 6; ++i) add(Vector3d(0.1 * i, 0.0, 0.0));
  const auto evict = keyframeToEvict(*map_, own_, 5, KeyframeRetentionOptions{});
  ASSERT_TRUE(evict.has_value());
  EXPECT_EQ(*evict, own_.front());
}

TEST_F(KeyframeRetentionTest, TheNewerOfTwoKeyframesAtOnePlaceGoesAndTheNewestStay) {
  // Older than the newest three: keyframes at x = 0, 5, 10 m and one back at x = 5.02 m (a second visit).
  add(Vector3d(0.0, 0.0, 0.0));
  const PoolHandle first_visit = add(Vector3d(5.0, 0.0, 0.0));
  add(Vector3d(10.0, 0.0, 0.0));
  const PoolHandle second_visit = add(Vector3d(5.02, 0.0, 0.0));
  // The newest three, all at one place: they stay whatever their places.
  for (int i = 0; i < 3; ++i) add(Vector3d(20.0, 0.0, 0.0));
  KeyframeRetentionOptions options;
  options.place_keyframes = 4;
  const auto evict = keyframeToEvict(*map_, own_, 3, options);
  ASSERT_TRUE(evict.has_value());
  EXPECT_EQ(*evict, second_visit);
  EXPECT_NE(*evict, first_visit);
}

TEST_F(KeyframeRetentionTest, AViewOfThePlaceFromAnotherDirectionIsAPlaceOfItsOwn) {
  add(Vector3d(0.0, 0.0, 0.0));
  add(Vector3d(3.0, 0.0, 0.0));
  const PoolHandle near_but_turned = add(Vector3d(0.0, 0.0, 0.0), 3.0);  // the same spot, looking back
  const PoolHandle one_metre_on = add(Vector3d(4.0, 0.0, 0.0));          // 1 m from the one at x = 3, same view
  add(Vector3d(50.0, 0.0, 0.0));
  KeyframeRetentionOptions options;
  options.place_keyframes = 4;
  options.angle_weight_m = 1.0;  // 3 rad apart: as far as 3 m
  const auto evict = keyframeToEvict(*map_, own_, 1, options);
  ASSERT_TRUE(evict.has_value());
  EXPECT_EQ(*evict, one_metre_on);
  // Without the viewing direction the turned keyframe is the one at the other's place.
  options.angle_weight_m = 0.0;
  EXPECT_EQ(*keyframeToEvict(*map_, own_, 1, options), near_but_turned);
}

TEST_F(KeyframeRetentionTest, TheOldestStaysWhenAnotherCanGo) {
  // No older keyframe covers the oldest: the one 10 m from it goes, although no keyframe covers that one either.
  add(Vector3d(0.0, 0.0, 0.0));
  add(Vector3d(10.0, 0.0, 0.0));
  add(Vector3d(10.0, 0.0, 0.0));  // the newest: stays
  KeyframeRetentionOptions options;
  options.place_keyframes = 2;
  const auto evict = keyframeToEvict(*map_, own_, 1, options);
  ASSERT_TRUE(evict.has_value());
  EXPECT_EQ(*evict, own_[1]);
}

TEST_F(KeyframeRetentionTest, OfTwoEquallyCoveredKeyframesTheNewerGoes) {
  add(Vector3d(0.0, 0.0, 0.0));
  add(Vector3d(1.0, 0.0, 0.0));  // 1 m from the first
  add(Vector3d(10.0, 0.0, 0.0));
  const PoolHandle newer = add(Vector3d(11.0, 0.0, 0.0));  // 1 m from the one before
  add(Vector3d(30.0, 0.0, 0.0));
  KeyframeRetentionOptions options;
  options.place_keyframes = 4;
  EXPECT_EQ(*keyframeToEvict(*map_, own_, 1, options), newer);
}

TEST_F(KeyframeRetentionTest, EmptyWhenThereIsNoOwnKeyframe) {
  EXPECT_FALSE(keyframeToEvict(*map_, own_, 3, KeyframeRetentionOptions{}).has_value());
}

TEST(KeyframeRetentionOptions, NamesBadValues) {
  KeyframeRetentionOptions options;
  EXPECT_TRUE(options.validate().ok());
  options.place_keyframes = -1;
  EXPECT_NE(options.validate().error().message().find("place_keyframes"), std::string::npos);
  options = {};
  options.angle_weight_m = -0.5;
  EXPECT_NE(options.validate().error().message().find("place_angle_weight_m"), std::string::npos);
}

}  // namespace
}  // namespace cvislam::agent
