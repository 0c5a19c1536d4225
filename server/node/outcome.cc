#include "server/node/outcome.h"

#include "absl/strings/str_format.h"

namespace interslice::server::node {

std::string CStoreStatusText(uint16_t status) {
  switch (status) {
    case 0x0000:
      return "Success";
    case 0x0122:
      return "Refused: SOPClassNotSupported";
    case 0xB000:
      return "Warning: CoercionOfDataElements";
    case 0xB006:
      return "Warning: ElementsDiscarded";
    case 0xB007:
      return "Warning: DataSetDoesNotMatchSOPClass";
    default:
      break;
  }
  switch (status & 0xFF00) {
    case 0xA700:
      return "Refused: OutOfResources";
    case 0xA900:
      return "Error: DataSetDoesNotMatchSOPClass";
    default:
      break;
  }
  if ((status & 0xF000) == 0xC000) return "Error: CannotUnderstand";
  return absl::StrFormat("Unknown Status: 0x%x", status);
}

uint16_t StoreStatusOfRefusal(const absl::Status& refusal) {
  switch (refusal.code()) {
    case absl::StatusCode::kOk:
      return 0x0000;
    case absl::StatusCode::kResourceExhausted:
      return kStoreOutOfResources;
    case absl::StatusCode::kUnimplemented:
      return kStoreSopClassNotSupported;
    case absl::StatusCode::kInvalidArgument:
      return kStoreCannotUnderstand;
    default:
      return kStoreProcessingFailure;
  }
}

}  // namespace interslice::server::node
