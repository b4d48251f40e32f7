// The agent's side of the downlink's covisible map: a server message checked and written into the fixed-size
// AnchorMessage that goes on to mapping. The server is trusted no more than any peer: a message with a
// non-finite value, a pose that is not a rotation, columns of different lengths, an octave beyond the pyramid,
// an agent id over 16 bits, or more than the capacity, is refused whole, with an error that names the field;
// the agent keeps going. Whether an observed point is one the agent still holds is for mapping to resolve (it
// may have evicted it): the decoder checks the form, not the agent's map.
#pragma once

#include "agent_rt/messages/messages.hpp"
#include "common/core/result.hpp"

#include <google/protobuf/repeated_ptr_field.h>

namespace cvislam::v1 {
class CovisibleMap;
class KeyframeState;
}  // namespace cvislam::v1

namespace cvislam::agent {

// Fills `out` (its counts and the entries below them) from `in`. On error, `out` is left with zero counts.
Status decodeCovisibleMap(const v1::CovisibleMap& in, std::uint64_t sequence, AnchorMessage& out);

// Fills out.corrections from the downlink's corrected keyframes of agent `agent`: the newest (highest counters)
// kMaxAnchorCorrectionsPerMessage when there are more. A correction with a non-finite or malformed state is
// refused whole, like a covisible map (`out` then has no corrections).
Status decodeCorrections(const google::protobuf::RepeatedPtrField<v1::KeyframeState>& in, AgentId agent,
                         AnchorMessage& out);

}  // namespace cvislam::agent
