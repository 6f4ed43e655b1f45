# SPDX-License-Identifier: Apache-2.0
"""Where the shared real data lies, and which labelled real scans it holds.

The one place that knows the path (tests, benchmarks and benchmarks/dump_labels.py read it from
here): ``$GP_GROUND_SEG_DATA`` when set, else ``shared/data`` beside the checkout or beside one
of its parent directories (a clone in /work/main and a worktree in /work/wt-x both find
/work/shared/data). The data and its provenance: that directory's README.md.

:func:`labelled_scans` lists every labelled real scan with its cross-validation group (its
KITTI sequence, or RELLIS-3D): the seven SemanticKITTI sequences 00 (frames 0-2, one scene),
02, 04, 05, 06, 08 (the spvnas scan, frame 0) and 10, then the RELLIS-3D scan (README sections
1, 6 and 7).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gp_ground_segmentation.tools.evaluation import RELLIS_3D, SEMANTIC_KITTI, LabelOntology
from gp_ground_segmentation.tools.io import read_kitti_bin, read_semantickitti_labels

REPO = Path(__file__).resolve().parents[1]
DATA_ENV = 'GP_GROUND_SEG_DATA'


def find_data_dir(repo: Path = REPO) -> Path:
    """``$GP_GROUND_SEG_DATA``, else the first ``shared/data`` directory beside ``repo`` or one
    of its parents, else ``repo/../shared/data`` (absent: what needs it is skipped)."""
    if os.environ.get(DATA_ENV):
        return Path(os.environ[DATA_ENV])
    for parent in repo.parents:
        if (parent / 'shared' / 'data').is_dir():
            return parent / 'shared' / 'data'
    return repo.parent / 'shared' / 'data'


DATA_DIR = find_data_dir()


@dataclass(frozen=True)
class LabelledScan:
    """A real scan (KITTI .bin: x, y, z, remission) with per-point labels of ``ontology``."""

    name: str  # e.g. 'kitti00_000001', 'kitti08_000000', 'rellis3d_000001'
    group: str  # its cross-validation group: the KITTI sequence ('kitti00') or 'rellis3d'
    stem: Path  # the .bin and .label paths without their suffix
    ontology: LabelOntology

    @property
    def bin_path(self) -> Path:
        return self.stem.with_suffix('.bin')

    @property
    def label_path(self) -> Path:
        return self.stem.with_suffix('.label')

    def exists(self) -> bool:
        return self.bin_path.is_file() and self.label_path.is_file()

    def read(self) -> tuple:
        """(points (N, 4) float32, semantic classes (N,) uint32)."""
        points = np.ascontiguousarray(read_kitti_bin(self.bin_path), dtype=np.float32)
        return points, read_semantickitti_labels(self.label_path, expected_points=len(points))


# (KITTI sequence, frame, file stem under the data directory), in stream order
_KITTI_SCANS = ([('00', i, f'labeled/semantickitti_seq00_{i:06d}') for i in range(3)]
                + [(seq, 0, f'labeled/semantickitti_seq{seq}_000000')
                   for seq in ('02', '04', '05', '06')]
                + [('08', 0, 'kitti_sequnknown_spvnas_000000'),  # README section 7: seq 08
                   ('10', 0, 'labeled/semantickitti_seq10_000000')])


def labelled_scans(data_dir: Path = DATA_DIR) -> list:
    """Every labelled real scan the data README describes, present or not (``exists()``), in
    stream order: KITTI by sequence, then RELLIS-3D."""
    kitti = [LabelledScan(f'kitti{seq}_{frame:06d}', f'kitti{seq}', data_dir / stem,
                          SEMANTIC_KITTI) for seq, frame, stem in _KITTI_SCANS]
    return kitti + [LabelledScan('rellis3d_000001', 'rellis3d',
                                 data_dir / 'labeled' / 'rellis3d_examplebundle_000001',
                                 RELLIS_3D)]


def labelled_scan(name: str, data_dir: Path = DATA_DIR) -> LabelledScan:
    """The scan of :func:`labelled_scans` called ``name``; KeyError naming the known ones."""
    scans = {scan.name: scan for scan in labelled_scans(data_dir)}
    if name not in scans:
        raise KeyError(f'no labelled scan {name!r}; known: {", ".join(scans)}')
    return scans[name]
