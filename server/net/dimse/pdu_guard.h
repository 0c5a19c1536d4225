// The listener's inspector of what a peer sends, byte by byte, before DCMTK
// reads it (DICOM PS3.8 section 9, the upper layer PDUs).
//
// DCMTK parses PDUs and DIMSE command sets on the association's thread, and
// its data-set parser recurses without a depth limit, so a command set with
// nested sequences could overflow that thread's stack like a data set can
// (issue 22). Every byte the listener reads goes through a PduGuard first;
// the connection is cut at the first violation, before DCMTK has a complete
// PDU to act on. What it allows:
//  - first, one A-ASSOCIATE-RQ (type 01) of at most max_request_bytes whose
//    items tile it exactly: application context (10), presentation contexts
//    (20, at most max_presentation_contexts, each one abstract syntax (30)
//    and 1..max_transfer_syntaxes transfer syntaxes (40)), user information
//    (50, at most max_user_items sub-items, e.g. one role selection per
//    context, each of a known type (51-58) and well-formed by PS3.7
//    D.3.3); UIDs 1..64 bytes;
//  - then only P-DATA-TF (04, at most max_pdata_bytes, PDV items that tile
//    it, odd context IDs, no reserved control bits), A-RELEASE-RQ/RP (05,
//    06) and A-ABORT (07) of their fixed length;
//  - command sets (PS3.7 6.3.1: implicit VR little endian, group 0000 only)
//    made of elements DCMTK's dictionary knows as command elements, with
//    defined lengths, at most max_command_bytes and 64 elements: no
//    sequence can appear in one, and no element longer than a command set
//    may be (DCMTK allocates the declared length first); a command set that
//    gives its CommandGroupLength (0000,0000) must hold exactly that many
//    bytes after it when its last fragment ends (issue 39: one that lied
//    held an association slot until the DIMSE timeout);
//  - a data-set PDV only after a command whose CommandDataSetType
//    (0000,0800) announces one (PS3.7 9.3: not 0x0101), on that command's
//    presentation context, until its last fragment. Data-set fragments
//    pass otherwise unread (the listener writes them to a file and scans
//    it, dataset_scan.h). (Fuzzer finding: after a C-ECHO, data-set PDVs
//    holding a command set with a 4 GiB element made DCMTK allocate it.)
// Pure (no I/O, no clock): the connection wrapper feeds it and keeps time.
#ifndef INTERSLICE_SERVER_NET_DIMSE_PDU_GUARD_H_
#define INTERSLICE_SERVER_NET_DIMSE_PDU_GUARD_H_

#include <cstddef>
#include <cstdint>
#include <string>

#include "absl/status/status.h"

namespace interslice::server::dimse {

struct PduGuardLimits {
  uint32_t max_request_bytes = 256 * 1024;
  // The PDU length field of a P-DATA-TF: our announced maximum (PS3.8
  // D.1: it bounds the variable field) and some slack for peers that count
  // the header in.
  uint32_t max_pdata_bytes = 65536 + 64;
  uint32_t max_command_bytes = 64 * 1024;
  int max_presentation_contexts = 128;
  int max_transfer_syntaxes = 64;
  // Role selection (54) can come once per presentation context.
  int max_user_items = 256;
};

class PduGuard {
 public:
  explicit PduGuard(const PduGuardLimits& limits = {}) : limits_(limits) {}

  // The next `n` bytes from the peer. OK, or INVALID_ARGUMENT naming the
  // first violation (no data-set values in it); once failed, it stays
  // failed.
  absl::Status Feed(const unsigned char* data, size_t n);

  // A PDU has begun (its first byte was fed) and not ended.
  bool in_pdu() const { return header_fill_ > 0 || body_left_ > 0; }
  // The whole A-ASSOCIATE-RQ was fed (and was valid).
  bool request_complete() const { return pdus_ > 0; }
  // How many bytes of the first PDU (the request) are still to come, once
  // its header has been fed; 0 before that and after it.
  uint64_t request_bytes_left() const {
    return pdus_ == 0 && header_fill_ == 0 ? body_left_ : 0;
  }
  // PDUs completed so far.
  int64_t pdus() const { return pdus_; }

 private:
  absl::Status Fail(std::string what);
  absl::Status StartPdu();
  absl::Status CheckRequest() const;
  absl::Status FeedPData(const unsigned char* data, size_t n);
  absl::Status FeedCommand(const unsigned char* data, size_t n);
  absl::Status EndCommand();

  const PduGuardLimits limits_;
  absl::Status failed_;
  // The PDU being read.
  unsigned char header_[6];
  int header_fill_ = 0;
  uint8_t type_ = 0;
  uint64_t body_left_ = 0;
  int64_t pdus_ = 0;
  std::string request_;  // the A-ASSOCIATE-RQ's body, checked when complete
  // P-DATA-TF: the PDV item being read.
  unsigned char pdv_header_[6];
  int pdv_header_fill_ = 0;
  uint64_t pdv_left_ = 0;
  bool pdv_command_ = false;
  bool pdv_last_ = false;
  // The command set being read (across PDVs and PDUs).
  unsigned char element_header_[8];
  int element_header_fill_ = 0;
  uint64_t element_left_ = 0;
  uint64_t command_bytes_ = 0;
  int command_elements_ = 0;
  // CommandGroupLength (0000,0000) as it streams in, and the command set's
  // bytes when it has arrived whole (12: the element itself).
  unsigned char group_length_[4] = {};
  int group_length_fill_ = 0;
  bool group_length_given_ = false;
  // CommandDataSetType (0000,0800) of the command being read, as it
  // streams in (0x0101: no data set follows), and its context.
  uint16_t element_ = 0;
  unsigned char data_set_type_[2] = {0x01, 0x01};
  int data_set_type_fill_ = 0;
  uint8_t command_context_ = 0;
  // Whether the last command announced a data set that has not ended yet,
  // and on which presentation context it must come.
  bool data_set_expected_ = false;
  uint8_t data_set_context_ = 0;
};

}  // namespace interslice::server::dimse

#endif  // INTERSLICE_SERVER_NET_DIMSE_PDU_GUARD_H_
