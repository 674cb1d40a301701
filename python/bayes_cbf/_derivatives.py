"""Checks of user-supplied derivatives against finite differences."""

from __future__ import annotations

from typing import Callable, Optional

import numpy as np

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
    seed: int = 0,
) -> dict:
    """Compares ``grad`` (and ``hess``) with central differences of ``h`` (and
    ``grad``) at ``points`` (``(q, n)``; default: 10 standard-normal points in
    ``state_dim`` dimensions). An entry passes when its error is at most
    ``atol + rtol * |finite difference|``.

    Returns a dict with ``ok`` (bool), ``grad_error`` and ``hess_error`` (the
    largest absolute error, ``None`` without ``hess``) and ``worst_point``.
    Use it before :meth:`Barrier.callback`: wrong derivatives give wrong
    moments and an unsafe filter.
    """
    if points is None:
        if state_dim is None:
            raise InputError("check_derivatives: give points or state_dim")
        points = np.random.default_rng(seed).standard_normal((10, state_dim))
    points = np.atleast_2d(np.asarray(points, dtype=np.float64))
    if not np.all(np.isfinite(points)):
        raise InputError("points: entries must be finite")
    n = points.shape[1]
    eye = np.eye(n)
    worst_g, worst_h, worst_x = 0.0, 0.0 if hess is not None else None, None
    ok = True
    for x in points:
        g = np.asarray(grad(x), dtype=np.float64).reshape(-1)
        if g.shape != (n,):
            raise InputError(f"grad: returned {g.shape[0]} entries, expected {n}")
        fd = np.array([(h(x + step * e) - h(x - step * e)) / (2 * step) for e in eye])
        err = np.abs(g - fd)
        if err.max() > worst_g:
            worst_g, worst_x = float(err.max()), x
        ok &= bool(np.all(err <= atol + rtol * np.abs(fd)))
        if hess is not None:
            H = np.asarray(hess(x), dtype=np.float64)
            if H.shape != (n, n):
                raise InputError(f"hess: returned shape {H.shape}, expected ({n}, {n})")
            fdh = np.stack(
                [
                    (np.asarray(grad(x + step * e)) - np.asarray(grad(x - step * e))) / (2 * step)
                    for e in eye
                ]
            )
            errh = np.abs(H - fdh)
            if errh.max() > worst_h:
                worst_h, worst_x = float(errh.max()), x
            ok &= bool(np.all(errh <= atol + rtol * np.abs(fdh)))
    return {"ok": ok, "grad_error": worst_g, "hess_error": worst_h, "worst_point": worst_x}
