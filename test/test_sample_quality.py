# SPDX-License-Identifier: Apache-2.0
"""A real-data quality check that runs in a bare clone: the shipped sample (data/kitti00_sample,
KITTI 00 frames 0-2) against its shipped SemanticKITTI labels (data/kitti00_sample_labels),
through ``gp-ground-seg eval`` as a user runs it (one segmenter, theta warm-started frame to
frame, as in the node), under both scoring protocols.

Thresholds sit 0.005 below the pooled precision and recall measured on 2026-12-01
(``gp-ground-seg eval data/kitti00_sample --labels data/kitti00_sample_labels/00000{0,1,2}.label
--protocol P``): vegetation-nonground P 0.9483 R 0.9951 F1 0.9712; patchworkpp P 0.9939
R 0.9951 F1 0.9945. The labels' provenance (their checksums in data/README.md, point counts
equal to the sample's clouds, and, with ../shared/data, the sample's points being the labelled
scans' bytes) is checked too.
"""

import hashlib
import json
import re

import numpy as np
import pytest
from conftest import DATA, REPO

from gp_ground_segmentation.tools.bag import FrameSource
from gp_ground_segmentation.tools.cli import main
from gp_ground_segmentation.tools.io import read_semantickitti_labels

SAMPLE = REPO / 'data' / 'kitti00_sample'
LABELS = [REPO / 'data' / 'kitti00_sample_labels' / f'{i:06d}.label' for i in range(3)]
TOLERANCE = 0.005
# protocol -> (measured pooled precision, recall, F1), 2026-12-01
MEASURED = {'vegetation-nonground': (0.9483, 0.9951, 0.9712),
            'patchworkpp': (0.9939, 0.9951, 0.9945)}
# data/README.md section 6 of ../shared (and data/README.md here): ground and labelled points
GROUND = (67873, 66737, 65618)
LABELLED = (122480, 122421, 122375)


@pytest.mark.parametrize('protocol', sorted(MEASURED))
def test_sample_against_its_shipped_labels(protocol, capsys):
    assert main(['eval', str(SAMPLE), '--labels', *map(str, LABELS), '--protocol', protocol,
                 '--json']) == 0
    doc = json.loads(capsys.readouterr().out)
    frames, pooled = doc['frames'], doc['pooled']
    assert [f['points'] for f in frames] == [124668, 124605, 124478]
    assert [f['metrics']['tp'] + f['metrics']['fn'] for f in frames] == list(GROUND)
    if protocol == 'vegetation-nonground':  # vegetation is scored, as non-ground
        assert [f['metrics']['evaluated_points'] for f in frames] == list(LABELLED)
    precision, recall, f1 = MEASURED[protocol]
    print(f"{protocol}: pooled P {pooled['precision']:.4f} R {pooled['recall']:.4f} "
          f"F1 {pooled['f1']:.4f}")
    assert pooled['precision'] >= precision - TOLERANCE, pooled
    assert pooled['recall'] >= recall - TOLERANCE, pooled
    assert pooled['f1'] >= f1 - TOLERANCE, pooled


def _readme_checksums() -> dict:
    text = (REPO / 'data' / 'README.md').read_text()
    return dict(re.findall(r'\| `(\d{6}\.label)` \| [\d,]+ \| ([0-9a-f]{64}) \|', text))


def test_labels_match_their_readme_checksums_and_the_sample():
    sums = _readme_checksums()
    assert sorted(sums) == [p.name for p in LABELS]
    with FrameSource([SAMPLE]) as source:
        clouds = [frame.msg for frame in source]
    for path, cloud in zip(LABELS, clouds):
        assert hashlib.sha256(path.read_bytes()).hexdigest() == sums[path.name]
        labels = read_semantickitti_labels(path, expected_points=cloud.width * cloud.height)
        assert labels.size == cloud.width


@pytest.mark.skipif(not (DATA / 'labeled').is_dir(), reason='../shared/data not found')
def test_labels_are_those_of_the_shared_scans_whose_bytes_the_sample_holds():
    with FrameSource([SAMPLE]) as source:
        clouds = [frame.msg for frame in source]
    for i, (path, cloud) in enumerate(zip(LABELS, clouds)):
        shared = DATA / 'labeled' / f'semantickitti_seq00_{i:06d}'
        assert path.read_bytes() == shared.with_suffix('.label').read_bytes()
        assert np.array_equal(np.frombuffer(bytes(cloud.data), np.uint8),
                              np.fromfile(shared.with_suffix('.bin'), np.uint8))
