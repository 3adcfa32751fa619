//! A sparse GP whose posterior of the inducing outputs u = f(Z) is replaced: the model of a GP that
//! keeps learning online (`crate::mhe::LearningStageModel`), which predicts with the variance
//! given u, σ_f² − J (Kuu + δI) Jᵀ ([`SparseGp::set_conditional`]), and its snapshot. With
//! N(μ_u, Σ_u) in place of the fitted posterior (`posterior.rs`), the mean at d is J μ_u with
//! J = k(d, Z) (Kuu + δI)⁻¹, that is
//! t = (Kuu + δI)⁻¹ μ_u, and the latent variance σ_f² − J (Kuu + δI) Jᵀ + J Σ_u Jᵀ, that is
//! L_B L_Bᵀ = B = Lᵀ Σ_u⁻¹ L (P = L B Lᵀ = K Σ_u⁻¹ K): the prediction code is unchanged. J is
//! also the mean's derivative with respect to μ_u.

use std::sync::Arc;

use faer::linalg::solvers::Llt;
use faer::linalg::triangular_solve::{
    solve_lower_triangular_in_place, solve_upper_triangular_in_place,
};
use faer::{Mat, MatMut, MatRef, Par, Side};

use super::{SparseGp, SparseMultiGp};
use crate::error::{check_finite, check_len, Error, Result};
use crate::gp::kernel_column;

impl SparseGp {
    /// Whether predictions give the variance given the inducing outputs (u known), σ_f² −
    /// J (Kuu + δI) Jᵀ, rather than the posterior's; the mean and its gradients are the same.
    pub fn set_conditional(&mut self, on: bool) {
        self.conditional = on;
    }

    /// Sets the mean of the inducing outputs, μ_u (m values): t = (Kuu + δI)⁻¹ μ_u.
    pub fn set_inducing_mean(&mut self, mu: &[f64]) -> Result<()> {
        let m = self.n_inducing();
        check_len("mean", mu, m)?;
        check_finite("mean", mu)?;
        self.t.clear();
        self.t.extend_from_slice(mu);
        let mut t = MatMut::from_column_major_slice_mut(&mut self.t, m, 1);
        solve_lower_triangular_in_place(self.l.as_ref(), t.as_mut(), Par::Seq);
        solve_upper_triangular_in_place(self.l.transpose(), t, Par::Seq);
        self.mean_rounding = f64::EPSILON
            * self.kernel.variance()
            * self.t.iter().map(|a| a * a).sum::<f64>().sqrt();
        Ok(())
    }

    /// L_B for the covariance Σ_u of the inducing outputs (`sigma` m × m, symmetric positive
    /// definite): what [`SparseGp::set_inducing_posterior`] installs. A `Numerical` error if Σ_u
    /// or B is not positive definite.
    fn variance_factor(&self, sigma: MatRef<'_, f64>) -> Result<Mat<f64>> {
        let m = self.n_inducing();
        if sigma.nrows() != m || sigma.ncols() != m {
            return Err(Error::invalid("cov", format!("must be {m} x {m}")));
        }
        if (0..m).any(|j| (0..m).any(|i| !sigma[(i, j)].is_finite())) {
            return Err(Error::invalid("cov", "contains NaN or inf"));
        }
        let not_pd =
            || Error::numerical("the inducing outputs' covariance is not positive definite");
        let r = Llt::new(sigma, Side::Lower).map_err(|_| not_pd())?;
        // W = R⁻¹ L (Σ_u = R Rᵀ), B = WᵀW.
        let mut w = self.l.clone();
        solve_lower_triangular_in_place(r.L(), w.as_mut(), Par::Seq);
        let b = w.transpose() * &w;
        let lb: Mat<f64> = Llt::new(b.as_ref(), Side::Lower)
            .map_err(|_| not_pd())?
            .L()
            .to_owned();
        if (0..m).any(|j| !(lb[(j, j)].is_finite() && lb[(j, j)] > 0.0)) {
            return Err(not_pd());
        }
        Ok(lb)
    }

    /// Sets the posterior of the inducing outputs to N(μ_u, Σ_u) (`sigma` m × m, symmetric
    /// positive definite). Errors as [`SparseGp::variance_factor`]; nothing changes on error.
    pub fn set_inducing_posterior(&mut self, mu: &[f64], sigma: MatRef<'_, f64>) -> Result<()> {
        let lb = self.variance_factor(sigma)?;
        self.set_inducing_mean(mu)?;
        self.lb = lb;
        let m = self.n_inducing();
        let cov = (0..m * m).map(|k| sigma[(k / m, k % m)]).collect();
        self.replaced = Some(Arc::new((mu.to_vec(), cov)));
        Ok(())
    }

    /// The posterior (mean, row-major covariance) that replaced the fit's, if any.
    pub fn replaced_posterior(&self) -> Option<&(Vec<f64>, Vec<f64>)> {
        self.replaced.as_deref()
    }

    /// J = k(d, Z) (Kuu + δI)⁻¹ at k points `d` (k × n_d) into `out` (k × m, row-major): the
    /// derivative of the mean at each point with respect to μ_u.
    pub fn inducing_jacobian_into(&self, d: &[f64], out: &mut [f64]) -> Result<()> {
        let (m, nd) = (self.n_inducing(), self.dim());
        let k = d.len() / nd;
        check_len("out", out, k * m)?;
        let (w, s2) = (self.kernel.inv_lengthscales_sq(), self.kernel.variance());
        for (dj, col) in d.chunks_exact(nd).zip(out.chunks_exact_mut(m)) {
            kernel_column(&self.z, dj, w, s2, col);
        }
        let mut j = MatMut::from_column_major_slice_mut(out, m, k);
        solve_lower_triangular_in_place(self.l.as_ref(), j.as_mut(), Par::Seq);
        solve_upper_triangular_in_place(self.l.transpose(), j, Par::Seq);
        Ok(())
    }
}

impl SparseMultiGp {
    /// Output `o`'s GP, to replace its posterior of the inducing outputs (see `learning.rs`).
    pub fn gp_mut(&mut self, o: usize) -> Option<&mut SparseGp> {
        self.gps.get_mut(o)
    }
}
