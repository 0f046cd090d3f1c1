"""
The estimators' settings as parameter specs: each range written once.

The settings every estimator's constructor takes (:data:`SHARED_SETTINGS`:
the model structure, p0, the forgetting factor, the gate) and each
estimator's own options (:data:`BCIV_OPTIONS`, :data:`CL_BCLS_OPTIONS`,
:data:`RPEM_OPTIONS`) are parameter specs
(:class:`~bcid_ros.parameter_spec.ParameterSpec`).
The constructors check their keyword arguments through them
(:meth:`~bcid_ros.parameter_spec.ParameterSpec.check_argument`), the
registry lists the options, and the identifier's parameter table
(:mod:`bcid_ros.identifier.parameters`) takes the shared ones: the node, the
offline checks and a direct ``make_estimator`` call accept the same range, and
their messages name the setting, that range and the value.
"""

from __future__ import annotations

from bcid_ros.estimators.rules import IMPLAUSIBLE_ERROR
from bcid_ros.parameter_spec import parameter, ParameterSpec, spec_by_name

#: Largest dead time accepted (samples): the regressor keeps d_i more past inputs.
MAX_DELAY = 100000
#: Values of the ``detrend`` setting.
DETRENDS = ('none', 'mean')

#: The settings of every estimator's base constructor, by name, in the order of the
#: identifier's parameter table (which lists them all; ``BASE_SETTINGS`` there).
SHARED_SETTINGS: dict[str, ParameterSpec] = spec_by_name((
    parameter('order', 'integer', 2, 'Plant order n: number of a coefficients and of input '
              'lags.', low=1, high=64),
    parameter('num_inputs', 'integer', 1, 'Number of inputs r.', low=1, high=64),
    parameter('feedthrough', 'bool', False, 'Estimate the lag-0 input coefficients b{i}_0 '
              '(direct feedthrough).'),
    parameter('initial_covariance', 'double', 1e6, 'p0 of the initial covariance '
              'P(0) = p0 I.', low=0.0, high=1e15, low_open=True),
    parameter('forgetting_factor', 'double', 1.0, 'Exponential forgetting factor lambda; 1 '
              'means no forgetting. May be changed while running.', low=0.0, high=1.0,
              low_open=True, read_only=False),
    parameter('input_delay', 'integer_array', [0], 'Dead time d_i (samples) of each input, '
              'one integer per input or one for all: B_i(q) = q^-d_i (b_i1 q^-1 + ... + b_in '
              'q^-n); the parameter names carry the true lags. Not for cl_bcls.', low=0,
              high=MAX_DELAY),
    parameter('detrend', 'string', 'none', 'mean: regress the deviations from the recursive '
              'means of y and u (with the forgetting factor), published on ~/operating_point; '
              'none: the raw data.', choices=DETRENDS),
    parameter('adapt', 'bool', True, 'false holds the estimate, P and the noise statistics '
              'while samples keep flowing. May be changed while running.', read_only=False),
    parameter('outlier_threshold', 'double', 0.0, 'Refuse (and count) a sample whose '
              'normalised one-step prediction error exceeds this; 0 turns the gate off. May be '
              'changed while running.', low=0.0, high=IMPLAUSIBLE_ERROR, read_only=False),
))

BCIV_OPTIONS = (
    parameter('iv_lag', 'integer', None, 'bciv: IV lag l (the IV vector has n + 2l past inputs; '
              'colored input noise needs l >= 2n). Unset: the estimator default.',
              low=1, high=1000),
    parameter('input_noise', 'string', None, 'bciv: input measurement noise model. Unset: the '
              'estimator default.', choices=('colored', 'white')),
    parameter('idle_samples', 'integer', None, 'bciv: idle period L, samples before the bias '
              'compensation starts. Unset: the estimator default.', low=0, high=1e9),
    parameter('bciv_iterations', 'integer', None, 'bciv: alternations K of the compensation '
              'per sample. Unset: the estimator default.', low=1, high=10000),
    parameter('bciv_update', 'string', None, 'bciv: converged (K alternations from the IV '
              'estimate) or printed (the paper\'s one-step recursion). Unset: the estimator '
              'default.', choices=('converged', 'printed')),
    parameter('allow_underdetermined', 'bool', None, 'bciv: allow l < 2n with colored input '
              'noise (under-determined, poor). Unset: the estimator default.'),
)

CL_BCLS_OPTIONS = (
    parameter('controller_numerator', 'double_array', None, 'cl_bcls: controller numerator '
              'b_c in descending powers of q.'),
    parameter('controller_denominator', 'double_array', None, 'cl_bcls: controller '
              'denominator a_c in descending powers of q.'),
    parameter('controller_sign', 'string', None, 'cl_bcls: negative means u = (b_c/a_c)(r - y), '
              'positive means u = (b_c/a_c)(y - r). Unset: the estimator default (negative).',
              choices=('negative', 'positive')),
    parameter('prefilter_initial', 'double_array', None, 'cl_bcls: initial prefilter f(q): one '
              'pole [p] for (q - p)^n, or its n + 1 coefficients in descending powers of q. '
              'Unset: the estimator default.'),
    parameter('window', 'integer', None, 'cl_bcls: 0 (the estimator default) compensates over '
              'every sample since the last controller change (recursive moments); > 0 over the '
              'last window samples, for slowly varying plants. Unset: the estimator default.',
              low=0, high=1e9),
    parameter('redesign_period', 'integer', None, 'cl_bcls: samples between compensations and '
              'prefilter redesigns. Unset: the estimator default.', low=1, high=1e9),
    parameter('max_iterations', 'integer', None, 'cl_bcls: most prefilter redesign iterations '
              'per redesign. Unset: the estimator default.', low=1, high=10000),
    parameter('tolerance', 'double', None, 'cl_bcls: stop redesigning when the estimate moves '
              'less than this. Unset: the estimator default.', low=0.0, high=1e6,
              low_open=True),
)

#: Following a plant that changes (docs/tracking.md): rls, bcrls, rpem and the batched forms.
TRACKING_OPTIONS = (
    parameter('change_detection', 'bool', True, 'rls, bcrls, rpem: the CUSUM test of the '
              'one-step errors for a plant change (at most 1 false alarm per 100,000 samples '
              'of a plant that does not change); on a detection ~/valid turns false with '
              '"plant changed (sample k)" and the estimate restarts from the samples after '
              'the change point. May be changed while running.', read_only=False),
    parameter('adaptation', 'string', 'forgetting', 'rls, bcrls, rpem: forgetting (the '
              'forgetting_factor) or kalman (a random walk of the parameters, P <- P + Q at '
              'every sample, Q from parameter_drift).', choices=('forgetting', 'kalman')),
    parameter('parameter_drift', 'double', 0.0, 'rls, bcrls, rpem with adaptation: kalman: '
              'q, the variance of each parameter\'s random step per sample, for signals of '
              'unit size and relative to the noise variance (Q = q sigma2 S^-2; '
              'docs/tracking.md). May be changed while running.', low=0.0, high=1.0,
              read_only=False),
)
#: The tracking settings by name, for the constructors' checks.
TRACKING = spec_by_name(TRACKING_OPTIONS)

RPEM_OPTIONS = TRACKING_OPTIONS + (
    parameter('model', 'string', None, 'rpem: oe (output error y = sum B_i/F u_i + v, v of any '
              'colour) or armax (A y = sum B_i u_i + C e; adds c1..cn). Unset: the estimator '
              'default (oe).', choices=('oe', 'armax')),
)


def option(options: tuple[ParameterSpec, ...], name: str) -> ParameterSpec:
    """Return the spec of option ``name`` of an estimator's ``options``."""
    return spec_by_name(options)[name]


__all__ = ['BCIV_OPTIONS', 'CL_BCLS_OPTIONS', 'DETRENDS', 'MAX_DELAY', 'option', 'RPEM_OPTIONS',
           'SHARED_SETTINGS', 'TRACKING', 'TRACKING_OPTIONS']
