// The agent's threads talk through iceoryx: the topic names, the adapters that put iceoryx publishers and
// subscribers behind the tracker's, the link's and mapping's plain interfaces (KeyframeSink, AnchorSink,
// DeltaSource), and the ThreadSanitizer annotations for chunks handed between threads. Included by the agent's
// runtime only (agent.cpp, mapping_thread.cpp): iceoryx headers stay out of everything else.
#pragma once

#include <chrono>
#include <cstdint>
#include <optional>
#include <string>

#include "agent_rt/link/link.hpp"
#include "agent_rt/live/state_topics.hpp"
#include "agent_rt/messages/messages.hpp"
#include "agent_rt/runtime/channel_depths.hpp"
#include "agent_rt/tracking/tracker.hpp"
#include "common/core/steady_clock.hpp"
#include "iceoryx_posh/popo/publisher.hpp"
#include "iceoryx_posh/popo/subscriber.hpp"

namespace cvislam::agent {

// iceoryx hands chunks between threads through lock-free queues that synchronise with fences, which
// ThreadSanitizer does not model: without help it reports every message as a race. These annotations state
// the happens-before that iceoryx provides (publish -> take, release of a chunk -> its next loan); they are
// no-ops outside TSan builds.
#if defined(__SANITIZE_THREAD__)
extern "C" void __tsan_acquire(void* address);  // NOLINT(bugprone-reserved-identifier)
extern "C" void __tsan_release(void* address);  // NOLINT(bugprone-reserved-identifier)
inline void tsanAcquire(const void* chunk) {
  __tsan_acquire(const_cast<void*>(chunk));
}  // NOLINT(cppcoreguidelines-pro-type-const-cast)
inline void tsanRelease(const void* chunk) {
  __tsan_release(const_cast<void*>(chunk));
}  // NOLINT(cppcoreguidelines-pro-type-const-cast)
#else
inline void tsanAcquire(const void* /*chunk*/) {}
inline void tsanRelease(const void* /*chunk*/) {}
#endif

// Releases a received chunk (for TSan) when the sample holding it goes.
struct ChunkReleaseOnExit {
  const void* chunk;
  ~ChunkReleaseOnExit() { tsanRelease(chunk); }
};

// The topic `event` of agent `agent`.
inline iox::capro::ServiceDescription service(AgentId agent, const char* event) {
  const std::string instance = "agent" + std::to_string(agent);
  return {"cvislam", iox::capro::IdString_t(iox::cxx::TruncateToCapacity, instance.c_str()),
          iox::capro::IdString_t(iox::cxx::TruncateToCapacity, event)};
}

// A publisher's loan, written in place and published (or given back).
template <typename Message>
class IceoryxLoan {
 public:
  explicit IceoryxLoan(iox::popo::Publisher<Message>& publisher) : publisher_(publisher) {}
  Message* loan() {
    auto loaned = publisher_.loan();
    if (loaned.has_error()) return nullptr;
    sample_.emplace(std::move(loaned.value()));
    tsanAcquire(sample_->get());
    return sample_->get();
  }
  void publish() {
    if (!sample_) return;
    tsanRelease(sample_->get());
    sample_->publish();
    sample_.reset();
  }
  void discard() { sample_.reset(); }

 private:
  iox::popo::Publisher<Message>& publisher_;
  std::optional<iox::popo::Sample<Message>> sample_;
};

// Tracking writes its keyframes into iceoryx chunks for mapping.
class IceoryxKeyframeSink final : public KeyframeSink {
 public:
  explicit IceoryxKeyframeSink(iox::popo::Publisher<KeyframeMessage>& publisher) : loan_(publisher) {}
  KeyframeMessage* loan() override { return loan_.loan(); }
  void publish() override { loan_.publish(); }

 private:
  IceoryxLoan<KeyframeMessage> loan_;
};

// The link writes what the server sent down into iceoryx chunks for mapping.
class IceoryxAnchorSink final : public AnchorSink {
 public:
  explicit IceoryxAnchorSink(iox::popo::Publisher<AnchorMessage>& publisher) : loan_(publisher) {}
  AnchorMessage* loan() override { return loan_.loan(); }
  void publish() override { loan_.publish(); }
  void discard() override { loan_.discard(); }

 private:
  IceoryxLoan<AnchorMessage> loan_;
};

// The link reads tracking's newest frame state from the agent's own state topic ("frames", kept newest-only):
// whatever states came since the last batch, the newest is the one sent. Copies into the caller's value.
class IceoryxPoseSource final : public PoseSource {
 public:
  explicit IceoryxPoseSource(iox::popo::Subscriber<live::AgentStateMessage>& subscriber) : subscriber_(subscriber) {}
  bool newest(LivePose& out) override {
    while (true) {
      auto taken = subscriber_.take();
      if (taken.has_error()) break;
      const live::AgentStateMessage& state = *taken.value();
      if (state.status != live::StateStatus::kTracking) continue;  // a lost frame's pose is a guess: keep the last
      held_.t_ns = state.t_ns;
      held_.map_id = state.map_id;
      const Eigen::Quaterniond q(state.q_w_s[3], state.q_w_s[0], state.q_w_s[1], state.q_w_s[2]);
      held_.T_w_s = geometry::SE3d(q, Eigen::Vector3d(state.p_w_s[0], state.p_w_s[1], state.p_w_s[2]));
      held_.metric = (state.flags & live::kMetric) != 0U;
      have_ = true;
    }
    if (have_) out = held_;
    return have_;
  }

 private:
  iox::popo::Subscriber<live::AgentStateMessage>& subscriber_;
  LivePose held_;
  bool have_ = false;
};

// The link reads mapping's deltas from iceoryx.
class IceoryxDeltaSource final : public DeltaSource {
 public:
  explicit IceoryxDeltaSource(iox::popo::Subscriber<MapDeltaMessage>& subscriber) : subscriber_(subscriber) {}
  const MapDeltaMessage* next() override {
    auto taken = subscriber_.take();
    if (taken.has_error()) return nullptr;
    held_.emplace(std::move(taken.value()));
    tsanAcquire(held_->get());
    return held_->get();
  }
  void release() override {
    if (held_) tsanRelease(held_->get());
    held_.reset();
  }

 private:
  iox::popo::Subscriber<MapDeltaMessage>& subscriber_;
  std::optional<iox::popo::Sample<const MapDeltaMessage>> held_;
};

}  // namespace cvislam::agent
