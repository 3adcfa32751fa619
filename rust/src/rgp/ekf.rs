//! [`RgpEkf`], the RGP-dKF: the EKF on the state augmented by the RGPs' weights (or, in
//! pure-prediction mode, on the state alone with the GPs as noisy inputs): inference (16), the
//! structured covariance prediction (12)–(13), (17)–(18) and the update 4a / 4b (19).

use faer::linalg::matmul::matmul;
use faer::{Accum, Mat, MatRef, Par};

use super::dense::{cholesky, quad_form, rank_p_downdate, symmetric_from_lower};
use super::{Rgp, RgpBasis};
use crate::error::{check_finite, check_len, check_magnitude, Error, Result};
use crate::linalg::{add4, axpy, dot4, dot_lanes8, symv_column};

/// The RGP-dKF: EKF on μ = [x; μ_z1; …; μ_zq] with one RGP per disturbance z_j, or, in
/// pure-prediction mode, an EKF on x with the (fixed) GPs as noisy inputs.
///
/// Whitened weights: in augmented mode the block of a GP without process noise (σ_p = 0, the
/// paper's setting) holds u = L⁻¹ μ_z (L the Cholesky factor of that GP's K), with covariance
/// blocks L⁻¹ C_zz L⁻ᵀ and C_xz L⁻ᵀ. The filter is linear in the weights, so this is an exact
/// change of coordinates, and J_k μ_z = v · u with v = L⁻¹ k(X, X_k): the step needs one
/// triangular solve instead of two, and (12)–(19) hold with J_k replaced by vᵀ. [`Self::mu`],
/// [`Self::cov`], [`Self::gp_weights`] map back to the weights (L u, L C_u Lᵀ); a fresh GP starts
/// from u = 0, C_u = L⁻¹ K L⁻ᵀ = I. With σ_p > 0 the block stays in the weights' coordinates:
/// σ_p² I would become the dense σ_p² K⁻¹ there.
///
/// Storage of the symmetric covariance C: the per-step kernels keep only its lower triangle and
/// the complete first n columns (the state block and C[z, x]) up to date, which halves the work of
/// the rank-p update and of J C_z; the entries above the diagonal right of column n are stale.
/// [`Self::cov`] and [`Self::gp_weights`] return symmetric copies.
#[derive(Debug, Clone)]
pub struct RgpEkf {
    n: usize,
    gps: Vec<Rgp>,
    /// Start of each GP's weight block in μ (augmented mode).
    offsets: Vec<usize>,
    /// Whether each GP's block is stored whitened (augmented and σ_p = 0; see the struct's doc).
    whitened: Vec<bool>,
    augmented: bool,
    nt: usize,
    mu: Vec<f64>,
    cov: Mat<f64>,
    /// J_k of every GP, concatenated (Σ n_b).
    j: Vec<f64>,
    j_offsets: Vec<usize>,
    /// Variance of the GP noise input per disturbance, the diagonal of the term in (12).
    dvar: Vec<f64>,
    /// μ_z^p per disturbance, of the last [`Self::infer`] (staged for [`Self::predict`]).
    mu_zp: Vec<f64>,
    /// μ_z^p of the last completed [`Self::predict`] (a failed step leaves it unchanged).
    z_pred: Vec<f64>,
    inferred: bool,
    /// Scratch: Ã's top rows times C (n × N, row-major); J C_z (q × N, row-major); T J
    /// (n × q, row-major); C H̃ᵀ, then W (N × p, column-major).
    t: Vec<f64>,
    jc: Vec<f64>,
    tj: Vec<f64>,
    pht: Vec<f64>,
    /// Scratch of the update: S (p × p), its Cholesky factor L_S (both row-major), L_S⁻¹ ν.
    s_buf: Vec<f64>,
    ls: Vec<f64>,
    w: Vec<f64>,
    /// Last innovation, its covariance and log-likelihood.
    innovation: Vec<f64>,
    s: Mat<f64>,
    log_likelihood: f64,
}

/// The state of an [`RgpEkf`] that carries from one step to the next (everything but the scratch
/// buffers), for exact copies and checkpoints: μ, C as stored (N × N row-major, with its stale
/// upper entries), each GP's weights as stored, the last J rows, noise variances and μ_z^p,
/// whether a prediction step has run since the last update, and the last innovation, its
/// covariance (p × p row-major) and log-likelihood.
#[derive(Debug, Clone, PartialEq)]
pub struct RgpEkfState {
    pub mu: Vec<f64>,
    pub cov: Vec<f64>,
    pub gp_means: Vec<Vec<f64>>,
    pub gp_covs: Vec<Vec<f64>>,
    pub j: Vec<f64>,
    pub dvar: Vec<f64>,
    pub mu_zp: Vec<f64>,
    /// z of the last completed prediction (what `z_pred` reports).
    pub z_pred: Vec<f64>,
    pub inferred: bool,
    pub innovation: Vec<f64>,
    pub s: Vec<f64>,
    pub log_likelihood: f64,
}

fn mat_raw(m: &Mat<f64>) -> Vec<f64> {
    let c = m.ncols();
    (0..m.nrows() * c).map(|k| m[(k / c, k % c)]).collect()
}

impl RgpEkf {
    /// The recursive GPs (their weights are only current in the pure-prediction mode).
    pub fn gps(&self) -> &[Rgp] {
        &self.gps
    }

    /// A copy of the state (see [`RgpEkfState`]).
    pub fn state(&self) -> RgpEkfState {
        RgpEkfState {
            mu: self.mu.clone(),
            cov: mat_raw(&self.cov),
            gp_means: self.gps.iter().map(|g| g.mean().to_vec()).collect(),
            gp_covs: self.gps.iter().map(|g| g.cov_raw()).collect(),
            j: self.j.clone(),
            dvar: self.dvar.clone(),
            mu_zp: self.mu_zp.clone(),
            z_pred: self.z_pred.clone(),
            inferred: self.inferred,
            innovation: self.innovation.clone(),
            s: mat_raw(&self.s),
            log_likelihood: self.log_likelihood,
        }
    }

    /// Replaces the state by `st` (from [`RgpEkf::state`] of an estimator with the same
    /// dimensions and GPs). Every length is checked against this estimator's, every value must be
    /// finite; an error names the entry and changes nothing.
    pub fn set_state(&mut self, st: RgpEkfState) -> Result<()> {
        let (nt, q) = (self.nt, self.gps.len());
        check_len("mu", &st.mu, nt)?;
        check_len("cov", &st.cov, nt * nt)?;
        if st.gp_means.len() != q || st.gp_covs.len() != q {
            return Err(Error::invalid(
                "gp_weights",
                format!("expected the weights of {q} GPs"),
            ));
        }
        check_len("j", &st.j, self.j.len())?;
        check_len("dvar", &st.dvar, q)?;
        check_len("mu_zp", &st.mu_zp, q)?;
        check_len("z_pred", &st.z_pred, q)?;
        let p = st.innovation.len();
        check_len("S", &st.s, p * p)?;
        for (name, v) in [
            ("mu", &st.mu),
            ("cov", &st.cov),
            ("j", &st.j),
            ("dvar", &st.dvar),
            ("mu_zp", &st.mu_zp),
            ("z_pred", &st.z_pred),
            ("innovation", &st.innovation),
            ("S", &st.s),
        ] {
            check_finite(name, v)?;
        }
        if st.log_likelihood.is_nan() {
            return Err(Error::invalid("log_likelihood", "must not be NaN"));
        }
        let mut gps = self.gps.clone();
        for (i, (g, (m, c))) in gps
            .iter_mut()
            .zip(st.gp_means.iter().zip(&st.gp_covs))
            .enumerate()
        {
            let nb = g.basis.n_basis();
            check_len(&format!("gp_mean_{i}"), m, nb)?;
            check_len(&format!("gp_cov_{i}"), c, nb * nb)?;
            check_finite(&format!("gp_mean_{i}"), m)?;
            check_finite(&format!("gp_cov_{i}"), c)?;
            g.set_weights_raw(m, c)?;
        }
        self.gps = gps;
        self.mu = st.mu;
        self.cov = Mat::from_fn(nt, nt, |r, c| st.cov[r * nt + c]);
        self.j = st.j;
        self.dvar = st.dvar;
        self.mu_zp = st.mu_zp;
        self.z_pred = st.z_pred;
        self.inferred = st.inferred;
        self.innovation = st.innovation;
        self.s = Mat::from_fn(p, p, |r, c| st.s[r * p + c]);
        self.log_likelihood = st.log_likelihood;
        Ok(())
    }
}

impl RgpEkf {
    /// `x0` (n), `p0` (n × n row-major), the GPs (their current weights initialise the GP block,
    /// C_z = K for a fresh RGP), `augmented` = false for the pure-prediction mode of §3.2.
    pub fn new(x0: &[f64], p0: &[f64], gps: Vec<Rgp>, augmented: bool) -> Result<Self> {
        let n = x0.len();
        if n == 0 {
            return Err(Error::invalid("x0", "needs at least one state"));
        }
        if gps.is_empty() {
            return Err(Error::invalid("gps", "needs at least one recursive GP"));
        }
        check_finite("x0", x0)?;
        check_len("P0", p0, n * n)?;
        check_finite("P0", p0)?;
        let q = gps.len();
        let mut offsets = Vec::with_capacity(q);
        let mut j_offsets = Vec::with_capacity(q);
        let (mut off, mut joff) = (n, 0);
        for g in &gps {
            offsets.push(off);
            j_offsets.push(joff);
            joff += g.basis.n_basis();
            if augmented {
                off += g.basis.n_basis();
            }
        }
        let nt = off;
        let mut mu = vec![0.0; nt];
        mu[..n].copy_from_slice(x0);
        let mut cov = Mat::zeros(nt, nt);
        for i in 0..n {
            for jj in 0..n {
                cov[(i, jj)] = 0.5 * (p0[i * n + jj] + p0[jj * n + i]);
            }
        }
        let whitened: Vec<bool> = gps
            .iter()
            .map(|g| augmented && g.basis.sigma_p2 == 0.0)
            .collect();
        if augmented {
            for ((g, &o), &w) in gps.iter().zip(&offsets).zip(&whitened) {
                let nb = g.basis.n_basis();
                let mut u = g.mean.clone();
                let mut block = cov.as_mut().submatrix_mut(o, o, nb, nb);
                if w {
                    g.basis.whiten(&mut u);
                    block.copy_from(g.basis.whiten_cov(g.cov.as_ref()));
                } else {
                    block.copy_from(g.cov.as_ref());
                }
                mu[o..o + nb].copy_from_slice(&u);
            }
        }
        Ok(Self {
            n,
            offsets,
            whitened,
            augmented,
            nt,
            mu,
            cov,
            j: vec![0.0; joff],
            j_offsets,
            dvar: vec![0.0; q],
            mu_zp: vec![0.0; q],
            z_pred: vec![0.0; q],
            inferred: false,
            t: vec![0.0; n * nt],
            jc: vec![0.0; q * nt],
            tj: vec![0.0; n * q],
            pht: Vec::new(),
            s_buf: Vec::new(),
            ls: Vec::new(),
            w: Vec::new(),
            innovation: Vec::new(),
            s: Mat::zeros(0, 0),
            log_likelihood: 0.0,
            gps,
        })
    }

    pub fn dim_x(&self) -> usize {
        self.n
    }

    /// Number of disturbances (GPs).
    pub fn n_gps(&self) -> usize {
        self.gps.len()
    }

    /// Σ n_b over the GPs.
    pub fn n_basis_total(&self) -> usize {
        self.j.len()
    }

    /// Total augmented dimension N.
    pub fn dim_total(&self) -> usize {
        self.nt
    }

    pub fn augmented(&self) -> bool {
        self.augmented
    }

    pub fn gp_basis(&self, g: usize) -> &RgpBasis {
        &self.gps[g].basis
    }

    /// Replaces the state estimate x (the first n entries of μ). On error nothing changes.
    pub fn set_x(&mut self, x: &[f64]) -> Result<()> {
        check_len("x", x, self.n)?;
        check_finite("x", x)?;
        self.mu[..self.n].copy_from_slice(x);
        Ok(())
    }

    /// Replaces the state covariance P (n × n row-major, symmetrised; the caller checks that it is
    /// positive semi-definite). The cross-covariance between the states and the GP weights is
    /// reset to zero, so that C stays positive semi-definite whatever P is. On error nothing
    /// changes.
    pub fn set_p(&mut self, p: &[f64]) -> Result<()> {
        let n = self.n;
        check_len("P", p, n * n)?;
        check_finite("P", p)?;
        for c in 0..self.nt {
            for r in 0..n {
                let v = if c < n {
                    0.5 * (p[r * n + c] + p[c * n + r])
                } else {
                    0.0
                };
                self.cov[(r, c)] = v;
                self.cov[(c, r)] = v;
            }
        }
        Ok(())
    }

    /// μ_z^p of the last completed [`Self::predict`] (one per disturbance).
    pub fn z_pred(&self) -> &[f64] {
        &self.z_pred
    }

    /// μ_z^p of the last [`Self::infer`], which the next [`Self::predict`] uses.
    pub fn inferred_z(&self) -> &[f64] {
        &self.mu_zp
    }

    /// The state estimate x (the first n entries of μ).
    pub fn x(&self) -> &[f64] {
        &self.mu[..self.n]
    }

    /// The state covariance P (the state block of C, stored complete and exactly symmetric).
    pub fn p(&self) -> MatRef<'_, f64> {
        self.cov.as_ref().submatrix(0, 0, self.n, self.n)
    }

    /// GP g's offset in the state, its offset in J, and its number of basis vectors.
    fn block(&self, g: usize) -> (usize, usize, usize) {
        (
            self.offsets[g],
            self.j_offsets[g],
            self.gps[g].basis.n_basis(),
        )
    }

    /// The GPs whose weights are stored whitened, with their offsets in the state.
    fn whitened_gps(&self) -> impl Iterator<Item = (&Rgp, usize)> {
        self.gps
            .iter()
            .zip(&self.offsets)
            .zip(&self.whitened)
            .filter(|(_, &w)| w)
            .map(|((g, &o), _)| (g, o))
    }

    /// The augmented mean μ = [x; μ_z1; …] (the weights mapped back from whitened coordinates).
    pub fn mu(&self) -> Vec<f64> {
        let mut mu = self.mu.clone();
        for (g, o) in self.whitened_gps() {
            let nb = g.basis.n_basis();
            let w = g.basis.unwhiten(&self.mu[o..o + nb]);
            mu[o..o + nb].copy_from_slice(&w);
        }
        mu
    }

    /// The augmented covariance C, in the weights' coordinates: T C_stored Tᵀ with
    /// T = blockdiag(I, L_1, …), exactly symmetric.
    pub fn cov(&self) -> Mat<f64> {
        let mut c = symmetric_from_lower(self.cov.as_ref());
        let nt = self.nt;
        for (g, o) in self.whitened_gps() {
            let nb = g.basis.n_basis();
            let l = g.basis.chol.as_ref();
            let mut rows = Mat::<f64>::zeros(nb, nt);
            matmul(
                rows.as_mut(),
                Accum::Replace,
                l,
                c.as_ref().submatrix(o, 0, nb, nt),
                1.0,
                Par::Seq,
            );
            c.as_mut().submatrix_mut(o, 0, nb, nt).copy_from(&rows);
            let mut cols = Mat::<f64>::zeros(nt, nb);
            matmul(
                cols.as_mut(),
                Accum::Replace,
                c.as_ref().submatrix(0, o, nt, nb),
                l.transpose(),
                1.0,
                Par::Seq,
            );
            c.as_mut().submatrix_mut(0, o, nt, nb).copy_from(&cols);
        }
        symmetric_from_lower(c.as_ref())
    }

    pub fn innovation(&self) -> &[f64] {
        &self.innovation
    }

    pub fn innovation_cov(&self) -> MatRef<'_, f64> {
        self.s.as_ref()
    }

    pub fn log_likelihood(&self) -> f64 {
        self.log_likelihood
    }

    /// Weights' mean and covariance of GP `g` (the state block mapped back from whitened
    /// coordinates, L u and L C_u Lᵀ, or the fixed GP in pure mode).
    pub fn gp_weights(&self, g: usize) -> (Vec<f64>, Mat<f64>) {
        let (o, nb) = (self.offsets[g], self.gps[g].basis.n_basis());
        if self.augmented && !self.whitened[g] {
            (
                self.mu[o..o + nb].to_vec(),
                symmetric_from_lower(self.cov.as_ref().submatrix(o, o, nb, nb)),
            )
        } else if self.augmented {
            let basis = &self.gps[g].basis;
            let cu = symmetric_from_lower(self.cov.as_ref().submatrix(o, o, nb, nb));
            let l = basis.chol.as_ref();
            let c = l * cu * l.transpose();
            (
                basis.unwhiten(&self.mu[o..o + nb]),
                symmetric_from_lower(c.as_ref()),
            )
        } else {
            (self.gps[g].mean.clone(), self.gps[g].cov.clone())
        }
    }

    /// Mean (prior mean included) and variance (σ_r² included) of GP `g` at the row-major
    /// inputs `zetas`.
    pub fn gp_predict(&mut self, g: usize, zetas: &[f64]) -> Result<(Vec<f64>, Vec<f64>)> {
        if g >= self.gps.len() {
            return Err(Error::invalid(
                "index",
                format!("there are {} GPs, got index {g}", self.gps.len()),
            ));
        }
        if !self.augmented {
            return self.gps[g].predict(zetas);
        }
        let m = self.gps[g].basis.count_inputs(zetas)?;
        let (mut mu, mut var) = (vec![0.0; m], vec![0.0; m]);
        let (o, nb) = (self.offsets[g], self.gps[g].basis.n_basis());
        let whitened = self.whitened[g];
        let Self {
            gps,
            mu: state,
            cov,
            ..
        } = self;
        let gp = &mut gps[g];
        let cz = symmetric_from_lower(cov.as_ref().submatrix(o, o, nb, nb));
        gp.basis.predict_with(
            &state[o..o + nb],
            cz.as_ref(),
            whitened,
            zetas,
            &mut gp.j,
            &mut mu,
            &mut var,
        );
        Ok((mu, var))
    }

    /// Step 1 (16): J_k and μ_z^p = J_k μ_z (+ m(ζ_j) for a GP with a prior mean) for every GP
    /// at its input ζ_j (the inputs of all GPs concatenated). Returns μ_z^p (one per disturbance). Must precede [`Self::predict`].
    pub fn infer(&mut self, zetas: &[f64]) -> Result<&[f64]> {
        self.infer_dispatch(zetas)?;
        Ok(&self.mu_zp)
    }

    fn infer_dispatch(&mut self, zetas: &[f64]) -> Result<()> {
        with_avx2!(RgpEkf, self.infer_impl(zetas: &[f64]) -> Result<()>)
    }

    #[inline(always)]
    fn infer_impl(&mut self, zetas: &[f64]) -> Result<()> {
        let total: usize = self.gps.iter().map(|g| g.basis.dim()).sum();
        check_len("zeta", zetas, total)?;
        check_finite("zeta", zetas)?;
        let mut zo = 0;
        for g in &self.gps {
            let nx = g.basis.dim();
            g.basis.check_prior_mean("zeta", &zetas[zo..zo + nx])?;
            zo += nx;
        }
        zo = 0;
        for g in 0..self.gps.len() {
            let (jo, nb, nx) = (
                self.j_offsets[g],
                self.gps[g].basis.n_basis(),
                self.gps[g].basis.dim(),
            );
            let j = &mut self.j[jo..jo + nb];
            let gp = &mut self.gps[g];
            // augmented: the weights are stored whitened, so J_k μ_z = v · u and one triangular
            // solve gives everything the step needs (see the struct's doc)
            let jkj = if self.whitened[g] {
                gp.basis.infer_whitened(&zetas[zo..zo + nx], j)
            } else {
                gp.basis.infer(&zetas[zo..zo + nx], j)
            };
            let m = gp.basis.prior_mean_at(&zetas[zo..zo + nx]);
            zo += nx;
            let base = (gp.basis.sigma_k2() - jkj).max(0.0) + gp.basis.sigma_r2;
            if self.augmented {
                let o = self.offsets[g];
                self.mu_zp[g] = dot_lanes8(j, &self.mu[o..o + nb]) + m;
                self.dvar[g] = base;
            } else {
                self.mu_zp[g] = dot_lanes8(j, &gp.mean) + m;
                self.dvar[g] = base + quad_form(gp.cov.as_ref(), j).max(0.0);
            }
        }
        self.inferred = true;
        Ok(())
    }

    /// Steps 2–3 (17), (18) with the structured product: the caller evaluated the predicted state
    /// `x_pred` = f(x, u, μ_z^p), A = ∂f/∂x (n × n) and e = ∂f/∂z (n × q), row-major, at
    /// (x, u, μ_z^p); `q_x` is Q_x (n × n). C⁺ = Ã C Ãᵀ + ẽ D ẽᵀ + blockdiag(Q_x, σ_p² I) where
    /// only the first n rows of Ã differ from the identity, so the GP block is untouched but for σ_p².
    pub fn predict(&mut self, x_pred: &[f64], a: &[f64], e: &[f64], q_x: &[f64]) -> Result<()> {
        with_avx2!(RgpEkf, self.predict_impl(x_pred: &[f64], a: &[f64], e: &[f64], q_x: &[f64]) -> Result<()>)
    }

    #[inline(always)]
    fn predict_impl(&mut self, x_pred: &[f64], a: &[f64], e: &[f64], q_x: &[f64]) -> Result<()> {
        self.check_predict_inputs(x_pred, a, e, q_x)?;
        let n = self.n;
        if self.augmented {
            self.weights_times_cov();
        }
        self.propagate_rows(a, e);
        self.predicted_state_block(a, e, q_x);
        if self.augmented {
            self.predicted_weight_blocks();
        }
        self.mu[..n].copy_from_slice(x_pred);
        self.z_pred.copy_from_slice(&self.mu_zp);
        self.inferred = false;
        Ok(())
    }

    /// The inputs of [`Self::predict`], checked in order; [`Self::infer`] must have run first.
    fn check_predict_inputs(
        &self,
        x_pred: &[f64],
        a: &[f64],
        e: &[f64],
        q_x: &[f64],
    ) -> Result<()> {
        let (n, q) = (self.n, self.gps.len());
        if !self.inferred {
            return Err(Error::invalid(
                "zeta",
                "infer(zeta) must be called before predict in every step",
            ));
        }
        check_len("f(x, u, z)", x_pred, n)?;
        check_len("A", a, n * n)?;
        check_len("e", e, n * q)?;
        check_len("Q_x", q_x, n * n)?;
        check_magnitude("f(x, u, z)", x_pred)?;
        check_magnitude("A", a)?;
        check_magnitude("e", e)?;
        check_finite("Q_x", q_x)?;
        Ok(())
    }

    /// Augmented mode: jc[g, :] = J_g C[z_g, :] for every GP (see the comment inside).
    #[inline(always)]
    fn weights_times_cov(&mut self) {
        let (q, nt) = (self.gps.len(), self.nt);
        // The products below involve an n-row block and vectors of length N; at these sizes plain
        // loops over C's contiguous columns beat faer's matmul dispatch.
        // jc[g, :] = J_g C[z_g, :] = (C J̃_g)ᵀ with J̃_g = J_g on the block z_g, 0 elsewhere: a
        // symmetric matrix-vector product from the stored lower triangle (see the struct's doc)
        for g in 0..q {
            let (o, jo, nb) = self.block(g);
            let jg = &self.j[jo..jo + nb];
            let out = &mut self.jc[g * nt..(g + 1) * nt];
            // columns before the block: C[i, z_g] = C[z_g, i], stored in column i
            for (i, v) in out[..o].iter_mut().enumerate() {
                *v = dot_lanes8(&self.cov.col_as_slice(i)[o..o + nb], jg);
            }
            out[o..].fill(0.0);
            // four columns k..k+4 at a time: below their 4 × 4 diagonal block, out[i] +=
            // Σ_t J_t C[i, k+t] in one pass (lower part) and out[k+t] += C[i, k+t] J_i in
            // another (upper part of rows k..k+4, = columns by symmetry; four dots sharing J)
            let mut b = 0;
            while b + 4 <= nb {
                let k = o + b;
                let c = |t: usize| &self.cov.col_as_slice(k + t)[k + 4..o + nb];
                let a = [jg[b], jg[b + 1], jg[b + 2], jg[b + 3]];
                add4(&mut out[k + 4..o + nb], a, [c(0), c(1), c(2), c(3)]);
                let d = dot4([c(0), c(1), c(2), c(3)], &jg[b + 4..]);
                for t in 0..4 {
                    let col = self.cov.col_as_slice(k + t);
                    out[k + t] += a[t] * col[k + t];
                    for s2 in t + 1..4 {
                        out[k + s2] += a[t] * col[k + s2];
                        out[k + t] += col[k + s2] * a[s2];
                    }
                    out[k + t] += d[t];
                    axpy(&mut out[o + nb..], a[t], &col[o + nb..]);
                }
                b += 4;
            }
            for (b, &jb) in jg.iter().enumerate().skip(b) {
                let k = o + b;
                let col = self.cov.col_as_slice(k);
                // one pass over column k below the diagonal: out[i] += J_b C[i, k] (lower
                // part) and out[k] += C[k, i] J_i (upper part of row k, = column k by symmetry)
                let up = symv_column(
                    &mut out[k + 1..o + nb],
                    jb,
                    &col[k + 1..o + nb],
                    &jg[b + 1..],
                );
                out[k] += up + jb * col[k];
                axpy(&mut out[o + nb..], jb, &col[o + nb..]);
            }
        }
    }

    /// T = Ã[0..n, :] C (`t`) and, augmented, tj = T[:, z_g] J_gᵀ: everything the new state rows
    /// need from the old C.
    #[inline(always)]
    fn propagate_rows(&mut self, a: &[f64], e: &[f64]) {
        let (n, q, nt) = (self.n, self.gps.len(), self.nt);
        // T = Ã[0..n, :] C = A C[x, :] + e (J C[z, :])   (n × N, row-major: t[r N + c]). Row r
        // is Σ_k A[r, k] C[:, k] + Σ_g e[r, g] jc[g, :]: axpys over the complete columns 0..n of C
        // (C[x, c] = C[c, x] for every c, the state block being exactly symmetric).
        for (r, row) in self.t.chunks_exact_mut(nt).enumerate() {
            row.fill(0.0);
            for k in 0..n {
                let ark = a[r * n + k];
                if ark != 0.0 {
                    axpy(row, ark, self.cov.col_as_slice(k));
                }
            }
            if self.augmented {
                for g in 0..q {
                    let erg = e[r * q + g];
                    if erg != 0.0 {
                        axpy(row, erg, &self.jc[g * nt..(g + 1) * nt]);
                    }
                }
            }
        }
        // tj[r, g] = T[r, z_g] J_gᵀ   (n × q, row-major)
        if self.augmented {
            for g in 0..q {
                let (o, jo, nb) = self.block(g);
                for r in 0..n {
                    self.tj[r * q + g] =
                        dot_lanes8(&self.t[r * nt + o..r * nt + o + nb], &self.j[jo..jo + nb]);
                }
            }
        }
    }

    /// The new state block C[x, x] (exactly symmetric).
    #[inline(always)]
    fn predicted_state_block(&mut self, a: &[f64], e: &[f64], q_x: &[f64]) {
        let (n, q, nt) = (self.n, self.gps.len(), self.nt);
        // C[x, x] = T[:, x] Aᵀ + tj eᵀ + e D eᵀ + Q_x: the lower half, mirrored (exactly
        // symmetric); T and tj hold everything needed from the old C
        for c in 0..n {
            for r in c..n {
                let mut s = 0.5 * (q_x[r * n + c] + q_x[c * n + r]);
                for k in 0..n {
                    s += self.t[r * nt + k] * a[c * n + k];
                }
                for g in 0..q {
                    if self.augmented {
                        s += self.tj[r * q + g] * e[c * q + g];
                    }
                    s += e[r * q + g] * self.dvar[g] * e[c * q + g];
                }
                self.cov[(r, c)] = s;
                self.cov[(c, r)] = s;
            }
        }
    }

    /// Augmented mode: the new C[z, x] and σ_p² added to the weights' diagonal blocks.
    #[inline(always)]
    fn predicted_weight_blocks(&mut self) {
        let (n, q, nt) = (self.n, self.gps.len(), self.nt);
        // C[z, x] = T[:, z]ᵀ (C[x, z] above the diagonal is not stored); C[z, z] += σ_p² I
        for r in 0..n {
            self.cov.col_as_slice_mut(r)[n..].copy_from_slice(&self.t[r * nt + n..(r + 1) * nt]);
        }
        for g in 0..q {
            let (o, nb, sp2) = (
                self.offsets[g],
                self.gps[g].basis.n_basis(),
                self.gps[g].basis.sigma_p2,
            );
            if sp2 != 0.0 {
                for i in o..o + nb {
                    self.cov.col_as_slice_mut(i)[i] += sp2;
                }
            }
        }
    }

    /// Step 4 (19): EKF update with the innovation ν = y − h(x^p) (length p), H = ∂h/∂x (p × n)
    /// and R_x (p × p), row-major. `learning` = true: 4a, states and weights; false: 4b, the
    /// weights' mean and covariance stay as predicted and the state rows get the Schmidt update
    /// (x += K_x ν, C[x, ·] −= K_x H C[x, ·]). Returns the log-likelihood of ν. On error the state
    /// is unchanged.
    pub fn update(&mut self, nu: &[f64], h: &[f64], r: &[f64], learning: bool) -> Result<f64> {
        with_avx2!(RgpEkf, self.update_impl(nu: &[f64], h: &[f64], r: &[f64], learning: bool) -> Result<f64>)
    }

    #[inline(always)]
    fn update_impl(&mut self, nu: &[f64], h: &[f64], r: &[f64], learning: bool) -> Result<f64> {
        let (n, nt) = (self.n, self.nt);
        let p = nu.len();
        if p == 0 {
            return Err(Error::invalid("y", "needs at least one output"));
        }
        check_magnitude("y - h(x)", nu)?;
        check_len("H", h, p * n)?;
        check_magnitude("H", h)?;
        check_len("R_x", r, p * p)?;
        check_finite("R_x", r)?;
        if self.pht.len() != nt * p {
            self.pht = vec![0.0; nt * p];
        }
        // C H̃ᵀ = C[:, x] Hᵀ (N × p, column-major): column k = Σ_j H[k, j] C[:, j]
        for k in 0..p {
            let col = &mut self.pht[k * nt..(k + 1) * nt];
            col.fill(0.0);
            for jj in 0..n {
                let hkj = h[k * n + jj];
                if hkj != 0.0 {
                    axpy(col, hkj, self.cov.col_as_slice(jj));
                }
            }
        }
        // S = H C[x, :] H̃ᵀ + R_x, exactly symmetric (row-major)
        let s = &mut self.s_buf;
        s.resize(p * p, 0.0);
        for i in 0..p {
            for jj in 0..=i {
                let v = 0.5
                    * (dot_lanes8(&h[i * n..(i + 1) * n], &self.pht[jj * nt..jj * nt + n])
                        + dot_lanes8(&h[jj * n..(jj + 1) * n], &self.pht[i * nt..i * nt + n]))
                    + 0.5 * (r[i * p + jj] + r[jj * p + i]);
                s[i * p + jj] = v;
                s[jj * p + i] = v;
            }
        }
        let ls = &mut self.ls;
        ls.resize(p * p, 0.0);
        if !cholesky(s, p, ls) {
            return Err(Error::numerical(
                "the innovation covariance H P Hᵀ + R_x is not positive definite",
            ));
        }
        // W = C H̃ᵀ L_S⁻ᵀ, column by column in place (column k: (column k − Σ_{m<k} L_S[k, m]
        // W[:, m]) / L_S[k, k]); w = L_S⁻¹ ν
        for k in 0..p {
            let (done, rest) = self.pht.split_at_mut(k * nt);
            let col = &mut rest[..nt];
            for m in 0..k {
                let lkm = ls[k * p + m];
                for (v, wm) in col.iter_mut().zip(&done[m * nt..(m + 1) * nt]) {
                    *v -= lkm * wm;
                }
            }
            let d = ls[k * p + k];
            for v in col.iter_mut() {
                *v /= d;
            }
        }
        let w = &mut self.w;
        w.clear();
        w.extend_from_slice(nu);
        for k in 0..p {
            let mut v = w[k];
            for m in 0..k {
                v -= ls[k * p + m] * w[m];
            }
            w[k] = v / ls[k * p + k];
        }
        let logdet: f64 = (0..p).map(|i| ls[i * p + i].ln()).sum::<f64>() * 2.0;
        let mahal: f64 = w.iter().map(|v| v * v).sum();
        let rows = if learning || !self.augmented { nt } else { n };
        for (k, wk) in w.iter().enumerate() {
            axpy(&mut self.mu[..rows], *wk, &self.pht[k * nt..k * nt + rows]);
        }
        // 4a: C −= W Wᵀ; 4b: only the state rows and columns (C[x, ·] and C[·, x])
        rank_p_downdate(&mut self.cov, &self.pht, p, n, rows == nt);
        self.innovation.clear();
        self.innovation.extend_from_slice(nu);
        if self.s.nrows() != p {
            self.s = Mat::zeros(p, p);
        }
        for i in 0..p {
            for jj in 0..p {
                self.s[(i, jj)] = self.s_buf[i * p + jj];
            }
        }
        self.log_likelihood =
            -0.5 * (mahal + logdet + p as f64 * (2.0 * std::f64::consts::PI).ln());
        Ok(self.log_likelihood)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Dense C⁺ = Ã C Ãᵀ + ẽ D ẽᵀ + blockdiag(Q_x, σ_p² I), formula (12)–(13).
    fn dense_prediction(
        c: &Mat<f64>,
        a: &Mat<f64>,
        e: &[f64],
        j: &[f64],
        d: f64,
        qx: &Mat<f64>,
        sp2: f64,
    ) -> Mat<f64> {
        let n = a.nrows();
        let nt = c.nrows();
        let mut at = Mat::<f64>::identity(nt, nt);
        for r in 0..n {
            for cc in 0..n {
                at[(r, cc)] = a[(r, cc)];
            }
            for (b, jb) in j.iter().enumerate() {
                at[(r, n + b)] = e[r] * jb;
            }
        }
        let mut out = &at * c * at.transpose();
        for r in 0..nt {
            for cc in 0..nt {
                let er = if r < n { e[r] } else { 0.0 };
                let ec = if cc < n { e[cc] } else { 0.0 };
                out[(r, cc)] += er * d * ec;
                if r < n && cc < n {
                    out[(r, cc)] += qx[(r, cc)];
                }
            }
            if r >= n {
                out[(r, r)] += sp2;
            }
        }
        out
    }

    #[test]
    fn structured_prediction_equals_dense_formula() {
        let nb = 7;
        let b = RgpBasis::new(&[-1.0], &[3.0], &[nb], 2.0, 1.5, 0.2, 0.05).unwrap();
        let gp = Rgp::new(b);
        let n = 3;
        let nt = n + nb;
        // a random SPD covariance
        let mut seed = 12345u64;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        let g = Mat::<f64>::from_fn(nt, nt, |_, _| rnd());
        let c0 = &g * g.transpose() + Mat::<f64>::identity(nt, nt);
        let a = Mat::<f64>::from_fn(n, n, |_, _| rnd());
        let e: Vec<f64> = (0..n).map(|_| rnd()).collect();
        let qx = Mat::<f64>::from_fn(n, n, |r, c| if r == c { 0.01 } else { 0.0 });
        let mut x0 = vec![0.0; n];
        x0[0] = 0.3;
        let p0: Vec<f64> = (0..n * n)
            .map(|i| if i % (n + 1) == 0 { 1.0 } else { 0.0 })
            .collect();
        let mut ekf = RgpEkf::new(&x0, &p0, vec![gp], true).unwrap();
        ekf.cov.copy_from(&c0);
        ekf.infer(&[0.7]).unwrap();
        let j = ekf.j.clone();
        let d = ekf.dvar[0];
        let a_rm: Vec<f64> = (0..n * n).map(|i| a[(i / n, i % n)]).collect();
        let q_rm: Vec<f64> = (0..n * n).map(|i| qx[(i / n, i % n)]).collect();
        ekf.predict(&[1.0, 2.0, 3.0], &a_rm, &e, &q_rm).unwrap();
        // in the stored (whitened) coordinates, where J_k is the row v the step used
        let dense = dense_prediction(&c0, &a, &e, &j, d, &qx, 0.05 * 0.05);
        let cov = symmetric_from_lower(ekf.cov.as_ref());
        for r in 0..nt {
            for c in 0..nt {
                assert!(
                    (dense[(r, c)] - cov[(r, c)]).abs() < 1e-12 * (1.0 + dense[(r, c)].abs()),
                    "({r},{c}): {} vs {}",
                    dense[(r, c)],
                    cov[(r, c)]
                );
            }
        }
    }

    #[test]
    fn whitened_storage_maps_back_to_the_weights() {
        // a trained GP without process noise is stored whitened; mu, cov and gp_weights return
        // its weights, and a GP with σ_p > 0 is stored as is
        for sp in [0.0, 0.05] {
            let mut gp = Rgp::new(RgpBasis::new(&[-1.0], &[1.0], &[9], 1.5, 2.0, 0.1, sp).unwrap());
            for k in 0..30 {
                let z = (k as f64 * 0.377) % 2.0 - 1.0;
                gp.update(&[z], (2.0 * z).sin(), 0.01).unwrap();
            }
            let ekf =
                RgpEkf::new(&[0.5, -0.5], &[1.0, 0.2, 0.2, 2.0], vec![gp.clone()], true).unwrap();
            assert_eq!(ekf.whitened[0], sp == 0.0);
            let (m, c) = ekf.gp_weights(0);
            let (mu, cov) = (ekf.mu(), ekf.cov());
            for i in 0..9 {
                assert!((m[i] - gp.mean()[i]).abs() < 1e-12);
                assert!((mu[2 + i] - gp.mean()[i]).abs() < 1e-12);
                for jj in 0..9 {
                    assert!((c[(i, jj)] - gp.cov()[(i, jj)]).abs() < 1e-12);
                    assert!((cov[(2 + i, 2 + jj)] - gp.cov()[(i, jj)]).abs() < 1e-12);
                }
                assert_eq!(cov[(2 + i, 0)], 0.0);
            }
            assert_eq!(cov[(0, 1)], 0.2);
        }
    }

    #[test]
    fn covariance_stays_exactly_symmetric_and_psd() {
        let b = RgpBasis::new(&[-2.0], &[2.0], &[11], 3.0, 2.0, 0.1, 0.01).unwrap();
        let mut ekf =
            RgpEkf::new(&[0.0, 0.0], &[1.0, 0.0, 0.0, 1.0], vec![Rgp::new(b)], true).unwrap();
        let (a, e, q) = (
            [1.0, 0.01, -0.04, 0.96],
            [0.0, 0.01],
            [1e-6, 0.0, 0.0, 1e-6],
        );
        for k in 0..200 {
            let z = ((k * 37) % 100) as f64 / 25.0 - 2.0;
            let mzp = ekf.infer(&[z]).unwrap()[0];
            let x = ekf.mu()[..2].to_vec();
            let xp = [x[0] + 0.01 * x[1], -0.04 * x[0] + 0.96 * x[1] + 0.01 * mzp];
            ekf.predict(&xp, &a, &e, &q).unwrap();
            let nu = [z.sin() - xp[0], 0.1 - xp[1]];
            ekf.update(
                &nu,
                &[1.0, 0.0, 0.0, 1.0],
                &[1e-2, 0.0, 0.0, 1e-2],
                k % 3 != 0,
            )
            .unwrap();
            for i in 0..2 {
                assert_eq!(
                    ekf.cov[(i, 1 - i)],
                    ekf.cov[(1 - i, i)],
                    "stored state block"
                );
            }
            let c = ekf.cov();
            for i in 0..c.nrows() {
                assert!(c[(i, i)] > 0.0);
                for j in 0..i {
                    assert_eq!(c[(i, j)], c[(j, i)], "step {k}, ({i}, {j})");
                }
            }
        }
        let mut gp = Rgp::new(RgpBasis::new(&[0.0], &[1.0], &[7], 1.0, 1.0, 0.0, 0.01).unwrap());
        for k in 0..100 {
            let z = (k as f64 * 0.137) % 1.0;
            gp.update(&[z], z * z, 1e-3).unwrap();
        }
        let c = gp.cov();
        for i in 0..7 {
            for j in 0..i {
                assert_eq!(c[(i, j)], c[(j, i)]);
            }
        }
    }
}
