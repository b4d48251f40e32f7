// LTTng-UST tracepoints of cvislam's trace points (CMake option CVISLAM_LTTNG): every span and instant that
// common/trace/trace.hpp records also fires `cvislam:span`, whether or not the process writes its own trace, so a
// production system can trace with an LTTng session alone. Fields: the event's name, its start and duration on the
// steady clock (-1 for an instant), its argument keys joined by commas, and their integer values in that order.
// Only lttng_tracepoints.cpp and trace.cpp include this, and only with CVISLAM_LTTNG.
#undef LTTNG_UST_TRACEPOINT_PROVIDER
#define LTTNG_UST_TRACEPOINT_PROVIDER cvislam

#undef LTTNG_UST_TRACEPOINT_INCLUDE
#define LTTNG_UST_TRACEPOINT_INCLUDE "common/trace/lttng_tracepoints.h"

#if !defined(CVISLAM_LTTNG_TRACEPOINTS_H) || defined(LTTNG_UST_TRACEPOINT_HEADER_MULTI_READ)
#define CVISLAM_LTTNG_TRACEPOINTS_H

#include <lttng/tracepoint.h>
#include <stdint.h>

// clang-format off
LTTNG_UST_TRACEPOINT_EVENT(
    cvislam, span,
    LTTNG_UST_TP_ARGS(const char*, name, int64_t, begin_ns, int64_t, duration_ns, const char*, keys,
                      const int64_t*, values, unsigned int, count),
    LTTNG_UST_TP_FIELDS(
        lttng_ust_field_string(name, name)
        lttng_ust_field_integer(int64_t, begin_ns, begin_ns)
        lttng_ust_field_integer(int64_t, duration_ns, duration_ns)
        lttng_ust_field_string(keys, keys)
        lttng_ust_field_sequence(int64_t, values, values, unsigned int, count)))
// clang-format on

#endif  // CVISLAM_LTTNG_TRACEPOINTS_H

#include <lttng/tracepoint-event.h>
