//! [`Rgp`]: Huber's recursive GP on fixed basis vectors, the weights' mean μ_z and covariance
//! C_z, with inference (eq. 3), the update (eq. 4) with process noise σ_p and the
//! prediction-variance floor σ_r², and batches of updates.

use faer::linalg::matmul::matmul;
use faer::{Accum, Mat, MatMut, MatRef, Par};

use super::{check_nonneg, RgpBasis};
use crate::error::{check_finite, check_len, Error, Result};
use crate::linalg::dot_lanes8;

/// Huber's recursive GP on fixed basis vectors (a grid, or given points): weights' mean μ_z and
/// covariance C_z.
#[derive(Debug, Clone)]
pub struct Rgp {
    pub(super) basis: RgpBasis,
    pub(super) mean: Vec<f64>,
    pub(super) cov: Mat<f64>,
    pub(super) j: Vec<f64>,
    pub(super) g: Vec<f64>,
}

impl Rgp {
    /// A fresh RGP: μ_z = 0, C_z = K (eq. 2).
    pub fn new(basis: RgpBasis) -> Self {
        let nb = basis.n_basis();
        Self {
            mean: vec![0.0; nb],
            cov: basis.k.clone(),
            j: vec![0.0; nb],
            g: vec![0.0; nb],
            basis,
        }
    }

    pub fn basis(&self) -> &RgpBasis {
        &self.basis
    }

    pub fn mean(&self) -> &[f64] {
        &self.mean
    }

    pub fn cov(&self) -> MatRef<'_, f64> {
        self.cov.as_ref()
    }

    /// The weights' covariance C_z as stored (row-major n_b × n_b), for an exact copy.
    pub fn cov_raw(&self) -> Vec<f64> {
        let nb = self.basis.n_basis();
        (0..nb * nb).map(|k| self.cov[(k / nb, k % nb)]).collect()
    }

    /// Replaces μ_z and C_z by exactly these values (as [`Rgp::mean`], [`Rgp::cov_raw`] gave
    /// them; not symmetrised). On error nothing changes.
    pub fn set_weights_raw(&mut self, mean: &[f64], cov: &[f64]) -> Result<()> {
        let nb = self.basis.n_basis();
        check_len("mean", mean, nb)?;
        check_len("cov", cov, nb * nb)?;
        check_finite("mean", mean)?;
        check_finite("cov", cov)?;
        self.mean.copy_from_slice(mean);
        for (k, v) in cov.iter().enumerate() {
            self.cov[(k / nb, k % nb)] = *v;
        }
        Ok(())
    }

    /// Replaces the weights' mean and covariance (row-major n_b × n_b, symmetrised).
    pub fn set_weights(&mut self, mean: &[f64], cov: &[f64]) -> Result<()> {
        let nb = self.basis.n_basis();
        check_len("cov", cov, nb * nb)?;
        let sym: Vec<f64> = (0..nb * nb)
            .map(|k| {
                let (i, j) = (k / nb, k % nb);
                0.5 * (cov[i * nb + j] + cov[j * nb + i])
            })
            .collect();
        self.set_weights_raw(mean, &sym)
    }

    /// J_k for one input (for tests and diagnostics).
    pub fn j_row(&mut self, zeta: &[f64]) -> Result<Vec<f64>> {
        self.basis.check_zeta("zeta", zeta)?;
        let mut j = vec![0.0; self.basis.n_basis()];
        self.basis.infer(zeta, &mut j);
        Ok(j)
    }

    /// Mean (prior mean included) and variance (σ_r² included) at the row-major inputs `zetas`.
    pub fn predict(&mut self, zetas: &[f64]) -> Result<(Vec<f64>, Vec<f64>)> {
        let m = self.basis.count_inputs(zetas)?;
        let (mut mu, mut var) = (vec![0.0; m], vec![0.0; m]);
        let Self {
            basis,
            mean,
            cov,
            j,
            ..
        } = self;
        basis.predict_with(mean, cov.as_ref(), false, zetas, j, &mut mu, &mut var);
        Ok((mu, var))
    }

    /// One measurement y of the GP output at input ζ with noise variance `var_y` (eq. 3, 4):
    /// G = C_z Jᵀ / (C^p + σ_r² + σ_y²), μ_z += G (y − m(ζ) − J μ_z), C_z −= G J C_z,
    /// C_z += σ_p² I (m the prior mean, 0 without one). Returns the predicted mean
    /// m(ζ) + J μ_z before the update. On error the state is unchanged.
    pub fn update(&mut self, zeta: &[f64], y: f64, var_y: f64) -> Result<f64> {
        with_avx2!(Rgp, self.update_impl(zeta: &[f64], y: f64, var_y: f64) -> Result<f64>)
    }

    #[inline(always)]
    fn update_impl(&mut self, zeta: &[f64], y: f64, var_y: f64) -> Result<f64> {
        self.basis.check_zeta("zeta", zeta)?;
        if !y.is_finite() {
            return Err(Error::invalid("y", format!("must be finite, got {y}")));
        }
        check_nonneg("var_y", var_y)?;
        let nb = self.basis.n_basis();
        let jkj = self.basis.infer(zeta, &mut self.j);
        // g = C_z Jᵀ
        {
            let jcol = MatRef::from_column_major_slice(&self.j, nb, 1);
            let gcol = MatMut::from_column_major_slice_mut(&mut self.g, nb, 1);
            matmul(gcol, Accum::Replace, self.cov.as_ref(), jcol, 1.0, Par::Seq);
        }
        let jcj = dot_lanes8(&self.j, &self.g);
        let cp = (self.basis.sigma_k2() - jkj).max(0.0) + jcj;
        let s = cp + self.basis.sigma_r2 + var_y;
        if !(s.is_finite() && s > 0.0) {
            return Err(Error::numerical(format!(
                "innovation variance {s} is not positive (set var_y > 0 or sigma_r > 0)"
            )));
        }
        let mu_p = dot_lanes8(&self.j, &self.mean) + self.basis.prior_mean_at(zeta);
        let innov = (y - mu_p) / s;
        for (m, g) in self.mean.iter_mut().zip(&self.g) {
            *m += g * innov;
        }
        // C −= g gᵀ / s, column by column; (g_i g_j) / s is the same for (i, j) and (j, i), so C
        // stays exactly symmetric
        let inv_s = 1.0 / s;
        for jj in 0..nb {
            let gj = self.g[jj];
            let col = self.cov.col_as_slice_mut(jj);
            for (ci, gi) in col.iter_mut().zip(&self.g) {
                *ci -= (gi * gj) * inv_s;
            }
            col[jj] += self.basis.sigma_p2;
        }
        Ok(mu_p)
    }
}

impl Rgp {
    /// Sequential updates with m measurements in one call: `zetas` row-major (m × n_X), `ys` (m),
    /// `var_y` one variance for all or one per measurement. Returns the prediction J μ_z made
    /// before each update. All inputs are validated first; if an update fails numerically the
    /// weights are restored to their state before the call.
    pub fn update_many(&mut self, zetas: &[f64], ys: &[f64], var_y: &[f64]) -> Result<Vec<f64>> {
        let (nx, m) = (self.basis.dim(), ys.len());
        check_len("zeta", zetas, m * nx)?;
        check_finite("zeta", zetas)?;
        self.basis.check_prior_mean("zeta", zetas)?;
        check_finite("y", ys)?;
        if var_y.len() != 1 && var_y.len() != m {
            return Err(Error::invalid(
                "var_y",
                format!("expected 1 or {m} values, got {}", var_y.len()),
            ));
        }
        if let Some(v) = var_y.iter().find(|v| !(v.is_finite() && **v >= 0.0)) {
            return Err(Error::invalid(
                "var_y",
                format!("must be finite and >= 0, got {v}"),
            ));
        }
        let backup = (self.mean.clone(), self.cov.clone());
        let mut out = Vec::with_capacity(m);
        for i in 0..m {
            let v = if var_y.len() == 1 { var_y[0] } else { var_y[i] };
            let step = crate::interrupt::check()
                .and_then(|()| self.update(&zetas[i * nx..(i + 1) * nx], ys[i], v));
            match step {
                Ok(p) => out.push(p),
                Err(e) => {
                    (self.mean, self.cov) = backup;
                    return Err(e);
                }
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rgp::test_basis as basis;

    #[test]
    fn bad_input_is_rejected_and_leaves_state() {
        assert!(RgpBasis::new(&[0.0], &[0.0], &[5], 1.0, 1.0, 0.0, 0.0).is_err());
        assert!(RgpBasis::new(&[0.0], &[1.0], &[1], 1.0, 1.0, 0.0, 0.0).is_err());
        assert!(RgpBasis::new(&[0.0], &[1.0], &[5], -1.0, 1.0, 0.0, 0.0).is_err());
        assert!(RgpBasis::new(&[0.0], &[1.0], &[5], 1.0, f64::NAN, 0.0, 0.0).is_err());
        let mut gp = Rgp::new(basis(5));
        gp.update(&[0.1], 1.0, 0.01).unwrap();
        let (m, c) = (gp.mean().to_vec(), gp.cov().to_owned());
        assert!(gp.update(&[f64::NAN], 1.0, 0.01).is_err());
        assert!(gp.update(&[0.1, 0.2], 1.0, 0.01).is_err());
        assert!(gp.update(&[0.1], f64::INFINITY, 0.01).is_err());
        assert!(gp.update(&[0.1], 1.0, -1.0).is_err());
        assert_eq!(gp.mean(), &m[..]);
        assert_eq!(gp.cov().to_owned(), c);
    }

    #[test]
    fn batch_update_restores_weights_on_numerical_failure() {
        // σ_r = 0, var_y = 0 and K = I (up to e^-500): a second exact observation of a basis
        // vector has s = 0
        let mut gp = Rgp::new(RgpBasis::new(&[0.0], &[4.0], &[5], 1.0, 1e-3, 0.0, 0.0).unwrap());
        gp.update(&[3.0], 0.5, 0.1).unwrap();
        let (m, c) = (gp.mean().to_vec(), gp.cov().to_owned());
        let err = gp.update_many(&[1.0, 2.0, 2.0], &[0.1, 0.2, 0.2], &[0.0]);
        assert!(matches!(err, Err(Error::Numerical(_))));
        assert_eq!(gp.mean(), &m[..]);
        assert_eq!(gp.cov().to_owned(), c);
    }
}
