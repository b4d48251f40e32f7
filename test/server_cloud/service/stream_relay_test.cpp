// The relay of a server stream (read_forwarding.hpp) between two real gRPC servers on loopback: an owner that
// writes all its chunks and its status at once, the relay in front of it, and clients that read slowly or cancel
// at seeded random points. The owner's status then arrives while the relay is still writing to the client, which
// is when the relay must still hold the owner's call. Every chunk arrives once and in order, with the owner's
// status; the asan preset shows that nothing freed is touched.
#include <chrono>
#include <memory>
#include <random>
#include <string>
#include <thread>

#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include "cvislam/v1/map_service.grpc.pb.h"
#include "server_cloud/service/read_forwarding.hpp"

namespace cvislam::server {
namespace {

constexpr std::uint32_t kChunks = 12;

// Writes kChunks chunks back to back, then its status, without waiting for anyone.
class OwnerService final : public v1::MapService::CallbackService {
 public:
  grpc::ServerWriteReactor<v1::MapChunk>* GetMap(grpc::CallbackServerContext*, const v1::GetMapRequest*) override {
    class Writer final : public grpc::ServerWriteReactor<v1::MapChunk> {
     public:
      Writer() { next(); }
      void OnWriteDone(bool ok) override {
        if (!ok) {
          Finish(grpc::Status(grpc::StatusCode::CANCELLED, "the relay left"));
          return;
        }
        next();
      }
      void OnDone() override { delete this; }

     private:
      void next() {
        if (index_ == kChunks) {
          Finish(grpc::Status::OK);
          return;
        }
        chunk_.Clear();
        chunk_.set_index(index_);
        chunk_.set_last(index_ + 1 == kChunks);
        // Some weight, so that a chunk is more than a frame of the transport.
        chunk_.add_points()->set_orb_descriptor(std::string(16U << 10U, static_cast<char>(index_)));
        ++index_;
        StartWrite(&chunk_);
      }
      v1::MapChunk chunk_;
      std::uint32_t index_ = 0;
    };
    return new Writer();
  }
};

// Passes every GetMap on to the owner through a StreamRelay.
class RelayService final : public v1::MapService::CallbackService {
 public:
  explicit RelayService(std::string owner)
      : owner_(std::move(owner)),
        stub_(v1::MapService::NewStub(grpc::CreateChannel(owner_, grpc::InsecureChannelCredentials()))) {}
  grpc::ServerWriteReactor<v1::MapChunk>* GetMap(grpc::CallbackServerContext* context,
                                                 const v1::GetMapRequest* request) override {
    return new StreamRelay<v1::MapChunk>(forwardingContext(*context, /*unary=*/false), owner_,
                                         [&](grpc::ClientContext* call, grpc::ClientReadReactor<v1::MapChunk>* r) {
                                           stub_->async()->GetMap(call, request, r);
                                         });
  }

 private:
  std::string owner_;
  std::unique_ptr<v1::MapService::Stub> stub_;
};

std::unique_ptr<grpc::Server> serve(grpc::Service* service, int& port) {
  grpc::ServerBuilder builder;
  builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
  builder.RegisterService(service);
  return builder.BuildAndStart();
}

class StreamRelayTest : public ::testing::Test {
 protected:
  void SetUp() override {
    owner_server_ = serve(&owner_, owner_port_);
    ASSERT_NE(owner_server_, nullptr);
    relay_ = std::make_unique<RelayService>("127.0.0.1:" + std::to_string(owner_port_));
    relay_server_ = serve(relay_.get(), relay_port_);
    ASSERT_NE(relay_server_, nullptr);
    stub_ = v1::MapService::NewStub(
        grpc::CreateChannel("127.0.0.1:" + std::to_string(relay_port_), grpc::InsecureChannelCredentials()));
  }
  void TearDown() override {
    relay_server_->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(2));
    owner_server_->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(2));
  }

  // Reads through the relay, pausing `pause` after each chunk and cancelling after `cancel_after` chunks (never
  // when it is kChunks or more). Returns the status; *received counts the chunks, each checked for its index.
  grpc::Status read(std::chrono::milliseconds pause, std::uint32_t cancel_after, std::uint32_t* received) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
    v1::GetMapRequest request;
    auto reader = stub_->GetMap(&context, request);
    v1::MapChunk chunk;
    *received = 0;
    while (reader->Read(&chunk)) {
      EXPECT_EQ(chunk.index(), *received);
      ++*received;
      if (*received == cancel_after && cancel_after < kChunks) context.TryCancel();
      std::this_thread::sleep_for(pause);
    }
    return reader->Finish();
  }

  OwnerService owner_;
  int owner_port_ = 0;
  std::unique_ptr<grpc::Server> owner_server_;
  std::unique_ptr<RelayService> relay_;
  int relay_port_ = 0;
  std::unique_ptr<grpc::Server> relay_server_;
  std::unique_ptr<v1::MapService::Stub> stub_;
};

TEST_F(StreamRelayTest, ASlowReaderGetsEveryChunkAndTheOwnersStatusAfterTheOwnerHasFinished) {
  for (int round = 0; round < 3; ++round) {
    std::uint32_t received = 0;
    const grpc::Status status = read(std::chrono::milliseconds(40), kChunks, &received);
    EXPECT_TRUE(status.ok()) << status.error_message();
    EXPECT_EQ(received, kChunks);
  }
}

TEST_F(StreamRelayTest, ClientsThatCancelAtRandomPointsLeaveTheRelayWorking) {
  std::mt19937 random(20261127);
  std::uniform_int_distribution<std::uint32_t> point(1, kChunks - 1);
  std::uniform_int_distribution<int> pause_ms(0, 15);
  for (int round = 0; round < 25; ++round) {
    std::uint32_t received = 0;
    const std::uint32_t cancel_after = point(random);
    const grpc::Status status = read(std::chrono::milliseconds(pause_ms(random)), cancel_after, &received);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::CANCELLED) << "round " << round;
    EXPECT_GE(received, cancel_after);
  }
  std::uint32_t received = 0;
  EXPECT_TRUE(read(std::chrono::milliseconds(0), kChunks, &received).ok());
  EXPECT_EQ(received, kChunks);
}

}  // namespace
}  // namespace cvislam::server
