// The metrics endpoint's content, read from a core driven without gRPC: every stored batch is counted once in the
// ingest histogram, histogram buckets are cumulative and end at +Inf, mission labels stop at the cap (the rest sum
// under "_other"), and the text serves over HTTP at /metrics.
#include "server_cloud/service/metrics_endpoint.hpp"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cmath>
#include <set>
#include <string>

#include <gtest/gtest.h>
#include <prometheus/metric_family.h>

#include "server_cloud/core/server_core.hpp"
#include "test/server_cloud/link_messages.hpp"
#include "test/server_cloud/session_driver.hpp"

namespace cvislam::server {
namespace {

using test::batchMessage;
using test::helloMessage;
using test::makeKeyframeBatch;

const prometheus::MetricFamily* family(const std::vector<prometheus::MetricFamily>& families, const std::string& name) {
  for (const auto& f : families) {
    if (f.name == name) return &f;
  }
  return nullptr;
}

// One agent of each mission sends `batches` batches of two keyframes.
void fly(ServerCore& core, const std::vector<std::string>& missions, int batches) {
  std::uint64_t session_id = 100;
  for (const std::string& mission : missions) {
    auto session = core.openSession({});
    ASSERT_TRUE(test::sendTo(*session, helloMessage(mission, 1, ++session_id)).ok());
    for (int s = 1; s <= batches; ++s) {
      const Status sent = test::sendTo(
          *session,
          batchMessage(makeKeyframeBatch(static_cast<std::uint64_t>(s), static_cast<std::uint32_t>(2 * (s - 1)), 2)));
      ASSERT_TRUE(sent.ok()) << sent.error().toString();
    }
  }
}

TEST(LatencyHistogram, CountsEachDurationInTheFirstBucketThatHoldsIt) {
  LatencyHistogram h;
  h.observe(0.001);   // on a bound: that bucket
  h.observe(0.0011);  // just above: the next
  h.observe(100.0);   // above every bound: +Inf
  h.observe(-1.0);    // nonsense counts as 0
  const LatencyHistogram::Snapshot s = h.snapshot();
  EXPECT_EQ(s.count, 4U);
  EXPECT_EQ(s.counts[0], 2U);
  EXPECT_EQ(s.counts[1], 1U);
  EXPECT_EQ(s.counts.back(), 1U);
  EXPECT_NEAR(s.sum_s, 100.0021, 1e-9);
}

TEST(MetricsEndpoint, EveryStoredBatchIsCountedOnceAndBucketsAreCumulative) {
  ServerCore core(ServerOptions{});
  fly(core, {"alpha", "beta"}, 3);
  const auto families = collectMetrics(core, {});
  const auto* ingest = family(families, "cvislam_ingest_seconds");
  ASSERT_NE(ingest, nullptr);
  ASSERT_EQ(ingest->metric.size(), 1U);
  const auto& h = ingest->metric[0].histogram;
  EXPECT_EQ(h.sample_count, 6U);
  ASSERT_EQ(h.bucket.size(), LatencyHistogram::kBuckets);
  for (std::size_t b = 1; b < h.bucket.size(); ++b)
    EXPECT_GE(h.bucket[b].cumulative_count, h.bucket[b - 1].cumulative_count);
  EXPECT_EQ(h.bucket.back().cumulative_count, 6U);
  EXPECT_TRUE(std::isinf(h.bucket.back().upper_bound));

  const std::string text = metricsText(core, {});
  EXPECT_NE(text.find("cvislam_link_messages_total{direction=\"up\",kind=\"batch\",mission=\"alpha\"} 3"),
            std::string::npos)
      << text;
  EXPECT_NE(text.find("cvislam_agents{mission=\"beta\"} 1"), std::string::npos);
  EXPECT_NE(text.find("cvislam_agents_connected{mission=\"beta\"} 0"), std::string::npos);  // its stream ended
  EXPECT_NE(text.find("cvislam_missions 2"), std::string::npos);
}

TEST(MetricsEndpoint, MissionsBeyondTheCapAreSummedUnderOther) {
  ServerCore core(ServerOptions{});
  fly(core, {"m1", "m2", "m3", "m4"}, 2);
  MetricsOptions options;
  options.max_labelled_missions = 2;
  const auto families = collectMetrics(core, options);
  const auto* agents = family(families, "cvislam_agents");
  ASSERT_NE(agents, nullptr);
  std::set<std::string> labels;
  double other = 0.0;
  for (const auto& m : agents->metric) {
    ASSERT_EQ(m.label.size(), 1U);
    labels.insert(m.label[0].value);
    if (m.label[0].value == "_other") other = m.gauge.value;
  }
  EXPECT_EQ(labels, (std::set<std::string>{"m1", "m2", "_other"}));
  EXPECT_EQ(other, 2.0);  // m3 and m4, one agent each
}

// A plain HTTP GET over loopback, as Prometheus scrapes.
std::string httpGet(int port, const std::string& path) {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(static_cast<std::uint16_t>(port));
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (::connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)) != 0) {
    ::close(fd);
    return {};
  }
  const std::string request = "GET " + path + " HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n";
  (void)::send(fd, request.data(), request.size(), 0);
  std::string response;
  char buffer[4096];
  for (ssize_t n = ::recv(fd, buffer, sizeof(buffer), 0); n > 0; n = ::recv(fd, buffer, sizeof(buffer), 0)) {
    response.append(buffer, static_cast<std::size_t>(n));
  }
  ::close(fd);
  return response;
}

TEST(MetricsEndpoint, ServesTheTextOverHttp) {
  ServerCore core(ServerOptions{});
  fly(core, {"alpha"}, 2);
  auto endpoint = MetricsEndpoint::start(core, "127.0.0.1:0");
  ASSERT_TRUE(endpoint) << endpoint.error().toString();
  ASSERT_GT((*endpoint)->port(), 0);
  const std::string response = httpGet((*endpoint)->port(), "/metrics");
  EXPECT_NE(response.find("200 OK"), std::string::npos) << response.substr(0, 200);
  EXPECT_NE(response.find("cvislam_ingest_seconds_count 2"), std::string::npos);
}

TEST(MetricsEndpoint, AnAddressThatCannotBeBoundIsNamed) {
  ServerCore core(ServerOptions{});
  auto endpoint = MetricsEndpoint::start(core, "192.0.2.1:9");  // TEST-NET-1: not this machine's
  ASSERT_FALSE(endpoint);
  EXPECT_NE(endpoint.error().message().find("192.0.2.1:9"), std::string::npos) << endpoint.error().message();
}

}  // namespace
}  // namespace cvislam::server
