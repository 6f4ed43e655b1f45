# SPDX-License-Identifier: Apache-2.0
"""``gp-ground-seg``: tools around the segmenter (all but play/hz need no ROS graph).

Subcommands:

* ``eval FILE...``     segment point files (.bin/.pcd), bag frames (BAG:INDEX) or whole bags; print
  per-frame ground precision/recall/F1/IoU against labels (when given; SemanticKITTI classes, or
  --dataset rellis3d, or any --ground-classes; vegetation as --protocol says), pooled over the
  frames, and timings.
* ``replay IN OUT``    bag (or point files) in -> ROS 2 bag with <topic>/ground, <topic>/obstacles,
  <topic>/ground_surface (publish_ground_surface on, the default) and /diagnostics out, using
  the node's pipeline and parameter file.
* ``plot FRAME``       side view of one angular segment + bird's-eye view of the frame (PNG).
* ``make-sample``      re-write the first frames of a bag as a small compressed mcap (data/).
* ``batch IN... --out DIR``  replay many inputs, in-process or on Dask (tools/batch.py).
* ``tune FRAME... --out params.yaml``  Optuna search of parameters on labelled scans
  (tools/tune.py).
* ``play IN``          publish a bag's clouds live with their recorded timing (tools/play.py).
* ``hz TOPIC...``      print topic rates and a one-line summary of the last message.

Every expected failure prints one line ``gp-ground-seg <cmd>: error: ...`` on stderr and exits
with status 2 (tools/errors.py); there is no traceback for bad input. A usage error names its
subcommand too (an unknown option of ``replay``: ``gp-ground-seg replay: error: unrecognized
arguments: ...``). ``gp-ground-seg`` without a subcommand prints the help on stdout and exits
with status 2, argparse's status for a missing argument (a script that lost its subcommand does
not pass). This module is the entry point only: nothing in the package imports it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

import numpy as np

from ..core.allocator import keep_freed_memory
from ..core.segmenter import GroundSegmenter
from ..ros.pipeline import frame_timings, process_cloud
from . import batch, play, tune
from .bag import (FrameSource, is_point_file, load_segmenter_params, read_frame, replay,
                  warm_up_before_timing, write_sample_bag)
from .errors import EXIT_ERROR, EXPECTED_ERRORS, CliError, one_line
from .evaluation import labelled_ground_truth, pooled_metrics, truth_metrics
from .io import read_semantickitti_labels
from .options import (add_frame_id_option, add_label_class_arguments, add_labeled_option,
                      add_input_options, add_storage_option, label_classes, no_ground_note)
from .plot import plot_frame


# ---------------------------------------------------------------------------------------------
# eval
# ---------------------------------------------------------------------------------------------

def _one_point_file(path: Path) -> bool:
    """An ``eval`` input that is one point file: one frame."""
    return path.is_file() and is_point_file(path)


def _point_file_count(inputs):
    """How many frames ``inputs`` hold when every one is a point file (one frame each), else
    None (bags and directories are counted as they are read)."""
    paths = [Path(spec) for spec in inputs]
    if all(_one_point_file(path) for path in paths):
        return len(paths)
    return None


def _eval_frames(inputs, topic):
    """Yield (name, rclpy PointCloud2) for every input: point files, BAG:INDEX or whole bags."""
    for spec in inputs:
        path = Path(spec)
        if path.exists() and not _one_point_file(path):
            with FrameSource([path], topic) as source:
                for frame in source:
                    # a directory of point files: each frame by its file (the --labels order)
                    name = (str(source.paths[frame.index]) if source.kind == 'files'
                            else f'{path}:{frame.index}')
                    yield name, frame.msg
        else:
            msg, name = read_frame(spec, topic)
            yield name, msg


def _nan_to_none(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _metrics_text(m: dict) -> str:
    """'ground precision .. recall .. F1 .. IoU .. (TP .. FP .. FN .. TN ..' of metrics whose
    NaN ratios are None."""
    def fmt(v):
        return 'n/a' if v is None else f'{v:.4f}'
    return (f"ground precision {fmt(m['precision'])}  recall {fmt(m['recall'])}  "
            f"F1 {fmt(m['f1'])}  IoU {fmt(m['iou'])}  (TP {m['tp']} FP {m['fp']} FN {m['fn']} "
            f"TN {m['tn']}")


def _print_eval_row(row: dict, ground: tuple, repeat: int) -> None:
    """The text lines of one ``eval`` frame."""
    share = row['ground_share']
    print(f"{row['input']}: {row['points']} points, {row['valid']} valid, ground share "
          f"{share if share is None else format(share, '.3f')}")
    if 'metrics' in row:
        m = row['metrics']
        print(f"  {_metrics_text(m)}, {m['evaluated_points']} labelled points; ground classes "
              f"{','.join(map(str, ground))})")
    t = row['timings_ms']
    order = ('decode', 'grid', 'lines', 'gp_fit', 'predict', 'label', 'structure', 'segment',
             'encode')
    names = [s for s in order if s in t] + sorted(set(t) - set(order) - {'total'})
    stages = '  '.join(f'{s} {t[s]:.1f}' for s in names)
    rep = f' (median of {repeat})' if repeat > 1 else ''
    print(f"  ms{rep}: total {t.get('total', float('nan')):.1f}  [{stages}]")
    th = row['hyperparameters']
    print(f"  theta: sigma_f {th['sigma_f']:.4g} m, gain {th['gain']:.4g}, "
          f"sigma_n {th['sigma_n']:.4g} m")


def _segment_frame(name: str, msg, segmenter, repeat: int) -> tuple:
    """(result of the first run, the row of one ``eval`` frame without metrics)."""
    runs = [process_cloud(msg, segmenter) for _ in range(repeat)]
    out = runs[0]  # labels of the first run: the same warm-start history as the node
    res = out.result
    timings = {stage: float(np.median([frame_timings(r)[stage] for r in runs]))
               for stage in frame_timings(out)}
    n_valid = int(np.count_nonzero(res.valid_mask))
    if n_valid == 0:
        raise CliError(f'{name}: no valid point ({int(res.valid_mask.size)} points, all '
                       f'NaN/Inf or (0, 0, 0)): nothing to evaluate')
    n_ground = int(np.count_nonzero(res.ground_mask))
    row = {'input': name, 'points': int(res.valid_mask.size), 'valid': n_valid,
           'ground': n_ground, 'ground_share': n_ground / n_valid,
           'hyperparameters': dict(zip(('sigma_f', 'gain', 'sigma_n'),
                                       (float(v) for v in res.hyperparameters))),
           'timings_ms': timings, 'repeat': repeat}
    return res, row


def _score_frame(row: dict, res, labels_file, classes: tuple) -> None:
    """Add the labels file and the metrics of ``res`` against it to ``row``."""
    ground, ignored = classes
    labels = read_semantickitti_labels(labels_file, expected_points=row['points'])
    row['labels'] = str(labels_file)
    truth, evaluated = labelled_ground_truth(labels, ground, ignored)
    row['metrics'] = {key: _nan_to_none(v) for key, v in
                      truth_metrics(res.ground_mask, truth, evaluated).items()}
    note = no_ground_note(row['input'], row['metrics']['tp'] + row['metrics']['fn'], ground)
    if note:
        print(f'gp-ground-seg eval: note: {note}', file=sys.stderr)


EVAL_DESCRIPTION = ('Segment each input (KITTI .bin, .pcd, BAG:INDEX or a whole bag) with one '
                    'segmenter (theta warm-starts frame to frame, as in the node; --cold: a fresh '
                    'one per frame) and print ms per stage and, with --labels, ground precision, '
                    'recall, F1 and IoU under --protocol per frame and pooled over the frames '
                    '(TP/FP/FN summed).')


SLOW_WARM_UP_S = 5.0  # a warm-up this long compiled kernels (a cache load takes ~1 s)


def _eval_note(text: str) -> None:
    print(f'gp-ground-seg eval: note: {text}', file=sys.stderr)


def cmd_eval(args) -> int:
    if args.repeat < 1:
        raise CliError('--repeat must be at least 1')
    classes = label_classes(args)
    params = load_segmenter_params(args.params)
    labels_files = args.labels or []
    frame_count = _point_file_count(args.files)
    if labels_files and frame_count is not None and frame_count != len(labels_files):
        # known before any frame is segmented when every input is one point file
        raise CliError(f'{len(labels_files)} label file(s) given for {frame_count} frame(s); '
                       'give one --labels file per frame')
    segmenter = GroundSegmenter(params)
    warm_up_s = warm_up_before_timing(_eval_note, segmenter)
    if warm_up_s > SLOW_WARM_UP_S:  # say why nothing happened for so long
        _eval_note(f'warm-up {warm_up_s:.1f} s before the first frame (numba compiled its '
                   'kernels: a new install; later runs load them from its cache); not in the '
                   'timings')
    frames = []
    for k, (name, msg) in enumerate(_eval_frames(args.files, args.topic)):
        if labels_files and k >= len(labels_files):
            raise CliError(f'{len(labels_files)} label file(s) for more frames; give one '
                           f'--labels file per frame')
        if args.cold and k:
            segmenter = GroundSegmenter(params)
        res, row = _segment_frame(name, msg, segmenter, args.repeat)
        if labels_files:
            _score_frame(row, res, labels_files[k], classes)
        frames.append(row)
        if not args.json:  # as it comes: a bad frame later does not lose this one
            _print_eval_row(row, classes[0], args.repeat)
    if labels_files and len(labels_files) != len(frames):
        raise CliError(f'{len(labels_files)} label file(s) given for {len(frames)} frame(s)')
    pooled = pooled_metrics([row['metrics'] for row in frames]) if labels_files else None
    if pooled is not None:
        pooled = {key: _nan_to_none(v) for key, v in pooled.items()}
        pooled['evaluated_points'] = sum(row['metrics']['evaluated_points'] for row in frames)
    if args.json:
        print(json.dumps({'frames': frames, 'pooled': pooled, 'params_file': args.params,
                          'cold': args.cold, 'protocol': args.protocol, 'dataset': args.dataset,
                          'ground_classes': list(classes[0]),
                          'ignored_classes': list(classes[1])}, indent=2))
    elif pooled is not None and len(frames) > 1:
        print(f'pooled over {len(frames)} frames (counts summed): {_metrics_text(pooled)}; '
              f'protocol {args.protocol})')
    return 0


# ---------------------------------------------------------------------------------------------
# replay
# ---------------------------------------------------------------------------------------------

REPLAY_DESCRIPTION = ('Segment every PointCloud2 of a bag (ROS 2 mcap/sqlite3 directory or file, '
                      'ROS 1 .bag), every scan of a Velodyne packet bag or .pcap capture, or '
                      '.bin/.pcd files (stamps i*0.1 s from 0, --frame-id) with the node '
                      'pipeline, and write a ROS 2 bag with <topic>/ground, <topic>/obstacles, '
                      '<topic>/ground_surface (unless publish_ground_surface is false; see '
                      '--output-prefix), <topic>/labeled (--labeled) and /diagnostics.')


def cmd_replay(args) -> int:
    inputs, out = args.inputs[:-1], args.inputs[-1]
    if not inputs:
        raise CliError('give an input (bag or point files) and an output bag directory')
    summary = replay(inputs, out, topic=args.topic, params_file=args.params,
                     storage=args.storage, force=args.force, max_frames=args.max_frames,
                     output_prefix=args.output_prefix, frame_id=args.frame_id,
                     labeled=args.labeled, imu_topic=args.imu_topic,
                     log=lambda text: print(f'gp-ground-seg replay: note: {text}',
                                            file=sys.stderr))
    print(summary.table())
    if summary.skipped:
        print(f'gp-ground-seg replay: warning: {summary.skipped} frame(s) skipped, see the '
              f'summary and /diagnostics', file=sys.stderr)
    if summary.imu and summary.imu['static']:
        print(f"gp-ground-seg replay: warning: {summary.imu['static']} frame(s) without an IMU "
              f"sample near their stamp kept the static pose, see the summary", file=sys.stderr)
    return 0


# ---------------------------------------------------------------------------------------------
# plot
# ---------------------------------------------------------------------------------------------

def cmd_plot(args) -> int:
    out = Path(args.out)
    if (out.exists() or out.is_symlink()) and not args.force:
        raise CliError(f'{out} exists; pass --force to overwrite it')
    params = load_segmenter_params(args.params)
    msg, name = read_frame(args.frame, args.topic)
    labels = None
    classes = label_classes(args)
    if args.labels:
        labels = read_semantickitti_labels(args.labels,
                                           expected_points=int(msg.height) * int(msg.width))
    info = plot_frame(msg, out, params=params, segment=args.segment, labels=labels, title=name,
                      label_classes=classes, extent=args.extent)
    if 'metrics' in info:
        note = no_ground_note(args.labels, info['metrics']['tp'] + info['metrics']['fn'],
                              classes[0])
        if note:
            print(f'gp-ground-seg plot: note: {note}', file=sys.stderr)
    print(f'wrote {out} (segment {info["segment"]}, {info["points"]} points, bird\'s-eye '
          f'extent +-{info["extent_m"]:g} m)')
    return 0


# ---------------------------------------------------------------------------------------------
# make-sample
# ---------------------------------------------------------------------------------------------

def cmd_make_sample(args) -> int:
    digest = write_sample_bag(args.source, args.out, frames=args.frames, topic=args.topic)
    print(f'wrote {args.out} ({args.frames} frames of {args.topic}); mcap sha256 {digest}')
    return 0


# ---------------------------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------------------------

class _Parser(argparse.ArgumentParser):
    """argparse with exit status 2 and a one-line message (its default, made explicit);
    ``subcommands``: name -> parser of the subcommands (set by build_parser)."""

    subcommands: dict = {}

    def error(self, message):
        self.exit(EXIT_ERROR, f'{self.prog}: error: {" ".join(message.split())}\n')

    def parse_command_line(self, argv):
        """parse_args, with an unknown option reported by the subcommand it was given to
        (argparse reports it as the main parser's); no subcommand at all: the help, status 2."""
        argv = list(sys.argv[1:] if argv is None else argv)
        if not argv:
            self.print_help()
            self.exit(EXIT_ERROR)
        args, unknown = self.parse_known_args(argv)
        if unknown:
            before = argv[:argv.index(args.command)] if args.command in argv else argv
            owner = self if set(unknown) & set(before) else self.subcommands[args.command]
            owner.error(f'unrecognized arguments: {" ".join(unknown)}')
        return args


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog='gp-ground-seg', description='Offline tools for the GP ground '
                     'segmenter: evaluate, replay bags, plot a frame.')
    sub = parser.add_subparsers(dest='command', required=True, parser_class=_Parser)
    for add in (_add_eval_parser, _add_replay_parser, _add_plot_parser, _add_make_sample_parser,
                batch.add_parser, tune.add_parser, play.register):  # play.register: play, hz
        add(sub)
    parser.subcommands = dict(sub.choices)
    return parser


def _add_eval_parser(sub) -> None:
    p = sub.add_parser('eval', help='segment point files / bag frames and print metrics',
                       description=EVAL_DESCRIPTION)
    p.add_argument('files', nargs='+', metavar='FILE', help='.bin, .pcd, .pcap, BAG, BAG:INDEX')
    p.add_argument('--labels', nargs='+', metavar='FILE.label',
                   help='.label file(s) (uint32 per point, class in the low 16 bits), one per '
                   'frame in order')
    add_label_class_arguments(p)
    add_input_options(p)
    p.add_argument('--json', action='store_true', help='print JSON instead of text')
    p.add_argument('--cold', action='store_true',
                   help='a fresh segmenter per frame (no theta warm start; the cold rows of '
                   'benchmarks/bench_quality.py)')
    p.add_argument('--repeat', type=int, default=1, metavar='K',
                   help='segment each frame K times and report the median ms (labels/metrics '
                   'are those of the first run)')
    p.set_defaults(func=cmd_eval)


def _add_replay_parser(sub) -> None:
    p = sub.add_parser('replay', help='bag in -> ground/obstacles/surface/diagnostics bag out',
                       description=REPLAY_DESCRIPTION)
    p.add_argument('inputs', nargs='+', metavar='IN ... OUT_BAG',
                   help='input bag, Velodyne .pcap, point files or a directory of them; last: '
                   'the output bag')
    add_input_options(p)
    p.add_argument('--force', action='store_true', help='overwrite OUT_BAG if it exists')
    add_storage_option(p)
    p.add_argument('--max-frames', type=int, metavar='K', help='stop after K frames')
    p.add_argument('--output-prefix', metavar='PREFIX', default=None,
                   help='output topics PREFIX/ground, PREFIX/obstacles and PREFIX/ground_surface '
                   "(default: the input topic, so outputs sit beside their input; '' gives "
                   '/ground, /obstacles and /ground_surface like the node in the root '
                   'namespace)')
    add_frame_id_option(p)
    add_labeled_option(p)
    p.add_argument('--imu-topic', metavar='TOPIC', default=None,
                   help='sensor_msgs/Imu topic of the input bag: level each cloud with the IMU '
                   'sample nearest its stamp, as the node\'s imu_topic parameter does (its '
                   'imu_* parameters from --params); frames without a sample within '
                   'imu_max_age_s keep the static pose and are counted in the summary')
    p.set_defaults(func=cmd_replay)


def _add_plot_parser(sub) -> None:
    p = sub.add_parser('plot', help='plot one frame (side view of a segment + bird\'s-eye view)',
                       description='FRAME: a .bin/.pcd file or BAG:INDEX (e.g. '
                       'data/kitti00_sample:0).')
    p.add_argument('frame', metavar='FRAME', help='.bin or .pcd file, or BAG:INDEX (a bag '
                   'frame from 0; a .pcap capture too)')
    p.add_argument('--segment', type=int, metavar='K',
                   help='angular segment for the side view (default: the one straight ahead, '
                   '+x)')
    p.add_argument('--labels', metavar='FILE.label', help='colour the top view by TP/FP/FN')
    p.add_argument('--extent', type=float, metavar='M',
                   help='half-width of the bird\'s-eye panels in m (default: fitted to the data, '
                   'the 98th percentile of max(|x|, |y|) of the points plus 5 %%, rounded up)')
    add_label_class_arguments(p)
    add_input_options(p)
    p.add_argument('--out', required=True, metavar='FIG.png',
                   help='figure file to write (PNG; .svg and .pdf work too); its parent '
                   'directories are created')
    p.add_argument('--force', action='store_true', help='overwrite FIG.png if it exists')
    p.set_defaults(func=cmd_plot)


def _add_make_sample_parser(sub) -> None:
    p = sub.add_parser('make-sample', help='write the small sample bag shipped in data/',
                       description='Copy the first messages of a bag topic unchanged (raw '
                       'bytes, same bag times) into a new zstd-compressed mcap bag, as '
                       'data/kitti00_sample was made (data/README.md), and print its sha256.')
    p.add_argument('source', help='input rosbag2 (e.g. ../shared/data/kitti00_velodyne_points)')
    p.add_argument('out', help='output bag directory (must not exist)')
    p.add_argument('--frames', type=int, default=3, metavar='K',
                   help='how many messages to copy, from the first (default 3)')
    p.add_argument('--topic', default='/velodyne_points',
                   help='topic whose messages are copied (default /velodyne_points)')
    p.set_defaults(func=cmd_make_sample)


def main(argv=None) -> int:
    """Entry point of ``gp-ground-seg``; returns the exit status (0 ok, 2 error)."""
    parser = build_parser()
    args = parser.parse_command_line(argv)
    prog = f'gp-ground-seg {args.command}'
    # the process is ours: keep each frame's freed memory for the next frame (a third less
    # time per replayed frame; core/allocator.py). Where it does not apply, nothing changes.
    keep_freed_memory()
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print(f'{prog}: interrupted', file=sys.stderr)
        return 130
    except BrokenPipeError:  # stdout closed early (e.g. '| head'): the work itself is done
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no 2nd error at exit
        return 0
    except EXPECTED_ERRORS as err:
        print(f'{prog}: error: {one_line(err)}', file=sys.stderr)
        return EXIT_ERROR


if __name__ == '__main__':
    sys.exit(main())
