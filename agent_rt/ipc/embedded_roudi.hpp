// The iceoryx routing daemon (RouDi) inside the agent process, so that the agent is a single process with
// nothing to start first. Tracking and mapping then exchange fixed-size messages through iceoryx shared
// memory, zero-copy: a publisher loans a chunk, writes into it and publishes; the subscriber reads the same
// memory.
//
// iceoryx allows one RouDi per machine (its lock file and shared-memory names are fixed): start() refuses,
// with a message, when an iox-roudi or another agent already runs one, instead of letting iceoryx abort. Use an
// external iox-roudi (deploy/roudi_config.toml) to run several agents on one machine.
//
// iceoryx headers stay out of this header; the iceoryx objects live behind a pointer.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "common/core/result.hpp"

namespace cvislam::agent {

// One iceoryx memory pool: `chunk_count` chunks that each carry up to `chunk_payload_bytes` of message.
struct MemPoolSpec {
  std::uint32_t chunk_payload_bytes = 0;
  std::uint32_t chunk_count = 0;
};

struct EmbeddedRouDiOptions {
  std::string runtime_name = "cvislam_agent";  // the process's name in iceoryx; unique per RouDi
  // Pools for the agent's messages. Every message type needs a pool at least its size, with enough chunks
  // for what publishers hold loaned plus what subscribers keep queued.
  std::vector<MemPoolSpec> mempools = {{128, 1000}, {1024, 500}, {16 * 1024, 200}, {1024 * 1024, 32}};

  // Names the bad field: empty name, no pools or too many, a pool of zero size or count, sizes that do not
  // increase strictly (iceoryx would abort).
  [[nodiscard]] Status validate() const;
};

// Attaches this process to an external iox-roudi (deploy/roudi_config.toml) as `runtime_name`. Fails at once,
// saying what to start, when none runs (iceoryx itself would wait 60 s and abort).
Status attachToExternalRouDi(const std::string& runtime_name);

class EmbeddedRouDi {
 public:
  // Starts RouDi and this process's iceoryx runtime; publishers and subscribers may be created afterwards,
  // from any thread, until this object is destroyed. Fails, saying why, when another RouDi runs.
  static Result<std::unique_ptr<EmbeddedRouDi>> start(const EmbeddedRouDiOptions& options);
  ~EmbeddedRouDi();

  EmbeddedRouDi(const EmbeddedRouDi&) = delete;
  EmbeddedRouDi& operator=(const EmbeddedRouDi&) = delete;

 private:
  struct Impl;
  explicit EmbeddedRouDi(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace cvislam::agent
