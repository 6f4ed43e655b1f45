# SPDX-License-Identifier: Apache-2.0
"""Unit tests of SegmenterParams validation and describe_params (params.py).

Out-of-range values are generated from each field's own metadata (min/max), so the tests follow
the ranges instead of repeating them.
"""

import dataclasses

import pytest

from gp_ground_segmentation import SegmenterParams, describe_params

FIELDS = dataclasses.fields(SegmenterParams)
DEFAULTS = SegmenterParams()
# fields that take part in a cross-field rule of validate()
CROSS = {'slope_floor', 'slope_ceiling', 'min_length_factor', 'max_length_factor',
         'sigma_f_init_m', 'sigma_f_min_m', 'sigma_f_max_m', 'length_scale_gain_init',
         'length_scale_gain_min', 'length_scale_gain_max', 'sigma_n_init_m', 'sigma_n_min_m',
         'sigma_n_max_m', 'ground_threshold_m', 'max_threshold_m', 'structure_rise_m',
         'structure_max_height_m'}
RANGED = [f for f in FIELDS if f.metadata.get('min') is not None
          or f.metadata.get('max') is not None]
NUMERIC = [f for f in FIELDS if not isinstance(f.default, bool)]


def with_value(name, value):
    """A copy with one field changed, bypassing replace()'s own validation."""
    return dataclasses.replace(DEFAULTS, **{name: value})


def below(f):
    low = f.metadata['min']
    if isinstance(f.default, int):
        return low - 1
    return low / 2.0 if low > 0 else low - abs(f.default) - 1.0


def above(f):
    high = f.metadata['max']
    return high + 1 if isinstance(f.default, int) else high * 2.0 + 1.0


def test_defaults_validate():
    assert DEFAULTS.validate() is DEFAULTS
    for f in FIELDS:
        value = getattr(DEFAULTS, f.name)
        assert type(value) is type(f.default)
        low, high = f.metadata.get('min'), f.metadata.get('max')
        if low is not None:
            assert value >= low, f.name
        if high is not None:
            assert value <= high, f.name


def test_every_numeric_field_has_a_range():
    assert {f.name for f in NUMERIC} == {f.name for f in RANGED}
    for f in RANGED:
        assert f.metadata['min'] < f.metadata['max'], f.name


@pytest.mark.parametrize('f', RANGED, ids=lambda f: f.name)
def test_out_of_range_raises_naming_the_field(f):
    for value in (below(f), above(f)):
        with pytest.raises(ValueError) as exc:
            with_value(f.name, value).validate()
        assert str(exc.value).startswith(f'{f.name}:'), str(exc.value)
        with pytest.raises(ValueError, match=f'^{f.name}:'):
            DEFAULTS.replace(**{f.name: value})


@pytest.mark.parametrize('f', [f for f in RANGED if f.name not in CROSS], ids=lambda f: f.name)
def test_range_ends_are_inclusive(f):
    for value in (f.metadata['min'], f.metadata['max']):
        value = type(f.default)(value)
        assert DEFAULTS.replace(**{f.name: value}) == with_value(f.name, value)


@pytest.mark.parametrize('f', FIELDS, ids=lambda f: f.name)
def test_wrong_types_raise(f):
    bad = ['1', None, [1], float('nan')]
    if isinstance(f.default, bool):
        bad += [1, 0, 1.0]
    elif isinstance(f.default, int):
        bad += [True, False, float(f.default), 2.5]
    else:
        bad += [True, False, float('inf'), float('-inf')]
    for value in bad:
        with pytest.raises(ValueError, match=f'^{f.name}:'):
            with_value(f.name, value).validate()


def test_int_accepted_for_float_fields():
    # YAML and ROS may hand over 1 for 1.0
    assert DEFAULTS.replace(ground_threshold_m=0).ground_threshold_m == 0


@pytest.mark.parametrize('changes,field', [
    (dict(slope_floor=0.5, slope_ceiling=0.4), 'slope_floor'),
    (dict(slope_floor=0.5, slope_ceiling=0.5), 'slope_floor'),
    (dict(min_length_factor=5.0, max_length_factor=5.0), 'min_length_factor'),
    (dict(min_length_factor=20.0, max_length_factor=10.0), 'min_length_factor'),
    (dict(sigma_f_min_m=5.0, sigma_f_max_m=1.0, sigma_f_init_m=2.0), 'sigma_f_min_m'),
    (dict(length_scale_gain_min=3.0, length_scale_gain_max=3.0, length_scale_gain_init=3.0),
     'length_scale_gain_min'),
    (dict(sigma_n_min_m=0.5, sigma_n_max_m=0.1, sigma_n_init_m=0.2), 'sigma_n_min_m'),
    (dict(sigma_f_init_m=30.0), 'sigma_f_init_m'),
    (dict(sigma_f_init_m=0.005), 'sigma_f_init_m'),
    (dict(length_scale_gain_init=500.0), 'length_scale_gain_init'),
    (dict(length_scale_gain_init=0.01), 'length_scale_gain_init'),
    (dict(sigma_n_init_m=3.0), 'sigma_n_init_m'),
    (dict(sigma_n_init_m=0.001), 'sigma_n_init_m'),
    (dict(ground_threshold_m=0.5), 'ground_threshold_m'),
    (dict(ground_threshold_m=0.2, max_threshold_m=0.1), 'ground_threshold_m'),
    (dict(structure_rise_m=0.7), 'structure_rise_m'),
    (dict(structure_rise_m=0.3, structure_max_height_m=0.2), 'structure_rise_m'),
])
def test_cross_field_rules(changes, field):
    # every value alone is inside its own range: only the cross-field rule can reject it
    for name, value in changes.items():
        f = next(f for f in FIELDS if f.name == name)
        assert f.metadata['min'] <= value <= f.metadata['max']
    with pytest.raises(ValueError, match=f'^{field}:'):
        dataclasses.replace(DEFAULTS, **changes).validate()


def test_ground_threshold_is_never_capped_silently():
    # issue 10, bug 8: 0.3, 0.5 and 2.0 used to give the same labels (all cut to the 0.3 cap)
    # while the node accepted up to 10. Now a threshold above the cap is refused, and the
    # message says which parameter to change first (ros2 param set takes one at a time).
    with pytest.raises(ValueError, match=r'^ground_threshold_m: .*raise max_threshold_m too '
                       r'\(with ros2 param set, first\)'):
        DEFAULTS.replace(ground_threshold_m=2.0)
    raised = DEFAULTS.replace(max_threshold_m=2.0).replace(ground_threshold_m=2.0)
    assert raised.ground_threshold_m == 2.0
    assert DEFAULTS.replace(ground_threshold_m=DEFAULTS.max_threshold_m).ground_threshold_m \
        == DEFAULTS.max_threshold_m


def test_cross_field_rules_accept_inits_on_their_bounds():
    p = DEFAULTS.replace(sigma_f_init_m=DEFAULTS.sigma_f_min_m,
                         length_scale_gain_init=DEFAULTS.length_scale_gain_max,
                         sigma_n_init_m=DEFAULTS.sigma_n_max_m)
    assert p.sigma_f_init_m == DEFAULTS.sigma_f_min_m
    assert DEFAULTS.replace(slope_floor=0.1, slope_ceiling=0.1 + 1e-9).slope_floor == 0.1


def test_replace_is_validated_frozen_and_rejects_unknown_names():
    p = DEFAULTS.replace(num_bins=64)
    assert p.num_bins == 64 and DEFAULTS.num_bins != 64
    with pytest.raises(TypeError):
        DEFAULTS.replace(no_such_parameter=1)
    with pytest.raises(dataclasses.FrozenInstanceError):
        DEFAULTS.num_bins = 10  # noqa: B003 -- the point of the test


# --------------------------------------------------------------------------------------------
# describe_params
# --------------------------------------------------------------------------------------------
def test_describe_params_lists_every_field():
    rows = describe_params()
    assert [row['name'] for row in rows] == [f.name for f in FIELDS]
    for row, f in zip(rows, FIELDS):
        assert set(row) >= {'name', 'default', 'type', 'description', 'min', 'max'}
        assert row['default'] == f.default == getattr(DEFAULTS, f.name)
        assert row['type'] in ('int', 'float', 'bool')
        type_name = type(f.default).__name__
        assert row['type'] == type_name
        assert row['min'] == f.metadata.get('min') and row['max'] == f.metadata.get('max')
        assert isinstance(row['description'], str) and len(row['description'].split()) >= 4


# Words that state a unit (or that the quantity has none) in a description.
UNIT_TOKENS = ('(m)', '(m ', 'm per', 'dimensionless', 'ratio', 'factor', 'multiplier',
               'dz/dr', 'slope', 'degrees', '(rad')


def _unit_cases():
    cases = []
    for f in FIELDS:
        if not isinstance(f.default, float):
            continue  # ints are counts, the bool is a switch
        cases.append(pytest.param(f, id=f.name))
    return cases


@pytest.mark.parametrize('f', _unit_cases())
def test_describe_params_states_units(f):
    row = next(row for row in describe_params() if row['name'] == f.name)
    text = row['description']
    if f.name.endswith('_m'):
        assert '(m)' in text, text  # metres, said explicitly
    else:
        assert any(token in text for token in UNIT_TOKENS), text


# --- one switch convention; an earlier version's keys and values ----------------------------

def test_every_addition_is_a_use_switch_of_the_stage_table():
    """Every use_* field is a bool that switches a row of the stage table (core/stages.py),
    every switch of the table is a use_* bool field, and no number turns a rule off: the values
    that did (RETIRED_OFF_VALUES) lie outside their fields' ranges now."""
    from gp_ground_segmentation.core import params, stages
    use_fields = {f.name for f in FIELDS if f.name.startswith('use_')}
    assert all(isinstance(getattr(DEFAULTS, name), bool) for name in use_fields)
    switches = {stage.switch for stage in stages.STAGES if stage.switch is not None}
    assert switches == use_fields
    assert all(stage.origin in ('paper', 'ours') for stage in stages.STAGES)
    # our additions can be switched off; of the paper's stages only the non-stationary length
    # scale, whose alternative (one length factor) the cross-validation chose
    assert all(stage.origin == 'ours' for stage in stages.STAGES
               if stage.switch and stage.switch != 'use_nonstationary_length_scale')
    meta = {f.name: f.metadata for f in FIELDS}
    for name, (off, switch) in params.RETIRED_OFF_VALUES.items():
        assert not meta[name]['min'] <= off <= meta[name]['max'] and switch in use_fields


@pytest.mark.parametrize('change, words', [
    ({'outlier_wide_terrain_m': 0.0}, ['outlier_wide_terrain_m: 0.0', 'use_wide_terrain_rule']),
    ({'length_factor_smoothing_passes': 0},
     ['length_factor_smoothing_passes: 0', 'use_length_factor_smoothing']),
    ({'outlier_std_factor': 0.0}, ['outlier_std_factor: 0.0', 'use_outlier_std_limit']),
])
def test_an_old_off_value_names_its_switch_in_one_line(change, words):
    for make in (lambda: SegmenterParams(**change).validate(), lambda: DEFAULTS.replace(**change)):
        with pytest.raises(ValueError) as exc:
            make()
        assert all(word in str(exc.value) for word in words) and '\n' not in str(exc.value)


def test_an_old_key_names_what_replaced_it_in_one_line():
    for make in (lambda: SegmenterParams(ground_threshold_std_factor=1.0),
                 lambda: DEFAULTS.replace(ground_threshold_std_factor=0.0)):
        with pytest.raises(TypeError) as exc:
            make()
        message = str(exc.value)
        assert message.startswith('ground_threshold_std_factor: replaced by use_std_threshold')
        assert 'std_threshold_factor' in message and '\n' not in message
    assert SegmenterParams(use_std_threshold=True, std_threshold_factor=1.0).validate()
