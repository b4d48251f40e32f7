// WriteGate: one write at a time, Finish exactly once and never during a write, the first status winning.
#include "server_cloud/service/write_gate.hpp"

#include <gtest/gtest.h>

namespace cvislam::server {
namespace {

TEST(WriteGate, AFinishWhileIdleGoesNowAndStopsWrites) {
  WriteGate gate;
  ASSERT_TRUE(gate.writable());

  const auto now = gate.finish(grpc::Status(grpc::StatusCode::NOT_FOUND, "gone"));

  ASSERT_TRUE(now.has_value());
  EXPECT_EQ(now->error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_TRUE(gate.finishing());
  EXPECT_FALSE(gate.writable());
  EXPECT_FALSE(gate.finish(grpc::Status::OK).has_value()) << "Finish() only once";
}

TEST(WriteGate, AFinishDuringAWriteWaitsForItAndTheFirstStatusWins) {
  WriteGate gate;
  gate.writeStarted();
  EXPECT_FALSE(gate.writable());

  const auto during = gate.finish(grpc::Status(grpc::StatusCode::CANCELLED, "cancelled"));
  const auto second = gate.finish(grpc::Status(grpc::StatusCode::UNAVAILABLE, "broke"));
  const auto after = gate.writeDone();

  EXPECT_FALSE(during.has_value());
  EXPECT_FALSE(second.has_value());
  ASSERT_TRUE(after.has_value());
  EXPECT_EQ(after->error_code(), grpc::StatusCode::CANCELLED);
  EXPECT_FALSE(gate.writable());
  EXPECT_FALSE(gate.writeDone().has_value()) << "the waiting finish comes back once";
}

TEST(WriteGate, WritesAlternateWithTheirCompletions) {
  WriteGate gate;
  gate.writeStarted();
  EXPECT_FALSE(gate.writable());
  EXPECT_FALSE(gate.writeDone().has_value());
  EXPECT_TRUE(gate.writable());
}

}  // namespace
}  // namespace cvislam::server
