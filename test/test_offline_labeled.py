# SPDX-License-Identifier: Apache-2.0
"""``replay --labeled`` and ``batch --labeled`` write the node's labelled cloud; the Python API
(labels.labeled_points) returns the same rows.

On the shipped sample (no ../shared needed): the labeled topic holds one message per frame at the
input's bag time and header, its rows are the valid points in input order with every input byte
unchanged, and their ``ground`` flags split them exactly into the ground and obstacle clouds of
the same bag. For a KITTI .bin the rows equal ``labeled_points(read_points_file(bin),
GroundSegmenter().segment(xyz))`` byte for byte. Without --labeled nothing changes.
"""

import numpy as np
import pytest
from conftest import REPO
from test_bag import as_items, read_bag, rows

from gp_ground_segmentation import GroundSegmenter
from gp_ground_segmentation.labels import GROUND_FIELD, HEIGHT_FIELD, labeled_points
from gp_ground_segmentation.ros.cloud import cloud_xyz, read_cloud
from gp_ground_segmentation.tools.cli import main
from gp_ground_segmentation.tools.io import read_points_file

SAMPLE = REPO / 'data' / 'kitti00_sample'
TOPIC = '/velodyne_points'


def _input_bytes(labeled_msg, point_step):
    """The input bytes of each labelled row (the row without its two label fields)."""
    return np.ascontiguousarray(rows(labeled_msg)[:, :point_step])


def test_replay_labeled_rows_split_like_the_ground_and_obstacle_clouds(tmp_path, capsys):
    out = tmp_path / 'out'
    assert main(['replay', str(SAMPLE), str(out), '--labeled', '--max-frames', '2']) == 0
    assert 'labeled' in capsys.readouterr().out  # its time is a stage of the summary
    topics = read_bag(out)
    assert f'{TOPIC}/labeled' in topics
    inputs = read_bag(SAMPLE, TOPIC)[TOPIC][:2]
    labeled = topics[f'{TOPIC}/labeled']
    assert len(labeled) == len(inputs) == 2
    for (t_in, m_in), (t_l, m_l), (_, m_g), (_, m_o) in zip(
            inputs, labeled, topics[f'{TOPIC}/ground'], topics[f'{TOPIC}/obstacles']):
        assert t_l == t_in and m_l.header == m_in.header
        assert [f.name for f in m_l.fields] == [f.name for f in m_in.fields] + [
            GROUND_FIELD, HEIGHT_FIELD]
        points = read_cloud(m_l)
        ground = points[GROUND_FIELD] == 1
        assert set(np.unique(points[GROUND_FIELD])) == {0, 1}
        assert np.isfinite(points[HEIGHT_FIELD]).all()
        own = as_items(_input_bytes(m_l, m_in.point_step))
        # KITTI has no invalid point: every input row, in input order
        assert np.array_equal(own, as_items(rows(m_in)))
        assert np.array_equal(own[ground], as_items(rows(m_g)))
        assert np.array_equal(own[~ground], as_items(rows(m_o)))


def test_replay_labeled_of_a_bin_is_what_the_python_api_returns(tmp_path):
    (_, first), = read_bag(SAMPLE, TOPIC)[TOPIC][:1]
    scan = tmp_path / '000000.bin'
    scan.write_bytes(bytes(first.data))  # the sample's points are KITTI .bin bytes
    out = tmp_path / 'out'
    assert main(['replay', str(scan), str(out), '--labeled', '--output-prefix', '']) == 0
    ((_, msg),) = read_bag(out, '/labeled')['/labeled']
    points = read_points_file(scan)
    result = GroundSegmenter().segment(cloud_xyz(points, dtype=None))
    api = labeled_points(points, result)
    assert api.dtype.itemsize == msg.point_step and len(api) == msg.width
    assert bytes(msg.data) == api.tobytes()


def test_batch_labeled_writes_the_labeled_topic(tmp_path):
    assert main(['batch', str(SAMPLE), '--out', str(tmp_path / 'res'), '--labeled']) == 0
    topics = read_bag(tmp_path / 'res' / 'kitti00_sample')
    assert len(topics[f'{TOPIC}/labeled']) == len(topics[f'{TOPIC}/ground']) == 3


def test_without_labeled_there_is_no_labeled_topic(tmp_path):
    out = tmp_path / 'out'
    assert main(['replay', str(SAMPLE), str(out), '--max-frames', '1']) == 0
    assert set(read_bag(out)) == {f'{TOPIC}/ground', f'{TOPIC}/obstacles',
                                  f'{TOPIC}/ground_surface', '/diagnostics'}


@pytest.mark.parametrize('command', ['replay', 'batch'])
def test_labeled_option_is_documented(command, capsys):
    with pytest.raises(SystemExit):
        main([command, '--help'])
    assert 'labeled_points' in ' '.join(capsys.readouterr().out.split())
