// The surface mesh as a DICOM object: Encapsulated STL (DICOM PS3.3 A.85,
// SOP Class 1.2.840.10008.5.1.4.1.1.104.3), so that 3D-printing and planning
// workstations find the mesh in the PACS, in the study it was made from.
//
// Contract:
// - `stl_path` is a binary STL file (as core/surface's WriteStl writes: LPS
//   millimetres in the source's frame of reference). Its bytes are embedded
//   unchanged as EncapsulatedDocument (padded to even length with one zero
//   byte, EncapsulatedDocumentLength = the file's size), so extracting them
//   gives the file back byte for byte. DCMTK's DcmEncapsulatedDocument (the
//   code behind stl2dcm) reads and checks the file: an ASCII STL, a file
//   whose size disagrees with its triangle count, or a missing/empty file is
//   INVALID_ARGUMENT naming the file.
// - `identity` is PlanDerivedObjects(...).surface_stl: its series, one SOP
//   instance, series number and description; study and frame of reference
//   are the source's (as for every derived object), and the Patient and
//   Study modules are copied from the first source file (see
//   dicom_writer.h, "Identity"). MeasurementUnitsCodeSequence is UCUM "mm";
//   the Frame of Reference module carries the source's FrameOfReferenceUID,
//   because the vertices are in its patient coordinates.
// - SourceInstanceSequence lists the source instances (the images the mesh
//   was derived from), ReferencedSeriesSequence the source series.
// - Written atomically (temporary file, fsync, rename) to `path`, whose
//   folder must exist; INTERNAL naming `path` when that fails,
//   FAILED_PRECONDITION when the source file cannot be read again.
// Messages never contain patient data.
#ifndef INTERSLICE_CORE_DICOM_OUT_ENCAPSULATED_STL_H_
#define INTERSLICE_CORE_DICOM_OUT_ENCAPSULATED_STL_H_

#include <string>

#include "absl/status/status.h"
#include "core/dicom/series_reader.h"
#include "core/dicom_out/dicom_writer.h"

namespace interslice {

// File name the pipeline gives the Encapsulated STL object in a job's output
// folder (docs/dicom-output.md).
inline constexpr char kEncapsulatedStlFileName[] = "surface-stl.dcm";

absl::Status WriteEncapsulatedStl(const DicomSeries& source,
                                  const std::string& stl_path,
                                  const DerivedObjectIdentity& identity,
                                  const DicomWriteOptions& options,
                                  const std::string& path);

}  // namespace interslice

#endif  // INTERSLICE_CORE_DICOM_OUT_ENCAPSULATED_STL_H_
