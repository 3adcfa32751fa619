"""Monte Carlo studies of estimators: `monte_carlo` runs every (estimator, seed) pair, serially or
on a Dask cluster, and returns a `StudyResult` (a pandas table of metrics per run).

The estimator interface (what a factory must return):

* ``update(u, y)``: one step with the input u(t) (``None`` when the system has no input) and the
  output y(t) (``None`` when the output is missing); the return value is ignored;
* ``x``: the estimate after the update, read right after each call (any shape with n values);
* ``form`` (optional): ``"prediction"`` if ``x`` after update t estimates x(t+1) (GPMHE's
  default form, an EKF's x̂(t+1|t)), ``"filtering"`` if it estimates x(t). Without the
  attribute, ``"prediction"`` is assumed;
* ``success`` (optional): ``False`` after an update whose solver did not converge; such updates
  are counted in the table's ``unconverged`` column.

`GPMHE` has this interface; `FilterAdapter` gives it to a filterpy-style filter
(``update(y)`` then ``predict(u)``, e.g. `gpmhe.baselines.ExactEKF`, `gpmhe.RGPEKF`).

pandas (always) and dask.distributed (with a cluster) are the optional ``distributed`` extra;
importing this module needs neither.
"""

from __future__ import annotations

import inspect
import math
import time
import traceback
import warnings
from typing import Any, Callable, Dict, Mapping, Optional, Sequence, Tuple

import numpy as np

from gpmhe._validation import boolean, float_array, integer, one_of

__all__ = ["monte_carlo", "StudyResult", "FilterAdapter", "default_metrics"]

_EXTRA = ("pip install pandas 'dask[distributed]' (without a network, from a wheelhouse made with "
          "--extras distributed: pip install --no-index --find-links wheelhouse 'gpmhe[distributed]')")


def _pandas():
    try:
        import pandas
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(f"gpmhe.monte_carlo needs pandas: {_EXTRA}") from exc
    return pandas


# ----------------------------------------------------------------------------------- metrics


def _rmse(est, truth, times):
    return float(np.sqrt(np.mean(np.sum((est - truth) ** 2, axis=1))))


def _rmse_late(est, truth, times):
    half = len(est) // 2
    return _rmse(est[half:], truth[half:], times[half:])


def _final_error(est, truth, times):
    return float(np.linalg.norm(est[-1] - truth[-1]))


def _ms_per_update(est, truth, times):
    return float(1e3 * np.median(times))


def default_metrics() -> Dict[str, Callable]:
    """The metrics `monte_carlo` computes when none are given.

    Returns
    -------
    dict
        ``"rmse"``: the RMSE of ‖x̂ − x‖ over the run; ``"rmse_late"``: the same over the second
        half of the run (rows ``T // 2`` to ``T − 1``); ``"final_error"``: ‖x̂ − x‖ at the last
        step; ``"ms_per_update"``: the median time of one ``update`` call in milliseconds. Each is
        ``fn(estimates (T, n), truth (T, n), times (T,)) -> float``.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.study import default_metrics
    >>> m = default_metrics()
    >>> list(m)
    ['rmse', 'rmse_late', 'final_error', 'ms_per_update']
    >>> est, truth = np.array([[0.0], [1.0]]), np.array([[0.0], [0.0]])
    >>> m["rmse"](est, truth, np.ones(2)), m["final_error"](est, truth, np.ones(2))
    (0.7071067811865476, 1.0)
    """
    return {"rmse": _rmse, "rmse_late": _rmse_late, "final_error": _final_error,
            "ms_per_update": _ms_per_update}


# ----------------------------------------------------------------------------------- adapter


class FilterAdapter:
    """A filterpy-style filter (``update(y)``, ``predict(u)``) as a `monte_carlo` estimator.

    ``update(u, y)`` calls ``filter.update(y)`` (skipped when y is None: a missing output), then
    ``filter.predict()`` (``filter.predict(u)`` when u is not None), so ``x`` is x̂(t+1|t):
    the prediction form.

    Parameters
    ----------
    filter : object
        Any object with ``update(y)``, ``predict()`` / ``predict(u)`` and ``x``, e.g. filterpy's
        ``KalmanFilter`` or ``ExtendedKalmanFilter``, `gpmhe.baselines.ExactEKF`,
        `gpmhe.baselines.GPEKF`, `gpmhe.RGPEKF`.

    Attributes
    ----------
    filter : object
        The wrapped filter.
    form : str
        ``"prediction"``.

    Examples
    --------
    >>> import numpy as np
    >>> from gpmhe.baselines import ExactEKF
    >>> from gpmhe.study import FilterAdapter
    >>> from gpmhe.systems import batch_reactor as br
    >>> ekf = ExactEKF(br.f, br.f_jacobian, br.h, br.h_jacobian, [3.0, 1.0], 0.1 * np.eye(2),
    ...                1e-3 * np.eye(2), 1e-2)
    >>> est = FilterAdapter(ekf)
    >>> est.update(None, [4.0])
    >>> print(np.round(est.x, 3))           # x̂(1|0) = f(x̂(0|0))
    [2.713 1.143]
    """

    form = "prediction"

    def __init__(self, filter: Any):
        for attr in ("update", "predict"):
            if not callable(getattr(filter, attr, None)):
                raise ValueError(f"filter: must have a method {attr}(), got {type(filter).__name__}")
        self.filter = filter

    def update(self, u: Any, y: Any) -> None:
        """One step: ``filter.update(y)`` (unless y is None), then ``filter.predict([u])``.

        Parameters
        ----------
        u : array_like or None
            Input u(t), passed to ``predict``; None calls ``predict()``.
        y : array_like or None
            Output y(t); None skips the measurement update.

        Examples
        --------
        >>> import numpy as np
        >>> from filterpy.kalman import KalmanFilter
        >>> from gpmhe.study import FilterAdapter
        >>> kf = KalmanFilter(dim_x=1, dim_z=1)
        >>> kf.x, kf.F, kf.H, kf.P = np.zeros((1, 1)), np.eye(1), np.eye(1), np.eye(1)
        >>> est = FilterAdapter(kf)
        >>> est.update(None, [1.0])
        >>> est.x
        array([0.5])
        """
        if y is not None:
            self.filter.update(y)
        if u is None:
            self.filter.predict()
        else:
            self.filter.predict(u)

    @property
    def x(self) -> np.ndarray:
        """The filter's estimate as a vector."""
        return np.asarray(self.filter.x, dtype=float).ravel()


# ----------------------------------------------------------------------------------- one run


def _call_factory(factory, seed):
    """A factory with a parameter named ``seed`` gets the seed; any other is called bare."""
    try:
        params = inspect.signature(factory).parameters
    except (TypeError, ValueError):
        params = {}
    return factory(seed=seed) if "seed" in params else factory()


def _simulated(sim, seed):
    """Check simulate's (U, Y, X): shapes (T, m) or None, (T, p), (T + 1, n)."""
    if not isinstance(sim, tuple) or len(sim) != 3:
        raise ValueError(f"simulate: must return a tuple (U, Y, X), got {type(sim).__name__}")
    U, Y, X = sim
    try:
        Y = np.asarray(Y, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"simulate: Y must be an array of numbers, got {type(Y).__name__}") from None
    if Y.ndim != 2:
        raise ValueError(f"simulate: Y must be (T, p), got shape {Y.shape}")
    float_array("simulate: Y", np.where(np.isnan(Y), 0.0, Y))  # NaN = missing; no inf
    T = len(Y)
    X = float_array("simulate: X", X, 2)
    if T == 0 or X.shape[0] != T + 1:
        raise ValueError(f"simulate: X must be (T + 1, n) finite true states for Y of {T} rows, "
                         f"got shape {X.shape} (seed {seed})")
    if U is not None:
        U = float_array("simulate: U", U)
        if U.ndim != 2 or U.shape[0] != T:
            raise ValueError(f"simulate: U must be None or ({T}, m), got shape {U.shape}")
    return U, Y, X


def _run_one(factory, simulate, metrics, seed):
    """One (estimator, seed) run: (metric values, unconverged updates, update times)."""
    U, Y, X = _simulated(simulate(seed), seed)
    est = _call_factory(factory, seed)
    form = one_of("form", getattr(est, "form", "prediction"), ("prediction", "filtering"))
    T, n = len(Y), X.shape[1]
    xs, times, unconverged = np.empty((T, n)), np.empty(T), 0
    missing = np.isnan(Y).any(axis=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # counted in `unconverged` instead
        for t in range(T):
            u = None if U is None else U[t]
            y = None if missing[t] else Y[t]
            t0 = time.perf_counter()
            est.update(u, y)
            times[t] = time.perf_counter() - t0
            xs[t] = np.asarray(est.x, dtype=float).ravel()
            if not np.all(np.isfinite(xs[t])):
                raise FloatingPointError(f"the estimate at t={t} is not finite: {xs[t]}")
            unconverged += getattr(est, "success", True) is False
    truth = X[1:] if form == "prediction" else X[:-1]
    values = {name: float(fn(xs, truth, times)) for name, fn in metrics.items()}
    return values, unconverged, times


def _run_chunk(payload, name, seeds):
    """Runs of one estimator over some seeds; a failing run becomes its row's error message.

    A run that raises SystemExit (``sys.exit`` in a user's function) is a failed run too: on a
    cluster it would otherwise end the worker process and lose the other seeds of its task.
    KeyboardInterrupt still stops the study."""
    estimators, simulate, metrics = payload
    out = []
    for seed in seeds:
        try:
            values, unconverged, times = _run_one(estimators[name], simulate, metrics, seed)
            out.append((name, seed, values, unconverged, times, None))
        except (Exception, SystemExit) as exc:  # reported in the row: one bad run must not end the study
            out.append((name, seed, {}, None, None, _message(exc)))
    return out


def _message(exc):
    return "".join(traceback.format_exception_only(type(exc), exc)).strip()


# ----------------------------------------------------------------------------------- result


class StudyResult:
    """The result of `monte_carlo`.

    Parameters
    ----------
    table : pandas.DataFrame
        One row per (estimator, seed) run, in the order of ``estimators`` then ``seeds``: columns
        ``estimator``, ``seed``, one per metric (NaN for a failed run), ``unconverged`` (updates
        whose estimator reported ``success=False``) and ``error`` (None, or the failure message).
    times : dict
        ``(estimator, seed) -> ndarray (T,)``: the time of every update in seconds (failed runs
        are absent).
    metrics : list of str
        The metric names (columns of ``table``).

    Attributes
    ----------
    table : pandas.DataFrame
        As given.
    times : dict
        As given.
    metrics : list of str
        As given.

    Examples
    --------
    `monte_carlo` builds it; the table can also be read back (e.g. from a saved CSV):

    >>> import pandas as pd
    >>> from gpmhe.study import StudyResult
    >>> table = pd.DataFrame({"estimator": ["a", "b"], "seed": [0, 0], "rmse": [0.1, None],
    ...                       "unconverged": [0, None], "error": [None, "ValueError: bad"]})
    >>> StudyResult(table, {}, ["rmse"])
    StudyResult(2 runs, 1 failed)
    """

    def __init__(self, table: Any, times: Dict[Tuple[str, int], np.ndarray], metrics: Sequence[str]):
        self.table, self.times, self.metrics = table, times, list(metrics)

    def summary(self) -> Any:
        """Per estimator: mean, median and std of each metric over its successful runs, and the
        number of runs and of failed runs.

        Returns
        -------
        pandas.DataFrame
            Indexed by estimator (in the study's order); columns ``(metric, statistic)`` and
            ``("runs", "")``, ``("failed", "")``.

        Examples
        --------
        >>> import numpy as np
        >>> import pandas as pd
        >>> from gpmhe.study import StudyResult
        >>> table = pd.DataFrame({"estimator": ["a", "a"], "seed": [0, 1], "rmse": [1.0, 3.0],
        ...                       "unconverged": [0, 0], "error": [None, None]})
        >>> StudyResult(table, {}, ["rmse"]).summary()["rmse"]
                  mean  median       std
        estimator
        a          2.0     2.0  1.414214
        """
        t = self.table
        stats = t.groupby("estimator", sort=False)[self.metrics].agg(["mean", "median", "std"])
        groups = t.groupby("estimator", sort=False)
        stats[("runs", "")] = groups.size()
        stats[("failed", "")] = groups["error"].apply(lambda e: int(e.notna().sum()))
        return stats

    def __repr__(self) -> str:
        return f"StudyResult({len(self.table)} runs, {int(self.table['error'].notna().sum())} failed)"


# ----------------------------------------------------------------------------------- the study


def monte_carlo(estimators: Mapping[str, Callable], simulate: Callable[[int], tuple],
                seeds: Sequence[int], metrics: Optional[Mapping[str, Callable]] = None,
                client: Any = None, progress: bool = True, *, chunk_size: Optional[int] = None,
                retries: int = 2) -> StudyResult:
    """Run every estimator on every seed's simulation and tabulate metrics of each run.

    For each (estimator, seed) pair: ``simulate(seed)`` gives the run's data, the estimator's
    factory builds a fresh estimator, and the estimator is fed ``update(u(t), y(t))`` for
    t = 0 … T−1; its ``x`` after each update is compared with the true state it estimates.

    Parameters
    ----------
    estimators : mapping of str to callable
        Name -> factory. A factory builds a fresh estimator: ``factory()``, or ``factory(seed=s)``
        if it has a parameter named ``seed`` (for estimators whose model depends on the run, e.g.
        GPs trained on the seed's data). The estimator must have ``update(u, y)`` and ``x``, and
        may have ``form`` and ``success`` (see the module's description): a `gpmhe.GPMHE`, or a
        filterpy-style filter wrapped in `FilterAdapter`.
    simulate : callable
        ``simulate(seed) -> (U, Y, X)``: inputs U of shape (T, m) or None, outputs Y of shape
        (T, p) (a row with a NaN is a missing output: the estimator gets ``y=None``), true states
        X of shape (T + 1, n), X[t] = x(t).
    seeds : sequence of int
        The seeds, each >= 0.
    metrics : mapping of str to callable, optional
        Name -> ``fn(estimates (T, n), truth (T, n), times (T,)) -> float``, where ``estimates[t]``
        is ``x`` after update t, ``truth[t]`` the state it estimates — x(t + 1) = X[t + 1] for the
        prediction form, x(t) = X[t] for the filtering form — and ``times[t]`` the duration of
        update t in seconds. Default: `default_metrics` (RMSE, RMSE over the second half, final
        error, median ms per update).
    client : dask.distributed.Client, optional
        Run on this cluster; None (the default) runs serially in this process. The factories,
        ``simulate`` and the metrics (and so the models they hold) are scattered once to every
        worker; each task is a chunk of seeds of one estimator.
    progress : bool, default True
        Show a progress bar on stderr (tqdm if installed, else one line per 10 %).
    chunk_size : int, optional
        Seeds per task on a cluster. Default: about 8 tasks per worker thread over the whole
        study, at most all seeds of one estimator.
    retries : int, default 2
        On a cluster, how often a task whose worker failed is retried (a task whose worker died
        is also rescheduled by Dask, up to ``distributed.scheduler.allowed-failures`` times);
        a task of several seeds that still fails is split into single seeds run one at a time,
        so that only a seed whose run kills its worker fails, with the message in its row.

    Returns
    -------
    StudyResult
        ``table`` (one row per run; the failure message in ``error`` when a run raised, called
        ``sys.exit``, or produced an estimate that is not finite), update ``times`` and
        ``summary()``. The metrics are the same serially and on any cluster (only
        times differ).

    Raises
    ------
    ValueError
        Bad arguments (an error naming the argument), among them a ``client`` whose cluster has
        no workers and gets none within `WORKER_WAIT` seconds. Errors inside a run do not
        raise: they are reported in its row.
    ImportError
        pandas (or, with a client, dask.distributed) is not installed:
        ``pip install pandas 'dask[distributed]'`` (the ``distributed`` extra).

    See Also
    --------
    FilterAdapter : A filterpy-style filter as an estimator.

    Notes
    -----
    Updates are timed with ``time.perf_counter`` around ``update`` alone. ``RuntimeWarning`` from
    the estimators (GPMHE's "window solver did not converge") is silenced inside a run and
    counted in ``unconverged``. Functions sent to a cluster must pickle: module-level functions
    and `functools.partial` of them always do; Dask's cloudpickle also sends lambdas and
    closures.

    Examples
    --------
    The exact-model MHE on the batch reactor, 3 seeds of 20 steps:

    >>> import numpy as np
    >>> import gpmhe
    >>> from gpmhe.systems import batch_reactor as br
    >>> model = gpmhe.KnownModel(br.f, br.h, 2, 1)
    >>> def simulate(seed):
    ...     x, y = br.simulate(br.X_TRUE0, 20, np.random.default_rng(seed))
    ...     return None, y[:20], x
    >>> def mhe():
    ...     return gpmhe.GPMHE(model, br.X_PRIOR0, x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    >>> result = gpmhe.monte_carlo({"MHE": mhe}, simulate, seeds=range(3), progress=False)
    >>> list(result.table.columns)
    ['estimator', 'seed', 'rmse', 'rmse_late', 'final_error', 'ms_per_update', 'unconverged', 'error']
    >>> result.table[["seed", "final_error", "error"]].round(2)
       seed  final_error error
    0     0         0.04  None
    1     1         0.13  None
    2     2         0.03  None
    >>> result.summary()["failed"]
    estimator
    MHE    0
    Name: failed, dtype: int64
    """
    pd = _pandas()
    if not isinstance(estimators, Mapping) or not estimators:
        raise ValueError("estimators: must be a non-empty mapping of names to factories")
    for name, factory in estimators.items():
        if not isinstance(name, str) or not callable(factory):
            raise ValueError(f"estimators: every key must be a str and every value a callable "
                             f"factory, got {name!r}: {factory!r}")
    if not callable(simulate):
        raise ValueError(f"simulate: must be callable, got {simulate!r}")
    if isinstance(seeds, (str, bytes)) or not hasattr(seeds, "__iter__"):
        raise ValueError(f"seeds: must be a sequence of integers, got {seeds!r}")
    seeds = [integer("seeds", s) for s in seeds]
    if not seeds:
        raise ValueError("seeds: must not be empty")
    metrics = default_metrics() if metrics is None else metrics
    if not isinstance(metrics, Mapping) or not metrics or not all(
            isinstance(k, str) and callable(v) for k, v in metrics.items()):
        raise ValueError("metrics: must be a non-empty mapping of names to functions")
    reserved = {"estimator", "seed", "unconverged", "error"} & set(metrics)
    if reserved:
        raise ValueError(f"metrics: names {sorted(reserved)} are reserved for the table's columns")
    progress = boolean("progress", progress)
    retries = integer("retries", retries)
    if chunk_size is not None:
        chunk_size = integer("chunk_size", chunk_size, low=1)
    estimators, metrics = dict(estimators), dict(metrics)
    payload = (estimators, simulate, metrics)
    names = list(estimators)

    if client is None:
        rows = []
        bar = _Progress(len(names) * len(seeds), progress)
        for name in names:
            for seed in seeds:
                rows.extend(_run_chunk(payload, name, [seed]))
                bar.update(1)
        bar.close()
    else:
        rows = _on_cluster(client, payload, names, seeds, chunk_size, retries, progress)

    order = {(name, seed): i for i, (name, seed) in
             enumerate((n, s) for n in names for s in seeds)}
    rows.sort(key=lambda r: order[(r[0], r[1])])
    records, times = [], {}
    for name, seed, values, unconverged, ts, error in rows:
        rec = {"estimator": name, "seed": seed}
        rec.update({m: values.get(m, math.nan) for m in metrics})
        rec["unconverged"] = unconverged
        rec["error"] = error
        records.append(rec)
        if ts is not None:
            times[(name, seed)] = ts
    columns = ["estimator", "seed", *metrics, "unconverged", "error"]
    table = pd.DataFrame.from_records(records, columns=columns)
    table["unconverged"] = table["unconverged"].astype("Int64")
    table["error"] = table["error"].astype(object).where(table["error"].notna(), None)
    return StudyResult(table, times, list(metrics))


def _on_cluster(client, payload, names, seeds, chunk_size, retries, progress):
    """Scatter the payload once to every worker, submit chunks of seeds per estimator, collect
    rows as they complete; a task that fails for good fills its rows with the message."""
    try:
        from distributed import as_completed
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(f"gpmhe.monte_carlo(client=...) needs dask.distributed: {_EXTRA}") from exc
    if not callable(getattr(client, "submit", None)) or not callable(getattr(client, "scatter", None)):
        raise ValueError(f"client: must be a dask.distributed.Client or None, got {client!r}")
    _wait_for_workers(client)
    if chunk_size is None:
        threads = max(1, sum(client.nthreads().values()))
        chunk_size = max(1, math.ceil(len(names) * len(seeds) / (8 * threads)))
    chunk_size = min(chunk_size, len(seeds))
    try:
        [shared] = client.scatter([payload], broadcast=True, hash=False)
    except Exception as exc:
        culprit = _unpicklable(payload)
        if culprit is None:  # it pickles: the cluster refused it for another reason
            raise RuntimeError(f"client: sending the study to the cluster failed: {_message(exc)}") from exc
        raise ValueError(f"{culprit}: must pickle to be sent to the cluster "
                         f"(module-level functions, or closures over picklable objects): "
                         f"{_message(exc)}") from exc
    futures = {}
    for name in names:
        for i in range(0, len(seeds), chunk_size):
            chunk = seeds[i:i + chunk_size]
            fut = client.submit(_run_chunk, shared, name, chunk, retries=retries, pure=False)
            futures[fut] = (name, chunk)
    rows = []
    bar = _Progress(len(names) * len(seeds), progress)
    running = as_completed(futures)
    # Seeds of chunks that failed for good, run one task at a time: a seed that kills its worker
    # then fails alone (Dask also blames the tasks queued on a dying worker).
    alone, split = [], set()

    def run_next_alone():
        if alone and not split:
            name, seed = alone.pop(0)
            # The task carries the study itself: dead workers may take every scattered copy.
            single = client.submit(_run_chunk, payload, name, [seed], retries=retries, pure=False)
            futures[single] = (name, [seed])
            split.add(single)
            running.add(single)

    try:
        for fut in running:
            name, chunk = futures[fut]
            split.discard(fut)
            try:
                rows.extend(fut.result())
            except Exception as exc:  # the task failed for good (e.g. KilledWorker)
                if len(chunk) > 1:
                    alone.extend((name, seed) for seed in chunk)
                    run_next_alone()
                    continue
                msg = f"task failed: {_message(exc)}"
                rows.extend((name, seed, {}, None, None, msg) for seed in chunk)
            bar.update(len(chunk))
            run_next_alone()
    finally:
        bar.close()
        client.cancel(list(futures) + [shared])
    return rows


#: How long `monte_carlo` waits for a cluster without workers to get one (seconds).
WORKER_WAIT = 10.0


def _wait_for_workers(client):
    """Fail early and clearly when the cluster has no workers (the tasks would wait forever, and
    sending the study would time out with a misleading message)."""
    if client.nthreads():
        return
    try:
        client.wait_for_workers(1, timeout=WORKER_WAIT)
    except Exception as exc:  # TimeoutError (asyncio's or dask's), or a closed client
        raise ValueError(f"client: the cluster has no workers (none joined within {WORKER_WAIT:g} s); "
                         f"start workers or check the scheduler address ({_message(exc)})") from None


def _unpicklable(payload):
    """The name of the first argument of the payload that cloudpickle cannot pickle, or None."""
    import cloudpickle

    for name, obj in zip(("estimators", "simulate", "metrics"), payload):
        try:
            cloudpickle.dumps(obj)
        except Exception:
            return name
    return None


class _Progress:
    """tqdm on stderr if installed, else a line every 10 %; nothing when disabled."""

    def __init__(self, total, enabled):
        self.total, self.done, self.enabled, self.bar, self.next = total, 0, enabled, None, 0.1
        if enabled:
            try:
                from tqdm.auto import tqdm

                self.bar = tqdm(total=total, unit="run", desc="monte_carlo")
            except ImportError:
                pass

    def update(self, k):
        self.done += k
        if self.bar is not None:
            self.bar.update(k)
        elif self.enabled and self.done >= self.next * self.total:
            import sys

            print(f"monte_carlo: {self.done}/{self.total} runs", file=sys.stderr, flush=True)
            self.next = math.floor(10 * self.done / self.total + 1) / 10

    def close(self):
        if self.bar is not None:
            self.bar.close()
