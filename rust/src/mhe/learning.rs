//! [`LearningStageModel`]: the learned model of GP-MHE whose f-GPs keep learning. The f-GPs are
//! sparse; their inducing outputs u_o = f_o(Z_o) (o = 1 … n) are the window's global variables
//! g = [u_1; …; u_n] ([`StageModel::n_globals`]). The mean of f_o at d is J_o(d) u_o plus its
//! prior mean (and x_o in the residual form), J_o(d) = k(d, Z_o) (K_o + δI)⁻¹, so ∂m_o/∂u_o =
//! J_o(d). The variances are those given u, σ²_o − J_o (K_o + δI) J_oᵀ: the uncertainty of u is
//! not in the model but in the window, as the prior of g (`joint_arrival.rs`), so that with the
//! states known the window's posterior of g is the recursive GP's (Huber's update, whose
//! observation noise is this variance). The variances do not depend on g. The h-GPs (exact or
//! sparse) are fixed. [`LearningStageModel::snapshot`] gives the sparse GPs of a posterior
//! N(μ_u, Σ_u), predicting with the full variance σ² − J K Jᵀ + J Σ_u Jᵀ.

use std::sync::Arc;

use faer::{Mat, MatRef};

use super::stage::{add_state, count_points, predict_outputs, StageEval, StageModel};
use crate::error::{check_len, Error, Result};
use crate::gp_model::{GpModel, ModelWorkspace};
use crate::sparse::{SparseMultiGp, SparseWorkspace};

/// A GP stage model whose sparse f-GPs' inducing outputs are global variables (module docs).
#[derive(Debug, Clone)]
pub struct LearningStageModel {
    /// The f-GPs as fitted (shared), and the copy whose inducing outputs are g.
    fitted: Arc<SparseMultiGp>,
    f: SparseMultiGp,
    h: Option<Arc<GpModel>>,
    f_residual: bool,
    n: usize,
    m: usize,
    /// Start of u_o in g, for o = 0 … n (the last entry is n_g).
    offsets: Vec<usize>,
    ws: SparseWorkspace,
    h_ws: ModelWorkspace,
    /// Scratch: every output's J at the points of an evaluation.
    jac: Vec<Vec<f64>>,
}

impl LearningStageModel {
    /// `f` has n outputs on inputs of dimension n + `dim_u`; `h` (None when p = 0) has p outputs
    /// on the same inputs. g starts at the fitted posterior mean.
    pub fn new(
        f: SparseMultiGp,
        h: Option<GpModel>,
        dim_u: usize,
        f_residual: bool,
    ) -> Result<Self> {
        let n = f.n_outputs();
        for (name, dim) in [("f", Some(f.dim())), ("h", h.as_ref().map(GpModel::dim))] {
            if let Some(dim) = dim.filter(|&d| d != n + dim_u) {
                return Err(Error::invalid(
                    name,
                    format!(
                        "GP input dimension {dim} is not dim_x + dim_u = {}",
                        n + dim_u
                    ),
                ));
            }
        }
        let fitted = Arc::new(f.clone());
        let mut f = f;
        let mut offsets = vec![0];
        for o in 0..n {
            let gp = f
                .gp_mut(o)
                .ok_or_else(|| Error::invalid("f", "missing output"))?;
            gp.set_conditional(true);
            offsets.push(offsets[o] + gp.n_inducing());
        }
        Ok(Self {
            fitted,
            f,
            h: h.map(Arc::new),
            f_residual,
            n,
            m: dim_u,
            offsets,
            ws: SparseWorkspace::default(),
            h_ws: ModelWorkspace::default(),
            jac: Vec::new(),
        })
    }

    /// Start of each output's inducing outputs in g (n + 1 values, the last is n_g).
    pub fn offsets(&self) -> &[usize] {
        &self.offsets
    }

    /// The f-GPs as fitted.
    pub fn fitted(&self) -> &Arc<SparseMultiGp> {
        &self.fitted
    }

    pub fn f_residual(&self) -> bool {
        self.f_residual
    }

    /// The fixed h-GPs, if any.
    pub fn h(&self) -> Option<&Arc<GpModel>> {
        self.h.as_ref()
    }

    /// The fitted posterior of the inducing outputs, N(μ_u, Σ_u) (n_g values and n_g × n_g,
    /// block-diagonal: the outputs' blocks): the prior learning starts from.
    pub fn fitted_posterior(&self) -> (Vec<f64>, Mat<f64>) {
        let ng = self.n_globals();
        let mut mean = Vec::with_capacity(ng);
        let mut cov = Mat::zeros(ng, ng);
        for (o, gp) in self.fitted.gps().iter().enumerate() {
            let (mu, sigma) = gp.inducing_posterior();
            let a = self.offsets[o];
            cov.as_mut()
                .submatrix_mut(a, a, mu.len(), mu.len())
                .copy_from(&sigma);
            mean.extend(mu);
        }
        (mean, cov)
    }

    /// The f-GPs with the posterior N(mean, cov) of the inducing outputs (n_g values, n_g × n_g;
    /// only the outputs' diagonal blocks enter their variances), predicting with the full
    /// variance: the learned model as a fixed one. A `Numerical` error if a block is not
    /// positive definite.
    pub fn snapshot(&self, mean: &[f64], cov: MatRef<'_, f64>) -> Result<SparseMultiGp> {
        let ng = self.n_globals();
        check_len("mean", mean, ng)?;
        if cov.nrows() != ng || cov.ncols() != ng {
            return Err(Error::invalid("cov", format!("must be {ng} x {ng}")));
        }
        let mut f = SparseMultiGp::clone(&self.fitted);
        for o in 0..self.n {
            let (a, b) = (self.offsets[o], self.offsets[o + 1]);
            let gp = f
                .gp_mut(o)
                .ok_or_else(|| Error::invalid("f", "missing output"))?;
            gp.set_inducing_posterior(&mean[a..b], cov.submatrix(a, a, b - a, b - a))?;
        }
        Ok(f)
    }

    /// GP values at the k points `d` into `out` (sized for k points and n_g global variables).
    fn predict(&mut self, d: &[f64], out: &mut StageEval) -> Result<()> {
        let (n, nd) = (self.n, self.n + self.m);
        self.f.predict_conditional_into(
            d,
            [
                &mut out.mean_x,
                &mut out.var_x,
                &mut out.dmean_x,
                &mut out.dvar_x,
            ],
            &mut self.jac,
            &mut self.ws,
        )?;
        if self.f_residual {
            add_state(d, n, nd, out);
        }
        let ng = self.n_globals();
        for (o, jo) in self.jac.iter().enumerate() {
            let (a, b) = (self.offsets[o], self.offsets[o + 1]);
            for (i, row) in jo.chunks_exact(b - a).enumerate() {
                out.dmean_x_dg[(i * n + o) * ng + a..(i * n + o) * ng + b].copy_from_slice(row);
            }
        }
        if let Some(h) = &self.h {
            predict_outputs(h, d, out, &mut self.h_ws)?;
        }
        Ok(())
    }
}

impl StageModel for LearningStageModel {
    fn dim_x(&self) -> usize {
        self.n
    }
    fn dim_u(&self) -> usize {
        self.m
    }
    fn dim_y(&self) -> usize {
        self.h.as_ref().map_or(0, |h| h.n_outputs())
    }
    fn n_globals(&self) -> usize {
        self.offsets[self.n]
    }

    /// Sets the f-GPs' inducing outputs to g (their means; the variances keep the posterior).
    fn set_globals(&mut self, g: &[f64]) -> Result<()> {
        check_len("globals", g, self.n_globals())?;
        for o in 0..self.n {
            let (a, b) = (self.offsets[o], self.offsets[o + 1]);
            let gp = self
                .f
                .gp_mut(o)
                .ok_or_else(|| Error::invalid("f", "missing output"))?;
            gp.set_inducing_mean(&g[a..b])?;
        }
        Ok(())
    }

    fn evaluate(&mut self, d: &[f64], out: &mut StageEval) -> Result<()> {
        let (n, m, p) = (self.n, self.m, self.dim_y());
        let k = count_points(d, n + m)?;
        out.resize(k, n, m, p);
        out.resize_globals(k, n, p, self.n_globals());
        self.f
            .rounding_into(&mut out.mean_x_rounding, &mut out.var_x_rounding);
        if let Some(h) = &self.h {
            h.rounding_into(&mut out.mean_y_rounding, &mut out.var_y_rounding);
        }
        self.predict(d, out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gp::tests::{data, theta};
    use crate::mhe::GpStageModel;
    use crate::sparse::SparseMethod;

    /// Sparse f-GPs (n = 2 outputs, m = 1 input, 6 and 9 inducing points) and an exact h-GP.
    fn model() -> (SparseMultiGp, GpModel) {
        let nd = 3;
        let (x, y0) = data(80, nd, 3);
        let (_, y1) = data(80, nd, 4);
        let y: Vec<f64> = y0.iter().chain(&y1).copied().collect();
        let (z0, z1) = (x[..6 * nd].to_vec(), x[20 * nd..29 * nd].to_vec());
        let th: Vec<f64> = theta(nd).iter().chain(&theta(nd)).copied().collect();
        let f = SparseMultiGp::new(&x, &y, &[&z0, &z1], &th, SparseMethod::Fitc).unwrap();
        let h = crate::gp::MultiGp::new(&x[..30 * nd], &y0[..30], &theta(nd)).unwrap();
        (f, GpModel::Exact(h))
    }

    fn points() -> Vec<f64> {
        data(5, 3, 9).0
    }

    #[test]
    fn it_predicts_the_fixed_models_means_and_its_snapshot_the_fixed_model() {
        let (f, h) = model();
        let mut fixed =
            GpStageModel::new(GpModel::Sparse(f.clone()), Some(h.clone()), 1, true).unwrap();
        let mut learning = LearningStageModel::new(f, Some(h), 1, true).unwrap();
        assert_eq!(learning.n_globals(), 15);
        assert_eq!(learning.offsets(), &[0, 6, 15]);
        let (mu, sigma) = learning.fitted_posterior();
        learning.set_globals(&mu).unwrap();
        let d = points();
        let (mut a, mut b) = (StageEval::default(), StageEval::default());
        fixed.evaluate(&d, &mut a).unwrap();
        learning.evaluate(&d, &mut b).unwrap();
        let close = |x: &[f64], y: &[f64]| {
            x.iter()
                .zip(y)
                .all(|(p, q)| (p - q).abs() <= 1e-9 * (1.0 + q.abs()))
        };
        assert!(close(&b.mean_x, &a.mean_x) && close(&b.dmean_x, &a.dmean_x));
        assert_eq!((&b.mean_y, &b.var_y), (&a.mean_y, &a.var_y));
        // The variance given u is below the fit's (the posterior of u adds J Σ_u Jᵀ ≥ 0).
        assert!(b.var_x.iter().zip(&a.var_x).all(|(c, p)| c <= p));
        // The snapshot of the fitted posterior is the fitted model.
        let snap = learning.snapshot(&mu, sigma.as_ref()).unwrap();
        let mut again = GpStageModel::new(GpModel::Sparse(snap), None, 1, true).unwrap();
        let mut c = StageEval::default();
        again.evaluate(&d, &mut c).unwrap();
        assert!(close(&c.mean_x, &a.mean_x) && close(&c.dmean_x, &a.dmean_x));
        assert!(close(&c.var_x, &a.var_x) && close(&c.dvar_x, &a.dvar_x));
    }

    #[test]
    fn conditional_variance_and_its_gradient_match_finite_differences() {
        let (f, h) = model();
        let mut learning = LearningStageModel::new(f, Some(h), 1, false).unwrap();
        let d = points();
        let mut ev = StageEval::default();
        learning.evaluate(&d, &mut ev).unwrap();
        let mut e2 = StageEval::default();
        for c in 0..3 {
            let mut dp = d.clone();
            dp[c] += 1e-6;
            learning.evaluate(&dp, &mut e2).unwrap();
            for o in 0..2 {
                let fd = (e2.var_x[o] - ev.var_x[o]) / 1e-6;
                assert!((ev.dvar_x[o * 3 + c] - fd).abs() <= 1e-5 * (1.0 + fd.abs()));
            }
        }
    }

    #[test]
    fn mean_jacobian_with_respect_to_the_globals_matches_finite_differences() {
        let (f, h) = model();
        let mut learning = LearningStageModel::new(f, Some(h), 1, false).unwrap();
        let (mu, _) = learning.fitted_posterior();
        let g: Vec<f64> = mu
            .iter()
            .enumerate()
            .map(|(i, v)| v + 0.05 * i as f64)
            .collect();
        let d = points();
        let mut ev = StageEval::default();
        learning.set_globals(&g).unwrap();
        learning.evaluate(&d, &mut ev).unwrap();
        let (k, n, ng) = (5, 2, 15);
        let mut e2 = StageEval::default();
        for c in 0..ng {
            let mut gp = g.clone();
            gp[c] += 1e-6;
            learning.set_globals(&gp).unwrap();
            learning.evaluate(&d, &mut e2).unwrap();
            for r in 0..k * n {
                let fd = (e2.mean_x[r] - ev.mean_x[r]) / 1e-6;
                assert!((ev.dmean_x_dg[r * ng + c] - fd).abs() <= 1e-6 * (1.0 + fd.abs()));
                // The variances do not depend on g.
                assert_eq!(e2.var_x[r], ev.var_x[r]);
            }
            assert!(e2.dmean_y_dg.iter().all(|&v| v == 0.0));
        }
    }

    #[test]
    fn bad_input_is_refused() {
        let (f, h) = model();
        let mut learning = LearningStageModel::new(f, Some(h), 1, false).unwrap();
        let (mu, sigma) = learning.fitted_posterior();
        let mut bad = sigma.clone();
        bad[(10, 10)] = -1.0;
        let e = learning.snapshot(&mu, bad.as_ref()).unwrap_err();
        assert!(matches!(e, Error::Numerical(_)));
        let e = learning.snapshot(&mu[1..], sigma.as_ref()).unwrap_err();
        assert!(matches!(e, Error::InvalidInput { ref arg, .. } if arg == "mean"));
        let e = learning.set_globals(&mu[1..]).unwrap_err();
        assert!(matches!(e, Error::InvalidInput { ref arg, .. } if arg == "globals"));
        let (f, h) = model();
        let e = LearningStageModel::new(f, Some(h), 2, false).unwrap_err();
        assert!(matches!(e, Error::InvalidInput { ref arg, .. } if arg == "f"));
    }
}
