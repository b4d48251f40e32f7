#include "server_cloud/stack/mission_events.hpp"

#include <algorithm>
#include <chrono>

namespace cvislam::server {

MissionEventLog::MissionEventLog(std::size_t capacity) : capacity_(std::max<std::size_t>(capacity, 1)) {}

std::uint64_t MissionEventLog::append(MissionEvent event) {
  event.t_unix_ns =
      std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::system_clock::now().time_since_epoch()).count();
  auto s = state_.write();
  event.number = s->next_number++;
  if (s->events.size() >= capacity_) s->events.pop_front();
  s->events.push_back(std::move(event));
  return s->next_number - 1;
}

MissionEventLog::Page MissionEventLog::read(std::uint64_t from, std::size_t max) const {
  Page page;
  auto s = state_.read();
  from = std::max<std::uint64_t>(from, 1);
  page.next = from;
  if (s->events.empty() || from >= s->next_number) return page;  // nothing from there on yet
  const std::uint64_t oldest = s->events.front().number;
  if (from < oldest) {
    page.skipped = oldest - from;
    from = oldest;
  }
  const std::size_t first = static_cast<std::size_t>(from - oldest);
  const std::size_t n = std::min(max, s->events.size() - first);
  page.events.assign(s->events.begin() + static_cast<std::ptrdiff_t>(first),
                     s->events.begin() + static_cast<std::ptrdiff_t>(first + n));
  page.next = from + n;
  return page;
}

std::uint64_t MissionEventLog::nextNumber() const {
  return state_.read()->next_number;
}

}  // namespace cvislam::server
