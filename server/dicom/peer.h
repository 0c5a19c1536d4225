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

// How we talk to a peer: DIMSE associations (C-STORE, C-GET, C-FIND,
// C-ECHO), or DICOMweb over HTTP(S) (STOW-RS, QIDO-RS, WADO-RS; PS3.18).
enum class PeerType { kDimse, kDicomWeb };

// How a series is pulled from a DIMSE peer (JobSpec.pacs_source): C-GET
// (the instances come back on our association), or C-MOVE with the
// server's own DICOM listener as the move destination (the peer opens
// associations to our first AE title; it must know that AE title, and the
// server must run its listener).
enum class RetrieveMethod { kGet, kMove };

// A DICOMweb peer's address and credentials. Paths, never secrets: the
// secret files are read when a request is made (so a rotated token is
// picked up without a restart), and their contents are never logged.
struct DicomWebEndpoint {
  // The service's base URL, http:// or https://, without credentials,
  // query or trailing slash ("http://pacs:8042/dicom-web"); requests go to
  // {url}/studies... (PS3.18 8.2 resource paths).
  std::string url;
  // At most one of: a bearer token (the file's text, trimmed, RFC 6750),
  // HTTP basic (user and the password file's text, trimmed, RFC 7617).
  std::string bearer_token_file;
  std::string basic_user;
  std::string basic_password_file;
  // Mutual TLS: our certificate and its unencrypted key (PEM), https only.
  std::string client_certificate;
  std::string client_key;
  // PEM CAs that sign the server's certificate (https; empty: the system's).
  std::string ca_certificates;
};

struct DicomPeer {
  std::string name;  // how rules and clients refer to it ("orthanc")
  PeerType type = PeerType::kDimse;
  // DICOMweb peers (type kDicomWeb) only; the DIMSE fields below (AE title,
  // host, port, tls, allowed_sources) are empty/default for them.
  DicomWebEndpoint web;
  std::string ae_title;  // 1-16 characters, no backslash
  std::string host;
  int port = 104;
  bool tls = false;  // associations with this peer use TLS
  // Deliveries to this peer send over up to this many associations at once
  // (1-16; 1: one after another). DIMSE waits for each C-STORE response, so
  // parallel associations keep a PACS's storage busy while we wait. For a
  // DICOMweb peer: STOW-RS requests in flight at once.
  int max_associations = 4;
  // DIMSE peers only (peers-file key `retrieve: get|move`).
  RetrieveMethod retrieve = RetrieveMethod::kGet;
  // Associations calling as this peer's AE title are accepted only from
  // these addresses (empty: from anywhere).
  std::vector<SourceNetwork> allowed_sources;
};

}  // namespace interslice::server::dicom

#endif  // INTERSLICE_SERVER_DICOM_PEER_H_
