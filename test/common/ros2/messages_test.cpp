// sensor_msgs Image and Imu in CDR: round trips, the byte layout that the npm reference serializer
// (@foxglove/rosmsg2-serialization's MessageWriter) gives the same messages (sizes, padding, the first bytes of an
// EuRoC frame), and hostile lengths, truncations and encapsulations.
#include "common/ros2/messages.hpp"

#include <cstring>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "common/ros2/cdr.hpp"

namespace cvislam::ros2 {
namespace {

using Bytes = std::vector<std::uint8_t>;

// EuRoC V1_01's first camera frame stamp.
constexpr std::int64_t kStampNs = 1403715273262142976;

ImageView euroCFrame(const Bytes& pixels, std::string_view frame_id = "cam0") {
  ImageView image;
  image.header = {timeFromNanoseconds(kStampNs).value(), frame_id};
  image.height = 480;
  image.width = 752;
  image.encoding = "mono8";
  image.step = 752;
  image.data = pixels;
  return image;
}

ImuView imuSample(std::string_view frame_id = "imu0") {
  ImuView imu;
  imu.header = {timeFromNanoseconds(kStampNs).value(), frame_id};
  imu.orientation_covariance[0] = -1;
  imu.angular_velocity_rad_s = {0.1, 0.2, 0.3};
  imu.linear_acceleration_m_s2 = {9.1, 0.1, -3.7};
  for (int i = 0; i < 9; ++i) imu.angular_velocity_covariance[i] = i * 0.5;
  imu.linear_acceleration_covariance[8] = 4e-4;
  return imu;
}

TEST(Image, EncodesAnEurocFrameAsTheReferenceSerializerDoes) {
  const Bytes pixels(std::size_t{752} * 480, 0x5a);
  Bytes cdr;

  ASSERT_TRUE(encodeImage(euroCFrame(pixels), cdr).ok());

  EXPECT_EQ(cdr.size(), 361012U);  // 4 + 48 + 360960
  const Bytes expected_start = {0x00, 0x01, 0x00, 0x00, 0xc9, 0xfe, 0xaa, 0x53, 0x00, 0xfc, 0x9f, 0x0f, 0x05, 0x00,
                                0x00, 0x00, 'c',  'a',  'm',  '0',  0x00, 0x00, 0x00, 0x00, 0xe0, 0x01, 0x00, 0x00,
                                0xf0, 0x02, 0x00, 0x00, 0x06, 0x00, 0x00, 0x00, 'm',  'o',  'n',  'o',  '8',  0x00,
                                0x00, 0x00, 0xf0, 0x02, 0x00, 0x00, 0x00, 0x82, 0x05, 0x00, 0x5a};
  EXPECT_EQ(Bytes(cdr.begin(), cdr.begin() + static_cast<std::ptrdiff_t>(expected_start.size())), expected_start);
}

TEST(Image, RoundTripsEveryField) {
  Bytes pixels(std::size_t{6} * 4 * 3);  // 6x4 rgb8
  for (std::size_t i = 0; i < pixels.size(); ++i) pixels[i] = static_cast<std::uint8_t>(i * 3);
  ImageView image;
  image.header = {{-5, 999'999'999}, "cam0_optical"};
  image.height = 4;
  image.width = 6;
  image.encoding = "rgb8";
  image.is_bigendian = 1;
  image.step = 18;
  image.data = pixels;
  Bytes cdr;
  ASSERT_TRUE(encodeImage(image, cdr).ok());

  auto sut = decodeImage(cdr);

  ASSERT_TRUE(sut.ok()) << sut.error().message();
  EXPECT_EQ(sut->header.stamp, image.header.stamp);
  EXPECT_EQ(sut->header.frame_id, "cam0_optical");
  EXPECT_EQ(sut->height, 4U);
  EXPECT_EQ(sut->width, 6U);
  EXPECT_EQ(sut->encoding, "rgb8");
  EXPECT_EQ(sut->is_bigendian, 1);
  EXPECT_EQ(sut->step, 18U);
  EXPECT_EQ(Bytes(sut->data.begin(), sut->data.end()), pixels);
  EXPECT_TRUE(checkImageLayout(sut.value()).ok());
  // A 13-byte frame_id (with its NUL) leaves 3 bytes of padding before height.
  EXPECT_EQ(cdr[4 + 8 + 4 + 13], 0);
  std::uint32_t height = 0;
  std::memcpy(&height, cdr.data() + 4 + 8 + 4 + 13 + 3, 4);
  EXPECT_EQ(height, 4U);
}

TEST(Imu, HasTheReferenceSizesAndAlignment) {
  Bytes imu0;
  Bytes imu;

  ASSERT_TRUE(encodeImu(imuSample("imu0"), imu0).ok());
  ASSERT_TRUE(encodeImu(imuSample("imu"), imu).ok());

  EXPECT_EQ(imu0.size(), 324U);
  EXPECT_EQ(imu.size(), 316U);
  // The first float64 (orientation.x) is 8-aligned counted after the header: file offset 28.
  double x = -1;
  std::memcpy(&x, imu0.data() + 28, 8);
  EXPECT_EQ(x, 0.0);
  double w = 0;
  std::memcpy(&w, imu0.data() + 28 + 24, 8);
  EXPECT_EQ(w, 1.0);
}

TEST(Imu, RoundTripsEveryField) {
  const ImuView imu = imuSample();
  Bytes cdr;
  ASSERT_TRUE(encodeImu(imu, cdr).ok());

  auto sut = decodeImu(cdr);

  ASSERT_TRUE(sut.ok()) << sut.error().message();
  EXPECT_EQ(sut->header.frame_id, "imu0");
  EXPECT_EQ(toNanoseconds(sut->header.stamp), kStampNs);
  EXPECT_EQ(sut->orientation.w, 1.0);
  EXPECT_EQ(sut->orientation_covariance, imu.orientation_covariance);
  EXPECT_EQ(sut->angular_velocity_rad_s.z, 0.3);
  EXPECT_EQ(sut->angular_velocity_covariance, imu.angular_velocity_covariance);
  EXPECT_EQ(sut->linear_acceleration_m_s2.x, 9.1);
  EXPECT_EQ(sut->linear_acceleration_m_s2.z, -3.7);
  EXPECT_EQ(sut->linear_acceleration_covariance, imu.linear_acceleration_covariance);
}

TEST(Cdr, EveryTruncationIsAnErrorNamingAField) {
  Bytes image_cdr;
  const Bytes pixels(40, 7);
  ImageView image = euroCFrame(pixels);
  image.height = 5;
  image.width = 8;
  image.step = 8;
  ASSERT_TRUE(encodeImage(image, image_cdr).ok());
  Bytes imu_cdr;
  ASSERT_TRUE(encodeImu(imuSample(), imu_cdr).ok());

  for (std::size_t n = 0; n < image_cdr.size(); ++n) {
    const auto r = decodeImage(std::span(image_cdr).first(n));
    ASSERT_FALSE(r.ok()) << "an Image cut to " << n << " bytes decoded";
    EXPECT_NE(r.error().message().find("sensor_msgs/msg/Image"), std::string::npos) << r.error().message();
  }
  for (std::size_t n = 0; n < imu_cdr.size(); ++n) {
    const auto r = decodeImu(std::span(imu_cdr).first(n));
    ASSERT_FALSE(r.ok()) << "an Imu cut to " << n << " bytes decoded";
  }
}

TEST(Cdr, AStringLengthPastTheBufferIsAnError) {
  Bytes cdr;
  ASSERT_TRUE(encodeImu(imuSample(), cdr).ok());
  cdr[12] = cdr[13] = cdr[14] = cdr[15] = 0xFF;  // frame_id's length: 4 GiB

  const auto sut = decodeImu(cdr);

  ASSERT_FALSE(sut.ok());
  EXPECT_NE(sut.error().message().find("field 'header.frame_id' needs 4294967295 bytes at byte 16"), std::string::npos)
      << sut.error().message();
}

TEST(Cdr, AnImageDataCountPastTheBufferIsAnError) {
  const Bytes pixels(16, 1);
  ImageView image = euroCFrame(pixels);
  Bytes cdr;
  ASSERT_TRUE(encodeImage(image, cdr).ok());
  const std::size_t count_at = cdr.size() - pixels.size() - 4;
  cdr[count_at] = 17;

  const auto sut = decodeImage(cdr);

  ASSERT_FALSE(sut.ok());
  EXPECT_NE(sut.error().message().find("field 'data'"), std::string::npos) << sut.error().message();
}

TEST(Cdr, AStringWithoutItsNulIsAnError) {
  Bytes cdr;
  ASSERT_TRUE(encodeImu(imuSample(), cdr).ok());
  cdr[16 + 4] = 'x';  // the NUL after "imu0"

  const auto sut = decodeImu(cdr);

  ASSERT_FALSE(sut.ok());
  EXPECT_NE(sut.error().message().find("does not end with a NUL"), std::string::npos) << sut.error().message();
}

TEST(Cdr, OtherEncapsulationsAreRefusedByName) {
  Bytes cdr;
  ASSERT_TRUE(encodeImu(imuSample(), cdr).ok());

  cdr[1] = 0x00;
  EXPECT_NE(decodeImu(cdr).error().message().find("big-endian CDR"), std::string::npos);
  cdr[1] = 0x03;
  EXPECT_NE(decodeImu(cdr).error().message().find("PL_CDR"), std::string::npos);
  cdr[1] = 0x07;
  EXPECT_NE(decodeImu(cdr).error().message().find("encapsulation 00 07"), std::string::npos);
  EXPECT_FALSE(decodeImu({}).ok());
}

TEST(Cdr, PaddingUpToThreeBytesAfterTheMessageIsAcceptedButNotMore) {
  Bytes cdr;
  ASSERT_TRUE(encodeImu(imuSample(), cdr).ok());

  cdr.resize(cdr.size() + 3, 0);
  EXPECT_TRUE(decodeImu(cdr).ok());
  cdr.push_back(0);
  const auto sut = decodeImu(cdr);
  ASSERT_FALSE(sut.ok());
  EXPECT_NE(sut.error().message().find("4 bytes follow the last field"), std::string::npos);
}

TEST(Cdr, AnEmptyStringDecodesWithOrWithoutItsNul) {
  // Ours writes "" as length 1 and the NUL; a bare length 0 is accepted too.
  Bytes with_nul;
  ASSERT_TRUE(encodeImu(imuSample(""), with_nul).ok());
  EXPECT_EQ(with_nul[12], 1);
  Bytes bare;
  CdrWriter w(bare);
  w.primitive(std::int32_t{1});
  w.primitive(std::uint32_t{2});
  w.primitive(std::uint32_t{0});  // frame_id: no bytes at all
  for (int i = 0; i < 4 + 9 + 3 + 9 + 3 + 9; ++i) w.primitive(0.0);

  const auto a = decodeImu(with_nul);
  const auto b = decodeImu(bare);

  ASSERT_TRUE(a.ok()) << a.error().message();
  ASSERT_TRUE(b.ok()) << b.error().message();
  EXPECT_EQ(a->header.frame_id, "");
  EXPECT_EQ(b->header.frame_id, "");
  EXPECT_EQ(b->header.stamp.nanosec, 2U);
}

TEST(Time, ConvertsNanosecondsBothWays) {
  EXPECT_EQ(timeFromNanoseconds(kStampNs).value(), (Time{1403715273, 262142976}));
  EXPECT_EQ(toNanoseconds(Time{1403715273, 262142976}), kStampNs);
  // Before the epoch, nanoseconds stay in [0, 1e9).
  EXPECT_EQ(timeFromNanoseconds(-1).value(), (Time{-1, 999'999'999}));
  EXPECT_EQ(toNanoseconds(Time{-1, 999'999'999}), -1);
  // int32 seconds end in January 2038.
  EXPECT_FALSE(timeFromNanoseconds(std::int64_t{1} << 62).ok());
}

TEST(Image, LayoutCheckCatchesDataAndStepThatDisagreeWithTheSize) {
  const Bytes pixels(100);
  ImageView image;
  image.width = 10;
  image.height = 10;
  image.step = 10;
  image.encoding = "mono8";
  image.data = pixels;
  EXPECT_TRUE(checkImageLayout(image).ok());

  image.height = 11;
  EXPECT_FALSE(checkImageLayout(image).ok());
  image.height = 10;
  image.encoding = "rgb8";
  EXPECT_FALSE(checkImageLayout(image).ok());  // a row of 10 rgb8 pixels needs 30 bytes
  image.height = 0xFFFFFFFF;
  image.step = 0xFFFFFFFF;
  EXPECT_FALSE(checkImageLayout(image).ok());
}

TEST(Schemas, TextsHaveTheRootThenEachDependencyOnce) {
  const std::string separator = "\n" + std::string(80, '=') + "\nMSG: ";
  const std::string image(kImageDefinition);
  const std::string imu(kImuDefinition);

  EXPECT_EQ(image.rfind("std_msgs/Header header\n", 0), 0U);
  EXPECT_NE(image.find(separator + "std_msgs/Header\n"), std::string::npos);
  EXPECT_NE(image.find(separator + "builtin_interfaces/Time\n"), std::string::npos);
  // rosbag2's order for Imu: Quaternion, Vector3, Header, then Time.
  const auto quaternion = imu.find(separator + "geometry_msgs/Quaternion\n");
  const auto vector3 = imu.find(separator + "geometry_msgs/Vector3\n");
  const auto header = imu.find(separator + "std_msgs/Header\n");
  const auto time = imu.find(separator + "builtin_interfaces/Time\n");
  ASSERT_NE(time, std::string::npos);
  EXPECT_LT(quaternion, vector3);
  EXPECT_LT(vector3, header);
  EXPECT_LT(header, time);
}

}  // namespace
}  // namespace cvislam::ros2
