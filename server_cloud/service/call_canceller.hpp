// Cancels a server call from another thread, safely at any time: while its reactor lives, and after it is done
// (then nothing happens). The reactor calls ended() in OnDone. Only service/ includes it (gRPC headers).
#pragma once

#include <mutex>

#include <grpcpp/server_context.h>

namespace cvislam::server {

class CallCanceller {
 public:
  explicit CallCanceller(grpc::CallbackServerContext* context) : context_(context) {}
  void cancel() {
    std::lock_guard lock(mutex_);
    if (context_ != nullptr) context_->TryCancel();
  }
  void ended() {
    std::lock_guard lock(mutex_);
    context_ = nullptr;
  }

 private:
  std::mutex mutex_;
  grpc::CallbackServerContext* context_;
};

}  // namespace cvislam::server
