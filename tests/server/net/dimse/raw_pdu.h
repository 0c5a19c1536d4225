// A raw DICOM upper-layer client for the listener's tests: builds PDUs and
// command sets byte by byte (PS3.8 section 9, PS3.7 section 9.3) so that a
// test can send what no well-behaved tool would (nested command sets,
// hostile data sets, requests at one byte a second, half-open connections)
// and read what the listener answers.
#ifndef INTERSLICE_TESTS_SERVER_DICOM_RAW_PDU_H_
#define INTERSLICE_TESTS_SERVER_DICOM_RAW_PDU_H_

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

namespace interslice::testing {

struct PresentationContext {
  uint8_t id = 1;
  std::string abstract_syntax;
  std::vector<std::string> transfer_syntaxes;
};

// A-ASSOCIATE-RQ (type 01); `extra_user_items` are appended to its user
// information item (after maximum length and implementation class UID).
std::string AssociateRq(const std::string& called_ae,
                        const std::string& calling_ae,
                        const std::vector<PresentationContext>& contexts,
                        uint32_t max_pdu = 16384,
                        const std::string& extra_user_items = "");
// An item or sub-item: type, reserved, 2-byte big-endian length, value.
std::string PduItem(uint8_t type, const std::string& value);
// P-DATA-TF (type 04) with one PDV item.
std::string PData(uint8_t context_id, bool command, bool last,
                  const std::string& fragment);
std::string ReleaseRq();
std::string AbortRq();

// An implicit-VR little-endian element (a command set is made of these).
std::string ImplicitElement(uint16_t group, uint16_t element,
                            const std::string& value);
std::string ImplicitUs(uint16_t element, uint16_t value);  // group 0000
std::string ImplicitUid(uint16_t element, const std::string& uid);
// A command set with its group length in front.
std::string CommandSet(const std::string& elements);
std::string CStoreRq(uint16_t message_id, const std::string& sop_class,
                     const std::string& sop_instance);
std::string CEchoRq(uint16_t message_id);

// An explicit-VR little-endian data set that names a CT image (SOP class,
// SOP instance, study and series UIDs, modality) and then nests `depth`
// sequences of undefined length, one item each: 20 bytes a level going in,
// 16 coming out (depth 10,000: about 360 KB, issue 22's instance).
std::string NestedDataset(const std::string& sop_instance, int depth);
// The data set of a DICOM file (its meta group dropped), re-encoded in
// explicit VR little endian with DCMTK.
std::string DatasetOf(const std::string& path);

// A connected client socket (loopback; `source` "127.0.0.2" etc. binds the
// local end first). -1 on failure.
int Connect(int port, const std::string& source = "127.0.0.1");
bool SendAll(int fd, const std::string& bytes);

struct Pdu {
  uint8_t type = 0;
  std::string body;
};
// The next PDU, or nullopt when the connection closed or nothing came
// within `seconds`.
std::optional<Pdu> ReadPdu(int fd, double seconds);
// From an A-ASSOCIATE-AC: the result of presentation context `id`
// (0 = acceptance), or -1.
int ContextResult(const Pdu& ac, uint8_t id);
// From a P-DATA-TF holding a whole response command: its Status (0000,0900),
// or -1.
int ResponseStatus(const Pdu& pdata);

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_SERVER_DICOM_RAW_PDU_H_
