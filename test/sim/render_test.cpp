// Reprojection: a surface point the renderer drew at a pixel, projected with the written ground truth and the
// written camera model, lands on that pixel (within 0.1 px); the written image is what the renderer drew.
#include "test/sim/renderer.hpp"

#include <gtest/gtest.h>

#include "common/dataset/euroc.hpp"
#include "test/sim/mission_writer.hpp"
#include "test/sim/presets.hpp"
#include "test/sim/random.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::sim {
namespace {

constexpr double kMaxReprojectionErrorPx = 0.1;

// Interpolates the 200 Hz ground truth at a camera timestamp (it is written at the same stamps).
const dataset::GroundTruthState& groundTruthAt(const dataset::EurocSequence& seq, std::int64_t t_ns) {
  for (const dataset::GroundTruthState& s : seq.groundTruth()) {
    if (s.t_ns == t_ns) return s;
  }
  ADD_FAILURE() << "no ground truth at " << t_ns;
  return seq.groundTruth().front();
}

TEST(Renderer, DrawnSurfacePointsReprojectOntoTheirPixelsWithTheWrittenGroundTruth) {
  const test::TempDir dir;
  MissionPlanOptions plan_options;
  plan_options.preset = "overlap2";
  plan_options.seed = 5;
  plan_options.duration_s = 1.0;
  auto plan = planMission(plan_options);
  ASSERT_TRUE(plan.ok()) << plan.error().toString();
  MissionWriterOptions options = defaultWriterOptions();
  options.out_dir = dir.path();
  options.seed = plan_options.seed;
  options.stereo = true;
  ASSERT_TRUE(writeMission(*plan, options).ok());

  WorldOptions world_options;
  world_options.seed = plan_options.seed;
  const World world(plan->layout, world_options);
  Rng rng(17);
  for (const AgentPlan& agent : plan->agents) {
    auto seq = dataset::EurocSequence::open(dir / agent.name);
    ASSERT_TRUE(seq.ok()) << seq.error().toString();
    for (int cam = 0; cam < 2; ++cam) {
      const dataset::CameraStream& stream = seq->camera(cam);
      auto written_model = camera::CameraModel::create(stream.calibration);
      ASSERT_TRUE(written_model.ok());
      const Renderer sut(*written_model);
      for (std::size_t frame = 0; frame < stream.frames.size(); frame += 7) {
        const dataset::GroundTruthState& gt = groundTruthAt(*seq, stream.frames[frame].t_ns);
        const geometry::SE3d T_w_c = gt.T_w_b * stream.calibration.T_b_c;
        auto image = seq->loadImage(cam, frame);
        ASSERT_TRUE(image.ok());
        // The written image is what the renderer draws from the written pose (nothing else changes pixels).
        dataset::GrayImage redrawn;
        sut.render(world, T_w_c, 1.0, redrawn);
        EXPECT_EQ(redrawn.pixels, image->pixels) << agent.name << " cam" << cam << " frame " << frame;
        double worst_px = 0.0;
        for (int i = 0; i < 300; ++i) {
          const int x = static_cast<int>(rng.index(static_cast<std::uint64_t>(sut.camera().width())));
          const int y = static_cast<int>(rng.index(static_cast<std::uint64_t>(sut.camera().height())));
          const RayHit hit = sut.castPixel(world, T_w_c, x, y);
          ASSERT_GE(hit.face, 0);
          // The point lies on the surface it was drawn from ...
          const int axis = (hit.face % 6) / 2;
          const Box& box = hit.face / 6 == 0 ? plan->layout.hall
                                             : plan->layout.obstacles[static_cast<std::size_t>(hit.face / 6 - 1)];
          EXPECT_NEAR(hit.p_w(axis), hit.face % 2 == 1 ? box.max_w(axis) : box.min_w(axis), 1e-9);
          // ... and the camera model projects it back onto the pixel.
          const auto projected = written_model->project(T_w_c.inverse() * hit.p_w);
          ASSERT_TRUE(projected.has_value());
          worst_px = std::max(worst_px, (*projected - Eigen::Vector2d(x, y)).norm());
        }
        EXPECT_LT(worst_px, kMaxReprojectionErrorPx) << agent.name << " cam" << cam << " frame " << frame;
      }
    }
  }
}

TEST(World, AxisParallelRaysHitTheRightWallsAndObstacles) {
  WorldLayout layout;
  layout.hall.min_w = Eigen::Vector3d(-10, -5, 0);
  layout.hall.max_w = Eigen::Vector3d(10, 5, 6);
  Box crate;
  crate.min_w = Eigen::Vector3d(2.0, -1.0, 0.0);
  crate.max_w = Eigen::Vector3d(3.0, 1.0, 2.0);
  layout.obstacles.push_back(crate);
  WorldOptions options;
  options.texture.texel_size_m = 0.1;
  const World sut(layout, options);
  const Eigen::Vector3d o(0.0, 0.0, 1.0);
  // Exactly axis-parallel rays have zero direction components (infinite inverse) on two axes.
  const RayHit east = sut.cast(o, Eigen::Vector3d::UnitX());
  EXPECT_DOUBLE_EQ(east.t_m, 2.0);
  EXPECT_EQ(east.face, 6 + 0);  // obstacle 0, x axis, min face
  const RayHit west = sut.cast(o, -Eigen::Vector3d::UnitX());
  EXPECT_DOUBLE_EQ(west.t_m, 10.0);
  EXPECT_EQ(west.face, 0);  // hall, x axis, min face
  const RayHit up = sut.cast(o, Eigen::Vector3d::UnitZ());
  EXPECT_DOUBLE_EQ(up.t_m, 5.0);
  EXPECT_EQ(up.face, 5);  // hall ceiling
  const RayHit north = sut.cast(o, Eigen::Vector3d::UnitY());
  EXPECT_DOUBLE_EQ(north.t_m, 5.0);
  EXPECT_EQ(north.face, 3);
  EXPECT_NEAR(sut.clearance(o), 1.0, 1e-12);  // the floor is 1 m below
}

TEST(Renderer, AKnownPointOnABoxCornerProjectsToWhereTheBoxSilhouetteIs) {
  // A lone crate in front of the camera: its near top corner projects to a pixel; the pixels just inside
  // the corner show the crate, the pixels just outside show the wall behind.
  WorldLayout layout;
  layout.hall.min_w = Eigen::Vector3d(-10, -10, 0);
  layout.hall.max_w = Eigen::Vector3d(10, 10, 6);
  layout.hall.kind = "hall";
  Box crate;
  crate.min_w = Eigen::Vector3d(3.0, -0.5, 0.0);
  crate.max_w = Eigen::Vector3d(4.0, 0.5, 1.0);
  layout.obstacles.push_back(crate);
  WorldOptions world_options;
  world_options.texture.texel_size_m = 0.05;
  const World world(layout, world_options);
  auto model = camera::CameraModel::create(dataset::eurocCam0());
  ASSERT_TRUE(model.ok());
  const Renderer sut(*model);
  // Camera at 1.5 m height looking along +x (camera z = world x, camera x = world -y, camera y = world -z).
  Eigen::Matrix3d R_w_c;
  R_w_c << 0, 0, 1, -1, 0, 0, 0, -1, 0;
  const geometry::SE3d T_w_c(geometry::SO3d(R_w_c), Eigen::Vector3d(0.2, 0.3, 1.5));
  const Eigen::Vector3d corner_w(3.0, 0.5, 1.0);  // near, left, top
  const auto corner_px = model->project(T_w_c.inverse() * corner_w);
  ASSERT_TRUE(corner_px.has_value());
  const int cx = static_cast<int>(std::lround(corner_px->x())), cy = static_cast<int>(std::lround(corner_px->y()));
  constexpr int kOffset = 2;
  const int crate_face = 6 * 1 + 2 * 0 + 0;  // obstacle 0, x axis, min side
  EXPECT_EQ(sut.castPixel(world, T_w_c, cx + kOffset, cy + kOffset).face, crate_face);
  EXPECT_NE(sut.castPixel(world, T_w_c, cx - kOffset, cy - kOffset).face, crate_face);
  EXPECT_NE(sut.castPixel(world, T_w_c, cx + kOffset, cy - kOffset).face, crate_face);
  EXPECT_NE(sut.castPixel(world, T_w_c, cx - kOffset, cy + kOffset).face, crate_face);
}

}  // namespace
}  // namespace cvislam::sim
