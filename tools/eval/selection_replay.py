#!/usr/bin/python3
"""Replays auto's per-label selection with other rules, on published CSVs.

Usage: /usr/bin/python3 tools/eval/selection_replay.py [EVAL_DIR]

EVAL_DIR (default docs/eval/segmentations) holds one folder per series as
scripts/eval-segmentations.sh --real publishes them: fill_metrics.csv (each
method's Dice per label on the withheld slices), fill_choices.csv (auto's
validation Dice D(2g) per candidate and label) and
fill_validation_slices.csv (the same per held-out key slice). A rule sees
only the validation, as auto does; the withheld truth only scores it. This
is how to try a selection rule in seconds instead of a 6-minute eval run.

Rules replayed:
- published: the argmax of D(2g) (AutoSelection::kDoubledGap, with the
  "everything below 0.1 -> morph" rule); it must make auto's published
  choice for every label (checked; exit status 1 if not).
- prefer B, z: start from the best of the base set B by D(2g); move to the
  overall best only when its paired mean gain over B's pick, across the
  held-out slices, exceeds z standard errors. A noise-aware rule: it asks
  whether the validation's ranking is more than the scatter of a few slices.

For each rule, over every series x k: cells below the better of copy and
linear (the issue-24 baseline, chosen per cell with hindsight), cells that
miss the Dice goal (below it, or less than +0.01 at k >= 5), the summed
margin and the worst cell. Labels without validation (drawn on one or two
key slices) keep the published choice. A rule that picks "blend" where the
published auto did not has no truth (the harness does not run the blend
alone): such picks are counted as "unscored" and scored as the published
choice. A label is scored with its pick's Dice from that method's own fill
of every label; in auto's fill its neighbours may have been filled by other
candidates, and where labels touch the merge differs, so on multi-label
series the replay of the published rule is close to auto's published Dice
but not equal (summed margin +0.326 against +0.340 on the published CSVs).
Compare rules with each other here, and confirm a rule worth adopting with
the eval itself. Standard library only.
"""
import collections
import csv
import math
import os
import statistics
import sys

CANDIDATES = ('copy', 'linear', 'blend', 'direct', 'morph')
TIE_ORDER = ('linear', 'direct', 'morph', 'blend', 'copy')  # label_fill.h


def load(folder):
    truth = collections.defaultdict(dict)  # (k, label) -> method -> Dice
    with open(os.path.join(folder, 'fill_metrics.csv')) as f:
        for row in csv.DictReader(f):
            truth[(int(row['k']), int(row['label']))][row['method']] = float(
                row['dice'])
    choices = {}
    with open(os.path.join(folder, 'fill_choices.csv')) as f:
        for row in csv.DictReader(f):
            if row['method'] == 'auto':
                choices[(int(row['k']), int(row['label']))] = row
    slices = collections.defaultdict(list)
    with open(os.path.join(folder, 'fill_validation_slices.csv')) as f:
        for row in csv.DictReader(f):
            if row['method'] == 'auto' and row['gap'] == '2g':
                slices[(int(row['k']), int(row['label']))].append(
                    {c: float(row[c]) for c in CANDIDATES})
    for key, row in choices.items():
        if row['chosen'] == 'blend' and 'auto' in truth[key]:
            truth[key]['blend'] = truth[key]['auto']
    return truth, choices, slices


def argmax(scores):
    best = None
    for c in TIE_ORDER:
        if c in scores and (best is None or scores[c] > scores[best]):
            best = c
    return best


def validation(row):
    """D(2g) per candidate, or None for a label without validation."""
    if row['d2_copy'] == '':
        return None
    return {c: float(row['d2_' + c]) for c in CANDIDATES}


def published(row, _slices):
    d2 = validation(row)
    if d2 is None:
        return row['chosen']
    if max(d2.values()) < 0.1:
        return 'morph'
    return argmax(d2)


def prefer(base_set, z):
    def rule(row, held_out):
        d2 = validation(row)
        if d2 is None or len(held_out) < 2:
            return row['chosen']
        if max(d2.values()) < 0.1:
            return 'morph'
        base = argmax({c: d2[c] for c in base_set})
        best = argmax(d2)
        if best == base:
            return base
        gains = [s[best] - s[base] for s in held_out]
        standard_error = statistics.stdev(gains) / math.sqrt(len(gains))
        return best if statistics.mean(gains) > z * standard_error else base
    return rule


def replay(data, rule):
    cells, unscored = {}, 0
    for series, (truth, choices, slices) in data.items():
        for k in sorted({k for (k, _) in truth}):
            labels = [l for (kk, l) in truth if kk == k
                      and 'auto' in truth[(kk, l)]]
            total = 0.0
            for label in labels:
                key = (k, label)
                pick = (rule(choices[key], slices.get(key, []))
                        if key in choices else 'auto')
                if pick not in truth[key]:
                    unscored += 1
                    pick = 'auto'
                total += truth[key][pick]
            baseline = max(
                sum(truth[(k, l)][m] for l in labels) / len(labels)
                for m in ('copy', 'linear'))
            cells[(series, k)] = (total / len(labels), baseline)
    return cells, unscored


def main():
    root = sys.argv[1] if len(sys.argv) > 1 else os.path.join(
        os.path.dirname(os.path.abspath(__file__)), '..', '..', 'docs',
        'eval', 'segmentations')
    data = {}
    for name in sorted(os.listdir(root)):
        folder = os.path.join(root, name)
        if os.path.isfile(os.path.join(folder, 'fill_validation_slices.csv')):
            data[name] = load(folder)
    if not data:
        print(f'selection_replay.py: no published series in {root}')
        return 1
    rules = [('published (argmax D(2g))', published)]
    for base in (('copy', 'linear'), ('morph',), ('morph', 'linear')):
        for z in (0.5, 1.0, 2.0):
            rules.append((f'prefer {"+".join(base)}, z = {z}', prefer(base, z)))
    print('| rule | below baseline | Dice goal missed | summed margin | '
          'worst cell | unscored picks |')
    print('|---|---|---|---|---|---|')
    for name, rule in rules:
        cells, unscored = replay(data, rule)
        below = sum(a < b - 1e-9 for a, b in cells.values())
        missed = sum(a < b - 1e-9 or (k >= 5 and a < b + 0.01 - 1e-9)
                     for (_, k), (a, b) in cells.items())
        margin = sum(a - b for a, b in cells.values())
        worst = min(a - b for a, b in cells.values())
        print(f'| {name} | {below} of {len(cells)} | {missed} | '
              f'{margin:+.4f} | {worst:+.4f} | {unscored} |')
    # The published rule must make the published choices.
    mismatched = [
        f'{series} k={k} label {label}'
        for series, (_, choices, slices) in data.items()
        for (k, label), row in choices.items()
        if published(row, slices.get((k, label), [])) != row['chosen']]
    print('published rule makes the published choice for every label'
          if not mismatched else
          'published rule differs from auto for: ' + ', '.join(mismatched))
    return 0 if not mismatched else 1

if __name__ == '__main__':
    sys.exit(main())
