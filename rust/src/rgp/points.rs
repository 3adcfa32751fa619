//! Recursive GPs on basis vectors at given points: [`RgpBasis::from_points`] (an SE-ARD kernel in
//! ζ units, no grid normalisation), the optional affine prior mean m(ζ) = b + wᵀζ, and
//! [`Rgp::from_sparse`], the recursive GP that predicts exactly as a fitted sparse GP.
//!
//! A sparse GP (VFE or FITC) with inducing inputs Z, kernel k and P = Kuu + Kuf Λ⁻¹ Kfu predicts
//! mean k*ᵀ P⁻¹ Kuf Λ⁻¹ y and latent variance σ_f² − k*ᵀ (Kuu⁻¹ − P⁻¹) k* (Kuu with the sparse
//! GP's jitter). With basis vectors X = Z, the same kernel and jitter, J = k*ᵀ Kuu⁻¹ and weights
//! w ~ N(μ_u, Σ_u), μ_u = Kuu P⁻¹ Kuf Λ⁻¹ y, Σ_u = Kuu P⁻¹ Kuu, a recursive GP predicts J μ_u and
//! σ_f² − J Kuu Jᵀ + J Σ_u Jᵀ: the same, exactly ([`crate::sparse::SparseGp::inducing_posterior`]).
//! A prior mean of the sparse GP (it regressed y − m(d)) is added to every prediction.

use super::basis::{check_sigma_k, Jitter};
use super::{Rgp, RgpBasis};
use crate::error::{check_finite, Error, Result};
use crate::kernel::SeArd;
use crate::sparse::SparseMultiGp;

/// Most basis vectors of a dense recursive GP (as for a grid).
const MAX_BASIS: usize = 20_000;

impl RgpBasis {
    /// Basis vectors at `points` (row-major n_b × n_X, ζ units), kernel `kernel` on ζ (its
    /// dimension is n_X), K factored under `jitter`, floor σ_r, process noise σ_p. Errors name
    /// the argument (`points`, `sigma_K`, `jitter`, `sigma_r`, `sigma_p`); a K that does not
    /// factor is a `Numerical` error.
    pub fn from_points(
        points: &[f64],
        kernel: SeArd,
        jitter: Jitter,
        sigma_r: f64,
        sigma_p: f64,
    ) -> Result<Self> {
        let nx = kernel.dim();
        let nb = kernel.count_points("points", points)?;
        if nb == 0 || nb > MAX_BASIS {
            return Err(Error::invalid(
                "points",
                format!("expected 1 to {MAX_BASIS} basis vectors, got {nb}"),
            ));
        }
        check_sigma_k(kernel.sigma_f())?;
        let layout = (vec![0.0; nx], vec![1.0; nx], Vec::new());
        Self::assemble(layout, points.to_vec(), kernel, jitter, sigma_r, sigma_p)
    }

    /// The same basis with the prior mean m(ζ) = b + wᵀζ, `coef` = [b, w_1, …, w_nX] (ζ units,
    /// finite; an error naming `prior_mean` otherwise).
    pub fn with_prior_mean(mut self, coef: &[f64]) -> Result<Self> {
        let nx = self.dim();
        if coef.len() != nx + 1 {
            return Err(Error::invalid(
                "prior_mean",
                format!("expected {} coefficients, got {}", nx + 1, coef.len()),
            ));
        }
        check_finite("prior_mean", coef)?;
        self.prior_mean = Some(coef.to_vec());
        Ok(self)
    }

    /// The prior mean's coefficients [b, w_1, …, w_nX], if any.
    pub fn prior_mean(&self) -> Option<&[f64]> {
        self.prior_mean.as_deref()
    }

    /// m(ζ) for one input (0 without a prior mean).
    #[inline(always)]
    pub(super) fn prior_mean_at(&self, zeta: &[f64]) -> f64 {
        match &self.prior_mean {
            None => 0.0,
            Some(c) => c[0] + c[1..].iter().zip(zeta).map(|(a, b)| a * b).sum::<f64>(),
        }
    }

    /// Checks that m(ζ) is finite at every row of `zetas` (finite inputs of dimension n_X); an
    /// error naming `arg` otherwise (the product of two large finite numbers can overflow).
    pub(super) fn check_prior_mean(&self, arg: &str, zetas: &[f64]) -> Result<()> {
        if self.prior_mean.is_none() {
            return Ok(());
        }
        match zetas
            .chunks_exact(self.dim())
            .position(|z| !self.prior_mean_at(z).is_finite())
        {
            None => Ok(()),
            Some(i) => Err(Error::invalid(
                arg,
                format!("the prior mean is not finite at input {i} (too large an input)"),
            )),
        }
    }
}

impl Rgp {
    /// The recursive GP that predicts as output `output` of the fitted sparse GPs `gps`: basis
    /// vectors at its inducing inputs, its kernel and jitter, weights N(μ_u, Σ_u) (module docs),
    /// its prior mean if it has one, and the floor σ_r and process noise σ_p. An error names
    /// `output` if out of range, or `sigma_r`, `sigma_p`.
    pub fn from_sparse(
        gps: &SparseMultiGp,
        output: usize,
        sigma_r: f64,
        sigma_p: f64,
    ) -> Result<Self> {
        let q = gps.n_outputs();
        let Some(gp) = gps.gps().get(output) else {
            return Err(Error::invalid(
                "output",
                format!("the sparse GP has {q} output(s), got output {output}"),
            ));
        };
        let jitter = Jitter::Fixed(gp.jitter());
        let mut basis =
            RgpBasis::from_points(gp.inducing(), gp.kernel().clone(), jitter, sigma_r, sigma_p)?;
        if let Some(m) = gps.mean() {
            let w = gps.dim() + 1;
            basis = basis.with_prior_mean(&m.coefficients()[output * w..(output + 1) * w])?;
        }
        let (mean, cov) = gp.inducing_posterior();
        let mut rgp = Rgp::new(basis);
        rgp.mean = mean;
        rgp.cov = cov;
        Ok(rgp)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sparse::{SparseMethod, SparseWorkspace};

    /// Deterministic pseudo-random numbers in [lo, hi) (the crate's test LCG).
    fn uniform(n: usize, lo: f64, hi: f64, seed: u64) -> Vec<f64> {
        crate::linalg::test_data(n, seed)
            .into_iter()
            .map(|v| lo + (hi - lo) * (v + 0.5))
            .collect()
    }

    /// A sparse GP on N noisy samples of Σ sin(1.3 ζ_l) in n_d dimensions, m inducing points
    /// (the last a copy of the first with `m` negative: then K(Z, Z) needs jitter).
    fn sparse(nd: usize, m: isize, method: SparseMethod, mean: Option<Vec<f64>>) -> SparseMultiGp {
        let n = 300;
        let x = uniform(n * nd, -2.0, 2.0, 1);
        let noise = uniform(n, -0.05, 0.05, 2);
        let y: Vec<f64> = x
            .chunks_exact(nd)
            .zip(&noise)
            .map(|(p, e)| p.iter().map(|v| (1.3 * v).sin()).sum::<f64>() + e)
            .collect();
        let mut z = uniform(m.unsigned_abs() * nd, -2.2, 2.2, 3);
        if m < 0 {
            z.extend_from_within(..nd);
        }
        let mut theta = vec![1.4f64.ln()];
        theta.extend((0..nd).map(|l| (0.6 + 0.3 * l as f64).ln()));
        theta.push(0.05f64.ln());
        let gp = SparseMultiGp::new(&x, &y, &[&z], &theta, method).unwrap();
        match mean {
            None => gp,
            Some(c) => gp
                .with_mean(crate::mean::AffineMean::new(1, nd, c).unwrap())
                .unwrap(),
        }
    }

    /// Largest |a − b| / scale.
    fn max_rel(a: &[f64], b: &[f64], scale: f64) -> f64 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs() / scale)
            .fold(0.0, f64::max)
    }

    #[test]
    fn from_sparse_predicts_as_the_sparse_gp() {
        for method in [SparseMethod::Vfe, SparseMethod::Fitc] {
            for (nd, m) in [(1, 12), (2, 30), (1, -8)] {
                for mean in [None, Some((0..=nd).map(|i| 0.5 - 0.3 * i as f64).collect())] {
                    let sp = sparse(nd, m, method, mean);
                    let mut rgp = Rgp::from_sparse(&sp, 0, 0.0, 0.0).unwrap();
                    assert_eq!(rgp.basis().jitter(), sp.gps()[0].jitter());
                    assert_eq!(rgp.basis().jitter() > 0.0, m < 0);
                    let d = uniform(200 * nd, -3.0, 3.0, 7);
                    let (mut mean_s, mut var_s) = (vec![0.0; 200], vec![0.0; 200]);
                    let mut ws = SparseWorkspace::default();
                    sp.predict_into(&d, &mut mean_s, &mut var_s, &mut ws)
                        .unwrap();
                    let (mean_r, var_r) = rgp.predict(&d).unwrap();
                    let mscale = mean_s.iter().fold(0.0f64, |a, b| a.max(b.abs()));
                    let s2 = sp.gps()[0].kernel().variance();
                    let (em, ev) = (
                        max_rel(&mean_r, &mean_s, mscale),
                        max_rel(&var_r, &var_s, s2),
                    );
                    assert!(em < 1e-9 && ev < 1e-9, "{method:?} {nd}: {em:e} {ev:e}");
                }
            }
        }
    }

    #[test]
    fn j_of_a_points_basis_solves_the_kernel_system() {
        let kernel = SeArd::new(1.7, &[0.8, 1.9]).unwrap();
        let pts = uniform(2 * 15, -1.0, 1.0, 11);
        let mut b = RgpBasis::from_points(&pts, kernel.clone(), Jitter::Search, 0.0, 0.0).unwrap();
        assert!(!b.is_grid() && b.n_points().is_empty());
        assert_eq!(b.basis_vectors(), pts);
        let mut j = vec![0.0; 15];
        let zeta = [0.3, -0.45];
        let jkj = b.infer(&zeta, &mut j);
        let k = b.kernel_matrix().to_owned();
        for c in 0..15 {
            let lhs: f64 = (0..15).map(|i| j[i] * k[(i, c)]).sum();
            let rhs = kernel.eval(&zeta, &pts[2 * c..2 * c + 2]);
            assert!((lhs - rhs).abs() < 1e-9, "{lhs} vs {rhs}");
        }
        let kx: Vec<f64> = pts.chunks_exact(2).map(|p| kernel.eval(&zeta, p)).collect();
        let jk: f64 = j.iter().zip(&kx).map(|(a, b)| a * b).sum();
        assert!((jkj - jk).abs() < 1e-9 * kernel.variance());
    }

    #[test]
    fn fitc_learning_continues_as_fitc_on_all_the_data() {
        // FITC's posterior of u is the exact posterior under y_i ~ N(J_i u, σ_f² − J_i Kuu J_iᵀ +
        // σ_ε²), which the recursive update applies one measurement at a time.
        let (n, m) = (120, 10);
        let x = uniform(n, -2.0, 2.0, 21);
        let y: Vec<f64> = x.iter().map(|v| v.sin()).collect();
        let z = uniform(m, -2.0, 2.0, 22);
        let theta = [1.2f64.ln(), 0.7f64.ln(), 0.1f64.ln()];
        let all = SparseMultiGp::new(&x, &y, &[&z], &theta, SparseMethod::Fitc).unwrap();
        let half = SparseMultiGp::new(&x[..60], &y[..60], &[&z], &theta, SparseMethod::Fitc);
        let mut rgp = Rgp::from_sparse(&half.unwrap(), 0, 0.0, 0.0).unwrap();
        rgp.update_many(&x[60..], &y[60..], &[0.01]).unwrap();
        let want = Rgp::from_sparse(&all, 0, 0.0, 0.0).unwrap();
        let scale = want.mean().iter().fold(0.0f64, |a, b| a.max(b.abs()));
        assert!(max_rel(rgp.mean(), want.mean(), scale) < 1e-8);
        let (c, cw) = (rgp.cov_raw(), want.cov_raw());
        assert!(max_rel(&c, &cw, 1.44) < 1e-8);
    }

    #[test]
    fn prior_mean_shifts_predictions_and_updates() {
        let sp = sparse(1, 8, SparseMethod::Vfe, None);
        let coef = [0.7, -0.4];
        let mut plain = Rgp::from_sparse(&sp, 0, 0.1, 0.0).unwrap();
        let mut shifted = plain.clone();
        shifted.basis = shifted.basis.with_prior_mean(&coef).unwrap();
        let d = [-1.0, 0.2, 2.5];
        let (m0, v0) = plain.predict(&d).unwrap();
        let (m1, v1) = shifted.predict(&d).unwrap();
        for i in 0..3 {
            assert!((m1[i] - m0[i] - (0.7 - 0.4 * d[i])).abs() < 1e-12);
        }
        assert_eq!(v0, v1);
        // a measurement y of z = m + g teaches g the residual y − m(ζ)
        let p1 = shifted.update(&[0.2], 1.5, 0.01).unwrap();
        let p0 = plain.update(&[0.2], 1.5 - (0.7 - 0.4 * 0.2), 0.01).unwrap();
        assert!((p1 - p0 - (0.7 - 0.4 * 0.2)).abs() < 1e-12);
        assert!(max_rel(shifted.mean(), plain.mean(), 1.0) < 1e-12);
        // the filter's μ_z^p includes it, in both modes
        for augmented in [false, true] {
            let mut ekfs = [&plain, &shifted].map(|g| {
                super::super::RgpEkf::new(&[0.0], &[1.0], vec![g.clone()], augmented).unwrap()
            });
            let z = ekfs.each_mut().map(|e| e.infer(&[-0.6]).unwrap()[0]);
            assert!(
                (z[1] - z[0] - (0.7 + 0.4 * 0.6)).abs() < 1e-12,
                "{augmented}"
            );
        }
        // a prior mean that overflows at an input is an error naming zeta; nothing changes
        let big = plain.basis.clone().with_prior_mean(&[0.0, 1e300]).unwrap();
        let mut gp = Rgp::new(big);
        let before = gp.mean().to_vec();
        for r in [
            gp.update(&[1e10], 1.0, 0.1).map(|_| ()),
            gp.predict(&[1e10]).map(|_| ()),
        ] {
            assert!(matches!(r, Err(Error::InvalidInput { ref arg, .. }) if arg == "zeta"));
        }
        assert_eq!(gp.mean(), &before[..]);
    }

    #[test]
    fn bad_points_bases_are_rejected_naming_the_argument() {
        let k = SeArd::new(1.0, &[0.5]).unwrap();
        let arg = |r: Result<RgpBasis>| match r {
            Err(Error::InvalidInput { arg, .. }) => arg,
            Err(e) => format!("{e}"),
            Ok(_) => "ok".into(),
        };
        let ok = [0.0, 1.0, 2.0];
        assert_eq!(
            arg(RgpBasis::from_points(
                &[],
                k.clone(),
                Jitter::Search,
                0.0,
                0.0
            )),
            "points"
        );
        assert_eq!(
            arg(RgpBasis::from_points(
                &[0.0, f64::NAN],
                k.clone(),
                Jitter::Search,
                0.0,
                0.0
            )),
            "points"
        );
        let k2 = SeArd::new(1.0, &[0.5, 0.5]).unwrap();
        assert_eq!(
            arg(RgpBasis::from_points(&ok, k2, Jitter::Search, 0.0, 0.0)),
            "points"
        );
        let huge = SeArd::new(1e200, &[0.5]).unwrap();
        assert_eq!(
            arg(RgpBasis::from_points(&ok, huge, Jitter::Search, 0.0, 0.0)),
            "sigma_K"
        );
        assert_eq!(
            arg(RgpBasis::from_points(
                &ok,
                k.clone(),
                Jitter::Fixed(-1.0),
                0.0,
                0.0
            )),
            "jitter"
        );
        assert_eq!(
            arg(RgpBasis::from_points(
                &ok,
                k.clone(),
                Jitter::Search,
                -1.0,
                0.0
            )),
            "sigma_r"
        );
        assert_eq!(
            arg(RgpBasis::from_points(
                &ok,
                k.clone(),
                Jitter::Search,
                0.0,
                f64::INFINITY
            )),
            "sigma_p"
        );
        let b = RgpBasis::from_points(&ok, k.clone(), Jitter::Search, 0.0, 0.0).unwrap();
        assert_eq!(arg(b.clone().with_prior_mean(&[1.0])), "prior_mean");
        assert_eq!(arg(b.with_prior_mean(&[1.0, f64::NAN])), "prior_mean");
        // duplicated points: the search adds jitter, a fixed jitter of 0 cannot factor K
        let dup = [0.0, 1.0, 1.0];
        let b = RgpBasis::from_points(&dup, k.clone(), Jitter::Search, 0.0, 0.0).unwrap();
        assert!(b.jitter() > 0.0);
        let r = RgpBasis::from_points(&dup, k, Jitter::Fixed(0.0), 0.0, 0.0);
        assert!(matches!(r, Err(Error::Numerical(_))));
        let sp = sparse(1, 5, SparseMethod::Vfe, None);
        assert!(matches!(Rgp::from_sparse(&sp, 1, 0.0, 0.0),
            Err(Error::InvalidInput { ref arg, .. }) if arg == "output"));
    }
}
