// What happened to a received or sent instance, in the words each
// protocol uses for it. DIMSE status codes are the common currency: a
// C-STORE response carries one, and DICOMweb's Store Instances Response
// reports the same codes as Failure Reason (0008,1197) (PS3.18 10.5.3), so
// both doors and both clients read and write them through here.
#ifndef INTERSLICE_SERVER_NODE_OUTCOME_H_
#define INTERSLICE_SERVER_NODE_OUTCOME_H_

#include <cstdint>
#include <string>

namespace interslice::server::node {

// A C-STORE status (PS3.4 B.2.3) as one phrase: "Refused: OutOfResources"
// for 0xA7xx, "Error: DataSetDoesNotMatchSOPClass" for 0xA9xx, "Error:
// CannotUnderstand" for 0xCxxx, the named warnings, "Success", and
// "Unknown Status: 0x<hex>" otherwise: word for word what DCMTK's
// DU_cstoreStatusString says (a test holds the two together), so that no
// protocol but DIMSE needs DCMTK's network library for it.
std::string CStoreStatusText(uint16_t status);

}  // namespace interslice::server::node

#endif  // INTERSLICE_SERVER_NODE_OUTCOME_H_
