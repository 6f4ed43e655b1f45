# SPDX-License-Identifier: Apache-2.0
"""Figures a person can read: one segment from the side, the frame and its ground from above.

Left panel (side view, r vs z of angular segment K): the raw points of the segment coloured
ground / obstacle, the ground candidates (lowest point per radial bin), the critical points
that end line-segments, the fitted line-segments, and the ground surface z +/- 2 z_std
(``result.ground_surface`` at the segment's bin edges).
Middle panel (bird's-eye view, x vs y): every valid point coloured ground / obstacle, or, when
labels are given (SemanticKITTI classes by default; --dataset), by error: true ground found
(TP), ground missed (FN), obstacle called ground (FP), obstacle kept (TN); the selected segment
is outlined. Both bird's-eye panels span +-extent m, fitted to the data (:func:`fitted_extent`:
a 10 m indoor cloud fills them as a 60 m road scan does) unless given.
Right panel (bird's-eye height map): the ground surface coloured by z, with contours of z_std
(the std of the ground height, surface.z_std) over the supported prediction points.

The intermediate arrays come from ``GroundSegmenter.segment(points, details=True).details``
(``segmenter.SegmentationDetails``); whatever the details do not provide is left out of the
legend rather than faked. matplotlib is an optional extra (``pip install .[plot]``) and is
imported only here, lazily.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..core.grid import segment_of
from ..core.params import SegmenterParams
from ..core.segmenter import GroundSegmenter
from ..ros.cloud import cloud_xyz, read_cloud
from .evaluation import (DEFAULT_PROTOCOL, SEMANTIC_KITTI, labelled_ground_truth,
                         truth_metrics)

FIGURE_METADATA_KEY = 'gp_ground_segmentation'  # PNG text chunk with the figure's numbers

COLOURS = {'ground': '#2ca02c', 'obstacle': '#d62728', 'candidate': '#1f77b4',
           'critical': '#ff7f0e', 'line': '#9467bd', 'gp': '#111111',
           'tp': '#2ca02c', 'fn': '#1f77b4', 'fp': '#d62728', 'tn': '#b0b0b0',
           'ignored': '#e0e0e0'}


class PlotError(ValueError):
    """Plotting is impossible (matplotlib missing, bad segment index ...); one-line message."""


def _pyplot():
    try:
        import matplotlib
        matplotlib.use('Agg')  # files only, never a window; works without a display
        import matplotlib.pyplot as plt
    except ImportError:
        raise PlotError('matplotlib is not installed: pip install "gp_ground_segmentation[plot]" '
                        '(or pip install matplotlib)') from None
    return plt


def segment_view(xyz: np.ndarray, result, segment: int, num_segments: int) -> dict:
    """Arrays of the side view of ``segment``: points, candidates, critical points, lines, GP.

    Only what is available is returned; keys: r, z, ground (points of the segment), and
    optionally cand_r, cand_z, critical_r, critical_z, lines [(r0, z0, r1, z1)], gp_r, gp_mean,
    gp_std, zhat_r, zhat.
    """
    valid = result.valid_mask
    seg_all = np.full(len(xyz), -1)
    seg_all[valid] = segment_of(xyz[valid, 0], xyz[valid, 1], num_segments)
    sel = seg_all == segment
    r = np.hypot(xyz[sel, 0], xyz[sel, 1])
    view = {'r': r, 'z': xyz[sel, 2], 'ground': result.ground_mask[sel]}
    zhat = result.ground_height[sel]
    order = np.argsort(r)
    ok = np.isfinite(zhat[order])
    view['zhat_r'], view['zhat'] = r[order][ok], zhat[order][ok]
    if result.details is not None:
        view.update(_details_view(result.details, segment))
    surface = getattr(result, 'ground_surface', None)
    if surface is not None:  # the published ground (with its calibration) wins over details
        view['gp_r'], view['gp_mean'] = surface.r[segment], surface.z[segment]
        view['gp_std'] = surface.z_std[segment]
        view['gp_label'] = 'ground surface z'
    return view


def _details_view(det, k: int) -> dict:
    """The segment's candidates, critical points, line-segments and GP curve from the details.

    ``det`` is a ``segmenter.SegmentationDetails``: (M, N) arrays indexed [segment, bin] for the
    grid candidates, ``lines`` (frame-unique line ids with Deming intercept/slope and r-range),
    ``training``/``outliers`` masks and the GP mean/std where it was evaluated.
    """
    grid, lines = det.grid, det.lines
    cr = np.asarray(grid.candidate_r[k], float)
    cz = np.asarray(grid.candidate_z[k], float)
    ok = np.isfinite(cr) & np.isfinite(cz)
    training = np.asarray(det.training[k], bool) & ok
    outliers = np.asarray(det.outliers[k], bool) & ok
    out = {'cand_r': cr, 'cand_z': cz, 'cand_train': training, 'cand_outlier': outliers,
           'cand_other': ok & ~training & ~outliers}
    critical = np.asarray(lines.is_critical[k], bool) & ok
    out['critical_r'], out['critical_z'] = cr[critical], cz[critical]
    segs = []
    for lid in np.unique(lines.line_id[k][ok]):
        if lid < 0:
            continue
        beta, alpha = float(lines.line_slope[lid]), float(lines.intercept[lid])
        if not (np.isfinite(beta) and np.isfinite(alpha)):
            continue  # a one-point line has no direction
        r0, r1 = (float(v) for v in lines.line_r_range[lid])
        segs.append((r0, alpha + beta * r0, r1, alpha + beta * r1))
    out['lines'] = segs
    # where the GP was evaluated: bin edges ('prediction_r'; 'bin_center_r' in earlier versions)
    where = getattr(det, 'prediction_r', None)
    gr = np.asarray((where if where is not None else det.bin_center_r)[k], float)
    gm = np.asarray(det.ground_mean[k], float)
    gs = np.asarray(det.ground_std[k], float)
    keep = np.isfinite(gr) & np.isfinite(gm)
    if np.any(keep):
        order = np.argsort(gr[keep])
        out['gp_r'], out['gp_mean'] = gr[keep][order], gm[keep][order]
        out['gp_std'] = gs[keep][order]
    return out


def default_segment(num_segments: int) -> int:
    """The segment straight ahead of the sensor (+x axis)."""
    return int(segment_of(np.array([1.0]), np.array([0.0]), num_segments)[0])


EXTENT_QUANTILE = 98.0  # percentile of max(|x|, |y|) of the valid points the panels show
MIN_EXTENT_M = 1.0


def fitted_extent(xyz: np.ndarray, valid: np.ndarray) -> float:
    """Half-width (m) of the bird's-eye panels that fits the data: the EXTENT_QUANTILE
    percentile of max(|x|, |y|) of the valid points (a few far returns do not shrink the rest to
    a dot), 5 % more, rounded up to a round step (half the power of ten below it: 53 -> 55 m,
    8.3 -> 8.5 m); at least MIN_EXTENT_M."""
    reach = np.max(np.abs(xyz[valid, :2]), axis=1) if np.any(valid) else np.zeros(1)
    half = 1.05 * float(np.percentile(reach, EXTENT_QUANTILE))
    if half <= MIN_EXTENT_M:
        return MIN_EXTENT_M
    step = 10.0 ** math.floor(math.log10(half)) / 2.0
    return math.ceil(half / step) * step


def plot_frame(msg, out_path, *, params=None, segment=None, labels=None, title='',
               label_classes=None, dpi=110, extent=None) -> dict:
    """Segment one PointCloud2 and save the three-panel figure to ``out_path`` (PNG, SVG, PDF).

    ``labels``: semantic classes per point (optional), scored with ``label_classes`` = (ground
    classes, ignored classes), default SemanticKITTI's under the default protocol. ``extent``:
    half-width (m) of the bird's-eye panels, default :func:`fitted_extent`. Returns a dict with
    the segment index, point count, the extent and, with labels, the metrics.
    """
    if extent is not None and not (math.isfinite(extent) and extent > 0):
        raise PlotError(f'--extent must be a finite number of metres > 0, got {extent}')

    plt = _pyplot()  # fail early, before the (slow) segmentation
    params = params or SegmenterParams()
    xyz = cloud_xyz(read_cloud(msg))
    m = params.num_segments
    if segment is None:
        segment = default_segment(m)
    if not 0 <= segment < m:
        raise PlotError(f'--segment {segment} is outside 0..{m - 1} (num_segments = {m})')
    result = GroundSegmenter(params).segment(xyz, details=True)
    reach = float(extent) if extent is not None else fitted_extent(xyz, result.valid_mask)
    view = segment_view(xyz, result, segment, m)
    n_valid = int(np.count_nonzero(result.valid_mask))
    n_ground = int(np.count_nonzero(result.ground_mask))
    theta = result.hyperparameters
    info = {'segment': segment, 'points': int(len(xyz)), 'ground_points': n_ground,
            'sigma_f': float(theta.sigma_f), 'gain': float(theta.gain),
            'sigma_n': float(theta.sigma_n), 'extent_m': reach}

    fig, (ax_side, ax_top, ax_surface) = plt.subplots(
        1, 3, figsize=(25, 7.2), gridspec_kw={'width_ratios': [1.45, 1, 1.15]})
    _draw_side(ax_side, view, segment, m)
    _draw_surface(ax_surface, result.ground_surface, fig, reach)
    ground_classes, ignored_classes = label_classes or DEFAULT_PROTOCOL.classes(SEMANTIC_KITTI)
    truth = evaluated = None
    if labels is not None:
        truth, evaluated = labelled_ground_truth(labels, ground_classes, ignored_classes)
        info['metrics'] = truth_metrics(result.ground_mask, truth, evaluated)
    _draw_top(ax_top, xyz, result, (truth, evaluated, ignored_classes), (segment, m), reach)
    # the surface panel's numbers too: a figure drawn before a change of z_std is stale
    surface_points = result.ground_surface.points()
    info['surface_z_std_mean'] = (float(np.mean(surface_points[:, 3]))
                                  if len(surface_points) else None)
    # no time in the title: one cold call says little, and a regenerated figure would differ
    sub = (f'{n_valid} valid points, ground share {n_ground / max(n_valid, 1):.2f}; '
           f'theta: sigma_f {theta.sigma_f:.3g} m, a {theta.gain:.3g}, '
           f'sigma_n {theta.sigma_n:.3g} m')
    if 'metrics' in info:
        mt = info['metrics']
        sub += (f'\nground precision {mt["precision"]:.3f}, recall {mt["recall"]:.3f}, '
                f'F1 {mt["f1"]:.3f} (ground classes '
                f'{",".join(map(str, ground_classes))})')
    fig.suptitle(f'{title}\n{sub}' if title else sub, fontsize=11)
    fig.tight_layout()
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    # The figure's numbers go into the PNG too (a tEXt chunk), so a test can tell a stale
    # figure from the code's current output.
    metadata = ({FIGURE_METADATA_KEY: json.dumps({k: v for k, v in info.items()
                                                  if k != 'metrics'}, sort_keys=True)}
                if out.suffix.lower() == '.png' else None)
    fig.savefig(out, dpi=dpi, metadata=metadata)
    plt.close(fig)
    return info


def _draw_side(ax, v, segment, m):
    width = 360.0 / m
    az0 = -180.0 + segment * width
    ax.scatter(v['r'][~v['ground']], v['z'][~v['ground']], s=4, c=COLOURS['obstacle'],
               label=f'obstacle points ({np.count_nonzero(~v["ground"])})', rasterized=True)
    ax.scatter(v['r'][v['ground']], v['z'][v['ground']], s=4, c=COLOURS['ground'],
               label=f'ground points ({np.count_nonzero(v["ground"])})', rasterized=True)
    if 'gp_r' in v:
        gr, gm = v['gp_r'], v['gp_mean']
        ok = np.isfinite(gr) & np.isfinite(gm)
        name = v.get('gp_label', 'GP mean')
        ax.plot(gr[ok], gm[ok], color=COLOURS['gp'], lw=1.6, label=name)
        if 'gp_std' in v:
            gs = v['gp_std'][ok]
            ax.fill_between(gr[ok], gm[ok] - 2 * gs, gm[ok] + 2 * gs, color=COLOURS['gp'],
                            alpha=0.15, lw=0, label=f'{name} ± 2σ')
    elif v['zhat_r'].size:
        ax.plot(v['zhat_r'], v['zhat'], color=COLOURS['gp'], lw=1.4,
                label='predicted ground height ẑ(r)')
    if 'cand_r' in v:
        cr, cz = v['cand_r'], v['cand_z']
        for key, marker, name in (('cand_train', 'o', 'ground candidates (GP training)'),
                                  ('cand_other', 's', 'candidates not used (steep line)'),
                                  ('cand_outlier', 'x', 'candidates rejected (outlier)')):
            mk = v[key]
            if not np.any(mk):
                continue
            style = ({'facecolors': 'none', 'edgecolors': COLOURS['candidate']}
                     if marker != 'x' else {'c': COLOURS['candidate']})
            ax.scatter(cr[mk], cz[mk], s=40, marker=marker, lw=1.3, zorder=3,
                       label=f'{name} ({np.count_nonzero(mk)})', **style)
    if 'critical_r' in v and v['critical_r'].size:
        ax.scatter(v['critical_r'], v['critical_z'], s=90, marker='D', facecolors='none',
                   edgecolors=COLOURS['critical'], lw=1.6, zorder=4,
                   label=f'critical points ({v["critical_r"].size})')
    for i, (r0, z0, r1, z1) in enumerate(v.get('lines', [])):
        ax.plot([r0, r1], [z0, z1], color=COLOURS['line'], lw=2.2, alpha=0.85, zorder=2,
                label=f'line-segments ({len(v["lines"])})' if i == 0 else None)
    ax.set_xlabel('radial distance r (m)')
    ax.set_ylabel('height z (m, sensor frame)')
    ax.set_title(f'side view of angular segment {segment} '
                 f'(azimuth {az0:.1f}° to {az0 + width:.1f}°, {v["r"].size} points)')
    if v['z'].size:
        lo, hi = np.percentile(v['z'], [0.5, 99.5])
        pad = 0.3 + 0.1 * (hi - lo)
        ax.set_ylim(lo - pad, hi + pad)  # below-ground reflection noise would squash the plot
    ax.grid(True, alpha=0.3)
    ax.legend(loc='upper left', fontsize=8, markerscale=1.5, framealpha=0.9)


def _draw_top(ax, xyz, result, scoring, segment_of_m, reach):
    """Bird's-eye panel of ``reach`` m; ``scoring``: (truth, evaluated, ignored classes) or
    Nones; ``segment_of_m``: (the side view's segment, num_segments)."""
    truth, evaluated, ignored_classes = scoring
    segment, m = segment_of_m
    valid = result.valid_mask
    ground = result.ground_mask
    x, y = xyz[:, 0], xyz[:, 1]
    if truth is None:
        groups = [('ground', ground, COLOURS['ground']),  # obstacles drawn on top
                  ('obstacle', valid & ~ground, COLOURS['obstacle'])]
        ax.set_title('bird\'s-eye view: segmenter labels')
    else:
        ev = evaluated & valid
        ignored = '/'.join(map(str, ignored_classes))
        groups = [(f'not evaluated (class {ignored})', valid & ~evaluated, COLOURS['ignored']),
                  ('TN obstacle kept', ev & ~ground & ~truth, COLOURS['tn']),
                  ('TP ground found', ev & ground & truth, COLOURS['tp']),
                  ('FN ground missed', ev & ~ground & truth, COLOURS['fn']),
                  ('FP obstacle called ground', ev & ground & ~truth, COLOURS['fp'])]
        ax.set_title('bird\'s-eye view: errors against the labels')
    for name, mask, colour in groups:
        ax.scatter(x[mask], y[mask], s=0.4 if 'TN' in name or 'not' in name else 0.8, c=colour,
                   lw=0, label=f'{name} ({np.count_nonzero(mask)})', rasterized=True)
    width = 2 * math.pi / m
    a0 = -math.pi + segment * width
    far = 2 * reach  # the wedge runs past the axes so it is visible at every azimuth
    wedge = [(0.0, 0.0), (far * math.cos(a0), far * math.sin(a0)),
             (far * math.cos(a0 + width), far * math.sin(a0 + width))]
    ax.fill(*zip(*wedge), color='#f5c400', alpha=0.35, lw=0.8, ec='k', ls='--', zorder=0.5,
            label=f'segment {segment} (side view)')
    _birds_eye_axes(ax, reach)
    ax.legend(loc='upper right', fontsize=8, markerscale=8, framealpha=0.9)


def _birds_eye_axes(ax, reach):
    """x/y axes of a bird's-eye panel: +-reach metres, equal aspect, grid."""
    ax.set_xlim(-reach, reach)
    ax.set_ylim(-reach, reach)
    ax.set_aspect('equal')
    ax.set_xlabel('x (m)')
    ax.set_ylabel('y (m)')
    ax.grid(True, alpha=0.3)


def _draw_surface(ax, surface, fig, reach):
    """Bird's-eye height map of the ground surface: z filled, z_std as labelled contours."""
    ax.set_title('ground surface: height z (colour), z_std (contours, m)')
    _birds_eye_axes(ax, reach)
    if surface is None:
        return
    keep = surface.supported & (np.abs(surface.x) <= 1.5 * reach) & (
        np.abs(surface.y) <= 1.5 * reach)
    if np.count_nonzero(keep) < 3:
        ax.text(0, 0, 'no supported ground surface', ha='center')
        return
    columns = (surface.x, surface.y, surface.z, surface.z_std)
    x, y, z, std = (np.asarray(a)[keep] for a in columns)
    lo, hi = np.percentile(z, [1, 99])
    filled = ax.tricontourf(x, y, np.clip(z, lo, hi), levels=20, cmap='viridis')
    fig.colorbar(filled, ax=ax, label='ground height z (m)', shrink=0.85)
    levels = np.unique(np.round(np.percentile(std, [50, 80, 95]), 3))  # where it gets unsure
    if levels.size and levels[-1] > 0:
        lines = ax.tricontour(x, y, std, levels=levels, colors='white', linewidths=0.7)
        ax.clabel(lines, fontsize=7, fmt='%.2f')
    ax.scatter(x, y, s=0.5, c='k', alpha=0.3, lw=0, label='prediction points (bin edges)')
    ax.legend(loc='upper right', fontsize=8, markerscale=8, framealpha=0.9)
