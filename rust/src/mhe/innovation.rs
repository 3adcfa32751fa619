//! The innovation of the last update (docs/user_guide/uncertainty.rst): the output y(t) minus
//! the output predicted before y(t) was seen, its covariance S, the normalised innovation squared
//! (NIS) and the Gaussian log-likelihood of y(t), over the channels measured.
//!
//! The prediction starts from what the estimator reported before the update (the outcome's
//! `x_before`, `covariance_before`): in the prediction form that is x̂(t) and its covariance
//! already; in the filtering form x̂(t − 1), carried over the stage with u(t − 1) as in an EKF,
//! x̂⁻ = m_x, P⁻ = A P Aᵀ + Q0 + diag σ²_x. With a model whose global variables g are estimated
//! (a GP that keeps learning) the stage is that of the posterior of g before the update, jointly
//! uncertain with x̂(t − 1) ([`GlobalsBefore`]): m_x at its mean, P⁻ = [A B] Σ [A B]ᵀ + Q0 +
//! diag σ²_x with Σ the joint covariance and B = ∂m_x/∂g. Then ŷ = m_y(x̂⁻, u(t)) and
//! S = C P⁻ Cᵀ + R(t) + diag σ²_y (R(t): the covariance given with the sample, or R0), A and C
//! the model's Jacobians there. On a linear-Gaussian model with the Kalman-filter settings these
//! are the Kalman filter's. Computed when asked for, from the history (and kept by
//! [`MovingHorizon::innovation`](super::MovingHorizon::innovation) until that changes): nothing
//! is added to an update.

use nalgebra::{DMatrix, DVector};

use super::arrival::evaluate_at;
use super::history::History;
use super::learning_state::GlobalsBefore;
use super::problem::{Form, WindowProblem};
use super::stage::StageModel;
use crate::error::{Error, Result};

/// See the module documentation. Before the first update (or after a reset, or when the state
/// before the update is unknown: a checkpoint of an older format) every value is NaN.
#[derive(Debug, Clone, PartialEq)]
pub struct Innovation {
    /// y(t) − ŷ (p; NaN for channels not measured).
    pub nu: Vec<f64>,
    /// The predicted output covariance S (p × p, row-major, every channel).
    pub s: Vec<f64>,
    /// νᵀS⁻¹ν over the measured channels (NaN when none is measured).
    pub nis: f64,
    /// log N(y; ŷ, S) over the measured channels (0 when none is measured).
    pub log_likelihood: f64,
    /// The number of measured channels.
    pub measured: usize,
}

impl Innovation {
    fn unknown(p: usize) -> Self {
        Self {
            nu: vec![f64::NAN; p],
            s: vec![f64::NAN; p * p],
            nis: f64::NAN,
            log_likelihood: f64::NAN,
            measured: 0,
        }
    }
}

/// The innovation of the newest sample in `history` (see the module documentation); `globals`
/// the posterior of the model's global variables before the update, if it has any (the model's
/// global variables are then left at its mean).
pub fn innovation(
    problem: &WindowProblem,
    history: &History,
    model: &mut dyn StageModel,
    globals: Option<&GlobalsBefore>,
) -> Result<Innovation> {
    let (n, p) = (problem.dim_x(), problem.dim_y());
    let outcome = history.outcome();
    let Some(sample) = history.newest_sample() else {
        return Ok(Innovation::unknown(p));
    };
    let (x, cov) = (&outcome.x_before, &outcome.covariance_before);
    if x.iter().chain(cov).any(|v| !v.is_finite()) {
        return Ok(Innovation::unknown(p));
    }
    let mut x = DVector::from_column_slice(x);
    let mut cov = DMatrix::from_row_slice(n, n, cov);
    if let (Form::Filtering, Some(u_before)) = (problem.form(), sample.u_before) {
        if let Some(b) = globals {
            if !b.is_known() {
                return Ok(Innovation::unknown(p));
            }
            model.set_globals(&b.g)?;
        }
        let st = evaluate_at(model, x.as_slice(), u_before)?;
        let nd = n + problem.dim_u();
        let a = DMatrix::from_fn(n, n, |i, j| st.dmean_x[i * nd + j]);
        let all: Vec<usize> = (0..n).collect();
        let q = problem.q0_cov().with_variances(&all, &st.var_x[..n]);
        cov = match globals {
            None => &a * cov * a.transpose() + q,
            Some(b) => joint_prediction(&a, &cov, b, &st.dmean_x_dg) + q,
        };
        x = DVector::from_column_slice(&st.mean_x[..n]);
    }
    let st = evaluate_at(model, x.as_slice(), sample.u)?;
    let nd = n + problem.dim_u();
    let c = DMatrix::from_fn(p, n, |i, j| st.dmean_y[i * nd + j]);
    let channels: Vec<usize> = (0..p).collect();
    let r = sample.r.unwrap_or(problem.r0_cov());
    let s = &c * cov * c.transpose() + r.with_variances(&channels, &st.var_y[..p]);
    let s = (&s + s.transpose()) * 0.5;
    let nu: Vec<f64> = (0..p)
        .map(|k| sample.y.map_or(f64::NAN, |y| y[k] - st.mean_y[k]))
        .collect();
    let measured: Vec<usize> = (0..p).filter(|&k| nu[k].is_finite()).collect();
    let (nis, log_likelihood) = if measured.is_empty() {
        (f64::NAN, 0.0)
    } else {
        let sm = DMatrix::from_fn(measured.len(), measured.len(), |i, j| {
            s[(measured[i], measured[j])]
        });
        let chol = sm.cholesky().ok_or_else(|| {
            Error::numerical("innovation: the predicted output covariance is not positive definite")
        })?;
        let v = DVector::from_iterator(measured.len(), measured.iter().map(|&k| nu[k]));
        let w = chol.l().solve_lower_triangular(&v).ok_or_else(|| {
            Error::numerical("innovation: the predicted output covariance is singular")
        })?;
        let nis = w.norm_squared();
        let log_det: f64 = chol.l().diagonal().iter().map(|d| 2.0 * d.ln()).sum();
        let k = measured.len() as f64;
        let ll = -0.5 * (nis + log_det + k * (2.0 * std::f64::consts::PI).ln());
        (nis, ll)
    };
    Ok(Innovation {
        nu,
        s: s.transpose().as_slice().to_vec(), // row-major (S is symmetric)
        nis,
        log_likelihood,
        measured: measured.len(),
    })
}

/// [A B] Σ [A B]ᵀ with Σ = [P Σ_xg; Σ_xgᵀ Σ_g] the joint covariance of x̂(t − 1) (P) and g
/// (`b`), B = ∂m_x/∂g (the first n rows of `dmean_x_dg`, row-major n × n_g).
fn joint_prediction(
    a: &DMatrix<f64>,
    p: &DMatrix<f64>,
    b: &GlobalsBefore,
    dmean_x_dg: &[f64],
) -> DMatrix<f64> {
    let (n, ng) = (a.nrows(), b.g.len());
    let bm = DMatrix::from_row_slice(n, ng, &dmean_x_dg[..n * ng]);
    let xg = DMatrix::from_row_slice(n, ng, &b.xg_cov);
    let gg = DMatrix::from_row_slice(ng, ng, &b.g_cov);
    let cross = a * &xg * bm.transpose();
    a * p * a.transpose() + &cross + cross.transpose() + &bm * gg * bm.transpose()
}
