// cvislam_trace: joins the traces of one mission (cvislam_server --trace, cvislam_agent --trace) into one file that
// Perfetto opens, with every agent's clock aligned to the server's, and prints the latency of each link of a
// keyframe's way from the camera to the server and back.
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include "common/trace/trace_join.hpp"

namespace {

using cvislam::trace::ProcessTrace;

struct MergeCommand {
  std::vector<std::string> traces;
  std::string output;
  std::string json_summary;
};

// The server's trace and the agents', told apart by what each says it is.
bool sortTraces(std::vector<ProcessTrace> all, ProcessTrace& server, std::vector<ProcessTrace>& agents) {
  bool have_server = false;
  for (ProcessTrace& t : all) {
    if (t.agent < 0) {
      if (have_server) {
        std::cerr << "cvislam_trace: two server traces (" << server.file << " and " << t.file
                  << "): join one mission's server with its agents\n";
        return false;
      }
      server = std::move(t);
      have_server = true;
    } else {
      for (const ProcessTrace& a : agents) {
        if (a.agent == t.agent) {
          std::cerr << "cvislam_trace: two traces of agent " << t.agent << " (" << a.file << " and " << t.file << ")\n";
          return false;
        }
      }
      agents.push_back(std::move(t));
    }
  }
  if (!have_server) {
    std::cerr << "cvislam_trace: no server trace among the files (cvislam_server --trace FILE writes one)\n";
    return false;
  }
  return true;
}

int merge(const MergeCommand& command) {
  std::vector<ProcessTrace> all;
  for (const std::string& file : command.traces) {
    auto trace = cvislam::trace::readProcessTrace(file);
    if (!trace) {
      std::cerr << "cvislam_trace: " << trace.error().message() << "\n";
      return 1;
    }
    all.push_back(std::move(*trace));
  }
  ProcessTrace server;
  std::vector<ProcessTrace> agents;
  if (!sortTraces(std::move(all), server, agents)) return 1;
  if (agents.empty()) {
    std::cerr << "cvislam_trace: no agent trace among the files (cvislam_agent --trace FILE writes one)\n";
    return 1;
  }
  for (const ProcessTrace& a : agents) {
    if (a.mission != agents.front().mission) {
      std::cerr << "cvislam_trace: " << a.file << " is of mission '" << a.mission << "', " << agents.front().file
                << " of '" << agents.front().mission << "': join the agents of one mission\n";
      return 1;
    }
  }
  server = cvislam::trace::onlyMission(server, agents.front().mission_key);
  std::printf("mission '%s': the server and %zu agents\n", agents.front().mission.c_str(), agents.size());

  nlohmann::json summary = {{"clocks", nlohmann::json::array()}, {"links", nlohmann::json::array()}};
  std::printf("clock offsets to the server (server = agent + offset), from the link's own messages:\n");
  for (ProcessTrace& agent : agents) {
    auto offset = cvislam::trace::estimateClockOffset(agent, server);
    if (!offset) {
      std::cerr << "cvislam_trace: " << offset.error().message() << "\n";
      return 1;
    }
    std::printf("  %-10s %+10.3f ms +- %.3f ms  (%zu batches, %zu downlink messages)\n", agent.process.c_str(),
                offset->offset_us * 1e-3, offset->uncertainty_us * 1e-3, offset->uplink_pairs, offset->downlink_pairs);
    summary["clocks"].push_back({{"agent", agent.agent},
                                 {"offset_ms", offset->offset_us * 1e-3},
                                 {"uncertainty_ms", offset->uncertainty_us * 1e-3},
                                 {"batches", offset->uplink_pairs},
                                 {"downlink_messages", offset->downlink_pairs}});
    cvislam::trace::shiftTrace(agent, offset->offset_us);
  }

  const cvislam::trace::Journeys journeys = cvislam::trace::followKeyframes(server, agents);
  std::printf("\na keyframe's way (%zu keyframes decided by %zu agents):\n", journeys.keyframes, agents.size());
  std::printf("  %-54s %6s %10s %10s %10s\n", "link", "n", "p50 [ms]", "p99 [ms]", "max [ms]");
  for (const cvislam::trace::LinkSummary& s : cvislam::trace::summarise(journeys)) {
    std::printf("  %-54s %6zu %10.1f %10.1f %10.1f\n", s.name.c_str(), s.ms.count, s.ms.p50, s.ms.p99, s.ms.max);
    summary["links"].push_back(
        {{"link", s.name}, {"n", s.ms.count}, {"p50_ms", s.ms.p50}, {"p99_ms", s.ms.p99}, {"max_ms", s.ms.max}});
  }
  if (journeys.merges_not_reaching_every_agent > 0) {
    std::printf(
        "  (%zu merges after which some agent of the merged map applied no correction before its trace ended)\n",
        journeys.merges_not_reaching_every_agent);
  }
  if (journeys.merges_not_reaching_every_agent_corrected_map > 0) {
    std::printf(
        "  (%zu merges after which some agent of the merged map applied nothing of the corrected map before its trace "
        "ended)\n",
        journeys.merges_not_reaching_every_agent_corrected_map);
  }
  summary["keyframes"] = journeys.keyframes;
  summary["merges_not_reaching_every_agent"] = journeys.merges_not_reaching_every_agent;
  summary["merges_not_reaching_every_agent_corrected_map"] = journeys.merges_not_reaching_every_agent_corrected_map;

  if (!command.output.empty()) {
    std::ofstream out(command.output, std::ios::binary | std::ios::trunc);
    out << cvislam::trace::joinedChromeJson(server, agents);
    if (!out) {
      std::cerr << "cvislam_trace: cannot write " << command.output << "\n";
      return 1;
    }
    std::printf("\njoined trace: %s (open it in https://ui.perfetto.dev)\n", command.output.c_str());
  }
  if (!command.json_summary.empty()) {
    std::ofstream out(command.json_summary, std::ios::trunc);
    out << summary.dump(2) << "\n";
    if (!out) {
      std::cerr << "cvislam_trace: cannot write " << command.json_summary << "\n";
      return 1;
    }
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "cvislam_trace: joins a mission's traces and follows its keyframes from the camera to the server "
      "and back"};
  app.require_subcommand(1);
  MergeCommand command;
  CLI::App* merge_app = app.add_subcommand(
      "merge", "Join the server's trace and its agents' into one (clocks aligned) and print the latency chain");
  merge_app->add_option("traces", command.traces, "Trace files: the server's and any of its agents'")
      ->required()
      ->check(CLI::ExistingFile);
  merge_app->add_option("-o,--output", command.output, "Write the joined Chrome Trace Event JSON here");
  merge_app->add_option("--json", command.json_summary, "Write the clock offsets and the latency chain here as JSON");
  CLI11_PARSE(app, argc, argv);
  return merge(command);
}
