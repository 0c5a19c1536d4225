// node/outcome.h speaks DIMSE's C-STORE statuses without DCMTK's network
// library (so that the DICOMweb side needs none): its words must be DCMTK's
// own, code for code.
#include "server/node/outcome.h"

#include <cstdint>
#include <string>

#include "gtest/gtest.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmnet/diutil.h"

namespace interslice::server::node {
namespace {

TEST(OutcomeTest, CStoreStatusTextIsDcmtksForEveryCode) {
  int differing = 0;
  std::string first;
  for (uint32_t code = 0; code <= 0xFFFF; ++code) {
    const std::string ours = CStoreStatusText(static_cast<uint16_t>(code));
    const std::string dcmtk = DU_cstoreStatusString(static_cast<Uint16>(code));
    if (ours != dcmtk) {
      if (differing++ == 0) {
        first = "0x" + std::to_string(code) + ": " + ours + " vs " + dcmtk;
      }
    }
  }
  EXPECT_EQ(differing, 0) << first;
  EXPECT_EQ(CStoreStatusText(0xA700), "Refused: OutOfResources");
  EXPECT_EQ(CStoreStatusText(0xC123), "Error: CannotUnderstand");
}

}  // namespace
}  // namespace interslice::server::node
