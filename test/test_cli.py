# SPDX-License-Identifier: Apache-2.0
"""gp-ground-seg eval / plot / make-sample, run in-process through cli.main().

Accuracy numbers are not asserted here (test_segmenter does that); these tests check that the
tool reads the real labelled frame, reports consistent metrics and timings, writes a real PNG,
rebuilds the shipped sample bag bit for bit, and fails with one line and status 2.
"""

import hashlib
import json
import re

import numpy as np
import pytest

from conftest import DATA, REPO
from gp_ground_segmentation.tools.cli import main

SCAN = DATA / 'kitti_sequnknown_spvnas_000000.bin'
LABELS = DATA / 'kitti_sequnknown_spvnas_000000.label'
BAG = DATA / 'kitti00_velodyne_points'
SAMPLE = REPO / 'data' / 'kitti00_sample'

needs_data = pytest.mark.skipif(not SCAN.is_file(), reason=f'real data not found: {DATA} '
                                '(../shared/data beside the repo)')


def _label_counts():
    classes = np.fromfile(LABELS, dtype='<u4') & 0xFFFF
    ground = np.isin(classes, (40, 44, 48, 49, 60, 72))
    evaluated = ~np.isin(classes, (0, 1))
    return int(np.count_nonzero(ground & evaluated)), int(np.count_nonzero(evaluated))


@needs_data
def test_eval_json_with_labels(capsys):
    assert main(['eval', str(SCAN), '--labels', str(LABELS), '--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    (frame,) = doc['frames']
    m = frame['metrics']
    n_truth_ground, n_evaluated = _label_counts()
    assert frame['points'] == SCAN.stat().st_size // 16
    assert m['evaluated_points'] == n_evaluated
    assert m['tp'] + m['fn'] == n_truth_ground
    assert m['tp'] + m['fp'] + m['fn'] + m['tn'] == n_evaluated
    assert m['precision'] == pytest.approx(m['tp'] / (m['tp'] + m['fp']))
    assert m['recall'] == pytest.approx(m['tp'] / (m['tp'] + m['fn']))
    assert m['iou'] == pytest.approx(m['tp'] / (m['tp'] + m['fp'] + m['fn']))
    assert doc['protocol'] == 'vegetation-nonground' and doc['cold'] is False
    assert doc['pooled']['tp'] == m['tp'] and doc['pooled']['f1'] == pytest.approx(m['f1'])
    for stage in ('decode', 'encode', 'total'):
        assert frame['timings_ms'][stage] > 0
    assert set(frame['hyperparameters']) == {'sigma_f', 'gain', 'sigma_n'}


@needs_data
def test_eval_text_with_labels_and_vegetation_flag(capsys):
    assert main(['eval', str(SCAN), '--labels', str(LABELS)]) == 0
    text = capsys.readouterr().out
    assert re.search(r'ground precision \d\.\d{4}\s+recall \d\.\d{4}\s+F1 \d\.\d{4}', text)
    assert 'ground classes 40,44,48,49,60,72)' in text and 'ms: total' in text
    assert main(['eval', str(SCAN), '--labels', str(LABELS), '--vegetation-ground',
                 '--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    classes = np.fromfile(LABELS, dtype='<u4') & 0xFFFF
    m = doc['frames'][0]['metrics']
    assert m['tp'] + m['fn'] == _label_counts()[0] + int(np.count_nonzero(classes == 70))


@needs_data
def test_eval_scores_rellis_labels_with_their_classes_and_flags_another_ontology(capsys):
    scan = DATA / 'labeled' / 'rellis3d_examplebundle_000001.bin'
    labels = scan.with_suffix('.label')
    # read as SemanticKITTI classes, RELLIS-3D labels hold no ground: a note, not a silent 0
    assert main(['eval', str(scan), '--labels', str(labels)]) == 0
    captured = capsys.readouterr()
    assert 'no labelled point is in the ground classes' in captured.err
    assert '--dataset rellis3d' in captured.err
    assert main(['eval', str(scan), '--labels', str(labels), '--dataset', 'rellis3d',
                 '--json']) == 0
    captured = capsys.readouterr()
    doc = json.loads(captured.out)
    assert doc['ground_classes'] == [1, 3, 10, 23, 31, 33] and 'note' not in captured.err
    assert doc['frames'][0]['metrics']['f1'] > 0.9  # 0.951 with the defaults (docs/results.md)
    # Patchwork++'s protocol leaves RELLIS-3D's 19 bush out of the score
    assert main(['eval', str(scan), '--labels', str(labels), '--dataset', 'rellis3d',
                 '--protocol', 'patchworkpp', '--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    classes = np.fromfile(labels, dtype='<u4') & 0xFFFF
    assert doc['ignored_classes'] == [0, 19]
    scored = int(np.count_nonzero(~np.isin(classes, (0, 19))))
    assert doc['frames'][0]['metrics']['evaluated_points'] == scored


SEQ00 = [DATA / 'labeled' / f'semantickitti_seq00_00000{i}' for i in range(3)]
needs_seq00 = pytest.mark.skipif(not all(s.with_suffix('.label').is_file() for s in SEQ00),
                                 reason=f'KITTI 00 labelled frames not found in {DATA}')


def _eval_json(capsys, *extra):
    argv = (['eval'] + [str(s.with_suffix('.bin')) for s in SEQ00] + ['--labels']
            + [str(s.with_suffix('.label')) for s in SEQ00] + ['--json', *extra])
    assert main(argv) == 0
    return json.loads(capsys.readouterr().out)


@needs_seq00
def test_eval_pools_several_frames_by_summing_their_counts(capsys):
    doc = _eval_json(capsys, '--protocol', 'patchworkpp', '--cold')
    assert doc['protocol'] == 'patchworkpp' and doc['ignored_classes'] == [0, 1, 70]
    per_frame = [f['metrics'] for f in doc['frames']]
    pooled = doc['pooled']
    for key in ('tp', 'fp', 'fn', 'tn', 'evaluated_points'):
        assert pooled[key] == sum(m[key] for m in per_frame)
    tp, fp, fn = pooled['tp'], pooled['fp'], pooled['fn']
    assert pooled['f1'] == pytest.approx(2 * tp / (2 * tp + fp + fn))  # not a mean of F1
    assert pooled['iou'] == pytest.approx(tp / (tp + fp + fn))
    # vegetation (70) is out of the score: the evaluated points are those of no class 0/1/70
    for f, stem in zip(doc['frames'], SEQ00):
        classes = np.fromfile(stem.with_suffix('.label'), dtype='<u4') & 0xFFFF
        assert f['metrics']['evaluated_points'] == int((~np.isin(classes, (0, 1, 70))).sum())
    # --cold: each frame as if it were alone (a fresh segmenter), so frame 2 scores the same
    alone = main(['eval', str(SEQ00[2].with_suffix('.bin')), '--labels',
                  str(SEQ00[2].with_suffix('.label')), '--protocol', 'patchworkpp', '--json'])
    assert alone == 0
    assert json.loads(capsys.readouterr().out)['frames'][0]['metrics'] == per_frame[2]


@needs_seq00
def test_eval_text_prints_a_pooled_line_under_the_protocol(capsys):
    argv = (['eval'] + [str(s.with_suffix('.bin')) for s in SEQ00] + ['--labels']
            + [str(s.with_suffix('.label')) for s in SEQ00])
    assert main(argv) == 0
    lines = capsys.readouterr().out.splitlines()
    assert sum('ground precision' in line for line in lines) == 4
    (pooled,) = [line for line in lines if 'pooled' in line]
    assert pooled.startswith('pooled over 3 frames') and 'protocol vegetation-nonground' in pooled
    doc = _eval_json(capsys)  # the same frames, same segmenter history: the same numbers
    assert f"F1 {doc['pooled']['f1']:.4f}" in pooled and f"TP {doc['pooled']['tp']} " in pooled
    # a protocol is one of the listed names
    with pytest.raises(SystemExit) as exit_status:
        main(argv + ['--protocol', 'nonsense'])
    assert exit_status.value.code == 2 and 'patchworkpp' in capsys.readouterr().err


@needs_data
def test_eval_without_labels_several_inputs_and_repeat(capsys):
    pcd = DATA / 'sensors' / 'velodyne_vlp32.pcd'
    assert main(['eval', str(SCAN), str(pcd), f'{BAG}:2', '--repeat', '2', '--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [f['input'] for f in doc['frames']][:2] == [str(SCAN), str(pcd)]
    assert doc['frames'][2]['input'].startswith(f'{BAG}:2')
    assert all('metrics' not in f and f['repeat'] == 2 for f in doc['frames'])
    assert all(0 < f['ground_share'] < 1 for f in doc['frames']) and doc['pooled'] is None
    assert main(['eval', str(pcd)]) == 0
    out = capsys.readouterr().out
    assert 'ground share' in out and 'precision' not in out


@needs_data
@pytest.mark.parametrize('argv, expected', [
    (['eval', str(SCAN), '--labels', str(LABELS), str(LABELS)], 'label file(s) given for 1'),
    (['eval', '/nonexistent.bin'], 'no such file'),
    (['eval', str(SCAN), '--labels', str(DATA / 'kitti_unlabeled_patchworkpp_000000.bin')],
     'labels but the scan has'),
    (['eval', str(SCAN), '--params', '/nonexistent.yaml'], 'parameter file not found'),
    (['plot', str(SCAN), '--segment', '100000', '--out', '/tmp/never.png'], 'outside 0..'),
])
def test_errors_are_one_line_exit_2(argv, expected, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and expected in err[0] and 'Traceback' not in err[0]


@needs_data
def test_eval_refuses_too_few_label_files_before_segmenting(capsys, monkeypatch):
    # two point files, one --labels file: refused before the first frame is segmented
    from gp_ground_segmentation.core import segmenter as segmenter_module

    def never(*_args, **_kwargs):
        raise AssertionError('segment() ran before the label count was checked')
    monkeypatch.setattr(segmenter_module.GroundSegmenter, 'segment', never)
    assert main(['eval', str(SCAN), str(SCAN), '--labels', str(LABELS)]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert err[-1].endswith('1 label file(s) given for 2 frame(s); give one --labels file per '
                            'frame'), err
    assert 'ground share' not in captured.out


def test_usage_error_exit_2(capsys):
    with pytest.raises(SystemExit) as exc:
        main(['frobnicate'])
    assert exc.value.code == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def _png_size(path):
    head = path.read_bytes()[:24]
    assert head[:8] == b'\x89PNG\r\n\x1a\n'
    return int.from_bytes(head[16:20], 'big'), int.from_bytes(head[20:24], 'big')


@needs_data
def test_plot_labelled_frame_writes_png(tmp_path, capsys):
    pytest.importorskip('matplotlib')
    out = tmp_path / 'figs' / 'frame.png'  # directory created by the tool
    assert main(['plot', str(SCAN), '--labels', str(LABELS), '--segment', '7',
                 '--out', str(out)]) == 0
    assert 'segment 7' in capsys.readouterr().out
    width, height = _png_size(out)
    assert width > 1000 and height > 500
    assert out.stat().st_size > 50_000  # a real picture, not an empty canvas


def test_plot_shipped_sample_bag_frame(tmp_path):
    pytest.importorskip('matplotlib')
    out = tmp_path / 'f.png'
    assert main(['plot', f'{SAMPLE}:1', '--out', str(out)]) == 0
    assert _png_size(out)[0] > 1000


def test_plot_side_view_data_comes_from_details():
    """The side view shows the segmenter's own candidates, lines and GP curve."""
    from gp_ground_segmentation.tools.bag import read_frame
    from gp_ground_segmentation.ros.cloud import cloud_xyz, read_cloud
    from gp_ground_segmentation.tools.plot import default_segment, segment_view
    from gp_ground_segmentation.core.segmenter import GroundSegmenter
    msg, _ = read_frame(f'{SAMPLE}:0')
    xyz = cloud_xyz(read_cloud(msg))
    seg = GroundSegmenter()
    res = seg.segment(xyz, details=True)
    k = default_segment(seg.params.num_segments)
    view = segment_view(xyz, res, k, seg.params.num_segments)
    assert view['r'].size > 100 and view['ground'].any()
    det = res.details
    n_cand = int(np.count_nonzero(np.isfinite(det.grid.candidate_r[k])))
    assert n_cand > 5
    assert int(np.count_nonzero(view['cand_train'] | view['cand_other'] | view['cand_outlier'])) \
        == n_cand
    assert view['lines'] and view['gp_r'].size > 5 and np.all(view['gp_std'] >= 0)


def test_plot_without_matplotlib_is_one_line(monkeypatch, tmp_path, capsys):
    import sys
    monkeypatch.setitem(sys.modules, 'matplotlib', None)  # import fails like a missing extra
    assert main(['plot', f'{SAMPLE}:0', '--out', str(tmp_path / 'x.png')]) == 2
    err = capsys.readouterr().err
    assert 'matplotlib is not installed' in err and len(err.strip().splitlines()) == 1


def _readme_sha256():
    text = (REPO / 'data' / 'README.md').read_text()
    match = re.search(r'kitti00_sample\.mcap[^\n]*?([0-9a-f]{64})', text)
    assert match, 'data/README.md must state the sha256 of kitti00_sample.mcap'
    return match.group(1)


def test_shipped_sample_matches_readme_checksum():
    mcap = SAMPLE / 'kitti00_sample.mcap'
    assert mcap.stat().st_size + (SAMPLE / 'metadata.yaml').stat().st_size <= 6 * 1024 * 1024
    assert hashlib.sha256(mcap.read_bytes()).hexdigest() == _readme_sha256()


def _messages(bag):
    from rosbags.highlevel import AnyReader
    with AnyReader([bag]) as reader:
        return [(c.topic, c.msgtype, t, bytes(raw)) for c, t, raw in reader.messages()]


@pytest.mark.skipif(not BAG.is_dir(), reason='real data not found')
def test_make_sample_rebuilds_the_shipped_bag(tmp_path, capsys):
    """The command in data/README.md re-creates the shipped sample: same messages, raw CDR
    bytes unchanged from the source bag (the file hash also matches with rosbags 0.11)."""
    out = tmp_path / 'kitti00_sample'
    assert main(['make-sample', str(BAG), str(out), '--frames', '3']) == 0
    digest = hashlib.sha256((out / 'kitti00_sample.mcap').read_bytes()).hexdigest()
    assert digest in capsys.readouterr().out
    rebuilt, shipped = _messages(out), _messages(SAMPLE)
    assert len(rebuilt) == 3 and rebuilt == shipped
    assert shipped == _messages(BAG)[:3]
    # zstd chunk compression: the file is smaller than the raw messages it holds
    assert (out / 'kitti00_sample.mcap').stat().st_size < sum(len(m[3]) for m in rebuilt)


@pytest.mark.parametrize('argv, words', [
    (['hz', '/x', '--duration', '0'], '--duration: expected a finite number > 0'),
    (['hz', '/x', '--period', 'nan'], '--period: expected a finite number > 0'),
    (['hz', '/x', '--window', '0'], '--window: expected an integer >= 1'),
    (['hz', 'bad topic', '--duration', '1'], "'/bad topic' is not a valid ROS 2 topic name"),
    (['play', str(REPO / 'data' / 'kitti00_sample'), '--topic', '/a//b',
      '--wait-for-subscriber', '0'], 'topic /a//b not in bag'),
    (['replay', str(REPO / 'data' / 'kitti00_sample'), 'OUT', '--output-prefix', '1st/x'],
     "--output-prefix '/1st/x' is not a valid ROS 2 topic name"),
])
def test_bad_topic_names_and_durations_are_one_line(argv, words, tmp_path, capsys):
    # an invalid name raised rclpy's exception with a traceback (play) or was never matched
    # (hz) or written into the bag (replay); 0 s meant 'forever' to hz
    argv = [str(tmp_path / 'out') if a == 'OUT' else a for a in argv]
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's own errors: usage line + error line, status 2
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert words in err[-1] and not any('Traceback' in line for line in err), err
    assert not (tmp_path / 'out').exists()


@needs_data
def test_eval_names_the_files_of_a_directory(tmp_path, capsys):
    # 'DIR:0', 'DIR:1' did not say which file a row (and so which --labels file) was
    for name in ('velodyne_vlp16.pcd', 'velodyne_vlp32.pcd'):
        (tmp_path / name).write_bytes((DATA / 'sensors' / name).read_bytes())
    assert main(['eval', str(tmp_path), '--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [f['input'] for f in doc['frames']] == [str(tmp_path / 'velodyne_vlp16.pcd'),
                                                   str(tmp_path / 'velodyne_vlp32.pcd')]


@needs_data
def test_eval_prints_each_frame_before_a_bad_one_stops_it(tmp_path, capsys):
    bad = tmp_path / 'bad.bin'
    bad.write_bytes(b'\x00' * 10)
    pcd = DATA / 'sensors' / 'velodyne_vlp16.pcd'
    assert main(['eval', str(pcd), str(bad)]) == 2
    captured = capsys.readouterr()
    assert captured.out.startswith(f'{pcd}: 14831 points'), captured.out
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].count(str(bad)) == 1, lines  # named once


def test_params_directory_and_output_inside_the_input_bag_are_one_line(tmp_path, capsys):
    bag = tmp_path / 'in_bag'
    bag.mkdir()
    for name in ('metadata.yaml', 'kitti00_sample.mcap'):
        (bag / name).write_bytes((SAMPLE / name).read_bytes())
    assert main(['replay', str(bag), str(bag / 'out')]) == 2
    assert 'lies inside the input' in capsys.readouterr().err
    assert sorted(p.name for p in bag.iterdir()) == ['kitti00_sample.mcap', 'metadata.yaml']
    assert main(['eval', f'{bag}:0', '--params', str(tmp_path)]) == 2
    assert 'is a directory; give the parameter file' in capsys.readouterr().err


@needs_data
def test_plot_colours_errors_against_rellis_labels_with_their_classes(tmp_path, capsys):
    pytest.importorskip('matplotlib')
    scan = DATA / 'labeled' / 'rellis3d_examplebundle_000001.bin'
    args = ['plot', str(scan), '--labels', str(scan.with_suffix('.label'))]
    assert main(args + ['--out', str(tmp_path / 'a.png')]) == 0
    assert 'no labelled point is in the ground classes' in capsys.readouterr().err
    assert main(args + ['--dataset', 'rellis3d', '--out', str(tmp_path / 'b.png')]) == 0
    assert 'note' not in capsys.readouterr().err and (tmp_path / 'b.png').stat().st_size > 0


def test_bag_topics_follow_ros1_rules_where_only_matched_and_ros2_rules_where_used():
    from gp_ground_segmentation.tools.bag import BagError, normalize_topic
    # reading a (ROS 1) bag only matches names: '/lidar/0/points' is a valid ROS 1 topic
    assert normalize_topic('/lidar/0/points') == '/lidar/0/points'
    assert normalize_topic('ns/points/') == '/ns/points'
    # what rclpy subscribes or publishes to must be a ROS 2 name
    with pytest.raises(BagError, match='not a valid ROS 2 topic name'):
        normalize_topic('/lidar/0/points', strict=True)
    assert normalize_topic('ns/points/', strict=True) == '/ns/points'
