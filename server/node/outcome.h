// What happened to a received or sent instance, in the words each
// protocol uses for it. DIMSE status codes are the common currency: a
// C-STORE response carries one, and DICOMweb's Store Instances Response
// reports the same codes as Failure Reason (0008,1197) (PS3.18 10.5.3), so
// both doors and both clients read and write them through here.
#ifndef INTERSLICE_SERVER_NODE_OUTCOME_H_
#define INTERSLICE_SERVER_NODE_OUTCOME_H_

#include <cstdint>
#include <string>

#include "absl/status/status.h"

namespace interslice::server::node {

// A C-STORE status (PS3.4 B.2.3) as one phrase: "Refused: OutOfResources"
// for 0xA7xx, "Error: DataSetDoesNotMatchSOPClass" for 0xA9xx, "Error:
// CannotUnderstand" for 0xCxxx, the named warnings, "Success", and
// "Unknown Status: 0x<hex>" otherwise: word for word what DCMTK's
// DU_cstoreStatusString says (a test holds the two together), so that no
// protocol but DIMSE needs DCMTK's network library for it.
std::string CStoreStatusText(uint16_t status);

// The status codes the intake's refusals become (PS3.4 B.2.3, and PS3.18
// 10.5.3's Failure Reason, which takes the same codes).
inline constexpr uint16_t kStoreProcessingFailure = 0x0110;
inline constexpr uint16_t kStoreSopClassNotSupported = 0x0122;
inline constexpr uint16_t kStoreOutOfResources = 0xA700;
inline constexpr uint16_t kStoreDoesNotMatch = 0xA900;
inline constexpr uint16_t kStoreCannotUnderstand = 0xC000;

// The one mapping of an instance's refusal by the intake (Intake::AddInstance,
// intake.h) to the status both doors answer with: RESOURCE_EXHAUSTED ->
// 0xA700 out of resources (limits, quota, a full disk); UNIMPLEMENTED ->
// 0x0122 SOP class not supported; INVALID_ARGUMENT -> 0xC000 cannot
// understand (not well-formed, no UIDs, another frame of reference);
// anything else -> 0x0110 processing failure. OK -> 0x0000.
uint16_t StoreStatusOfRefusal(const absl::Status& refusal);

}  // namespace interslice::server::node

#endif  // INTERSLICE_SERVER_NODE_OUTCOME_H_
