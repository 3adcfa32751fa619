//! Predictions of the sparse GPs: for k test points d, with k* = k(Z, d) (m values),
//! mean k*ᵀ t, latent variance σ_f² − ‖v‖² + ‖w‖² with v = L⁻¹ k*, w = L_B⁻¹ v (w = 0 for the
//! variance given the inducing outputs, `learning.rs`) (that is
//! σ_f² − k*ᵀ (Kuu⁻¹ − P⁻¹) k*, without explicit inverses), and their gradients w.r.t. d:
//! ∂mean/∂d_l = −w_l Σ_i t_i k_i (d_l − z_il), ∂var/∂d_l = 2 w_l Σ_i β_i k_i (d_l − z_il) with
//! β = (Kuu⁻¹ − P⁻¹) k* = L⁻ᵀ (v − L_B⁻ᵀ w). O(m n_d) per point for the mean, O(m²) for the
//! variance (two triangular solves, four with gradients), for a batch at once (faer).

use faer::linalg::triangular_solve::{
    solve_lower_triangular_in_place, solve_upper_triangular_in_place,
};
use faer::{MatMut, Par};

use super::{SparseGp, SparseMultiGp};
use crate::error::{Error, Result};
use crate::gp::kernel_column;

/// Scratch memory for batch predictions (m × k buffers and one of n_d); it only grows, so once
/// sized for the largest batch in use, predictions allocate nothing.
#[derive(Default, Clone, Debug)]
pub struct SparseWorkspace {
    kstar: Vec<f64>,
    v: Vec<f64>,
    w: Vec<f64>,
    g: Vec<f64>,
}

/// Where one output's results go: point j's value at `[j * q + o]`, its gradient at
/// `[(j * q + o) * n_d ..]`.
struct Out<'a> {
    o: usize,
    q: usize,
    mean: &'a mut [f64],
    var: Option<&'a mut [f64]>,
    grads: Option<(&'a mut [f64], &'a mut [f64])>,
    /// For a GP giving the variance given the inducing outputs: J (k × m, row-major), which is
    /// then the β of the variance's gradient (`learning.rs`).
    jac: Option<&'a mut [f64]>,
}

impl SparseGp {
    /// (Σ_i b_i k_i, Σ_i b_i k_i z_i) for one test point's kernel column `kc` and weights `b`;
    /// the gradient of Σ_i b_i k(z_i, d) w.r.t. d_l is then −w_l (d_l s − g_l).
    fn weighted(&self, kc: &[f64], b: &[f64], g: &mut [f64]) -> f64 {
        let nd = self.dim();
        g.iter_mut().for_each(|v| *v = 0.0);
        let mut s = 0.0;
        for ((kb, zi), bi) in kc.iter().zip(self.z.chunks_exact(nd)).zip(b) {
            let c = kb * bi;
            s += c;
            g.iter_mut().zip(zi).for_each(|(gl, zl)| *gl += c * zl);
        }
        s
    }

    fn predict_block(&self, d: &[f64], out: Out<'_>, ws: &mut SparseWorkspace) {
        super::dispatch(
            #[inline(always)]
            || self.predict_block_impl(d, out, ws),
        )
    }

    #[inline(always)]
    fn predict_block_impl(&self, d: &[f64], out: Out<'_>, ws: &mut SparseWorkspace) {
        let (m, nd) = (self.n_inducing(), self.dim());
        let k = d.len() / nd;
        let w = self.kernel.inv_lengthscales_sq();
        let s2 = self.kernel.variance();
        let Out {
            o,
            q,
            mean,
            var,
            mut grads,
            jac,
        } = out;
        ws.kstar.resize(m * k, 0.0);
        ws.g.resize(nd, 0.0);
        let kstar = &mut ws.kstar[..m * k];
        let g = &mut ws.g[..];
        for (j, dj) in d.chunks_exact(nd).enumerate() {
            let kc = &mut kstar[j * m..(j + 1) * m];
            kernel_column(&self.z, dj, w, s2, kc);
            let s = self.weighted(kc, &self.t, g);
            mean[j * q + o] = s;
            if let Some((dmean, _)) = grads.as_mut() {
                let gm = &mut dmean[(j * q + o) * nd..(j * q + o + 1) * nd];
                for l in 0..nd {
                    gm[l] = -w[l] * (dj[l] * s - g[l]);
                }
            }
        }
        let Some(var) = var else { return };
        ws.v.clear();
        ws.v.extend_from_slice(kstar);
        let v = MatMut::from_column_major_slice_mut(&mut ws.v[..], m, k);
        solve_lower_triangular_in_place(self.l.as_ref(), v, Par::Seq);
        ws.w.clear();
        if self.conditional {
            // Given the inducing outputs: no posterior term (w = 0, β = L⁻ᵀ v).
            ws.w.resize(m * k, 0.0);
        } else {
            ws.w.extend_from_slice(&ws.v);
            let wm = MatMut::from_column_major_slice_mut(&mut ws.w[..], m, k);
            solve_lower_triangular_in_place(self.lb.as_ref(), wm, Par::Seq);
        }
        for j in 0..k {
            let sq = |a: &[f64]| a[j * m..(j + 1) * m].iter().map(|x| x * x).sum::<f64>();
            // Clamp round-off negatives at 0 (a test point on top of noise-free data).
            var[j * q + o] = (s2 - sq(&ws.v) + sq(&ws.w)).max(0.0);
        }
        let Some((_, dvar)) = grads else { return };
        // β = L⁻ᵀ (v − L_B⁻ᵀ w), into v.
        if !self.conditional {
            let wm = MatMut::from_column_major_slice_mut(&mut ws.w[..], m, k);
            solve_upper_triangular_in_place(self.lb.transpose(), wm, Par::Seq);
            ws.v.iter_mut().zip(&ws.w).for_each(|(a, b)| *a -= b);
        }
        let v = MatMut::from_column_major_slice_mut(&mut ws.v[..], m, k);
        solve_upper_triangular_in_place(self.l.transpose(), v, Par::Seq);
        if let Some(jac) = jac {
            // β = L⁻ᵀ L⁻¹ k* = (Kuu + δI)⁻¹ k* = Jᵀ when w = 0.
            debug_assert!(self.conditional);
            jac[..m * k].copy_from_slice(&ws.v[..m * k]);
        }
        for (j, dj) in d.chunks_exact(nd).enumerate() {
            let s = self.weighted(
                &ws.kstar[j * m..(j + 1) * m],
                &ws.v[j * m..(j + 1) * m],
                &mut ws.g,
            );
            let gv = &mut dvar[(j * q + o) * nd..(j * q + o + 1) * nd];
            for l in 0..nd {
                gv[l] = 2.0 * w[l] * (dj[l] * s - ws.g[l]);
            }
        }
    }
}

impl SparseMultiGp {
    fn check_io(&self, d: &[f64], outs: &[(&str, &[f64], usize)]) -> Result<usize> {
        crate::gp::check_io(&self.gps[0].kernel, d, outs)
    }

    /// As [`crate::gp::MultiGp::predict_with_gradients_into`]: means and latent variances
    /// (k × q), ∂mean/∂d and ∂var/∂d (k × q × n_d), all row-major.
    pub fn predict_with_gradients_into(
        &self,
        d: &[f64],
        mean: &mut [f64],
        var: &mut [f64],
        dmean: &mut [f64],
        dvar: &mut [f64],
        ws: &mut SparseWorkspace,
    ) -> Result<()> {
        self.predict_all(d, [mean, var, dmean, dvar], None, ws)
    }

    /// [`predict_with_gradients_into`](Self::predict_with_gradients_into) for GPs that give the
    /// variance given the inducing outputs (`learning.rs`), with every output's J at the points
    /// (`jac[o]`: k × m_o, row-major), which that variance's gradient computes anyway. An
    /// `Invalid` error if a GP gives the posterior's variance.
    pub fn predict_conditional_into(
        &self,
        d: &[f64],
        [mean, var, dmean, dvar]: [&mut [f64]; 4],
        jac: &mut Vec<Vec<f64>>,
        ws: &mut SparseWorkspace,
    ) -> Result<()> {
        if self.gps.iter().any(|gp| !gp.conditional) {
            return Err(Error::invalid(
                "f",
                "J comes with the variance given the inducing outputs only",
            ));
        }
        let k = d.len() / self.dim();
        jac.resize(self.n_outputs(), Vec::new());
        for (gp, jo) in self.gps.iter().zip(jac.iter_mut()) {
            jo.resize(k * gp.n_inducing(), 0.0);
        }
        self.predict_all(d, [mean, var, dmean, dvar], Some(jac), ws)
    }

    fn predict_all(
        &self,
        d: &[f64],
        [mean, var, dmean, dvar]: [&mut [f64]; 4],
        mut jac: Option<&mut Vec<Vec<f64>>>,
        ws: &mut SparseWorkspace,
    ) -> Result<()> {
        let (q, nd) = (self.n_outputs(), self.dim());
        self.check_io(
            d,
            &[
                ("mean", mean, q),
                ("var", var, q),
                ("dmean", dmean, q * nd),
                ("dvar", dvar, q * nd),
            ],
        )?;
        for (o, gp) in self.gps.iter().enumerate() {
            let out = Out {
                o,
                q,
                mean: &mut *mean,
                var: Some(&mut *var),
                grads: Some((&mut *dmean, &mut *dvar)),
                jac: jac.as_mut().map(|j| &mut j[o][..]),
            };
            gp.predict_block(d, out, ws);
        }
        if let Some(m) = self.mean() {
            m.add_values(d, mean);
            m.add_gradients(dmean);
        }
        Ok(())
    }

    /// Means and latent variances only (k × q each).
    pub fn predict_into(
        &self,
        d: &[f64],
        mean: &mut [f64],
        var: &mut [f64],
        ws: &mut SparseWorkspace,
    ) -> Result<()> {
        let q = self.n_outputs();
        self.check_io(d, &[("mean", mean, q), ("var", var, q)])?;
        for (o, gp) in self.gps.iter().enumerate() {
            let out = Out {
                o,
                q,
                mean: &mut *mean,
                var: Some(&mut *var),
                grads: None,
                jac: None,
            };
            gp.predict_block(d, out, ws);
        }
        if let Some(m) = self.mean() {
            m.add_values(d, mean);
        }
        Ok(())
    }

    /// Means only (k × q), O(m n_d) per point and output.
    pub fn predict_mean_into(
        &self,
        d: &[f64],
        mean: &mut [f64],
        ws: &mut SparseWorkspace,
    ) -> Result<()> {
        let q = self.n_outputs();
        self.check_io(d, &[("mean", mean, q)])?;
        for (o, gp) in self.gps.iter().enumerate() {
            let out = Out {
                o,
                q,
                mean: &mut *mean,
                var: None,
                grads: None,
                jac: None,
            };
            gp.predict_block(d, out, ws);
        }
        if let Some(m) = self.mean() {
            m.add_values(d, mean);
        }
        Ok(())
    }
}
