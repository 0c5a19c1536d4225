// Test helpers shared by the DICOM output tests: small DCMTK accessors, and
// dciodvfy (dicom3tools) as the validator (tests/testing/dciodvfy.h).
#ifndef INTERSLICE_TESTS_CORE_DICOM_OUT_DICOM_TEST_UTIL_H_
#define INTERSLICE_TESTS_CORE_DICOM_OUT_DICOM_TEST_UTIL_H_

#include <memory>
#include <string>

#include "gtest/gtest.h"
#include "tests/testing/dciodvfy.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcitem.h"

namespace interslice::testing {

inline std::string GetString(DcmItem& item, const DcmTagKey& tag) {
  OFString value;
  item.findAndGetOFStringArray(tag, value);
  return std::string(value.c_str());
}

inline std::unique_ptr<DcmFileFormat> LoadDicom(const std::string& path) {
  auto file = std::make_unique<DcmFileFormat>();
  EXPECT_TRUE(file->loadFile(OFFilename(path.c_str())).good()) << path;
  return file;
}

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_CORE_DICOM_OUT_DICOM_TEST_UTIL_H_
