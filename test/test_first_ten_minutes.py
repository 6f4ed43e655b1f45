# SPDX-License-Identifier: Apache-2.0
"""gp-ground-seg's first ten minutes, as a new user meets them (issue 31, item 6, tools side).

``gp-ground-seg`` alone shows the help (status 2: a missing subcommand is a usage error); an
unknown option is reported by the subcommand it was given to; every option has a help text and
every subcommand is in the README; ``plot`` fits the bird's-eye extent to the data (a 10 m room
is not a dot in a +-40 m square) or takes ``--extent``; ``replay`` keeps numba's compilations
out of its timings and says how long the warm-up took. (play: test_play.py; tune below the
defaults: test_tune.py.)
"""

import numpy as np
import pytest
from conftest import REPO

from gp_ground_segmentation.tools.cli import build_parser, main

SAMPLE = REPO / 'data' / 'kitti00_sample'
SUBCOMMANDS = ('eval', 'replay', 'plot', 'make-sample', 'batch', 'tune', 'play', 'hz')


def test_no_subcommand_prints_the_help_and_exits_2(capsys):
    with pytest.raises(SystemExit) as stop:
        main([])
    assert stop.value.code == 2
    captured = capsys.readouterr()
    assert captured.out.startswith('usage: gp-ground-seg') and captured.err == ''
    for name in SUBCOMMANDS:
        assert name in captured.out


@pytest.mark.parametrize('argv', [
    ['replay', '--bogus', 'IN', 'OUT'], ['eval', 'x.bin', '--frobnicate'],
    ['plot', 'x.bin', '--out', 'f.png', '--bogus'], ['batch', 'x', '--out', 'd', '--bogus'],
    ['tune', 'x.bin', '--out', 'p.yaml', '--bogus'], ['play', 'x', '--bogus'],
    ['hz', '/ground', '--bogus'], ['make-sample', 'a', 'b', '--bogus']])
def test_an_unknown_option_is_reported_by_its_subcommand(argv, capsys):
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(f'gp-ground-seg {argv[0]}: error: unrecognized arguments: --'), err


def test_an_unknown_option_before_the_subcommand_is_the_main_commands(capsys):
    with pytest.raises(SystemExit):
        main(['--bogus', 'replay', 'IN', 'OUT'])
    assert capsys.readouterr().err.strip() == ('gp-ground-seg: error: unrecognized arguments: '
                                               '--bogus')


def test_every_option_of_every_subcommand_has_a_help_text():
    parser = build_parser()
    assert sorted(parser.subcommands) == sorted(SUBCOMMANDS)
    missing = [(name, action.option_strings or action.dest)
               for name, sub in parser.subcommands.items() for action in sub._actions
               if not action.help]
    assert missing == []


def test_the_readme_names_every_subcommand():
    readme = (REPO / 'README.md').read_text()
    for name in SUBCOMMANDS:
        assert f'gp-ground-seg {name} ' in readme, name


def _room(tmp_path):
    """A .pcd of a 10 m x 8 m room seen from 0.5 m above its floor: floor and four walls."""
    from gp_ground_segmentation.tools.io import write_pcd
    rng = np.random.default_rng(1)
    floor = np.c_[rng.uniform(-5, 5, 6000), rng.uniform(-4, 4, 6000),
                  rng.normal(-0.5, 0.01, 6000)]
    walls = []
    for x0, y0, x1, y1 in ((-5, -4, 5, -4), (5, -4, 5, 4), (5, 4, -5, 4), (-5, 4, -5, -4)):
        t = rng.uniform(0, 1, 1500)
        walls.append(np.c_[x0 + t * (x1 - x0), y0 + t * (y1 - y0), rng.uniform(-0.5, 2, 1500)])
    xyz = np.vstack([floor] + walls).astype('<f4')
    path = tmp_path / 'room.pcd'
    write_pcd(path, xyz.view([('x', '<f4'), ('y', '<f4'), ('z', '<f4')]).reshape(-1))
    return path


@pytest.mark.parametrize('source, extra, expected', [
    ('room', [], (5.0, 6.0)), ('sample', [], (40.0, 50.0)), ('room', ['--extent', '20'], (20, 20)),
    ('sample', ['--extent', '12.5'], (12.5, 12.5))])
def test_plot_fits_the_birds_eye_extent_to_the_data(source, extra, expected, tmp_path,
                                                    capsys, monkeypatch):
    pytest.importorskip('matplotlib')
    from gp_ground_segmentation.tools import plot
    shown = []  # the half-widths the two bird's-eye panels are drawn with
    real = plot._birds_eye_axes
    monkeypatch.setattr(plot, '_birds_eye_axes',
                        lambda ax, reach: (shown.append(reach), real(ax, reach))[1])
    frame = str(_room(tmp_path)) if source == 'room' else f'{SAMPLE}:0'
    assert main(['plot', frame, '--out', str(tmp_path / 'f.png'), *extra]) == 0
    assert len(shown) == 2 and shown[0] == shown[1]
    low, high = expected
    assert low <= shown[0] <= high, shown
    assert f'extent +-{shown[0]:g} m' in capsys.readouterr().out


def test_plot_extent_must_be_positive(tmp_path, capsys):
    pytest.importorskip('matplotlib')
    assert main(['plot', f'{SAMPLE}:0', '--out', str(tmp_path / 'f.png'), '--extent', '0']) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and '--extent must be a finite number of metres > 0' in err[0]
    assert not (tmp_path / 'f.png').exists()


def test_fitted_extent_rounds_up_past_the_bulk_of_the_points():
    from gp_ground_segmentation.tools.plot import fitted_extent
    xyz = np.zeros((1000, 3))
    xyz[:, 0] = np.linspace(-8, 8, 1000)
    assert fitted_extent(xyz, np.ones(1000, bool)) == 8.5  # 98 % of 8 m, + 5 %, step 0.5 m
    xyz[-5:, 0] = 500.0  # a few far returns do not shrink the rest to a dot
    assert fitted_extent(xyz, np.ones(1000, bool)) == 8.5
    assert fitted_extent(xyz * 0.01, np.ones(1000, bool)) == 1.0  # at least 1 m
    assert fitted_extent(xyz, np.zeros(1000, bool)) == 1.0  # no valid point


def test_replay_waits_for_numbas_compilations_before_the_first_frame(tmp_path, monkeypatch,
                                                                     capsys):
    import gp_ground_segmentation.ros.pipeline as pipeline
    from gp_ground_segmentation.core import compiled
    calls = []
    real_wait, real_process = compiled.wait, pipeline.process_cloud
    monkeypatch.setattr(compiled, 'wait', lambda timeout_s=None: (
        calls.append(('wait', timeout_s)), real_wait(timeout_s))[1])
    monkeypatch.setattr(pipeline, 'process_cloud', lambda *a, **kw: (
        calls.append('frame'), real_process(*a, **kw))[1])
    assert main(['replay', str(SAMPLE), str(tmp_path / 'out'), '--max-frames', '2']) == 0
    # every queued compilation is waited for (with a generous bound) before the first frame
    # (the segmenter's own warm-up waits a moment, for a cache load, before that)
    first = calls.index('frame')
    assert calls[first:] == ['frame', 'frame']
    assert calls[first - 1][0] == 'wait' and calls[first - 1][1] >= 60, calls
    out = capsys.readouterr().out
    assert 'warm-up ' in out and 's before the first frame' in out and 'not in the timings' in out
