// A DICOM application entity the server talks to: a PACS, a modality or a
// workstation, as listed in the peers file (--dicom-peers, see
// server/dicom/config.h for the file format).
//
// Shared by the receiving side (which calling AE titles may associate) and
// the sending side (where results are stored, where series are retrieved
// from). Plain data: no DCMTK types here, so that this header stays cheap.
#ifndef INTERSLICE_SERVER_DICOM_PEER_H_
#define INTERSLICE_SERVER_DICOM_PEER_H_

#include <cstdint>
#include <string>
#include <vector>

namespace interslice::server::dicom {

// TLS material for DICOM associations (DICOM PS3.15 Annex B, BCP 195
// profile). Empty paths mean "no TLS".
struct DicomTlsFiles {
  std::string certificate;      // PEM: our certificate
  std::string private_key;      // PEM: its key (unencrypted)
  std::string ca_certificates;  // PEM: CAs that sign peer certificates
};

// An address range: the first `prefix_bits` bits of `address` (IPv4 in the
// first 4 bytes, family 4; IPv6, family 6), as "10.1.0.0/16" or "::1".
struct SourceNetwork {
  int family = 4;
  unsigned char address[16] = {};
  int prefix_bits = 32;
  std::string text;  // as written, for messages
};

struct DicomPeer {
  std::string name;      // how rules and clients refer to it ("orthanc")
  std::string ae_title;  // 1-16 characters, no backslash
  std::string host;
  int port = 104;
  bool tls = false;  // associations with this peer use TLS
  // Deliveries to this peer send over up to this many associations at once
  // (1-16; 1: one after another). DIMSE waits for each C-STORE response, so
  // parallel associations keep a PACS's storage busy while we wait.
  int max_associations = 4;
  // Associations calling as this peer's AE title are accepted only from
  // these addresses (empty: from anywhere).
  std::vector<SourceNetwork> allowed_sources;
};

}  // namespace interslice::server::dicom

#endif  // INTERSLICE_SERVER_DICOM_PEER_H_
