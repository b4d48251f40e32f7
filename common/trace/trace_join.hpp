// Joining the traces of one mission (the server's and each agent's, common/trace/trace.hpp) into one timeline:
// each agent's clock aligned to the server's, and every keyframe followed from the camera to the server and back.
//
// Clock alignment uses the link's own messages, as NTP does with its packets: a batch cannot reach the server
// before the agent began to send it, and a downlink message cannot reach the agent before the server built it.
// Every batch bounds the offset from above, every downlink message from below; the estimate is the middle of the
// tightest pair of bounds, and half their distance says how well it is known. On one machine the steady clocks
// are the same and the estimate is 0 within that bound.
#pragma once

#include <cstdint>
#include <filesystem>
#include <map>
#include <string>
#include <vector>

#include "common/core/percentile.hpp"
#include "common/core/result.hpp"

namespace cvislam::trace {

struct TraceRecord {
  std::string name;
  std::string phase;    // "X" span, "i" instant, "M" metadata (kept for the joined file)
  double ts_us = 0.0;   // on the trace's own clock until aligned
  double dur_us = 0.0;  // spans only
  std::int64_t pid = 0;
  std::int64_t tid = 0;
  std::map<std::string, std::int64_t> args;  // integer arguments; metadata's name in `label`
  std::string label;
  [[nodiscard]] double endUs() const { return ts_us + dur_us; }
  [[nodiscard]] std::int64_t arg(const std::string& key, std::int64_t fallback = -1) const;
};

struct ProcessTrace {
  std::filesystem::path file;
  std::string process;  // "server", "agent 3"
  std::int64_t agent = -1;
  std::string mission;            // an agent's; the server's trace holds every mission's events
  std::int64_t mission_key = -1;  // trace::missionKey(mission): how the server's events name it
  std::vector<TraceRecord> records;
};

// The server's events of one mission (and the trace's metadata).
ProcessTrace onlyMission(const ProcessTrace& server, std::int64_t mission_key);

// Reads a trace written by trace::Session; names the file and what is wrong with it.
Result<ProcessTrace> readProcessTrace(const std::filesystem::path& file);

struct ClockOffset {
  // server clock = agent clock + offset_us
  double offset_us = 0.0;
  double uncertainty_us = 0.0;  // half the width of the interval the bounds leave
  double lower_us = 0.0;        // from the downlink
  double upper_us = 0.0;        // from the uplink
  std::size_t uplink_pairs = 0;
  std::size_t downlink_pairs = 0;
  [[nodiscard]] bool bothBounds() const { return uplink_pairs > 0 && downlink_pairs > 0; }
};

// The agent's offset to the server. An error when the traces share no batch and no downlink message, or when
// the bounds contradict each other (traces of two different runs).
Result<ClockOffset> estimateClockOffset(const ProcessTrace& agent, const ProcessTrace& server);

// Moves every record of `trace` by `offset_us` (onto the server's clock).
void shiftTrace(ProcessTrace& trace, double offset_us);

// One link of a keyframe's way, e.g. "keyframe decided -> stored on the server", with one sample per keyframe.
struct JourneyLink {
  std::string name;
  std::vector<double> ms;
};

struct Journeys {
  std::vector<JourneyLink> links;  // in the order of the way
  std::size_t keyframes = 0;       // decided by the agents
  // Per merge: from the match (its query's end) to the moment every agent of the merged map had applied a
  // downlink message with corrections; merges after which some agent never did are counted apart.
  std::vector<double> match_to_all_agents_corrected_ms;
  std::size_t merges_not_reaching_every_agent = 0;
  // Per merge: from the match to the moment every agent of the merged map had applied a downlink message built
  // after the map's first correction (its merge correction, else its GBA) that carried corrections or the
  // covisible map. An agent whose keyframes the correction did not move has nothing to correct, but its anchors
  // come from the corrected map from then on. Merges after which some agent never did are counted apart.
  std::vector<double> match_to_all_agents_holding_corrected_map_ms;
  std::size_t merges_not_reaching_every_agent_corrected_map = 0;
};

// Follows every keyframe through aligned traces of one mission (the server's filtered by onlyMission): captured ->
// decided -> local BA done -> sent -> stored -> queried, and, for the keyframes whose query found a match, ->
// matched/merged -> optimised by the GBA -> corrections applied by the agent.
Journeys followKeyframes(const ProcessTrace& server, const std::vector<ProcessTrace>& agents);

struct LinkSummary {
  std::string name;
  SampleSummary ms;  // over the link's samples [ms]
};
std::vector<LinkSummary> summarise(const Journeys& journeys);

// One Chrome Trace Event JSON of every process (each its own pid), with flow arrows from each keyframe's decision
// to the server's ingest of it.
std::string joinedChromeJson(const ProcessTrace& server, const std::vector<ProcessTrace>& agents);

}  // namespace cvislam::trace
