// A DICOM application entity the server talks to: a PACS, a modality or a
// workstation, as listed in the peers file (--dicom-peers, see
// server/dicom/config.h for the file format).
//
// Shared by the receiving side (which calling AE titles may associate) and
// the sending side (where results are stored, where series are retrieved
// from). Plain data: no DCMTK types here, so that this header stays cheap.
#ifndef INTERSLICE_SERVER_DICOM_PEER_H_
#define INTERSLICE_SERVER_DICOM_PEER_H_

#include <string>

namespace interslice::server::dicom {

// TLS material for DICOM associations (DICOM PS3.15 Annex B, BCP 195
// profile). Empty paths mean "no TLS".
struct DicomTlsFiles {
  std::string certificate;      // PEM: our certificate
  std::string private_key;      // PEM: its key (unencrypted)
  std::string ca_certificates;  // PEM: CAs that sign peer certificates
};

struct DicomPeer {
  std::string name;      // how rules and clients refer to it ("orthanc")
  std::string ae_title;  // 1-16 characters, no backslash
  std::string host;
  int port = 104;
  bool tls = false;  // associations with this peer use TLS
};

}  // namespace interslice::server::dicom

#endif  // INTERSLICE_SERVER_DICOM_PEER_H_
