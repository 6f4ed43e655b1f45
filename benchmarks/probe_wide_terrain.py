# SPDX-License-Identifier: Apache-2.0
"""Probe (issue 10): the wide-terrain rule of the outlier test on seeds nobody chose it on.

Usage::

    python benchmarks/probe_wide_terrain.py [--seeds 8]

What it measures: this project's pooled F1 on every bench_quality group -- the real scans
and each synthetic family with seeds 0 .. seeds-1 (bench_quality itself uses 0-2) -- for the
wide-terrain rule off (``outlier_wide_terrain_m`` 0), on at 0.5 / 1.0 / 2.0 m without the
slope limit, and at 1.0 m with slope limits 0.5 / 0.4 / 0.3 / 0.2
(``outlier_wide_terrain_max_slope``); everything else at the defaults, cold. Then the
leave-one-group-out choice among those settings, as bench_quality's ``--cv`` makes it. Four
decimals, because the rule moves most groups by less than 0.001. Prints markdown; nothing is
written.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_quality  # noqa: E402

from gp_ground_segmentation import SegmenterParams  # noqa: E402

NO_LIMIT = 100.0  # the parameter's upper bound: no candidate rises steeper than that


def settings() -> dict:
    """{name: SegmenterParams} of the probed settings."""
    d = SegmenterParams()

    def with_rule(tolerance, slope):
        return dataclasses.replace(d, outlier_wide_terrain_m=tolerance,
                                   outlier_wide_terrain_max_slope=slope).validate()

    out = {'off': with_rule(0.0, d.outlier_wide_terrain_max_slope)}
    for tolerance in (0.5, 1.0, 2.0):
        out[f'{tolerance} m, no slope limit'] = with_rule(tolerance, NO_LIMIT)
    for slope in (0.5, 0.4, 0.3, 0.2):
        out[f'1.0 m, slope <= {slope}'] = with_rule(1.0, slope)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seeds', type=int, default=8, help='seeds per synthetic family (default 8)')
    args = ap.parse_args(argv)
    start = time.time()
    groups = bench_quality.load_groups(seeds=args.seeds)
    candidates = settings()
    f1 = {name: {g.name: bench_quality.f1_of(bench_quality.evaluate(p, g.frames))
                 for g in groups} for name, p in candidates.items()}
    names = list(candidates)
    print(f'python benchmarks/probe_wide_terrain.py --seeds {args.seeds}; '
          f'{time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}\n')
    print('| group | ' + ' | '.join(names) + ' |')
    print('| :--- |' + ' ---: |' * len(names))
    for g in groups:
        print(f'| {g.name} | ' + ' | '.join(f'{f1[n][g.name]:.4f}' for n in names) + ' |')
    means = {n: float(np.mean(list(f1[n].values()))) for n in names}
    print('| **mean of groups** | ' + ' | '.join(f'{means[n]:.4f}' for n in names) + ' |\n')
    print('| held-out group | chosen on the rest | held-out F1 | off held-out F1 |')
    print('| :--- | :--- | ---: | ---: |')
    for g in groups:
        rest = {n: np.mean([v for k, v in f1[n].items() if k != g.name]) for n in names}
        chosen = max(rest, key=rest.get)
        print(f'| {g.name} | {chosen} | {f1[chosen][g.name]:.4f} | {f1["off"][g.name]:.4f} |')
    print(f'\n{time.time() - start:.0f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
