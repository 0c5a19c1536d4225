// Loads an interslice DICOM SEG the way a web viewer does (OHIF v3: Cornerstone3D's
// @cornerstonejs/adapters createFromDICOMSegBuffer, with the image series in a metadata provider)
// and checks that the overlay lands exactly where the mask NIfTI says it should.
//
//   node seg_overlay_test.mjs --seg SEG.dcm --series DIR --mask MASK.nii.gz
//
// Prints one summary line; exit 0 only if every SEG frame finds its image in DIR, no two frames
// land on one image, the adapter's labelmap equals the mask voxel for voxel and the NIfTI geometry
// agrees with the series'; otherwise exit 1 with a one-line reason.
//
// Packages (package-lock.json): @cornerstonejs/adapters 5.14.0 with its peers core, tools and
// metadata 5.14.0, dcmjs 0.52.0 (the version the adapter depends on, so there is one copy), and
// @babel/runtime 7.26.10, which the adapter imports without declaring it. The adapter's 4.x line
// does not load in Node at all (directory imports in its ESM build); 5.x runs in Node 20 as is and
// in Node 18 with the two shims below. npm warns that dcmjs asks for Node >= 22.13; it works.

import { readFileSync, readdirSync, statSync } from 'node:fs';
import { gunzipSync } from 'node:zlib';
import { join, resolve } from 'node:path';
import { pathToFileURL } from 'node:url';
import { register } from 'node:module';

const POS_TOL = 1e-3; // mm: SEG frame position vs its image's ImagePositionPatient
// NIfTI voxel -> patient point vs DICOM, per transform. The sform holds the affine in float32
// elements: exact up to float32 rounding, far below 1e-3 mm. The qform holds the rotation as a
// float32 quaternion (b, c, d; a = sqrt(1 - b^2 - c^2 - d^2) is implied): near a 180 degree
// rotation (a ~ 0, as for LPS -> RAS with a tilt) the rounding of b, c and d (2^-24 relative each)
// leaves a uncertain by up to sqrt(3 * 2 * 2^-24) ~ 6e-4, an angle error of twice that, so a
// point r mm from the origin voxel is only good to ~1.2e-3 * r mm (0.1 mm at 90 mm; the NIfTI-1
// header's quatern fields, nifti1.h). Measured: 0.04 mm on tests/data/ct-tilt, 0.025 mm on the
// tilted phantom.
const SFORM_TOL = 1e-3; // mm
const QFORM_TOL_PER_MM = 2 * Math.sqrt(6 * 2 ** -24); // rad: times the distance from voxel (0,0,0)

function fail(reason) {
  console.log(`FAIL: ${reason}`);
  process.exit(1);
}

function parseArgs(argv) {
  const args = {};
  for (let i = 0; i < argv.length; i++) {
    const key = argv[i];
    if (!['--seg', '--series', '--mask'].includes(key) || i + 1 >= argv.length) {
      fail(`usage: node seg_overlay_test.mjs --seg SEG.dcm --series DIR --mask MASK.nii.gz (bad argument ${key})`);
    }
    args[key.slice(2)] = argv[++i];
  }
  for (const k of ['seg', 'series', 'mask']) if (!args[k]) fail(`missing --${k}`);
  return args;
}

// Node < 20.19 (Debian bookworm has 18.20) does not detect ES-module syntax in a ".js" file of a
// package without "type": "module"; dcmjs's and gl-matrix's ESM builds are such files, which
// Cornerstone3D imports by name. This loader hook does what newer Node does: a file that does not
// compile as CommonJS is loaded as an ES module. Newer Node does not need (or get) it.
const ESM_DETECT_HOOK = `
import { readFile } from 'node:fs/promises';
import vm from 'node:vm';
export async function load(url, context, nextLoad) {
  const r = await nextLoad(url, context);
  if (r.format !== 'commonjs' || !url.startsWith('file:') || !url.includes('/node_modules/')) return r;
  const src = r.source != null ? String(r.source) : await readFile(new URL(url), 'utf8');
  try {
    vm.compileFunction(src, ['exports', 'require', 'module', '__filename', '__dirname']);
    return r;
  } catch (e) {
    if (!(e instanceof SyntaxError)) return r;
    return { format: 'module', source: src, shortCircuit: true };
  }
}`;
if (!process.features.require_module) {
  register(`data:text/javascript,${encodeURIComponent(ESM_DETECT_HOOK)}`, import.meta.url);
}
// Browser globals that Node 18 lacks (Node 20 has them): Web Crypto, for the ids Cornerstone gives
// the derived labelmap images (crypto.randomUUID()), and CustomEvent, for its load-progress events.
if (!globalThis.crypto) {
  const { webcrypto } = await import('node:crypto');
  Object.defineProperty(globalThis, 'crypto', { value: webcrypto, configurable: true });
}
if (!globalThis.CustomEvent) {
  globalThis.CustomEvent = class CustomEvent extends Event {
    constructor(type, options = {}) {
      super(type, options);
      this.detail = options.detail ?? null;
    }
  };
}

// The adapter reports frames it cannot place only as log warnings ("Image not present in stack,
// can't import frame : N."); loglevel binds console.warn when the logger is made, so capture it
// before the modules load.
const adapterWarnings = [];
const originalWarn = console.warn;
console.warn = (...a) => {
  adapterWarnings.push(a.map(String).join(' '));
};

const { default: dcmjs } = await import('dcmjs').then((m) => (m.default ? m : { default: m }));
const cornerstone = await import('@cornerstonejs/core');
const adapters = await import('@cornerstonejs/adapters');
const { createFromDICOMSegBuffer } = adapters.adaptersSEG.Cornerstone3D.Segmentation;
const { DicomMessage, DicomMetaDictionary } = dcmjs.data;

// ---------------------------------------------------------------- small vector helpers
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const dist = (a, b) => Math.hypot(...sub(a, b));
const nums = (v) => (Array.isArray(v) ? v : [v]).map(Number);
const first = (v) => (Array.isArray(v) ? v[0] : v);
const asArray = (v) => (v === undefined ? [] : Array.isArray(v) ? v : [v]);

function readDicom(path) {
  const buf = readFileSync(path);
  const arrayBuffer = buf.buffer.slice(buf.byteOffset, buf.byteOffset + buf.byteLength);
  const dicomData = DicomMessage.readFile(arrayBuffer);
  const dataset = DicomMetaDictionary.naturalizeDataset(dicomData.dict);
  dataset._meta = DicomMetaDictionary.namifyDataset(dicomData.meta);
  return { dataset, arrayBuffer };
}

// ---------------------------------------------------------------- the image series
const args = parseArgs(process.argv.slice(2));
const seriesDir = resolve(args.series);
const files = readdirSync(seriesDir)
  .map((f) => join(seriesDir, f))
  .filter((p) => statSync(p).isFile());
if (files.length === 0) fail(`no files in ${seriesDir}`);

const images = files.map((path) => {
  let dataset;
  try {
    ({ dataset } = readDicom(path));
  } catch (e) {
    fail(`${path} is not readable DICOM: ${e.message}`);
  }
  return { path, ds: dataset, imageId: `wadouri:${pathToFileURL(path).href}` };
});
const seriesUIDs = new Set(images.map((im) => im.ds.SeriesInstanceUID));
if (seriesUIDs.size !== 1) fail(`${seriesDir} holds ${seriesUIDs.size} series, expected one`);
const seriesUID = images[0].ds.SeriesInstanceUID;
const seriesFoR = images[0].ds.FrameOfReferenceUID;
const iop = nums(images[0].ds.ImageOrientationPatient);
const rowDir = iop.slice(0, 3); // direction of a row: column index increases along it
const colDir = iop.slice(3, 6); // direction of a column: row index increases along it
const normal = cross(rowDir, colDir);
const [rowSpacing, colSpacing] = nums(images[0].ds.PixelSpacing);
const Rows = Number(images[0].ds.Rows);
const Columns = Number(images[0].ds.Columns);
for (const im of images) {
  im.ipp = nums(im.ds.ImagePositionPatient);
  if (nums(im.ds.ImageOrientationPatient).some((v, i) => Math.abs(v - iop[i]) > 1e-6)) {
    fail(`${im.path}: ImageOrientationPatient differs within the series`);
  }
  if (Number(im.ds.Rows) !== Rows || Number(im.ds.Columns) !== Columns) fail(`${im.path}: size differs within the series`);
}
// A viewer shows the stack in spatial order; the NIfTI's k follows the same order.
images.sort((a, b) => dot(a.ipp, normal) - dot(b.ipp, normal));
const imageIds = images.map((im) => im.imageId);
const bySop = new Map(images.map((im, index) => [im.ds.SOPInstanceUID, { ...im, index }]));
const byImageId = new Map(images.map((im) => [im.imageId, im]));

// ---------------------------------------------------------------- metadata provider (as OHIF's)
const custom = new Map(); // imageId -> { type -> metadata }, for what the adapter adds (the SEG)
function moduleFor(type, imageId) {
  const extra = custom.get(imageId);
  if (extra && extra[type] !== undefined) return extra[type];
  const im = byImageId.get(imageId);
  if (!im) return undefined;
  const ds = im.ds;
  switch (type) {
    case 'instance':
      return ds;
    case 'generalSeriesModule':
      return {
        modality: ds.Modality,
        seriesInstanceUID: ds.SeriesInstanceUID,
        seriesNumber: Number(ds.SeriesNumber),
        studyInstanceUID: ds.StudyInstanceUID,
        seriesDate: ds.SeriesDate,
        seriesTime: ds.SeriesTime,
      };
    case 'generalImageModule':
      return {
        sopInstanceUID: ds.SOPInstanceUID,
        instanceNumber: Number(ds.InstanceNumber),
        lossyImageCompression: ds.LossyImageCompression,
      };
    case 'imagePlaneModule':
      return {
        frameOfReferenceUID: ds.FrameOfReferenceUID,
        rows: Rows,
        columns: Columns,
        imageOrientationPatient: iop,
        rowCosines: rowDir,
        columnCosines: colDir,
        imagePositionPatient: im.ipp,
        sliceThickness: Number(ds.SliceThickness),
        sliceLocation: ds.SliceLocation === undefined ? undefined : Number(ds.SliceLocation),
        pixelSpacing: [rowSpacing, colSpacing],
        rowPixelSpacing: rowSpacing,
        columnPixelSpacing: colSpacing,
      };
    case 'imagePixelModule':
      return {
        samplesPerPixel: Number(ds.SamplesPerPixel),
        photometricInterpretation: ds.PhotometricInterpretation,
        rows: Rows,
        columns: Columns,
        bitsAllocated: Number(ds.BitsAllocated),
        bitsStored: Number(ds.BitsStored),
        highBit: Number(ds.HighBit),
        pixelRepresentation: Number(ds.PixelRepresentation),
      };
    case 'modalityLutModule':
      return { rescaleIntercept: Number(ds.RescaleIntercept ?? 0), rescaleSlope: Number(ds.RescaleSlope ?? 1) };
    case 'sopCommonModule':
      return { sopClassUID: ds.SOPClassUID, sopInstanceUID: ds.SOPInstanceUID };
    default:
      return undefined;
  }
}
const metadataProvider = {
  get: moduleFor,
  add(imageId, type, metadata) {
    custom.set(imageId, { ...(custom.get(imageId) ?? {}), [type]: metadata });
  },
};
// Cornerstone's own registry: the derived labelmap images read the referenced images' planes there.
cornerstone.metaData.addProvider((type, imageId) => moduleFor(type, imageId), 10000);

// ---------------------------------------------------------------- the SEG, parsed independently
const { dataset: seg, arrayBuffer: segBuffer } = readDicom(resolve(args.seg));
if (seg.SOPClassUID !== '1.2.840.10008.5.1.4.1.1.66.4') fail(`${args.seg} is not a Segmentation Storage object`);
if (Number(seg.Rows) !== Rows || Number(seg.Columns) !== Columns) {
  fail(`SEG frames are ${seg.Columns}x${seg.Rows}, the series' images ${Columns}x${Rows}`);
}
const refSeries = asArray(seg.ReferencedSeriesSequence).map((s) => s.SeriesInstanceUID);
const perFrame = asArray(seg.PerFrameFunctionalGroupsSequence);
const nFrames = Number(seg.NumberOfFrames);
if (perFrame.length !== nFrames) fail(`NumberOfFrames ${nFrames} but ${perFrame.length} per-frame groups`);
const shared = first(seg.SharedFunctionalGroupsSequence) ?? {};

// Bit-packed binary frames (BitsAllocated 1), LSB first, frames follow each other without padding.
function segFrameBits(frameIndex) {
  const pd = seg.PixelData;
  const bytes = new Uint8Array(Array.isArray(pd) ? pd[0] : pd);
  const n = Rows * Columns;
  const out = new Uint8Array(n);
  if (Number(seg.BitsAllocated) === 1) {
    const base = frameIndex * n;
    for (let p = 0; p < n; p++) {
      const bit = base + p;
      out[p] = (bytes[bit >> 3] >> (bit & 7)) & 1;
    }
  } else {
    for (let p = 0; p < n; p++) out[p] = bytes[frameIndex * n + p] ? 1 : 0;
  }
  return out;
}

const frames = perFrame.map((g, i) => {
  const der = first(g.DerivationImageSequence);
  const refs = asArray(der?.SourceImageSequence).map((s) => s.ReferencedSOPInstanceUID);
  const segment = Number(first(g.SegmentIdentificationSequence)?.ReferencedSegmentNumber);
  const pos = nums(first(g.PlanePositionSequence)?.ImagePositionPatient ?? []);
  const frameIop = first(g.PlaneOrientationSequence ?? shared.PlaneOrientationSequence)?.ImageOrientationPatient;
  return { i, refs, segment, pos, iop: frameIop ? nums(frameIop) : undefined };
});

const problems = [];
if (!refSeries.includes(seriesUID)) {
  problems.push(`ReferencedSeriesSequence names ${refSeries.join(',') || 'nothing'}, not the series in DIR (${seriesUID})`);
}
if (seg.FrameOfReferenceUID !== seriesFoR) problems.push(`FrameOfReferenceUID ${seg.FrameOfReferenceUID} != series' ${seriesFoR}`);

let framesWithoutImage = 0;
let positionMismatches = 0;
const framesOnImage = new Map(); // `${segment}/${imageIndex}` -> frame indices
const expected = images.map(() => new Uint8Array(Rows * Columns)); // the SEG's own placement
for (const f of frames) {
  if (f.iop && f.iop.some((v, k) => Math.abs(v - iop[k]) > 1e-4)) problems.push(`frame ${f.i + 1} orientation differs from the series'`);
  // The frame's image: the first SourceImageSequence item that is an instance of DIR (the adapter
  // reads only the first item, so a first item outside DIR is counted as not finding its image).
  const im = f.refs.length > 0 ? bySop.get(f.refs[0]) : undefined;
  if (!im) {
    framesWithoutImage++;
    continue;
  }
  f.image = im.index;
  if (f.pos.length !== 3 || dist(f.pos, im.ipp) > POS_TOL) positionMismatches++;
  const key = `${f.segment}/${im.index}`;
  framesOnImage.set(key, [...(framesOnImage.get(key) ?? []), f.i]);
  const bits = segFrameBits(f.i);
  const e = expected[im.index];
  for (let p = 0; p < bits.length; p++) if (bits[p]) e[p] = 1;
}
const stacked = [...framesOnImage.values()].filter((v) => v.length > 1);
const framesStacked = stacked.reduce((s, v) => s + v.length, 0);

// ---------------------------------------------------------------- the adapter (what OHIF v3 does)
let result;
try {
  result = await createFromDICOMSegBuffer(imageIds, segBuffer, { metadataProvider });
} catch (e) {
  fail(`the adapter could not load the SEG: ${e.message}`);
}
const droppedFrames = adapterWarnings.filter((w) => /can't import frame/.test(w)).length;
const layers = result.labelMapImages; // [layer][image], layers > 1 only for overlapping segments
const overlay = images.map((_, k) => {
  const out = new Uint8Array(Rows * Columns);
  for (const layer of layers) {
    const img = layer[k];
    if (!img) continue;
    if (img.referencedImageId !== imageIds[k]) fail(`adapter labelmap ${k} refers to ${img.referencedImageId}, not ${imageIds[k]}`);
    const vm = img.voxelManager;
    const data = vm?.getScalarData ? vm.getScalarData() : img.getPixelData();
    if (data && data.length === out.length) {
      for (let p = 0; p < out.length; p++) if (data[p]) out[p] = 1;
    } else if (vm) {
      for (let p = 0; p < out.length; p++) if (vm.getAtIndex(p)) out[p] = 1;
    }
  }
  return out;
});
// Two frames of one segment on one image: when their pixels overlap the adapter switches to its
// overlapping-segments path (which keeps only one frame per image and segment); otherwise it
// records the segment twice for that image in segmentsOnFrame. (segmentsOnFrame also repeats
// entries after a switch, so it is counted only on the ordinary path.)
const adapterOverlapping = Boolean(result.overlappingSegments);
const adapterStackedImages = adapterOverlapping
  ? 0
  : (result.segmentsOnFrame ?? []).filter((s) => s && new Set(s).size !== s.length).length;

// The adapter's placement against the SEG's own references.
let placementMismatches = 0;
for (let k = 0; k < images.length; k++) {
  for (let p = 0; p < Rows * Columns; p++) if (overlay[k][p] !== expected[k][p]) placementMismatches++;
}

// ---------------------------------------------------------------- the mask NIfTI
function readNifti(path) {
  let buf = readFileSync(path);
  if (buf[0] === 0x1f && buf[1] === 0x8b) buf = gunzipSync(buf);
  let le = true;
  if (buf.readInt32LE(0) !== 348) {
    if (buf.readInt32BE(0) !== 348) fail(`${path} is not a NIfTI-1 file`);
    le = false;
  }
  const i16 = (o) => (le ? buf.readInt16LE(o) : buf.readInt16BE(o));
  const f32 = (o) => (le ? buf.readFloatLE(o) : buf.readFloatBE(o));
  const magic = buf.toString('latin1', 344, 347);
  if (magic !== 'n+1' && magic !== 'ni1') fail(`${path}: bad NIfTI magic ${JSON.stringify(magic)}`);
  const dim = [...Array(8)].map((_, k) => i16(40 + 2 * k));
  const datatype = i16(70);
  const pixdim = [...Array(8)].map((_, k) => f32(76 + 4 * k));
  const voxOffset = f32(108);
  const sclSlope = f32(112);
  const sclInter = f32(116);
  const qformCode = i16(252);
  const sformCode = i16(254);
  const [qb, qc, qd, qx, qy, qz] = [...Array(6)].map((_, k) => f32(256 + 4 * k));
  const srow = [0, 1, 2].map((r) => [0, 1, 2, 3].map((c) => f32(280 + 16 * r + 4 * c)));
  const [nx, ny, nz] = [dim[1], dim[2], Math.max(dim[3], 1)];
  if (dim[0] > 3 && dim.slice(4, dim[0] + 1).some((d) => d > 1)) fail(`${path}: more than 3 dimensions`);
  const n = nx * ny * nz;
  const readers = {
    2: (k) => buf.readUInt8(voxOffset + k),
    256: (k) => buf.readInt8(voxOffset + k),
    4: (k) => (le ? buf.readInt16LE(voxOffset + 2 * k) : buf.readInt16BE(voxOffset + 2 * k)),
    512: (k) => (le ? buf.readUInt16LE(voxOffset + 2 * k) : buf.readUInt16BE(voxOffset + 2 * k)),
    8: (k) => (le ? buf.readInt32LE(voxOffset + 4 * k) : buf.readInt32BE(voxOffset + 4 * k)),
    16: (k) => f32(voxOffset + 4 * k),
  };
  const rd = readers[datatype];
  if (!rd) fail(`${path}: unsupported NIfTI datatype ${datatype}`);
  if (buf.length < voxOffset + n * (datatype === 2 || datatype === 256 ? 1 : datatype === 4 || datatype === 512 ? 2 : 4)) {
    fail(`${path}: truncated voxel data`);
  }
  const slope = sclSlope === 0 || !Number.isFinite(sclSlope) ? 1 : sclSlope;
  const inter = Number.isFinite(sclInter) ? sclInter : 0;
  const voxels = new Uint8Array(n);
  for (let k = 0; k < n; k++) voxels[k] = rd(k) * slope + inter !== 0 ? 1 : 0;

  // voxel (i,j,k) -> RAS point, per the transforms the file sets (code > 0)
  const transforms = [];
  if (sformCode > 0) {
    transforms.push({ name: 'sform', map: (i, j, k) => srow.map((r) => r[0] * i + r[1] * j + r[2] * k + r[3]) });
  }
  if (qformCode > 0) {
    const qa = Math.sqrt(Math.max(0, 1 - (qb * qb + qc * qc + qd * qd)));
    const R = [
      [qa * qa + qb * qb - qc * qc - qd * qd, 2 * (qb * qc - qa * qd), 2 * (qb * qd + qa * qc)],
      [2 * (qb * qc + qa * qd), qa * qa + qc * qc - qb * qb - qd * qd, 2 * (qc * qd - qa * qb)],
      [2 * (qb * qd - qa * qc), 2 * (qc * qd + qa * qb), qa * qa + qd * qd - qc * qc - qb * qb],
    ];
    const qfac = pixdim[0] < 0 ? -1 : 1;
    const s = [pixdim[1], pixdim[2], pixdim[3] * qfac];
    transforms.push({
      name: 'qform',
      map: (i, j, k) => [0, 1, 2].map((r) => R[r][0] * s[0] * i + R[r][1] * s[1] * j + R[r][2] * s[2] * k + [qx, qy, qz][r]),
    });
  }
  return { nx, ny, nz, voxels, transforms };
}

const nii = readNifti(resolve(args.mask));
if (nii.nx !== Columns || nii.ny !== Rows || nii.nz !== images.length) {
  fail(`mask is ${nii.nx}x${nii.ny}x${nii.nz}, the series ${Columns}x${Rows}x${images.length}`);
}
if (nii.transforms.length === 0) fail('mask NIfTI sets neither sform nor qform');

// Geometry: each transform, at the four corners of every slice, against the DICOM plane.
let geomMaxErr = 0;
let geomWorst = '';
let geomOver = 0; // the largest excess over a transform's tolerance
let geomOverWhere = '';
for (const t of nii.transforms) {
  for (let k = 0; k < nii.nz; k++) {
    for (const [i, j] of [[0, 0], [nii.nx - 1, 0], [0, nii.ny - 1], [nii.nx - 1, nii.ny - 1]]) {
      const ras = t.map(i, j, k);
      const lps = [-ras[0], -ras[1], ras[2]];
      const dicom = add(add(images[k].ipp, scale(rowDir, i * colSpacing)), scale(colDir, j * rowSpacing));
      const err = dist(lps, dicom);
      const tol = t.name === 'sform' ? SFORM_TOL : SFORM_TOL + QFORM_TOL_PER_MM * dist(dicom, images[0].ipp);
      if (err > geomMaxErr) {
        geomMaxErr = err;
        geomWorst = `${t.name} voxel (${i},${j},${k})`;
      }
      if (err > tol && err - tol > geomOver) {
        geomOver = err - tol;
        geomOverWhere = `${t.name} voxel (${i},${j},${k}): ${err.toFixed(4)} mm > ${tol.toFixed(4)} mm`;
      }
    }
  }
}
const geometryOk = geomOver === 0;

// Voxel for voxel: NIfTI (i,j,k) is column i, row j of the k-th image along the normal.
let compared = 0;
let mismatches = 0;
let both = 0;
let inMask = 0;
let inOverlay = 0;
for (let k = 0; k < nii.nz; k++) {
  const ov = overlay[k];
  for (let j = 0; j < nii.ny; j++) {
    for (let i = 0; i < nii.nx; i++) {
      const m = nii.voxels[i + nii.nx * (j + nii.ny * k)];
      const o = ov[j * Columns + i];
      compared++;
      if (m !== o) mismatches++;
      if (m) inMask++;
      if (o) inOverlay++;
      if (m && o) both++;
    }
  }
}
const dice = inMask + inOverlay === 0 ? 1 : (2 * both) / (inMask + inOverlay);

console.warn = originalWarn;
console.log(
  `seg-overlay: frames=${nFrames} images=${images.length} frames_without_image=${framesWithoutImage} ` +
    `frames_stacked=${framesStacked} adapter_dropped=${droppedFrames} adapter_stacked_images=${adapterStackedImages} adapter_overlap_path=${adapterOverlapping ? 1 : 0} ` +
    `position_mismatches=${positionMismatches} placement_mismatches=${placementMismatches} ` +
    `voxels=${compared} mismatches=${mismatches} mask_voxels=${inMask} overlay_voxels=${inOverlay} ` +
    `dice=${dice.toFixed(6)} geometry_max_err_mm=${geomMaxErr.toExponential(2)}`,
);

if (framesWithoutImage > 0) {
  const f = frames.find((x) => x.image === undefined);
  problems.unshift(
    `${framesWithoutImage} of ${nFrames} SEG frames reference no image of the series (frame ${f.i + 1} references ${f.refs[0] ?? 'nothing'})` +
      (droppedFrames > 0 ? `; the adapter dropped ${droppedFrames} frames` : '') +
      (framesWithoutImage > droppedFrames
        ? `; the adapter placed ${framesWithoutImage - droppedFrames} of them by position (its geometry fallback)`
        : ''),
  );
}
if (stacked.length > 0) {
  problems.push(`${framesStacked} SEG frames stacked on ${stacked.length} images (frames ${stacked[0].map((x) => x + 1).join(',')} on one image)`);
}
if (adapterOverlapping) {
  problems.push('the adapter found overlapping frames of one segment and took its overlapping-segments path');
} else if (adapterStackedImages > 0) {
  problems.push(`the adapter put several frames of one segment on ${adapterStackedImages} images`);
}
if (positionMismatches > 0) problems.push(`${positionMismatches} frames' PlanePosition differs from their image's ImagePositionPatient by > ${POS_TOL} mm`);
if (placementMismatches > 0 && framesWithoutImage === 0) problems.push(`the adapter's labelmap differs from the SEG frames' own placement in ${placementMismatches} voxels`);
if (!geometryOk) problems.push(`NIfTI geometry differs from the series' beyond its tolerance (${geomOverWhere})`);
if (mismatches > 0) problems.push(`${mismatches} voxels of the overlay differ from the mask (Dice ${dice.toFixed(6)})`);

if (problems.length > 0) fail(problems.join('; '));
console.log('PASS');
process.exit(0);
