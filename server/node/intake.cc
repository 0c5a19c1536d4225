#include "server/node/intake.h"

#include <algorithm>

#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcuid.h"

namespace interslice::server::node {

const std::vector<std::string>& StorableSopClasses() {
  // The images the pipeline reads (core/io: CT and MR, single- and
  // multi-frame), and SEG and RTSTRUCT: segmentations drawn on a series
  // held in the spool, which rules with `fill` make fill jobs of
  // (series_assembler.h). Nothing else makes a job, so nothing else is
  // taken at any door (issue 39: STOW took Secondary Capture and DX).
  static const std::vector<std::string> kClasses = {
      UID_CTImageStorage,
      UID_EnhancedCTImageStorage,
      UID_LegacyConvertedEnhancedCTImageStorage,
      UID_MRImageStorage,
      UID_EnhancedMRImageStorage,
      UID_LegacyConvertedEnhancedMRImageStorage,
      UID_SegmentationStorage,
      UID_RTStructureSetStorage};
  return kClasses;
}

bool StorableSopClass(const std::string& sop_class_uid) {
  const std::vector<std::string>& classes = StorableSopClasses();
  return std::find(classes.begin(), classes.end(), sop_class_uid) !=
         classes.end();
}

}  // namespace interslice::server::node
