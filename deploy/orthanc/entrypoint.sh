#!/bin/sh
# Writes the settings that come from the environment (ports; where the
# interslice DICOM listener is, as the modality "interslice") next to the
# fixed orthanc.json, then runs Orthanc on both (Orthanc merges the .json
# files of a folder). Runs as the orthanc user; only /tmp is written, so the
# root filesystem may be read-only.
set -eu
conf=/tmp/orthanc-config
mkdir -p "$conf"
cp /etc/orthanc-interslice/orthanc.json "$conf/orthanc.json"
cat > "$conf/environment.json" <<JSON
{
  "HttpPort": ${ORTHANC_HTTP_PORT},
  "DicomPort": ${ORTHANC_DICOM_PORT},
  "DicomModalities": {
    "interslice": ["${INTERSLICE_DICOM_AET}", "${INTERSLICE_DICOM_HOST}", ${INTERSLICE_DICOM_PORT}]
  }
}
JSON
exec /usr/sbin/Orthanc "$conf"
