# SPDX-License-Identifier: Apache-2.0
"""``gp-ground-seg tune``: search segmenter parameters on labelled scans with Optuna.

* Search space: :data:`SEARCH_SPACE`, a documented subset of ``SegmenterParams`` with search
  ranges narrower than the validity ranges (docs/parameters.md
  has the table generated from it). Values lie
  on a grid (``step``) so the written YAML holds round numbers.
* Objective: pooled ground F1 (TP/FP/FN summed over the frames, then F1) against per-point
  labels (SemanticKITTI-style ``.label``: uint32, class in the low 16 bits) with the ground and
  left-out classes of the labels' ontology under a scoring protocol (``--dataset``,
  ``--protocol``; :mod:`.evaluation`). Every frame is segmented by a fresh segmenter (a cold
  start), so the score does not depend on the frame order.
* A trial whose values break a cross-field rule of ``SegmenterParams.validate()`` (e.g.
  ``sigma_n_init_m`` below ``sigma_n_min_m``) is pruned, not evaluated. The first trial of
  every study is the defaults, so a study's best is never worse than the defaults on its own
  training frames.
* Generalisation: frames are grouped into scenes (consecutive frames of one drive are one
  scene; by default the file name without its trailing frame number, ``--scene-of`` changes
  the rule). With two or more scenes, leave-one-scene-out (:mod:`.crossval`): for each scene a
  study is run on the others and its best set scored on the held-out scene; held-out counts
  are pooled over the folds. That cross-validated F1 of the tuned sets is reported next to the
  defaults' F1 on the same frames. The written parameters come from a final study on all frames.
* Trials run ``engine.workers`` at a time on the same engine as ``batch`` (in-process or Dask).

The output is a ROS 2 parameter file with the layout of config/params.yaml (``'/**':`` /
``ros__parameters:``: the node in any namespace), only the keys that differ from the defaults,
and a comment header saying what it was tuned on and the scores; the node (``--params-file``)
and ``replay --params`` load it.

A tuned set whose cross-validated F1 does not beat the defaults' (:func:`improves`) is no
improvement, whatever it scores on its training frames: the output says so plainly (stdout and
a warning on stderr), and the file keeps the defaults (no key set) with the tuned values in its
comments, so that a file used without reading the report does no harm; ``--write-tuned`` writes
them anyway. The exit status stays 0: the search worked, its finding is that the defaults
generalise better. With one scene there is no cross-validation: the tuned keys are written.
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import json
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..core.params import SegmenterParams, describe_params
from ..core.segmenter import GroundSegmenter
from ..ros.config import render_param_overrides
from .crossval import leave_one_group_out, pooled_f1
from .engine import add_engine_arguments, open_engine
from .errors import CliError
from .evaluation import labelled_ground_truth, truth_metrics
from .io import read_points_file, read_semantickitti_labels
from .options import add_label_class_arguments, label_classes, no_ground_note

OPTUNA_MISSING = ("tune needs Optuna, which is not installed: pip install "
                  "'gp_ground_segmentation[tune]' (or: pip install optuna)")
DEFAULT_SCENE_RULE = r'^(.*?)[_-]?\d+$'


@dataclass(frozen=True)
class SearchRange:
    """One searched parameter: inclusive range, grid step and why this range. ``switch``: the
    use_* field of the parameter's rule, which the range's low end stands for: a searched
    ``low`` is the rule off (``as_params``), any other value is the rule on with that value."""

    name: str
    low: float
    high: float
    step: float
    why: str
    switch: Optional[str] = None

    def suggest(self, trial):
        if isinstance(self.low, int) and isinstance(self.step, int):
            return trial.suggest_int(self.name, self.low, self.high, step=self.step)
        # rounded so 0.1 + 2 * 0.1 is written and evaluated as 0.3, not 0.30000000000000004
        return round(trial.suggest_float(self.name, self.low, self.high, step=self.step), 9)


# The one place that says what is tuned and over which range (docs/parameters.md from it).
SEARCH_SPACE = (
    SearchRange('ground_threshold_m', 0.08, 0.40, 0.01,
                'height above the GP ground that still counts as ground; curbs are ~0.1-0.2 m'),
    SearchRange('max_threshold_m', 0.15, 0.60, 0.01,
                'cap of the total threshold; above ~0.6 m low obstacles vanish into the ground'),
    SearchRange('std_threshold_factor', 0.0, 2.0, 0.1,
                'widen the threshold where the GP is unsure (far, sparse bins)',
                switch='use_std_threshold'),
    SearchRange('line_max_slope', 0.3, 1.2, 0.05,
                'steepest line still taken as ground (dz/dr); ramps of 10-20 deg are 0.18-0.36'),
    SearchRange('line_max_distance_m', 0.05, 0.40, 0.01,
                'distance from the running line that ends it; ~sensor noise to a curb height'),
    SearchRange('plateau_step_m', 0.15, 0.80, 0.05,
                'step up that starts an elevated plateau; must stay above curb height'),
    SearchRange('outlier_residual_m', 0.3, 1.6, 0.05,
                'leave-one-out residual that marks a candidate as an obstacle top'),
    SearchRange('sigma_n_min_m', 0.01, 0.06, 0.005,
                'floor of the learned GP noise std; HDL-64 range noise is ~0.02 m'),
    SearchRange('sigma_n_init_m', 0.02, 0.15, 0.005,
                'start of the GP noise std (first frame); must be >= sigma_n_min_m'),
    SearchRange('num_bins', 16, 36, 4,
                'radial bins per segment: resolution of the ground profile vs cost'),
    SearchRange('structure_rise_m', 0.15, 0.35, 0.01,
                'height over the ground that makes a point a column of the structure test; '
                'above curb height'),
)


def search_space_defaults() -> dict:
    """The defaults as searched values (a switched rule that is off: its range's low end)."""
    defaults = SegmenterParams()
    return {r.name: (r.low if r.switch and not getattr(defaults, r.switch)
                     else getattr(defaults, r.name)) for r in SEARCH_SPACE}


def as_params(values: dict) -> dict:
    """Searched ``values`` as SegmenterParams fields: a switched parameter at its range's low
    end is its rule off (``switch`` false), any other value the rule on with that value (the
    switch set only where its default is off)."""
    defaults, ranges = SegmenterParams(), {r.name: r for r in SEARCH_SPACE}
    out = {}
    for name, value in values.items():
        r = ranges.get(name)
        if r is None or r.switch is None:
            out[name] = value
        elif value <= r.low:
            out[r.switch] = False
        else:
            out[name] = value
            if not getattr(defaults, r.switch):
                out[r.switch] = True
    return out


def render_search_space_table() -> str:
    """Markdown table of the search space (docs/parameters.md)."""
    specs = {row['name']: row for row in describe_params()}
    out = ['| parameter | default | search range (step) | validity range | why this range |',
           '|---|---|---|---|---|']
    defaults = search_space_defaults()
    for r in SEARCH_SPACE:
        spec = specs[r.name]
        searched = f'{r.low} .. {r.high} ({r.step})'
        if r.switch:
            searched += f'; {r.low} = `{r.switch}` false'
        out.append(f"| `{r.name}` | `{defaults[r.name]}` | {searched} | "
                   f"{spec['min']} .. {spec['max']} | {r.why} |")
    return '\n'.join(out) + '\n'


# ---------------------------------------------------------------------------------------------
# Frames and their evaluation (runs in the tasks)
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class LabelledFrame:
    """A scan file, its .label file, its scene and the class lists that define ground."""

    points: str
    labels: str
    scene: str
    ground_classes: tuple
    ignored_classes: tuple


def _xyz(points_path: str) -> np.ndarray:
    arr = read_points_file(points_path)
    return np.stack([np.asarray(arr[c], dtype=np.float32) for c in ('x', 'y', 'z')], axis=1)


@functools.lru_cache(maxsize=32)
def load_frame(frame: LabelledFrame) -> tuple:
    """(xyz, truth ground mask, evaluated mask) of a frame; cached per process, so each worker
    reads a frame once however many trials it evaluates."""
    xyz = _xyz(frame.points)
    labels = read_semantickitti_labels(frame.labels, expected_points=len(xyz))
    truth, evaluated = labelled_ground_truth(labels, frame.ground_classes, frame.ignored_classes)
    return xyz, truth, evaluated


def evaluate(values: dict, frames: Sequence[LabelledFrame]) -> list:
    """Per-frame confusion counts {tp, fp, fn, tn} of the defaults with ``values`` applied."""
    params = SegmenterParams().replace(**as_params(values))
    counts = []
    for frame in frames:
        xyz, truth, evaluated = load_frame(frame)
        ground = GroundSegmenter(params).segment(xyz).ground_mask
        m = truth_metrics(ground, truth, evaluated)
        counts.append({k: m[k] for k in ('tp', 'fp', 'fn', 'tn')})
    return counts


# ---------------------------------------------------------------------------------------------
# Studies
# ---------------------------------------------------------------------------------------------

def _import_optuna():
    try:
        import optuna
    except ImportError:
        raise CliError(OPTUNA_MISSING) from None
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    return optuna


@dataclass
class StudyResult:
    best_values: dict  # the searched parameters of the best trial
    best_f1: float
    defaults_f1: float
    complete: int
    pruned: int
    failed: int


def run_study(engine, frames: Sequence[LabelledFrame], trials: int, seed: int,
              first_trials: Optional[Sequence[dict]] = None) -> StudyResult:
    """Maximise pooled ground F1 on ``frames`` with ``trials`` trials (TPE, seeded), evaluating
    ``engine.workers`` trials at a time. ``first_trials`` (default: the defaults) are evaluated
    before the sampler's own."""
    optuna = _import_optuna()
    from optuna.trial import TrialState
    study = optuna.create_study(direction='maximize',
                                sampler=optuna.samplers.TPESampler(seed=seed))
    for values in (first_trials if first_trials is not None else [search_space_defaults()]):
        study.enqueue_trial(values)
    frames = tuple(frames)
    pending: dict = {}
    asked = 0
    while asked < trials or pending:
        while asked < trials and len(pending) < engine.workers:
            trial = study.ask()
            asked += 1
            values = {r.name: r.suggest(trial) for r in SEARCH_SPACE}
            trial.set_user_attr('values', values)
            try:
                SegmenterParams().replace(**as_params(values))
            except ValueError as err:  # a cross-field rule: not a point of the search space
                trial.set_user_attr('pruned_because', str(err))
                study.tell(trial, state=TrialState.PRUNED)
                continue
            pending[engine.submit(evaluate, values, frames)] = trial
        if not pending:
            continue
        done, _ = engine.wait_first(list(pending))
        for fut in done:
            trial = pending.pop(fut)
            try:
                study.tell(trial, pooled_f1(fut.result()))
            except (ValueError, RuntimeError, np.linalg.LinAlgError) as err:
                trial.set_user_attr('failed_because', str(err))
                study.tell(trial, state=TrialState.FAIL)
    states = [t.state for t in study.trials]
    first = study.trials[0]
    defaults_f1 = first.value if first.state == TrialState.COMPLETE else float('nan')
    complete = states.count(TrialState.COMPLETE)
    if complete == 0:
        raise CliError('no trial completed; see the pruned/failed reasons (too few trials?)')
    return StudyResult(dict(study.best_trial.user_attrs['values']), float(study.best_value),
                       defaults_f1,
                       complete, states.count(TrialState.PRUNED), states.count(TrialState.FAIL))


def changed_values(values: dict) -> dict:
    """The searched values that differ from the defaults."""
    defaults = search_space_defaults()
    return {k: v for k, v in values.items() if not np.isclose(v, defaults[k], rtol=0, atol=1e-9)}


@dataclass
class TuneReport:
    frames: list
    scenes: dict  # scene -> frame count
    trials: int
    seed: int
    engine: str
    final: StudyResult
    tuned: dict  # changed SegmenterParams fields of the final best set (as_params)
    train_f1_tuned: float
    train_f1_defaults: float
    cv_f1_tuned: Optional[float]
    cv_f1_defaults: Optional[float]
    folds: list  # per held-out scene: its frames' F1 of the fold's tuned set and of the defaults

    def as_dict(self) -> dict:
        doc = dataclasses.asdict(self)
        doc['frames'] = [dataclasses.asdict(f) for f in self.frames]
        doc['improvement'] = improves(self)
        return doc


def improves(report: TuneReport) -> bool:
    """Whether the tuned set is an improvement to present: it changes a value, and with
    cross-validation its held-out F1 is above the defaults' on the same frames (without, one
    scene, there is nothing to tell it by)."""
    if not report.tuned:
        return False
    if report.cv_f1_tuned is None or report.cv_f1_defaults is None:
        return True
    return report.cv_f1_tuned > report.cv_f1_defaults


def not_an_improvement(report: TuneReport) -> str:
    """The plain sentence for a tuned set that does not beat the defaults on held-out scenes
    ('' when it does, or changes nothing)."""
    if not report.tuned or improves(report):
        return ''
    return (f'not an improvement: the tuned set scores {_fmt(report.cv_f1_tuned)} cross-validated '
            f'F1 against {_fmt(report.cv_f1_defaults)} for the defaults on the held-out scenes; '
            f'keep the defaults')


def tune(frames: Sequence[LabelledFrame], engine, trials: int, seed: int = 0,
         log=None) -> TuneReport:
    """Leave-one-scene-out studies (when there are >= 2 scenes), then one on all frames."""
    if trials < 1:
        raise CliError('--trials must be at least 1')
    log = log or (lambda text: None)
    frames = list(frames)
    scenes: dict = {}
    for f in frames:
        scenes[f.scene] = scenes.get(f.scene, 0) + 1
    default_counts = engine.submit(evaluate, {}, tuple(frames)).result()
    by_frame = dict(zip(frames, default_counts))

    def study_without(fold):
        return run_study(engine, fold.train, trials, seed + 1 + fold.index)

    def held_out_counts(study, test):
        return engine.submit(evaluate, study.best_values, tuple(test)).result()

    cv = leave_one_group_out(frames, lambda f: f.scene, study_without, held_out_counts)
    folds = []
    for k, fold in enumerate(cv.folds):
        base = [by_frame[f] for f in frames if f.scene == fold.held_out]
        folds.append({'held_out': fold.held_out, 'frames': len(base),
                      'train_f1': fold.choice.best_f1,
                      'test_f1_tuned': pooled_f1(fold.test_counts),
                      'test_f1_defaults': pooled_f1(base),
                      'changed': as_params(changed_values(fold.choice.best_values))})
        log(f'fold {k + 1}/{len(scenes)} (held out {fold.held_out}): test F1 tuned '
            f'{pooled_f1(fold.test_counts):.4f}, defaults {pooled_f1(base):.4f}')
    final = run_study(engine, frames, trials, seed)
    log(f'final study on all {len(frames)} frames: F1 {final.best_f1:.4f} (defaults '
        f'{final.defaults_f1:.4f}); {final.pruned} pruned, {final.failed} failed')
    held_defaults = [by_frame[f] for fold in cv.folds for f in frames if f.scene == fold.held_out]
    return TuneReport(frames, scenes, trials, seed, engine.description, final,
                      as_params(changed_values(final.best_values)), final.best_f1,
                      pooled_f1(default_counts),
                      cv.pooled['f1'] if folds else None,
                      pooled_f1(held_defaults) if folds else None, folds)


def _fmt(value: Optional[float]) -> str:
    return 'n/a' if value is None else f'{value:.4f}'


def params_yaml(report: TuneReport, dataset_text: str, write_tuned: bool = False) -> str:
    """The parameter file: node layout, only the changed keys (none when the tuned set is not
    an improvement, unless ``write_tuned``), a header with data and scores."""
    now = datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')
    scenes = ', '.join(f'{s} ({n} frame(s))' for s, n in report.scenes.items())
    cv = (f'leave-one-scene-out CV ground F1 (pooled over held-out scenes): tuned '
          f'{_fmt(report.cv_f1_tuned)}, defaults {_fmt(report.cv_f1_defaults)}'
          if report.folds else 'no cross-validation: one scene only (add frames of another '
          'scene)')
    header = [f'Tuned by gp-ground-seg tune, {now}.',
              f'Frames: {len(report.frames)} in {len(report.scenes)} scene(s): {scenes}.',
              f'Labels: {dataset_text}.',
              f'Search: Optuna TPE, {report.trials} trial(s) per study, seed {report.seed}; '
              f'searched: {", ".join(r.name for r in SEARCH_SPACE)}.',
              f'Pooled ground F1 on these frames (training score): tuned '
              f'{_fmt(report.train_f1_tuned)}, defaults {_fmt(report.train_f1_defaults)}.',
              cv + '.',
              'Only the keys that differ from the defaults are listed.']
    verdict = not_an_improvement(report)
    if verdict and not write_tuned:
        header += [f'NOT AN IMPROVEMENT: the tuned set scores {_fmt(report.cv_f1_tuned)} '
                   f'cross-validated F1 against {_fmt(report.cv_f1_defaults)} for the defaults. '
                   'This file keeps the defaults (it sets no parameter). The tuned values, not '
                   'set: ' + ', '.join(f'{k}: {v}' for k, v in report.tuned.items()) + '.']
        return render_param_overrides({}, header)
    if verdict:
        header += [f'NOT AN IMPROVEMENT ({verdict}); written as asked (--write-tuned).']
    return render_param_overrides(report.tuned, header)


# ---------------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------------

def labelled_frames(paths: Sequence[str], labels_dir: Optional[str], ground: tuple,
                    ignored: tuple, scene_rule: str) -> list:
    """LabelledFrame per path; the label file is ``<labels-dir or the frame's dir>/<stem>.label``
    and the scene is group 1 of ``scene_rule`` on the file stem (the stem if it does not match).
    Raises CliError for missing files and stems that collide."""
    try:
        rule = re.compile(scene_rule)
    except re.error as err:
        raise CliError(f'--scene-of {scene_rule!r}: not a regular expression ({err})') from None
    frames, stems, matched = [], {}, 0
    for p in paths:
        path = Path(p)
        if not path.is_file():
            raise CliError(f'{path}: no such file')
        if path.stem in stems:
            raise CliError(f'{stems[path.stem]} and {path} have the same name; their labels '
                           f'would be the same file')
        stems[path.stem] = path
        label = Path(labels_dir or path.parent) / f'{path.stem}.label'
        if not label.is_file():
            raise CliError(f'{label}: label file not found (expected <labels-dir>/<frame '
                           f'name>.label)')
        match = rule.match(path.stem)
        matched += bool(match)
        scene = match.group(1) if match and match.groups() else path.stem
        frames.append(LabelledFrame(str(path.resolve()), str(label.resolve()), scene, ground,
                                    ignored))
    if frames and not matched and scene_rule != DEFAULT_SCENE_RULE:  # surely not meant
        raise CliError(f'--scene-of {scene_rule!r} matches none of the frame names (e.g. '
                       f'{next(iter(stems))!r}); group 1 of a match names the scene')
    return frames


def add_parser(sub) -> None:
    """Register ``gp-ground-seg tune``."""
    p = sub.add_parser('tune', help='search parameters on labelled scans, write params.yaml',
                       description='Optuna search of the segmenter parameters listed in '
                       'docs/parameters.md ("What gp-ground-seg tune searches") for the best '
                       'pooled '
                       'ground F1 on labelled scans; reports leave-one-scene-out cross-validated '
                       'F1 of the tuned set vs the defaults and writes a node parameter file '
                       'with the changed keys.')
    p.add_argument('frames', nargs='+', metavar='FRAME', help='.bin or .pcd scans')
    p.add_argument('--labels-dir', metavar='D', help='directory of <frame name>.label files '
                   '(default: beside each frame)')
    add_label_class_arguments(p)
    p.add_argument('--trials', type=int, default=40, metavar='N', help='trials per study '
                   '(one study per held-out scene plus the final one; default 40)')
    p.add_argument('--seed', type=int, default=0, help='TPE sampler seed (default 0)')
    p.add_argument('--scene-of', default=DEFAULT_SCENE_RULE, metavar='REGEX',
                   help='group 1 of this regex on the file stem names the scene (default: the '
                   'stem without its trailing frame number)')
    add_engine_arguments(p)
    p.add_argument('--json', action='store_true', help='print the report as JSON')
    p.add_argument('--out', required=True, metavar='params.yaml', help='parameter file to write')
    p.add_argument('--force', action='store_true', help='overwrite --out if it exists')
    p.add_argument('--write-tuned', action='store_true',
                   help='write the tuned values even when their cross-validated F1 does not beat '
                   'the defaults\' (otherwise the file then keeps the defaults and lists them as '
                   'comments)')
    p.set_defaults(func=cmd_tune)


def cmd_tune(args) -> int:
    ground, ignored = label_classes(args)
    out = Path(args.out)
    if out.is_dir():
        raise CliError(f'{out} is a directory; give a file name for the parameters')
    if (out.exists() or out.is_symlink()) and not args.force:
        raise CliError(f'{out} exists; pass --force to overwrite it')
    frames = labelled_frames(args.frames, args.labels_dir, ground, ignored, args.scene_of)
    notes = []
    for f in frames:
        truth, evaluated = labelled_ground_truth(read_semantickitti_labels(f.labels), ground,
                                                 ignored)
        notes.append(no_ground_note(f.points, int(np.count_nonzero(truth & evaluated)), ground))
    if all(notes):  # nothing to tune for; one frame without ground is only a note
        raise CliError(f'no frame has a labelled point in the ground classes '
                       f'{",".join(map(str, ground))}: labels of another data set? '
                       '(--dataset rellis3d, --ground-classes)')
    for note in filter(None, notes):
        print(f'gp-ground-seg tune: note: {note}', file=sys.stderr)
    _import_optuna()  # fail before starting a cluster
    with open_engine(args.jobs, args.scheduler) as engine:
        engine.check_shared([f.points for f in frames] + [f.labels for f in frames])
        report = tune(frames, engine, args.trials, args.seed,
                      log=lambda text: print(f'gp-ground-seg tune: {text}', file=sys.stderr))
    dataset = (f'{args.dataset}, protocol {args.protocol}; ground classes '
               f'{",".join(map(str, ground))}; ignored '
               f'{",".join(map(str, ignored))}')
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(params_yaml(report, dataset, args.write_tuned))
    written = report.tuned if improves(report) or args.write_tuned else {}
    verdict = not_an_improvement(report)
    if verdict:
        print(f'gp-ground-seg tune: warning: {verdict}', file=sys.stderr)
    if args.json:
        print(json.dumps(dict(report.as_dict(), out=str(out), labels=dataset, written=written),
                         indent=2))
        return 0
    _print_report(report, args.trials)
    if verdict:
        print(f'  {verdict}')
    what = (f'{len(written)} changed key(s)' if written else 'the defaults: no key set'
            + ('; the tuned values are in its comments' if verdict else ''))
    print(f'wrote {out} ({what})')
    return 0


def _print_report(report: TuneReport, trials: int) -> None:
    print(f'tuned on {len(report.frames)} frame(s), {len(report.scenes)} scene(s); {trials} '
          f'trials per study on {report.engine}')
    print(f'  training F1 (all frames): tuned {_fmt(report.train_f1_tuned)}, defaults '
          f'{_fmt(report.train_f1_defaults)}')
    print(f'  leave-one-scene-out CV F1: tuned {_fmt(report.cv_f1_tuned)}, defaults '
          f'{_fmt(report.cv_f1_defaults)}')
    print(f'  {"changed" if improves(report) else "tuned values"}: '
          f'{report.tuned or "nothing (the defaults won)"}')
