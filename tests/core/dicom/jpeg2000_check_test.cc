// CheckJpeg2000Codestream: what is refused before GDCM's codec sees a
// codestream (core/dicom/gdcm_decode.h).
#include <cstdint>
#include <vector>

#include "core/dicom/gdcm_decode.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace interslice::dicom_internal {
namespace {

using ::testing::HasSubstr;

void Put16(std::vector<uint8_t>& b, uint16_t v) {
  b.push_back(v >> 8);
  b.push_back(v & 0xff);
}
void Put32(std::vector<uint8_t>& b, uint32_t v) {
  Put16(b, v >> 16);
  Put16(b, v & 0xffff);
}

struct Siz {
  uint32_t width = 512, height = 512, tile = 512;
  uint16_t components = 1;
  uint8_t precision = 16;  // bits
  bool is_signed = true;
};

// SOC, SIZ, a COD segment and EOC: enough for the checks, not for decoding.
std::vector<uint8_t> Codestream(const Siz& s) {
  std::vector<uint8_t> b;
  Put16(b, 0xff4f);
  Put16(b, 0xff51);
  Put16(b, 38 + 3 * s.components);
  Put16(b, 0);  // Rsiz
  Put32(b, s.width);
  Put32(b, s.height);
  Put32(b, 0);
  Put32(b, 0);
  Put32(b, s.tile);
  Put32(b, s.tile);
  Put32(b, 0);
  Put32(b, 0);
  Put16(b, s.components);
  for (int c = 0; c < s.components; ++c) {
    b.push_back((s.is_signed ? 0x80 : 0) | (s.precision - 1));
    b.push_back(1);
    b.push_back(1);
  }
  Put16(b, 0xff52);  // COD, 12 bytes
  Put16(b, 12);
  for (int i = 0; i < 10; ++i) b.push_back(i == 9 ? 1 : 0);
  Put16(b, 0xffd9);
  return b;
}

const Jpeg2000Target kTarget = {.rows = 512,
                                .columns = 512,
                                .bits_allocated = 16,
                                .bits_stored = 16,
                                .is_signed = true};

absl::Status Check(const std::vector<uint8_t>& b,
                   const Jpeg2000Target& target = kTarget) {
  return CheckJpeg2000Codestream(b.data(), b.size(), "x.dcm", target);
}

TEST(CheckJpeg2000CodestreamTest, AcceptsWhatTheHeaderDescribes) {
  EXPECT_TRUE(Check(Codestream({})).ok());
  Siz twelve;
  twelve.precision = 12;  // fits 16 bits allocated
  EXPECT_TRUE(Check(Codestream(twelve)).ok());
}

TEST(CheckJpeg2000CodestreamTest, RefusesWhatGdcmWouldMishandle) {
  Siz colour;
  colour.components = 3;  // GDCM asserts numcomps == SamplesPerPixel
  EXPECT_THAT(Check(Codestream(colour)).message(), HasSubstr("3 components"));
  Siz larger;
  larger.width = 1024;  // GDCM writes past its buffer
  EXPECT_THAT(Check(Codestream(larger)).message(), HasSubstr("1024 x 512"));
  Siz tiny_tiles;
  tiny_tiles.tile = 1;  // 262144 tiles of coding parameters
  EXPECT_THAT(Check(Codestream(tiny_tiles)).message(), HasSubstr("tiles"));
  Jpeg2000Target eight = kTarget;
  eight.bits_allocated = eight.bits_stored = 8;
  EXPECT_THAT(Check(Codestream({}), eight).message(),
              HasSubstr("16-bit samples do not fit BitsAllocated 8"));
  // A JP2 file (signature box first) instead of a bare codestream.
  std::vector<uint8_t> jp2 = {0,   0,   0,  12, 'j',  'P',
                              ' ', ' ', 13, 10, 0x87, 10};
  for (uint8_t byte : Codestream({})) jp2.push_back(byte);
  EXPECT_THAT(Check(jp2).message(), HasSubstr("JP2"));
  // Too short for a SIZ marker.
  EXPECT_FALSE(Check({0xff, 0x4f, 0xff, 0x51}).ok());
}

TEST(CheckJpeg2000CodestreamTest, RefusesMarkersRunningPastTheData) {
  // GDCM's parsej2k_imp trusts a marker length and reads COD bytes 4 and 9.
  std::vector<uint8_t> b = Codestream({});
  b.resize(b.size() - 2 - 14);  // drop COD and EOC
  Put16(b, 0xff64);             // COM claiming 1000 bytes
  Put16(b, 1000);
  EXPECT_THAT(Check(b).message(), HasSubstr("past the end"));
  b.resize(b.size() - 4);
  Put16(b, 0xff52);  // COD cut short
  Put16(b, 12);
  b.push_back(0);
  EXPECT_THAT(Check(b).message(), HasSubstr("past the end"));
}

}  // namespace
}  // namespace interslice::dicom_internal
