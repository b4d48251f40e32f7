// The trace library: spans nest and close on their thread, every thread gets its own track, a full ring keeps the
// newest events and counts the rest, recording allocates nothing, and the JSON is what Perfetto's importer reads.
#include "common/trace/trace.hpp"

#include <set>
#include <thread>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "test/support/allocation_counter.hpp"

namespace cvislam::trace {
namespace {

using nlohmann::json;

SessionOptions options(std::size_t events_per_thread = 1024) {
  SessionOptions o;
  o.process_name = "agent 7";
  o.agent = 7;
  o.events_per_thread = events_per_thread;
  return o;
}

// The events of the trace that are not metadata.
std::vector<json> spansAndInstants(const json& trace) {
  std::vector<json> out;
  for (const json& e : trace.at("traceEvents")) {
    if (e.at("ph") != "M") out.push_back(e);
  }
  return out;
}

TEST(Trace, WithoutASessionNothingRecords) {
  bindThread("nobody");
  EXPECT_EQ(currentTrack(), nullptr);
  Span span("orb", {{"frame", 1}});
  EXPECT_FALSE(span.active());
  instant("x");
}

TEST(Trace, SpansNestAndCarryTheirArgumentsIntoChromeJson) {
  Session session(options());
  bindThread("tracking");
  {
    Span frame("track_frame", {{"frame", 3}});
    { Span orb("orb", {{"frame", 3}}); }
    frame.set("keyframe", 12);
    instant("keyframe_decided", {{"keyframe", 12}});
  }
  const json trace = json::parse(session.chromeJson());
  EXPECT_EQ(trace.at("otherData").at("process"), "agent 7");
  EXPECT_EQ(trace.at("otherData").at("agent"), 7);
  const std::vector<json> events = spansAndInstants(trace);
  ASSERT_EQ(events.size(), 3U);
  // In recording order: a span is recorded when it closes.
  const json& orb = events[0];
  const json& decided = events[1];
  const json& frame = events[2];
  EXPECT_EQ(orb.at("name"), "orb");
  EXPECT_EQ(orb.at("ph"), "X");
  EXPECT_EQ(decided.at("ph"), "i");
  EXPECT_EQ(decided.at("args").at("keyframe"), 12);
  EXPECT_EQ(frame.at("args").at("frame"), 3);
  EXPECT_EQ(frame.at("args").at("keyframe"), 12);
  // The inner span lies within the outer one, on the same thread.
  const double frame_begin = frame.at("ts").get<double>();
  const double frame_end = frame_begin + frame.at("dur").get<double>();
  EXPECT_GE(orb.at("ts").get<double>(), frame_begin);
  EXPECT_LE(orb.at("ts").get<double>() + orb.at("dur").get<double>(), frame_end);
  EXPECT_EQ(orb.at("tid"), frame.at("tid"));
  bool named = false;
  for (const json& e : trace.at("traceEvents")) {
    if (e.at("ph") == "M" && e.at("name") == "thread_name" && e.at("tid") == frame.at("tid")) {
      named = e.at("args").at("name") == "tracking";
    }
  }
  EXPECT_TRUE(named);
}

TEST(Trace, EachThreadRecordsIntoItsOwnTrack) {
  Session session(options());
  std::vector<std::thread> threads;
  for (int t = 0; t < 3; ++t) {
    threads.emplace_back([t] {
      bindThread(t == 0 ? "mapping" : "link");
      for (int i = 0; i < 10; ++i) Span span("work", {{"i", i}, {"thread", t}});
    });
  }
  for (std::thread& th : threads) th.join();
  const json trace = json::parse(session.chromeJson());
  std::set<std::int64_t> tids;
  for (const json& e : spansAndInstants(trace)) tids.insert(e.at("tid").get<std::int64_t>());
  EXPECT_EQ(tids.size(), 3U);
  EXPECT_EQ(session.totals().threads, 3U);
  EXPECT_EQ(session.totals().events, 30U);
}

TEST(Trace, UnboundThreadsRecordOnlyWhenTheSessionSaysSo) {
  {
    Session session(options());
    std::thread([] { Span span("ingest"); }).join();
    EXPECT_EQ(session.totals().events, 0U);
  }
  SessionOptions o = options();
  o.trace_unbound_threads = true;
  Session session(o);
  std::thread([] { Span span("ingest"); }).join();
  EXPECT_EQ(session.totals().events, 1U);
  EXPECT_EQ(session.totals().threads, 1U);
}

TEST(Trace, AFullRingKeepsTheNewestEventsAndCountsTheRest) {
  Session session(options(16));
  bindThread("tracking");
  for (int i = 0; i < 40; ++i) instant("frame", {{"frame", i}});
  const SessionTotals totals = session.totals();
  EXPECT_EQ(totals.events, 40U);
  EXPECT_EQ(totals.overwritten, 24U);
  const json trace = json::parse(session.chromeJson());
  const std::vector<json> events = spansAndInstants(trace);
  ASSERT_EQ(events.size(), 16U);
  EXPECT_EQ(events.front().at("args").at("frame"), 24);
  EXPECT_EQ(events.back().at("args").at("frame"), 39);
  EXPECT_EQ(trace.at("otherData").at("overwritten"), 24);
}

TEST(Trace, ABindingEndsWithItsSession) {
  {
    Session first(options());
    bindThread("tracking");
    EXPECT_NE(currentTrack(), nullptr);
  }
  EXPECT_EQ(currentTrack(), nullptr);  // the first session's track is gone; it must not be touched
  Session second(options());
  EXPECT_EQ(currentTrack(), nullptr);  // not bound to the second one yet
  bindThread("tracking");
  instant("x");
  EXPECT_EQ(second.totals().events, 1U);
}

TEST(Trace, RecordingAllocatesNothingOnceBound) {
  Session session(options(256));
  bindThread("tracking");
  const long before = test::allocationCount();
  for (int i = 0; i < 1000; ++i) {
    Span frame("track_frame", {{"frame", i}});
    { Span orb("orb"); }
    frame.set("keyframe", i);
    instant("keyframe_decided", {{"keyframe", i}});
    complete("local_ba", 1000, 2000, {{"keyframe", i}});
  }
  EXPECT_EQ(test::allocationCount() - before, 0);
  EXPECT_EQ(session.totals().events, 4000U);
}

TEST(Trace, OptionsAreChecked) {
  SessionOptions o = options();
  EXPECT_TRUE(o.validate().ok());
  o.events_per_thread = 4;
  EXPECT_NE(o.validate().error().message().find("events per thread"), std::string::npos);
  o = options();
  o.process_name.clear();
  EXPECT_FALSE(o.validate().ok());
}

TEST(Trace, TimesAreMicrosecondsWithNanosecondDigits) {
  Session session(options());
  bindThread("t");
  complete("span", 1'234'567'891, 1'234'570'000);
  const json trace = json::parse(session.chromeJson());
  const json e = spansAndInstants(trace).at(0);
  EXPECT_DOUBLE_EQ(e.at("ts").get<double>(), 1234567.891);
  EXPECT_DOUBLE_EQ(e.at("dur").get<double>(), 2.109);
}

}  // namespace
}  // namespace cvislam::trace
