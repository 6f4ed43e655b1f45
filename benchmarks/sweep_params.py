# SPDX-License-Identifier: Apache-2.0
"""Parameter sweep: how the defaults were chosen (accuracy only, no timing).

Every variant is run on ALL the labelled data we have -- the SemanticKITTI frame and the eight
synthetic scenes -- so that no default is tuned to one frame. Each scene is segmented twice in a
row (cold start, then warm-started) and the second frame is scored. Prints one markdown row per
variant: precision / recall per scene and the real frame's F1.

    python benchmarks/sweep_params.py                       # the default sweep below
    python benchmarks/sweep_params.py ground_threshold_m=0.15 ground_threshold_m=0.25
    python benchmarks/sweep_params.py "num_bins=16 num_segments=90"
"""

from __future__ import annotations

import argparse
import sys

from common import (REPO, command_line, load_labeled_kitti, machine_markdown, markdown_table,
                    parse_param_values, score, synthetic_datasets, update_results_section)

from gp_ground_segmentation import GroundSegmenter, SegmenterParams  # noqa: E402 (path via common)

DEFAULT_VARIANTS = (
    '',  # the defaults
    'ground_threshold_m=0.15', 'ground_threshold_m=0.25',
    'ground_threshold_std_factor=1.0', 'num_bins=16', 'num_bins=32',
    'num_segments=90', 'num_segments=180', 'outlier_residual_m=0.4',
    'anchor_std_m=3.0', 'plateau_step_m=10.0', 'length_scale_gain_max=200.0',
    'max_length_factor=50.0', 'density_in_flat_branch=true', 'deming_variance_ratio=0.1',
    'use_elevated_plateaus=false', 'use_anchor=false', 'use_outlier_rejection=false',
)


def parse_variant(text: str) -> dict:
    """'a=1 b=2.0' -> {'a': 1, 'b': 2.0}, typed like the SegmenterParams defaults."""
    return parse_param_values(text.split())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('variants', nargs='*', help='"name=value ..." per variant')
    parser.add_argument('--no-write', action='store_true',
                        help='print only; do not update benchmarks/RESULTS.md')
    args = parser.parse_args(argv)
    variants = args.variants or list(DEFAULT_VARIANTS)
    frames = []
    real = load_labeled_kitti()
    if real is not None:
        frames += real.frames
    for dataset in synthetic_datasets():
        frames += dataset.frames
    headers = ['variant'] + [f.name for f in frames] + ['real F1']
    rows = []
    for text in variants:
        params = SegmenterParams(**parse_variant(text)).validate()
        row = [text or '(defaults)']
        real_f1 = '-'
        for frame in frames:
            seg = GroundSegmenter(params)
            seg.segment(frame.points)
            metrics = score(seg.segment(frame.points).ground_mask, frame)
            row.append(f"{metrics['precision']:.3f} / {metrics['recall']:.3f}")
            if real is not None and any(frame is f for f in real.frames):
                real_f1 = f"{metrics['f1']:.3f}"
        rows.append(row + [real_f1])
        print(' | '.join(row + [real_f1]), file=sys.stderr, flush=True)
    table = markdown_table(headers, rows)
    print(table)
    if not args.no_write:
        text = ('## Parameter sweep (`sweep_params.py`)\n\n' + machine_markdown(command_line())
                + '\nEach cell: ground precision / recall of the second (warm-started) frame; '
                'SemanticKITTI scored with the Patchwork protocol (vegetation non-ground), '
                'synthetic scenes against exact truth. One parameter changed per row.\n\n'
                + table + '\n')
        update_results_section(REPO / 'benchmarks' / 'RESULTS.md', 'sweep_params', text)
    return 0


if __name__ == '__main__':
    sys.exit(main())
