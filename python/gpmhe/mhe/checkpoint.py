"""Checkpoints of a `GPMHE`: its settings (`MHESettings.entries`) and the core's whole state
(history, last report, the learned model's cache) in a plain ``.npz`` file without pickles, and
back. Format 3 keeps the estimate and the last update's report only in the core's state; files of
formats 1 and 2, which also kept them as attributes, still load.
"""

from __future__ import annotations

import numpy as np

from gpmhe._npz import NpzReader
from gpmhe.mhe.settings import MHESettings

__all__ = ["FORMAT_VERSION", "save", "load"]

# 2: arrival cost, full weights, parameters, pending input; 3: the estimate and the last update's
# report only in the core's state (core_outcome_*), not also as attributes; 4: the output loss
# (loss, loss_scale); 5: the output covariance given with each sample in the history (core_r_given,
# core_r); 6: a model with a time step keeps each sample's interval as the last column of core_u;
# 7: the estimate and covariance before the last update and the window's covariances
# (core_outcome_x_before, core_outcome_P_before, core_outcome_P_window); 8: an estimator that
# learns (learning, learning_drift and its core state core_learning_*; no evaluation cache); 9: the
# learning state's cross covariance of the newest state and g and its posterior of g before the
# last update (core_learning_xg_cov, core_learning_*_before).
FORMAT_VERSION = 9

_CACHE_PARTS = ("d", "mean_x", "var_x", "dmean_x", "dvar_x", "mean_y", "var_y", "dmean_y",
                "dvar_y")


def save(est, path):
    """Write ``est`` to ``path`` (see `GPMHE.save`)."""
    settings = est._settings
    n, p, m, k = settings.dims
    np.savez(path, kind="GPMHE", format_version=FORMAT_VERSION,
             model_kind=type(est.model).__name__, dim_x=n, dim_y=p, dim_u=m, dim_p=k,
             **settings.entries(),
             **{"core_" + key: value for key, value in est._core.__getstate__().items()})


def load(cls, path, model):
    """The `GPMHE` (class ``cls``) saved at ``path``, on ``model`` (see `GPMHE.load`)."""
    with NpzReader(path, "GPMHE", FORMAT_VERSION) as f:
        f.allow_nonfinite = ("x_lower", "x_upper", "p_lower", "p_upper", "cost",
                             "projected_gradient", "core_outcome_cost",
                             "core_outcome_projected_gradient", "core_outcome_x_before",
                             "core_outcome_P_before", "core_outcome_P_window",
                             "core_learning_xg_cov", "core_learning_g_before",
                             "core_learning_g_cov_before", "core_learning_xg_cov_before",
                             "core_y")  # NaN: channels not measured (the core refuses inf)
        kind = f.string("model_kind")
        if kind not in ("LearnedModel", "KnownModel"):
            raise f.error("model_kind", f"must be 'LearnedModel' or 'KnownModel', got {kind!r}")
        if type(model).__name__ != kind:
            raise ValueError(f"model: the file {f.name} was saved with a {kind} (entry "
                             f"'model_kind'), got {type(model).__name__}")
        n, p, m = (f.integer(key) for key in ("dim_x", "dim_y", "dim_u"))
        k = f.integer("dim_p") if f.version >= 2 else 0
        if (getattr(model, "dim_x", None), getattr(model, "dim_y", None),
                getattr(model, "dim_u", None), getattr(model, "dim_p", 0)) != (n, p, m, k):
            raise ValueError(f"model: the file {f.name} was saved with dim_x={n}, "
                             f"dim_y={p}, dim_u={m}, dim_p={k}")
        settings = MHESettings.from_file(f, (n, p, m, k))
        est = cls._from_settings(model, settings, np.clip(np.zeros(n), *settings.x_bounds))
        state = _core_state(f, n + k, m, p, kind, est._dt, settings.learning)
        state.update(_outcome(f, n + k) if f.version >= 3
                     else _outcome_of_format2(f, state["t"], n, k, settings.scaling))
        try:
            est._core.__setstate__(state)
        except ValueError as e:
            raise f.state_error("core_", e) from None
    return est


def _core_state(f, na, m, p, kind, dt, learning):
    """The core's history (and the learned model's cache, or the learning state of an estimator
    that learns) in the file; ``dt`` the time step of a model that has one (None: none)."""
    state = {"t": f.integer("core_t"), "window_t0": f.integer("core_window_t0"),
             "present": f.array("core_present", "b", (None,))}
    timed = dt is not None and f.version >= 6  # earlier files: every interval was dt
    for key, cols in (("u", m + timed), ("y", p), ("priors", na), ("x_window", na)):
        state[key] = f.floats("core_" + key, (None, cols))
    if dt is not None and not timed:
        u = state["u"]
        state["u"] = np.column_stack([u, np.full(len(u), dt)])
    if f.version >= 2:
        state["arrival_sqrt"] = f.floats("core_arrival_sqrt", (na, na))
    if f.version >= 5:  # earlier files: every sample with R0
        state["r_given"] = f.array("core_r_given", "b", (None,))
        state["r"] = f.floats("core_r", (None, p * p))
    if learning:
        g0 = f.floats("core_learning_g0", (None,))
        ng = len(g0)
        state.update(learning_g0=g0, learning_sigma0=f.floats("core_learning_sigma0", (ng, ng)),
                     learning_drift=f.float("core_learning_drift"),
                     learning_arrival_g=f.floats("core_learning_arrival_g", (ng,)),
                     learning_arrival_cov=f.floats("core_learning_arrival_cov", (na + ng, na + ng)),
                     learning_g=f.floats("core_learning_g", (ng,)),
                     learning_g_cov=f.floats("core_learning_g_cov", (ng, ng)))
        if f.version >= 9:  # format 8: not known (NaN) until the second update after loading
            state.update(learning_xg_cov=f.floats("core_learning_xg_cov", (na, ng)),
                         learning_g_before=f.floats("core_learning_g_before", (ng,)),
                         learning_g_cov_before=f.floats("core_learning_g_cov_before", (ng, ng)),
                         learning_xg_cov_before=f.floats("core_learning_xg_cov_before", (na, ng)))
    elif kind == "LearnedModel":
        for key in _CACHE_PARTS:
            state["cache_" + key] = f.floats("core_cache_" + key, (None,))
    return state


def _outcome(f, na):
    """The core's record of the last update (core_outcome_*) in a file of format >= 3."""
    return {"outcome_x_prior": f.floats("core_outcome_x_prior", (na,)),
            "outcome_P": f.floats("core_outcome_P", (na, na)),
            "outcome_cost": f.float("core_outcome_cost"),
            "outcome_success": f.boolean("core_outcome_success"),
            "outcome_nit": f.integer("core_outcome_nit"),
            "outcome_nfev": f.integer("core_outcome_nfev"),
            "outcome_projected_gradient": f.float("core_outcome_projected_gradient"),
            "outcome_message": f.string("core_outcome_message"),
            "outcome_input_pending": f.boolean("core_outcome_input_pending"),
            **({"outcome_x_before": f.floats("core_outcome_x_before", (na,)),
                "outcome_P_before": f.floats("core_outcome_P_before", (na, na)),
                "outcome_P_window": f.floats("core_outcome_P_window", (None, na))}
               if f.version >= 7 else {})}  # earlier files: unknown (NaN) until the next update


def _outcome_of_format2(f, t_core, n, k, scaling):
    """The core's record of the last update from the attributes a file of format 1 or 2 saved
    beside the core's state (P and P_p become the blocks of the augmented covariance; their
    cross-covariance was not saved and is zero)."""
    t = f.integer("t")
    if t != t_core:
        raise f.error("core_t", f"is {t_core} but entry 't' is {t}")
    P, x_prior = f.floats("P", (n, n)), f.floats("x_prior", (n,))
    if k:
        P = scaling.covariance(P, f.floats("P_p", (k, k)))
        x_prior = scaling.state(x_prior, f.floats("p", (k,)))
    return {"outcome_x_prior": x_prior, "outcome_P": np.ascontiguousarray(P),
            "outcome_cost": f.float("cost"), "outcome_success": f.boolean("success"),
            "outcome_nit": f.integer("nit"), "outcome_nfev": f.integer("nfev"),
            "outcome_projected_gradient": f.float("projected_gradient"),
            "outcome_message": f.string("message"),
            "outcome_input_pending": f.boolean("input_pending") if f.version >= 2 else False}
