#include "common/mcap/records.hpp"

#include <cstdio>

namespace cvislam::mcap {

std::string opcodeName(std::uint8_t opcode) {
  switch (static_cast<Opcode>(opcode)) {
    case Opcode::kHeader:
      return "Header";
    case Opcode::kFooter:
      return "Footer";
    case Opcode::kSchema:
      return "Schema";
    case Opcode::kChannel:
      return "Channel";
    case Opcode::kMessage:
      return "Message";
    case Opcode::kChunk:
      return "Chunk";
    case Opcode::kMessageIndex:
      return "MessageIndex";
    case Opcode::kChunkIndex:
      return "ChunkIndex";
    case Opcode::kAttachment:
      return "Attachment";
    case Opcode::kAttachmentIndex:
      return "AttachmentIndex";
    case Opcode::kStatistics:
      return "Statistics";
    case Opcode::kMetadata:
      return "Metadata";
    case Opcode::kMetadataIndex:
      return "MetadataIndex";
    case Opcode::kSummaryOffset:
      return "SummaryOffset";
    case Opcode::kDataEnd:
      return "DataEnd";
  }
  char text[16];
  std::snprintf(text, sizeof text, "opcode 0x%02x", static_cast<unsigned>(opcode));
  return text;
}

std::string_view compressionName(Compression compression) {
  switch (compression) {
    case Compression::kNone:
      return "";
    case Compression::kZstd:
      return "zstd";
    case Compression::kLz4:
      return "lz4";
  }
  return "";
}

}  // namespace cvislam::mcap
