// FixedPool: capacity, stale handles, iteration, and no heap allocation after construction. This binary
// replaces global operator new to count allocations.
#include "agent_rt/map/fixed_pool.hpp"

#include <memory>
#include <unordered_set>
#include <vector>

#include <gtest/gtest.h>

#include "agent_rt/map/capacities.hpp"
#include "common/core/ids.hpp"
#include "test/support/allocation_counter.hpp"

namespace cvislam::agent {
namespace {

struct Payload {
  KeyframeId id;
  double value = 0.0;
};

constexpr std::size_t kCapacity = 8;

TEST(FixedPool, InsertWhenFullReturnsNothingAndKeepsWhatItHolds) {
  FixedPool<Payload, kCapacity> sut;
  IdCounter<KeyframeId> ids(3);
  std::vector<PoolHandle> handles;
  for (std::size_t i = 0; i < kCapacity; ++i) {
    const auto handle = sut.insert({ids.next(), static_cast<double>(i)});
    ASSERT_TRUE(handle.has_value());
    handles.push_back(*handle);
  }
  EXPECT_TRUE(sut.full());
  EXPECT_FALSE(sut.insert({ids.next(), 99.0}).has_value());
  EXPECT_EQ(sut.size(), kCapacity);
  for (std::size_t i = 0; i < kCapacity; ++i) {
    ASSERT_NE(sut.get(handles[i]), nullptr);
    EXPECT_EQ(sut.get(handles[i])->value, static_cast<double>(i));
    EXPECT_EQ(sut.get(handles[i])->id, (KeyframeId{3, static_cast<std::uint32_t>(i)}));
  }
}

TEST(FixedPool, EraseFreesTheSlotAndTheOldHandleBecomesStale) {
  FixedPool<Payload, kCapacity> sut;
  const PoolHandle first = *sut.insert({KeyframeId{1, 0}, 1.0});
  EXPECT_EQ(first.index, 0U);
  EXPECT_FALSE(first == PoolHandle{});
  ASSERT_TRUE(sut.erase(first));
  EXPECT_FALSE(sut.erase(first));  // twice is refused
  EXPECT_EQ(sut.get(first), nullptr);
  const PoolHandle reused = *sut.insert({KeyframeId{1, 1}, 2.0});
  EXPECT_EQ(reused.index, first.index);  // the slot is reused...
  EXPECT_EQ(sut.get(first), nullptr);    // ...but the old handle does not alias the new object
  ASSERT_NE(sut.get(reused), nullptr);
  EXPECT_EQ(sut.get(reused)->value, 2.0);
  EXPECT_FALSE(sut.valid(PoolHandle{static_cast<std::uint32_t>(kCapacity), 1}));  // out of range
  EXPECT_FALSE(sut.valid(PoolHandle{}));  // an unset handle never refers to an object, even in slot 0
}

TEST(FixedPool, ForEachVisitsExactlyTheLiveObjectsInSlotOrder) {
  FixedPool<Payload, kCapacity> sut;
  std::vector<PoolHandle> handles;
  for (int i = 0; i < 6; ++i) handles.push_back(*sut.insert({KeyframeId{0, static_cast<std::uint32_t>(i)}, 0.0}));
  sut.erase(handles[1]);
  sut.erase(handles[4]);
  std::vector<std::uint32_t> visited;
  sut.forEach([&](PoolHandle handle, Payload& p) {
    EXPECT_TRUE(sut.valid(handle));
    visited.push_back(p.id.counter);
  });
  EXPECT_EQ(visited, (std::vector<std::uint32_t>{0, 2, 3, 5}));
}

TEST(FixedPool, ChurnAtTheConfiguredCapacityNeverAllocates) {
  auto sut = std::make_unique<FixedPool<Payload, kMaxKeyframes>>();  // constructed before counting
  IdCounter<KeyframeId> ids(7);
  std::vector<PoolHandle> handles;
  handles.reserve(kMaxKeyframes);
  const long before = test::allocationCount();
  for (int round = 0; round < 100; ++round) {
    handles.clear();  // capacity reserved above: no allocation
    while (auto handle = sut->insert({ids.next(), 0.0})) handles.push_back(*handle);
    EXPECT_EQ(sut->size(), kMaxKeyframes);
    for (std::size_t i = 0; i < handles.size(); i += 2) sut->erase(handles[i]);
  }
  EXPECT_EQ(test::allocationCount() - before, 0);
}

TEST(FixedPool, TheCounterSeesAnAllocation) {
  const long before = test::allocationCount();
  auto p = std::make_unique<int>(1);
  EXPECT_GE(test::allocationCount() - before, 1);
}

TEST(ObjectIds, TwoAgentsCountingIndependentlyNeverCollide) {
  IdCounter<MapPointId> a(0);
  IdCounter<MapPointId> b(1);
  std::unordered_set<MapPointId> seen;
  for (int i = 0; i < 1000; ++i) {
    EXPECT_TRUE(seen.insert(a.next()).second);
    EXPECT_TRUE(seen.insert(b.next()).second);
  }
  EXPECT_LT((MapPointId{0, 5}), (MapPointId{1, 0}));
  EXPECT_EQ((KeyframeId{2, 17}).toString(), "2:17");
}

}  // namespace
}  // namespace cvislam::agent
