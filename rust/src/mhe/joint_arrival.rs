//! The arrival cost of an estimator whose model has global variables g (a GP that keeps learning,
//! `learning.rs`): the prior of the window's first state and g together, N([x̂; ĝ], Π), carried
//! from window to window by one extended Kalman filter step of the pair over the node that
//! leaves the window, linearised at the window's solution (x̄_0, g):
//!
//! * update with the leaving node's output y_0 (the window's whitened, ψ-weighted rows J =
//!   [J_x, J_g], targets e): K = Π Jᵀ (J Π Jᵀ + I)⁻¹, w⁺ = w̄ + K (e − J (w̄ − w_0)), Π⁺ = Π − K J Π;
//! * prediction over its stage, g constant up to a random walk of variance `drift` per step:
//!   x' = m_x(w_0) + A (x⁺ − x̄_0) + B (g⁺ − g), g' = g⁺, Π' = F Π⁺ Fᵀ + diag(Q, drift I) with
//!   F = [A B; 0 I], A = ∂m_x/∂x, B = ∂m_x/∂g, Q = diag σ²_x + Q0.
//!
//! On a model linear in (x, g) this is the Kalman filter of the pair; with the states measured
//! exactly it is the recursive GP's update of g from each transition (Huber's, which
//! `RecursiveGP.from_sparse` continues). The window's prior rows need S with SᵀS = Π⁻¹
//! ([`joint_sqrt`]).

use faer::linalg::matmul::matmul;
use faer::linalg::solvers::Llt;
use faer::linalg::triangular_solve::solve_lower_triangular_in_place;
use faer::{Accum, Mat, MatMut, MatRef, Par, Side};
use nalgebra::{DMatrix, DVector};

use super::arrival::output_rows;
use super::problem::WindowProblem;
use super::stage::StageEval;
use crate::error::{check_finite, check_len, Error, Result};

/// The joint arrival prior's g-part: mean ĝ (n_g) and the covariance Π of (x, g) ((n + n_g)²,
/// row-major); x̂ is the estimator's arrival prior of the states.
#[derive(Debug, Clone, PartialEq)]
pub struct JointArrival {
    pub g: Vec<f64>,
    pub cov: Vec<f64>,
}

impl JointArrival {
    /// Checks ĝ and Π (lengths, finite values, symmetry to rounding); positive definiteness is
    /// checked where S is computed ([`joint_sqrt`]).
    pub fn new(n: usize, g: Vec<f64>, cov: Vec<f64>) -> Result<Self> {
        let d = n + g.len();
        check_len("cov", &cov, d * d)?;
        check_finite("mean", &g)?;
        check_finite("cov", &cov)?;
        let scale = cov.iter().fold(0.0f64, |a, v| a.max(v.abs()));
        for i in 0..d {
            for j in 0..i {
                if (cov[i * d + j] - cov[j * d + i]).abs() > 1e-10 * scale {
                    return Err(Error::invalid("cov", "must be symmetric"));
                }
            }
        }
        Ok(Self { g, cov })
    }

    /// n_g.
    pub fn dim(&self) -> usize {
        self.g.len()
    }
}

/// S = L⁻¹ ((n + n_g)², row-major) with Π = L Lᵀ, so that SᵀS = Π⁻¹; a `Numerical` error if Π
/// is not positive definite.
pub fn joint_sqrt(cov: &[f64], d: usize) -> Result<Vec<f64>> {
    let not_pd = || Error::numerical("the joint arrival covariance is not positive definite");
    let llt =
        Llt::new(MatRef::from_row_major_slice(cov, d, d), Side::Lower).map_err(|_| not_pd())?;
    // L⁻¹ solved in place in a row-major identity: S is written where it is returned.
    let mut out = vec![0.0; d * d];
    out.iter_mut().step_by(d + 1).for_each(|v| *v = 1.0);
    let s = MatMut::from_row_major_slice_mut(&mut out, d, d);
    solve_lower_triangular_in_place(llt.L(), s, Par::Seq);
    match out.iter().all(|v| v.is_finite()) {
        true => Ok(out),
        false => Err(not_pd()),
    }
}

/// The leaving node's linearisation point and values: its solution x̄_0 and the window's g, and
/// the model's values there (`st`, first point, with ∂m/∂g).
pub struct LeavingNode<'a> {
    pub st: &'a StageEval,
    pub z0: &'a [f64],
    pub g: &'a [f64],
    pub y0: Option<&'a [f64]>,
}

/// One EKF step of the pair (module docs) from the prior (`x_prior`, `prior`): the next x̂ and
/// the next [`JointArrival`]. A `Numerical` error if a matrix is not positive definite (the
/// caller keeps the old prior).
pub fn joint_ekf_step(
    problem: &WindowProblem,
    node: &LeavingNode<'_>,
    x_prior: &[f64],
    prior: &JointArrival,
    drift: f64,
) -> Result<(Vec<f64>, JointArrival)> {
    let (n, ng) = (problem.dim_x(), prior.dim());
    let nd = n + problem.dim_u();
    let st = node.st;
    if st.dmean_x_dg.len() < n * ng || st.mean_x.len() < n || st.dmean_x.len() < n * nd {
        return Err(Error::numerical(
            "joint arrival update: no model values at the node",
        ));
    }
    let not_pd = || Error::numerical("joint arrival update: a matrix is not positive definite");
    let w0: Vec<f64> = node.z0.iter().chain(node.g).copied().collect();
    let mut w: Vec<f64> = x_prior.iter().chain(&prior.g).copied().collect();
    let mut pi = prior.cov.clone();
    if let Some((j, e)) = output_rows(st, problem, node.y0, ng)? {
        measurement_update(&mut pi, &mut w, &w0, &j, &e).ok_or_else(not_pd)?;
    }
    let a = MatRef::from_row_major_slice(&st.dmean_x[..n * nd], n, nd).subcols(0, n);
    let b = MatRef::from_row_major_slice(&st.dmean_x_dg[..n * ng], n, ng);
    let all: Vec<usize> = (0..n).collect();
    let q = problem.q0_cov().with_variances(&all, &st.var_x[..n]);
    let cov = time_update(&pi, a, b, &q, drift);
    // x' = m_x(w0) + A (x⁺ − x̄_0) + B (g⁺ − g).
    let dw: Vec<f64> = w.iter().zip(&w0).map(|(p, q)| p - q).collect();
    let x_next: Vec<f64> = (0..n)
        .map(|r| {
            let ax: f64 = (0..n).map(|c| a[(r, c)] * dw[c]).sum();
            let bg: f64 = (0..ng).map(|c| b[(r, c)] * dw[n + c]).sum();
            st.mean_x[r] + ax + bg
        })
        .collect();
    if x_next.iter().chain(cov.iter()).any(|v| !v.is_finite()) {
        return Err(not_pd());
    }
    Ok((
        x_next,
        JointArrival {
            g: w[n..].to_vec(),
            cov,
        },
    ))
}

/// The update with the whitened output rows J (k × D, unit noise) and targets e, linearised at
/// w0: K = Π Jᵀ (J Π Jᵀ + I)⁻¹, w += K (e − J (w − w0)), Π −= G Gᵀ with G = Π Jᵀ L⁻ᵀ
/// (L Lᵀ = J Π Jᵀ + I). `pi` is D × D row-major. None if J Π Jᵀ + I is not positive definite.
fn measurement_update(
    pi: &mut [f64],
    w: &mut [f64],
    w0: &[f64],
    j: &DMatrix<f64>,
    e: &DVector<f64>,
) -> Option<()> {
    let (k, d) = (j.nrows(), j.ncols());
    // J is column-major (nalgebra): Jᵀ is a row-major D × k view of the same values.
    let jt = MatRef::from_row_major_slice(j.as_slice(), d, k);
    let mut pjt = Mat::<f64>::zeros(d, k);
    let p = MatRef::from_row_major_slice(pi, d, d);
    matmul(pjt.as_mut(), Accum::Replace, p, jt, 1.0, Par::Seq);
    let pjt_n = DMatrix::from_fn(d, k, |r, c| pjt[(r, c)]);
    let s = j * &pjt_n + DMatrix::identity(k, k);
    let chol = s.cholesky()?;
    let dw = DVector::from_iterator(d, w.iter().zip(w0).map(|(a, b)| a - b));
    let gain = &pjt_n * chol.solve(&(e - j * dw));
    w.iter_mut().zip(gain.iter()).for_each(|(a, g)| *a += g);
    // G = Π Jᵀ L⁻ᵀ: Gᵀ = L⁻¹ (Π Jᵀ)ᵀ.
    let gt = chol.l().solve_lower_triangular(&pjt_n.transpose())?;
    let g = MatRef::from_row_major_slice(gt.as_slice(), d, k);
    let pm = MatMut::from_row_major_slice_mut(pi, d, d);
    matmul(pm, Accum::Add, g, g.transpose(), -1.0, Par::Seq);
    Some(())
}

/// Π' = F Π Fᵀ + diag(Q, drift I) with F = [A B; 0 I] (`pi` D × D row-major, A n × n, B
/// n × n_g), symmetrised; row-major.
fn time_update(
    pi: &[f64],
    a: MatRef<'_, f64>,
    b: MatRef<'_, f64>,
    q: &DMatrix<f64>,
    drift: f64,
) -> Vec<f64> {
    let (n, ng) = (a.nrows(), b.ncols());
    let d = n + ng;
    let p = MatRef::from_row_major_slice(pi, d, d);
    // Y = [A B] Π over the states' rows (n × D): the rows of F Π.
    let mut y = Mat::<f64>::zeros(n, d);
    matmul(
        y.as_mut(),
        Accum::Replace,
        a,
        p.subrows(0, n),
        1.0,
        Par::Seq,
    );
    matmul(y.as_mut(), Accum::Add, b, p.subrows(n, ng), 1.0, Par::Seq);
    let mut pxx = Mat::<f64>::zeros(n, n);
    matmul(
        pxx.as_mut(),
        Accum::Replace,
        y.as_ref().subcols(0, n),
        a.transpose(),
        1.0,
        Par::Seq,
    );
    matmul(
        pxx.as_mut(),
        Accum::Add,
        y.as_ref().subcols(n, ng),
        b.transpose(),
        1.0,
        Par::Seq,
    );
    let mut out = vec![0.0; d * d];
    for r in 0..d {
        for c in 0..d {
            out[r * d + c] = match (r < n, c < n) {
                (true, true) => 0.5 * (pxx[(r, c)] + pxx[(c, r)]) + q[(r, c)],
                (true, false) => y[(r, c)],
                (false, true) => y[(c, r)],
                (false, false) => {
                    let sym = 0.5 * (pi[r * d + c] + pi[c * d + r]);
                    if r == c {
                        sym + drift
                    } else {
                        sym
                    }
                }
            };
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mhe::Form;

    /// x' = A x + B g, y = C x + D g (n = 2, p = 1, n_g = 3, no input).
    const A: [f64; 4] = [0.9, 0.2, -0.1, 0.8];
    const B: [f64; 6] = [0.3, 0.0, -0.2, 0.1, 0.5, 0.0];
    const C: [f64; 2] = [1.0, 0.5];
    const D: [f64; 3] = [0.0, 0.2, 0.0];
    /// The model's values at (x, g).
    fn node_values(x: &[f64], g: &[f64]) -> StageEval {
        let mut st = StageEval::default();
        st.resize(1, 2, 0, 1);
        st.resize_globals(1, 2, 1, 3);
        for r in 0..2 {
            st.mean_x[r] = (0..2).map(|c| A[r * 2 + c] * x[c]).sum::<f64>()
                + (0..3).map(|c| B[r * 3 + c] * g[c]).sum::<f64>();
        }
        st.mean_y[0] = C[0] * x[0] + C[1] * x[1] + (0..3).map(|c| D[c] * g[c]).sum::<f64>();
        st.dmean_x.copy_from_slice(&A);
        st.dmean_x_dg.copy_from_slice(&B);
        st.dmean_y.copy_from_slice(&C);
        st.dmean_y_dg.copy_from_slice(&D);
        st
    }

    #[test]
    fn on_a_linear_model_the_step_is_the_kalman_filter_of_the_pair() {
        let q0 = [0.01, 0.002, 0.002, 0.02];
        let problem = WindowProblem::new(
            2,
            0,
            1,
            1.0,
            &q0,
            &[0.1],
            &[1.0, 0.0, 0.0, 1.0],
            Form::Prediction,
        )
        .unwrap();
        let l = DMatrix::from_fn(5, 5, |i, j| match i >= j {
            true => 0.3 + 0.1 * (i + 2 * j) as f64 / (1.0 + (i == j) as u8 as f64),
            false => 0.0,
        });
        let pi = &l * l.transpose();
        let prior =
            JointArrival::new(2, vec![0.2, -0.1, 0.4], pi.transpose().as_slice().to_vec()).unwrap();
        let x_prior = [0.5, -0.3];
        let drift = 1e-3;
        // Kalman filter of w = [x; g]: F = [A B; 0 I], H = [C D].
        let mut f = DMatrix::identity(5, 5);
        f.view_mut((0, 0), (2, 2))
            .copy_from(&DMatrix::from_row_slice(2, 2, &A));
        f.view_mut((0, 2), (2, 3))
            .copy_from(&DMatrix::from_row_slice(2, 3, &B));
        let h = DMatrix::from_row_slice(1, 5, &[C[0], C[1], D[0], D[1], D[2]]);
        let mut q = DMatrix::identity(5, 5) * drift;
        q.view_mut((0, 0), (2, 2))
            .copy_from(&DMatrix::from_row_slice(2, 2, &q0));
        let wbar = DVector::from_column_slice(&[0.5, -0.3, 0.2, -0.1, 0.4]);
        for y in [Some(0.7), None] {
            let (w_plus, p_plus) = match y {
                Some(y) => {
                    let s = (&h * &pi * h.transpose())[0] + 0.1;
                    let k = &pi * h.transpose() / s;
                    (&wbar + &k * (y - (&h * &wbar)[0]), &pi - &k * &h * &pi)
                }
                None => (wbar.clone(), pi.clone()),
            };
            let want_w = &f * w_plus;
            let want_p = &f * p_plus * f.transpose() + &q;
            // Wherever the model is linearised.
            for (z0, g0) in [
                ([0.1, 0.2], [0.0, 0.3, -0.2]),
                ([3.0, -2.0], [1.0, 1.0, 1.0]),
            ] {
                let st = node_values(&z0, &g0);
                let y0 = y.map(|v| vec![v]);
                let node = LeavingNode {
                    st: &st,
                    z0: &z0,
                    g: &g0,
                    y0: y0.as_deref(),
                };
                let (x, next) = joint_ekf_step(&problem, &node, &x_prior, &prior, drift).unwrap();
                for i in 0..2 {
                    assert!((x[i] - want_w[i]).abs() < 1e-12, "{y:?} x");
                }
                for i in 0..3 {
                    assert!((next.g[i] - want_w[2 + i]).abs() < 1e-12, "{y:?} g");
                }
                for i in 0..25 {
                    assert!(
                        (next.cov[i] - want_p[(i / 5, i % 5)]).abs() < 1e-12,
                        "{y:?} cov"
                    );
                }
            }
        }
        // S of the window's prior rows: SᵀS = Π⁻¹.
        let s = DMatrix::from_row_slice(5, 5, &joint_sqrt(&prior.cov, 5).unwrap());
        assert!((s.transpose() * s - pi.try_inverse().unwrap()).norm() < 1e-9);
    }

    #[test]
    fn bad_priors_are_refused() {
        let e = JointArrival::new(2, vec![0.0], vec![1.0; 4]).unwrap_err();
        assert!(matches!(e, Error::InvalidInput { ref arg, .. } if arg == "cov"));
        let mut cov = vec![0.0; 9];
        cov[1] = 1.0;
        let e = JointArrival::new(2, vec![0.0], cov).unwrap_err();
        assert!(matches!(e, Error::InvalidInput { ref arg, .. } if arg == "cov"));
        let e = joint_sqrt(&[1.0, 0.0, 0.0, -1.0], 2).unwrap_err();
        assert!(matches!(e, Error::Numerical(_)));
    }
}
