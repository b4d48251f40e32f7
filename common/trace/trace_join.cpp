#include "common/trace/trace_join.hpp"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <limits>
#include <optional>
#include <set>
#include <sstream>

#include <nlohmann/json.hpp>

#include "common/core/percentile.hpp"

namespace cvislam::trace {

using nlohmann::json;

std::int64_t TraceRecord::arg(const std::string& key, std::int64_t fallback) const {
  const auto it = args.find(key);
  return it == args.end() ? fallback : it->second;
}

namespace {

Error badTrace(const std::filesystem::path& file, const std::string& what) {
  return Error{ErrorCode::kParseError, file.string() + ": " + what};
}

Result<TraceRecord> recordOf(const json& e) {
  if (!e.is_object() || !e.contains("ph") || !e.contains("name") || !e.contains("pid") || !e.contains("tid")) {
    return Error{ErrorCode::kParseError, "an event without ph, name, pid or tid"};
  }
  TraceRecord r;
  r.phase = e.at("ph").get<std::string>();
  r.name = e.at("name").get<std::string>();
  r.pid = e.at("pid").get<std::int64_t>();
  r.tid = e.at("tid").get<std::int64_t>();
  if (r.phase == "M") {
    if (e.contains("args") && e.at("args").contains("name")) r.label = e.at("args").at("name").get<std::string>();
    return r;
  }
  if (!e.contains("ts")) return Error{ErrorCode::kParseError, "event '" + r.name + "' has no ts"};
  r.ts_us = e.at("ts").get<double>();
  if (r.phase == "X") {
    if (!e.contains("dur")) return Error{ErrorCode::kParseError, "span '" + r.name + "' has no dur"};
    r.dur_us = e.at("dur").get<double>();
    if (!(r.dur_us >= 0.0)) return Error{ErrorCode::kParseError, "span '" + r.name + "' has a negative dur"};
  }
  if (e.contains("args")) {
    for (const auto& [key, value] : e.at("args").items()) {
      if (value.is_number_integer()) r.args[key] = value.get<std::int64_t>();
    }
  }
  return r;
}

// The first record of each key, in time order.
template <typename Key, typename KeyOf>
std::map<Key, const TraceRecord*> firstBy(const ProcessTrace& trace, const std::string& name, KeyOf key_of) {
  std::map<Key, const TraceRecord*> out;
  for (const TraceRecord& r : trace.records) {
    if (r.name != name) continue;
    const auto [it, inserted] = out.emplace(key_of(r), &r);
    if (!inserted && r.ts_us < it->second->ts_us) it->second = &r;
  }
  return out;
}

std::vector<const TraceRecord*> named(const ProcessTrace& trace, const std::string& name) {
  std::vector<const TraceRecord*> out;
  for (const TraceRecord& r : trace.records) {
    if (r.name == name) out.push_back(&r);
  }
  std::sort(out.begin(), out.end(), [](const TraceRecord* a, const TraceRecord* b) { return a->ts_us < b->ts_us; });
  return out;
}

// The first of `sorted` (by ts) that begins at or after `t_us` and passes `accept`.
template <typename Accept>
const TraceRecord* firstFrom(const std::vector<const TraceRecord*>& sorted, double t_us, Accept accept) {
  auto it =
      std::lower_bound(sorted.begin(), sorted.end(), t_us, [](const TraceRecord* r, double t) { return r->ts_us < t; });
  for (; it != sorted.end(); ++it) {
    if (accept(**it)) return *it;
  }
  return nullptr;
}

}  // namespace

Result<ProcessTrace> readProcessTrace(const std::filesystem::path& file) {
  std::ifstream in(file);
  if (!in) return Error{ErrorCode::kNotFound, "cannot open the trace " + file.string()};
  json doc;
  try {
    doc = json::parse(in);
  } catch (const json::exception& e) {
    return badTrace(file, std::string("not JSON (") + e.what() + ")");
  }
  if (!doc.is_object() || !doc.contains("otherData") || !doc.contains("traceEvents")) {
    return badTrace(file, "not a cvislam trace (no otherData or traceEvents): write it with --trace");
  }
  const json& other = doc.at("otherData");
  if (!other.contains("format") || other.at("format").get<std::string>().rfind("cvislam trace", 0) != 0) {
    return badTrace(file, "not a cvislam trace (otherData.format)");
  }
  ProcessTrace trace;
  trace.file = file;
  try {
    trace.process = other.at("process").get<std::string>();
    trace.agent = other.at("agent").get<std::int64_t>();
    if (other.contains("mission")) trace.mission = other.at("mission").get<std::string>();
    if (other.contains("mission_key")) trace.mission_key = other.at("mission_key").get<std::int64_t>();
    for (const json& e : doc.at("traceEvents")) {
      auto r = recordOf(e);
      if (!r) return badTrace(file, r.error().message());
      trace.records.push_back(std::move(*r));
    }
  } catch (const json::exception& e) {
    return badTrace(file, std::string("a field of the wrong type (") + e.what() + ")");
  }
  return trace;
}

ProcessTrace onlyMission(const ProcessTrace& server, std::int64_t mission_key) {
  ProcessTrace out = server;
  out.records.clear();
  for (const TraceRecord& r : server.records) {
    if (r.phase == "M" || r.arg("mission") == mission_key) out.records.push_back(r);
  }
  return out;
}

Result<ClockOffset> estimateClockOffset(const ProcessTrace& agent, const ProcessTrace& server) {
  // The server's events of this agent: its id within its mission (the same id may fly in another).
  const auto ofAgent = [&](const TraceRecord& r) {
    return r.arg("agent") == agent.agent && r.arg("mission") == agent.mission_key;
  };
  ClockOffset c;
  // Uplink: the server began to ingest batch b after the agent began the span that sent it.
  double upper = std::numeric_limits<double>::infinity();
  const auto sent = firstBy<std::int64_t>(agent, "uplink_batch", [](const TraceRecord& r) { return r.arg("batch"); });
  for (const TraceRecord& r : server.records) {
    if (r.name != "ingest" || !ofAgent(r)) continue;
    const auto it = sent.find(r.arg("batch"));
    if (it == sent.end()) continue;
    upper = std::min(upper, r.ts_us - it->second->ts_us);
    ++c.uplink_pairs;
  }
  // Downlink: the agent received message d after the server finished building it. Sequences start again on
  // every stream, so the k-th message numbered d at one end is the k-th at the other.
  double lower = -std::numeric_limits<double>::infinity();
  std::map<std::int64_t, std::vector<double>> built;
  for (const TraceRecord* r : named(server, "downlink_build")) {
    if (ofAgent(*r)) built[r->arg("downlink")].push_back(r->endUs());
  }
  std::map<std::int64_t, std::size_t> seen;
  for (const TraceRecord* r : named(agent, "downlink_received")) {
    const std::int64_t d = r->arg("downlink");
    const std::size_t k = seen[d]++;
    const auto it = built.find(d);
    if (it == built.end() || k >= it->second.size()) continue;
    lower = std::max(lower, it->second[k] - r->ts_us);
    ++c.downlink_pairs;
  }
  const std::string who = agent.process + " (" + agent.file.string() + ")";
  if (c.uplink_pairs == 0 || c.downlink_pairs == 0) {
    return Error{ErrorCode::kDataError,
                 who + " and the server's trace share " + std::to_string(c.uplink_pairs) + " batches and " +
                     std::to_string(c.downlink_pairs) +
                     " downlink messages: both are needed to align the clocks (are they of the same mission?)"};
  }
  // Timestamps carry nanosecond digits; a microsecond of slack covers their rounding.
  if (lower > upper + 1.0) {
    std::ostringstream text;
    text << who << ": the link's messages contradict each other (offset >= " << lower
         << " us from the downlink, <= " << upper << " us from the uplink): are the traces of the same run?";
    return Error{ErrorCode::kDataError, text.str()};
  }
  c.lower_us = lower;
  c.upper_us = upper;
  c.offset_us = 0.5 * (lower + upper);
  c.uncertainty_us = std::max(0.0, 0.5 * (upper - lower));
  return c;
}

void shiftTrace(ProcessTrace& trace, double offset_us) {
  for (TraceRecord& r : trace.records) {
    if (r.phase != "M") r.ts_us += offset_us;
  }
}

namespace {

// A downlink message (built or applied) that carried corrections or the covisible map.
bool carriesMap(const TraceRecord& r) {
  return r.arg("corrections", 0) > 0 || r.arg("covisible", 0) > 0;
}

// What one agent's trace says of its keyframes, indexed.
struct AgentIndex {
  std::map<std::int64_t, double> captured, decided, mapped, sent;
  std::map<std::int64_t, std::int64_t> batch_of, map_of;
  std::map<std::int64_t, double> map_ready;  // when the agent's map's frame became final (its keyframes may go)
  std::vector<const TraceRecord*> corrections_applied;  // apply_downlink spans carrying corrections, by time
  std::vector<const TraceRecord*> content_applied;      // ... carrying corrections or a covisible map, by time

  explicit AgentIndex(const ProcessTrace& t) {
    for (const TraceRecord& r : t.records) {
      const std::int64_t kf = r.arg("keyframe");
      if (kf < 0) continue;
      if (r.name == "track_frame") captured.emplace(kf, r.ts_us - static_cast<double>(r.arg("since_capture_us", 0)));
      if (r.name == "keyframe_write") decided.emplace(kf, r.endUs());
      if (r.name == "map_keyframe") mapped.emplace(kf, r.endUs());
      if (r.name == "keyframe_sent" && sent.emplace(kf, r.ts_us).second) {
        batch_of[kf] = r.arg("batch");
        map_of[kf] = r.arg("map");
      }
    }
    for (const TraceRecord* r : named(t, "map_ready")) map_ready.emplace(r->arg("map"), r->ts_us);
    for (const TraceRecord* r : named(t, "apply_downlink")) {
      if (r->arg("corrections", 0) > 0) corrections_applied.push_back(r);
      if (carriesMap(*r)) content_applied.push_back(r);
    }
  }

  // Decided before its map's frame was final: it waited in the store for that, not for the link.
  [[nodiscard]] bool heldForItsMap(std::int64_t kf, double decided_us) const {
    const auto m = map_of.find(kf);
    if (m == map_of.end()) return false;
    const auto ready = map_ready.find(m->second);
    return ready != map_ready.end() && decided_us < ready->second;
  }

  [[nodiscard]] const TraceRecord* correctionsFrom(double t_us) const {
    return firstFrom(corrections_applied, t_us, [](const TraceRecord&) { return true; });
  }
};

using AgentKeyframe = std::pair<std::int64_t, std::int64_t>;

}  // namespace

// Each agent's downlink messages as the server built them, by time.
std::map<std::int64_t, std::vector<const TraceRecord*>> buildsByAgent(const ProcessTrace& server) {
  std::map<std::int64_t, std::vector<const TraceRecord*>> out;
  for (const TraceRecord* r : named(server, "downlink_build")) out[r->arg("agent")].push_back(r);
  return out;
}

// When a merge's map was first corrected after it: the end of its merge correction, else of the map's first GBA.
double correctedUs(const ProcessTrace& server, const TraceRecord& merge) {
  const auto ofMap = [&](const TraceRecord& r) { return r.arg("map") == merge.arg("map"); };
  if (const TraceRecord* c = firstFrom(named(server, "merge_correction"), merge.ts_us, ofMap)) return c->endUs();
  if (const TraceRecord* g = firstFrom(named(server, "global_ba"), merge.endUs(), ofMap)) return g->endUs();
  return -1.0;
}

// Per merge: when every agent of the merged map held the corrected map. The first downlink message the server
// built for an agent after the map's first correction says: carrying corrections or covisible keyframes, the agent
// holds the corrected map once it applied that message (the first it applied with either since); carrying
// neither, nothing the agent holds had changed, so it held it when that message was built.
void followCorrectedMaps(const ProcessTrace& server, const std::map<std::int64_t, AgentIndex>& by_agent,
                         const std::map<AgentKeyframe, const TraceRecord*>& queried, Journeys& j) {
  const auto builds = buildsByAgent(server);
  const std::vector<const TraceRecord*> members = named(server, "merged_map_agent");
  for (const TraceRecord* merge : named(server, "merge")) {
    std::vector<std::int64_t> agents;
    for (const TraceRecord* member : members) {
      if (member->ts_us >= merge->ts_us && member->ts_us <= merge->endUs() && member->tid == merge->tid &&
          member->arg("map") == merge->arg("map")) {
        agents.push_back(member->arg("agent"));
      }
    }
    if (agents.empty()) continue;  // a stale match: its maps were one already
    const auto q = queried.find({merge->arg("agent"), merge->arg("keyframe")});
    const double match_us = q != queried.end() ? q->second->endUs() : merge->ts_us;
    const double corrected_us = correctedUs(server, *merge);
    double last_us = match_us;
    bool every = corrected_us >= 0.0;
    for (std::size_t i = 0; every && i < agents.size(); ++i) {
      const auto built = builds.find(agents[i]);
      const TraceRecord* first = built == builds.end()
                                     ? nullptr
                                     : firstFrom(built->second, corrected_us, [](const TraceRecord&) { return true; });
      const auto a = by_agent.find(agents[i]);
      double held_us = -1.0;
      if (first != nullptr && !carriesMap(*first)) {
        held_us = first->endUs();
      } else if (first != nullptr && a != by_agent.end()) {
        if (const TraceRecord* applied =
                firstFrom(a->second.content_applied, first->endUs(), [](const TraceRecord&) { return true; })) {
          held_us = applied->ts_us;
        }
      }
      every = held_us >= 0.0;
      last_us = std::max(last_us, held_us);
    }
    if (every) {
      j.match_to_all_agents_holding_corrected_map_ms.push_back((last_us - match_us) * 1e-3);
    } else {
      ++j.merges_not_reaching_every_agent_corrected_map;
    }
  }
}

Journeys followKeyframes(const ProcessTrace& server, const std::vector<ProcessTrace>& agents) {
  Journeys j;
  const std::vector<std::string> names = {
      "frame captured -> keyframe decided",       "keyframe decided -> local BA done",
      "keyframe decided -> batch sent",           "batch sent -> stored on the server",
      "keyframe decided -> stored on the server", "keyframe decided -> stored, start-up waits left out",
      "stored -> place recognition queried",      "queried -> matched and merged (or loop closed)",
      "merged -> optimised by the GBA",           "optimised -> corrections applied by the agent"};
  for (const std::string& n : names) j.links.push_back({n, {}});
  const auto add = [&](std::size_t link, double from_us, double to_us) {
    j.links[link].ms.push_back((to_us - from_us) * 1e-3);
  };

  const auto stored = firstBy<AgentKeyframe>(server, "ingest", [](const TraceRecord& r) {
    return AgentKeyframe{r.arg("agent"), r.arg("batch")};
  });
  const auto queried = firstBy<AgentKeyframe>(server, "recognition_query", [](const TraceRecord& r) {
    return AgentKeyframe{r.arg("agent"), r.arg("keyframe")};
  });
  std::map<AgentKeyframe, const TraceRecord*> matched;
  for (const char* kind : {"merge", "loop"}) {
    for (const auto& [key, r] : firstBy<AgentKeyframe>(server, kind, [](const TraceRecord& r) {
           return AgentKeyframe{r.arg("agent"), r.arg("keyframe")};
         })) {
      matched.emplace(key, r);
    }
  }
  const std::vector<const TraceRecord*> gbas = named(server, "global_ba");
  std::map<std::int64_t, AgentIndex> by_agent;
  for (const ProcessTrace& a : agents) by_agent.emplace(a.agent, AgentIndex(a));

  for (const auto& [agent, index] : by_agent) {
    for (const auto& [kf, decided] : index.decided) {
      ++j.keyframes;
      if (const auto c = index.captured.find(kf); c != index.captured.end()) add(0, c->second, decided);
      if (const auto m = index.mapped.find(kf); m != index.mapped.end()) add(1, decided, m->second);
      const auto s = index.sent.find(kf);
      if (s == index.sent.end()) continue;
      add(2, decided, s->second);
      const auto st = stored.find({agent, index.batch_of.at(kf)});
      if (st == stored.end()) continue;
      add(3, s->second, st->second->endUs());
      add(4, decided, st->second->endUs());
      if (!index.heldForItsMap(kf, decided)) add(5, decided, st->second->endUs());
      const auto q = queried.find({agent, kf});
      if (q == queried.end()) continue;
      add(6, st->second->endUs(), q->second->endUs());
      const auto m = matched.find({agent, kf});
      if (m == matched.end()) continue;
      add(7, q->second->endUs(), m->second->endUs());
      const TraceRecord* merge = m->second;
      const TraceRecord* gba =
          firstFrom(gbas, merge->endUs(), [&](const TraceRecord& g) { return g.arg("map") == merge->arg("map"); });
      if (gba == nullptr) continue;
      add(8, merge->endUs(), gba->endUs());
      if (const TraceRecord* applied = index.correctionsFrom(gba->endUs())) add(9, gba->endUs(), applied->ts_us);
    }
  }

  // Per merge: every agent of the merged map holding corrections made after the merge joined them.
  const std::vector<const TraceRecord*> members = named(server, "merged_map_agent");
  for (const TraceRecord* merge : named(server, "merge")) {
    const auto q = queried.find({merge->arg("agent"), merge->arg("keyframe")});
    const double match_us = q != queried.end() ? q->second->endUs() : merge->ts_us;
    double last_us = match_us;
    bool every = false;
    int members_found = 0;
    for (const TraceRecord* member : members) {
      if (member->ts_us < merge->ts_us || member->ts_us > merge->endUs() || member->tid != merge->tid ||
          member->arg("map") != merge->arg("map")) {
        continue;
      }
      every = true;
      ++members_found;
      const auto a = by_agent.find(member->arg("agent"));
      const TraceRecord* applied = a == by_agent.end() ? nullptr : a->second.correctionsFrom(member->ts_us);
      if (applied == nullptr) {
        every = false;
        break;
      }
      last_us = std::max(last_us, applied->ts_us);
    }
    if (!every && members_found == 0) continue;  // a stale match: its maps were one already
    if (every) {
      j.match_to_all_agents_corrected_ms.push_back((last_us - match_us) * 1e-3);
    } else {
      ++j.merges_not_reaching_every_agent;
    }
  }
  followCorrectedMaps(server, by_agent, queried, j);
  return j;
}

std::vector<LinkSummary> summarise(const Journeys& journeys) {
  std::vector<LinkSummary> out;
  const auto one = [](const std::string& name, const std::vector<double>& ms) {
    return LinkSummary{name, summariseSamples(ms)};
  };
  for (const JourneyLink& link : journeys.links) out.push_back(one(link.name, link.ms));
  out.push_back(one("map match -> every agent of the merged map corrected", journeys.match_to_all_agents_corrected_ms));
  out.push_back(one("map match -> every agent of the merged map holding the corrected map",
                    journeys.match_to_all_agents_holding_corrected_map_ms));
  return out;
}

std::string joinedChromeJson(const ProcessTrace& server, const std::vector<ProcessTrace>& agents) {
  json events = json::array();
  std::set<std::int64_t> pids_taken;
  std::map<std::int64_t, std::int64_t> agent_pid;  // agent -> pid in the joined file
  const auto emit = [&](const ProcessTrace& t, std::int64_t pid) {
    for (const TraceRecord& r : t.records) {
      json e = {{"ph", r.phase}, {"name", r.name}, {"pid", pid}, {"tid", r.tid}};
      if (r.phase == "M") {
        e["args"] = {{"name", r.label}};
      } else {
        e["cat"] = "cvislam";
        e["ts"] = r.ts_us;
        if (r.phase == "X") e["dur"] = r.dur_us;
        if (r.phase == "i") e["s"] = "t";
        e["args"] = r.args;
      }
      events.push_back(std::move(e));
    }
  };
  const std::int64_t server_pid = server.records.empty() ? 1 : server.records.front().pid;
  pids_taken.insert(server_pid);
  emit(server, server_pid);
  for (const ProcessTrace& a : agents) {
    // Processes of several machines may share a pid.
    std::int64_t pid = a.records.empty() ? 2 : a.records.front().pid;
    while (pids_taken.count(pid) != 0) pid += 1'000'000;
    pids_taken.insert(pid);
    agent_pid[a.agent] = pid;
    emit(a, pid);
  }
  // An arrow from each keyframe's decision to the server's ingest of the batch that carried it.
  const auto stored = firstBy<AgentKeyframe>(server, "ingest", [](const TraceRecord& r) {
    return AgentKeyframe{r.arg("agent"), r.arg("batch")};
  });
  std::int64_t flow = 0;
  for (const ProcessTrace& a : agents) {
    const auto writes =
        firstBy<std::int64_t>(a, "keyframe_write", [](const TraceRecord& r) { return r.arg("keyframe"); });
    const auto sent = firstBy<std::int64_t>(a, "keyframe_sent", [](const TraceRecord& r) { return r.arg("keyframe"); });
    for (const auto& [kf, write] : writes) {
      const auto s = sent.find(kf);
      if (s == sent.end()) continue;
      const auto st = stored.find({a.agent, s->second->arg("batch")});
      if (st == stored.end()) continue;
      ++flow;
      events.push_back({{"ph", "s"},
                        {"name", "keyframe"},
                        {"cat", "journey"},
                        {"id", flow},
                        {"pid", agent_pid[a.agent]},
                        {"tid", write->tid},
                        {"ts", write->ts_us + 0.5 * write->dur_us}});
      events.push_back({{"ph", "f"},
                        {"bp", "e"},
                        {"name", "keyframe"},
                        {"cat", "journey"},
                        {"id", flow},
                        {"pid", server_pid},
                        {"tid", st->second->tid},
                        {"ts", st->second->ts_us + 0.5 * st->second->dur_us}});
    }
  }
  json doc = {{"displayTimeUnit", "ms"}, {"traceEvents", std::move(events)}};
  return doc.dump() + "\n";
}

}  // namespace cvislam::trace
