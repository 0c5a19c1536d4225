// Writes a deliberately displaced copy of a DICOM SEG: every frame's pixels moved COLUMNS columns
// to the right (bits leaving the frame dropped), everything else unchanged. The viewer tests run
// against it to show that they fail when the overlay does not lie on the anatomy.
//
//   node make_displaced_seg.mjs IN.dcm OUT.dcm COLUMNS
import { readFileSync, writeFileSync } from 'node:fs';

const [input, output, shiftArg] = process.argv.slice(2);
const shift = Number(shiftArg);
if (!input || !output || !Number.isInteger(shift) || shift <= 0) {
  console.log('FAIL: usage: node make_displaced_seg.mjs IN.dcm OUT.dcm COLUMNS (a positive integer)');
  process.exit(1);
}
const { default: dcmjs } = await import('dcmjs').then((m) => (m.default ? m : { default: m }));
const buf = readFileSync(input);
const dicom = dcmjs.data.DicomMessage.readFile(buf.buffer.slice(buf.byteOffset, buf.byteOffset + buf.byteLength));
const pixelData = dicom.dict['7FE00010'];
const rows = dicom.dict['00280010'].Value[0];
const cols = dicom.dict['00280011'].Value[0];
const frames = Number(dicom.dict['00280008'].Value[0]);
if (dicom.dict['00280100'].Value[0] !== 1) {
  console.log('FAIL: only binary (BitsAllocated 1) SEGs are displaced');
  process.exit(1);
}
const bytes = new Uint8Array(pixelData.Value[0]);
const out = new Uint8Array(bytes.length);
const perFrame = rows * cols;
for (let f = 0; f < frames; f++) {
  for (let r = 0; r < rows; r++) {
    for (let c = 0; c + shift < cols; c++) {
      const from = f * perFrame + r * cols + c;
      if ((bytes[from >> 3] >> (from & 7)) & 1) {
        const to = from + shift;
        out[to >> 3] |= 1 << (to & 7);
      }
    }
  }
}
pixelData.Value = [out.buffer];
writeFileSync(output, Buffer.from(dicom.write()));
