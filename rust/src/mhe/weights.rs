//! The noise covariances Q0 and R0 of the window problem (docs/user_guide/weights.rst), diagonal
//! or full, and the whitening of one stage's residual block with a full covariance:
//!
//! r = a L⁻¹ e,   e = target − m(d̄),   L Lᵀ = S = diag σ²(d̄) + C   (C: Q0 or R0 on the rows used),
//!
//! with its Jacobian with respect to the stage's own node x̄ (column c):
//!
//! ∂r/∂x̄_c = −a L⁻¹ ∂m/∂x̄_c − Φ(L⁻¹ diag(∂σ²/∂x̄_c) L⁻ᵀ) r,
//!
//! where Φ keeps the lower triangle and halves the diagonal (the derivative of a Cholesky
//! factor: dL = L Φ(L⁻¹ dS L⁻ᵀ)). With a diagonal covariance every row is whitened alone
//! (`problem.rs`, the fast path); this module is the block path for full ones.

use nalgebra::{DMatrix, DVector};

use crate::error::{check_finite, Error, Result};

/// A symmetric positive definite covariance (Q0 or R0), from its diagonal or the whole matrix.
#[derive(Debug, Clone, PartialEq)]
pub struct Covariance {
    dim: usize,
    /// dim × dim, row-major.
    full: Vec<f64>,
    diagonal: bool,
}

impl Covariance {
    /// From `values`: the diagonal (`dim` values) or the whole symmetric positive definite
    /// matrix (`dim²` values, row-major). `name` names the argument in errors.
    pub fn new(name: &str, values: &[f64], dim: usize) -> Result<Self> {
        check_finite(name, values)?;
        let full = if values.len() == dim {
            let mut full = vec![0.0; dim * dim];
            (0..dim).for_each(|i| full[i * dim + i] = values[i]);
            full
        } else if values.len() == dim * dim {
            values.to_vec()
        } else {
            return Err(Error::invalid(
                name,
                format!(
                    "needs {dim} values (the diagonal) or {} (the matrix), got {}",
                    dim * dim,
                    values.len()
                ),
            ));
        };
        let at = |i: usize, j: usize| full[i * dim + j];
        for i in 0..dim {
            for j in 0..i {
                let tol = 1e-12 * (at(i, i).abs() * at(j, j).abs()).sqrt();
                if (at(i, j) - at(j, i)).abs() > tol {
                    return Err(Error::invalid(name, "must be symmetric"));
                }
            }
        }
        let matrix = DMatrix::from_row_slice(dim, dim, &full);
        if (0..dim).any(|i| at(i, i) <= 0.0) || matrix.cholesky().is_none() {
            return Err(Error::invalid(name, "must be positive definite"));
        }
        let diagonal = (0..dim).all(|i| (0..dim).all(|j| i == j || at(i, j) == 0.0));
        Ok(Self {
            dim,
            full,
            diagonal,
        })
    }

    pub fn dim(&self) -> usize {
        self.dim
    }
    /// Whether every off-diagonal entry is zero (rows are then whitened one by one).
    pub fn is_diagonal(&self) -> bool {
        self.diagonal
    }
    pub fn get(&self, i: usize, j: usize) -> f64 {
        self.full[i * self.dim + j]
    }
    /// The whole matrix, row-major.
    pub fn as_slice(&self) -> &[f64] {
        &self.full
    }

    /// This covariance with the channels `channels` measured apart: their block taken from
    /// `other`, their covariances with every other channel zero (block-diagonal, so positive
    /// definite when both are).
    pub fn with_block(&self, other: &Covariance, channels: &[usize]) -> Result<Covariance> {
        let dim = self.dim;
        let full: Vec<f64> = (0..dim * dim)
            .map(|k| {
                let (i, j) = (k / dim, k % dim);
                match (channels.contains(&i), channels.contains(&j)) {
                    (true, true) => other.get(i, j),
                    (false, false) => self.get(i, j),
                    _ => 0.0,
                }
            })
            .collect();
        Covariance::new("R", &full, dim)
    }

    /// diag(var) + C[rows, rows] (var: one value per selected row, clamped at 0).
    pub(super) fn with_variances(&self, rows: &[usize], var: &[f64]) -> DMatrix<f64> {
        let k = rows.len();
        DMatrix::from_fn(k, k, |i, j| {
            let c = self.get(rows[i], rows[j]);
            if i == j {
                c + var[i].max(0.0)
            } else {
                c
            }
        })
    }
}

/// One stage block whitened with a full covariance (see the module docs).
pub(super) struct WhitenedBlock {
    /// r (k).
    pub r: Vec<f64>,
    /// ∂r/∂x̄ of the stage's own node (k × n, row-major), if derivatives were asked for.
    pub ja: Vec<f64>,
    /// a L⁻¹ (k × k, row-major): ∂r/∂target.
    pub a_linv: Vec<f64>,
    /// Typical rounding error of each r from the rounding of the means and variances.
    pub rounding: Vec<f64>,
}

/// The inputs of [`whiten`] for the k selected rows of one stage.
pub(super) struct Block<'a> {
    pub a: f64,
    /// target − mean (k).
    pub e: &'a [f64],
    /// σ²(d̄) (k).
    pub var: &'a [f64],
    /// ∂m/∂x̄ and ∂σ²/∂x̄ (k × n each, row-major), or None without derivatives.
    pub derivs: Option<(&'a [f64], &'a [f64])>,
    /// Rounding of each mean and the relative rounding of each variance (k each).
    pub mean_rounding: &'a [f64],
    pub var_rounding: &'a [f64],
}

/// Whitens `block` with S = diag σ² + C[rows, rows] (see the module docs); `n` is the node size.
pub(super) fn whiten(
    cov: &Covariance,
    rows: &[usize],
    block: &Block<'_>,
    n: usize,
) -> Result<WhitenedBlock> {
    let k = rows.len();
    let s = cov.with_variances(rows, block.var);
    let chol = s.clone().cholesky().ok_or_else(|| {
        Error::numerical("a stage covariance diag(σ²) + Q0 or R0 is not positive definite")
    })?;
    let l = chol.l();
    let mut linv = DMatrix::identity(k, k);
    if !l.solve_lower_triangular_mut(&mut linv) {
        return Err(Error::numerical("a stage covariance is singular"));
    }
    let a_linv = linv.scale(block.a);
    let r = &a_linv * DVector::from_column_slice(block.e);
    let mut ja = Vec::new();
    if let Some((dm, dv)) = block.derivs {
        ja = vec![0.0; k * n];
        let dm = DMatrix::from_row_slice(k, n, dm);
        let jm = -(&a_linv * dm); // −a L⁻¹ ∂m (k × n)
        for c in 0..n {
            let dvar: Vec<f64> = (0..k).map(|i| dv[i * n + c]).collect();
            let mut col = jm.column(c).into_owned();
            if dvar.iter().any(|&v| v != 0.0) {
                // M = L⁻¹ diag(dvar) L⁻ᵀ; subtract Φ(M) r.
                let scaled = DMatrix::from_fn(k, k, |i, j| linv[(i, j)] * dvar[j]);
                let m = scaled * linv.transpose();
                for i in 0..k {
                    let mut acc = 0.5 * m[(i, i)] * r[i];
                    for j in 0..i {
                        acc += m[(i, j)] * r[j];
                    }
                    col[i] -= acc;
                }
            }
            for i in 0..k {
                ja[i * n + c] = col[i];
            }
        }
    }
    let rounding = (0..k)
        .map(|i| {
            let mean: f64 = (0..k)
                .map(|j| (a_linv[(i, j)] * block.mean_rounding[j]).powi(2))
                .sum();
            let var = block.var_rounding.iter().fold(0.0f64, |acc, &v| acc.max(v));
            mean.sqrt().hypot(0.5 * r[i] * var)
        })
        .collect();
    Ok(WhitenedBlock {
        r: r.as_slice().to_vec(),
        ja,
        a_linv: a_linv.transpose().as_slice().to_vec(), // row-major
        rounding,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cov3() -> Covariance {
        Covariance::new("Q0", &[2.0, 0.5, 0.1, 0.5, 1.0, -0.2, 0.1, -0.2, 0.8], 3).unwrap()
    }

    /// r and its Jacobian against a dense evaluation and central differences, for a stage whose
    /// mean and variance depend on the node linearly: m = M x, σ² = exp(V x).
    #[test]
    fn whitened_block_and_its_jacobian_match_finite_differences() {
        let (k, n) = (3, 2);
        let cov = cov3();
        let rows = [0, 1, 2];
        let mm = [0.3, -1.0, 0.7, 0.2, -0.4, 0.9];
        let vv = [0.1, 0.2, -0.3, 0.05, 0.4, -0.1];
        let target = [0.4, -0.2, 1.1];
        let eval = |x: &[f64]| {
            let m: Vec<f64> = (0..k)
                .map(|i| mm[2 * i] * x[0] + mm[2 * i + 1] * x[1])
                .collect();
            let var: Vec<f64> = (0..k)
                .map(|i| (vv[2 * i] * x[0] + vv[2 * i + 1] * x[1]).exp())
                .collect();
            (m, var)
        };
        let x = [0.7, -0.3];
        let (m, var) = eval(&x);
        let e: Vec<f64> = (0..k).map(|i| target[i] - m[i]).collect();
        let dv: Vec<f64> = (0..k * n).map(|t| vv[t] * var[t / n]).collect();
        let zeros = [0.0; 3];
        let block = Block {
            a: 1.3,
            e: &e,
            var: &var,
            derivs: Some((&mm, &dv)),
            mean_rounding: &zeros,
            var_rounding: &zeros,
        };
        let w = whiten(&cov, &rows, &block, n).unwrap();
        // ‖r‖² = a² eᵀ S⁻¹ e.
        let s = cov.with_variances(&rows, &var);
        let ev = DVector::from_column_slice(&e);
        let quad = (ev.transpose() * s.try_inverse().unwrap() * &ev)[0];
        let rr: f64 = w.r.iter().map(|v| v * v).sum();
        assert!((rr - 1.69 * quad).abs() < 1e-12 * rr);
        let h = 1e-6;
        for c in 0..n {
            let at = |delta: f64| {
                let mut xp = x;
                xp[c] += delta;
                let (m, var) = eval(&xp);
                let e: Vec<f64> = (0..k).map(|i| target[i] - m[i]).collect();
                let b = Block {
                    a: 1.3,
                    e: &e,
                    var: &var,
                    derivs: None,
                    mean_rounding: &zeros,
                    var_rounding: &zeros,
                };
                whiten(&cov, &rows, &b, n).unwrap().r
            };
            let (p, q) = (at(h), at(-h));
            for i in 0..k {
                let fd = (p[i] - q[i]) / (2.0 * h);
                assert!(
                    (w.ja[i * n + c] - fd).abs() < 1e-7,
                    "{i},{c}: {} vs {fd}",
                    w.ja[i * n + c]
                );
            }
        }
    }

    #[test]
    fn a_diagonal_covariance_whitens_row_by_row() {
        let cov = Covariance::new("R0", &[4.0, 0.25], 2).unwrap();
        assert!(cov.is_diagonal());
        let zeros = [0.0; 2];
        let b = Block {
            a: 2.0,
            e: &[1.0, 1.0],
            var: &[0.0, 0.75],
            derivs: None,
            mean_rounding: &zeros,
            var_rounding: &zeros,
        };
        let w = whiten(&cov, &[0, 1], &b, 1).unwrap();
        assert!((w.r[0] - 1.0).abs() < 1e-15 && (w.r[1] - 2.0).abs() < 1e-15);
    }

    #[test]
    fn bad_covariances_are_rejected_naming_the_argument() {
        let err = |v: &[f64], d| Covariance::new("Q0", v, d).unwrap_err().to_string();
        assert!(err(&[1.0, 2.0, 3.0], 2).starts_with("Q0: needs 2 values"));
        assert!(err(&[1.0, 0.5, 0.4, 1.0], 2).contains("symmetric"));
        assert!(err(&[1.0, 2.0, 2.0, 1.0], 2).contains("positive definite"));
        assert!(err(&[0.0, 1.0], 2).contains("positive definite"));
        assert!(err(&[f64::NAN, 1.0], 2).starts_with("Q0: contains a non-finite"));
        assert!(!cov3().is_diagonal());
    }
}
