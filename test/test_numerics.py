# SPDX-License-Identifier: Apache-2.0
"""Numerical safety of the GP (issue 7, point 3): ill-conditioned problems never raise.

Covered, through ``FrameGP`` directly and through ``GroundSegmenter.segment`` on crafted clouds:
duplicate r values, a single candidate in a segment, all candidates equal, huge and tiny rho~
(relative density 1e-9 and 1e9), slopes >= 1, +-inf and NaN, theta at every corner of the widest
bounds the parameters allow, and point coordinates at float extremes (1e6 m away, 1e-6 m spacing).
Cholesky failures fall back to growing diagonal jitter and are counted, from
``FrameGP.cholesky_fallbacks`` through ``result.stats`` to the node's diagnostics; a failed or
diverging theta optimisation keeps the last good theta and is counted in
``stats['optimizer_failures']``, and the frame is still labelled.

Failures are injected by monkeypatching ``np.linalg.cholesky`` and
``FrameGP.lml_and_gradient`` (the objective of the theta search), so they are deterministic.
"""

import dataclasses
import itertools
import time
import warnings

import numpy as np
import pytest
from conftest import status_values, wait_for

from gp_ground_segmentation import GroundSegmenter, Hyperparameters, SegmenterParams
from gp_ground_segmentation.core import segmenter as segmenter_module
from gp_ground_segmentation.core import compiled, gp as gp_module, length_factors, stages
from gp_ground_segmentation.core.gp import FrameGP
from gp_ground_segmentation.core.length_factors import length_scale_factors
from scenes.synthetic import make_scene, simulate_scan

# Widest hyperparameter bounds SegmenterParams accepts (each field's own min/max).
SIGMA_F = (1e-4, 1e3)  # m
GAIN = (1e-4, 1e5)  # m per unit d
SIGMA_N = (1e-5, 100.0)  # m
CORNERS = list(itertools.product(SIGMA_F, GAIN, SIGMA_N))
WIDE = dict(sigma_f_min_m=SIGMA_F[0], sigma_f_max_m=SIGMA_F[1],
            length_scale_gain_min=GAIN[0], length_scale_gain_max=GAIN[1],
            sigma_n_min_m=SIGMA_N[0], sigma_n_max_m=SIGMA_N[1],
            min_length_factor=1e-4, max_length_factor=1e5, slope_floor=1e-6,
            slope_ceiling=0.999)
# theta learned on every frame (the defaults skip the frames between optimizer_interval_frames)
LEARN_EVERY_FRAME = SegmenterParams(optimizer_interval_frames=1)


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------
@pytest.fixture(scope='module')
def ramp_points():
    """A 20k-point subsample of the synthetic 15 % ramp (float32 x, y, z): quick to segment."""
    pts = simulate_scan(make_scene('ramp15'), seed=0).points[:, :3].astype(np.float32)
    rng = np.random.default_rng(0)
    return np.ascontiguousarray(pts[np.sort(rng.choice(len(pts), 20000, replace=False))])


def nasty_problem(m_count=6, n_count=8, seed=3):
    """(r, z, mask) (M, N) with every ill-conditioned case in one batch.

    Row 0: all r equal (duplicate r); row 1: all candidates equal (same r and z); row 2: a
    block of duplicate r inside increasing r; row 3: a single candidate; row 4: ordinary;
    row 5: no candidate at all.
    """
    rng = np.random.default_rng(seed)
    r = np.sort(rng.uniform(2.0, 40.0, (m_count, n_count)), axis=1)
    z = rng.normal(-1.7, 0.1, (m_count, n_count))
    r[0] = 5.0
    r[1], z[1] = 7.5, -1.6
    r[2] = np.linspace(3.0, 30.0, n_count)
    r[2, 2:6] = r[2, 2]
    mask = np.ones((m_count, n_count), dtype=bool)
    mask[3] = False
    mask[3, 4] = True
    mask[5] = False
    return r, z, mask


SPECIAL_SLOPES = np.array([0.0, 1e-12, 0.5, 1.0, 1.5, 1e6, np.inf, -np.inf, np.nan, -0.3])


def factors(density_rel, n_count=8, m_count=6, **kw):
    """Length-scale factors d (M, N) for slopes of every special kind at one relative density."""
    slope = np.resize(SPECIAL_SLOPES, (m_count, n_count))
    opts = dict(slope_floor=1e-6, slope_ceiling=0.999, d_min=1e-4, d_max=1e5)
    opts.update(kw)
    return length_scale_factors(slope, np.full((m_count, n_count), density_rel), **opts)


def assert_solution_finite(gp, theta):
    sol = gp.solve(theta)
    assert np.isfinite(sol.lml)
    lml, grad = gp.lml_and_gradient(np.log(theta))
    assert np.isfinite(lml) and np.all(np.isfinite(grad))
    assert np.all(np.isfinite(gp.loo_residuals(sol)))
    r_star = np.linspace(0.0, 50.0, 5)[None, :].repeat(gp.segments.size, axis=0)
    mean, std = gp.predict(sol, r_star, np.ones_like(r_star))
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(std)) and np.all(std >= 0)
    return sol


def assert_result_sane(res, n_points):
    assert res.ground_mask.shape == res.valid_mask.shape == (n_points,)
    assert not np.any(res.ground_mask & ~res.valid_mask)
    assert np.all(np.isfinite(res.ground_height[res.valid_mask]))
    assert all(np.isfinite(v) and v > 0 for v in res.hyperparameters)
    assert res.stats['cholesky_fallbacks'] >= 0 and res.stats['optimizer_failures'] in (0, 1)


# --------------------------------------------------------------------------------------------
# FrameGP directly
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize('density_rel', [1e-9, 1.0, 1e9])
def test_length_scale_factors_finite_and_clipped_for_special_slopes(density_rel):
    d = factors(density_rel)
    assert np.all(np.isfinite(d)) and np.all((d >= 1e-4) & (d <= 1e5))
    # slopes >= 1 (and +-inf) are steep: the shortest factor of their density, never <= 0
    slope = np.resize(SPECIAL_SLOPES, d.shape)
    steep = np.abs(np.nan_to_num(slope)) >= 1
    flat = np.nan_to_num(np.abs(slope), nan=0.0) <= 1e-6
    assert np.all(d[steep] <= d[flat].min())


@pytest.mark.parametrize('density_rel', [1e-9, 1e9])
@pytest.mark.parametrize('theta', CORNERS, ids=lambda t: 'sf{:g}-a{:g}-sn{:g}'.format(*t))
def test_frame_gp_at_theta_corners_and_density_extremes(theta, density_rel):
    r, z, mask = nasty_problem()
    gp = FrameGP(r, z, factors(density_rel), mask)
    with warnings.catch_warnings():
        warnings.simplefilter('error')  # no overflow / invalid-value warnings either
        assert_solution_finite(gp, theta)


def test_identical_candidates_make_cholesky_fall_back_and_count():
    # rows of identical (r, z, d) make K = sigma_f^2 * ones (rank one); at sigma_f = 1e3 m the
    # noise 1e-10 m^2 is below float64 resolution of 1e6: A is exactly singular.
    r, z, mask = nasty_problem()
    gp = FrameGP(r, z, np.ones_like(r), mask)
    sol = assert_solution_finite(gp, (1e3, 1e5, 1e-5))
    assert gp.cholesky_fallbacks >= 1 and sol.jitter > 0


def test_cholesky_jitter_grows_until_success_and_every_retry_is_counted(monkeypatch):
    r, z, mask = nasty_problem()
    gp = FrameGP(r, z, factors(1.0), mask, backend='numpy')  # inject into numpy's path
    real = np.linalg.cholesky
    added = []

    def flaky(a):
        # diagonal added on top of the first attempt's matrix = the jitter of this attempt
        added.append(float(np.min(np.diagonal(a, axis1=1, axis2=2)[gp.valid])))
        if len(added) <= 4:
            raise np.linalg.LinAlgError('injected')
        return real(a)
    monkeypatch.setattr(np.linalg, 'cholesky', flaky)
    sol = gp.solve((0.5, 2.0, 0.05))
    assert gp.cholesky_fallbacks == 4 and len(added) == 5
    assert all(b > a for a, b in zip(added, added[1:]))  # strictly growing jitter
    assert sol.jitter > 0 and np.isfinite(sol.lml)
    steps = np.diff(added)
    assert np.all(steps[1:] > 10 * steps[:-1])  # geometric growth, not a constant nudge


def test_fit_with_every_failure_mode_keeps_start(monkeypatch):
    r, z, mask = nasty_problem()
    gp = FrameGP(r, z, factors(1.0), mask)
    bounds = [SIGMA_F, GAIN, SIGMA_N]
    theta0 = np.array([0.5, 2.0, 0.05])
    for failure in ('nan', 'raise'):
        def objective(self, log_theta, failure=failure):
            if failure == 'raise':
                raise FloatingPointError('injected')
            return float('nan'), np.full(3, np.nan)
        monkeypatch.setattr(FrameGP, 'lml_and_gradient', objective)
        theta, info = gp.fit(theta0, bounds, 20)
        assert info['failed'] and np.array_equal(theta, theta0)


@pytest.mark.parametrize('theta0', CORNERS, ids=lambda t: 'sf{:g}-a{:g}-sn{:g}'.format(*t))
def test_fit_from_every_corner_stays_finite_and_in_bounds(theta0):
    r, z, mask = nasty_problem()
    gp = FrameGP(r, z, factors(1.0), mask)
    bounds = [SIGMA_F, GAIN, SIGMA_N]
    theta, info = gp.fit(theta0, bounds, 15)
    assert np.all(np.isfinite(theta))
    assert np.all(theta >= np.array(bounds)[:, 0] * (1 - 1e-9))
    assert np.all(theta <= np.array(bounds)[:, 1] * (1 + 1e-9))
    assert gp.solve(theta).lml >= gp.solve(np.asarray(theta0, float)).lml - 1e-6 * abs(
        gp.solve(np.asarray(theta0, float)).lml)


# --------------------------------------------------------------------------------------------
# GroundSegmenter on crafted clouds
# --------------------------------------------------------------------------------------------
def _ring(n, radius, z):
    a = np.linspace(-np.pi, np.pi, n, endpoint=False)
    return np.c_[radius * np.cos(a), radius * np.sin(a), np.broadcast_to(z, (n,))]


def _crafted_clouds():
    rng = np.random.default_rng(5)
    grid = np.stack(np.meshgrid(np.arange(1, 201), np.arange(-100, 100)), -1).reshape(-1, 2)
    ramp_r = np.linspace(1.0, 30.0, 4000)
    return {
        'one_ring_duplicate_r': _ring(6000, 10.0, rng.normal(-1.7, 0.05, 6000)),
        'same_point_repeated': np.tile([[5.0, 1.0, -1.7]], (1000, 1)),
        'single_point': np.array([[5.0, 1.0, -1.7]]),
        'two_points': np.array([[5.0, 1.0, -1.7], [6.0, 1.0, -1.7]]),
        'one_candidate_per_segment': _ring(120, 10.0, rng.normal(-1.7, 1.0, 120)),
        'all_candidates_equal': np.repeat(_ring(240, 8.0, -1.7), 5, axis=0),
        'slope_exactly_1': np.c_[ramp_r, np.zeros_like(ramp_r), ramp_r - 1.7],
        'slope_10': np.c_[ramp_r, 0.1 * np.sin(ramp_r), 10.0 * ramp_r],
        'vertical_wall': np.c_[np.full(3000, 5.0), np.repeat(np.linspace(-1, 1, 30), 100),
                               np.tile(np.linspace(-2.0, 5.0, 100), 30)],
        'offset_1e6_m': np.c_[grid + [1e6, 0.0], np.full(len(grid), -1.7)],
        'spacing_1e-6_m': np.c_[grid * 1e-6, rng.normal(0, 1e-7, len(grid))],
        'z_1e6_m': np.c_[grid * 0.1, np.where(np.arange(len(grid)) % 97 == 0, 1e6, -1.7)],
    }


CRAFTED = _crafted_clouds()


@pytest.mark.parametrize('dtype', [np.float32, np.float64])
@pytest.mark.parametrize('name', sorted(CRAFTED))
def test_crafted_clouds_never_raise(name, dtype):
    pts = CRAFTED[name].astype(dtype)
    seg = GroundSegmenter(SegmenterParams())
    for _ in range(2):  # cold start, then warm-started with the trust region
        res = seg.segment(pts)
        assert_result_sane(res, len(pts))
    assert res.valid_mask.all()


def test_real_scene_far_away_and_shrunk_still_labelled(ramp_points):
    base = GroundSegmenter().segment(ramp_points)
    for pts in (ramp_points.astype(np.float64) + [1e6, -1e6, 0.0],  # 1e6 m from the sensor
                ramp_points.astype(np.float64) * 1e-6):  # micrometre scene
        res = GroundSegmenter().segment(pts)
        assert_result_sane(res, len(pts))
        assert res.ground_mask.any()
    assert base.ground_mask.sum() > 0.3 * len(ramp_points)


@pytest.mark.parametrize('frozen', [True, False], ids=['frozen', 'learning'])
def test_segment_with_theta_at_every_bound_corner(ramp_points, frozen):
    evals = 0 if frozen else 5
    params = SegmenterParams().replace(optimizer_max_evaluations=evals,
                                       optimizer_first_frame_evaluations=evals, **WIDE)
    for corner in CORNERS:
        seg = GroundSegmenter(params, Hyperparameters(*corner))
        assert seg.hyperparameters == Hyperparameters(*corner)
        res = seg.segment(ramp_points)
        assert_result_sane(res, len(ramp_points))
        if frozen:
            assert res.hyperparameters == Hyperparameters(*corner)


@pytest.mark.parametrize('density_rel', [1e-9, 1e9])
def test_segment_with_extreme_relative_density(ramp_points, monkeypatch, density_rel):
    def extreme(log_r, log_rho, log_ratio):  # every usable bin's rho: density_rel
        return np.full(log_r.size, np.log(density_rel))
    monkeypatch.setattr(length_factors, 'RING', dataclasses.replace(
        length_factors.RING, reference=extreme, kernel=extreme, exact=False))
    params = SegmenterParams().replace(**WIDE)
    seg = GroundSegmenter(params)
    for _ in range(2):
        res = seg.segment(ramp_points)
        assert_result_sane(res, len(ramp_points))
        assert res.ground_mask.any()


@pytest.mark.parametrize('slope', [1.0, 3.0, np.inf, -np.inf, np.nan])
def test_segment_with_special_line_slopes(ramp_points, monkeypatch, slope):
    real = segmenter_module.extract_lines

    def special(*args, **kw):
        lines = real(*args, **kw)
        has = lines.line_id >= 0
        lines.slope[has & (np.arange(lines.slope.shape[1]) % 3 == 0)] = slope
        return lines
    monkeypatch.setattr(segmenter_module, 'extract_lines', special)
    seg = GroundSegmenter(SegmenterParams().replace(line_max_slope=100.0, **WIDE))
    for _ in range(2):
        res = seg.segment(ramp_points)
        assert_result_sane(res, len(ramp_points))
        assert res.ground_mask.any()


# --------------------------------------------------------------------------------------------
# Cholesky fallback counted in result.stats; optimiser failure keeps the last good theta
# --------------------------------------------------------------------------------------------
def _fail_first_cholesky_calls(monkeypatch, count):
    real = np.linalg.cholesky
    state = {'left': count}

    def flaky(a):
        if state['left'] > 0:
            state['left'] -= 1
            raise np.linalg.LinAlgError('injected')
        return real(a)
    # the compiled kernel (if used) reports every matrix as not PD: numpy's path runs

    def not_pd(r, *args):
        return (np.zeros(r.shape[0], dtype=bool),) + (None,) * 6
    monkeypatch.setattr(gp_module, 'SOLVE', dataclasses.replace(gp_module.SOLVE, kernel=not_pd))
    monkeypatch.setattr(np.linalg, 'cholesky', flaky)
    return state


@pytest.mark.parametrize('count', [1, 3, 5])
def test_cholesky_fallbacks_reach_result_stats(ramp_points, monkeypatch, count):
    seg = GroundSegmenter()
    clean = seg.segment(ramp_points)
    assert clean.stats['cholesky_fallbacks'] == 0
    state = _fail_first_cholesky_calls(monkeypatch, count)
    res = seg.segment(ramp_points)
    assert state['left'] == 0
    assert res.stats['cholesky_fallbacks'] == count
    assert_result_sane(res, len(ramp_points))
    # a retry with jitter (>= 1e-8 sigma_f^2) barely moves the answer
    assert np.mean(res.ground_mask == clean.ground_mask) > 0.99


def _fails(kind):
    def objective(self, log_theta):
        if kind == 'nan':
            return float('nan'), np.zeros(3)
        if kind == 'inf':
            return float('inf'), np.zeros(3)
        if kind == 'nan_gradient':
            return -1.0, np.full(3, np.nan)
        raise kind('injected')
    return objective


@pytest.mark.parametrize('kind', ['nan', 'inf', 'nan_gradient', np.linalg.LinAlgError,
                                  FloatingPointError, OverflowError, ZeroDivisionError,
                                  ValueError, RuntimeError],
                         ids=lambda k: k if isinstance(k, str) else k.__name__)
def test_failed_optimisation_keeps_last_good_theta(ramp_points, monkeypatch, kind):
    seg = GroundSegmenter(LEARN_EVERY_FRAME)  # the second frame learns
    good = seg.segment(ramp_points)
    assert good.stats['optimizer_failures'] == 0
    theta = seg.hyperparameters
    monkeypatch.setattr(FrameGP, 'lml_and_gradient', _fails(kind))
    res = seg.segment(ramp_points)
    assert seg.hyperparameters == theta and res.hyperparameters == theta
    assert res.stats['optimizer_failures'] == 1
    assert_result_sane(res, len(ramp_points))
    assert np.mean(res.ground_mask == good.ground_mask) > 0.99  # still labelled, same theta
    monkeypatch.undo()
    after = seg.segment(ramp_points)  # recovers once the objective is sane again
    assert after.stats['optimizer_failures'] == 0


def test_diverging_optimisation_keeps_last_good_theta(ramp_points, monkeypatch):
    """Sane at the start point, NaN/+inf likelihood anywhere else: theta must not move."""
    seg = GroundSegmenter(LEARN_EVERY_FRAME)  # the second frame learns
    seg.segment(ramp_points)
    theta = seg.hyperparameters
    real = FrameGP.lml_and_gradient
    start = np.log(np.asarray(theta, dtype=np.float64))
    calls = []

    def diverging(self, log_theta):
        calls.append(1)
        lml, grad = real(self, log_theta)
        if np.allclose(log_theta, start, rtol=0, atol=1e-12):
            return lml, grad
        return (float('inf') if len(calls) % 2 else float('nan')), grad
    monkeypatch.setattr(FrameGP, 'lml_and_gradient', diverging)
    res = seg.segment(ramp_points)
    assert len(calls) >= 2  # the optimiser did try to move
    assert seg.hyperparameters == theta and res.hyperparameters == theta
    assert_result_sane(res, len(ramp_points))


def test_failed_first_frame_optimisation_keeps_initial_theta(ramp_points, monkeypatch):
    seg = GroundSegmenter()
    theta = seg.hyperparameters
    monkeypatch.setattr(FrameGP, 'lml_and_gradient', _fails('nan'))
    res = seg.segment(ramp_points)
    assert res.stats['optimizer_failures'] == 1 and seg.hyperparameters == theta
    assert res.ground_mask.any()


# --------------------------------------------------------------------------------------------
# End to end: the counters reach the node's /diagnostics
# --------------------------------------------------------------------------------------------
def test_fallbacks_and_optimizer_failures_reach_node_diagnostics(ramp_points, monkeypatch,
                                                                 ros_harness):
    from rclpy.parameter import Parameter
    from std_msgs.msg import Header

    from gp_ground_segmentation.ros.cloud import make_cloud

    h = ros_harness(node_kwargs={'parameter_overrides': [
        Parameter('diagnostics_period_s', value=0.2),
        Parameter('optimizer_interval_frames', value=1)]})  # the second frame learns

    def frame(sec):
        header = Header(frame_id='crafted')
        header.stamp.sec = sec
        return make_cloud(header, ramp_points)

    # frame 1: two Cholesky failures inside the worker thread
    state = _fail_first_cholesky_calls(monkeypatch, 2)
    h.publish_and_wait(frame(1))
    assert state['left'] == 0
    status = h.wait_status(lambda s: status_values(s).get('frames_processed') == '1')
    assert status is not None
    values = status_values(status)
    assert values['cholesky_fallbacks'] == '2' and values['cholesky_fallbacks_window'] == '2'
    assert values['optimizer_failures'] == '0'
    theta = h.node.segmenter.hyperparameters
    assert values['sigma_f'] == f'{theta.sigma_f:.3f}'

    # frame 2: the theta search returns NaN everywhere -> counted, theta kept, frame published
    monkeypatch.undo()
    monkeypatch.setattr(FrameGP, 'lml_and_gradient', _fails('nan'))
    h.publish_and_wait(frame(2))
    status = h.wait_status(lambda s: status_values(s).get('frames_processed') == '2')
    assert status is not None
    values = status_values(status)
    assert values['optimizer_failures'] == '1' and values['optimizer_failures_window'] == '1'
    assert values['cholesky_fallbacks'] == '0' and values['cholesky_fallbacks_window'] == '2'
    assert h.node.segmenter.hyperparameters == theta
    assert values['frames_failed'] == '0'
    assert wait_for(lambda: len(h.ground) >= 2, 20.0)


@pytest.mark.parametrize('dtype, big', [(np.float32, 1e20), (np.float32, 3e38),
                                        (np.float64, 1e200), (np.float64, 1e300)])
def test_finite_coordinates_whose_square_overflows(ramp_points, dtype, big):
    # x*x overflows for these finite coordinates; the grid must still bin them (far, valid)
    pts = np.r_[ramp_points.astype(dtype), np.array([[big, 0.0, 0.0], [0.0, -big, 1.0]], dtype)]
    res = GroundSegmenter().segment(pts)
    assert_result_sane(res, len(pts))
    assert res.valid_mask.all()
    # only the two segments holding a far point lose resolution: the rest of the frame agrees
    base = GroundSegmenter().segment(ramp_points)
    assert np.mean(res.ground_mask[:-2] == base.ground_mask) > 0.9


# --------------------------------------------------------------------------------------------
# A broken compiled kernel: that segmenter falls back to numpy, no other is affected
# --------------------------------------------------------------------------------------------
@pytest.mark.skipif(not compiled.AVAILABLE, reason='numba not installed')
def test_broken_compiled_kernel_makes_that_segmenter_use_numpy(ramp_points, monkeypatch):
    params = SegmenterParams(optimizer_first_frame_evaluations=3)
    reference = GroundSegmenter(params, backend='numpy').segment(ramp_points)

    def broken(*args):
        raise RuntimeError('no LLVM here')
    monkeypatch.setattr(gp_module, 'SOLVE', dataclasses.replace(gp_module.SOLVE, kernel=broken))
    seg = GroundSegmenter(params, backend='numba')
    res = seg.segment(ramp_points)
    assert seg.backend == 'numpy'
    np.testing.assert_array_equal(res.ground_mask, reference.ground_mask)
    assert GroundSegmenter(params).backend == 'numba'  # a choice per segmenter, not global


@pytest.mark.skipif(not compiled.AVAILABLE, reason='numba not installed')
def test_failed_warm_up_switches_the_segmenter_to_numpy(ramp_points, monkeypatch):
    def broken(background_too=False):
        raise RuntimeError('no LLVM here')
    monkeypatch.setattr(stages, 'compile_round_off', broken)
    seg = GroundSegmenter(backend='auto')
    with pytest.raises(RuntimeError, match='no LLVM'):
        seg.warm_up()
    assert seg.backend == 'numpy'
    assert seg.segment(ramp_points).ground_mask.any()
    numpy_seg = GroundSegmenter(backend='numpy')
    numpy_seg.warm_up()  # nothing to compile: never fails


@pytest.mark.parametrize('gp_load_s, waits', [(0.0, True), (None, False)])
def test_warm_up_waits_for_background_stages_only_when_the_cache_was_filled(
        gp_load_s, waits, monkeypatch):
    """A GP step that loads fast (cache filled) -> wait for the background stages to load too;
    one that took longer than _GP_CACHE_LOAD_MAX_S (compiled: cache empty) -> no wait, since
    they are compiling and frames take their numpy twins meanwhile."""
    from gp_ground_segmentation.core import segmenter
    if not compiled.AVAILABLE:
        pytest.skip('numba not installed')
    slow = segmenter._GP_CACHE_LOAD_MAX_S + 0.05
    monkeypatch.setattr(stages, 'compile_round_off',
                        lambda background_too=False: time.sleep(slow if gp_load_s is None
                                                                else gp_load_s))
    calls = []
    monkeypatch.setattr(compiled, 'wait', lambda timeout_s=None: calls.append(timeout_s))
    GroundSegmenter().warm_up()
    assert (calls == [segmenter._BACKGROUND_WAIT_S]) is waits and (calls == []) is not waits
