// ExportMap's files, made from map snapshots (map_reader.hpp): what a user opens in a point-cloud viewer, an
// evaluation tool or a script, without a gRPC client of their own.
#pragma once

#include <string>
#include <vector>

#include "server_cloud/maps/map_reader.hpp"

namespace cvislam::server::maps {

struct ExportedFile {
  std::string name;  // a plain file name
  std::string data;
};

// Per map M of `snapshots`:
//   map<M>.ply                       ASCII PLY: every point (x y z in M [m], float) with its observation count;
//   keyframes_agent<N>_map<M>.txt    TUM ("t[s] x y z qx qy qz qw"): agent N's keyframes in M, by time;
//   map<M>.json                      the mission, map id, origin, agents, counts, refined keyframes, the time
//                                    span and the points' bounding box.
std::vector<ExportedFile> exportMaps(const std::vector<MapSnapshot>& snapshots);

}  // namespace cvislam::server::maps
