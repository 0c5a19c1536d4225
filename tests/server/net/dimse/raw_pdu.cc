#include "tests/server/net/dimse/raw_pdu.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <cstring>

#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcostrmb.h"
#include "dcmtk/dcmdata/dcuid.h"

namespace interslice::testing {
namespace {

void Be16(std::string& out, uint16_t v) {
  out.push_back(static_cast<char>(v >> 8));
  out.push_back(static_cast<char>(v & 0xFF));
}
void Be32(std::string& out, uint32_t v) {
  Be16(out, static_cast<uint16_t>(v >> 16));
  Be16(out, static_cast<uint16_t>(v & 0xFFFF));
}
void Le16(std::string& out, uint16_t v) {
  out.push_back(static_cast<char>(v & 0xFF));
  out.push_back(static_cast<char>(v >> 8));
}
void Le32(std::string& out, uint32_t v) {
  Le16(out, static_cast<uint16_t>(v & 0xFFFF));
  Le16(out, static_cast<uint16_t>(v >> 16));
}
std::string Item(uint8_t type, const std::string& value) {
  std::string out;
  out.push_back(static_cast<char>(type));
  out.push_back(0);
  Be16(out, static_cast<uint16_t>(value.size()));
  return out + value;
}
std::string MakePdu(uint8_t type, const std::string& body) {
  std::string out;
  out.push_back(static_cast<char>(type));
  out.push_back(0);
  Be32(out, static_cast<uint32_t>(body.size()));
  return out + body;
}
std::string Ae(const std::string& ae) {
  std::string out = ae.substr(0, 16);
  out.resize(16, ' ');
  return out;
}
std::string Even(std::string uid) {
  if (uid.size() % 2 != 0) uid.push_back('\0');
  return uid;
}
// Explicit VR little endian, short form.
std::string Explicit(uint16_t group, uint16_t element, const char* vr,
                     const std::string& value) {
  std::string out;
  Le16(out, group);
  Le16(out, element);
  out.append(vr, 2);
  Le16(out, static_cast<uint16_t>(value.size()));
  return out + value;
}

}  // namespace

std::string PduItem(uint8_t type, const std::string& value) {
  return Item(type, value);
}

std::string AssociateRq(const std::string& called_ae,
                        const std::string& calling_ae,
                        const std::vector<PresentationContext>& contexts,
                        uint32_t max_pdu, const std::string& extra_user_items) {
  std::string body;
  Be16(body, 1);  // protocol version
  Be16(body, 0);
  body += Ae(called_ae) + Ae(calling_ae);
  body.append(32, '\0');
  body += Item(0x10, "1.2.840.10008.3.1.1.1");
  for (const PresentationContext& c : contexts) {
    std::string value;
    value.push_back(static_cast<char>(c.id));
    value.append(3, '\0');
    value += Item(0x30, c.abstract_syntax);
    for (const std::string& ts : c.transfer_syntaxes) value += Item(0x40, ts);
    body += Item(0x20, value);
  }
  std::string max_length;
  Be32(max_length, max_pdu);
  std::string user =
      Item(0x51, max_length) + Item(0x52, "1.2.3.4.5.6.7.8") + extra_user_items;
  body += Item(0x50, user);
  return MakePdu(0x01, body);
}

std::string PData(uint8_t context_id, bool command, bool last,
                  const std::string& fragment) {
  std::string item;
  Be32(item, static_cast<uint32_t>(fragment.size() + 2));
  item.push_back(static_cast<char>(context_id));
  item.push_back(static_cast<char>((command ? 1 : 0) | (last ? 2 : 0)));
  return MakePdu(0x04, item + fragment);
}

std::string ReleaseRq() { return MakePdu(0x05, std::string(4, '\0')); }
std::string AbortRq() { return MakePdu(0x07, std::string(4, '\0')); }

std::string ImplicitElement(uint16_t group, uint16_t element,
                            const std::string& value) {
  std::string out;
  Le16(out, group);
  Le16(out, element);
  Le32(out, static_cast<uint32_t>(value.size()));
  return out + value;
}
std::string ImplicitUs(uint16_t element, uint16_t value) {
  std::string v;
  Le16(v, value);
  return ImplicitElement(0x0000, element, v);
}
std::string ImplicitUid(uint16_t element, const std::string& uid) {
  return ImplicitElement(0x0000, element, Even(uid));
}
std::string CommandSet(const std::string& elements) {
  std::string length;
  Le32(length, static_cast<uint32_t>(elements.size()));
  return ImplicitElement(0x0000, 0x0000, length) + elements;
}
std::string CStoreRq(uint16_t message_id, const std::string& sop_class,
                     const std::string& sop_instance) {
  return CommandSet(
      ImplicitUid(0x0002, sop_class) + ImplicitUs(0x0100, 0x0001) +
      ImplicitUs(0x0110, message_id) + ImplicitUs(0x0700, 0) +
      ImplicitUs(0x0800, 0x0000) + ImplicitUid(0x1000, sop_instance));
}
std::string CEchoRq(uint16_t message_id) {
  return CommandSet(ImplicitUid(0x0002, UID_VerificationSOPClass) +
                    ImplicitUs(0x0100, 0x0030) +
                    ImplicitUs(0x0110, message_id) +
                    ImplicitUs(0x0800, 0x0101));
}

std::string NestedDataset(const std::string& sop_instance, int depth) {
  std::string out;
  out += Explicit(0x0008, 0x0016, "UI", Even(UID_CTImageStorage));
  out += Explicit(0x0008, 0x0018, "UI", Even(sop_instance));
  out += Explicit(0x0008, 0x0060, "CS", "CT");
  out += Explicit(0x0020, 0x000D, "UI", Even("1.2.826.0.1.3680043.2.1125.1"));
  out += Explicit(0x0020, 0x000E, "UI", Even("1.2.826.0.1.3680043.2.1125.2"));
  std::string open, close;
  for (int i = 0; i < depth; ++i) {
    // (0040,A730) ContentSequence, SQ, undefined length; an item of
    // undefined length.
    Le16(open, 0x0040);
    Le16(open, 0xA730);
    open += "SQ";
    Le16(open, 0);
    Le32(open, 0xFFFFFFFFu);
    Le16(open, 0xFFFE);
    Le16(open, 0xE000);
    Le32(open, 0xFFFFFFFFu);
  }
  for (int i = 0; i < depth; ++i) {
    Le16(close, 0xFFFE);
    Le16(close, 0xE00D);
    Le32(close, 0);
    Le16(close, 0xFFFE);
    Le16(close, 0xE0DD);
    Le32(close, 0);
  }
  return out + open + close;
}

std::string DatasetOf(const std::string& path) {
  DcmFileFormat ff;
  if (ff.loadFile(path.c_str()).bad()) return "";
  DcmDataset* ds = ff.getDataset();
  if (ds->chooseRepresentation(EXS_LittleEndianExplicit, nullptr).bad()) {
    return "";
  }
  std::string out(
      ds->calcElementLength(EXS_LittleEndianExplicit, EET_ExplicitLength) +
          1024,
      '\0');
  DcmOutputBufferStream stream(out.data(), out.size());
  ds->transferInit();
  const OFCondition c =
      ds->write(stream, EXS_LittleEndianExplicit, EET_ExplicitLength, nullptr);
  ds->transferEnd();
  if (c.bad()) return "";
  void* buffer = nullptr;
  offile_off_t length = 0;
  stream.flushBuffer(buffer, length);
  out.resize(static_cast<size_t>(length));
  return out;
}

int Connect(int port, const std::string& source) {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  if (fd < 0) return -1;
  const int on = 1;
  ::setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &on, sizeof(on));
  if (source != "127.0.0.1") {
    sockaddr_in local{};
    local.sin_family = AF_INET;
    inet_pton(AF_INET, source.c_str(), &local.sin_addr);
    if (::bind(fd, reinterpret_cast<sockaddr*>(&local), sizeof(local)) != 0) {
      ::close(fd);
      return -1;
    }
  }
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(static_cast<uint16_t>(port));
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) != 0) {
    ::close(fd);
    return -1;
  }
  return fd;
}

bool SendAll(int fd, const std::string& bytes) {
  size_t at = 0;
  while (at < bytes.size()) {
    const ssize_t n =
        ::send(fd, bytes.data() + at, bytes.size() - at, MSG_NOSIGNAL);
    if (n <= 0) return false;
    at += static_cast<size_t>(n);
  }
  return true;
}

namespace {
bool ReadExactly(int fd, char* out, size_t n,
                 std::chrono::steady_clock::time_point end) {
  size_t got = 0;
  while (got < n) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
                          end - std::chrono::steady_clock::now())
                          .count();
    if (left <= 0) return false;
    pollfd p{fd, POLLIN, 0};
    if (::poll(&p, 1, static_cast<int>(left)) <= 0) return false;
    const ssize_t r = ::recv(fd, out + got, n - got, 0);
    if (r <= 0) return false;
    got += static_cast<size_t>(r);
  }
  return true;
}
}  // namespace

std::optional<Pdu> ReadPdu(int fd, double seconds) {
  const auto end = std::chrono::steady_clock::now() +
                   std::chrono::milliseconds(static_cast<int>(seconds * 1000));
  char header[6];
  if (!ReadExactly(fd, header, 6, end)) return std::nullopt;
  const auto* h = reinterpret_cast<const unsigned char*>(header);
  const uint32_t length = (uint32_t{h[2]} << 24) | (uint32_t{h[3]} << 16) |
                          (uint32_t{h[4]} << 8) | h[5];
  if (length > (16u << 20)) return std::nullopt;
  Pdu pdu;
  pdu.type = h[0];
  pdu.body.resize(length);
  if (!ReadExactly(fd, pdu.body.data(), length, end)) return std::nullopt;
  return pdu;
}

int ContextResult(const Pdu& ac, uint8_t id) {
  if (ac.type != 0x02 || ac.body.size() < 68) return -1;
  const auto* b = reinterpret_cast<const unsigned char*>(ac.body.data());
  size_t at = 68;
  while (at + 4 <= ac.body.size()) {
    const size_t length = (size_t{b[at + 2]} << 8) | b[at + 3];
    if (b[at] == 0x21 && length >= 4 && b[at + 4] == id) return b[at + 6];
    at += 4 + length;
  }
  return -1;
}

int ResponseStatus(const Pdu& pdata) {
  if (pdata.type != 0x04 || pdata.body.size() < 6) return -1;
  const std::string command = pdata.body.substr(6);
  size_t at = 0;
  while (at + 8 <= command.size()) {
    const auto* e = reinterpret_cast<const unsigned char*>(command.data()) + at;
    const uint16_t group = static_cast<uint16_t>(e[0] | (e[1] << 8));
    const uint16_t element = static_cast<uint16_t>(e[2] | (e[3] << 8));
    const uint32_t length = uint32_t{e[4]} | (uint32_t{e[5]} << 8) |
                            (uint32_t{e[6]} << 16) | (uint32_t{e[7]} << 24);
    if (group == 0 && element == 0x0900 && length == 2 &&
        at + 10 <= command.size()) {
      return e[8] | (e[9] << 8);
    }
    at += 8 + length;
  }
  return -1;
}

}  // namespace interslice::testing
