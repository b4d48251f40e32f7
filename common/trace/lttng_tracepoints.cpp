// The probes of common/trace/lttng_tracepoints.h, compiled once (CMake option CVISLAM_LTTNG).
#define LTTNG_UST_TRACEPOINT_CREATE_PROBES
#define LTTNG_UST_TRACEPOINT_DEFINE
#include "common/trace/lttng_tracepoints.h"
