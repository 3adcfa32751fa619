//! The arrival cost of the next window (docs/user_guide/window.rst, *Arrival cost*): which
//! mean and which weight the prior term 2η^{M_t} ‖x̄_0 − x̂‖²_{P} of the next window gets once
//! the window slides.
//!
//! * mean: the estimator's own estimate of x(t − M) (the paper's, [`ArrivalMean::Estimate`]),
//!   the smoothed estimate of the new first node from the window just solved
//!   ([`ArrivalMean::Smoothed`]), or the leaving node's prior updated with its output and carried
//!   over its stage, linearised at the window's solution ([`ArrivalMean::Filtered`],
//!   [`ekf_mean_step`]: the mean of the EKF step of the weight);
//! * weight: P2 for ever (the paper's, [`ArrivalWeight::Constant`]), or an extended Kalman
//!   filter step of the arrival covariance Π = P⁻¹ over the node that leaves the window
//!   ([`ArrivalWeight::Ekf`], [`ekf_step`]).

use nalgebra::{DMatrix, DVector};

use super::problem::WindowProblem;
use super::stage::{StageEval, StageModel};
use crate::error::{Error, Result};

/// The arrival mean (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ArrivalMean {
    #[default]
    Estimate,
    Smoothed,
    Filtered,
}

/// The arrival weight (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ArrivalWeight {
    #[default]
    Constant,
    Ekf,
}

/// The arrival cost settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Arrival {
    pub mean: ArrivalMean,
    pub weight: ArrivalWeight,
}

/// The model's values at the single point d = [x; u] (for [`ekf_step`] when no window
/// evaluation at that node is at hand).
pub fn evaluate_at(model: &mut dyn StageModel, x: &[f64], u: &[f64]) -> Result<StageEval> {
    let mut d = x.to_vec();
    d.extend_from_slice(u);
    let mut st = StageEval::default();
    model.evaluate(&d, &mut st)?;
    st.check_sizes(1, model.dim_x(), model.dim_u(), model.dim_y())?;
    Ok(st)
}

/// One EKF step of the arrival covariance over the node x̄_0 that leaves the window (input u_0,
/// output y_0 with NaN for channels not measured, None if not measured or not in the window):
/// the measurement update W⁺ = W + Cᵀ R⁻¹ C with W = SᵀS, then the time update
/// Π' = A (W⁺)⁻¹ Aᵀ + Q, with A = ∂m_x/∂x, C = ∂m_y/∂x, Q = diag σ²_x + Q0, R = diag σ²_y + R0
/// (R0: the covariance given with y_0, if any, [`WindowProblem::output_cov`]) at
/// d̄_0 = [x̄_0; u_0], read from the first point of `st` (the model's values there: the window's
/// last evaluation, or [`evaluate_at`]). Returns S' (n × n, row-major) with S'ᵀS' = Π'⁻¹ (with a
/// robust penalty, each whitened output row of y_0 weighted by ψ′ of its residual, `loss.rs`);
/// a numerical error if a matrix is not positive definite (the caller keeps the old weight).
pub fn ekf_step(
    st: &StageEval,
    problem: &WindowProblem,
    y0: Option<&[f64]>,
    s: &[f64],
) -> Result<Vec<f64>> {
    let n = problem.dim_x();
    let nd = n + problem.dim_u();
    check_node_values(st, problem)?;
    let not_pd =
        || Error::numerical("arrival covariance update: a matrix is not positive definite");
    let s = DMatrix::from_row_slice(n, n, s);
    let mut info = s.transpose() * &s;
    if let Some((rows, _)) = output_rows(st, problem, y0, 0)? {
        info += rows.transpose() * rows;
    }
    let pi_plus = info.cholesky().ok_or_else(not_pd)?.inverse();
    let a = DMatrix::from_fn(n, n, |i, j| st.dmean_x[i * nd + j]);
    let all: Vec<usize> = (0..n).collect();
    let q = problem.q0_cov().with_variances(&all, &st.var_x[..n]);
    let pi = &a * pi_plus * a.transpose() + q;
    let pi = (&pi + pi.transpose()) * 0.5;
    let l = pi.cholesky().ok_or_else(not_pd)?.l();
    let mut s_next = DMatrix::identity(n, n);
    if !l.solve_lower_triangular_mut(&mut s_next) || s_next.iter().any(|v| !v.is_finite()) {
        return Err(not_pd());
    }
    Ok(s_next.transpose().as_slice().to_vec()) // row-major
}

/// The mean of the EKF step of [`ekf_step`]: the arrival prior `x_prior` of the node that leaves
/// (information W = SᵀS) updated with its output y_0 and carried over its stage, with the model
/// linearised at the window's solution `z0` of that node (values and Jacobians in `st`):
/// x⁺ = (W + JᵀJ)⁻¹ (W x̄ + Jᵀ(r + J z0)) with the whitened output rows J = ψ′ L⁻¹ C and
/// targets r = ψ(L⁻¹(y_0 − m_y(z0))) (e and ψ(e) = e for the squared loss, so W + JᵀJ is
/// `ekf_step`'s information), then m_x(z0) + A (x⁺ − z0). On a linear model the linearisation
/// point does not matter and this is the Kalman filter's prediction. A numerical error if a
/// matrix is not positive definite.
pub fn ekf_mean_step(
    st: &StageEval,
    problem: &WindowProblem,
    y0: Option<&[f64]>,
    s: &[f64],
    x_prior: &[f64],
    z0: &[f64],
) -> Result<Vec<f64>> {
    let n = problem.dim_x();
    let nd = n + problem.dim_u();
    check_node_values(st, problem)?;
    let not_pd = || Error::numerical("arrival mean update: a matrix is not positive definite");
    let s = DMatrix::from_row_slice(n, n, s);
    let mut info = s.transpose() * &s;
    let z0 = DVector::from_column_slice(z0);
    let mut b = &info * DVector::from_column_slice(x_prior);
    if let Some((rows, target)) = output_rows(st, problem, y0, 0)? {
        let target = target + &rows * &z0;
        info += rows.transpose() * &rows;
        b += rows.transpose() * target;
    }
    let posterior = info.cholesky().ok_or_else(not_pd)?.solve(&b);
    let a = DMatrix::from_fn(n, n, |i, j| st.dmean_x[i * nd + j]);
    let next = DVector::from_column_slice(&st.mean_x[..n]) + a * (posterior - z0);
    if next.iter().any(|v| !v.is_finite()) {
        return Err(not_pd());
    }
    Ok(next.as_slice().to_vec())
}

/// A numerical error unless `st` holds the model's values and Jacobians at (at least) one point.
fn check_node_values(st: &StageEval, problem: &WindowProblem) -> Result<()> {
    let (n, p) = (problem.dim_x(), problem.dim_y());
    let nd = n + problem.dim_u();
    let short = st.mean_x.len() < n
        || st.var_x.len() < n
        || st.mean_y.len() < p
        || st.var_y.len() < p
        || st.dmean_x.len() < n * nd
        || st.dmean_y.len() < p * nd;
    match short {
        true => Err(Error::numerical(
            "arrival update: no model values at the node",
        )),
        false => Ok(()),
    }
}

/// The whitened rows of the leaving node's output y_0 as the window weighs them, on its measured
/// channels: J = ψ′(e) L⁻¹C and targets ψ(e) with e = L⁻¹(y_0 − m_y) (J = L⁻¹C and e for the
/// squared loss), L Lᵀ = R + diag σ²_y (R the covariance given with y_0, or R0), C = ∂m_y/∂x, read
/// from `st` at the node, followed by ∂m_y/∂g for `ng` > 0 global variables; None without a
/// measured channel.
pub(super) fn output_rows(
    st: &StageEval,
    problem: &WindowProblem,
    y0: Option<&[f64]>,
    ng: usize,
) -> Result<Option<(DMatrix<f64>, DVector<f64>)>> {
    let (n, p) = (problem.dim_x(), problem.dim_y());
    let nd = n + problem.dim_u();
    let Some(y) = y0 else { return Ok(None) };
    let measured: Vec<usize> = (0..p).filter(|&k| y[k].is_finite()).collect();
    if measured.is_empty() {
        return Ok(None);
    }
    let not_pd =
        || Error::numerical("arrival update: the output covariance is not positive definite");
    let r = problem.output_cov(0).with_variances(
        &measured,
        &measured.iter().map(|&k| st.var_y[k]).collect::<Vec<_>>(),
    );
    let c = DMatrix::from_fn(measured.len(), n + ng, |i, j| match j < n {
        true => st.dmean_y[measured[i] * nd + j],
        false => st.dmean_y_dg[measured[i] * ng + j - n],
    });
    let rc = r.cholesky().ok_or_else(not_pd)?;
    let mut rows = rc.l().solve_lower_triangular(&c).ok_or_else(not_pd)?;
    let e = DVector::from_iterator(
        measured.len(),
        measured.iter().map(|&k| y[k] - st.mean_y[k]),
    );
    let mut target = rc.l().solve_lower_triangular(&e).ok_or_else(not_pd)?;
    let loss = problem.loss();
    if !loss.is_squared() {
        // A robust penalty: each whitened row times ψ′(e), its target ψ(e), as in the window.
        for i in 0..measured.len() {
            let (psi, slope) = loss.psi(target[i]);
            rows.row_mut(i).scale_mut(slope);
            target[i] = psi;
        }
    }
    Ok(Some((rows, target)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mhe::problem::Form;

    /// x(t+1) = A x, y = C x with constant matrices (n = 2, p = 1, no input).
    struct Linear;
    impl StageModel for Linear {
        fn dim_x(&self) -> usize {
            2
        }
        fn dim_u(&self) -> usize {
            0
        }
        fn dim_y(&self) -> usize {
            1
        }
        fn evaluate(&mut self, d: &[f64], out: &mut StageEval) -> Result<()> {
            out.resize(1, 2, 0, 1);
            out.mean_x
                .copy_from_slice(&[0.9 * d[0] + 0.2 * d[1], 0.8 * d[1]]);
            out.dmean_x.copy_from_slice(&[0.9, 0.2, 0.0, 0.8]);
            out.mean_y[0] = d[0];
            out.dmean_y.copy_from_slice(&[1.0, 0.0]);
            Ok(())
        }
    }

    const Q0: [f64; 4] = [0.01, 0.002, 0.002, 0.02];

    /// The window problem of `Linear` with Q0, R0 = 0.1, η = 1 and P2 = I.
    fn linear_problem() -> WindowProblem {
        let p2 = [1.0, 0.0, 0.0, 1.0];
        WindowProblem::new(2, 0, 1, 1.0, &Q0, &[0.1], &p2, Form::Prediction).unwrap()
    }

    /// On a linear-Gaussian model the step is the Kalman filter's covariance recursion.
    #[test]
    fn ekf_step_is_the_kalman_covariance_recursion() {
        let (q0, problem) = (Q0, linear_problem());
        let s = [2.0, 0.0, 0.5, 1.0];
        let st = evaluate_at(&mut Linear, &[0.3, -0.2], &[]).unwrap();
        let next = ekf_step(&st, &problem, Some(&[0.1]), &s).unwrap();
        // Kalman: Π = (SᵀS)⁻¹; K = ΠCᵀ(CΠCᵀ + R)⁻¹; Π⁺ = (I − KC)Π; Π' = AΠ⁺Aᵀ + Q.
        let sm = DMatrix::from_row_slice(2, 2, &s);
        let pi = (sm.transpose() * &sm).try_inverse().unwrap();
        let c = DMatrix::from_row_slice(1, 2, &[1.0, 0.0]);
        let k = &pi * c.transpose() / ((&c * &pi * c.transpose())[0] + 0.1);
        let pi_plus = (DMatrix::identity(2, 2) - &k * &c) * &pi;
        let a = DMatrix::from_row_slice(2, 2, &[0.9, 0.2, 0.0, 0.8]);
        let expected = &a * pi_plus * a.transpose() + DMatrix::from_row_slice(2, 2, &q0);
        let sn = DMatrix::from_row_slice(2, 2, &next);
        let got = (sn.transpose() * sn).try_inverse().unwrap();
        assert!((got - expected).norm() < 1e-12);
        // Without the output only the time update remains.
        let next = ekf_step(&st, &problem, Some(&[f64::NAN]), &s).unwrap();
        let sn = DMatrix::from_row_slice(2, 2, &next);
        let got = (sn.transpose() * sn).try_inverse().unwrap();
        let expected = &a * pi * a.transpose() + DMatrix::from_row_slice(2, 2, &q0);
        assert!((got - expected).norm() < 1e-12);
    }

    /// On a linear-Gaussian model the mean step is the Kalman filter's update and prediction,
    /// wherever the model is linearised.
    #[test]
    fn ekf_mean_step_is_the_kalman_mean_recursion() {
        let problem = linear_problem();
        let s = [2.0, 0.0, 0.5, 1.0];
        let (prior, y) = ([0.4, -0.1], 0.7);
        let sm = DMatrix::from_row_slice(2, 2, &s);
        let pi = (sm.transpose() * &sm).try_inverse().unwrap();
        let c = DMatrix::from_row_slice(1, 2, &[1.0, 0.0]);
        let k = &pi * c.transpose() / ((&c * &pi * c.transpose())[0] + 0.1);
        let x = DVector::from_column_slice(&prior);
        let x_plus = &x + &k * (y - (&c * &x)[0]);
        let a = DMatrix::from_row_slice(2, 2, &[0.9, 0.2, 0.0, 0.8]);
        let expected = &a * x_plus;
        for z0 in [[0.3, -0.2], [5.0, 3.0]] {
            let st = evaluate_at(&mut Linear, &z0, &[]).unwrap();
            let got = ekf_mean_step(&st, &problem, Some(&[y]), &s, &prior, &z0).unwrap();
            assert!((DVector::from_column_slice(&got) - &expected).norm() < 1e-12);
            // Without the output: the prior carried over the stage.
            let got = ekf_mean_step(&st, &problem, None, &s, &prior, &z0).unwrap();
            assert!((DVector::from_column_slice(&got) - &a * &x).norm() < 1e-12);
        }
    }
}
