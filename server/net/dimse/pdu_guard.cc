#include "server/net/dimse/pdu_guard.h"

#include <algorithm>
#include <utility>

#include "absl/strings/str_cat.h"
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dctag.h"

namespace interslice::server::dimse {
namespace {

constexpr uint8_t kAssociateRq = 0x01;
constexpr uint8_t kPData = 0x04;
constexpr uint8_t kReleaseRq = 0x05;
constexpr uint8_t kReleaseRp = 0x06;
constexpr uint8_t kAbort = 0x07;
// PS3.8 9.3.2: protocol version, reserved, called and calling AE titles,
// reserved: 68 bytes before the variable items.
constexpr size_t kRequestFixedPart = 68;

uint32_t Be32(const unsigned char* b) {
  return (uint32_t{b[0]} << 24) | (uint32_t{b[1]} << 16) |
         (uint32_t{b[2]} << 8) | b[3];
}
uint16_t Be16(const unsigned char* b) {
  return static_cast<uint16_t>((b[0] << 8) | b[1]);
}
uint16_t Le16(const unsigned char* b) {
  return static_cast<uint16_t>(b[0] | (b[1] << 8));
}
uint32_t Le32(const unsigned char* b) {
  return uint32_t{b[0]} | (uint32_t{b[1]} << 8) | (uint32_t{b[2]} << 16) |
         (uint32_t{b[3]} << 24);
}

// Sub-items (type, reserved, 2-byte length, value) that must tile
// [begin, end) exactly; `visit` sees each.
template <typename Visit>
absl::Status ForEachItem(const std::string& bytes, size_t begin, size_t end,
                         const char* where, Visit visit) {
  size_t at = begin;
  while (at < end) {
    if (end - at < 4) {
      return absl::InvalidArgumentError(
          absl::StrCat("an item of the ", where, " is cut short"));
    }
    const auto* p = reinterpret_cast<const unsigned char*>(bytes.data()) + at;
    const size_t length = Be16(p + 2);
    if (length > end - at - 4) {
      return absl::InvalidArgumentError(
          absl::StrCat("an item of the ", where, " runs past its end"));
    }
    if (absl::Status s = visit(p[0], at + 4, length); !s.ok()) return s;
    at += 4 + length;
  }
  return absl::OkStatus();
}

absl::Status CheckUid(size_t length, const char* what) {
  if (length < 1 || length > 64) {
    return absl::InvalidArgumentError(
        absl::StrCat("a ", what, " is not 1 to 64 bytes long"));
  }
  return absl::OkStatus();
}

// A user information sub-item, by its structure in PS3.7 D.3.3 and PS3.8
// D.3.3: DCMTK 3.6.7 leaks memory on some malformed ones (found by
// tests/fuzz/dicom_listener_fuzzer: an extended negotiation item whose UID
// length runs past it), so only well-formed known ones reach it.
absl::Status CheckUserItem(uint8_t type, const unsigned char* v, size_t l) {
  auto bad = [type](const char* what) {
    return absl::InvalidArgumentError(absl::StrCat(
        "user information sub-item ", absl::Hex(type), ": ", what));
  };
  // A 2-byte length and a UID of 1-64 bytes at `at`; the offset after it.
  auto uid_at = [&](size_t at, size_t* next) {
    if (at + 2 > l) return false;
    const size_t n = Be16(v + at);
    if (n < 1 || n > 64 || at + 2 + n > l) return false;
    *next = at + 2 + n;
    return true;
  };
  size_t next = 0;
  switch (type) {
    case 0x51:  // maximum length
    case 0x53:  // asynchronous operations window
      return l == 4 ? absl::OkStatus() : bad("not 4 bytes long");
    case 0x52:  // implementation class UID
      return l >= 1 && l <= 64 ? absl::OkStatus() : bad("not a UID");
    case 0x55:  // implementation version name
      return l >= 1 && l <= 16 ? absl::OkStatus() : bad("not 1-16 bytes");
    case 0x54:  // SCP/SCU role selection: UID, SCU role, SCP role
      return uid_at(0, &next) && next + 2 == l ? absl::OkStatus()
                                               : bad("malformed");
    case 0x56:  // SOP class extended negotiation: UID, application info
      return uid_at(0, &next) ? absl::OkStatus() : bad("malformed");
    case 0x57: {  // SOP class common extended negotiation
      size_t after_service = 0;
      if (!uid_at(0, &next) || !uid_at(next, &after_service) ||
          after_service + 2 > l) {
        return bad("malformed");
      }
      const size_t list = Be16(v + after_service);
      size_t at = after_service + 2;
      if (at + list != l) return bad("malformed");
      while (at < l) {
        if (!uid_at(at, &at)) return bad("malformed");
      }
      return absl::OkStatus();
    }
    case 0x58: {  // user identity: type, response wanted, two fields
      if (l < 6) return bad("malformed");
      const size_t primary = Be16(v + 2);
      if (4 + primary + 2 > l) return bad("malformed");
      const size_t secondary = Be16(v + 4 + primary);
      return 4 + primary + 2 + secondary == l ? absl::OkStatus()
                                              : bad("malformed");
    }
    default:
      return bad("of an unknown type");
  }
}

}  // namespace

absl::Status PduGuard::Fail(std::string what) {
  failed_ = absl::InvalidArgumentError(
      absl::StrCat("protocol violation in PDU ", pdus_ + 1, ": ", what));
  return failed_;
}

absl::Status PduGuard::StartPdu() {
  type_ = header_[0];
  body_left_ = Be32(header_ + 2);
  if (pdus_ == 0) {
    if (type_ != kAssociateRq) {
      return Fail("the first PDU is not an A-ASSOCIATE-RQ");
    }
    if (body_left_ < kRequestFixedPart ||
        body_left_ > limits_.max_request_bytes) {
      return Fail(absl::StrCat("an A-ASSOCIATE-RQ of ", body_left_,
                               " bytes (at most ", limits_.max_request_bytes,
                               ")"));
    }
    request_.clear();
    request_.reserve(static_cast<size_t>(body_left_));
    return absl::OkStatus();
  }
  switch (type_) {
    case kPData:
      // At least one PDV item (PS3.8 9.3.5): 4-byte length, context ID and
      // message control header.
      if (body_left_ < 6 || body_left_ > limits_.max_pdata_bytes) {
        return Fail(absl::StrCat("a P-DATA-TF of ", body_left_,
                                 " bytes (at most ", limits_.max_pdata_bytes,
                                 ")"));
      }
      return absl::OkStatus();
    case kReleaseRq:
    case kReleaseRp:
    case kAbort:
      if (body_left_ != 4) return Fail("a release or abort PDU of bad length");
      return absl::OkStatus();
    default:
      return Fail(absl::StrCat("PDU type ", static_cast<int>(type_),
                               " within an association"));
  }
}

absl::Status PduGuard::CheckRequest() const {
  const std::string& r = request_;
  const auto* p = reinterpret_cast<const unsigned char*>(r.data());
  if ((Be16(p) & 1) == 0) {
    return absl::InvalidArgumentError("protocol version 1 is not offered");
  }
  int contexts = 0, application_contexts = 0, user_infos = 0;
  absl::Status s = ForEachItem(
      r, kRequestFixedPart, r.size(), "A-ASSOCIATE-RQ",
      [&](uint8_t type, size_t at, size_t length) -> absl::Status {
        switch (type) {
          case 0x10:
            ++application_contexts;
            return CheckUid(length, "application context name");
          case 0x20: {
            if (++contexts > limits_.max_presentation_contexts) {
              return absl::InvalidArgumentError(
                  absl::StrCat("more than ", limits_.max_presentation_contexts,
                               " presentation contexts"));
            }
            if (length < 4) {
              return absl::InvalidArgumentError(
                  "a presentation context is cut short");
            }
            const uint8_t id = p[at];
            if ((id & 1) == 0) {
              return absl::InvalidArgumentError(
                  "a presentation context ID is even");
            }
            int abstract = 0, transfer = 0;
            absl::Status sub = ForEachItem(
                r, at + 4, at + length, "presentation context",
                [&](uint8_t t, size_t, size_t l) -> absl::Status {
                  if (t == 0x30) {
                    ++abstract;
                    return CheckUid(l, "abstract syntax name");
                  }
                  if (t == 0x40) {
                    if (++transfer > limits_.max_transfer_syntaxes) {
                      return absl::InvalidArgumentError(absl::StrCat(
                          "a presentation context offers more than ",
                          limits_.max_transfer_syntaxes, " transfer syntaxes"));
                    }
                    return CheckUid(l, "transfer syntax name");
                  }
                  return absl::InvalidArgumentError(
                      absl::StrCat("sub-item type ", static_cast<int>(t),
                                   " in a presentation context"));
                });
            if (!sub.ok()) return sub;
            if (abstract != 1 || transfer < 1) {
              return absl::InvalidArgumentError(
                  "a presentation context without exactly one abstract "
                  "syntax and a transfer syntax");
            }
            return absl::OkStatus();
          }
          case 0x50: {
            ++user_infos;
            int items = 0;
            return ForEachItem(
                r, at, at + length, "user information",
                [&](uint8_t t, size_t from, size_t l) -> absl::Status {
                  if (++items > limits_.max_user_items) {
                    return absl::InvalidArgumentError(
                        absl::StrCat("more than ", limits_.max_user_items,
                                     " user information sub-items"));
                  }
                  return CheckUserItem(t, p + from, l);
                });
          }
          default:
            return absl::InvalidArgumentError(absl::StrCat(
                "item type ", static_cast<int>(type), " in an A-ASSOCIATE-RQ"));
        }
      });
  if (!s.ok()) return s;
  if (application_contexts != 1 || contexts < 1 || user_infos != 1) {
    return absl::InvalidArgumentError(
        "an A-ASSOCIATE-RQ without one application context, one user "
        "information item and a presentation context");
  }
  return absl::OkStatus();
}

absl::Status PduGuard::FeedCommand(const unsigned char* data, size_t n) {
  command_bytes_ += n;
  if (command_bytes_ > limits_.max_command_bytes) {
    return Fail(absl::StrCat("a command set longer than ",
                             limits_.max_command_bytes, " bytes"));
  }
  while (n > 0) {
    if (element_left_ > 0) {
      const uint64_t take = std::min<uint64_t>(element_left_, n);
      if (element_ == 0x0800) {  // CommandDataSetType (US): keep its value
        for (uint64_t i = 0; i < take && data_set_type_fill_ < 2; ++i) {
          data_set_type_[data_set_type_fill_++] = data[i];
        }
      }
      if (element_ == 0x0000) {  // CommandGroupLength (UL): keep its value
        for (uint64_t i = 0; i < take && group_length_fill_ < 4; ++i) {
          group_length_[group_length_fill_++] = data[i];
        }
      }
      element_left_ -= take;
      data += take;
      n -= static_cast<size_t>(take);
      continue;
    }
    const size_t take =
        std::min<size_t>(8 - static_cast<size_t>(element_header_fill_), n);
    std::copy(data, data + take, element_header_ + element_header_fill_);
    element_header_fill_ += static_cast<int>(take);
    data += take;
    n -= take;
    if (element_header_fill_ < 8) break;
    element_header_fill_ = 0;
    const uint16_t group = Le16(element_header_);
    const uint16_t element = Le16(element_header_ + 2);
    const uint32_t length = Le32(element_header_ + 4);
    if (++command_elements_ > 64) {
      return Fail("a command set of more than 64 elements");
    }
    if (group != 0x0000) {
      return Fail("a command set holds an element outside group 0000");
    }
    // Only command elements the dictionary knows, none of them a
    // sequence: DCMTK then reads each as a plain value.
    const DcmEVR vr = DcmTag(group, element).getEVR();
    if (vr == EVR_SQ || vr == EVR_UN || vr == EVR_UNKNOWN ||
        vr == EVR_UNKNOWN2B) {
      return Fail(absl::StrCat("command element (0000,",
                               absl::Hex(element, absl::kZeroPad4),
                               ") is not a known command field"));
    }
    if (length == 0xFFFFFFFFu) {
      return Fail("a command element of undefined length");
    }
    // DCMTK allocates an element's whole declared length before it reads
    // the value: a command element longer than a command set may be would
    // cost that much memory whether or not its bytes ever come (fuzzer
    // finding: 4 GiB).
    if (length > limits_.max_command_bytes) {
      return Fail(absl::StrCat("a command element of ", length,
                               " bytes (a command set has at most ",
                               limits_.max_command_bytes, ")"));
    }
    element_ = element;
    if (element == 0x0800) {
      if (length != 2) return Fail("a CommandDataSetType that is not a US");
      data_set_type_fill_ = 0;
    }
    if (element == 0x0000) {
      if (length != 4 || command_elements_ != 1) {
        return Fail("a CommandGroupLength that is not the first element, a UL");
      }
      group_length_given_ = true;
      group_length_fill_ = 0;
    }
    element_left_ = length;
  }
  return absl::OkStatus();
}

absl::Status PduGuard::EndCommand() {
  if (element_header_fill_ != 0 || element_left_ != 0) {
    return Fail("a command set ends inside an element");
  }
  if (group_length_given_) {
    // The CommandGroupLength element itself is 12 bytes (tag, length,
    // value); what follows it is what it counts.
    const uint64_t said = Le32(group_length_);
    if (command_bytes_ != 12 + said) {
      return Fail(absl::StrCat("a command set whose CommandGroupLength says ",
                               said, " bytes follow it, but ",
                               command_bytes_ - 12, " do"));
    }
    group_length_given_ = false;
  }
  command_bytes_ = 0;
  command_elements_ = 0;
  element_ = 0;
  // No CommandDataSetType (DCMTK refuses such a command): no data set.
  const uint16_t type =
      data_set_type_fill_ == 2 ? Le16(data_set_type_) : 0x0101;
  data_set_expected_ = type != 0x0101;
  data_set_context_ = command_context_;
  data_set_type_[0] = data_set_type_[1] = 0x01;
  data_set_type_fill_ = 2;
  return absl::OkStatus();
}

absl::Status PduGuard::FeedPData(const unsigned char* data, size_t n) {
  while (n > 0) {
    if (pdv_left_ == 0) {
      const size_t take =
          std::min<size_t>(6 - static_cast<size_t>(pdv_header_fill_), n);
      std::copy(data, data + take, pdv_header_ + pdv_header_fill_);
      pdv_header_fill_ += static_cast<int>(take);
      data += take;
      n -= take;
      if (pdv_header_fill_ < 6) break;
      pdv_header_fill_ = 0;
      const uint32_t item_length = Be32(pdv_header_);
      const uint8_t context = pdv_header_[4];
      const uint8_t control = pdv_header_[5];
      // What is left of the PDU: the rest of this chunk and body_left_
      // (Feed has already taken the chunk off it).
      if (item_length < 2 || item_length - 2 > body_left_ + n) {
        return Fail("a PDV item does not fit its P-DATA-TF");
      }
      if ((context & 1) == 0 || (control & 0xFC) != 0) {
        return Fail("a PDV item with an even context ID or reserved bits");
      }
      pdv_command_ = (control & 1) != 0;
      pdv_last_ = (control & 2) != 0;
      if (pdv_command_) {
        command_context_ = context;
      } else if (!data_set_expected_ || context != data_set_context_) {
        return Fail(
            "a data-set PDV that no command announced on its presentation "
            "context");
      }
      pdv_left_ = item_length - 2;
      if (pdv_left_ == 0 && !pdv_command_ && pdv_last_) {
        data_set_expected_ = false;
      }
      if (pdv_left_ == 0 && pdv_command_ && pdv_last_) {
        if (absl::Status s = EndCommand(); !s.ok()) return s;
      }
      continue;
    }
    const size_t take = static_cast<size_t>(std::min<uint64_t>(pdv_left_, n));
    if (pdv_command_) {
      if (absl::Status s = FeedCommand(data, take); !s.ok()) return s;
    }
    pdv_left_ -= take;
    data += take;
    n -= take;
    if (pdv_left_ == 0 && pdv_command_ && pdv_last_) {
      if (absl::Status s = EndCommand(); !s.ok()) return s;
    }
    if (pdv_left_ == 0 && !pdv_command_ && pdv_last_) {
      data_set_expected_ = false;
    }
  }
  return absl::OkStatus();
}

absl::Status PduGuard::Feed(const unsigned char* data, size_t n) {
  if (!failed_.ok()) return failed_;
  while (n > 0) {
    if (body_left_ == 0) {
      const size_t take =
          std::min<size_t>(6 - static_cast<size_t>(header_fill_), n);
      std::copy(data, data + take, header_ + header_fill_);
      header_fill_ += static_cast<int>(take);
      data += take;
      n -= take;
      if (header_fill_ < 6) break;
      header_fill_ = 0;
      if (absl::Status s = StartPdu(); !s.ok()) return s;
      pdv_header_fill_ = 0;
      pdv_left_ = 0;
      if (body_left_ == 0) ++pdus_;
      continue;
    }
    const size_t take = static_cast<size_t>(std::min<uint64_t>(body_left_, n));
    body_left_ -= take;
    if (pdus_ == 0) {
      request_.append(reinterpret_cast<const char*>(data), take);
      if (body_left_ == 0) {
        if (absl::Status s = CheckRequest(); !s.ok()) {
          return Fail(std::string(s.message()));
        }
      }
    } else if (type_ == kPData) {
      if (absl::Status s = FeedPData(data, take); !s.ok()) return s;
      if (body_left_ == 0 && (pdv_left_ != 0 || pdv_header_fill_ != 0)) {
        return Fail("a PDV item does not fit its P-DATA-TF");
      }
    }
    data += take;
    n -= take;
    if (body_left_ == 0) {
      ++pdus_;
      if (pdus_ == 1) {
        request_.clear();
        request_.shrink_to_fit();
      }
    }
  }
  return absl::OkStatus();
}

}  // namespace interslice::server::dimse
