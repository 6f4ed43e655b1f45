# SPDX-License-Identifier: Apache-2.0
"""gp-ground-seg tune: Optuna search on the real labelled scans, with a CI-sized budget.

Checks: the search space is a documented subset with ranges inside (and narrower than) the
validity ranges, defaults on its grid, and its
table in docs/parameters.md up to date; a tiny study on two real
frames of two scenes (on a 2-process Dask LocalCluster) reports leave-one-scene-out CV F1 of the
tuned set and the defaults, never scores the tuned set below the defaults on its training frames,
and writes a parameter file with only changed keys that load_params_file, `replay --params` and
the node (`--params-file`) accept; rule-breaking trials are pruned; RELLIS-3D's ontology is used
for its scan; bad input fails in one line.
"""

import json

import pytest

pytest.importorskip('optuna')

from conftest import DATA, REPO  # noqa: E402
from gp_ground_segmentation.tools import tune  # noqa: E402

LABELED = DATA / 'labeled'
SEQ00 = LABELED / 'semantickitti_seq00_000000.bin'
SEQ04, SEQ06 = (LABELED / f'semantickitti_seq{n}_000000.bin' for n in ('04', '06'))
SPVNAS = DATA / 'kitti_sequnknown_spvnas_000000.bin'
RELLIS = LABELED / 'rellis3d_examplebundle_000001.bin'

needs_data = pytest.mark.skipif(not SEQ00.is_file(), reason=f'real data not found: {DATA}')


def test_search_space_is_a_narrower_documented_subset():
    from gp_ground_segmentation.core.params import SegmenterParams, describe_params
    specs = {row['name']: row for row in describe_params()}
    defaults = SegmenterParams()
    names = [r.name for r in tune.SEARCH_SPACE]
    assert len(set(names)) == len(names)
    searched_defaults = tune.search_space_defaults()
    for r in tune.SEARCH_SPACE:
        spec = specs[r.name]
        assert type(r.low) is type(spec['default']) and r.why
        if r.switch:  # the low end stands for the rule off: below the parameter's range
            assert isinstance(getattr(defaults, r.switch), bool)
            assert r.low < spec['min'] <= r.low + r.step
            assert tune.as_params({r.name: r.low}) == {r.switch: False}
        else:
            assert spec['min'] <= r.low
        assert r.low < r.high <= spec['max']
        assert (r.low, r.high) != (spec['min'], spec['max'])
        default = searched_defaults[r.name]
        steps = (default - r.low) / r.step
        assert r.low <= default <= r.high
        assert abs(steps - round(steps)) < 1e-9, r.name  # the defaults are a grid point
    assert SegmenterParams().replace(**tune.as_params(searched_defaults)) == defaults


def test_parameters_page_has_the_generated_search_space_table():
    page = (REPO / 'docs' / 'parameters.md').read_text()
    assert tune.render_search_space_table() in page, (
        'docs/parameters.md search-space table is stale: paste render_search_space_table() output')


@needs_data
def test_rellis_ontology_and_scene_rule():
    from gp_ground_segmentation.tools.evaluation import DEFAULT_PROTOCOL, ONTOLOGIES
    ground, ignored = DEFAULT_PROTOCOL.classes(ONTOLOGIES['rellis3d'])
    (frame,) = tune.labelled_frames([str(RELLIS)], None, ground, ignored, tune.DEFAULT_SCENE_RULE)
    assert frame.scene == 'rellis3d_examplebundle'
    (counts,) = tune.evaluate({}, [frame])
    # data README: 39,856 ground among 61,781 labelled (non-void) points
    assert counts['tp'] + counts['fn'] == 39856
    assert sum(counts.values()) == 61781
    assert tune.pooled_f1([counts]) > 0.5
    frames = tune.labelled_frames([str(SEQ00), str(LABELED / 'semantickitti_seq00_000001.bin')],
                                  str(LABELED),
                                  *DEFAULT_PROTOCOL.classes(ONTOLOGIES['semantickitti']),
                                  tune.DEFAULT_SCENE_RULE)
    assert {f.scene for f in frames} == {'semantickitti_seq00'}


@needs_data
def test_rule_breaking_trials_are_pruned_not_crashed():
    from gp_ground_segmentation.tools.engine import InProcessEngine
    from gp_ground_segmentation.tools.evaluation import DEFAULT_PROTOCOL, SEMANTIC_KITTI
    frames = tune.labelled_frames([str(SEQ00)], None, *DEFAULT_PROTOCOL.classes(SEMANTIC_KITTI),
                                  tune.DEFAULT_SCENE_RULE)
    bad = dict(tune.search_space_defaults(), sigma_n_min_m=0.05, sigma_n_init_m=0.02)
    study = tune.run_study(InProcessEngine(), frames, 3, seed=0,
                           first_trials=[bad, tune.search_space_defaults()])
    assert study.pruned >= 1 and study.complete >= 1
    assert study.best_values['sigma_n_init_m'] >= study.best_values['sigma_n_min_m']


@pytest.fixture(scope='module')
def tuned(tmp_path_factory):
    """8 trials per study on 2 real frames of 2 scenes, on a 2-worker LocalCluster."""
    pytest.importorskip('distributed')
    if not SPVNAS.is_file():
        pytest.skip(f'real data not found: {DATA}')
    import contextlib
    import io

    from gp_ground_segmentation.tools.cli import main
    out = tmp_path_factory.mktemp('tune') / 'tuned.yaml'
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        # --write-tuned: the tuned keys are written even though they do not beat the defaults
        # on held-out scenes here (see test_a_tuned_set_below_the_defaults...)
        rc = main(['tune', str(SEQ00), str(SPVNAS), '--trials', '8', '--jobs', '2', '--json',
                   '--write-tuned', '--out', str(out)])
    assert rc == 0
    return out, json.loads(buf.getvalue())


@needs_data
def test_tune_reports_cross_validated_f1_and_writes_changed_keys(tuned):
    from gp_ground_segmentation.ros.config import load_params_file
    out, doc = tuned
    assert doc['scenes'] == {'semantickitti_seq00': 1, 'kitti_sequnknown_spvnas': 1}
    assert len(doc['folds']) == 2 and doc['engine'].startswith('Dask LocalCluster')
    for key in ('cv_f1_tuned', 'cv_f1_defaults', 'train_f1_tuned', 'train_f1_defaults'):
        assert 0.8 < doc[key] < 1.0, key  # the defaults reach ~0.96 on these frames
    # the defaults are the first trial of every study: the tuned set is never worse on the
    # frames it was tuned on (held-out scenes may go either way)
    assert doc['train_f1_tuned'] >= doc['train_f1_defaults']
    assert doc['train_f1_defaults'] == pytest.approx(doc['final']['defaults_f1'])
    for fold in doc['folds']:
        assert 0.8 < fold['test_f1_tuned'] < 1.0
    assert doc['final']['complete'] + doc['final']['pruned'] + doc['final']['failed'] == 8
    text = out.read_text()
    assert 'leave-one-scene-out CV ground F1' in text
    assert f"tuned {doc['cv_f1_tuned']:.4f}, defaults {doc['cv_f1_defaults']:.4f}" in text
    assert 'ground classes 40,44,48,49,60,72' in text and '8 trial(s) per study' in text
    seg, node = load_params_file(out)
    # the shipped file's '/**' section: the node in a namespace reads it too
    assert "'/**':" in text.splitlines()
    assert load_params_file(out, namespace='/seg')[0] == seg
    from gp_ground_segmentation.core.params import SegmenterParams
    defaults = SegmenterParams()
    for name, value in doc['tuned'].items():  # SegmenterParams fields, as written
        assert getattr(seg, name) == value and value != getattr(defaults, name)
    keys = [ln.split(':')[0].strip() for ln in text.splitlines() if ln.startswith('    ')]
    assert sorted(keys) == sorted(doc['tuned'])


@needs_data
def test_tuned_file_loads_in_replay_and_the_node(tuned, tmp_path, capsys):
    import rclpy

    from gp_ground_segmentation.ros.node import GroundSegmentationNode
    from gp_ground_segmentation.tools.cli import main
    out, doc = tuned
    assert main(['replay', str(SEQ00), str(tmp_path / 'bag'), '--params', str(out)]) == 0
    assert 'frames        1 processed' in capsys.readouterr().out
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = GroundSegmentationNode(context=ctx,
                                      cli_args=['--ros-args', '--params-file', str(out)])
        try:
            for name, value in doc['tuned'].items():
                assert node.get_parameter(name).value == value
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


@needs_data
def test_one_scene_says_there_is_no_cross_validation(tmp_path, capsys):
    from gp_ground_segmentation.tools.cli import main
    out = tmp_path / 'p.yaml'
    assert main(['tune', str(SEQ00), '--trials', '2', '--out', str(out)]) == 0
    assert 'CV F1: tuned n/a' in capsys.readouterr().out
    assert 'no cross-validation: one scene only' in out.read_text()


@needs_data
@pytest.mark.parametrize('extra, words', [
    (['--labels-dir', '/nonexistent'], 'label file not found'),
    (['--ground-classes', '40,x'], 'comma-separated integers'),
    (['--trials', '0'], '--trials must be at least 1'),
    (['--scene-of', '(('], 'not a regular expression'),
    (['--scene-of', r'xyz(\d+)'], 'matches none of the frame names'),
    (['--ground-classes', '999'], 'no frame has a labelled point in the ground classes 999'),
])
def test_bad_input_one_line(extra, words, tmp_path, capsys):
    from gp_ground_segmentation.tools.cli import main
    assert main(['tune', str(SEQ00), '--out', str(tmp_path / 'p.yaml')] + extra) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err
    assert not (tmp_path / 'p.yaml').exists()


@needs_data
def test_an_existing_out_file_needs_force(tmp_path, capsys):
    from gp_ground_segmentation.tools.cli import main
    out = tmp_path / 'p.yaml'
    out.write_text('# an earlier result\n')
    assert main(['tune', str(SEQ00), '--trials', '1', '--out', str(out)]) == 2
    assert 'pass --force' in capsys.readouterr().err
    assert out.read_text() == '# an earlier result\n'
    assert main(['tune', str(SEQ00), '--trials', '1', '--out', str(out), '--force']) == 0
    assert 'ros__parameters' in out.read_text()


@needs_data
def test_without_optuna_one_line(monkeypatch, tmp_path, capsys):
    import sys

    from gp_ground_segmentation.tools.cli import main
    monkeypatch.setitem(sys.modules, 'optuna', None)
    assert main(['tune', str(SEQ00), '--out', str(tmp_path / 'p.yaml')]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install 'gp_ground_segmentation[tune]'" in err[0]


@needs_data
def test_a_tuned_set_below_the_defaults_is_not_presented_as_an_improvement(tmp_path, capsys):
    import re

    from gp_ground_segmentation.core.params import SegmenterParams
    from gp_ground_segmentation.ros.config import load_params_file
    from gp_ground_segmentation.tools.cli import main
    out = tmp_path / 'p.yaml'
    # a study that ends below the defaults: sequences 04 and 06, 3 trials
    assert main(['tune', str(SEQ04), str(SEQ06), '--trials', '3', '--out', str(out)]) == 0
    captured = capsys.readouterr()
    tuned, defaults = (float(v) for v in re.search(
        r'CV F1: tuned ([\d.]+), defaults ([\d.]+)', captured.out).groups())
    # measured 2026-12-01: 0.9832 vs 0.9836 (the case was 0.9744 vs 0.9747 on 00 and
    # the spvnas scan under the earlier defaults)
    assert tuned <= defaults, 'this study no longer ends below the defaults: pick another'
    assert f'not an improvement: the tuned set scores {tuned:.4f} cross-validated F1 against ' \
           f'{defaults:.4f} for the defaults' in captured.out
    assert 'gp-ground-seg tune: warning: not an improvement' in captured.err
    assert '  changed:' not in captured.out and '  tuned values: {' in captured.out
    assert 'the defaults: no key set; the tuned values are in its comments' in captured.out
    text = out.read_text()
    assert 'NOT AN IMPROVEMENT' in text and 'ros__parameters: {}' in text
    comments = ' '.join(line[2:] for line in text.splitlines() if line.startswith('# '))
    assert re.search(r'The tuned values, not set: \w+: ', comments)
    assert load_params_file(out)[0] == SegmenterParams()
    # --write-tuned writes them, still saying what they are
    assert main(['tune', str(SEQ04), str(SEQ06), '--trials', '3', '--out', str(out), '--force',
                 '--write-tuned']) == 0
    assert 'NOT AN IMPROVEMENT' in out.read_text()
    assert load_params_file(out)[0] != SegmenterParams()


def test_improves_needs_a_change_and_a_better_held_out_score():
    report = tune.TuneReport(frames=[], scenes={}, trials=1, seed=0, engine='', final=None,
                             tuned={'num_bins': 20}, train_f1_tuned=0.98,
                             train_f1_defaults=0.97, cv_f1_tuned=0.9744, cv_f1_defaults=0.9747,
                             folds=[{}])
    assert not tune.improves(report) and tune.not_an_improvement(report)
    for cv_tuned, expected in ((0.9747, False), (0.9748, True)):
        report.cv_f1_tuned = cv_tuned
        assert tune.improves(report) is expected
        assert bool(tune.not_an_improvement(report)) is not expected
    report.cv_f1_tuned = report.cv_f1_defaults = None  # one scene: nothing to tell it by
    assert tune.improves(report)
    report.tuned = {}  # nothing changed: nothing to present
    assert not tune.improves(report) and not tune.not_an_improvement(report)
