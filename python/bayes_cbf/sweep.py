"""Monte Carlo sweeps on Ray: seed sweeps of any scenario and the
``calibration`` experiment, split into shards that run as Ray tasks on a
local Ray or a cluster.

Each shard is the one ``bayes-cbf run ... --shard I/N`` runs; the shards are
merged by the same library code as ``bayes-cbf merge``, so a sweep returns
exactly the summary of the unsharded CLI run (counts and statistics to the
bit; timings differ). Ray is an optional extra: ``pip install '.[ray]'``.

Local (uses the cores of this machine)::

    from bayes_cbf import sweep
    summary = sweep.seeds("pendulum-safe", range(0, 200))
    cal = sweep.calibration(episodes=200, seed=0)

On a cluster, start Ray there (``ray start --head`` on one node,
``ray start --address=HEAD:6379`` on the others) and pass its address
(``address="auto"`` from a node of the cluster, or ``"ray://HEAD:10001"``
from outside)::

    summary = sweep.seeds("pendulum-safe", range(0, 100_000), address="auto", shards=512)
"""

from __future__ import annotations

import json
import numbers
import os
import socket
from typing import Any, Iterable, Optional, Union

from . import _core
from ._core import InputError

_RAY_MISSING = "bayes_cbf.sweep needs Ray: pip install 'bayes_cbf[ray]' (or pip install ray)"


def _ray():
    try:
        import ray
    except ImportError as e:  # pragma: no cover - exercised only without Ray
        raise ImportError(_RAY_MISSING) from e
    return ray


def _init(address: Optional[str], num_cpus: Optional[int]):
    if num_cpus is not None and (
        not isinstance(num_cpus, numbers.Integral) or isinstance(num_cpus, bool) or num_cpus < 1
    ):
        raise InputError(f"num_cpus: {num_cpus!r}, must be an integer >= 1")
    if address is not None and not isinstance(address, str):
        raise InputError(f"address: {address!r}, must be a string such as 'auto' or 'HOST:PORT'")
    ray = _ray()
    if not ray.is_initialized():
        kw: dict[str, Any] = {"ignore_reinit_error": True, "log_to_driver": False}
        if address is not None:
            _reachable(address)
            kw["address"] = address
        elif num_cpus is not None:
            kw["num_cpus"] = num_cpus
        ray.init(**kw)
    return ray


# how long a cluster's address may take to accept a connection
_CONNECT_TIMEOUT_S = 10.0


def _reachable(address: str) -> None:
    """Raises ``ConnectionError`` naming ``address`` when its ``HOST:PORT``
    (after ``ray://``) does not accept a connection within
    ``_CONNECT_TIMEOUT_S``: Ray itself retries an unreachable address for
    minutes. Addresses without a port (``"auto"``, ``"local"``) are Ray's."""
    target = address[len("ray://"):] if address.startswith("ray://") else address
    host, sep, port = target.rpartition(":")
    if not sep:
        return
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError(f"address: {address!r}, its port {port!r} is not a port number")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), _CONNECT_TIMEOUT_S):
            pass
    except OSError as e:
        raise ConnectionError(
            f"address: no Ray cluster answers at {address!r} ({e}); start one there "
            "(ray start --head) or pass address=None for a local Ray"
        ) from e


def _shard_count(ray, shards: Optional[int], items: int) -> int:
    if shards is None:
        shards = int(ray.cluster_resources().get("CPU", 1))
    if not isinstance(shards, numbers.Integral) or isinstance(shards, bool) or shards < 1:
        raise InputError(f"shards: {shards!r}, must be an integer >= 1")
    return max(1, min(int(shards), items))


# one core per task: the shard runs its episodes in sequence and Ray runs as
# many shards at once as there are cores
_ENV = {"env_vars": {"RAYON_NUM_THREADS": "1"}}


def _sweep_task(meta: str) -> str:
    return _core.sweep_shard(meta)


def _calibration_task(
    seed: int, quick: bool, episodes: Optional[int], i: int, n: int, fallback: Optional[str]
) -> str:
    return _core.calibration_shard(seed, quick, episodes, i, n, fallback)


def _sets(overrides: Optional[dict]) -> list[str]:
    return _core.override_sets(overrides)


_MAX_SEED = 2**63 - 1


def _seed_range(seeds: Iterable[int]) -> tuple[int, int]:
    if isinstance(seeds, range):
        # range's own len() overflows beyond sys.maxsize
        if seeds.step != 1 or seeds.stop <= seeds.start:
            raise InputError("seeds: expected a non-empty range with step 1, e.g. range(0, 100)")
        start, stop = seeds.start, seeds.stop
    else:
        seeds = list(seeds)
        for x in seeds:
            if not isinstance(x, numbers.Integral) or isinstance(x, bool):
                raise InputError(f"seeds: {x!r} is not an integer seed")
        s = sorted(int(x) for x in seeds)
        # consecutive: distinct, and as many as the span (no list of the span)
        if not s or len(set(s)) != len(s) or s[-1] - s[0] + 1 != len(s):
            raise InputError("seeds: expected consecutive seeds, e.g. range(0, 100)")
        start, stop = s[0], s[-1] + 1
    # a negative start is named by the library's check
    if stop - 1 > _MAX_SEED:
        raise InputError(f"seeds: {start}..{stop}: seeds are at most {_MAX_SEED} (2^63 − 1)")
    return start, stop


def seeds(
    scenario: Union[str, os.PathLike],
    seeds: Iterable[int],
    overrides: Optional[dict] = None,
    shards: Optional[int] = None,
    address: Optional[str] = None,
    num_cpus: Optional[int] = None,
    rows: bool = False,
) -> dict:
    """Runs ``scenario`` once per seed as Ray tasks and returns the summary
    of ``bayes-cbf run SCENARIO --seeds A..B`` (``sweep_summary.json``): the
    count of each outcome with its Wilson interval. A seed whose run stops
    with an error is counted in ``"stopped"`` and listed, with its error, in
    ``"stopped_seeds"``; if every seed stops, ``InputError`` names the first.

    ``shards`` tasks (default: the cluster's CPUs) each run every
    ``shards``-th seed. ``address`` selects a Ray cluster (default: start or
    reuse a local Ray with ``num_cpus``). With ``rows=True`` the summary
    gains ``"rows"``, the text of ``sweep.csv``.
    """
    if isinstance(scenario, os.PathLike):
        scenario = os.fspath(scenario)
    start, end = _seed_range(seeds)
    sets = _sets(overrides)
    # fail fast on a bad seed range, before Ray starts
    _core.sweep_meta(scenario, start, end, sets)
    ray = _init(address, num_cpus)
    n = _shard_count(ray, shards, end - start)
    metas = [_core.sweep_meta(scenario, start, end, sets, i, n) for i in range(n)]
    # fail fast on a bad scenario or override, before any task runs
    _core.check_scenario(scenario, sets + [f"seed={start}"])
    task = ray.remote(num_cpus=1)(_sweep_task).options(runtime_env=_ENV)
    csvs = ray.get([task.remote(m) for m in metas])
    summary_json, csv = _core.sweep_merge(list(zip(metas, csvs)))
    summary = json.loads(summary_json)
    if rows:
        summary["rows"] = csv
    return summary


def calibration(
    episodes: Optional[int] = None,
    seed: int = 0,
    quick: bool = False,
    shards: Optional[int] = None,
    address: Optional[str] = None,
    num_cpus: Optional[int] = None,
    fallback: Optional[str] = None,
) -> dict:
    """Runs ``bayes-cbf run calibration`` as Ray tasks and returns its
    ``summary.json`` (as a dict; ``"episodes_csv"`` holds ``episodes.csv``).

    ``episodes`` per (system, truth) (default 200, or 12 with ``quick``),
    ``seed`` as ``--seed``, ``fallback`` as ``--fallback`` (``"relax"``,
    the default, ``"max_margin"``, ``"brake"`` or ``"hold"``); ``shards``,
    ``address`` and ``num_cpus`` as in :func:`seeds`.
    """
    # fail fast on bad arguments, before Ray starts
    _core.calibration_check(seed, quick, episodes, fallback)
    ray = _init(address, num_cpus)
    n = _shard_count(ray, shards, 10**9)
    task = ray.remote(num_cpus=1)(_calibration_task).options(runtime_env=_ENV)
    parts = ray.get([task.remote(seed, quick, episodes, i, n, fallback) for i in range(n)])
    summary_json, csv = _core.calibration_merge(parts)
    summary = json.loads(summary_json)
    summary["episodes_csv"] = csv
    return summary
