"""
The parameter table of the adaptive controller node (pure Python, no ROS).

It uses the :class:`bcid_ros.parameter_spec.ParameterSpec` of the other nodes,
so the node declares its ROS parameters with descriptors from it and the
same checks run offline (``check_controller_parameters`` on a YAML section).
"""

from __future__ import annotations

from typing import Any

from bcid_ros.control.design import Controller, ModelStructure, required_pole_count
from bcid_ros.control.reference import REFERENCE_SIGNALS
from bcid_ros.parameter_spec import check_parameters, parameter as _p, ParameterSpec


#: The controller node's parameters, in declaration order (all fixed at start-up).
CONTROLLER_PARAMETERS: tuple[ParameterSpec, ...] = (
    _p('identifier', 'string', '/bcid_identifier', 'Topic prefix of the identifier whose '
       'parameters, parameter_std and valid are used.'),
    # --- the model the estimates must have
    _p('order', 'integer', 2, 'Plant order n of the estimates (names a1..an); an estimate of '
       'another order is refused.', low=1, high=64),
    _p('feedthrough', 'bool', False, 'Whether the estimates carry b1_<d> (lag-0 input '
       'coefficient, after the delay).'),
    _p('input_delay', 'integer', 0, 'Dead time d (samples) of the estimates: b1 lags d + 1 .. '
       'd + n.', low=0, high=1000),
    # --- the design
    _p('closed_loop_poles', 'double_array', [], 'Desired closed-loop poles, real, inside the '
       'unit circle; their number is deg A + [integral_action] + deg R\' (at least the '
       'number the start-up error names).', low=-1.0, high=1.0),
    _p('integral_action', 'bool', False, 'Put (q - 1) in the controller denominator: zero '
       'steady-state error on steps, offset-free at an operating point.'),
    _p('computation_delay', 'bool', True, 'The plant applies the input computed from y_t at '
       'the next sample, as a zero-order hold of the latest command does: the controller is '
       'then strictly proper, and u_t = C(q)(r\'_t - y_t) in the plant\'s sample index.'),
    _p('max_condition', 'double', 1e4, 'Refuse a design whose scaled Sylvester matrix has a '
       'larger condition number (near pole-zero cancellation); keep the last controller.',
       low=1.0, high=1e300),
    _p('redesign_tolerance', 'double', 0.02, 'Do not switch when the controller in the loop '
       'already places the closed-loop poles of a new trusted estimate within this distance '
       'of the target (every switch restarts a closed-loop identifier\'s window); 0 switches '
       'at every trusted estimate.', low=0.0, high=2.0),
    # --- the trust gate
    _p('redesign_period', 'double', 1.0, 'Seconds between two looks at the latest estimate '
       '(and redesigns).', low=0.0, high=3600.0, low_open=True),
    _p('max_relative_std', 'double', 0.1, 'Use an estimate only if the relative std of A '
       '(|std_a| / |[1, a]|) and of B (|std_b| / |b|) are at most this; 0 turns the check '
       'off (no parameter_std needed).', low=0.0, high=1e6),
    _p('estimate_timeout', 'double', 5.0, 'Warn (and count) when no estimate arrived for '
       'this many seconds; the last good controller stays. 0 turns the check off.',
       low=0.0, high=1e6),
    _p('fallback_numerator', 'double_array', [0.0], 'Controller until a trusted estimate '
       'exists: numerator of C(q), descending powers of q.'),
    _p('fallback_denominator', 'double_array', [1.0], 'Controller until a trusted estimate '
       'exists: denominator of C(q), descending powers of q.'),
    # --- the input
    _p('input_limit', 'double', 10.0, 'The input is saturated to [-input_limit, '
       'input_limit].', low=0.0, high=1e12, low_open=True),
    _p('antiwindup_pole', 'double', 0.0, 'Pole p_o of the anti-windup observer (q - p_o)^deg '
       'R; 0 is the velocity form.', low=0.0, high=0.999),
    # --- the reference r' = setpoint + excitation
    _p('reference_offset', 'double', 0.0, 'Setpoint until a message on reference arrives '
       '(which then replaces it).'),
    _p('reference_signal', 'string', 'none', 'Excitation added to the setpoint: square, prbs '
       '(random +-amplitude from reference_seed) or none.', choices=REFERENCE_SIGNALS),
    _p('reference_amplitude', 'double', 1.0, 'Amplitude of the excitation.',
       low=0.0, high=1e12),
    _p('reference_period', 'integer', 100, 'Square: samples per period (>= 2). PRBS: samples '
       'each level is held.', low=1, high=1e9),
    _p('reference_seed', 'integer', 0, 'Seed of the PRBS.', low=0, high=2 ** 63 - 1),
)


def structure_of(values: dict[str, Any]) -> ModelStructure:
    """Return the model structure the parameters configure."""
    return ModelStructure(values['order'], values['feedthrough'], values['input_delay'])


def check_controller_parameters(values: dict[str, Any]) -> dict[str, Any]:
    """
    Check controller parameters and return all of them, defaults filled in.

    Besides each parameter's own range this checks that the poles lie inside
    the unit circle and are enough for a causal design, and that the
    fallback controller is causal (strictly proper where the design must be).

    Raises
    ------
    ValueError
        Naming the parameter, its allowed values and the value given.

    """
    checked = check_parameters(values, CONTROLLER_PARAMETERS)
    structure = structure_of(checked)
    poles = checked['closed_loop_poles']
    strict = checked['computation_delay'] or structure.lags[0] == 0
    needed = required_pole_count(structure, integral=checked['integral_action'],
                                 strictly_proper=strict)
    if len(poles) < needed or any(abs(p) >= 1.0 for p in poles):
        raise ValueError(f'parameter \'closed_loop_poles\' must be at least {needed} real '
                         f'poles inside the unit circle for order {structure.order}, '
                         f'input_delay {structure.input_delay}, feedthrough '
                         f'{str(structure.feedthrough).lower()}, integral_action '
                         f'{str(checked["integral_action"]).lower()}, computation_delay '
                         f'{str(checked["computation_delay"]).lower()}; got {poles!r}')
    try:
        fallback = Controller.from_coefficients(checked['fallback_numerator'],
                                                checked['fallback_denominator'])
    except ValueError as error:
        raise ValueError(f'parameters \'fallback_numerator\', \'fallback_denominator\': '
                         f'{error}') from None
    if strict and not fallback.strictly_proper:
        raise ValueError(f'parameters \'fallback_numerator\', \'fallback_denominator\' must '
                         f'be a strictly proper controller (fewer numerator coefficients) '
                         f'with computation_delay or a lag-0 feedthrough, got '
                         f'{checked["fallback_numerator"]!r}, '
                         f'{checked["fallback_denominator"]!r}')
    if checked['reference_signal'] == 'square' and checked['reference_period'] < 2:
        raise ValueError(f'parameter \'reference_period\' must be an integer >= 2 for a '
                         f'square wave, got {checked["reference_period"]!r}')
    return checked


__all__ = ['CONTROLLER_PARAMETERS', 'check_controller_parameters', 'structure_of']
