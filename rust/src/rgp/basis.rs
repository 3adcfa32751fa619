//! [`RgpBasis`]: the fixed part of one recursive GP (basis vectors on a unit grid, or at given
//! points with `points.rs`; the kernel, the Cholesky factor of K = k(X, X), the optional prior
//! mean), the inference row J_k = k(X_k, X) K⁻¹ (two triangular solves, or one for whitened
//! weights) and the changes to and from whitened coordinates.

use faer::linalg::solvers::Llt;
use faer::{Mat, MatRef, Par, Side};

use super::dense::quad_form;
use super::{check_nonneg, check_positive, MAX_REL_JITTER, TINY_REL};
use crate::error::{check_finite, check_len, Error, Result};
use crate::kernel::SeArd;
use crate::linalg::{self, axpy, dot_lanes8, ReciprocalWithFloor};

/// How the Cholesky factor of K gets its diagonal jitter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Jitter {
    /// None if K factors, else from 1e-12·σ_K² growing tenfold up to 1e-6·σ_K² (the grid's).
    Search,
    /// Exactly this jitter (a sparse GP's own, say); a `Numerical` error if K + jitter·I does
    /// not factor.
    Fixed(f64),
}

/// The fixed part of one recursive GP: basis vectors, kernel, Cholesky factor of K, σ_r, σ_p and
/// the optional prior mean.
#[derive(Debug, Clone)]
pub struct RgpBasis {
    /// The normalisation x = (ζ − lower) · scale (lower 0 and scale 1 for a points basis).
    pub(super) lower: Vec<f64>,
    /// (N_i − 1) / (upper_i − lower_i), eq. (6).
    pub(super) scale: Vec<f64>,
    /// Basis vectors per axis of a grid; empty for a basis at given points.
    pub(super) n_points: Vec<usize>,
    /// Normalised basis vectors, row-major (n_b × n_X).
    pub(super) basis: Vec<f64>,
    pub(super) kernel: SeArd,
    pub(super) k: Mat<f64>,
    /// Lower Cholesky factor of K + jitter·I.
    pub(super) chol: Mat<f64>,
    /// 1 / diag(L), for the substitutions.
    pub(super) inv_diag: Vec<f64>,
    pub(super) jitter: f64,
    pub(super) sigma_r2: f64,
    pub(super) sigma_p2: f64,
    /// The prior mean m(ζ) = b + wᵀζ as [b, w_1, …, w_nX] (ζ units), if any (`points.rs`).
    pub(super) prior_mean: Option<Vec<f64>>,
    /// Scratch: the normalised test input.
    pub(super) xk: Vec<f64>,
}

impl RgpBasis {
    /// A grid of `n_points[i]` basis vectors per axis between `lower[i]` and `upper[i]` (in ζ
    /// units), kernel σ_K² exp(−‖x − x'‖²/(2L)) on the normalised grid, floor σ_r, process noise σ_p.
    pub fn new(
        lower: &[f64],
        upper: &[f64],
        n_points: &[usize],
        sigma_k: f64,
        l: f64,
        sigma_r: f64,
        sigma_p: f64,
    ) -> Result<Self> {
        let nx = lower.len();
        let nb = check_grid(lower, upper, n_points)?;
        check_sigma_k(sigma_k)?;
        check_positive("L", l)?;
        let kernel = SeArd::new(sigma_k, &vec![l.sqrt(); nx])?;
        let scale = (0..nx)
            .map(|i| (n_points[i] - 1) as f64 / (upper[i] - lower[i]))
            .collect();
        let layout = (lower.to_vec(), scale, n_points.to_vec());
        Self::assemble(
            layout,
            unit_grid(n_points, nb),
            kernel,
            Jitter::Search,
            sigma_r,
            sigma_p,
        )
    }

    /// The basis with normalisation (lower, scale, n_points) and normalised basis vectors
    /// `basis`: checks σ_r, σ_p and the jitter, and factors K under the jitter policy.
    pub(super) fn assemble(
        (lower, scale, n_points): (Vec<f64>, Vec<f64>, Vec<usize>),
        basis: Vec<f64>,
        kernel: SeArd,
        jitter: Jitter,
        sigma_r: f64,
        sigma_p: f64,
    ) -> Result<Self> {
        check_nonneg("sigma_r", sigma_r)?;
        check_nonneg("sigma_p", sigma_p)?;
        if let Jitter::Fixed(j) = jitter {
            check_nonneg("jitter", j)?;
        }
        let nb = basis.len() / kernel.dim();
        let mut k = kernel.gram(&basis);
        let s2 = kernel.variance();
        zero_below(&mut k, TINY_REL * s2);
        let (chol, jitter) = match jitter {
            Jitter::Search => factor_with_jitter(&k, s2)?,
            Jitter::Fixed(j) => (factor_fixed(&k, s2, j)?, j),
        };
        Ok(Self {
            xk: vec![0.0; lower.len()],
            lower,
            scale,
            n_points,
            basis,
            kernel,
            k,
            inv_diag: (0..nb).map(|i| 1.0 / chol[(i, i)]).collect(),
            chol,
            jitter,
            sigma_r2: sigma_r * sigma_r,
            sigma_p2: sigma_p * sigma_p,
            prior_mean: None,
        })
    }

    /// Input dimension n_X.
    pub fn dim(&self) -> usize {
        self.lower.len()
    }

    /// Checks that `zetas` holds finite row-major inputs of dimension n_X at which the prior
    /// mean (if any) is finite (an error naming `zeta` otherwise) and returns how many.
    pub fn count_inputs(&self, zetas: &[f64]) -> Result<usize> {
        let m = self.kernel.count_points("zeta", zetas)?;
        self.check_prior_mean("zeta", zetas)?;
        Ok(m)
    }

    /// Number of basis vectors n_b.
    pub fn n_basis(&self) -> usize {
        self.basis.len() / self.dim()
    }

    /// Basis vectors per axis of a grid (empty for a basis at given points).
    pub fn n_points(&self) -> &[usize] {
        &self.n_points
    }

    /// Whether the basis vectors form a grid ([`RgpBasis::new`]).
    pub fn is_grid(&self) -> bool {
        !self.n_points.is_empty()
    }

    /// The kernel on the normalised inputs (ζ units for a basis at given points).
    pub fn kernel(&self) -> &SeArd {
        &self.kernel
    }

    /// The kernel's length-scales in ζ units (a grid's √L / scale_i).
    pub fn lengthscales_zeta(&self) -> Vec<f64> {
        if !self.is_grid() {
            return self.kernel.lengthscales().to_vec();
        }
        let ls = self.kernel.lengthscales();
        ls.iter().zip(&self.scale).map(|(l, s)| l / s).collect()
    }

    /// σ_K².
    pub fn sigma_k2(&self) -> f64 {
        self.kernel.variance()
    }

    pub fn sigma_r2(&self) -> f64 {
        self.sigma_r2
    }

    pub fn sigma_p2(&self) -> f64 {
        self.sigma_p2
    }

    /// The jitter added to K's diagonal for its Cholesky factor (0 unless K was near singular).
    pub fn jitter(&self) -> f64 {
        self.jitter
    }

    /// The kernel matrix K = k(X, X) (without jitter).
    pub fn kernel_matrix(&self) -> MatRef<'_, f64> {
        self.k.as_ref()
    }

    /// Basis vectors in ζ units, row-major (n_b × n_X).
    pub fn basis_vectors(&self) -> Vec<f64> {
        let nx = self.dim();
        self.basis
            .iter()
            .enumerate()
            .map(|(i, v)| self.lower[i % nx] + v / self.scale[i % nx])
            .collect()
    }

    /// Writes J_k = k(X_k, X) K⁻¹ into `j` (length n_b) for the input `zeta` (ζ units, length n_X,
    /// already validated) and returns J_k K J_kᵀ = ‖L⁻¹ k(X, X_k)‖².
    #[inline(always)]
    pub fn infer(&mut self, zeta: &[f64], j: &mut [f64]) -> f64 {
        let jkj = self.infer_whitened(zeta, j);
        back_substitution(&self.chol, &self.inv_diag, TINY_REL, j);
        jkj
    }

    /// The whitened inference row v = L⁻¹ k(X, X_k) (J_k = vᵀ L⁻¹, so J_k w = v · L⁻¹w for weights
    /// w, and J_k C Jᵀ = vᵀ L⁻¹ C L⁻ᵀ v) into `v` (length n_b); returns J_k K J_kᵀ = ‖v‖². One
    /// triangular solve instead of two.
    #[inline(always)]
    pub fn infer_whitened(&mut self, zeta: &[f64], j: &mut [f64]) -> f64 {
        let nx = self.dim();
        for (((x, z), lo), sc) in self
            .xk
            .iter_mut()
            .zip(zeta)
            .zip(&self.lower)
            .zip(&self.scale)
        {
            *x = (z - lo) * sc;
        }
        // k(x, X); values below e^-322 σ_K² ≈ 1e-140 σ_K² are set to 0 without calling exp (see
        // TINY_REL)
        let s2 = self.kernel.variance();
        for (b, jb) in j.iter_mut().enumerate() {
            let r2 = self
                .kernel
                .scaled_sq_dist(&self.xk, &self.basis[b * nx..(b + 1) * nx]);
            *jb = if r2 > 644.0 {
                0.0
            } else {
                s2 * (-0.5 * r2).exp()
            };
        }
        forward_substitution(&self.chol, &self.inv_diag, TINY_REL * s2.sqrt(), j);
        dot_lanes8(j, j)
    }

    /// L⁻¹ m in place (weights to whitened coordinates).
    pub(super) fn whiten(&self, m: &mut [f64]) {
        forward_substitution(&self.chol, &self.inv_diag, 0.0, m);
    }

    /// L u (whitened coordinates to weights).
    pub(super) fn unwhiten(&self, u: &[f64]) -> Vec<f64> {
        let mut out = vec![0.0; u.len()];
        for (jj, uj) in u.iter().enumerate() {
            axpy(&mut out[jj..], *uj, &self.chol.col_as_slice(jj)[jj..]);
        }
        out
    }

    /// L⁻¹ C L⁻ᵀ for a symmetric C (weights' covariance to whitened coordinates), symmetric.
    pub(super) fn whiten_cov(&self, c: MatRef<'_, f64>) -> Mat<f64> {
        use faer::linalg::triangular_solve::solve_lower_triangular_in_place;
        let mut m = c.to_owned();
        solve_lower_triangular_in_place(self.chol.as_ref(), m.as_mut(), Par::Seq);
        let mut m = m.transpose().to_owned();
        solve_lower_triangular_in_place(self.chol.as_ref(), m.as_mut(), Par::Seq);
        let n = m.nrows();
        Mat::from_fn(n, n, |i, jj| 0.5 * (m[(i, jj)] + m[(jj, i)]))
    }

    /// Checks one input ζ (finite, of dimension n_X, the prior mean finite there).
    pub fn check_zeta(&self, arg: &str, zeta: &[f64]) -> Result<()> {
        check_len(arg, zeta, self.dim())?;
        check_finite(arg, zeta)?;
        self.check_prior_mean(arg, zeta)
    }

    /// Mean (prior mean included) and variance (σ_r² floor included) of the GP with weights
    /// (`mean`, `cov`) at the row-major inputs `zetas` (checked with [`Self::check_inputs`]); `j` is scratch of length n_b. With `whitened`, `mean` and `cov`
    /// are in whitened coordinates (L⁻¹ w, L⁻¹ C L⁻ᵀ).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn predict_with(
        &mut self,
        mean: &[f64],
        cov: MatRef<'_, f64>,
        whitened: bool,
        zetas: &[f64],
        j: &mut [f64],
        mean_out: &mut [f64],
        var_out: &mut [f64],
    ) {
        let nx = self.dim();
        let s2 = self.sigma_k2();
        for (q, z) in zetas.chunks_exact(nx).enumerate() {
            let jkj = if whitened {
                self.infer_whitened(z, j)
            } else {
                self.infer(z, j)
            };
            mean_out[q] = dot_lanes8(j, mean) + self.prior_mean_at(z);
            let jcj = quad_form(cov, j);
            var_out[q] = (s2 - jkj).max(0.0) + jcj.max(0.0) + self.sigma_r2;
        }
    }
}

/// σ_K > 0 whose square is a normal float: σ_K² scales K and the jitter (1e200² overflows to inf,
/// 1e-200² underflows to 0, and neither K nor its jitter would make sense).
pub(super) fn check_sigma_k(sigma_k: f64) -> Result<()> {
    check_positive("sigma_K", sigma_k)?;
    if !(sigma_k * sigma_k).is_normal() {
        return Err(Error::invalid(
            "sigma_K",
            format!("sigma_K² must be a finite, normal float, got sigma_K = {sigma_k:e}"),
        ));
    }
    Ok(())
}

/// Checks the grid's arguments, naming the bad one, and returns the number of basis vectors.
fn check_grid(lower: &[f64], upper: &[f64], n_points: &[usize]) -> Result<usize> {
    let nx = lower.len();
    if nx == 0 {
        return Err(Error::invalid(
            "lower",
            "needs at least one input dimension",
        ));
    }
    check_finite("lower", lower)?;
    check_finite("upper", upper)?;
    check_len("upper", upper, nx)?;
    if n_points.len() != nx {
        return Err(Error::invalid(
            "n_points",
            format!("expected {nx} values, got {}", n_points.len()),
        ));
    }
    if let Some(i) = (0..nx).find(|&i| upper[i] <= lower[i]) {
        return Err(Error::invalid(
            "upper",
            format!("must exceed lower on every axis (axis {i})"),
        ));
    }
    if let Some(n) = n_points.iter().find(|&&n| n < 2) {
        return Err(Error::invalid(
            "n_points",
            format!("need at least 2 points per axis, got {n}"),
        ));
    }
    let nb: usize = n_points.iter().product();
    if nb > 20_000 {
        return Err(Error::invalid(
            "n_points",
            format!("{nb} basis vectors is too many for a dense recursive GP"),
        ));
    }
    Ok(nb)
}

/// The grid of eq. (5) in grid units (n_b × n_X row-major): the first axis varies fastest.
fn unit_grid(n_points: &[usize], nb: usize) -> Vec<f64> {
    let nx = n_points.len();
    let mut basis = vec![0.0; nb * nx];
    for b in 0..nb {
        let mut rest = b;
        for i in 0..nx {
            basis[b * nx + i] = (rest % n_points[i]) as f64;
            rest /= n_points[i];
        }
    }
    basis
}

/// The lower Cholesky factor of K + jitter·I, entries below TINY_REL·σ_K set to 0, with the
/// jitter: none if K factors, else from 1e-12·σ_K² growing tenfold up to MAX_REL_JITTER·σ_K².
fn factor_with_jitter(k: &Mat<f64>, s2: f64) -> Result<(Mat<f64>, f64)> {
    let nb = k.nrows();
    let mut jitter = 0.0;
    let too_large = || {
        Error::numerical(format!(
            "the kernel matrix K of {nb} basis vectors is not positive definite even with \
             jitter {:.1e}·σ_K²; use a shorter length-scale (smaller L) or fewer basis vectors",
            MAX_REL_JITTER
        ))
    };
    // 0, then 1e-12·s2 growing tenfold past MAX_REL_JITTER·s2: 8 factorisations for a normal
    // s2; the cap also bounds the loop should s2 not be (the jitter would then never grow).
    for _ in 0..JITTER_TRIES {
        crate::interrupt::check()?;
        let mut kj = k.clone();
        for i in 0..nb {
            kj[(i, i)] += jitter;
        }
        if let Ok(llt) = Llt::new(kj.as_ref(), Side::Lower) {
            let mut l = llt.L().to_owned();
            zero_below(&mut l, TINY_REL * s2.sqrt());
            return Ok((l, jitter));
        }
        jitter = if jitter == 0.0 {
            1e-12 * s2
        } else {
            jitter * 10.0
        };
        if jitter > MAX_REL_JITTER * s2 {
            return Err(too_large());
        }
    }
    Err(too_large())
}

/// The lower Cholesky factor of K + jitter·I (entries below TINY_REL·σ_K set to 0), a `Numerical`
/// error if that is not positive definite.
fn factor_fixed(k: &Mat<f64>, s2: f64, jitter: f64) -> Result<Mat<f64>> {
    let mut kj = k.clone();
    for i in 0..kj.nrows() {
        kj[(i, i)] += jitter;
    }
    let llt = Llt::new(kj.as_ref(), Side::Lower).map_err(|_| {
        Error::numerical(format!(
            "the kernel matrix K of {} basis vectors plus the jitter {jitter:.3e} is not \
             positive definite (duplicated basis vectors?)",
            kj.nrows()
        ))
    })?;
    let mut l = llt.L().to_owned();
    zero_below(&mut l, TINY_REL * s2.sqrt());
    Ok(l)
}

/// Sets the entries of `m` below `tiny` in magnitude to 0 (K and its factor: see TINY_REL).
fn zero_below(m: &mut Mat<f64>, tiny: f64) {
    for c in 0..m.ncols() {
        for v in m.col_as_slice_mut(c) {
            if v.abs() < tiny {
                *v = 0.0;
            }
        }
    }
}

/// The most factorisations [`factor_with_jitter`] tries (it needs 8 with MAX_REL_JITTER = 1e-6).
const JITTER_TRIES: usize = 16;

// The per-step triangular solves with K's Cholesky factor for one right-hand side of length
// n_b ≤ a few hundred: `linalg::triangular` with this module's rounding ([`ReciprocalWithFloor`]:
// the diagonal applied as a multiplication by its precomputed reciprocal, tiny results set to 0,
// the backward sweep in dot form reading L's columns again).

/// Solves L v = b in place (L lower triangular, column-major; `inv_diag` = 1 / diag(L)); entries
/// of v below `tiny` in magnitude are set to 0 (see TINY_REL).
#[inline(always)]
fn forward_substitution(l: &Mat<f64>, inv_diag: &[f64], tiny: f64, v: &mut [f64]) {
    let rounding = ReciprocalWithFloor { inv_diag, tiny };
    linalg::forward_substitution(|j| l.col_as_slice(j), &rounding, v)
}

/// Solves Lᵀ v = b in place with the same lower factor L (column-major; `inv_diag` =
/// 1 / diag(L)); entries of v below `tiny` in magnitude are set to 0.
#[inline(always)]
fn back_substitution(l: &Mat<f64>, inv_diag: &[f64], tiny: f64, v: &mut [f64]) {
    let rounding = ReciprocalWithFloor { inv_diag, tiny };
    linalg::back_substitution(|j| l.col_as_slice(j), &rounding, v)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rgp::test_basis as basis;
    use faer::MatMut;

    #[test]
    fn sigma_k_whose_square_is_not_a_normal_float_is_rejected() {
        for s in [1e200, 1e-200, f64::MAX] {
            let e = RgpBasis::new(&[0.0], &[1.0], &[5], s, 0.5, 0.0, 0.0).unwrap_err();
            assert!(
                matches!(e, Error::InvalidInput { ref arg, .. } if arg == "sigma_K"),
                "{s}"
            );
        }
        assert!(RgpBasis::new(&[0.0], &[1.0], &[5], 1e150, 0.5, 0.0, 0.0).is_ok());
    }

    #[test]
    fn jitter_search_is_bounded_for_any_scale() {
        let k = Mat::<f64>::from_fn(2, 2, |_, _| -1.0);
        for s2 in [0.0, f64::INFINITY, f64::NAN, 1.0] {
            assert!(factor_with_jitter(&k, s2).is_err(), "{s2}");
        }
    }

    #[test]
    fn substitutions_match_faer_triangular_solves() {
        use faer::linalg::triangular_solve::{
            solve_lower_triangular_in_place, solve_upper_triangular_in_place,
        };
        // sizes around and between the blocks of four columns
        for nb in [2, 3, 4, 5, 7, 8, 9, 37, 40, 43] {
            let b = RgpBasis::new(&[0.0], &[1.0], &[nb], 2.0, 0.5, 0.0, 0.0).unwrap();
            let rhs: Vec<f64> = (0..nb).map(|i| ((i * 7919) % 13) as f64 - 6.0).collect();
            let (mut ours, mut theirs) = (rhs.clone(), rhs.clone());
            forward_substitution(&b.chol, &b.inv_diag, 0.0, &mut ours);
            let mut col = MatMut::from_column_major_slice_mut(&mut theirs, nb, 1);
            solve_lower_triangular_in_place(b.chol.as_ref(), col.as_mut(), Par::Seq);
            for (o, t) in ours.iter().zip(&theirs) {
                assert!((o - t).abs() <= 1e-10 * (1.0 + t.abs()), "{nb}: {o} vs {t}");
            }
            let (mut ours, mut theirs) = (rhs.clone(), rhs);
            back_substitution(&b.chol, &b.inv_diag, 0.0, &mut ours);
            let mut col = MatMut::from_column_major_slice_mut(&mut theirs, nb, 1);
            solve_upper_triangular_in_place(b.chol.transpose(), col.as_mut(), Par::Seq);
            for (o, t) in ours.iter().zip(&theirs) {
                assert!((o - t).abs() <= 1e-8 * (1.0 + t.abs()), "{nb}: {o} vs {t}");
            }
        }
    }

    #[test]
    fn j_solves_the_kernel_system() {
        let mut b = basis(9);
        let mut j = vec![0.0; 9];
        b.infer(&[0.37], &mut j);
        // J K = k(x, X)
        let k = b.kernel_matrix().to_owned();
        let xk = [(0.37 + 2.0) * 8.0 / 4.0];
        for c in 0..9 {
            let lhs: f64 = (0..9).map(|i| j[i] * k[(i, c)]).sum();
            let rhs = b.kernel.eval(&xk, &[c as f64]);
            assert!((lhs - rhs).abs() < 1e-9, "{lhs} vs {rhs}");
        }
        // at a basis vector J is the unit vector
        b.infer(&[-2.0 + 3.0 * 0.5], &mut j);
        for (i, v) in j.iter().enumerate() {
            let want = if i == 3 { 1.0 } else { 0.0 };
            assert!((v - want).abs() < 1e-8);
        }
    }
}
