# SPDX-License-Identifier: Apache-2.0
"""``gp-ground-seg tune`` with a real budget: cross-validated F1 of the tuned set vs defaults.

Usage::

    python benchmarks/bench_tune.py [--trials 40] [--jobs N] [--seed 0] [--no-write]

Two runs through ``tune.tune`` (the code of ``gp-ground-seg tune``), ``--trials`` trials per
study, leave-one-scene-out over the scenes:

1. SemanticKITTI: every labelled KITTI scan of ``scenes.real_data`` (sequences 00 (frames 0-2),
   02, 04, 05, 06, 08 and 10: seven scenes, one per sequence); ground 40, 44, 48, 49, 60, 72;
   0, 1 ignored; vegetation non-ground (the default protocol).
2. The same plus the RELLIS-3D off-road Ouster scan as one more scene, scored with RELLIS-3D's
   own classes (ground 1, 3, 10, 23, 31, 33; 0 ignored): does a set tuned on KITTI carry over
   to another sensor and world, and the other way round?

Per run: pooled ground F1 of the defaults and of the tuned set on the training frames (final
study on all frames), the leave-one-scene-out CV F1 (held-out counts pooled over the folds) of
the tuned sets vs the defaults on the same frames, each fold, the changed keys, trial states and
wall time. The written parameter file of run 1 is checked with ``load_params_file``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402

from gp_ground_segmentation.ros.config import load_params_file  # noqa: E402
from gp_ground_segmentation.tools import tune  # noqa: E402
from gp_ground_segmentation.tools.engine import open_engine  # noqa: E402
from gp_ground_segmentation.tools.evaluation import DEFAULT_PROTOCOL  # noqa: E402

RESULTS = Path(__file__).resolve().parent / 'RESULTS.md'


def frames_of(data: Path, with_rellis: bool) -> list:
    """tune's frames of every labelled KITTI scan found (each sequence a scene: the file stem
    without its frame number), and the RELLIS-3D scan with its own classes."""
    frames = []
    for scan in common.labelled_scans(data):
        if not scan.exists() or (scan.group == 'rellis3d' and not with_rellis):
            continue
        frames += tune.labelled_frames([str(scan.bin_path)], None,
                                       *DEFAULT_PROTOCOL.classes(scan.ontology),
                                       tune.DEFAULT_SCENE_RULE)
    return frames


def run(frames, engine, trials, seed):
    t0 = time.perf_counter()
    report = tune.tune(frames, engine, trials, seed,
                       log=lambda text: print(f'  {text}', flush=True))
    return report, time.perf_counter() - t0


def section(title, report, wall_s) -> str:
    rows = [['all frames (training score, final study)', f'{report.train_f1_defaults:.4f}',
             f'{report.train_f1_tuned:.4f}',
             f'{report.train_f1_tuned - report.train_f1_defaults:+.4f}'],
            ['**leave-one-scene-out CV (pooled held-out)**', tune._fmt(report.cv_f1_defaults),
             tune._fmt(report.cv_f1_tuned),
             f'{report.cv_f1_tuned - report.cv_f1_defaults:+.4f}' if report.folds else 'n/a']]
    for fold in report.folds:
        rows.append([f"held out {fold['held_out']} ({fold['frames']} frame(s))",
                     f"{fold['test_f1_defaults']:.4f}", f"{fold['test_f1_tuned']:.4f}",
                     f"{fold['test_f1_tuned'] - fold['test_f1_defaults']:+.4f}"])
    table = common.markdown_table(['ground F1', 'defaults', 'tuned', 'tuned - defaults'], rows)
    final = report.final
    folds = '; '.join(f"without {f['held_out']}: {f['changed'] or 'defaults'}"
                      for f in report.folds)
    return (f'### {title}\n\n{table}\n\n'
            f'- Final study: {final.complete} trials complete, {final.pruned} pruned '
            f'(cross-field rule), {final.failed} failed; changed keys: '
            f'{report.tuned or "none (the defaults won)"}.\n'
            f'- Fold studies chose: {folds or "n/a"}.\n'
            f'- Wall time {wall_s:.0f} s on {report.engine} '
            f'({len(report.scenes) + 1 if report.folds else 1} studies x {report.trials} '
            f'trials).\n')


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--trials', type=int, default=40)
    parser.add_argument('--jobs', type=int, default=None)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--no-write', action='store_true')
    args = parser.parse_args(argv)
    data = common.DATA_DIR
    if not (data / 'labeled').is_dir():
        print(f'skipped: {data / "labeled"} not found')
        return 0
    parts = []
    with open_engine(jobs=args.jobs) as engine:
        print('run 1: SemanticKITTI frames', flush=True)
        report, wall = run(frames_of(data, False), engine, args.trials, args.seed)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / 'tuned.yaml'
            path.write_text(tune.params_yaml(report, 'semantickitti'))
            load_params_file(path)  # the written file is one the node accepts
            written = path.read_text()
        parts.append(section(f'SemanticKITTI: {len(report.frames)} scans, '
                             f'{len(report.scenes)} scenes (one per sequence)', report, wall))
        print('Written parameter file (run 1):\n' + written)
        lines = len(written.splitlines())
        parts.append(f'The parameter file run 1 wrote ({lines} lines: a header with the data '
                     'and scores, the changed keys) loads with the node\'s `load_params_file`; '
                     'the script prints it.\n')
        print('run 2: + RELLIS-3D as one more scene', flush=True)
        report2, wall2 = run(frames_of(data, True), engine, args.trials, args.seed)
        parts.append(section('SemanticKITTI + RELLIS-3D (one more scene, its own classes)',
                             report2, wall2))
    text = (f'## Tuner: cross-validated ground F1, tuned vs defaults (`bench_tune.py`)\n\n'
            f'{common.machine_markdown(common.command_line())}'
            f'- Optuna TPE (seed {args.seed}), {args.trials} trials per study; the first trial '
            f'of each study is the defaults; objective = pooled ground F1; every frame segmented '
            f'cold (fresh segmenter). Scenes = file name without the frame number.\n\n'
            + '\n'.join(parts))
    print(text)
    if not args.no_write:
        common.update_results_section(RESULTS, 'bench_tune', text)
    return 0


if __name__ == '__main__':  # required: Dask starts worker processes with 'spawn'
    sys.exit(main())
