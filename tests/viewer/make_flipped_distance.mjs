// A distance map with its slices in reverse order, on the same grid: what the OHIF test must tell
// apart from the real one (run_ohif_test.sh --flipped-distance).
//   node make_flipped_distance.mjs IN.nii.gz OUT.nii.gz
import { readFileSync, writeFileSync } from 'node:fs';
import { gunzipSync, gzipSync } from 'node:zlib';

const [input, output] = process.argv.slice(2);
if (!input || !output) {
  console.log('FAIL: usage: node make_flipped_distance.mjs IN.nii.gz OUT.nii.gz');
  process.exit(1);
}
const buf = gunzipSync(readFileSync(input));
if (buf.readInt32LE(0) !== 348) {
  console.log(`FAIL: ${input} is not a little-endian NIfTI-1 file`);
  process.exit(1);
}
const [nx, ny, nz] = [1, 2, 3].map((k) => buf.readInt16LE(40 + 2 * k));
const bytes = { 16: 4, 64: 8 }[buf.readInt16LE(70)];
if (!bytes || nz < 2) {
  console.log(`FAIL: ${input} is not a float volume of several slices`);
  process.exit(1);
}
const offset = buf.readFloatLE(108);
const slice = nx * ny * bytes;
const out = Buffer.from(buf);
for (let k = 0; k < nz; k++) buf.copy(out, offset + (nz - 1 - k) * slice, offset + k * slice, offset + (k + 1) * slice);
writeFileSync(output, gzipSync(out));
