// One PostgreSQL connection (libpq), with parameters and results in binary form: what the replicas' shared store
// and their mission leases are written with. libpq's header stays in pg_connection.cpp.
//
// Not thread-safe: one caller at a time (its owners hold it under their own mutex). A connection that broke is
// re-established at the next exec(); the statement that saw it break fails with kUnavailable and is not retried,
// since it may have committed.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "common/core/result.hpp"

struct pg_conn;
struct pg_result;

namespace cvislam::server::cluster {

// Parameters $1, $2, ... of one statement, each with its type.
class PgParams {
 public:
  PgParams& text(std::string_view value);
  PgParams& bytes(std::string_view value);  // bytea
  PgParams& i16(std::int16_t value);
  PgParams& i32(std::int32_t value);
  PgParams& i64(std::int64_t value);
  PgParams& f64(double value);

  [[nodiscard]] int size() const { return static_cast<int>(values_.size()); }
  [[nodiscard]] const std::vector<unsigned int>& types() const { return types_; }
  [[nodiscard]] const std::vector<std::string>& values() const { return values_; }

 private:
  PgParams& add(unsigned int type, std::string value);
  std::vector<unsigned int> types_;
  std::vector<std::string> values_;
};

// A statement's rows, in binary form: read each column with the getter of its SQL type.
class PgResult {
 public:
  explicit PgResult(pg_result* result);
  ~PgResult();
  PgResult(PgResult&& other) noexcept;
  PgResult& operator=(PgResult&&) = delete;
  PgResult(const PgResult&) = delete;
  PgResult& operator=(const PgResult&) = delete;

  [[nodiscard]] int rows() const;
  [[nodiscard]] std::int64_t affected() const;  // rows an INSERT, UPDATE or DELETE changed
  [[nodiscard]] bool isNull(int row, int column) const;
  [[nodiscard]] std::string_view bytes(int row, int column) const;  // text and bytea
  [[nodiscard]] std::int16_t i16(int row, int column) const;
  [[nodiscard]] std::int32_t i32(int row, int column) const;
  [[nodiscard]] std::int64_t i64(int row, int column) const;
  [[nodiscard]] double f64(int row, int column) const;
  [[nodiscard]] bool boolean(int row, int column) const;
  [[nodiscard]] pg_result* raw() const { return result_; }

 private:
  pg_result* result_;
};

// How long a call may wait on the database. Without bounds a statement blocks for as long as TCP keeps a dead
// connection open (minutes), and the replica's appends and lease renewals wait behind it. Each is a default that
// the connection string may override (connect_timeout, keepalives_*, tcp_user_timeout), except the statement
// timeout, which is set on the session.
struct PgTimeouts {
  int connect_s = 5;
  int statement_ms = 10000;      // the server cancels a statement that runs longer (waiting on a lock included)
  int unacked_ms = 10000;        // tcp_user_timeout: sent data unacknowledged this long breaks the connection
  int keepalive_idle_s = 5;      // a silent connection is probed after this long ...
  int keepalive_interval_s = 2;  // ... every this long ...
  int keepalive_count = 3;       // ... and given up after this many unanswered probes
};

class PgConnection {
 public:
  // Connects with a libpq connection string ("host=127.0.0.1 port=5432 user=cvislam dbname=cvislam"). The error
  // names the server and libpq's reason; `what` says what the connection is for.
  static Result<std::unique_ptr<PgConnection>> open(const std::string& conninfo, const std::string& what,
                                                    const PgTimeouts& timeouts = {});
  ~PgConnection();
  PgConnection(const PgConnection&) = delete;
  PgConnection& operator=(const PgConnection&) = delete;

  // Runs statements separated by ';' that take no parameters and return no rows (schema set-up).
  Status execScript(const std::string& sql);
  // Runs one statement. A unique
  // violation is kAlreadyExists, a lost connection kUnavailable, anything else kIoError with the server's message.
  Result<PgResult> exec(const std::string& sql, const PgParams& params = {});

  [[nodiscard]] const std::string& describe() const { return description_; }  // "postgresql host:port/db"

 private:
  PgConnection(pg_conn* connection, std::string description, std::string what, PgTimeouts timeouts);
  // Sets the session's statement timeout (after connecting, and after every reconnection).
  bool configureSession();
  // Reconnects a broken connection; false when the database stays unreachable.
  bool reconnect();
  pg_conn* connection_;
  PgTimeouts timeouts_;
  std::string description_;
  std::string what_;
};

// "host=... password=secret" with the password's value replaced, for messages and logs.
std::string redactConninfo(const std::string& conninfo);

}  // namespace cvislam::server::cluster
