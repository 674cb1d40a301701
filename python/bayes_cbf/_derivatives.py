"""Checks of user-supplied derivatives against finite differences."""

from __future__ import annotations

from typing import Any, Callable, Optional

import numpy as np

from ._checks import count, real
from ._core import InputError


def check_derivatives(
    h: Callable[[np.ndarray], float],
    grad: Callable[[np.ndarray], np.ndarray],
    hess: Optional[Callable[[np.ndarray], np.ndarray]] = None,
    points: Optional[np.ndarray] = None,
    state_dim: Optional[int] = None,
    step: float = 1e-5,
    rtol: float = 1e-4,
    atol: float = 1e-6,
    seed: Optional[int] = 0,
) -> dict:
    """Compares ``grad`` (and ``hess``) with central differences of ``h`` (and
    ``grad``) at ``points`` (``(q, n)``; default: 10 standard-normal points in
    ``state_dim`` dimensions). An entry passes when its error is at most
    ``atol + rtol * |finite difference| + round-off``, where the round-off
    of a central difference of ``f`` is ``4 eps max|f(x ± step e)| / step``
    (``eps`` the float64 machine epsilon): a large ``h`` (``1e9 + x²``)
    cannot be differenced more finely than that at this ``step``. Where that
    round-off exceeds ``atol`` plus a tenth of the largest entry of the
    gradient (or Hessian) compared at that point, the entry is
    *unresolved*: the differences cannot tell a right value from a wrong
    one there, and the check does not pass (raise ``step``, or drop a large
    constant from ``h``).

    Returns a dict with ``ok`` (bool: every entry passed and was resolved),
    ``grad_error`` and ``hess_error`` (the largest absolute error, ``inf``
    where a function returned a non-finite value, ``None`` without
    ``hess``), ``unresolved`` (the entries the differences could not
    resolve) and ``worst_point``.
    Use it before :meth:`Barrier.callback`: wrong derivatives give wrong
    moments and an unsafe filter.
    """
    step, rtol, atol = real("step", step), real("rtol", rtol), real("atol", atol)
    if not (np.isfinite(step) and step > 0):
        raise InputError(f"step: {step!r} must be finite and > 0")
    for name, tol in (("rtol", rtol), ("atol", atol)):
        if not (np.isfinite(tol) and tol >= 0):
            raise InputError(f"{name}: {tol!r} must be finite and >= 0")
    if state_dim is not None:
        state_dim = count("state_dim", state_dim, 1)
    if points is None:
        if state_dim is None:
            raise InputError("check_derivatives: give points or state_dim")
        rng = np.random.default_rng(None if seed is None else count("seed", seed, 0))
        points = rng.standard_normal((10, state_dim))
    points = np.atleast_2d(np.asarray(points, dtype=np.float64))
    if points.ndim != 2 or points.shape[0] == 0 or points.shape[1] == 0:
        raise InputError(f"points: expected a non-empty (q, n) array, got shape {points.shape}")
    if state_dim is not None and points.shape[1] != state_dim:
        raise InputError(
            f"points: {points.shape[1]} columns, but state_dim is {state_dim}"
        )
    if not np.all(np.isfinite(points)):
        raise InputError("points: entries must be finite")
    n = points.shape[1]
    eye = np.eye(n)
    # a non-finite error (h, grad or hess returned NaN or inf) is the worst
    worst_g, worst_h, worst_x = -1.0, -1.0 if hess is not None else None, None

    def worst(err: np.ndarray) -> float:
        return float("inf") if not np.all(np.isfinite(err)) else float(err.max())

    def wrap(name: str, f: Callable[[np.ndarray], Any]) -> Callable[[np.ndarray], Any]:
        # a callback's exception as the barrier's own calls raise it
        def call(x: np.ndarray) -> Any:
            try:
                return f(x)
            except Exception as e:
                raise InputError(f"{name} failed at x = {x.tolist()}: {e!r}") from e

        return call

    def scalar(f: Callable[[np.ndarray], Any]) -> Callable[[np.ndarray], float]:
        # h's value as Barrier.callback reads it: a float (or a 0-d array)
        def call(x: np.ndarray) -> float:
            v = f(x)
            if np.ndim(v) != 0:
                raise InputError(
                    f"h: returned an array of shape {np.shape(v)} at x = {x.tolist()}, "
                    "expected a float (as Barrier.callback does)"
                )
            return float(v)

        return call

    def round_off(values: np.ndarray) -> np.ndarray:
        # the rounding of a central difference of the values at x ± step e_j
        # (axis 1), per direction j (axis 0)
        return 4 * np.finfo(np.float64).eps * np.abs(values).max(axis=1) / step

    def passes(got: np.ndarray, fd: np.ndarray, values: np.ndarray) -> bool:
        # within tolerance and resolved (counting the unresolved entries)
        nonlocal unresolved
        ro = round_off(values)
        scale = max(np.abs(fd).max(), np.abs(got).max())
        # a floor of 1e-9 where atol is 0: an all-zero derivative (a linear
        # h's Hessian) is resolved to within its differences' round-off
        unresolved += int(np.sum(ro > max(atol, 1e-9) + 0.1 * scale))
        return bool(np.all(np.abs(got - fd) <= atol + rtol * np.abs(fd) + ro))

    h, grad = scalar(wrap("h", h)), wrap("grad", grad)
    if hess is not None:
        hess = wrap("hess", hess)
    ok, unresolved = True, 0
    for x in points:
        g = np.asarray(grad(x), dtype=np.float64).reshape(-1)
        if g.shape != (n,):
            raise InputError(f"grad: returned {g.shape[0]} entries, expected {n}")
        hp = np.array([[h(x + step * e), h(x - step * e)] for e in eye])
        fd = (hp[:, 0] - hp[:, 1]) / (2 * step)
        err = np.abs(g - fd)
        if worst(err) > worst_g:
            worst_g, worst_x = worst(err), x
        ok &= passes(g, fd, hp)
        if hess is not None:
            H = np.asarray(hess(x), dtype=np.float64)
            if H.shape != (n, n):
                raise InputError(f"hess: returned shape {H.shape}, expected ({n}, {n})")
            # gp[j, 0] = grad(x + step e_j), gp[j, 1] = grad(x − step e_j)
            gp = np.stack(
                [
                    np.stack([np.asarray(grad(x + step * e)), np.asarray(grad(x - step * e))])
                    for e in eye
                ]
            ).astype(np.float64)
            fdh = (gp[:, 0] - gp[:, 1]) / (2 * step)
            errh = np.abs(H - fdh)
            if worst(errh) > worst_h:
                worst_h, worst_x = worst(errh), x
            ok &= passes(H, fdh, gp)
    return {
        "ok": ok and unresolved == 0,
        "grad_error": worst_g,
        "hess_error": worst_h,
        "unresolved": unresolved,
        "worst_point": worst_x,
    }
