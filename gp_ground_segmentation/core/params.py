# SPDX-License-Identifier: Apache-2.0
"""Parameters of the ground segmenter: one frozen dataclass, every field documented with units.

Each field carries ``metadata`` with a human description (units included), and a numeric range
(``min``/``max``, inclusive) so that the ROS node can build ``ParameterDescriptor`` objects and
validate ``ros2 param set`` without repeating any of it. ``SegmenterParams.validate()`` checks
the ranges (:func:`value_problem`, shared with the node) and the cross-field rules; it raises
``ValueError`` naming the offending field.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from .sensor_frame import SensorPose


TYPE_NAMES = {'float': 'a double (write it with a decimal point, e.g. 80.0)',
              'int': 'an integer (no decimal point)', 'bool': 'a bool (true/false)'}
_SHOWN_TYPES = {'bool': 'bool', 'int': 'integer', 'float': 'double'}


def kind_of(value) -> str | None:
    """'bool', 'int', 'float' (bool before int: True is an int in Python), or None."""
    for kind, python_type in (('bool', bool), ('int', int), ('float', float)):
        if isinstance(value, python_type):
            return kind
    return None


def value_problem(value, kind: str, low=None, high=None, *, int_as_float=False) -> str | None:
    """What is wrong with ``value`` for a parameter of type ``kind`` ('float', 'int' or 'bool')
    and inclusive range [low, high]; None if nothing. The one check behind
    ``SegmenterParams.validate`` and the node's parameters (``ros.config``).

    ``int_as_float`` accepts an int for a float (Python callers); ROS parameter files and
    ``ros2 param set`` do not (rclpy types are strict).
    """
    got = kind_of(value)
    if got != kind and not (int_as_float and kind == 'float' and got == 'int'):
        shown = _SHOWN_TYPES[got] if got else type(value).__name__
        return f'expected {TYPE_NAMES[kind]}, got {shown} {value!r}'
    if kind == 'bool':
        return None
    if not math.isfinite(value):
        return f'must be finite, got {value!r}'
    if (low is not None and value < low) or (high is not None and value > high):
        return f'{value!r} is outside [{low}, {high}]'
    return None


# Keys and values of earlier versions that mean something else now: each gives one line naming
# what replaced it (SegmenterParams, the node's parameter files)
RETIRED_KEYS = {
    'ground_threshold_std_factor': 'replaced by use_std_threshold and std_threshold_factor '
    '(0.0 is use_std_threshold: false, the default; a value above 0 is use_std_threshold: '
    'true with std_threshold_factor that value)',
}
RETIRED_OFF_VALUES = {  # name: (the value that turned a rule off, the switch that does now)
    'outlier_wide_terrain_m': (0.0, 'use_wide_terrain_rule'),
    'length_factor_smoothing_passes': (0, 'use_length_factor_smoothing'),
    'outlier_std_factor': (0.0, 'use_outlier_std_limit'),
}


def retired_problem(name: str, value=None) -> str | None:
    """What is wrong with key ``name`` (and ``value``) of an earlier version (``RETIRED_KEYS``,
    ``RETIRED_OFF_VALUES``), naming what replaced it, in one line; None for a current one."""
    if name in RETIRED_KEYS:
        return RETIRED_KEYS[name]
    if name in RETIRED_OFF_VALUES and kind_of(value) in ('int', 'float'):
        off, switch = RETIRED_OFF_VALUES[name]
        if value == off:
            return (f'{value!r} no longer turns the rule off; set {switch}: false instead '
                    f'(and leave {name} in its range)')
    return None


def _param(default, description: str, low=None, high=None):
    return field(default=default, metadata={'description': description, 'min': low, 'max': high})


@dataclass(frozen=True)
class SegmenterParams:
    """All tunables of the Gaussian-process ground segmenter.

    Every addition of ours is switched by a ``use_<stage>`` bool, its numbers beside it; no
    number turns a rule off. The defaults are the leave-one-group-out choice over both scoring
    protocols among the candidates of benchmarks/bench_quality.py (every labelled real scene
    and synthetic family; benchmarks/RESULTS.md, "Ground quality"), never tuned on one frame:
    the coupled surface and free space on, the cross-slope threshold off, ground_threshold_m
    0.25 and one length factor instead of the paper's non-stationary one.
    """

    # --- radial grid (grid.py) -------------------------------------------------------------
    num_segments: int = _param(
        120, 'M: number of angular segments of the radial grid (each 360/M degrees wide)', 8, 1440)
    num_bins: int = _param(
        24, 'N: radial bins per segment, spread evenly between that segment\'s own r_min and '
        'r_max (the paper\'s "divided unevenly" grid)', 4, 512)
    noise_spike_m: float = _param(
        1.0, 'a ground candidate whose leave-one-out GP residual is below minus this (m) is '
        'below-ground reflection noise: it stops training the GP', 0.05, 100.0)

    # --- line extraction (lines.py) ----------------------------------------------------------
    deming_variance_ratio: float = _param(
        1.0, 'lambda: ratio var(z error)/var(r error) of the errors-in-variables (Deming) line '
        'fit; the default 1 is orthogonal regression, the fit the paper rejects because it '
        'assumes equal errors in r and z (large values tend to OLS of z on r)', 1e-4, 1e4)
    line_max_slope: float = _param(
        0.7, 'zeta_b: a line whose |slope| (dz/dr) would exceed this ends at a critical point; '
        'lines steeper than this are treated as non-ground structure', 0.01, 100.0)
    line_max_distance_m: float = _param(
        0.15, 'delta: perpendicular distance (m) from a new candidate to the current line above '
        'which the candidate is a critical point', 0.005, 10.0)
    use_chord_slope_for_single_points: bool = _param(
        True, 'ours: a one-point line (a string of them is how Algorithm 1 sees a wall) gets the '
        '|slope| of the chord from the previous candidate of its segment instead of none (read '
        'as flat); steeper than zeta_b it does not train the GP, otherwise it sets its L')
    use_elevated_plateaus: bool = _param(
        True, 'ours, not the paper\'s: candidates on an elevated plateau (see plateau_step_m) '
        'do not train the GP; false trains on them')
    plateau_step_m: float = _param(
        0.3, 'a steep step up higher than this (m) between successive candidates starts an '
        'elevated plateau (an obstacle top whose ground is occluded), which does not train the '
        'GP; keep it above curb height', 0.05, 10.0)
    plateau_from_sensor_ground: bool = _param(
        True, 'ours: every segment\'s plateau test starts from the ground under the sensor '
        '(r = 0, the anchor height), so a person or car filling a segment next to the sensor '
        'is a step up; false starts at the segment\'s first candidate')
    plateau_ends_on_drop: bool = _param(
        False, 'a plateau also ends where the next candidate drops more than plateau_step_m '
        '(the earlier rule); false ends it only back at the ground level or after a gap, so '
        'a drop that stays above the ground (roof to bonnet, high wall to low) keeps it')
    line_max_gap_m: float = _param(
        6.0, 'zeta_m: radial gap (m) between successive candidates above which a line ends', 0.1,
        1000.0)
    line_max_density_jump: float = _param(
        8.0, 'a change of rho~ by more than this factor between successive candidates ends a '
        'line (the paper\'s "smoothness of rho~")', 1.0, 1e6)

    # --- Gaussian process (gp.py) -------------------------------------------------------------
    slope_floor: float = _param(
        0.02, 'g_d: slopes below this use log(1/g_d), keeping length scales finite on flat ground',
        1e-6, 0.9)
    slope_ceiling: float = _param(
        0.9, 'slopes are clipped to this (< 1) so log(1/g) stays positive', 0.05, 0.999)
    density_in_flat_branch: bool = _param(
        False, 'also divide the flat-branch length scale log(1/g_d) by rho~ (continuous in g at '
        'g_d; acts on the paper\'s length factors only, use_nonstationary_length_scale); False '
        'is the paper\'s formula')
    use_nonstationary_length_scale: bool = _param(
        False, 'paper (eqs. 8, 12): each candidate\'s length scale L_i = a d_i from its line\'s '
        'slope and rho~ (Paciorek\'s non-stationary kernel); false: one length factor, '
        'max_length_factor, for every candidate (a stationary kernel of length a '
        'max_length_factor)')
    min_length_factor: float = _param(
        0.05, 'lower clip of the length-scale factor d_i = log(1/g_i)/rho_i (dimensionless; '
        'L_i = a*d_i in m)', 1e-4, 100.0)
    max_length_factor: float = _param(
        2.0, 'upper clip of the length-scale factor d_i (dimensionless), and the one length '
        'factor of every candidate without use_nonstationary_length_scale', 1e-2, 1e5)
    use_density_ring_normalisation: bool = _param(
        True, 'ours, not the paper\'s: rho_i in d_i = log(1/g_i)/rho_i is the bin\'s rho~ (a 2-D '
        'point density, points per m^2 of its sector) over its geometric mean among the '
        'training candidates in the same log-range ring (r within 15 %), so that L means the '
        'same near and far and for any beam count; false divides by rho~ itself')
    use_length_factor_smoothing: bool = _param(
        True, 'ours, not the paper\'s: smooth log d_i along each segment '
        '(length_factor_smoothing_passes), so L_i does not jump between neighbouring bins with '
        'how many rings each holds; false keeps the paper\'s raw d_i')
    length_factor_smoothing_passes: int = _param(
        5, 'passes of the (1, 2, 1) / 4 running mean of log d_i over each segment\'s training '
        'candidates (neighbours in bin order) (use_length_factor_smoothing)', 1, 20)
    sigma_f_init_m: float = _param(0.5, 'initial sigma_f, GP signal std (m)', 1e-3, 100.0)
    length_scale_gain_init: float = _param(
        2.0, 'initial a, the gain of L_i = a*d_i (m per unit d)', 1e-3, 1e3)
    sigma_n_init_m: float = _param(0.05, 'initial sigma_n, GP noise std (m)', 1e-4, 10.0)
    sigma_f_min_m: float = _param(0.01, 'lower bound of sigma_f during learning (m)', 1e-4, 100.0)
    sigma_f_max_m: float = _param(20.0, 'upper bound of sigma_f during learning (m)', 1e-3, 1e3)
    length_scale_gain_min: float = _param(
        0.05, 'lower bound of a during learning (m per unit d)', 1e-4, 1e3)
    length_scale_gain_max: float = _param(
        5.0, 'upper bound of a during learning (m per unit d)', 1e-3, 1e5)
    sigma_n_min_m: float = _param(0.02, 'lower bound of sigma_n during learning (m)', 1e-5, 10.0)
    sigma_n_max_m: float = _param(2.0, 'upper bound of sigma_n during learning (m)', 1e-4, 100.0)
    optimizer_max_evaluations: int = _param(
        2, 'cap on marginal-likelihood evaluations (one whole-frame factorisation each) spent '
        'on learning theta on each learning frame after the first (optimizer_interval_frames), '
        'warm-started from the current theta; 0 keeps the first frame\'s theta', 0, 1000)
    optimizer_max_step_ratio: float = _param(
        1.5, 'after the first frame each hyperparameter may change by at most this factor per '
        'learning frame (a trust region: one odd frame cannot throw theta to its bounds)',
        1.01, 1e6)
    optimizer_first_frame_evaluations: int = _param(
        40, 'the same cap for the first frame (cold start)', 0, 10000)
    optimizer_interval_frames: int = _param(
        10, 'ours, not the paper\'s: after the first frame, theta is learned on every '
        'this-many-th frame of a stream (with optimizer_max_evaluations) and kept in between; '
        '1 learns on every frame, the paper\'s reading. Learning after the first frame '
        'measured no gain (benchmarks/RESULTS.md) and costs two factorisations a frame',
        1, 1000000)
    use_outlier_rejection: bool = _param(
        True, 'ours, not the paper\'s: candidates whose leave-one-out GP residual is above '
        'outlier_residual_m or below -noise_spike_m stop training the GP; false keeps them all')
    outlier_residual_m: float = _param(
        0.8, 'a candidate whose leave-one-out GP residual is above this (m) is an obstacle top, '
        'not ground: it stops training the GP (checked before and after learning theta)',
        0.01, 100.0)
    use_outlier_std_limit: bool = _param(
        True, 'ours: a candidate is an obstacle top only when its leave-one-out residual is '
        'also above outlier_std_factor leave-one-out predictive stds; where candidates are '
        'sparse (16-beam rings, far ground, high mounts) the GP predicts a left-out candidate '
        'loosely and the fixed limit rejected true ground; false uses outlier_residual_m alone')
    outlier_std_factor: float = _param(
        3.0, 'multiplier (dimensionless) of the leave-one-out predictive std (sqrt(1 / '
        '[A^-1]_ii), sensor noise included) in the outlier limit (use_outlier_std_limit; 3 = '
        'the usual Gaussian bound)', 0.01, 100.0)
    outlier_worst_per_segment: bool = _param(
        False, 'ours: each outlier pass drops at most one obstacle-top candidate per segment '
        '(the highest leave-one-out residual above outlier_residual_m), so ground next to an '
        'obstacle top is not dropped with it; false drops all above the limit at once')
    use_wide_terrain_rule: bool = _param(
        True, 'ours: an obstacle-top candidate that both neighbouring segments continue '
        '(outlier_wide_terrain_m, outlier_wide_terrain_max_slope) keeps training the GP: '
        'terrain is wider than a segment, a bin filled by one object is not. Without it sparse '
        'far ground on rising terrain (16-beam rings, high mounts) is rejected as obstacle tops')
    outlier_wide_terrain_m: float = _param(
        1.0, 'the wide-terrain rule (use_wide_terrain_rule) keeps an obstacle-top candidate when '
        'both neighbouring segments have a candidate within one bin of it and within this '
        'height (m) of it, and no candidate within one bin of it, in its own segment or the two '
        'beside it, lies more than this below it', 0.01, 10.0)
    outlier_wide_terrain_max_slope: float = _param(
        0.3, 'ours: the wide-terrain rule (outlier_wide_terrain_m) keeps a candidate only if it '
        'rises above the previous candidate of its own segment no steeper than this (dz/dr, '
        'dimensionless): the lowest visible part of a wall behind an occlusion shadow is '
        'continued by its neighbours like terrain, but stands steeply above the ground before '
        'the shadow', 0.0, 100.0)

    use_anchor: bool = _param(
        True, 'ours, not the paper\'s: every segment\'s GP gets a shared pseudo-candidate at '
        'r = 0, the ground under the vehicle (median of the first lines\' intercepts); false '
        'leaves segments independent')
    prior_mean_at_anchor: bool = _param(
        True, 'ours: the GP prior mean is the height of the ground under the vehicle (the '
        'anchor, clipped to the training candidates\' heights; needs use_anchor), so long gaps '
        'fall back to the vehicle\'s own ground level; false uses the median height of the '
        'training candidates')
    anchor_std_m: float = _param(
        0.3, 'noise std (m) of the shared pseudo-candidate at r = 0 that tells every segment '
        'the height of the ground under the vehicle', 0.01, 100.0)

    # --- labelling (segmenter.py) -------------------------------------------------------------
    ground_threshold_m: float = _param(
        0.25, 'a point is ground when z - z_hat(r) <= this (m), widened by the std and '
        'cross-slope rules and capped at max_threshold_m', 0.0, 10.0)
    use_std_threshold: bool = _param(
        False, 'ours: widen the ground threshold by std_threshold_factor times the GP\'s '
        'posterior std, so it grows where the GP is unsure (far, sparse bins)')
    std_threshold_factor: float = _param(
        1.0, 'multiplier (dimensionless) of the GP posterior std added to ground_threshold_m '
        '(use_std_threshold)', 0.01, 100.0)
    use_cross_slope_threshold: bool = _param(
        False, 'ours, not the paper\'s: widen the ground threshold by the rise of the predicted '
        'ground across the segment (where the neighbouring segments at the same r rise on one '
        'side and fall on the other; the smaller step, capped at a cross_slope_max slope), so '
        'the high side of ground sloping across the beams stays ground')
    cross_slope_max: float = _param(
        0.35, 'largest ground slope across the beams (dz per m of arc) that widens the threshold '
        '(use_cross_slope_threshold); a steeper rise between neighbouring segments is '
        'structure and widens it no more than this slope would', 0.0, 10.0)
    max_threshold_m: float = _param(
        0.3, 'cap (m) on the total ground threshold, however large the predictive std; must be '
        'at least ground_threshold_m', 0.0, 100.0)

    use_coupled_surface: bool = _param(
        True, 'ours: the ground on each border between two segments from a GP over both '
        'segments\' training candidates at their (x, y) (the paper\'s kernel in 2-D, the '
        'frame\'s theta), each point\'s height linear in azimuth between its segment\'s '
        'borders, so the ground follows slopes across the beams (coupled_surface.py); false: '
        'the paper\'s height per segment')

    # --- feet of vertical structures (structure.py) ------------------------------------------
    use_vertical_structure_test: bool = _param(
        True, 'ours: relabel as obstacle a ground point with another point within a few cm '
        'horizontally (its polar cell or the 8 around it) that stands between structure_rise_m '
        'and structure_max_height_m above the predicted ground: the lowest returns of walls, '
        'fences, cars, trunks and bushes')
    structure_cell_m: float = _param(
        0.03, 'radial size (m) of the cells of the structure test near the sensor; beyond the '
        'range where an azimuth cell is this wide, cells grow in proportion to the range',
        0.005, 1.0)
    structure_cell_deg: float = _param(
        0.25, 'azimuth size (degrees) of the cells of the structure test', 0.01, 10.0)
    structure_rise_m: float = _param(
        0.2, 'a point more than this (m) above the predicted ground is part of a column: it '
        'makes the ground points of its neighbourhood structure feet; keep it above curb '
        'height', 0.0, 10.0)
    structure_step_m: float = _param(
        0.05, 'a column point must also stand more than this (m) above the ground point it '
        'condemns (neighbours on a ramp differ by less over a few cm)', 0.0, 10.0)
    structure_max_height_m: float = _param(
        0.7, 'points higher than this (m) above the predicted ground are not columns (tree '
        'crowns, car bodies and signs overhanging visible ground); above structure_rise_m',
        0.0, 100.0)
    use_free_space_feet: bool = _param(
        True, 'ours: a structure foot stays ground when the sensor saw under its column: a '
        'ground return farther out whose ray passed between the foot and the column\'s lowest '
        'point (the ground under a car sill, a bumper, a canopy; free_space.py); needs '
        'use_vertical_structure_test')
    free_space_clearance_m: float = _param(
        0.03, 'the ray that spares a foot passes more than this (m) above the foot and below the '
        'lowest column point above it (use_free_space_feet)', 0.0, 1.0)
    free_space_beyond_m: float = _param(
        0.1, 'the return of that ray lies more than this (m) farther out than the foot '
        '(use_free_space_feet)', 0.0, 10.0)

    # --- sensor pose in the cloud's frame (sensor_frame.py) ------------------------------------
    sensor_x_m: float = _param(
        0.0, 'x of the sensor in the cloud\'s frame (m): the radial grid is centred on the sensor '
        '(e.g. its mounting offset when clouds come in base_link)', -1e4, 1e4)
    sensor_y_m: float = _param(0.0, 'y of the sensor in the cloud\'s frame (m)', -1e4, 1e4)
    sensor_z_m: float = _param(0.0, 'z of the sensor in the cloud\'s frame (m)', -1e4, 1e4)
    sensor_roll_rad: float = _param(
        0.0, 'roll of the cloud\'s frame against level ground (rad, about x, REP 103); the '
        'cloud is levelled with it, e.g. for a tilted mount publishing in its own frame',
        -math.pi, math.pi)
    sensor_pitch_rad: float = _param(
        0.0, 'pitch of the cloud\'s frame against level ground (rad, about y after roll; '
        'positive = x axis pointing down)', -math.pi / 2, math.pi / 2)

    def __new__(cls, *args, **kwargs):
        # an earlier version's key: one line naming what replaced it, not "unexpected keyword"
        for name in kwargs:
            problem = retired_problem(name)
            if problem:
                raise TypeError(f'{name}: {problem}')
        return super().__new__(cls)

    def __post_init__(self):
        # numpy scalars (np.int64(120), np.float32(0.2): what arrays and configs hand out) as the
        # Python numbers they stand for, so that validate() judges the value, not its class
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.generic) and value.dtype.kind in 'biuf':
                object.__setattr__(self, f.name, value.item())

    @property
    def sensor_pose(self) -> SensorPose:
        """Where the sensor is in the cloud's frame and how that frame is tilted."""
        return SensorPose(self.sensor_x_m, self.sensor_y_m, self.sensor_z_m,
                          self.sensor_roll_rad, self.sensor_pitch_rad)

    def validate(self) -> 'SegmenterParams':
        """Check every range and cross-field rule; raise ValueError naming the field."""
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            retired = retired_problem(f.name, value)
            if retired:
                raise ValueError(f'{f.name}: {retired}')
            problem = value_problem(value, type(f.default).__name__, f.metadata.get('min'),
                                    f.metadata.get('max'), int_as_float=True)
            if problem:
                raise ValueError(f'{f.name}: {problem}')
        if self.slope_floor >= self.slope_ceiling:
            raise ValueError('slope_floor: must be below slope_ceiling')
        if self.min_length_factor >= self.max_length_factor:
            raise ValueError('min_length_factor: must be below max_length_factor')
        if self.ground_threshold_m > self.max_threshold_m:
            # max_threshold_m caps the total threshold: a larger ground_threshold_m would be cut
            # back to it silently (ros2 param set changes one parameter at a time)
            raise ValueError(f'ground_threshold_m: {self.ground_threshold_m!r} is above '
                             f'max_threshold_m {self.max_threshold_m!r}, the cap on the total '
                             'threshold; raise max_threshold_m too (with ros2 param set, '
                             'first), or lower ground_threshold_m to lower the cap')
        if self.structure_rise_m >= self.structure_max_height_m:
            raise ValueError(f'structure_rise_m: {self.structure_rise_m!r} must be below '
                             f'structure_max_height_m {self.structure_max_height_m!r}; raise '
                             'structure_max_height_m first')
        for init, low, high in (('sigma_f_init_m', 'sigma_f_min_m', 'sigma_f_max_m'),
                                ('length_scale_gain_init', 'length_scale_gain_min',
                                 'length_scale_gain_max'),
                                ('sigma_n_init_m', 'sigma_n_min_m', 'sigma_n_max_m')):
            if not getattr(self, low) < getattr(self, high):
                raise ValueError(f'{low}: must be below {high}')
            if not getattr(self, low) <= getattr(self, init) <= getattr(self, high):
                raise ValueError(f'{init}: {getattr(self, init)} is outside [{low}, {high}]')
        return self

    def replace(self, **changes) -> 'SegmenterParams':
        """Return a validated copy with ``changes`` applied (unknown names raise TypeError)."""
        return dataclasses.replace(self, **changes).validate()


def describe_params() -> list[dict]:
    """One dict per field: name, default, type, description, min, max (for node and docs)."""
    rows = []
    for f in dataclasses.fields(SegmenterParams):
        rows.append({'name': f.name, 'default': f.default, 'type': type(f.default).__name__,
                     'description': f.metadata['description'], 'min': f.metadata.get('min'),
                     'max': f.metadata.get('max')})
    return rows
