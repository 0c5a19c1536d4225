// node/outcome.h speaks DIMSE's C-STORE statuses without DCMTK's network
// library (so that the DICOMweb side needs none): its words must be DCMTK's
// own, code for code.
#include "server/node/outcome.h"

#include <cstdint>
#include <string>

#include "gtest/gtest.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmnet/dimse.h"
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

// Both doors answer a refusal with the status of this one mapping; the codes
// are DCMTK's C-STORE statuses.
TEST(OutcomeTest, RefusalsMapToDimseStoreStatuses) {
  EXPECT_EQ(StoreStatusOfRefusal(absl::OkStatus()), STATUS_Success);
  EXPECT_EQ(StoreStatusOfRefusal(absl::ResourceExhaustedError("quota")),
            STATUS_STORE_Refused_OutOfResources);
  EXPECT_EQ(StoreStatusOfRefusal(absl::UnimplementedError("SC")),
            STATUS_STORE_Refused_SOPClassNotSupported);
  EXPECT_EQ(StoreStatusOfRefusal(absl::InvalidArgumentError("no UIDs")),
            STATUS_STORE_Error_CannotUnderstand);
  EXPECT_EQ(StoreStatusOfRefusal(absl::InternalError("?")), 0x0110);
  EXPECT_EQ(CStoreStatusText(kStoreSopClassNotSupported),
            "Refused: SOPClassNotSupported");
}

}  // namespace
}  // namespace interslice::server::node
