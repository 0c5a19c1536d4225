#!/usr/bin/python3
"""How well the thick series' own slices match the thin truth.

Usage: /usr/bin/python3 tools/eval/key_slice_ceiling.py THIN_DIR THICK_DIR [HU ...]

Every interpolation method keeps the original (key) slices, so on thick ->
thin the key slices' own agreement with the thin series at the same table
position bounds what any method can reach: a thick slice is a 5 mm
reconstruction, its threshold contour is not the thin slice's. Prints, per
threshold, the pooled Dice over the coinciding positions (the harness's
definition: 2|A n B| / (|A| + |B|) summed over slices) and the ratio of
object pixels thick / thin. Needs DCMTK's dcmdump and numpy; reads
uncompressed CT only (as the shipped phantom is). Exits 0 with a message when
a folder is absent.
"""
import glob
import os
import subprocess
import sys
import tempfile

import numpy as np


def element(text, tag):
    return text.split(f'({tag})')[1].split('[')[1].split(']')[0]


def load(folder, scratch):
    """{z (mm, rounded to 0.01): HU image} of a folder of single-frame CT."""
    slices = {}
    for path in sorted(glob.glob(os.path.join(folder, '*'))):
        text = subprocess.run(
            ['dcmdump', '+P', '0020,0032', '+P', '0028,1052', '+P',
             '0028,1053', '+P', '0028,0103', '+P', '0028,0010', '+P',
             '0028,0011', path], capture_output=True, text=True).stdout
        if '(0020,0032)' not in text:
            continue  # not an image (the Philips folders hold other files)
        z = float(element(text, '0020,0032').split('\\')[2])
        intercept = float(element(text, '0028,1052'))
        slope = float(element(text, '0028,1053'))
        rows = int(text.split('(0028,0010) US ')[1].split()[0])
        columns = int(text.split('(0028,0011) US ')[1].split()[0])
        signed = text.split('(0028,0103) US ')[1].split()[0] == '1'
        subprocess.run(['dcmdump', '-q', '+W', scratch, path],
                       capture_output=True, check=True)
        raw = os.path.join(scratch, os.path.basename(path) + '.0.raw')
        pixels = np.fromfile(raw, dtype=np.int16 if signed else np.uint16)
        os.remove(raw)
        slices[round(z, 2)] = (pixels.astype(np.float64) * slope +
                               intercept).reshape(rows, columns)
    return slices


def main():
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    thin_dir, thick_dir = sys.argv[1], sys.argv[2]
    levels = [float(v) for v in sys.argv[3:]] or [300.0]
    for folder in (thin_dir, thick_dir):
        if not os.path.isdir(folder):
            print(f'key_slice_ceiling: {folder} not found; skipped')
            return
    with tempfile.TemporaryDirectory() as scratch:
        thin, thick = load(thin_dir, scratch), load(thick_dir, scratch)
    common = sorted(set(thin) & set(thick))
    print(f'{len(common)} thick slices lie on a thin slice position')
    for level in levels:
        overlap = total = thick_pixels = thin_pixels = 0
        per_slice = []
        for z in common:
            a, b = thick[z] >= level, thin[z] >= level
            if a.sum() + b.sum() == 0:
                continue
            overlap += 2 * int((a & b).sum())
            total += int(a.sum() + b.sum())
            thick_pixels += int(a.sum())
            thin_pixels += int(b.sum())
            per_slice.append(2 * (a & b).sum() / (a.sum() + b.sum()))
        print(f'{level:g} HU: pooled Dice {overlap / total:.4f} over '
              f'{len(per_slice)} slices (per slice median '
              f'{np.median(per_slice):.4f}, min {min(per_slice):.4f}); '
              f'object pixels thick / thin {thick_pixels / thin_pixels:.3f}')


if __name__ == '__main__':
    main()
