# SPDX-License-Identifier: Apache-2.0
"""Shared helpers of the benchmark scripts: data sets, scoring, timing, memory, tables, machine.

Data (``scenes.real_data`` finds ../shared/data and lists its labelled scans; every loader
returns ``None`` or skips with a printed reason when its file is absent, so a benchmark runs on
whatever is there):

* ``labelled_groups``  every labelled real scan, one ``Dataset`` per cross-validation group: the
                     KITTI sequences 00 (frames 0-2), 02, 04, 05, 06, 08 (the spvnas scan), 10
                     with SemanticKITTI labels, and the RELLIS-3D scan with its own;
* ``load_labeled_kitti`` the spvnas scan alone (KITTI 08 frame 0, 123,389 points), the one
                     labelled ~120k-point frame of the speed benchmarks;
* ``kitti00_bag``    the 6 KITTI 00 PointCloud2 frames of the mcap bag, read with rosbags and
                     decoded with ``gp_ground_segmentation.ros.cloud`` (the node's decoder);
                     no labels;
* ``kitti_unlabeled`` the single KITTI .bin (it is byte-for-byte frame 0 of the bag);
* ``vlp16`` / ``vlp32`` / ``xt32`` single indoor scans of other sensors (PCD), no labels;
* synthetic scenes of ``scenes.synthetic`` with exact truth, grouped as
  flat (``flat``, ``crowned_curb``), sloped (``ramp10/15/20``, ``onslope15``, ``hill``) and mixed.

Every frame's ``points`` is an ``(N, 4)`` C-contiguous float32 array x, y, z (m), intensity: the
one array every method is fed. Intensity is KITTI remission (0..1) for the KITTI frames, the
synthetic reflectance for the scenes, a uint8 intensity / 255 for the VLP-16 and 0 where the file
has none (``has_intensity`` False then).

Scoring is ``gp_ground_segmentation.tools.evaluation`` for everyone, under a named protocol
(default: vegetation non-ground; ``patchworkpp``: vegetation not scored). A labelled real frame
keeps its classes, so it is scored under any protocol (``Frame.scoring``). Synthetic truth is
``is_ground`` (terrain surface, curb faces included as ground, as SemanticKITTI labels curbs
sidewalk), the same under every protocol. Metrics of several frames are pooled (summed
TP/FP/FN), not averaged.
"""

from __future__ import annotations

import contextlib
import datetime
import os
import platform
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from gp_ground_segmentation.tools.evaluation import (  # noqa: E402
    DEFAULT_PROTOCOL, SEMANTIC_KITTI, LabelOntology, ScoringProtocol, ground_truth_from_labels,
    pooled_metrics, truth_metrics)
from scenes.real_data import DATA_DIR, LabelledScan, labelled_scan, labelled_scans  # noqa: E402

UNLABELED_BIN = 'kitti_unlabeled_patchworkpp_000000.bin'
BAG_DIR = 'kitti00_velodyne_points'
BAG_TOPIC = '/velodyne_points'
SENSOR_PCDS = (('vlp16', 'sensors/velodyne_vlp16.pcd'), ('vlp32', 'sensors/velodyne_vlp32.pcd'),
               ('xt32', 'sensors/hesai_xt32.pcd'))

FLAT_SCENES = ('flat', 'crowned_curb')
SLOPED_SCENES = ('ramp10', 'ramp15', 'ramp20', 'onslope15', 'hill')
MIXED_SCENES = ('mixed',)

KITTI_SENSOR_HEIGHT_M = 1.73  # Velodyne HDL-64E above the road on the KITTI car (m)


# ------------------------------------------------------------------------------------ data

@dataclass
class Frame:
    """One cloud fed to every method, with its truth when known."""

    name: str
    points: np.ndarray  # (N, 4) float32 x, y, z, intensity, C-contiguous
    has_intensity: bool
    truth: Optional[np.ndarray] = None  # (N,) bool true ground, or None
    evaluated: Optional[np.ndarray] = None  # (N,) bool points that are scored, or None = all
    mount_height_m: Optional[float] = None  # sensor above the ground (m), for peers that need it
    classes: Optional[np.ndarray] = None  # (N,) semantic classes of a labelled real scan
    ontology: Optional[LabelOntology] = None  # the classes' ontology

    @property
    def labeled(self) -> bool:
        return self.truth is not None

    def scoring(self, protocol: ScoringProtocol = DEFAULT_PROTOCOL) -> tuple:
        """(truth, evaluated) under ``protocol``: from the classes of a labelled real scan, the
        synthetic truth as it is (it has no vegetation class to treat apart)."""
        if self.classes is None:
            return self.truth, self.evaluated
        return ground_truth_from_labels(self.classes, self.ontology, protocol)

    def __len__(self):
        return int(self.points.shape[0])


@dataclass
class Dataset:
    """Frames played in order as one stream (a new segmenter per data set)."""

    name: str
    frames: list
    description: str = ''
    group: str = 'real'  # real, sensor, synthetic-flat, synthetic-sloped, synthetic-mixed
    notes: list = field(default_factory=list)

    @property
    def labeled(self) -> bool:
        return all(f.labeled for f in self.frames)

    @property
    def points_per_frame(self) -> float:
        return float(np.mean([len(f) for f in self.frames]))


def _xyzi(xyz, intensity=None) -> np.ndarray:
    out = np.zeros((len(xyz), 4), dtype=np.float32)
    out[:, :3] = xyz
    if intensity is not None:
        out[:, 3] = intensity
    return out


def _missing(path: Path) -> bool:
    if not path.exists():
        print(f'[data] skipped: {path} not found', file=sys.stderr)
        return True
    return False


def labelled_frame(scan: LabelledScan) -> Frame:
    """The Frame of a labelled real scan, truth under the default protocol (``Frame.scoring``
    gives any other). KITTI: remission intensity, the HDL-64E's 1.73 m mount; RELLIS-3D: its
    intensity is normalised to ~0..0.012, not remission, so it is treated as absent (steps tuned
    for remission, Patchwork++'s RNR, are not misled), and its mount is measured once
    (:func:`rellis_mount_height`)."""
    points, classes = scan.read()
    truth, evaluated = ground_truth_from_labels(classes, scan.ontology)
    kitti = scan.ontology is SEMANTIC_KITTI
    mount = KITTI_SENSOR_HEIGHT_M if kitti else rellis_mount_height(points, truth)
    return Frame(scan.name, points, kitti, truth, evaluated, mount, classes, scan.ontology)


def labelled_groups(data_dir: Path = DATA_DIR) -> list:
    """One Dataset per cross-validation group of the labelled real scans found (a KITTI
    sequence, ``kitti00`` holding frames 0-2 in order, or ``rellis3d``); a missing scan is
    skipped with a line on stderr."""
    groups: dict = {}
    for scan in labelled_scans(data_dir):
        if _missing(scan.bin_path) or _missing(scan.label_path):
            continue
        groups.setdefault(scan.group, []).append(labelled_frame(scan))
    return [Dataset(name, frames, _group_text(frames), 'real') for name, frames in groups.items()]


def _group_text(frames) -> str:
    first = frames[0]
    if first.ontology is SEMANTIC_KITTI:
        return (f'SemanticKITTI sequence {first.name[5:7]}, frame(s) '
                f'{", ".join(str(int(f.name[-6:])) for f in frames)} (HDL-64E)')
    return 'RELLIS-3D off-road Ouster OS1-64 scan, organised, its own ontology'


def load_labeled_kitti(data_dir: Path = DATA_DIR) -> Optional[Dataset]:
    """The spvnas SemanticKITTI scan (KITTI 08 frame 0) alone, truth under the default
    protocol: the labelled ~120k-point frame of the speed benchmarks."""
    scan = labelled_scan('kitti08_000000', data_dir)
    if _missing(scan.bin_path) or _missing(scan.label_path):
        return None
    return Dataset('kitti_labeled', [labelled_frame(scan)], 'SemanticKITTI scan (KITTI 08 '
                   'frame 0), labels', 'real')


def labelled_group(name: str, data_dir: Path = DATA_DIR) -> Optional[Dataset]:
    """The :func:`labelled_groups` group ``name`` (e.g. 'kitti00', 'rellis3d'), or None."""
    return next((g for g in labelled_groups(data_dir) if g.name == name), None)


def rellis_mount_height(points: np.ndarray, truth: np.ndarray) -> float:
    """Sensor height over the ground (m): minus the median z of true ground at 3-10 m range.

    What a user measures once for a mount; only the peers that need a height are given it.
    """
    r = np.hypot(points[:, 0], points[:, 1])
    near = truth & (r > 3.0) & (r < 10.0)
    return float(-np.median(points[near, 2]))


def load_family(family: str, seeds) -> Optional[Dataset]:
    """Members ``seeds`` of a randomised synthetic family (``scenes.synthetic.family_scan``)."""
    try:
        from scenes import synthetic
    except ImportError as exc:
        print(f'[data] skipped synthetic families: {exc}', file=sys.stderr)
        return None
    frames, group = [], ''
    for seed in seeds:
        member = synthetic.family_scene(family, seed)
        # family_scan's body, on the scene already made (building it twice costs its checks)
        scan = synthetic.simulate_scan(member.scene, seed=seed, **member.scan_kwargs)
        # Intensity is not physically modelled (see scenes.synthetic): flagged as absent so that
        # intensity-based steps (Patchwork++'s RNR) are not driven by made-up values.
        frames.append(Frame(f'{family}_{seed}', np.ascontiguousarray(scan.points), False,
                            np.asarray(scan.is_ground, dtype=bool).copy(),
                            np.asarray(scan.returned, dtype=bool).copy(),
                            member.sensor_height_m))
        group = member.group
    description = (f'synthetic family {family!r}, seeds {", ".join(map(str, seeds))} (one random '
                   'scene each)')
    return Dataset(family, frames, description, 'synthetic-' + group)


def parse_param_values(items) -> dict:
    """['a=1', 'b=2.0', 'c=true'] -> {'a': 1, 'b': 2.0, 'c': True}, typed like SegmenterParams.

    Raises ValueError naming an unknown parameter or a malformed item.
    """
    import dataclasses
    from gp_ground_segmentation import SegmenterParams
    fields = {f.name: f for f in dataclasses.fields(SegmenterParams)}
    out = {}
    for item in items:
        name, sep, value = item.partition('=')
        name = name.strip()
        if not sep or name not in fields:
            raise ValueError(f'{item!r}: expected name=value with a SegmenterParams field name')
        kind = type(fields[name].default)
        out[name] = (value.strip().lower() in ('1', 'true', 'yes')) if kind is bool \
            else kind(value)
    return out


def load_unlabeled_kitti(data_dir: Path = DATA_DIR) -> Optional[Dataset]:
    """The single unlabeled KITTI scan (= frame 0 of the bag)."""
    from gp_ground_segmentation.tools.io import read_kitti_bin
    path = data_dir / UNLABELED_BIN
    if _missing(path):
        return None
    pts = np.ascontiguousarray(read_kitti_bin(path), dtype=np.float32)
    return Dataset('kitti_unlabeled', [Frame('kitti00_000000', pts, True)],
                   'KITTI scan, no labels', 'real')


def load_bag_frames(data_dir: Path = DATA_DIR, topic: str = BAG_TOPIC) -> Optional[Dataset]:
    """The PointCloud2 frames of the KITTI 00 mcap bag, decoded as the node decodes them.

    rosbags reads and deserializes (its typestore knows sensor_msgs); the message is then decoded
    by ``gp_ground_segmentation.ros.cloud.read_cloud`` / ``cloud_xyz`` (duck-typed),
    intensity kept.
    """
    path = data_dir / BAG_DIR
    if _missing(path):
        return None
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:
        print(f'[data] skipped bag: rosbags not importable ({exc})', file=sys.stderr)
        return None
    from gp_ground_segmentation.ros.cloud import cloud_xyz, read_cloud
    frames = []
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        for i, (conn, _, raw) in enumerate(reader.messages(connections=conns)):
            msg = reader.deserialize(raw, conn.msgtype)
            cloud = read_cloud(msg)
            inten = cloud['intensity'] if 'intensity' in cloud.dtype.names else None
            frames.append(Frame(f'bag_{i}', _xyzi(cloud_xyz(cloud), inten), inten is not None))
    if not frames:
        print(f'[data] skipped bag: no messages on {topic}', file=sys.stderr)
        return None
    return Dataset('kitti00_bag', frames, f'KITTI 00 bag, {len(frames)} PointCloud2 frames, '
                   'no labels', 'real')


def load_sensor_pcds(data_dir: Path = DATA_DIR) -> list:
    """VLP-16, VLP-32C, PandarXT-32 scans: one single-frame Dataset each (indoor, low mount)."""
    from gp_ground_segmentation.tools.io import read_points_file
    out = []
    for name, rel in SENSOR_PCDS:
        path = data_dir / rel
        if _missing(path):
            continue
        arr = read_points_file(path)
        xyz = np.stack([arr['x'], arr['y'], arr['z']], axis=1)
        inten = None
        if 'intensity' in arr.dtype.names:
            inten = arr['intensity'].astype(np.float32)
            if np.issubdtype(arr.dtype['intensity'], np.integer):
                inten = inten / 255.0  # uint8 intensity -> 0..1 like KITTI remission
        out.append(Dataset(name, [Frame(name, _xyzi(xyz, inten), inten is not None)],
                           f'{Path(rel).name}, indoor, floor near z = -0.5 m, no labels',
                           'sensor'))
    return out


def load_synthetic(names, group: str, seed: int = 0) -> Optional[Dataset]:
    """Synthetic HDL-64E-like scans of ``names`` (``synthetic.simulate_scan``), exact truth."""
    try:
        from scenes import synthetic
    except ImportError as exc:
        print(f'[data] skipped synthetic scenes: {exc}', file=sys.stderr)
        return None
    frames = []
    for name in names:
        if name not in synthetic.SCENE_NAMES:
            print(f'[data] skipped unknown synthetic scene {name!r}', file=sys.stderr)
            continue
        scan = synthetic.simulate_scan(synthetic.make_scene(name), seed=seed)
        pts = np.ascontiguousarray(scan.points, dtype=np.float32)
        frames.append(Frame(name, pts, True, np.asarray(scan.is_ground, dtype=bool).copy()))
    if not frames:
        return None
    return Dataset(group, frames, 'synthetic ' + ', '.join(f.name for f in frames)
                   + ' (truth = terrain hit, curb faces ground)', group)


def synthetic_datasets(seed: int = 0) -> list:
    """Flat, sloped and mixed synthetic groups (missing module -> empty list)."""
    out = []
    for names, group in ((FLAT_SCENES, 'synthetic-flat'), (SLOPED_SCENES, 'synthetic-sloped'),
                         (MIXED_SCENES, 'synthetic-mixed')):
        ds = load_synthetic(names, group, seed)
        if ds is not None:
            out.append(ds)
    return out


def real_frame_120k(data_dir: Path = DATA_DIR) -> Optional[Frame]:
    """A ~120k-point real KITTI frame: the labeled scan, else the unlabeled one."""
    for loader in (load_labeled_kitti, load_unlabeled_kitti):
        ds = loader(data_dir)
        if ds is not None:
            return ds.frames[0]
    return None


def real_frames(data_dir: Path = DATA_DIR) -> list:
    """All distinct real KITTI frames: the labeled scan + the 6 bag frames (else the .bin)."""
    frames = []
    for ds in (load_labeled_kitti(data_dir), load_bag_frames(data_dir)):
        if ds is not None:
            frames.extend(ds.frames)
    if len(frames) < 2:
        ds = load_unlabeled_kitti(data_dir)
        if ds is not None:
            frames.extend(ds.frames)
    return frames


def make_cloud_of_size(frames, n_points: int, rng: np.random.Generator,
                       jitter_m: float = 0.01) -> np.ndarray:
    """An (n_points, 4) float32 cloud that keeps the structure of real frames.

    Fewer points than one frame: a random subset of the first frame (density drops, structure
    stays). More: whole frames stacked, each copy after the first turned by a random yaw about the
    sensor's vertical axis (ground stays ground) and jittered by ``jitter_m`` (m, Gaussian) so no
    point is repeated exactly, then cut to ``n_points``.
    """
    base = frames[0].points
    if n_points <= len(base):
        idx = np.sort(rng.choice(len(base), n_points, replace=False))
        return np.ascontiguousarray(base[idx])
    parts, total, k = [], 0, 0
    while total < n_points:
        pts = frames[k % len(frames)].points
        if k >= len(frames):  # a repeat of a frame: new yaw and jitter
            yaw = rng.uniform(0.0, 2.0 * np.pi)
            c, s = np.float32(np.cos(yaw)), np.float32(np.sin(yaw))
            pts = pts.copy()
            x, y = pts[:, 0].copy(), pts[:, 1].copy()
            pts[:, 0] = c * x - s * y
            pts[:, 1] = s * x + c * y
            pts[:, :3] += rng.normal(0.0, jitter_m, (len(pts), 3)).astype(np.float32)
        parts.append(pts)
        total += len(pts)
        k += 1
    return np.ascontiguousarray(np.concatenate(parts)[:n_points])


# ------------------------------------------------------------------------------------ scoring

def score(pred_ground: np.ndarray, frame: Frame,
          protocol: ScoringProtocol = DEFAULT_PROTOCOL) -> Optional[dict]:
    """Ground precision/recall/F1/IoU + counts of one frame under ``protocol``, or None when the
    frame has no truth."""
    if frame.truth is None:
        return None
    return truth_metrics(pred_ground, *frame.scoring(protocol))


def pool(metrics: list) -> Optional[dict]:
    """Pool per-frame metrics (sum TP/FP/FN) into one precision/recall/F1 (None if none)."""
    return pooled_metrics(metrics)


# ------------------------------------------------------------------------------------ timing

def timed(fn: Callable, *args):
    """(result, seconds) of one call, measured with time.perf_counter."""
    t0 = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t0


def time_repeated(fn: Callable, repeats: int, warmup: int = 1) -> list:
    """Seconds of ``repeats`` calls of ``fn()`` after ``warmup`` untimed calls."""
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(repeats):
        out.append(timed(fn)[1])
    return out


def summary_ms(seconds) -> dict:
    """median / p95 / min / mean of a list of durations in seconds, as milliseconds."""
    a = np.asarray(seconds, dtype=float) * 1e3
    if a.size == 0:
        return {'median': float('nan'), 'p95': float('nan'), 'min': float('nan'),
                'mean': float('nan'), 'n': 0}
    return {'median': float(np.median(a)), 'p95': float(np.percentile(a, 95)),
            'min': float(a.min()), 'mean': float(a.mean()), 'n': int(a.size)}


def median(values):
    values = [v for v in values if v is not None and np.isfinite(v)]
    return statistics.median(values) if values else float('nan')


# ------------------------------------------------------------------------------------ memory

def rss_bytes() -> tuple:
    """(current RSS, peak RSS since the last reset) of this process in bytes (Linux /proc)."""
    cur = peak = 0
    try:
        with open('/proc/self/status') as fh:
            for line in fh:
                if line.startswith('VmRSS:'):
                    cur = int(line.split()[1]) * 1024
                elif line.startswith('VmHWM:'):
                    peak = int(line.split()[1]) * 1024
    except OSError:
        pass
    return cur, peak


def reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS counter (VmHWM) to the current RSS; False if not possible."""
    try:
        with open('/proc/self/clear_refs', 'w') as fh:
            fh.write('5')
        return True
    except OSError:
        return False


# ------------------------------------------------------------------------------------ output

@contextlib.contextmanager
def quiet_stdout():
    """Silence C++ ``std::cout`` chatter of peer constructors (fd 1); never used while timing."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, 'w') as null:
            os.dup2(null.fileno(), 1)
            yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def fmt(value, digits: int = 1) -> str:
    """A number for a table cell; '-' for None/NaN."""
    if value is None:
        return '-'
    try:
        if not np.isfinite(value):
            return '-'
    except TypeError:
        return str(value)
    if isinstance(value, (int, np.integer)):
        return f'{int(value):,}'
    return f'{value:,.{digits}f}'


def markdown_table(headers, rows) -> str:
    """A GitHub markdown table; first column left-aligned, the rest right-aligned."""
    align = [':---'] + ['---:'] * (len(headers) - 1)
    lines = ['| ' + ' | '.join(str(h) for h in headers) + ' |', '| ' + ' | '.join(align) + ' |']
    for row in rows:
        lines.append('| ' + ' | '.join(str(c) for c in row) + ' |')
    return '\n'.join(lines)


def _package_version(name: str) -> str:
    try:
        from importlib.metadata import version
        return version(name)
    except Exception:  # noqa: BLE001 - not installed or no metadata
        return 'not installed'


def machine_info() -> dict:
    """nproc, CPU model, load average, Python/numpy/scipy and peer versions, UTC date."""
    cpu = platform.processor() or 'unknown'
    try:
        with open('/proc/cpuinfo') as fh:
            for line in fh:
                if line.startswith('model name'):
                    cpu = line.split(':', 1)[1].strip()
                    break
    except OSError:
        pass
    import scipy
    try:
        load = ' '.join(f'{x:.2f}' for x in os.getloadavg())
    except OSError:
        load = 'unknown'
    return {
        'date': datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC'),
        'nproc': os.cpu_count(),
        'affinity': len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else None,
        'cpu': cpu,
        'load_average': load,
        'python': platform.python_version(),
        'numpy': np.__version__,
        'scipy': scipy.__version__,
        'pypatchworkpp': _package_version('pypatchworkpp'),
        'linefit': _package_version('linefit'),
        'blas_threads': os.environ.get('OMP_NUM_THREADS', 'unset'),
    }


def machine_markdown(command: str) -> str:
    """The machine/command preamble of a RESULTS.md section."""
    m = machine_info()
    return (f'- Date: {m["date"]}; command: `{command}`\n'
            f'- Machine: {m["nproc"]} CPUs ({m["cpu"]}), load average at start '
            f'{m["load_average"]}; '
            f'Python {m["python"]}, numpy {m["numpy"]}, scipy {m["scipy"]}, '
            f'pypatchworkpp {m["pypatchworkpp"]}, linefit {m["linefit"]}\n')


def command_line() -> str:
    """The command that ran this script, relative to the repository when possible."""
    script = Path(sys.argv[0])
    try:
        script = script.resolve().relative_to(REPO)
    except ValueError:
        pass
    return ' '.join(['python', str(script)] + sys.argv[1:])


def update_results_section(path: Path, section: str, text: str) -> None:
    """Replace (or append) the block between ``<!-- BEGIN s -->`` and ``<!-- END s -->``.

    Each benchmark script owns one section of RESULTS.md, so running one script does not erase
    the others' results.
    """
    begin, end = f'<!-- BEGIN {section} -->', f'<!-- END {section} -->'
    block = f'{begin}\n{text.rstrip()}\n{end}\n'
    path = Path(path)
    old = path.read_text() if path.exists() else ''
    if begin in old and end in old:
        head, rest = old.split(begin, 1)
        tail = rest.split(end, 1)[1].lstrip('\n')
        new = head + block + ('\n' + tail if tail else '')
    else:
        if not old:
            old = RESULTS_HEADER
        new = old.rstrip() + '\n\n' + block
    path.write_text(new)


RESULTS_HEADER = """# Benchmark results

Written by the scripts in `benchmarks/` (each owns one section below; rerun a script to refresh
its section). See `benchmarks/README.md` for what each measures and how. The machine is shared
with other jobs (each section's load average says how busy it was): absolute times are noisy;
compare methods only as ratios within one run.
"""
