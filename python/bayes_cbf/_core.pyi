"""Type stubs of the compiled module bayes_cbf._core."""

from os import PathLike
from typing import Any, Callable, Final, Literal, Mapping, Optional, Sequence, Union

import numpy as np
import numpy.typing as npt
from typing_extensions import Self

ArrayLike = npt.ArrayLike
F64 = npt.NDArray[np.float64]
Rank = Union[Literal["full", "diag"], int]
Path = Union[str, PathLike[str]]
Gains = Optional[Sequence[float]]

__version__: str

class InputError(ValueError):
    """Bad input; the message names the field."""

class NumericalError(RuntimeError):
    """A numerical failure (factorisation, optimiser)."""

class MVGP:
    """Matrix-variate GP of F(x) = [f(x) g(x)]: vec F ~ GP(vec M0, B k0 ⊗ A), noise σ² A."""

    @property
    def fit_report(self) -> Optional[dict[str, float]]:
        """Report of the last fit (initial_log_likelihood, log_likelihood,
        evaluations, starts), or None."""
    def log_marginal_likelihood(self) -> float: ...
    @property
    def state_dim(self) -> int: ...
    @property
    def control_dim(self) -> int: ...
    def __len__(self) -> int: ...

    def __init__(
        self, state_dim: int, control_dim: int, lengthscales: ArrayLike,
        A: ArrayLike, B: ArrayLike, noise_sigma: float,
        prior_mean: Optional[Union[str, dict[str, Any]]] = None, input_map: Optional[list[Any]] = None,
        variance: float = 1.0, known_rows: Optional[Sequence[int]] = None,
    ) -> None: ...
    def fit(
        self, X: ArrayLike, U: ArrayLike, Xdot: ArrayLike,
        rank_a: Rank = "full", rank_b: Rank = "full",
        max_iters: int = 100, seed: int = 0, restarts: int = 0, sigma_min: float = 0.0,
    ) -> Self:
        """Learns the hyperparameters on (X, U, Xdot), which replace the data;
        sigma_min floors noise_sigma * sqrt(A[0, 0])."""
    def predict(self, Xq: ArrayLike) -> tuple[F64, F64]:
        """Means (q, n, 1+m) and B_k(x, x) (q, 1+m, 1+m); Cov(vec F(x)) = B_k ⊗ row_cov
        (row_cov is A with the known rows' rows and columns zero)."""
    def rust_predict_time_s(self, Xq: ArrayLike, repeats: int = 5) -> float: ...
    def add_observation(self, x: ArrayLike, u: ArrayLike, xdot: ArrayLike) -> None: ...
    def add_observation_within_budget(
        self, x: ArrayLike, u: ArrayLike, xdot: ArrayLike, budget: int
    ) -> int | None:
        """Adds (x, u, ẋ) keeping at most `budget` observations: drops the least
        informative of the stored points and the new one, and returns its index
        among the k + 1 (k: the new point was not stored); None below the budget."""
    def remove_oldest(self) -> None: ...
    def save(self, path: Path) -> None:
        """Writes the model file (model.json) completely or not at all,
        creating its directory if it is missing."""
    @staticmethod
    def load(path: Path) -> "MVGP": ...
    @staticmethod
    def from_json(text: str) -> "MVGP": ...
    def to_json(self) -> str: ...
    A: Final[F64]
    """Row covariance A (n × n)."""
    B: Final[F64]
    """Column covariance B ((1+m) × (1+m))."""
    known_rows: Final[list[int]]
    """Rows of F known exactly from the prior mean."""
    row_cov: Final[F64]
    """A with the known rows and columns zeroed: Cov(vec F(x)) = B_k(x, x) ⊗ row_cov."""
    lengthscales: Final[F64]
    """Kernel lengthscales."""
    variance: Final[float]
    """Kernel output scale."""
    noise_sigma: Final[float]
    """Noise scale σ."""
    X: Final[F64]
    """The training states (k, n)."""
    U: Final[F64]
    """The training controls (k, m)."""
    Xdot: Final[F64]
    """The training derivatives (k, n)."""

class CoGP:
    """Coregionalisation GP baseline: vec F ~ GP(vec M0, k0 Σ), noise S."""

    @property
    def fit_report(self) -> Optional[dict[str, float]]:
        """Report of the last fit (initial_log_likelihood, log_likelihood,
        evaluations, starts), or None."""
    def log_marginal_likelihood(self) -> float: ...
    @property
    def state_dim(self) -> int: ...
    @property
    def control_dim(self) -> int: ...
    def __len__(self) -> int: ...

    def __init__(
        self, state_dim: int, control_dim: int, lengthscales: ArrayLike,
        Sigma: Optional[ArrayLike] = None, S: Optional[ArrayLike] = None,
        prior_mean: Optional[Union[str, dict[str, Any]]] = None, input_map: Optional[list[Any]] = None,
        variance: float = 1.0,
    ) -> None: ...
    def fit(
        self, X: ArrayLike, U: ArrayLike, Xdot: ArrayLike,
        rank_sigma: Rank = "full", rank_s: Rank = "full",
        max_iters: int = 100, seed: int = 0, restarts: int = 0,
    ) -> Self: ...
    def predict(self, Xq: ArrayLike) -> tuple[F64, F64]:
        """Means (q, n, 1+m) and covariances of vec F(x) (q, n(1+m), n(1+m))."""
    Sigma: Final[F64]
    """Output covariance Σ (n(1+m) square)."""
    S: Final[F64]
    """Noise covariance S (n × n)."""
    lengthscales: Final[F64]
    """Kernel lengthscales."""
    variance: Final[float]
    """Kernel output scale."""
    X: Final[F64]
    """The training states (k, n)."""
    U: Final[F64]
    """The training controls (k, m)."""
    Xdot: Final[F64]
    """The training derivatives (k, n)."""

class Barrier:
    """A control barrier function; the safe set is {x : h(x) >= 0}.

    Every constructor takes the class-K gains as `alpha` (relative degree 1)
    or `k_alpha` (one gain per derivative order, relative degree >= 2).
    """

    @staticmethod
    def from_json(text: str) -> "Barrier": ...
    @staticmethod
    def load(path: Path) -> "Barrier": ...
    @staticmethod
    def pendulum_sector(
        theta_c: float, delta: float,
        relative_degree: int = 2, alpha: Optional[float] = None, k_alpha: Gains = None,
    ) -> "Barrier": ...
    @staticmethod
    def pendulum_sector_edge(
        theta_c: float, delta: float, edge: Literal["upper", "lower"],
        relative_degree: int = 2, alpha: Optional[float] = None, k_alpha: Gains = None,
    ) -> "Barrier": ...
    @staticmethod
    def circle_heading(
        center: Sequence[float], radius: float, q1: float, q2: float,
        relative_degree: int = 1, alpha: Optional[float] = None, k_alpha: Gains = None,
    ) -> "Barrier": ...
    @staticmethod
    def disc(
        state_dim: int, indices: Sequence[int], center: Sequence[float], radius: float,
        relative_degree: int = 1, alpha: Optional[float] = None, k_alpha: Gains = None,
    ) -> "Barrier": ...
    @staticmethod
    def half_space(
        normal: Sequence[float], offset: float,
        relative_degree: int = 1, alpha: Optional[float] = None, k_alpha: Gains = None,
    ) -> "Barrier": ...
    @staticmethod
    def expression(
        h: str, state: Sequence[str], params: Optional[Mapping[str, float]] = None,
        relative_degree: int = 1, alpha: Optional[float] = None, k_alpha: Gains = None,
    ) -> "Barrier":
        """h written as an expression over the named states (exact derivatives)."""
    @staticmethod
    def callback(
        h: Callable[[F64], float], grad: Callable[[F64], ArrayLike],
        hess: Optional[Callable[[F64], ArrayLike]] = None, state_dim: int = 2,
        relative_degree: int = 1, alpha: Optional[float] = None, k_alpha: Gains = None,
        name: str = "callback",
    ) -> "Barrier": ...
    def value(self, x: ArrayLike) -> float: ...
    def gradient(self, x: ArrayLike) -> F64: ...
    def hessian(self, x: ArrayLike) -> F64: ...
    state_dim: Final[int]
    relative_degree: Final[int]
    gains: Final[list[float]]
    """Class-K gains: [alpha] or k_alpha."""
    name: Final[str]
    """The barrier's name in reports: its type (``"disc"``, ...), its ``h`` for
    an expression, the given name for a callback, the file's path for
    :meth:`Barrier.load` (as the command line's ``control`` names it)."""
    def to_json(self) -> Optional[str]: ...

class CLF:
    """A control Lyapunov function for the filter's CLF constraint."""

    @staticmethod
    def from_json(text: str) -> "CLF": ...
    @staticmethod
    def ackermann(w1: float, w2: float, gamma: float) -> "CLF": ...
    @staticmethod
    def expression(
        V: str,
        state: Sequence[str],
        params: Optional[Mapping[str, float]] = None,
        gamma: float = 1.0,
    ) -> "CLF":
        """V(x, x_d) over the state names and the references <name>_d."""
    def to_json(self) -> str:
        """The JSON text from_json reads back."""
        ...

class FilterResult:
    """The result of one filter step."""

    u: Final[F64]
    status: Final[Literal["optimal", "infeasible"]]
    p_star: Final[Optional[float]]
    fallback: Final[Optional[str]]
    violated: Final[Optional[list[int]]]
    constraints: Final[list[dict[str, Any]]]
    """Per barrier: barrier, relative_degree, mean, std, c and slack."""
    solve_time_us: Final[float]

class SafetyFilter:
    """The chance-constrained CBF(-CLF) SOCP safety filter."""

    def __init__(
        self,
        model: MVGP,
        barriers: Sequence[Barrier],
        clf: Optional[CLF] = None,
        probability: float = 0.99,
        zeta: float = 0.0,
        u_min: Optional[ArrayLike] = None,
        u_max: Optional[ArrayLike] = None,
        R: Optional[ArrayLike] = None,
        fallback: Literal["max_margin", "brake", "hold", "relax"] = "max_margin",
        clf_weight: float = 1.0,
        predictive: bool = False,
    ) -> None:
        """The control closest to u_ref in ‖R(u − u_ref)‖ (R: m × m, invertible;
        identity by default; weights more than 1e3 apart are refused, and
        more than 100 apart warned of: the solver resolves the lightly
        weighted controls only roughly) that meets every condition with the
        probability. A bounded control lies within u_min and u_max exactly.

        The default is the paper's condition on the latent F, with the
        variance bc.moments gives. In a closed loop whose state carries
        process noise, pass predictive=True (each condition as realised over
        the step, the model's noise included) and, with input bounds,
        fallback="relax": the defaults of scenario files. Held at the
        boundary under the latent condition, the state's own noise takes h
        below zero."""
    def filter(
        self,
        x: ArrayLike,
        u_ref: ArrayLike,
        x_d: Optional[ArrayLike] = None,
        xdot_d: Optional[ArrayLike] = None,
    ) -> FilterResult: ...
    def rust_step_time_us(self, x: ArrayLike, u_ref: ArrayLike, repeats: int = 1000) -> float: ...
    model: Final[MVGP]
    barrier_names: Final[list[str]]

def moments(
    model: MVGP,
    barrier: Barrier,
    x: ArrayLike,
    u: ArrayLike,
    samples: int = 20000,
    step: float = 1e-2,
    seed: int = 0,
) -> tuple[float, float]:
    """(mean, variance) of the barrier condition at (x, u); relative degree ≥ 3
    by Monte Carlo (samples, seed) with central differences of step, which is
    refused where the rounding of h, of the mean of F or of the posterior
    draws would bias the moments, or where the truncation of the differences
    would."""

def run_scenario(
    name: Path,
    seed: Optional[int] = None,
    overrides: Optional[dict[str, Any]] = None,
) -> dict[str, Any]:
    """The summary and trajectory of a scenario run (a built-in name or a
    TOML file); seed from 0 to 2^63 − 1, overrides as --set key=value (finite
    numbers, strings, lists, dicts)."""
def list_scenarios() -> list[str]: ...

# Private: the engine of bayes_cbf.sweep (JSON and CSV text in and out).
def sweep_meta(
    scenario: str, start: int, end: int, sets: list[str],
    index: int = 0, count: int = 1, goal_tolerance: float = 1.0,
) -> str: ...
def check_scenario(name: str, sets: list[str]) -> None: ...
def override_sets(overrides: Optional[dict[str, Any]]) -> list[str]: ...
def sweep_shard(meta: str) -> str: ...
def sweep_merge(parts: list[tuple[str, str]]) -> tuple[str, str]: ...
def calibration_shard(
    seed: int = 0, quick: bool = False, episodes: Optional[int] = None,
    index: int = 0, count: int = 1, fallback: Optional[str] = None,
) -> str: ...
def calibration_check(
    seed: int = 0, quick: bool = False, episodes: Optional[int] = None,
    fallback: Optional[str] = None,
) -> None: ...
def calibration_merge(parts: list[str]) -> tuple[str, str]: ...
