// The inspector of what a peer sends (server/net/dimse/pdu_guard.h): what DCMTK
// tools and the raw builders send passes, however it is split; what could
// make DCMTK recurse or allocate without bound fails before it is whole.
#include "server/net/dimse/pdu_guard.h"

#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/server/net/dimse/raw_pdu.h"
#include "tests/testing/paths.h"

namespace interslice::server::dimse {
namespace {

using ::testing::HasSubstr;
namespace raw = interslice::testing;

std::string Request(int contexts = 1) {
  std::vector<raw::PresentationContext> list;
  for (int i = 0; i < contexts; ++i) {
    list.push_back({static_cast<uint8_t>(2 * i + 1),
                    UID_CTImageStorage,
                    {UID_LittleEndianExplicitTransferSyntax}});
  }
  return raw::AssociateRq("INTERSLICE", "STORESCU", list);
}

absl::Status FeedAll(PduGuard& guard, const std::string& bytes) {
  return guard.Feed(reinterpret_cast<const unsigned char*>(bytes.data()),
                    bytes.size());
}
absl::Status FeedByteByByte(PduGuard& guard, const std::string& bytes) {
  for (char c : bytes) {
    const unsigned char b = static_cast<unsigned char>(c);
    if (absl::Status s = guard.Feed(&b, 1); !s.ok()) return s;
  }
  return absl::OkStatus();
}

// A whole well-behaved session: request, echo, store, release.
std::string Session() {
  const std::string dataset = raw::NestedDataset("1.2.3.4", 3);
  return Request() + raw::PData(1, true, true, raw::CEchoRq(1)) +
         raw::PData(1, true, true,
                    raw::CStoreRq(2, UID_CTImageStorage, "1.2.3.4")) +
         raw::PData(1, false, false, dataset.substr(0, 40)) +
         raw::PData(1, false, true, dataset.substr(40)) + raw::ReleaseRq();
}

TEST(PduGuardTest, AWellBehavedSessionPassesHoweverItIsSplit) {
  PduGuard whole;
  EXPECT_TRUE(FeedAll(whole, Session()).ok());
  EXPECT_TRUE(whole.request_complete());
  EXPECT_FALSE(whole.in_pdu());
  EXPECT_EQ(whole.pdus(), 6);
  PduGuard bytes;
  EXPECT_TRUE(FeedByteByByte(bytes, Session()).ok());
  EXPECT_EQ(bytes.pdus(), 6);
}

TEST(PduGuardTest, TracksPdusAndTheRequest) {
  PduGuard guard;
  const std::string rq = Request();
  ASSERT_TRUE(FeedAll(guard, rq.substr(0, 3)).ok());
  EXPECT_TRUE(guard.in_pdu());
  EXPECT_EQ(guard.request_bytes_left(), 0u);  // header not complete yet
  ASSERT_TRUE(FeedAll(guard, rq.substr(3, 7)).ok());
  EXPECT_EQ(guard.request_bytes_left(), rq.size() - 10);
  EXPECT_FALSE(guard.request_complete());
  ASSERT_TRUE(FeedAll(guard, rq.substr(10)).ok());
  EXPECT_TRUE(guard.request_complete());
  EXPECT_FALSE(guard.in_pdu());
}

TEST(PduGuardTest, RequestViolations) {
  struct Case {
    const char* what;
    std::string bytes;
    const char* message;
  };
  std::string http = "GET / HTTP/1.1\r\n\r\n";
  std::string huge = std::string("\x01\x00\xff\xff\xff\xff", 6);
  std::string even_id = raw::AssociateRq(
      "A", "B",
      {{2, UID_CTImageStorage, {UID_LittleEndianExplicitTransferSyntax}}});
  std::string no_ts = raw::AssociateRq("A", "B", {{1, UID_CTImageStorage, {}}});
  const std::vector<Case> cases = {
      {"not DICOM", http, "not an A-ASSOCIATE-RQ"},
      {"4 GiB request", huge, "A-ASSOCIATE-RQ of 4294967295 bytes"},
      {"129 contexts", Request(129), "more than 128 presentation contexts"},
      {"even context id", even_id, "even"},
      {"no transfer syntax", no_ts, "exactly one abstract syntax"},
      {"data before the request", raw::PData(1, true, true, raw::CEchoRq(1)),
       "not an A-ASSOCIATE-RQ"},
  };
  for (const Case& c : cases) {
    PduGuard guard;
    absl::Status s = FeedAll(guard, c.bytes);
    ASSERT_FALSE(s.ok()) << c.what;
    EXPECT_THAT(std::string(s.message()), HasSubstr(c.message)) << c.what;
    // And it stays failed.
    EXPECT_FALSE(FeedAll(guard, Session()).ok()) << c.what;
  }
}

TEST(PduGuardTest, ItemLengthsMustTileTheRequest) {
  std::string rq = Request();
  // The application context item's length (bytes 76-77 of the PDU, after 6
  // header and 68 fixed bytes, the item's type and a reserved byte) made one
  // longer than it is.
  rq[77] = static_cast<char>(rq[77] + 1);
  PduGuard guard;
  absl::Status s = FeedAll(guard, rq);
  ASSERT_FALSE(s.ok());
}

// User information sub-items reach DCMTK only well-formed: DCMTK 3.6.7
// leaks memory on a malformed extended negotiation item (the fuzzer's
// case), and nothing else of them is needed.
TEST(PduGuardTest, UserInformationSubItemsMustBeWellFormed) {
  auto request = [](const std::string& extra) {
    return raw::AssociateRq(
        "INTERSLICE", "STORESCU",
        {{1, UID_CTImageStorage, {UID_LittleEndianExplicitTransferSyntax}}},
        16384, extra);
  };
  auto uid = [](const std::string& u) {
    return std::string(1, static_cast<char>(u.size() >> 8)) +
           std::string(1, static_cast<char>(u.size() & 0xFF)) + u;
  };
  // Well-formed: a role selection for each of 128 contexts (getscu sends
  // such), an extended negotiation item, a user identity item.
  std::string roles;
  for (int i = 0; i < 128; ++i) {
    roles += raw::PduItem(0x54, uid(UID_CTImageStorage) + std::string("\1\1"));
  }
  PduGuard good;
  EXPECT_TRUE(
      FeedAll(good,
              request(roles + raw::PduItem(0x56, uid("1.2.3") + "\x01\x00") +
                      raw::PduItem(0x58, std::string("\x01\x00"
                                                     "\x00\x04"
                                                     "user"
                                                     "\x00\x00",
                                                     10))))
          .ok());
  const std::vector<std::pair<std::string, std::string>> bad = {
      {"extended negotiation UID past its item",
       raw::PduItem(0x56, "1.2.3.4.5.6.7.8")},
      {"role selection with a byte too many",
       raw::PduItem(0x54, uid("1.2.3") + std::string("\1\1\1"))},
      {"maximum length of 2 bytes", raw::PduItem(0x51, std::string("\0\1"))},
      {"user identity fields that do not add up",
       raw::PduItem(0x58, std::string("\x01\x00\x00\x09user", 8))},
      {"an unknown sub-item type", raw::PduItem(0x5F, "x")},
  };
  for (const auto& [what, item] : bad) {
    PduGuard guard;
    absl::Status s = FeedAll(guard, request(item));
    ASSERT_FALSE(s.ok()) << what;
    EXPECT_THAT(std::string(s.message()),
                HasSubstr("user information sub-item"))
        << what;
  }
  // The fuzzer's input (after its mode byte).
  std::ifstream in(
      std::string(::interslice::testing::SourceDir()) +
          "/tests/server/net/dimse/fuzz_cases/extended-negotiation-leak.bin",
      std::ios::binary);
  const std::string input((std::istreambuf_iterator<char>(in)),
                          std::istreambuf_iterator<char>());
  ASSERT_GT(input.size(), 1u);
  PduGuard fuzzed;
  absl::Status s = FeedAll(fuzzed, input.substr(1));
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(std::string(s.message()), HasSubstr("sub-item 56"));
}

TEST(PduGuardTest, CommandSetsCannotNest) {
  // A C-STORE-RQ whose command set carries a sequence (nested 10,000 deep,
  // as issue 22's data set was): cut at its first element outside group
  // 0000, long before the PDU is whole.
  const std::string nested = raw::NestedDataset("1.2.3", 10000);
  const std::string command =
      raw::CStoreRq(1, UID_CTImageStorage, "1.2.3") + nested;
  PduGuard guard;
  ASSERT_TRUE(FeedAll(guard, Request()).ok());
  // In PDUs of 16 KB, each within the size limit, fed in 1 KiB chunks as a
  // socket would deliver them: the violation comes with the first chunk
  // that holds the sequence's tag, long before a PDU is whole.
  std::string pdata;
  for (size_t at = 0; at < command.size(); at += 16000) {
    pdata += raw::PData(1, true, at + 16000 >= command.size(),
                        command.substr(at, 16000));
  }
  size_t fed = 0;
  absl::Status s;
  while (fed < pdata.size() && s.ok()) {
    const std::string chunk = pdata.substr(fed, 1024);
    s = FeedAll(guard, chunk);
    fed += chunk.size();
  }
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(std::string(s.message()), HasSubstr("outside group 0000"));
  EXPECT_LE(fed, 2048u);
}

// Issue 39, finding 7: a command set whose CommandGroupLength says more
// (or fewer) bytes than it holds held its association until the DIMSE
// timeout. It is cut when its last fragment ends.
TEST(PduGuardTest, CommandSetMustHoldWhatItsGroupLengthSays) {
  const std::string echo = raw::CEchoRq(1);
  for (const int lie : {+40, -2}) {
    SCOPED_TRACE(lie);
    std::string command = echo;
    // The group length's value: bytes 8-11 of the command set.
    uint32_t said = static_cast<unsigned char>(command[8]) |
                    (static_cast<unsigned char>(command[9]) << 8);
    said = static_cast<uint32_t>(static_cast<int64_t>(said) + lie);
    command[8] = static_cast<char>(said & 0xFF);
    command[9] = static_cast<char>((said >> 8) & 0xFF);
    PduGuard guard;
    ASSERT_TRUE(FeedAll(guard, Request()).ok());
    const absl::Status s = FeedAll(guard, raw::PData(1, true, true, command));
    ASSERT_FALSE(s.ok());
    EXPECT_THAT(std::string(s.message()), HasSubstr("CommandGroupLength says"));
  }
  // The honest command passes.
  PduGuard guard;
  ASSERT_TRUE(FeedAll(guard, Request()).ok());
  EXPECT_TRUE(FeedAll(guard, raw::PData(1, true, true, echo)).ok());
}

TEST(PduGuardTest, CommandElementsMustBeKnownAndDefined) {
  struct Case {
    const char* what;
    std::string command;
    const char* message;
  };
  const std::vector<Case> cases = {
      {"unknown command element",
       raw::CommandSet(raw::ImplicitElement(0x0000, 0x9999, "ab")),
       "not a known command field"},
      {"undefined length",
       raw::CommandSet(std::string("\x00\x00\x02\x00\xff\xff\xff\xff", 8)),
       "undefined length"},
  };
  for (const Case& c : cases) {
    PduGuard guard;
    ASSERT_TRUE(FeedAll(guard, Request()).ok());
    absl::Status s = FeedAll(guard, raw::PData(1, true, true, c.command));
    ASSERT_FALSE(s.ok()) << c.what;
    EXPECT_THAT(std::string(s.message()), HasSubstr(c.message)) << c.what;
  }
  // A command set of 64 KiB and more.
  PduGuard big;
  ASSERT_TRUE(FeedAll(big, Request()).ok());
  absl::Status s = absl::OkStatus();
  for (int i = 0; i < 20 && s.ok(); ++i) {
    s = FeedAll(big, raw::PData(1, true, false,
                                raw::ImplicitElement(0x0000, 0x0902,
                                                     std::string(4000, 'x'))));
  }
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(std::string(s.message()), HasSubstr("command set longer than"));
}

TEST(PduGuardTest, PDataFramingAndTypes) {
  PduGuardLimits limits;
  limits.max_pdata_bytes = 1000;
  {
    PduGuard guard(limits);
    ASSERT_TRUE(FeedAll(guard, Request()).ok());
    absl::Status s =
        FeedAll(guard, raw::PData(1, false, true, std::string(2000, '\0')));
    ASSERT_FALSE(s.ok());
    EXPECT_THAT(std::string(s.message()), HasSubstr("P-DATA-TF of 2006 bytes"));
  }
  {
    // A PDV item that claims more than its PDU holds.
    PduGuard guard;
    ASSERT_TRUE(FeedAll(guard, Request()).ok());
    std::string pdata = raw::PData(1, false, true, std::string(10, '\0'));
    pdata[9] = static_cast<char>(pdata[9] + 4);  // item length + 4
    absl::Status s = FeedAll(guard, pdata);
    ASSERT_FALSE(s.ok());
    EXPECT_THAT(std::string(s.message()), HasSubstr("does not fit"));
  }
  {
    // A second A-ASSOCIATE-RQ within the association.
    PduGuard guard;
    ASSERT_TRUE(FeedAll(guard, Request()).ok());
    absl::Status s = FeedAll(guard, Request());
    ASSERT_FALSE(s.ok());
    EXPECT_THAT(std::string(s.message()),
                HasSubstr("PDU type 1 within an association"));
  }
}

// Fuzzer finding: after a C-ECHO (no data set), data-set PDVs holding a
// command set with a 4 GiB element went to DCMTK, which allocated it. A
// data set comes only after a command that announces one, on its context.
TEST(PduGuardTest, DataSetsOnlyAfterACommandThatAnnouncesOne) {
  const std::string dataset = raw::NestedDataset("1.2.3.4", 3);
  {
    PduGuard guard;
    ASSERT_TRUE(FeedAll(guard, Request()).ok());
    ASSERT_TRUE(
        FeedAll(guard, raw::PData(1, true, true, raw::CEchoRq(1))).ok());
    absl::Status s = FeedAll(guard, raw::PData(1, false, true, dataset));
    ASSERT_FALSE(s.ok());
    EXPECT_THAT(std::string(s.message()), HasSubstr("no command announced"));
  }
  {
    // Announced on context 1, sent on context 3.
    PduGuard guard;
    ASSERT_TRUE(FeedAll(guard, Request(2)).ok());
    ASSERT_TRUE(FeedAll(guard, raw::PData(1, true, true,
                                          raw::CStoreRq(1, UID_CTImageStorage,
                                                        "1.2.3.4")))
                    .ok());
    EXPECT_FALSE(FeedAll(guard, raw::PData(3, false, true, dataset)).ok());
  }
  {
    // A stored instance's data set passes; a second one after its last
    // fragment, with no command of its own, does not.
    PduGuard guard;
    ASSERT_TRUE(FeedAll(guard, Request()).ok());
    ASSERT_TRUE(FeedAll(guard, raw::PData(1, true, true,
                                          raw::CStoreRq(1, UID_CTImageStorage,
                                                        "1.2.3.4")))
                    .ok());
    EXPECT_TRUE(FeedAll(guard, raw::PData(1, false, true, dataset)).ok());
    EXPECT_FALSE(FeedAll(guard, raw::PData(1, false, true, dataset)).ok());
  }
  {
    // A command element longer than a command set may be.
    PduGuard guard;
    ASSERT_TRUE(FeedAll(guard, Request()).ok());
    std::string command = raw::CEchoRq(1);
    command += std::string("\x00\x00\x10\x01\x02\x00\x00\xff", 8);
    absl::Status s = FeedAll(guard, raw::PData(1, true, true, command));
    ASSERT_FALSE(s.ok());
    EXPECT_THAT(std::string(s.message()), HasSubstr("command element of"));
  }
  // The fuzzer's input (after its mode byte).
  std::ifstream in(
      std::string(::interslice::testing::SourceDir()) +
          "/tests/server/net/dimse/fuzz_cases/data-set-after-echo-4gib.bin",
      std::ios::binary);
  const std::string input((std::istreambuf_iterator<char>(in)),
                          std::istreambuf_iterator<char>());
  ASSERT_GT(input.size(), 1u);
  PduGuard fuzzed;
  absl::Status s = FeedAll(fuzzed, input.substr(1));
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(std::string(s.message()), HasSubstr("no command announced"));
}

}  // namespace
}  // namespace interslice::server::dimse
