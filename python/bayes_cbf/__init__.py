"""bayes_cbf: learn a robot's dynamics online and keep it safe while it learns.

Python interface of the Rust library bayes-cbf, an implementation of
Dhiman, Khojasteh, Franceschetti and Atanasov, *Control Barriers in Bayesian
Learning of System Dynamics*, IEEE TAC 2021.

- :class:`MVGP` learns ``F(x) = [f(x) g(x)]`` of ``xdot = f(x) + g(x) u`` as a
  matrix-variate Gaussian process, with O(k^2) online updates;
  :class:`CoGP` is the coregionalisation baseline.
- :class:`Barrier` describes a safe set ``h(x) >= 0`` (from a barrier file, a
  built-in constructor, or Python callbacks); :func:`moments` gives the mean
  and variance of its condition under the posterior.
- :class:`SafetyFilter` solves the chance-constrained SOCP at each step.
- :func:`run_scenario` runs a closed-loop scenario like ``bayes-cbf run``.
- :mod:`bayes_cbf.gym` wraps any continuous-action gymnasium environment.

Arrays are numpy ``float64``: ``X`` is ``(k, n)``, ``U`` is ``(k, m)``,
``Xdot`` is ``(k, n)``. Bad input raises :class:`InputError` (a
``ValueError`` naming the field); numerical failures raise
:class:`NumericalError`; an infeasible filter step is a status.
"""

from ._core import (
    CLF,
    MVGP,
    Barrier,
    CoGP,
    FilterResult,
    InputError,
    NumericalError,
    SafetyFilter,
    __version__,
    list_scenarios,
    moments,
    run_scenario,
)
from ._derivatives import check_derivatives

__all__ = [
    "CLF",
    "MVGP",
    "Barrier",
    "CoGP",
    "FilterResult",
    "InputError",
    "NumericalError",
    "SafetyFilter",
    "__version__",
    "check_derivatives",
    "list_scenarios",
    "moments",
    "run_scenario",
]
