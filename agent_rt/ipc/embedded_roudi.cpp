#include "agent_rt/ipc/embedded_roudi.hpp"

#include <optional>
#include <utility>

#include "iceoryx_hoofs/log/logmanager.hpp"
#include "iceoryx_hoofs/posix_wrapper/file_lock.hpp"
#include "iceoryx_hoofs/posix_wrapper/posix_access_rights.hpp"
#include "iceoryx_posh/iceoryx_posh_config.hpp"
#include "iceoryx_posh/iceoryx_posh_types.hpp"
#include "iceoryx_posh/internal/mepoo/mem_pool.hpp"
#include "iceoryx_posh/internal/roudi/roudi.hpp"
#include "iceoryx_posh/roudi/iceoryx_roudi_components.hpp"
#include "iceoryx_posh/runtime/posh_runtime.hpp"
#include "iceoryx_posh/runtime/posh_runtime_single_process.hpp"

namespace cvislam::agent {

namespace {
// iceoryx wants chunk sizes in multiples of its chunk alignment; payloads are rounded up to them.
std::uint32_t alignedPayload(std::uint32_t bytes) {
  constexpr auto kAlignment = static_cast<std::uint32_t>(iox::mepoo::MemPool::CHUNK_MEMORY_ALIGNMENT);
  return (bytes + kAlignment - 1) / kAlignment * kAlignment;
}
}  // namespace

Status EmbeddedRouDiOptions::validate() const {
  if (runtime_name.empty() || runtime_name.size() > iox::MAX_RUNTIME_NAME_LENGTH) {
    return Error{ErrorCode::kInvalidArgument,
                 "iceoryx runtime_name must have 1 to " + std::to_string(iox::MAX_RUNTIME_NAME_LENGTH) + " characters"};
  }
  if (mempools.empty() || mempools.size() > iox::MAX_NUMBER_OF_MEMPOOLS) {
    return Error{ErrorCode::kInvalidArgument,
                 "iceoryx mempools: give 1 to " + std::to_string(iox::MAX_NUMBER_OF_MEMPOOLS) + " pools"};
  }
  for (std::size_t i = 0; i < mempools.size(); ++i) {
    if (mempools[i].chunk_payload_bytes == 0 || mempools[i].chunk_count == 0) {
      return Error{ErrorCode::kInvalidArgument,
                   "iceoryx mempools[" + std::to_string(i) + "]: chunk_payload_bytes and chunk_count must be > 0"};
    }
    // iceoryx aborts unless the (aligned) sizes increase strictly.
    if (i > 0 &&
        alignedPayload(mempools[i].chunk_payload_bytes) <= alignedPayload(mempools[i - 1].chunk_payload_bytes)) {
      return Error{ErrorCode::kInvalidArgument,
                   "iceoryx mempools[" + std::to_string(i) + "]: sizes must increase strictly, in steps of at least " +
                       std::to_string(iox::mepoo::MemPool::CHUNK_MEMORY_ALIGNMENT) + " bytes"};
    }
  }
  return Status::Ok();
}

struct EmbeddedRouDi::Impl {
  explicit Impl(const iox::RouDiConfig_t& config)
      : components(config),
        roudi(components.rouDiMemoryManager, components.portManager,
              iox::roudi::RouDi::RoudiStartupParameters{iox::roudi::MonitoringMode::OFF, false}) {}

  iox::roudi::IceOryxRouDiComponents components;
  iox::roudi::RouDi roudi;
  std::optional<iox::runtime::PoshRuntimeSingleProcess> runtime;
};

EmbeddedRouDi::EmbeddedRouDi(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
EmbeddedRouDi::~EmbeddedRouDi() {
  if (impl_) impl_->runtime.reset();  // the runtime goes before RouDi
}

namespace {
// iceoryx logs every port it creates at debug level; the agent wants its warnings and errors only.
void quietIceoryxLog() {
  iox::log::LogManager::GetLogManager().SetDefaultLogLevel(iox::log::LogLevel::kWarn);
}
}  // namespace

Status attachToExternalRouDi(const std::string& runtime_name) {
  quietIceoryxLog();
  if (runtime_name.empty() || runtime_name.size() > iox::MAX_RUNTIME_NAME_LENGTH) {
    return Error{ErrorCode::kInvalidArgument,
                 "iceoryx runtime name must have 1 to " + std::to_string(iox::MAX_RUNTIME_NAME_LENGTH) + " characters"};
  }
  {
    auto lock = iox::posix::FileLock::create(iox::roudi::ROUDI_LOCK_NAME);
    if (!lock.has_error()) {
      return Error{ErrorCode::kNotFound,
                   "no iox-roudi runs on this machine: start one first (iox-roudi -m off -c deploy/roudi_config.toml) "
                   "or let the agent embed RouDi"};
    }
  }
  iox::runtime::PoshRuntime::initRuntime(iox::RuntimeName_t(iox::cxx::TruncateToCapacity, runtime_name));
  return Status::Ok();
}

Result<std::unique_ptr<EmbeddedRouDi>> EmbeddedRouDi::start(const EmbeddedRouDiOptions& options) {
  if (Status status = options.validate(); !status.ok()) return status.error();
  quietIceoryxLog();

  // iceoryx aborts the process when a second RouDi starts; take its lock first to fail gracefully instead.
  {
    auto lock = iox::posix::FileLock::create(iox::roudi::ROUDI_LOCK_NAME);
    if (lock.has_error()) {
      if (lock.get_error() == iox::posix::FileLockError::LOCKED_BY_OTHER_PROCESS) {
        return Error{ErrorCode::kInternal,
                     "another iceoryx RouDi runs on this machine (an iox-roudi or another agent): stop it, or "
                     "attach to it instead of embedding one"};
      }
      return Error{ErrorCode::kIoError, "cannot take iceoryx's RouDi lock file (" +
                                            std::string(iox::roudi::ROUDI_LOCK_NAME) +
                                            ".lock in the temp folder): check that it is writable"};
    }
  }  // released here; RouDi takes it again below (a RouDi started in between still makes iceoryx abort)

  iox::mepoo::MePooConfig mempool_config;
  for (const MemPoolSpec& pool : options.mempools) {
    mempool_config.addMemPool({alignedPayload(pool.chunk_payload_bytes), pool.chunk_count});
  }
  iox::RouDiConfig_t config;
  const auto group = iox::posix::PosixGroup::getGroupOfCurrentProcess().getName();
  config.m_sharedMemorySegments.push_back({group, group, mempool_config});
  config.setModuleDefaults<iox::config::RouDiConfig>();

  auto impl = std::make_unique<Impl>(config);
  impl->runtime.emplace(iox::RuntimeName_t(iox::cxx::TruncateToCapacity, options.runtime_name));
  return std::unique_ptr<EmbeddedRouDi>(new EmbeddedRouDi(std::move(impl)));
}

}  // namespace cvislam::agent
