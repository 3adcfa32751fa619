//! Copies, pickles and checkpoints of a `MovingHorizon`: its whole state as a dict of plain
//! values (numbers, strings, float64 and bool arrays) and back, every entry checked on the way
//! in (a ValueError names it).

use numpy::{PyArray1, PyArrayDyn, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::stage_model::Model;
use crate::mhe::{
    Covariance, GlobalsBefore, GpStageModel, HistoryState, JointArrival, Learning, LearningState,
    MovingHorizon, Outcome, GP_CACHE_PARTS,
};
use crate::python::convert::array2;

/// The float64 array `state[key]` with `cols` columns (2-D), as a flat row-major vector; a
/// ValueError naming the entry otherwise.
fn state_rows(state: &Bound<'_, PyDict>, key: &str, cols: usize) -> PyResult<Vec<f64>> {
    let a = state_item(state, key)?;
    let a = a
        .cast::<PyArrayDyn<f64>>()
        .map_err(|_| PyValueError::new_err(format!("{key}: must be a float64 array")))?;
    if a.ndim() != 2 || a.shape()[1] != cols {
        return Err(PyValueError::new_err(format!(
            "{key}: must have shape (rows, {cols}), got {:?}",
            a.shape()
        )));
    }
    Ok(a.readonly().as_array().iter().copied().collect())
}

/// The 1-D float64 array `state[key]` as a vector; a ValueError naming the entry otherwise.
fn state_rows_1d(state: &Bound<'_, PyDict>, key: &str) -> PyResult<Vec<f64>> {
    let a = state_item(state, key)?;
    let a = a
        .cast::<PyArrayDyn<f64>>()
        .map_err(|_| PyValueError::new_err(format!("{key}: must be a float64 array")))?;
    if a.ndim() != 1 {
        return Err(PyValueError::new_err(format!("{key}: must be 1-D")));
    }
    Ok(a.readonly().as_array().iter().copied().collect())
}

fn state_item<'py>(state: &Bound<'py, PyDict>, key: &str) -> PyResult<Bound<'py, PyAny>> {
    state
        .get_item(key)?
        .ok_or_else(|| PyValueError::new_err(format!("{key}: missing from the state")))
}

fn state_usize(state: &Bound<'_, PyDict>, key: &str) -> PyResult<usize> {
    state_item(state, key)?
        .extract::<usize>()
        .map_err(|_| PyValueError::new_err(format!("{key}: must be a non-negative integer")))
}

/// The estimator's state as a dict of plain values: the history (`t`, `window_t0` (ints), `u`
/// (rows, m), `y` (rows, p), `present` (rows,) bool, `r_given` (rows,) bool and `r` (rows, p²),
/// `priors` (k, n), `x_window` (nodes, n), `arrival_sqrt` (n, n)), the last update's report
/// (`outcome_*`, see `outcome_items`), for the learned model its evaluation cache (`cache_*`),
/// and for an estimator that learns its learning part (`learning_*`, see `learning_items`).
pub(super) fn get_state<'py>(
    py: Python<'py>,
    core: &MovingHorizon,
    model: &Model,
) -> PyResult<Bound<'py, PyDict>> {
    let s = core.history_state();
    let p = core.problem();
    let (n, m, dy) = (p.dim_x(), p.dim_u(), p.dim_y());
    let rows = s.present.len();
    let d = PyDict::new(py);
    d.set_item("t", s.t)?;
    d.set_item("window_t0", s.window_t0)?;
    d.set_item("u", array2(py, s.u, rows, m)?)?;
    d.set_item("y", array2(py, s.y, rows, dy)?)?;
    d.set_item("present", PyArray1::from_vec(py, s.present))?;
    // The covariance given with each row's output (`r_given`), as p × p rows of `r` (zeros
    // where none was given).
    let given: Vec<bool> = s.r.iter().map(Option::is_some).collect();
    let r: Vec<f64> =
        s.r.iter()
            .flat_map(|c| {
                c.as_ref()
                    .map_or(vec![0.0; dy * dy], |c| c.as_slice().to_vec())
            })
            .collect();
    d.set_item("r_given", PyArray1::from_vec(py, given))?;
    d.set_item("r", array2(py, r, rows, dy * dy)?)?;
    let k = s.priors.len() / n;
    d.set_item("priors", array2(py, s.priors, k, n)?)?;
    let nodes = s.x_window.len() / n;
    d.set_item("x_window", array2(py, s.x_window, nodes, n)?)?;
    d.set_item("arrival_sqrt", array2(py, s.arrival_sqrt, n, n)?)?;
    outcome_items(py, &d, s.outcome, n)?;
    if let Model::Gp(gp) = model {
        for (name, part) in GP_CACHE_PARTS.iter().zip(gp.cache()) {
            d.set_item(format!("cache_{name}"), PyArray1::from_vec(py, part))?;
        }
    }
    if let Some(l) = core.learning() {
        learning_items(py, &d, l, n)?;
    }
    Ok(d)
}

/// Writes the learning part: its prior `learning_g0` (n_g,), `learning_sigma0` (n_g, n_g),
/// `learning_drift`, and its state `learning_arrival_g` (n_g,), `learning_arrival_cov` (n + n_g,
/// n + n_g), `learning_g` (n_g,), `learning_g_cov` (n_g, n_g), `learning_xg_cov` (n, n_g) and
/// the last three before the last update (`learning_g_before`, `learning_g_cov_before`,
/// `learning_xg_cov_before`).
fn learning_items(py: Python<'_>, d: &Bound<'_, PyDict>, l: &Learning, n: usize) -> PyResult<()> {
    let (g0, sigma0) = l.prior();
    let (ng, s) = (l.dim(), l.state().clone());
    d.set_item("learning_g0", PyArray1::from_slice(py, g0))?;
    d.set_item("learning_sigma0", array2(py, sigma0.to_vec(), ng, ng)?)?;
    d.set_item("learning_drift", l.drift())?;
    d.set_item("learning_arrival_g", PyArray1::from_vec(py, s.arrival.g))?;
    d.set_item(
        "learning_arrival_cov",
        array2(py, s.arrival.cov, n + ng, n + ng)?,
    )?;
    d.set_item("learning_g", PyArray1::from_vec(py, s.g))?;
    d.set_item("learning_g_cov", array2(py, s.g_cov, ng, ng)?)?;
    d.set_item("learning_xg_cov", array2(py, s.xg_cov, n, ng)?)?;
    let b = s.before;
    d.set_item("learning_g_before", PyArray1::from_vec(py, b.g))?;
    d.set_item("learning_g_cov_before", array2(py, b.g_cov, ng, ng)?)?;
    d.set_item("learning_xg_cov_before", array2(py, b.xg_cov, n, ng)?)?;
    Ok(())
}

/// The learning part in a state dict (None without `learning_g0`), checked against `core`.
fn read_learning(state: &Bound<'_, PyDict>, core: &MovingHorizon) -> PyResult<Option<Learning>> {
    if !state.contains("learning_g0")? {
        return Ok(None);
    }
    let n = core.problem().dim_x();
    let g0 = state_rows_1d(state, "learning_g0")?;
    let ng = g0.len();
    let drift: f64 = state_item(state, "learning_drift")?
        .extract()
        .map_err(|_| PyValueError::new_err("learning_drift: must be a number"))?;
    let learning_state = LearningState {
        arrival: JointArrival {
            g: state_rows_1d(state, "learning_arrival_g")?,
            cov: state_rows(state, "learning_arrival_cov", n + ng)?,
        },
        g: state_rows_1d(state, "learning_g")?,
        g_cov: state_rows(state, "learning_g_cov", ng)?,
        xg_cov: match state.contains("learning_xg_cov")? {
            true => state_rows(state, "learning_xg_cov", ng)?,
            false => vec![f64::NAN; n * ng],
        },
        before: match state.contains("learning_g_before")? {
            true => GlobalsBefore {
                g: state_rows_1d(state, "learning_g_before")?,
                g_cov: state_rows(state, "learning_g_cov_before", ng)?,
                xg_cov: state_rows(state, "learning_xg_cov_before", ng)?,
            },
            // A state saved before these were kept: not known until the updates fill them in.
            false => GlobalsBefore::unknown(n, ng),
        },
    };
    let sigma0 = state_rows(state, "learning_sigma0", ng)?;
    Ok(Some(core.restored_learning(
        &g0,
        &sigma0,
        drift,
        learning_state,
    )?))
}

/// Restores `get_state`'s dict into `core`; returns the learned model with the restored cache
/// (None for a callback model). Every entry is checked (a ValueError names it); on error
/// nothing changes.
pub(super) fn set_state(
    state: &Bound<'_, PyDict>,
    core: &mut MovingHorizon,
    model: &Model,
) -> PyResult<Option<GpStageModel>> {
    let p = core.problem();
    let (n, m, dy) = (p.dim_x(), p.dim_u(), p.dim_y());
    let present = state_item(state, "present")?;
    let present = present
        .cast::<PyArrayDyn<bool>>()
        .map_err(|_| PyValueError::new_err("present: must be a bool array"))?;
    if present.ndim() != 1 {
        return Err(PyValueError::new_err("present: must be 1-D"));
    }
    let s = HistoryState {
        t: state_usize(state, "t")?,
        u: state_rows(state, "u", m)?,
        y: state_rows(state, "y", dy)?,
        present: present.readonly().as_array().iter().copied().collect(),
        r: read_covariances(state, dy)?,
        priors: state_rows(state, "priors", n)?,
        x_window: state_rows(state, "x_window", n)?,
        window_t0: state_usize(state, "window_t0")?,
        // States saved before the arrival weight was recorded ran with P2.
        arrival_sqrt: match state.contains("arrival_sqrt")? {
            true => state_rows(state, "arrival_sqrt", n)?,
            false => p.p2_sqrt().to_vec(),
        },
        outcome: read_outcome(state, core.history().outcome(), n)?,
    };
    // The learned model's cache of the last evaluation (see `GpStageModel::cache`).
    let gp = match model {
        Model::Gp(gp) => {
            let mut parts: [Vec<f64>; 9] = Default::default();
            for (part, name) in parts.iter_mut().zip(GP_CACHE_PARTS) {
                *part = state_rows_1d(state, &format!("cache_{name}"))?;
            }
            let mut gp = (**gp).clone();
            gp.set_cache(parts)
                .map_err(|e| PyValueError::new_err(format!("cache_{e}")))?;
            Some(gp)
        }
        _ => None,
    };
    let learning = read_learning(state, core)?;
    core.set_history_state(s)?;
    if learning.is_some() {
        core.set_learning(learning);
    }
    Ok(gp)
}

/// The covariances given with the rows' outputs (`r_given`, `r`; all R0 in states saved before
/// they were recorded).
fn read_covariances(state: &Bound<'_, PyDict>, p: usize) -> PyResult<Vec<Option<Covariance>>> {
    if !state.contains("r_given")? {
        let rows = state_item(state, "present")?.len()?;
        return Ok(vec![None; rows]);
    }
    let given = state_item(state, "r_given")?;
    let given = given
        .cast::<PyArrayDyn<bool>>()
        .map_err(|_| PyValueError::new_err("r_given: must be a bool array"))?;
    let given: Vec<bool> = given.readonly().as_array().iter().copied().collect();
    let values = state_rows(state, "r", p * p)?;
    if values.len() != given.len() * p * p {
        return Err(PyValueError::new_err(
            "r: needs one row per entry of r_given",
        ));
    }
    given
        .iter()
        .zip(values.chunks_exact(p * p).chain(std::iter::repeat(&[][..])))
        .map(|(&g, v)| g.then(|| Covariance::new("r", v, p)).transpose())
        .collect::<crate::error::Result<_>>()
        .map_err(Into::into)
}

/// Writes `outcome` into a state dict as `outcome_x_prior`, `outcome_P`, `outcome_cost`,
/// `outcome_success`, `outcome_nit`, `outcome_nfev`, `outcome_projected_gradient`,
/// `outcome_message`, `outcome_input_pending`, `outcome_x_before`, `outcome_P_before` and
/// `outcome_P_window` (the window's blocks stacked, (nodes·n, n)).
fn outcome_items(py: Python<'_>, d: &Bound<'_, PyDict>, o: Outcome, n: usize) -> PyResult<()> {
    d.set_item("outcome_x_before", PyArray1::from_vec(py, o.x_before))?;
    d.set_item("outcome_P_before", array2(py, o.covariance_before, n, n)?)?;
    let rows = o.window_covariance.len() / n;
    d.set_item(
        "outcome_P_window",
        array2(py, o.window_covariance, rows, n)?,
    )?;
    d.set_item("outcome_x_prior", PyArray1::from_vec(py, o.x_prior))?;
    d.set_item("outcome_P", array2(py, o.covariance, n, n)?)?;
    d.set_item("outcome_cost", o.cost)?;
    d.set_item("outcome_success", o.success)?;
    d.set_item("outcome_nit", o.nit)?;
    d.set_item("outcome_nfev", o.nfev)?;
    d.set_item("outcome_projected_gradient", o.projected_gradient)?;
    d.set_item("outcome_message", o.message)?;
    d.set_item("outcome_input_pending", o.input_pending)?;
    Ok(())
}

/// The outcome in a state dict (see `outcome_items`); a state without one (saved before
/// estimators recorded it) keeps `current`, one without the state before the update and the
/// window's covariances (saved before they were recorded) has them NaN. An entry of the wrong
/// type is a ValueError naming it; the values are checked by `HistoryState`'s restore.
fn read_outcome(state: &Bound<'_, PyDict>, current: &Outcome, n: usize) -> PyResult<Outcome> {
    if !state.contains("outcome_x_prior")? {
        return Ok(current.clone());
    }
    let item = |key: &str| state_item(state, key);
    let typed = |key: &str, what: &str| PyValueError::new_err(format!("{key}: must be {what}"));
    let (x_before, covariance_before, window_covariance) = if state.contains("outcome_x_before")? {
        (
            state_rows_1d(state, "outcome_x_before")?,
            state_rows(state, "outcome_P_before", n)?,
            state_rows(state, "outcome_P_window", n)?,
        )
    } else {
        let nodes = state_rows(state, "x_window", n)?.len() / n;
        (
            vec![f64::NAN; n],
            vec![f64::NAN; n * n],
            vec![f64::NAN; nodes * n * n],
        )
    };
    Ok(Outcome {
        x_before,
        covariance_before,
        window_covariance,
        x_prior: state_rows_1d(state, "outcome_x_prior")?,
        covariance: state_rows(state, "outcome_P", n)?,
        cost: item("outcome_cost")?
            .extract()
            .map_err(|_| typed("outcome_cost", "a number"))?,
        success: item("outcome_success")?
            .extract()
            .map_err(|_| typed("outcome_success", "a bool"))?,
        nit: state_usize(state, "outcome_nit")?,
        nfev: state_usize(state, "outcome_nfev")?,
        projected_gradient: item("outcome_projected_gradient")?
            .extract()
            .map_err(|_| typed("outcome_projected_gradient", "a number"))?,
        message: item("outcome_message")?
            .extract()
            .map_err(|_| typed("outcome_message", "a string"))?,
        input_pending: item("outcome_input_pending")?
            .extract()
            .map_err(|_| typed("outcome_input_pending", "a bool"))?,
    })
}
