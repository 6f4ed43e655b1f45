# SPDX-License-Identifier: Apache-2.0
"""Command-line options that several gp-ground-seg subcommands share, and what they mean.

* which labels are ground (``--dataset``, ``--protocol``, ``--ground-classes``,
  ``--ignore-classes``; eval, plot, tune), resolved by :func:`label_classes` with the ontologies
  and protocols of :mod:`.evaluation`;
* the frame id of clouds made from point files (``--frame-id``; replay, play);
* the input topic of a bag and the node's parameter file (``--topic``, ``--params``; eval,
  replay, plot, batch);
* the labelled cloud among the outputs (``--labeled``) and the output bags' storage
  (``--storage``; replay, batch).
"""

from __future__ import annotations

from .bag import DEFAULT_TOPIC, SYNTHETIC_FRAME_ID
from .errors import CliError
from .evaluation import DEFAULT_PROTOCOL, ONTOLOGIES, PROTOCOLS


def add_label_class_arguments(parser) -> None:
    """--dataset / --protocol (with its shorthand --vegetation-ground) / --ground-classes /
    --ignore-classes: which label classes are ground and which are not scored."""
    parser.add_argument('--dataset', choices=sorted(ONTOLOGIES), default='semantickitti',
                        help='label ontology: its ground, left-out and vegetation classes '
                        '(default semantickitti; rellis3d for RELLIS-3D .label files)')
    group = parser.add_mutually_exclusive_group()
    vegetation = ', '.join(f'{o.name} {",".join(map(str, o.vegetation))}'
                           for o in ONTOLOGIES.values())
    group.add_argument('--protocol', choices=list(PROTOCOLS), default=DEFAULT_PROTOCOL.name,
                       help=f'scoring protocol: what is done with vegetation ({vegetation}): '
                       + '; '.join(f'{p.name}: {p.summary}' for p in PROTOCOLS.values())
                       + f' (default {DEFAULT_PROTOCOL.name})')
    group.add_argument('--vegetation-ground', dest='protocol', action='store_const',
                       const='vegetation-ground', help='the same as --protocol vegetation-ground')
    parser.add_argument('--ground-classes', metavar='C,C,...',
                        help='override the ground classes (the protocol\'s otherwise)')
    parser.add_argument('--ignore-classes', metavar='C,C,...',
                        help='override the classes left out of the score (the protocol\'s '
                        'otherwise)')


def label_classes(args) -> tuple[tuple, tuple]:
    """(ground classes, classes left out) of :func:`add_label_class_arguments`' options."""
    ground, ignored = PROTOCOLS[args.protocol].classes(ONTOLOGIES[args.dataset])
    if args.ground_classes:
        ground = class_list(args.ground_classes)
    if args.ignore_classes:
        ignored = class_list(args.ignore_classes)
    return tuple(ground), tuple(ignored)


def class_list(text: str) -> tuple:
    """'40,44, 48' -> (40, 44, 48); CliError for anything but comma-separated integers."""
    try:
        return tuple(sorted({int(v) for v in text.split(',') if v.strip()}))
    except ValueError:
        raise CliError(f'class list {text!r}: expected comma-separated integers, e.g. '
                       f'40,44,48') from None


def no_ground_note(name: str, ground_points: int, ground: tuple):
    """A one-line note when none of a frame's evaluated labels is a ground class
    (``ground_points``: how many are, e.g. TP + FN of its metrics; labels of another data set's
    ontology score 0 without it), else None."""
    if ground_points:
        return None
    return (f'{name}: no labelled point is in the ground classes {",".join(map(str, ground))}; '
            'labels of another data set? (--dataset rellis3d, --ground-classes)')


def add_frame_id_option(parser) -> None:
    """--frame-id: the header.frame_id given to clouds made from .bin/.pcd files."""
    parser.add_argument('--frame-id', default=SYNTHETIC_FRAME_ID,
                        help='header.frame_id of clouds made from .bin/.pcd files (default '
                        f'{SYNTHETIC_FRAME_ID})')


def add_labeled_option(parser) -> None:
    """--labeled: also write <prefix>/labeled, the node's labeled topic."""
    parser.add_argument('--labeled', action='store_true',
                        help='also write PREFIX/labeled, the node\'s labeled cloud: every valid '
                        'point in input order, its fields byte for byte plus ground (uint8, 1 = '
                        'ground) and height_above_ground (float32, m); the rows '
                        'gp_ground_segmentation.labels.labeled_points returns (default off)')


def add_storage_option(parser) -> None:
    """--storage: the output bags' rosbag2 storage plugin."""
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap',
                        help='storage of the output bag(s): mcap (one .mcap file, default) or '
                        'sqlite3 (.db3, the rosbag2 default before Iron)')


def add_input_options(parser) -> None:
    """--topic (the bag topic read: clouds or Velodyne packets) and --params (the node's
    parameter file)."""
    parser.add_argument('--params', metavar='YAML',
                        help='node parameter file (config/params.yaml)')
    parser.add_argument('--topic', default=None,
                        help='input topic of a bag: sensor_msgs/PointCloud2, or raw Velodyne '
                        'packets (velodyne_msgs/VelodyneScan, decoded; pip install '
                        f"'gp_ground_segmentation[packets]') (default {DEFAULT_TOPIC}; if the bag "
                        'has none, its one PointCloud2 topic, else its one VelodyneScan topic)')
