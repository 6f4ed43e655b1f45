# SPDX-License-Identifier: Apache-2.0
"""The stage table (core/stages.py): every compiled twin against its numpy reference.

No kernel is listed here: the test iterates ``stages.twins()``. Frames (real scans, a synthetic
scene and family member, under the default parameters, every switch flipped, the options
flipped and a sensor pose) are segmented with every twin's arguments recorded; the frames run
the numpy references (so that twins reached only from another twin's reference, such as the
wide-terrain loop, are recorded too). Then every twin's kernel runs on the recorded arguments
and must give its reference's outputs: bit for bit (dtypes too) for an exact twin, to
round-off for the GP step's. A twin no frame reached fails the test: a new row of the table
is tested as soon as it is registered.
"""

import copy
from collections import defaultdict

import numpy as np
import pytest
from conftest import DATA

from gp_ground_segmentation import GroundSegmenter, SegmenterParams
from gp_ground_segmentation.core import compiled, stages

pytestmark = pytest.mark.skipif(not compiled.AVAILABLE, reason='numba not installed')

# calls kept per twin (spread over the frames: the first of each frame and parameter set)
_CALLS_PER_TWIN = 12
# the GP step's twins: LAPACK against loops. The std sqrt(sigma_f^2 - k*^T A^-1 k*) cancels
# where it is small: another summation order moves it by up to ~2e-7 m there
_ROUND_OFF = dict(rtol=1e-6, atol=1e-6)


def _frames():
    """(name, points) of the recorded frames: real scans of three sensors (one organised, with
    (0, 0, 0) no-returns), a synthetic scene in float32 and an organised 16-beam family member."""
    from gp_ground_segmentation.tools.io import read_points_file
    from scenes import synthetic
    for name in ('sensors/velodyne_vlp16.pcd', 'kitti_sequnknown_spvnas_000000.bin',
                 'labeled/rellis3d_examplebundle_000001.bin'):
        if (DATA / name).exists():
            arr = read_points_file(DATA / name)
            yield name, np.stack([arr[c].astype(np.float32) for c in 'xyz'], axis=1)
    yield 'mixed', synthetic.scan_scene('mixed').points[:, :3].astype(np.float32)
    member = synthetic.family_scene('beams16', 0)
    yield 'beams16', synthetic.simulate_scan(member.scene, seed=0, **member.scan_kwargs).points


def _parameter_sets():
    defaults = SegmenterParams()
    flipped = {f: not getattr(defaults, f) for f in ('use_chord_slope_for_single_points',
                                                     'use_anchor', 'use_cross_slope_threshold',
                                                     'use_std_threshold', 'use_wide_terrain_rule',
                                                     'use_density_ring_normalisation',
                                                     'use_coupled_surface',
                                                     'use_free_space_feet',
                                                     'use_nonstationary_length_scale')}
    return [defaults, defaults.replace(**flipped),
            defaults.replace(use_outlier_std_limit=False, use_elevated_plateaus=False,
                             use_length_factor_smoothing=False, use_outlier_rejection=False,
                             use_vertical_structure_test=False,
                             use_nonstationary_length_scale=True),
            defaults.replace(plateau_ends_on_drop=True, plateau_from_sensor_ground=False,
                             outlier_worst_per_segment=True, density_in_flat_branch=True,
                             prior_mean_at_anchor=False),
            defaults.replace(sensor_x_m=0.4, sensor_z_m=0.3, sensor_roll_rad=0.02,
                             sensor_pitch_rad=-0.03)]


@pytest.fixture(scope='module')
def recorded():
    """twin -> [arguments], recorded from frames that run the numpy references."""
    calls = defaultdict(list)
    original = compiled.Twin.run

    def recording(twin, use_compiled, *args):
        if len(calls[twin]) < _CALLS_PER_TWIN and frame_key not in seen[twin]:
            seen[twin].add(frame_key)
            calls[twin].append(copy.deepcopy(args))
        return original(twin, False, *args)

    seen = defaultdict(set)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(compiled.Twin, 'run', recording)
        for name, points in _frames():
            for k, params in enumerate(_parameter_sets()):
                frame_key = (name, k)
                with np.errstate(all='ignore'):  # without details, z_std is read later
                    result = GroundSegmenter(params).segment(points, details=k % 2 == 1)
                    result.ground_surface.points()
    return calls


def _assert_same(ours, reference, exact, where):
    """Outputs equal: tuples and lists element by element, arrays by dtype and value (NaN
    equal to NaN), scalars by value; to round-off unless ``exact``."""
    if isinstance(reference, (tuple, list)):
        assert isinstance(ours, (tuple, list)) and len(ours) == len(reference), where
        for i, (a, b) in enumerate(zip(ours, reference)):
            _assert_same(a, b, exact, f'{where}[{i}]')
    elif reference is None:
        assert ours is None, where
    elif exact:
        a, b = np.asarray(ours), np.asarray(reference)
        assert a.dtype == b.dtype and a.shape == b.shape, (where, a.dtype, b.dtype)
        np.testing.assert_array_equal(a, b, err_msg=where)
    else:
        np.testing.assert_allclose(np.asarray(ours, dtype=float),
                                   np.asarray(reference, dtype=float), err_msg=where,
                                   **_ROUND_OFF)


@pytest.mark.parametrize('twin', stages.twins(), ids=lambda twin: twin.name)
def test_every_twin_equals_its_reference_on_real_frames(recorded, twin):
    assert twin.kernel is not None
    assert recorded[twin], f'no frame reached {twin.name!r}: add a frame or parameter set'
    for n, args in enumerate(recorded[twin]):
        with np.errstate(all='ignore'):
            reference = twin.reference(*copy.deepcopy(args))
            ours = twin.kernel(*copy.deepcopy(args))
        if twin.outputs is not None:  # the kernel leaves scratch in some of its outputs
            ours, reference = twin.outputs(args, ours), twin.outputs(args, reference)
        _assert_same(ours, reference, twin.exact, f'{twin.name} call {n}')
    assert not compiled.failed(twin.kernel)


@pytest.mark.parametrize('twin', stages.twins(), ids=lambda twin: twin.name)
def test_every_twin_runs_its_warm_up_examples(twin):
    """The examples warm_up compiles are valid arguments: both sides run them, alike."""
    for dtype in stages.POINT_DTYPES:
        for args in twin.examples(dtype):
            with np.errstate(all='ignore'):
                reference = twin.reference(*copy.deepcopy(args))
                ours = twin.kernel(*copy.deepcopy(args))
            if twin.outputs is not None:
                ours, reference = twin.outputs(args, ours), twin.outputs(args, reference)
            _assert_same(ours, reference, twin.exact, f'{twin.name} example')
