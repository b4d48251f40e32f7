// Failures of the server's own storage (its store file, its database) as a client may see them. Their text names
// file paths and database hosts, which are the operator's business: the text goes to the server's log under a
// number, and the client gets the number to quote.
#pragma once

#include <string>

#include "common/core/result.hpp"

namespace cvislam::server {

// Logs `error` as "[server] error #N: ..." on stderr and returns "server error #N, in its log".
std::string logForOperator(const Error& error);

}  // namespace cvislam::server
