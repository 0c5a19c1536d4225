#include "tests/testing/made_elsewhere.h"

#include "absl/strings/str_cat.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"

namespace interslice::testing {

absl::Status MarkAsMadeElsewhere(const std::string& path) {
  DcmFileFormat file;
  if (OFCondition c = file.loadFile(path.c_str()); c.bad()) {
    return absl::InvalidArgumentError(
        absl::StrCat("cannot read ", path, ": ", c.text()));
  }
  // In memory whole before the file is written over (DCMTK reads large
  // elements such as the pixel data from the file on demand).
  if (OFCondition c = file.loadAllDataIntoMemory(); c.bad()) {
    return absl::InvalidArgumentError(
        absl::StrCat("cannot read ", path, ": ", c.text()));
  }
  DcmDataset* ds = file.getDataset();
  ds->putAndInsertString(DCM_Manufacturer, "a contouring workstation");
  ds->putAndInsertString(DCM_ManufacturerModelName, "test");
  // The file's own transfer syntax, so that nothing else changes.
  if (OFCondition c = file.saveFile(path.c_str(), ds->getOriginalXfer());
      c.bad()) {
    return absl::InternalError(
        absl::StrCat("cannot write ", path, ": ", c.text()));
  }
  return absl::OkStatus();
}

}  // namespace interslice::testing
