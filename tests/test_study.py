"""gpmhe.monte_carlo: the serial table (columns, metric values against a direct computation),
failing runs reported in their rows, a 2-process LocalCluster giving the serial table, and a
worker killed during a study. The functions sent to the cluster are module-level."""

import functools
import os
import pathlib
import sys

import numpy as np
import pytest

pd = pytest.importorskip("pandas")

import gpmhe  # noqa: E402
from gpmhe import GPMHE, KnownModel  # noqa: E402
from gpmhe.baselines import ExactEKF  # noqa: E402
from gpmhe.study import FilterAdapter, default_metrics  # noqa: E402
from gpmhe.systems import batch_reactor as br  # noqa: E402

STEPS = 20
SEEDS = [0, 1, 2, 3]
MODEL = KnownModel(br.f_batch, br.h_batch, 2, 1, f_jacobian=br.f_jacobian_batch,
                   h_jacobian=br.h_jacobian_batch, vectorized=True)


def simulate(seed, steps=STEPS):
    x, y = br.simulate(br.X_TRUE0, steps, np.random.default_rng(seed))
    y = y[:steps].copy()
    y[5] = np.nan  # one missing output per run
    return None, y, x


def mhe(form="prediction"):
    return GPMHE(MODEL, br.X_PRIOR0, x_bounds=br.X_BOUNDS, form=form, **br.MHE_SETTINGS)


def ekf():
    return FilterAdapter(ExactEKF(br.f, br.f_jacobian, br.h, br.h_jacobian, br.X_PRIOR0,
                                  np.eye(2), br.SIGMA_W**2 * np.eye(2), br.SIGMA_V**2 * np.eye(1)))


def broken_factory():
    raise RuntimeError("no estimator today")


def simulate_fails_on_2(seed):
    if seed == 2:
        raise ValueError("bad seed")
    return simulate(seed)


def max_abs_error(est, truth, times):
    return float(np.abs(est - truth).max())


ESTIMATORS = {"MHE": mhe, "MHE filtering": functools.partial(mhe, form="filtering"), "EKF": ekf}
METRIC_COLUMNS = ["rmse", "rmse_late", "final_error"]  # the deterministic ones


def direct_run(factory, seed):
    """The run done by hand: estimates (T, n) and the truth each estimates."""
    _, y, x = simulate(seed)
    est = factory()
    xs = []
    for t in range(len(y)):
        est.update(None, None if np.isnan(y[t]).any() else y[t])
        xs.append(np.array(est.x, dtype=float).ravel())
    xs = np.array(xs)
    return xs, (x[1:] if getattr(est, "form", "prediction") == "prediction" else x[:-1])


@pytest.fixture(scope="module")
def serial():
    return gpmhe.monte_carlo(ESTIMATORS, simulate, SEEDS, progress=False)


def test_serial_table(serial):
    t = serial.table
    assert list(t.columns) == ["estimator", "seed", "rmse", "rmse_late", "final_error",
                               "ms_per_update", "unconverged", "error"]
    assert list(t["estimator"]) == [n for n in ESTIMATORS for _ in SEEDS]
    assert list(t["seed"]) == SEEDS * len(ESTIMATORS)
    assert t["error"].isna().all() and t["error"].map(lambda e: e is None).all()
    assert (t["ms_per_update"] > 0).all()
    for name in ("MHE", "MHE filtering", "EKF"):
        xs, truth = direct_run(ESTIMATORS[name], 1)
        row = t[(t.estimator == name) & (t.seed == 1)].iloc[0]
        err = np.linalg.norm(xs - truth, axis=1)
        assert row["rmse"] == pytest.approx(np.sqrt(np.mean(err**2)), rel=1e-12)
        assert row["rmse_late"] == pytest.approx(np.sqrt(np.mean(err[STEPS // 2:] ** 2)), rel=1e-12)
        assert row["final_error"] == pytest.approx(err[-1], rel=1e-12)
    assert len(serial.times[("MHE", 0)]) == STEPS
    s = serial.summary()
    assert list(s.index) == list(ESTIMATORS)
    assert s.loc["MHE", ("rmse", "mean")] == pytest.approx(t[t.estimator == "MHE"].rmse.mean())
    assert (s[("failed", "")] == 0).all() and (s[("runs", "")] == len(SEEDS)).all()


def test_user_metrics_and_seeded_factory():
    seen = []

    def seeded(seed):
        seen.append(seed)
        return mhe()

    r = gpmhe.monte_carlo({"MHE": seeded}, simulate, [3, 1], metrics={"maxerr": max_abs_error},
                          progress=False)
    assert seen == [3, 1] and list(r.table.columns) == ["estimator", "seed", "maxerr",
                                                       "unconverged", "error"]
    xs, truth = direct_run(mhe, 1)
    assert r.table.maxerr.iloc[1] == pytest.approx(np.abs(xs - truth).max(), rel=1e-12)


def test_failures_are_reported_in_their_rows():
    r = gpmhe.monte_carlo({"MHE": mhe, "broken": broken_factory}, simulate_fails_on_2, [1, 2],
                          progress=False)
    t = r.table.set_index(["estimator", "seed"])
    assert t.loc[("MHE", 1), "error"] is None and np.isfinite(t.loc[("MHE", 1), "rmse"])
    assert t.loc[("MHE", 2), "error"] == "ValueError: bad seed"
    assert np.isnan(t.loc[("MHE", 2), "rmse"])
    assert t.loc[("broken", 1), "error"] == "RuntimeError: no estimator today"
    assert list(r.summary()[("failed", "")]) == [1, 2]


@pytest.mark.parametrize("kwargs, name", [
    (dict(estimators={}), "estimators"), (dict(estimators={"a": 1}), "estimators"),
    (dict(simulate=3), "simulate"), (dict(seeds=[-1]), "seeds"), (dict(seeds=[]), "seeds"),
    (dict(seeds=[0.5]), "seeds"), (dict(metrics={"m": 2}), "metrics"),
    (dict(metrics={"error": max_abs_error}), "metrics"), (dict(progress=1), "progress"),
    (dict(client="tcp://nowhere"), "client"),
])
def test_bad_arguments(kwargs, name):
    args = dict(estimators={"MHE": mhe}, simulate=simulate, seeds=[0], progress=False)
    args.update(kwargs)
    with pytest.raises(ValueError, match=f"^{name}:"):
        gpmhe.monte_carlo(**args)


# ------------------------------------------------------------------------------------ cluster


@pytest.fixture(scope="module")
def client():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        with distributed.Client(cluster) as c:
            yield c


def test_cluster_equals_serial(serial, client):
    r = gpmhe.monte_carlo(ESTIMATORS, simulate, SEEDS, client=client, progress=False, chunk_size=3)
    cols = ["estimator", "seed", *METRIC_COLUMNS, "unconverged", "error"]
    pd.testing.assert_frame_equal(r.table[cols], serial.table[cols])  # exactly equal numbers
    assert set(r.times) == set(serial.times)


def test_cluster_failure_in_row(client):
    r = gpmhe.monte_carlo({"MHE": mhe}, simulate_fails_on_2, [1, 2], client=client,
                          progress=False)
    assert list(r.table.error) == [None, "ValueError: bad seed"]


def test_unpicklable_payload_is_named(client):
    import threading

    lock = threading.Lock()

    def simulate_with_lock(seed):
        with lock:
            return simulate(seed)

    with pytest.raises(ValueError, match="^simulate: must pickle"):
        gpmhe.monte_carlo({"MHE": mhe}, simulate_with_lock, [0], client=client, progress=False)


def simulate_dies_once(seed, marker):
    """Kills its worker process the first time it runs seed 1 (the marker file says it did)."""
    marker = pathlib.Path(marker)
    if seed == 1 and not marker.exists():
        marker.write_text("killed once")
        os._exit(1)
    return simulate(seed)


def test_killed_worker_is_retried_or_reported(serial, client, tmp_path):
    """A worker that dies mid-study: Dask runs its task again elsewhere (the usual outcome) or,
    when the cluster gives up on it, the rows of that task report the failure; every other row
    equals the serial run and the study completes."""
    marker = tmp_path / "killed"
    r = gpmhe.monte_carlo({"MHE": mhe}, functools.partial(simulate_dies_once,
                                                          marker=str(marker)),
                          SEEDS, client=client, progress=False, chunk_size=1)
    assert marker.exists()  # a worker did die
    expected = serial.table[serial.table.estimator == "MHE"].reset_index(drop=True)
    cols = ["estimator", "seed", *METRIC_COLUMNS, "error"]
    failed = r.table.error.notna()
    assert set(r.table.seed[failed]) <= {1}  # only the killed task can have failed
    pd.testing.assert_frame_equal(r.table[cols][~failed], expected[cols][~failed])


def test_default_metrics_names():
    assert list(default_metrics()) == ["rmse", "rmse_late", "final_error", "ms_per_update"]


@pytest.mark.parametrize("module, kwargs", [("pandas", {}), ("distributed", {"client": object()})])
def test_missing_extra_names_the_install_line(monkeypatch, module, kwargs):
    monkeypatch.setitem(sys.modules, module, None)  # `import module` raises ImportError
    with pytest.raises(ImportError, match=r"pip install pandas 'dask\[distributed\]' .*"
                                          r"--find-links wheelhouse 'gpmhe\[distributed\]'"):
        gpmhe.monte_carlo({"MHE": mhe}, simulate, [0], progress=False, **kwargs)


# ------------------------------------------------------------------------ every run accounted


class _Diverging:
    """An estimator whose estimate turns NaN at its third update."""

    def __init__(self):
        self.t, self.x = 0, np.zeros(2)

    def update(self, u, y):
        self.t += 1
        self.x = np.full(2, np.nan) if self.t >= 3 else np.ones(2)


def diverging():
    return _Diverging()


def exits_on_2(seed):
    if seed == 2:
        sys.exit("seed 2 gives up")
    return mhe()


def test_a_nan_estimate_fails_its_run():
    r = gpmhe.monte_carlo({"NaN": diverging}, simulate, [0, 1], progress=False)
    assert list(r.table.error) == ["FloatingPointError: the estimate at t=2 is not finite: [nan nan]"] * 2
    assert list(r.summary()[("failed", "")]) == [2]


def test_sys_exit_fails_its_row_only(serial):
    r = gpmhe.monte_carlo({"MHE": exits_on_2}, simulate, SEEDS, progress=False)
    assert list(r.table.error.notna()) == [False, False, True, False]
    assert "seed 2 gives up" in r.table.error[2]
    ok = r.table.error.isna()
    expected = serial.table[serial.table.estimator == "MHE"].reset_index(drop=True)
    pd.testing.assert_frame_equal(r.table[METRIC_COLUMNS][ok], expected[METRIC_COLUMNS][ok])


def test_sys_exit_on_a_cluster_fails_its_row_only(client):
    r = gpmhe.monte_carlo({"MHE": exits_on_2}, simulate, SEEDS, client=client, progress=False,
                          chunk_size=4)
    assert list(r.table.error.notna()) == [False, False, True, False]


def simulate_kills_on_1(seed):
    if seed == 1:
        os._exit(1)  # kills the worker process every time
    return simulate(seed)


def test_a_seed_that_kills_its_worker_fails_alone(client):
    """A chunk of four seeds whose seed 1 kills every worker that runs it: the chunk is split
    into single seeds and only seed 1 fails."""
    r = gpmhe.monte_carlo({"MHE": mhe}, simulate_kills_on_1, SEEDS, client=client, progress=False,
                          chunk_size=4, retries=0)
    assert list(r.table.error.notna()) == [False, True, False, False]
    assert r.table.error[1].startswith("task failed")


def test_a_cluster_without_workers_is_an_early_clear_error(monkeypatch):
    distributed = pytest.importorskip("distributed")
    monkeypatch.setattr(gpmhe.study, "WORKER_WAIT", 1.0)
    with distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=None) as cluster:
        with distributed.Client(cluster) as c:
            with pytest.raises(ValueError, match="^client: the cluster has no workers"):
                gpmhe.monte_carlo({"MHE": mhe}, simulate, [0], client=c, progress=False)
