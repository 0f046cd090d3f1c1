"""
The estimator registry: everything the rest of bcid_ros asks about an estimator.

One :class:`EstimatorEntry` per estimator, by the name the ``estimator``
parameter takes. It names the single-plant class and the batched (many
plants) class, the estimator's own options with their parameter specs, its
model kind and the identifier input modes it supports. Every other list of
estimator names in the package derives from :data:`REGISTRY` (the parameter
table, the CLI's choices, the joint-state mode, the analysis): a new
estimator is its module plus one entry here.

The classes are imported when first asked for, so that reading the registry
imports no estimator module (and no scipy): each entry holds a loader, a
function whose import statement grep and the layer test see like any other.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

from bcid_ros.estimators.settings import (BCIV_OPTIONS, CL_BCLS_OPTIONS, RPEM_OPTIONS,
                                          TRACKING_OPTIONS)
from bcid_ros.parameter_spec import ParameterSpec

#: The model kinds: what the estimator assumes about the plant and its noise.
#: ``arx``: A y = B u + e, e white (equation error); ``output_error``:
#: y = B/A u + v (the simulated output's error is what the model explains);
#: ``errors_in_variables``: both y and u measured with noise; ``closed_loop``:
#: the plant under a known feedback controller.
MODEL_KINDS = ('arx', 'output_error', 'errors_in_variables', 'closed_loop')
#: The identifier's input modes (the ``input_mode`` parameter).
INPUT_MODES = ('combined', 'separate', 'joint_state')
#: Model kinds identified from open-loop input/output data as they come.
OPEN_LOOP_KINDS = ('arx', 'output_error')


@dataclasses.dataclass(frozen=True)
class EstimatorEntry:
    """
    One registered estimator.

    Attributes
    ----------
    name : str
        The value of the ``estimator`` parameter.
    single : callable
        Returns the single-plant estimator class (importing its module).
    batched : callable or None
        Returns the class that runs many plants at once, or None.
    model : str
        One of :data:`MODEL_KINDS`.
    options : tuple of ParameterSpec
        The estimator's own constructor keywords, as identifier parameters
        (default None: the class's default).
    summary : str
        One line for the docs and the command-line help.
    supports_delay : bool
        Whether it takes a dead time (``input_delay`` other than 0).
    takes_controller : bool
        Whether it identifies under a known controller (``set_controller``,
        the ``controller_topic`` parameter, the demo's closed loop).

    """

    name: str
    single: Callable[[], Any]
    batched: Callable[[], Any] | None
    model: str
    options: tuple[ParameterSpec, ...] = ()
    summary: str = ''
    supports_delay: bool = True
    takes_controller: bool = False

    @property
    def input_modes(self) -> tuple[str, ...]:
        """Return the identifier input modes this estimator runs in."""
        return INPUT_MODES if self.batched else INPUT_MODES[:2]

    @property
    def option_names(self) -> tuple[str, ...]:
        """Return the names of the estimator's own options."""
        return tuple(spec.name for spec in self.options)

    @property
    def open_loop(self) -> bool:
        """Whether the estimator identifies open-loop input/output data as they come."""
        return self.model in OPEN_LOOP_KINDS


# the loaders: each imports its module on first use


def _rls() -> Any:
    from bcid_ros.estimators.rls import Rls
    return Rls


def _batched_rls() -> Any:
    from bcid_ros.estimators.batched import BatchedRls
    return BatchedRls


def _bcrls() -> Any:
    from bcid_ros.estimators.bcrls import Bcrls
    return Bcrls


def _batched_bcrls() -> Any:
    from bcid_ros.estimators.batched_bcrls import BatchedBcrls
    return BatchedBcrls


def _bciv() -> Any:
    from bcid_ros.estimators.bciv import Bciv
    return Bciv


def _cl_bcls() -> Any:
    from bcid_ros.estimators.cl_bcls import ClosedLoopBcls
    return ClosedLoopBcls


def _rpem() -> Any:
    from bcid_ros.estimators.rpem import Rpem
    return Rpem


#: The registered estimators, by name, in the order the docs list them.
REGISTRY: dict[str, EstimatorEntry] = {entry.name: entry for entry in (
    EstimatorEntry('rls', _rls, _batched_rls, 'arx', TRACKING_OPTIONS,
                   summary='recursive least squares (the biased baseline)'),
    EstimatorEntry('bcrls', _bcrls, _batched_bcrls, 'output_error', TRACKING_OPTIONS,
                   summary='bias-compensated RLS, MISO output error (Ding et al. 2006)'),
    EstimatorEntry('bciv', _bciv, None, 'errors_in_variables', BCIV_OPTIONS,
                   summary='recursive bias-compensated IV, errors in variables '
                   '(Ikenoue et al. 2008)'),
    EstimatorEntry('cl_bcls', _cl_bcls, None, 'closed_loop', CL_BCLS_OPTIONS,
                   summary='BCLS in closed loop with prefilter redesign (Ikeda 2008)',
                   supports_delay=False, takes_controller=True),
    EstimatorEntry('rpem', _rpem, None, 'output_error', RPEM_OPTIONS,
                   summary='recursive prediction-error method, OE or ARMAX, with a '
                   'batch-refined start (Ljung and Soderstrom 1983)'),
)}

#: The registered names, in registry order.
ESTIMATOR_NAMES = tuple(REGISTRY)


def entry(name: str) -> EstimatorEntry:
    """
    Return the registry entry of estimator ``name``.

    Raises
    ------
    ValueError
        If ``name`` is not registered.

    """
    if name not in REGISTRY:
        raise ValueError(f'estimator must be one of {", ".join(REGISTRY)}; got {name!r}')
    return REGISTRY[name]


def names_where(**conditions: Any) -> tuple[str, ...]:
    """
    Return the names of the estimators whose entry has every attribute value given.

    ``names_where(open_loop=True)``, ``names_where(model='arx')``; an
    attribute that is a tuple (``input_modes``) matches when it contains the
    value.
    """
    def matches(item: EstimatorEntry) -> bool:
        for key, wanted in conditions.items():
            value = getattr(item, key)
            if not (wanted in value if isinstance(value, tuple) else value == wanted):
                return False
        return True

    return tuple(name for name, item in REGISTRY.items() if matches(item))


def option_specs() -> tuple[ParameterSpec, ...]:
    """Return every registered estimator's options, each name once, in registry order."""
    specs: dict[str, ParameterSpec] = {}
    for item in REGISTRY.values():
        for spec in item.options:
            specs.setdefault(spec.name, spec)
    return tuple(specs.values())


def estimator_class(name: str) -> Any:
    """
    Return the single-plant class of estimator ``name`` (its module imported on first use).

    Raises
    ------
    ValueError
        If ``name`` is not registered.

    """
    return entry(name).single()


def batched_class(name: str) -> Any:
    """
    Return the many-plants class of estimator ``name``.

    Raises
    ------
    ValueError
        If ``name`` is not registered or has no batched form.

    """
    load = entry(name).batched
    if load is None:
        batched = ', '.join(names_where(input_modes='joint_state'))
        raise ValueError(f'estimator must be one of {batched} for many plants; got {name!r}')
    return load()


__all__ = ['ESTIMATOR_NAMES', 'EstimatorEntry', 'INPUT_MODES', 'MODEL_KINDS', 'OPEN_LOOP_KINDS',
           'REGISTRY', 'batched_class', 'entry', 'estimator_class', 'names_where',
           'option_specs']
