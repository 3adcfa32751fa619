"""Long runs: thousands of updates keep memory flat (Python objects and the process's resident
set) and every estimate finite. benches/long_run.py runs 10^5 updates and prints the table."""

import os
import tracemalloc
import warnings

import numpy as np
import pytest

from gpmhe import GPMHE, KnownModel
from gpmhe.systems import batch_reactor as br

from conftest import fitted_reactor_model

UPDATES, WARMUP = 3000, 500


def rss_bytes():
    """The process's resident set size now (Linux), or None."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


def models():
    known = KnownModel(br.f_batch, br.h_batch, 2, 1, vectorized=True,
                       f_jacobian=br.f_jacobian_batch, h_jacobian=br.h_jacobian_batch)
    return {"known (vectorized)": lambda: known, "learned": lambda: fitted_reactor_model(11, 1)}


@pytest.mark.parametrize("name", list(models()))
def test_thousands_of_updates_keep_memory_flat_and_estimates_finite(name):
    model = models()[name]()
    ys = br.simulate(br.X_TRUE0, UPDATES, np.random.default_rng(7))[1]
    ys[::10] = np.nan  # every tenth output missing
    mhe = GPMHE(model, x0=[3.0, 1.0], x_bounds=br.X_BOUNDS, **br.MHE_SETTINGS)
    finite = True
    tracemalloc.start()
    try:
        # (a window that stops without converging warns; that is not what this test checks)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            for i, y in enumerate(ys[:UPDATES]):
                if i == WARMUP:  # the window is full and every buffer has its final size
                    py0, _ = tracemalloc.get_traced_memory()
                    rss0 = rss_bytes()
                mhe.update(None, None if np.isnan(y).any() else y)
                finite &= bool(np.isfinite(mhe.x).all() and np.isfinite(mhe.P).all()
                               and np.isfinite(mhe.cost))
        py1, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    rss1 = rss_bytes()
    assert finite
    assert mhe.t == UPDATES
    # Python allocations: no per-update growth (well under 100 bytes per update)
    assert py1 - py0 < 256 * 1024, py1 - py0
    # resident set (Rust buffers included): no growth beyond allocator noise
    if rss0 is not None and rss1 is not None:
        assert rss1 - rss0 < 4 * 1024 * 1024, rss1 - rss0
