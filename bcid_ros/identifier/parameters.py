"""
The parameter tables of the identifier and simulator nodes (pure Python, no ROS).

One table per node lists every parameter: name, type, default, description,
allowed values or range, and whether it may change while the node runs. The
nodes declare their ROS parameters from these tables, and the offline tools
(``bcid replay``) take their defaults from the same tables, so a parameter
file builds the same estimator online and offline:

>>> values = check_identifier_parameters(load_yaml_parameters('config/ding_miso.yaml'))
>>> estimator = estimator_from_parameters(values)

The estimator-specific options (docs/nodes.md: ``iv_lag``, ... for
``bciv``; ``controller_numerator``, ... for ``cl_bcls``; ``model`` for
``rpem``) default to
``None``, which means "the estimator class's own default": they are only
passed to the constructor when set, and the constructor validates them.
"""

from __future__ import annotations

import inspect
from typing import Any

from bcid_ros.estimators import RecursiveEstimator
from bcid_ros.estimators.registry import (entry, ESTIMATOR_NAMES, estimator_class, INPUT_MODES,
                                          names_where, option_specs)
from bcid_ros.estimators.settings import SHARED_SETTINGS
from bcid_ros.identifier.interface import (check_input_width, INPUT_TYPES, MESSAGE_TYPES,
                                           OUTPUT_TYPES)
from bcid_ros.parameter_spec import (check_parameters, load_yaml_parameters, markdown_table,
                                     parameter as _p, ParameterSpec, spec_by_name)
from bcid_ros.simulation import SCENARIOS

#: The keyword arguments of every estimator's base constructor.
BASE_SETTINGS = tuple(SHARED_SETTINGS)

#: The JointState field of y when ``output_field`` is empty, by ``input_mode``.
OUTPUT_FIELD_DEFAULTS = {'combined': 'position', 'separate': 'position',
                         'joint_state': 'velocity'}

#: The identifier node's parameters (docs/nodes.md), in declaration order.
IDENTIFIER_PARAMETERS: tuple[ParameterSpec, ...] = (
    # --- the estimator and the model structure
    _p('estimator', 'string', 'bcrls', 'Estimator, by its registry name '
       '(docs/estimators.md describes each).', choices=ESTIMATOR_NAMES),
    *SHARED_SETTINGS.values(),
    # --- beside a real plant
    _p('freeze_unexcited', 'bool', False, 'Hold the adaptation while the input has not '
       'changed for excitation_window samples (instead of only warning).'),
    # --- node: input topics, pairing, publishing
    _p('input_mode', 'string', 'combined', 'combined: y and u in one Float64MultiArray on '
       'samples (single samples or frames). separate: u on input and y on output. '
       'joint_state: one estimator per joint of joints, fed from joint_states.',
       choices=INPUT_MODES),
    _p('joints', 'string_array', [], 'joint_state mode (required there): the joint names, one '
       'single-input estimator each; each name becomes a topic token (letters, digits, _).'),
    _p('sync', 'string', 'arrival', 'Separate mode pairing: arrival (FIFO in arrival order) or '
       'stamp (header stamps equal within sync_tolerance; needs JointState).',
       choices=('arrival', 'stamp')),
    _p('sync_tolerance', 'double', 0.001, 'Stamp pairing: largest stamp difference (s) of a '
       'pair.', low=0.0, high=3600.0),
    _p('queue_size', 'integer', 100, 'Separate mode: most unpaired messages kept per topic; '
       'the oldest is dropped (and counted) beyond it.', low=1, high=1000000),
    _p('sample_period', 'double', 0.0, 'Stamp mode: nominal sample period (s) used to detect '
       'gaps (an interval above 1.5 periods restarts the regressor). 0: the median of the '
       'first 20 intervals.', low=0.0, high=3600.0),
    _p('input_type', 'string', 'float64', 'Separate mode: type of the input topic.',
       choices=INPUT_TYPES),
    _p('output_type', 'string', 'float64', 'Separate mode: type of the output topic.',
       choices=OUTPUT_TYPES),
    _p('input_joints', 'string_array', [], 'JointState input: joint names of u1..ur, in order '
       '(empty: the first r entries).'),
    _p('input_field', 'string', 'effort', 'JointState input (separate and joint_state '
       'modes): the field holding u.', choices=('position', 'velocity', 'effort')),
    _p('output_joint', 'string', '', 'JointState output: joint name of y (empty: the first '
       'entry).'),
    _p('output_field', 'string', '', 'JointState output: the field holding y. Empty: '
       'position in separate mode, velocity in joint_state mode.',
       choices=('', 'position', 'velocity', 'effort')),
    _p('publish_period', 'integer', 1, 'Publish the estimates every this many samples. May be '
       'changed while running.', low=1, high=1000000, read_only=False),
    _p('excitation_window', 'integer', 200, 'Warn (and count) when the input has not changed '
       'for this many samples (no excitation); 0 turns the check off.', low=0, high=1e9),
    _p('stale_after', 'double', 0.0, 'Seconds without a sample after which ~/valid turns '
       'false (reason: no samples for T s), true again when samples resume. 0: automatic, '
       'ten times the median interval between recent samples and at least 1 s; negative: '
       'never.', low=-1e9, high=1e9),
    # --- the adaptive loop
    _p('controller_topic', 'string', '', 'cl_bcls only: take the controller in the loop from '
       'this topic (Float64MultiArray, latched; numerator then denominator in descending '
       'powers of q, as the adaptive controller\'s ~/controller) and restart the compensation '
       'at every change. Empty: the controller is fixed by controller_numerator/'
       'controller_denominator.'),
    # --- keeping the state across restarts
    _p('state_file', 'string', '', 'File that keeps the estimator state across restarts: '
       'saved atomically every state_save_period and at shutdown, restored at start-up if it '
       'matches the configuration. Empty: off.'),
    _p('state_save_period', 'double', 10.0, 'Seconds between saves of state_file.',
       low=0.0, high=86400.0, low_open=True),
    # --- the estimators' own options (from the estimator registry)
    *option_specs(),
)

#: The simulator node's parameters (docs/nodes.md), in declaration order.
SIMULATOR_PARAMETERS: tuple[ParameterSpec, ...] = (
    _p('scenario', 'string', 'ding_miso', 'The papers\' scenarios, custom (plant, noise and '
       'input given by the custom parameters below), or joints (num_joints random plants on '
       'joint_states).', choices=tuple(SCENARIOS)),
    _p('rate_hz', 'double', 100.0, 'Samples per second.', low=0.0, high=1e6, low_open=True),
    _p('seed', 'integer', 0, 'Seed of the random generator; the same seed gives the same '
       'data at any rate and frame size.', low=0, high=2 ** 63 - 1),
    _p('num_samples', 'integer', 0, 'Samples to publish before exiting; 0 runs forever.',
       low=0, high=1e12),
    _p('frame_size', 'integer', 1, 'Samples per samples message (k > 1: frames, see '
       'docs/nodes.md).', low=1, high=100000),
    _p('output_mode', 'string', 'combined', 'combined: samples topic; separate: input and '
       'output topics; both: all three.', choices=('combined', 'separate', 'both')),
    _p('input_type', 'string', 'float64_multi_array', 'Type of the input topic (float64 only '
       'for one input).', choices=INPUT_TYPES),
    _p('output_type', 'string', 'float64', 'Type of the output topic.', choices=OUTPUT_TYPES),
    _p('start_delay', 'double', 0.5, 'Seconds to wait after start-up before the first sample, '
       'so that subscribers can connect.', low=0.0, high=3600.0),
    _p('wait_for_subscribers', 'integer', 0, 'Before the first sample, wait until the samples '
       '(or output) topic has this many subscribers.', low=0, high=1000),
    # --- the joints scenario
    _p('num_joints', 'integer', 6, 'joints: number of joints K, each an independent random '
       'stable second-order plant drawn from seed.', low=1, high=100000),
    _p('joints', 'string_array', [], 'joints: the joint names, num_joints of them (empty: '
       'joint_1 ... joint_K).'),
    # --- the custom scenario
    _p('plant_denominator', 'double_array', [1.0, -0.8], 'custom: A(z) = 1 + a1 z^-1 + ... + '
       'an z^-n, as [1, a1, ..., an].'),
    _p('plant_numerator', 'double_array', [0.0, 0.5], 'custom: B_i(z) = b_i0 + b_i1 z^-1 + '
       '... + b_in z^-n for each input, concatenated: r (n + 1) numbers.'),
    _p('noise_numerator', 'double_array', [1.0], 'custom: C(z) of the output noise '
       'v = C/D e, as [1, c1, ...].'),
    _p('noise_denominator', 'double_array', [1.0], 'custom: D(z) of the output noise, as '
       '[1, d1, ...].'),
    _p('noise_variance', 'double', 0.01, 'custom: variance of the white e driving the output '
       'noise.', low=0.0, high=1e12),
    _p('equation_error', 'bool', False, 'custom: add the noise as A y = B u + v (equation '
       'error) instead of y = B/A u + v (output error).'),
    _p('input_signal', 'string', 'white', 'custom: white (Gaussian) or binary (random +-1 '
       'held for input_hold samples), times sqrt(input_variance), then input_numerator/'
       'input_denominator.', choices=('white', 'binary')),
    _p('input_variance', 'double', 1.0, 'custom: variance of the input driving signal.',
       low=0.0, high=1e12),
    _p('input_hold', 'integer', 1, 'custom: samples each binary level is held.',
       low=1, high=1e9),
    _p('input_numerator', 'double_array', [1.0], 'custom: numerator of the input colouring '
       'filter.'),
    _p('input_denominator', 'double_array', [1.0], 'custom: denominator of the input '
       'colouring filter.'),
    _p('input_noise_variance', 'double', 0.0, 'custom: variance of white measurement noise '
       'added to the published inputs (errors in variables).', low=0.0, high=1e12),
    _p('input_delay', 'integer_array', [0], 'custom: dead time d_i of each input in samples '
       '(one integer for all inputs or one per input).', low=0, high=100000),
    _p('input_offset', 'double_array', [0.0], 'custom: operating point u0_i of each input '
       '(one number or one per input): y = y0 + B/A (u - u0) + v.'),
    _p('output_offset', 'double', 0.0, 'custom: operating point y0 of the output.'),
    # --- plant mode: the plant in a loop (docs/adaptive_loop.md)
    _p('mode', 'string', 'open_loop', 'open_loop: the scenario draws its own inputs. plant '
       '(custom only): the input is read from the input topic and held (zero-order hold, 0 '
       'until the first command); samples [y, u] and output are published at rate_hz.',
       choices=('open_loop', 'plant')),
    _p('change_after_samples', 'integer', 0, 'custom scenario (either mode): after this many '
       'samples the plant becomes plant_denominator_after / plant_numerator_after and the truth '
       'topics are published again; 0: no change.', low=0, high=1e12),
    _p('plant_denominator_after', 'double_array', [], 'custom scenario: A(z) after the change, '
       'as [1, a1, ..., an] (empty: unchanged).'),
    _p('plant_numerator_after', 'double_array', [], 'custom scenario: B_i(z) after the change, '
       'concatenated as plant_numerator (empty: unchanged).'),
    _p('lockstep', 'bool', False, 'plant mode: before each sample, wait (up to 1 s) for the '
       'command computed from the previous output, so that a slow controller never misses '
       'a sample (a simulation in step with the controller, not real time).'),
)

#: Custom-plant settings beyond CUSTOM_SETTINGS: dead time and operating point.
OPERATING_POINT_SETTINGS = ('input_delay', 'input_offset', 'output_offset')

#: The custom scenario's parameter names (passed to CustomScenario).
CUSTOM_SETTINGS = ('plant_denominator', 'plant_numerator', 'noise_numerator',
                   'noise_denominator', 'noise_variance', 'equation_error', 'input_signal',
                   'input_variance', 'input_hold', 'input_numerator', 'input_denominator',
                   'input_noise_variance', 'input_delay', 'input_offset', 'output_offset')

#: Parameters that may change while the identifier runs.
IDENTIFIER_LIVE = tuple(p.name for p in IDENTIFIER_PARAMETERS if not p.read_only)


def check_identifier_parameters(values: dict[str, Any]) -> dict[str, Any]:
    """
    Check identifier parameters and return all of them, defaults filled in.

    Besides each parameter's own range this checks that the estimator is
    installed and that ``sync: stamp`` has stamped topic types. Options of
    other estimators are allowed (so that ``--estimator`` can override a
    file) and ignored by :func:`estimator_settings`.

    Parameters
    ----------
    values : dict
        ``{name: value}``, e.g. from :func:`load_yaml_parameters`.

    Returns
    -------
    dict
        Every parameter of :data:`IDENTIFIER_PARAMETERS`.

    Raises
    ------
    ValueError
        Naming the parameter and its allowed values.

    """
    checked = check_parameters(values, IDENTIFIER_PARAMETERS)
    if checked['input_mode'] == 'separate':
        check_input_width(checked['input_type'], checked['num_inputs'])
        if checked['sync'] == 'stamp':
            stamped = [name for name, kind in MESSAGE_TYPES.items() if kind.stamped]
            for name in ('input_type', 'output_type'):
                if not MESSAGE_TYPES[checked[name]].stamped:
                    raise ValueError(f'parameter {name!r} must be a stamped type (one of '
                                     f'{", ".join(stamped)}) with sync: stamp, got '
                                     f'{checked[name]!r}')
    if not checked['output_field']:
        checked['output_field'] = OUTPUT_FIELD_DEFAULTS[checked['input_mode']]
    if checked['input_mode'] == 'joint_state':
        _check_joint_state_parameters(checked)
    delays = checked['input_delay']
    if len(delays) not in (1, checked['num_inputs']):
        raise ValueError(f"parameter 'input_delay' must have one integer or num_inputs = "
                         f"{checked['num_inputs']} integers, got {delays!r}")
    if checked['controller_topic'] and not entry(checked['estimator']).takes_controller:
        takers = ', '.join(names_where(takes_controller=True))
        raise ValueError(f"parameter 'controller_topic' applies to estimator {takers} only "
                         f"(it identifies under a known controller), got estimator "
                         f"{checked['estimator']!r} with controller_topic "
                         f"{checked['controller_topic']!r}")
    if not entry(checked['estimator']).supports_delay and any(delays):
        raise ValueError(f"parameter 'input_delay' must be 0 with estimator "
                         f"{checked['estimator']!r} (no dead time in its model), got {delays!r}")
    if checked['input_joints'] and len(checked['input_joints']) != checked['num_inputs']:
        raise ValueError(f"parameter 'input_joints' must have num_inputs = "
                         f"{checked['num_inputs']} names (or none), got "
                         f"{checked['input_joints']!r}")
    estimator_options(checked['estimator'])  # raises if the estimator is not installed
    return checked


def _check_joint_state_parameters(checked: dict[str, Any]) -> None:
    """Check what ``input_mode: joint_state`` needs: names, a batched estimator, one input."""
    from bcid_ros.identifier.joint_feeder import check_joint_names

    check_joint_names(checked['joints'])
    batched = names_where(input_modes='joint_state')
    if checked['estimator'] not in batched:
        raise ValueError(f"parameter 'estimator' must be one of {', '.join(batched)} "
                         f"with input_mode: joint_state (the estimators with a batched form), "
                         f"got {checked['estimator']!r}")
    if checked['num_inputs'] != 1:
        raise ValueError(f"parameter 'num_inputs' must be 1 with input_mode: joint_state (one "
                         f"single-input estimator per joint), got {checked['num_inputs']}")
    if checked['input_field'] == checked['output_field']:
        raise ValueError(f"parameters 'input_field' and 'output_field' must differ with "
                         f"input_mode: joint_state, both are {checked['input_field']!r}")


def estimator_options(name: str) -> tuple[str, ...]:
    """
    Return the options (own constructor keywords, ROS parameter names) of estimator ``name``.

    Raises
    ------
    ValueError
        If ``name`` is not a registered estimator or its module is missing.

    """
    options = entry(name).option_names
    try:
        estimator_class(name)
    except ImportError as error:
        raise ValueError(f'parameter \'estimator\': {name!r} is not available in this '
                         f'installation ({error})') from None
    return options


def unused_options(values: dict[str, Any]) -> list[str]:
    """Return the estimator options that are set but do not apply to the estimator."""
    options = estimator_options(values['estimator'])
    return [spec.name for spec in IDENTIFIER_PARAMETERS
            if spec.default is None and values.get(spec.name) is not None
            and spec.name not in options]


def estimator_settings(values: dict[str, Any]) -> dict[str, Any]:
    """
    Return the constructor keywords of the configured estimator.

    These are the base settings plus those of the estimator's registry options that
    are set (not ``None``).

    Raises
    ------
    ValueError
        If an option the estimator requires (e.g. ``controller_numerator``
        for ``cl_bcls``) is not set.

    """
    settings = {name: values[name] for name in BASE_SETTINGS}
    for name in estimator_options(values['estimator']):
        if values.get(name) is not None:
            settings[name] = values[name]
    signature = inspect.signature(estimator_class(values['estimator']))
    for name, argument in signature.parameters.items():
        if argument.default is inspect.Parameter.empty and name not in settings and \
                argument.kind is inspect.Parameter.KEYWORD_ONLY:
            raise ValueError(f'parameter {name!r} is required by estimator '
                             f'{values["estimator"]!r} and not set')
    return settings


def estimator_from_parameters(values: dict[str, Any]) -> RecursiveEstimator:
    """
    Build the estimator that the identifier node builds from the same parameters.

    Parameters
    ----------
    values : dict
        Parameters; checked (and defaults filled) with
        :func:`check_identifier_parameters` first.

    Returns
    -------
    RecursiveEstimator
        A fresh estimator.

    Raises
    ------
    ValueError
        If a parameter is not allowed (named in the message).

    """
    checked = check_identifier_parameters(values)
    return estimator_class(checked['estimator'])(**estimator_settings(checked))


def check_simulator_parameters(values: dict[str, Any]) -> dict[str, Any]:
    """
    Check simulator parameters and return all of them, defaults filled in.

    A bad value raises the ValueError of :func:`check_identifier_parameters`,
    naming the parameter and its allowed values.
    """
    checked = check_parameters(values, SIMULATOR_PARAMETERS)
    if checked['scenario'] == 'joints':
        from bcid_ros.identifier.joint_feeder import check_joint_names

        if checked['joints']:
            check_joint_names(checked['joints'])
            if len(checked['joints']) != checked['num_joints']:
                raise ValueError(f"parameter 'joints' must have num_joints = "
                                 f"{checked['num_joints']} names (or none), got "
                                 f"{len(checked['joints'])}")
        if checked['frame_size'] != 1:
            raise ValueError(f"parameter 'frame_size' must be 1 with scenario joints (one "
                             f"JointState per sample), got {checked['frame_size']}")
    return checked


__all__ = ['CUSTOM_SETTINGS', 'IDENTIFIER_LIVE', 'IDENTIFIER_PARAMETERS',
           'OPERATING_POINT_SETTINGS', 'SIMULATOR_PARAMETERS', 'check_identifier_parameters',
           'check_simulator_parameters', 'estimator_from_parameters', 'estimator_options',
           'estimator_settings', 'load_yaml_parameters', 'markdown_table', 'spec_by_name',
           'unused_options']
