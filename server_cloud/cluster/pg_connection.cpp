#include "server_cloud/cluster/pg_connection.hpp"

#include <libpq-fe.h>

#include <cstring>
#include <regex>

namespace cvislam::server::cluster {

namespace {

// The OIDs of the built-in types the parameters use (pg_type.dat; fixed since PostgreSQL 7).
constexpr unsigned int kBytea = 17;
constexpr unsigned int kInt8 = 20;
constexpr unsigned int kInt2 = 21;
constexpr unsigned int kInt4 = 23;
constexpr unsigned int kText = 25;
constexpr unsigned int kFloat8 = 701;

std::string bigEndian(std::uint64_t v, int bytes) {
  std::string out(static_cast<std::size_t>(bytes), '\0');
  for (int i = 0; i < bytes; ++i)
    out[static_cast<std::size_t>(i)] = static_cast<char>((v >> (8 * (bytes - 1 - i))) & 0xFFU);
  return out;
}

std::uint64_t fromBigEndian(const char* data, int bytes) {
  std::uint64_t v = 0;
  for (int i = 0; i < bytes; ++i) v = (v << 8U) | static_cast<std::uint8_t>(data[i]);
  return v;
}

std::string trimmed(const char* message) {
  std::string s = message != nullptr ? message : "";
  while (!s.empty() && (s.back() == '\n' || s.back() == ' ')) s.pop_back();
  return s;
}

}  // namespace

PgParams& PgParams::add(unsigned int type, std::string value) {
  types_.push_back(type);
  values_.push_back(std::move(value));
  return *this;
}
PgParams& PgParams::text(std::string_view value) {
  return add(kText, std::string(value));
}
PgParams& PgParams::bytes(std::string_view value) {
  return add(kBytea, std::string(value));
}
PgParams& PgParams::i16(std::int16_t value) {
  return add(kInt2, bigEndian(static_cast<std::uint16_t>(value), 2));
}
PgParams& PgParams::i32(std::int32_t value) {
  return add(kInt4, bigEndian(static_cast<std::uint32_t>(value), 4));
}
PgParams& PgParams::i64(std::int64_t value) {
  return add(kInt8, bigEndian(static_cast<std::uint64_t>(value), 8));
}
PgParams& PgParams::f64(double value) {
  std::uint64_t bits = 0;
  std::memcpy(&bits, &value, sizeof bits);
  return add(kFloat8, bigEndian(bits, 8));
}

PgResult::PgResult(pg_result* result) : result_(result) {}
PgResult::~PgResult() {
  PQclear(result_);
}
PgResult::PgResult(PgResult&& other) noexcept : result_(other.result_) {
  other.result_ = nullptr;
}
int PgResult::rows() const {
  return PQntuples(result_);
}
std::int64_t PgResult::affected() const {
  const char* n = PQcmdTuples(result_);
  return n != nullptr && *n != '\0' ? std::strtoll(n, nullptr, 10) : 0;
}
bool PgResult::isNull(int row, int column) const {
  return PQgetisnull(result_, row, column) != 0;
}
std::string_view PgResult::bytes(int row, int column) const {
  return {PQgetvalue(result_, row, column), static_cast<std::size_t>(PQgetlength(result_, row, column))};
}
std::int16_t PgResult::i16(int row, int column) const {
  return static_cast<std::int16_t>(fromBigEndian(PQgetvalue(result_, row, column), 2));
}
std::int32_t PgResult::i32(int row, int column) const {
  return static_cast<std::int32_t>(fromBigEndian(PQgetvalue(result_, row, column), 4));
}
std::int64_t PgResult::i64(int row, int column) const {
  return static_cast<std::int64_t>(fromBigEndian(PQgetvalue(result_, row, column), 8));
}
double PgResult::f64(int row, int column) const {
  const std::uint64_t bits = fromBigEndian(PQgetvalue(result_, row, column), 8);
  double v = 0.0;
  std::memcpy(&v, &bits, sizeof v);
  return v;
}
bool PgResult::boolean(int row, int column) const {
  return *PQgetvalue(result_, row, column) != 0;
}

std::string redactConninfo(const std::string& conninfo) {
  static const std::regex kPassword(R"((password\s*=\s*)('[^']*'|\S+))");
  // A URI carries it as postgresql://user:secret@host/db.
  static const std::regex kUriPassword(R"(((?:postgres|postgresql)://[^:/@\s]*:)[^@\s]*@)");
  return std::regex_replace(std::regex_replace(conninfo, kPassword, "$1***"), kUriPassword, "$1***@");
}

Result<std::unique_ptr<PgConnection>> PgConnection::open(const std::string& conninfo, const std::string& what,
                                                         const PgTimeouts& timeouts) {
  if (conninfo.empty()) return Error{ErrorCode::kInvalidArgument, what + ": no PostgreSQL connection string given"};
  char* parse_error = nullptr;
  PQconninfoOption* parsed = PQconninfoParse(conninfo.c_str(), &parse_error);
  if (parsed == nullptr) {
    const std::string reason = trimmed(parse_error);
    PQfreemem(parse_error);
    return Error{ErrorCode::kInvalidArgument, what + ": the PostgreSQL connection string '" + redactConninfo(conninfo) +
                                                  "' does not parse: " + reason};
  }
  PQconninfoFree(parsed);
  // Our bounds first, then the connection string expanded over them: what it says wins.
  const std::string connect = std::to_string(timeouts.connect_s);
  const std::string unacked = std::to_string(timeouts.unacked_ms);
  const std::string idle = std::to_string(timeouts.keepalive_idle_s);
  const std::string interval = std::to_string(timeouts.keepalive_interval_s);
  const std::string count = std::to_string(timeouts.keepalive_count);
  const char* const keys[] = {"connect_timeout",  "keepalives",       "keepalives_idle", "keepalives_interval",
                              "keepalives_count", "tcp_user_timeout", "dbname",          nullptr};
  const char* const values[] = {
      connect.c_str(), "1", idle.c_str(), interval.c_str(), count.c_str(), unacked.c_str(), conninfo.c_str(), nullptr};
  PGconn* connection = PQconnectdbParams(keys, values, /*expand_dbname=*/1);
  if (connection == nullptr) return Error{ErrorCode::kInternal, what + ": libpq could not allocate a connection"};
  if (PQstatus(connection) != CONNECTION_OK) {
    const std::string reason = trimmed(PQerrorMessage(connection));
    PQfinish(connection);
    return Error{ErrorCode::kUnavailable, what + ": cannot connect to PostgreSQL ('" + redactConninfo(conninfo) +
                                              "'): " + reason + "; is the database running and reachable?"};
  }
  // Warnings (e.g. "relation already exists, skipping") are not errors: keep them out of the server's log.
  PQsetNoticeProcessor(
      connection, [](void*, const char*) {}, nullptr);
  std::string description =
      std::string("postgresql ") + PQhost(connection) + ":" + PQport(connection) + "/" + PQdb(connection);
  std::unique_ptr<PgConnection> out(new PgConnection(connection, std::move(description), what, timeouts));
  if (!out->configureSession()) {
    return Error{ErrorCode::kUnavailable, what + ": " + out->describe() + ": cannot set the statement timeout: " +
                                              trimmed(PQerrorMessage(connection))};
  }
  return out;
}

PgConnection::PgConnection(pg_conn* connection, std::string description, std::string what, PgTimeouts timeouts)
    : connection_(connection), timeouts_(timeouts), description_(std::move(description)), what_(std::move(what)) {}

bool PgConnection::configureSession() {
  const std::string sql = "SET statement_timeout = " + std::to_string(timeouts_.statement_ms);
  PgResult result(PQexec(connection_, sql.c_str()));
  return result.raw() != nullptr && PQresultStatus(result.raw()) == PGRES_COMMAND_OK;
}

bool PgConnection::reconnect() {
  PQreset(connection_);
  return PQstatus(connection_) == CONNECTION_OK && configureSession();
}

PgConnection::~PgConnection() {
  PQfinish(connection_);
}

Status PgConnection::execScript(const std::string& sql) {
  if (PQstatus(connection_) != CONNECTION_OK) (void)reconnect();
  PgResult result(PQexec(connection_, sql.c_str()));
  pg_result* raw = result.raw();
  if (raw != nullptr && PQresultStatus(raw) == PGRES_COMMAND_OK) return Status::Ok();
  const std::string message = trimmed(raw != nullptr ? PQresultErrorMessage(raw) : PQerrorMessage(connection_));
  return Error{ErrorCode::kIoError, what_ + " (" + description_ + "): " + message};
}

Result<PgResult> PgConnection::exec(const std::string& sql, const PgParams& params) {
  if (PQstatus(connection_) != CONNECTION_OK) {
    if (!reconnect()) {
      return Error{ErrorCode::kUnavailable,
                   what_ + ": " + description_ + " is unreachable: " + trimmed(PQerrorMessage(connection_))};
    }
  }
  pg_result* raw = nullptr;
  if (params.size() == 0) {
    raw = PQexecParams(connection_, sql.c_str(), 0, nullptr, nullptr, nullptr, nullptr, /*resultFormat=*/1);
  } else {
    std::vector<const char*> values;
    std::vector<int> lengths;
    std::vector<int> formats(static_cast<std::size_t>(params.size()), 1);
    for (const std::string& v : params.values()) {
      values.push_back(v.data());
      lengths.push_back(static_cast<int>(v.size()));
    }
    raw = PQexecParams(connection_, sql.c_str(), params.size(), params.types().data(), values.data(), lengths.data(),
                       formats.data(), /*resultFormat=*/1);
  }
  PgResult result(raw);
  const ExecStatusType status = raw != nullptr ? PQresultStatus(raw) : PGRES_FATAL_ERROR;
  if (status == PGRES_COMMAND_OK || status == PGRES_TUPLES_OK) return result;
  const char* state = raw != nullptr ? PQresultErrorField(raw, PG_DIAG_SQLSTATE) : nullptr;
  const std::string message = trimmed(raw != nullptr ? PQresultErrorMessage(raw) : PQerrorMessage(connection_));
  if (state != nullptr && std::strcmp(state, "23505") == 0) {
    return Error{ErrorCode::kAlreadyExists, what_ + ": " + message};
  }
  if (PQstatus(connection_) != CONNECTION_OK) {
    return Error{ErrorCode::kUnavailable, what_ + ": the connection to " + description_ + " broke: " + message};
  }
  return Error{ErrorCode::kIoError, what_ + " (" + description_ + "): " + message};
}

}  // namespace cvislam::server::cluster
