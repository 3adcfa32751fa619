//! Exact Gaussian-process regression with the SE-ARD kernel (docs/user_guide/gaussian_processes.rst).
//!
//! [`Gp`] is one zero-mean output: built once from training inputs D (N × n_d, row-major), targets
//! y (N) and log-hyperparameters θ = log([σ_f, φ_1..φ_nd, σ_ε]); it caches the Cholesky factor L of
//! K + σ_ε² I (faer) and α = L⁻ᵀ L⁻¹ y. [`MultiGp`] holds q independent GPs on shared inputs, one
//! per output column, each with its own θ. Predictions for a batch of k test points give the
//! posterior mean m(d*) = k*ᵀ α, the latent (noise-free) variance σ²(d*) = σ_f² − ‖L⁻¹ k*‖² and
//! their analytic gradients w.r.t. d*, written into caller buffers with a reusable [`GpWorkspace`].
//! [`log_marginal_likelihood`] returns the LML and its gradient w.r.t. θ.
//!
//! **Jitter policy.** K + σ_ε² I is first factored as is. If the Cholesky factorisation fails
//! (a non-positive pivot), a diagonal jitter δ = 10⁻¹⁰·(σ_f² + σ_ε²) is added and multiplied by
//! ten on every further failure, up to 10⁻⁶·(σ_f² + σ_ε²) (five attempts). The jitter that worked
//! is recorded ([`Gp::jitter`], 0 when none was needed) and acts as extra noise variance in every
//! later prediction and in the LML; if the largest jitter still fails, a `Numerical` error is
//! returned.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt;
use faer::linalg::triangular_solve::{
    solve_lower_triangular_in_place, solve_upper_triangular_in_place,
};
use faer::{Mat, MatMut, MatRef, Par};

use crate::error::{check_finite, check_len, Error, Result};
use crate::kernel::SeArd;
use crate::linalg::{
    back_substitution, dot_lanes4, forward_substitution, sum_lanes4, sum_of_squares_lanes4,
    DivideByDiagonal,
};
use crate::mean::AffineMean;

/// Relative size of the first jitter tried, and of the largest (see the module docs).
const JITTER_START: f64 = 1e-10;
const JITTER_MAX: f64 = 1e-6;
/// Number of jittered attempts: 1e-10, 1e-9, …, 1e-6 (relative).
const JITTER_STEPS: i32 = 5;
/// Units in the last place of σ_f² for the typical rounding error of a latent variance
/// (measured standard deviation on the batch-reactor f-GP with σ_f = 1000: ~2.5 ulp).
const VARIANCE_ULPS: f64 = 3.0;

/// Scratch memory for batch predictions: three N × k column-major buffers and a small
/// (n_d + 1) × k one. It only grows, so once it has been sized for the largest (N, k) in use,
/// the GP code allocates nothing per prediction (faer's kernels manage their own small scratch).
#[derive(Default, Clone, Debug)]
pub struct GpWorkspace {
    kstar: Vec<f64>,
    v: Vec<f64>,
    prod: Vec<f64>,
    sums: Vec<f64>,
}

/// The buffers of one prediction, see [`GpWorkspace`].
struct Buffers<'a> {
    kstar: &'a mut [f64],
    v: &'a mut [f64],
    prod: &'a mut [f64],
    sums: &'a mut [f64],
}

impl GpWorkspace {
    pub fn new() -> Self {
        Self::default()
    }

    fn buffers(&mut self, len: usize, sums: usize) -> Buffers<'_> {
        if self.kstar.len() < len {
            self.kstar.resize(len, 0.0);
            self.v.resize(len, 0.0);
            self.prod.resize(len, 0.0);
        }
        if self.sums.len() < sums {
            self.sums.resize(sums, 0.0);
        }
        Buffers {
            kstar: &mut self.kstar[..len],
            v: &mut self.v[..len],
            prod: &mut self.prod[..len],
            sums: &mut self.sums[..sums],
        }
    }
}

/// One exact zero-mean GP with the SE-ARD kernel and a cached Cholesky factor.
#[derive(Clone, Debug)]
pub struct Gp {
    /// Training inputs, N × n_d row-major.
    x: Vec<f64>,
    y: Vec<f64>,
    theta: Vec<f64>,
    kernel: SeArd,
    sigma_eps: f64,
    jitter: f64,
    /// The Cholesky factor L of K + (σ_ε² + jitter) I in its lower triangle and Lᵀ in its strict
    /// upper triangle (faer's triangular solves read one triangle only). The second copy costs no
    /// memory (the upper half would be zeros) and makes the Lᵀ solve column-major, which faer
    /// runs ~1.4× faster than on the transposed view of L at N = 150. Stored column-major
    /// without padding (N × N), so that every column is one slice for [`substitution`].
    chol: Vec<f64>,
    /// (K + (σ_ε² + jitter) I)⁻¹ y.
    alpha: Vec<f64>,
    /// [`Gp::mean_rounding`], fixed once α is.
    mean_rounding: f64,
    /// Xᵀ, n_d × N row-major (each input coordinate contiguous, for the weighted sums of
    /// `predict_block`).
    xt: Vec<f64>,
    lml: f64,
}

/// Splits θ = log([σ_f, φ_1..φ_nd, σ_ε]) into a kernel and σ_ε, naming `theta` on bad values.
pub(crate) fn hyperparameters(theta: &[f64]) -> Result<(SeArd, f64)> {
    if theta.len() < 3 {
        return Err(Error::invalid(
            "theta",
            format!(
                "needs n_d + 2 >= 3 values log([sigma_f, lengthscales.., sigma_eps]), got {}",
                theta.len()
            ),
        ));
    }
    check_finite("theta", theta)?;
    let p: Vec<f64> = theta.iter().map(|t| t.exp()).collect();
    if let Some(i) = p.iter().position(|v| !(v.is_finite() && *v > 0.0)) {
        return Err(Error::invalid(
            "theta",
            format!(
                "exp(theta[{i}]) = exp({}) is not a finite positive number",
                theta[i]
            ),
        ));
    }
    let nd = theta.len() - 2;
    if let Some(l) = (1..=nd).find(|&l| !crate::kernel::inverse_square_finite(p[l])) {
        return Err(Error::invalid(
            "theta",
            format!(
                "length-scale exp(theta[{l}]) = exp({}) is too small: 1/lengthscale^2 overflows \
                 (theta[{l}] must be above about -354)",
                theta[l]
            ),
        ));
    }
    if !((p[0] * p[0]).is_finite() && (p[nd + 1] * p[nd + 1]).is_finite()) {
        return Err(Error::invalid(
            "theta",
            "sigma_f^2 or sigma_eps^2 overflows; theta is far outside a usable range",
        ));
    }
    let kernel = SeArd::new(p[0], &p[1..=nd])?;
    Ok((kernel, p[nd + 1]))
}

/// Checks the training set against the input dimension `nd` and returns N.
pub(crate) fn check_training(x: &[f64], y: &[f64], nd: usize) -> Result<usize> {
    let n = y.len();
    if n < 2 {
        return Err(Error::invalid(
            "y",
            format!("needs at least 2 training points, got {n}"),
        ));
    }
    check_len("x", x, n * nd).map_err(|_| {
        Error::invalid(
            "x",
            format!(
                "expected {n} points of dimension {nd} ({} values), got {} values",
                n * nd,
                x.len()
            ),
        )
    })?;
    check_finite("x", x)?;
    check_finite("y", y)?;
    Ok(n)
}

/// Cholesky factor of `gram` + noise_var·I under the jitter policy; returns (S, jitter) with L in
/// the lower and Lᵀ in the strict upper triangle of S.
fn factor_with_jitter(gram: &Mat<f64>, noise_var: f64, signal_var: f64) -> Result<(Mat<f64>, f64)> {
    let n = gram.nrows();
    let mut a = Mat::<f64>::zeros(n, n);
    let mut mem = MemBuffer::new(llt::factor::cholesky_in_place_scratch::<f64>(
        n,
        Par::Seq,
        Default::default(),
    ));
    let scale = signal_var + noise_var;
    // Attempt 0 without jitter, then JITTER_START·scale growing tenfold up to JITTER_MAX·scale.
    for attempt in 0..=JITTER_STEPS {
        crate::interrupt::check()?;
        let jitter = if attempt == 0 {
            0.0
        } else {
            JITTER_START * scale * 10f64.powi(attempt - 1)
        };
        a.copy_from(gram);
        for i in 0..n {
            a[(i, i)] += noise_var + jitter;
        }
        let factored = llt::factor::cholesky_in_place(
            a.as_mut(),
            Default::default(),
            Par::Seq,
            MemStack::new(&mut mem),
            Default::default(),
        );
        if factored.is_ok() {
            for j in 0..n {
                for i in 0..j {
                    a[(i, j)] = a[(j, i)];
                }
            }
            return Ok((a, jitter));
        }
    }
    Err(Error::numerical(format!(
        "K + sigma_eps^2 I is not positive definite even with a diagonal jitter of {:.3e} \
         (N = {n}, sigma_f^2 = {signal_var:.3e}, sigma_eps^2 = {noise_var:.3e}); \
         check for duplicated inputs or increase sigma_eps",
        JITTER_MAX * scale
    )))
}

impl Gp {
    /// Fits the posterior cache. `x`: N × n_d row-major training inputs, `y`: N targets,
    /// `theta` = log([σ_f, φ_1..φ_nd, σ_ε]) (n_d is `theta.len() - 2`). Bad input gives
    /// `InvalidInput` naming the argument; a matrix that stays indefinite under the jitter policy
    /// (module docs) gives `Numerical`.
    pub fn new(x: &[f64], y: &[f64], theta: &[f64]) -> Result<Gp> {
        let (kernel, sigma_eps) = hyperparameters(theta)?;
        let nd = kernel.dim();
        let n = check_training(x, y, nd)?;
        let gram = kernel.gram(x);
        let (chol, jitter) = factor_with_jitter(&gram, sigma_eps * sigma_eps, kernel.variance())?;
        let l = chol.as_ref();
        let mut alpha = y.to_vec();
        {
            let mut rhs = MatMut::from_column_major_slice_mut(&mut alpha[..], n, 1);
            solve_lower_triangular_in_place(l, rhs.as_mut(), Par::Seq);
            solve_upper_triangular_in_place(l, rhs.as_mut(), Par::Seq);
        }
        let half_logdet: f64 = (0..n).map(|i| l[(i, i)].ln()).sum();
        let data_fit: f64 = y.iter().zip(&alpha).map(|(a, b)| a * b).sum();
        let lml =
            -0.5 * data_fit - half_logdet - 0.5 * n as f64 * (2.0 * std::f64::consts::PI).ln();
        if !lml.is_finite() {
            return Err(Error::numerical(
                "the log marginal likelihood is not finite (ill-conditioned K + sigma_eps^2 I)",
            ));
        }
        let mean_rounding =
            f64::EPSILON * kernel.variance() * alpha.iter().map(|a| a * a).sum::<f64>().sqrt();
        Ok(Gp {
            x: x.to_vec(),
            y: y.to_vec(),
            theta: theta.to_vec(),
            kernel,
            sigma_eps,
            jitter,
            chol: (0..n * n).map(|t| chol[(t % n, t / n)]).collect(),
            alpha,
            xt: (0..nd * n).map(|t| x[(t % n) * nd + t / n]).collect(),
            mean_rounding,
            lml,
        })
    }

    /// Input dimension n_d.
    pub fn dim(&self) -> usize {
        self.kernel.dim()
    }

    /// Number of training points N.
    pub fn n_train(&self) -> usize {
        self.y.len()
    }

    /// θ = log([σ_f, φ_1..φ_nd, σ_ε]).
    pub fn theta(&self) -> Vec<f64> {
        self.theta.clone()
    }

    pub fn kernel(&self) -> &SeArd {
        &self.kernel
    }

    pub fn sigma_eps(&self) -> f64 {
        self.sigma_eps
    }

    /// Diagonal jitter added by the jitter policy (0 if none was needed).
    pub fn jitter(&self) -> f64 {
        self.jitter
    }

    /// Training inputs (N × n_d row-major) and targets.
    pub fn x_train(&self) -> &[f64] {
        &self.x
    }

    pub fn y_train(&self) -> &[f64] {
        &self.y
    }

    /// α = (K + σ_ε² I)⁻¹ y.
    pub fn alpha(&self) -> &[f64] {
        &self.alpha
    }

    /// A copy of the lower Cholesky factor L of K + (σ_ε² + jitter) I (zeros above the diagonal).
    pub fn cholesky(&self) -> Mat<f64> {
        let n = self.n_train();
        let s = self.chol_ref();
        Mat::from_fn(n, n, |i, j| if i >= j { s[(i, j)] } else { 0.0 })
    }

    /// The Cholesky storage as a faer matrix view.
    fn chol_ref(&self) -> MatRef<'_, f64> {
        let n = self.n_train();
        MatRef::from_column_major_slice(&self.chol, n, n)
    }

    /// log p(y | D, θ) at this GP's θ.
    pub fn log_marginal_likelihood(&self) -> f64 {
        self.lml
    }

    /// log p(y | D, θ) and its gradient w.r.t. θ = log([σ_f, φ.., σ_ε]):
    /// ∂/∂θ_j = ½ tr((α αᵀ − K⁻¹) ∂K/∂θ_j), with ∂K/∂log σ_f = 2 K_f,
    /// ∂K/∂log φ_l = K_f ∘ (x_il − x_jl)²/φ_l², ∂K/∂log σ_ε = 2 σ_ε² I. O(N³) for K⁻¹.
    pub fn log_marginal_likelihood_gradient(&self) -> Vec<f64> {
        let n = self.n_train();
        let nd = self.dim();
        // K⁻¹ from the cached factor (faer's Cholesky inverse; it reads the lower triangle of
        // `chol` and writes the lower triangle of `kinv`, the only part used below).
        let mut kinv = Mat::<f64>::zeros(n, n);
        let mut mem = MemBuffer::new(llt::inverse::inverse_scratch::<f64>(n, Par::Seq));
        llt::inverse::inverse(
            kinv.as_mut(),
            self.chol_ref(),
            Par::Seq,
            MemStack::new(&mut mem),
        );
        let w = self.kernel.inv_lengthscales_sq();
        let s2 = self.kernel.variance();
        let a = &self.alpha;
        let x = &self.x;
        let mut g = vec![0.0; nd + 2];
        let mut trace_w = 0.0;
        for j in 0..n {
            let xj = &x[j * nd..(j + 1) * nd];
            // Diagonal: K_f = σ_f², no length-scale term.
            let wjj = a[j] * a[j] - kinv[(j, j)];
            trace_w += wjj;
            g[0] += wjj * s2;
            for i in j + 1..n {
                let xi = &x[i * nd..(i + 1) * nd];
                let kf = self.kernel.eval(xi, xj);
                // Both (i, j) and (j, i): factor 2.
                let wij = 2.0 * (a[i] * a[j] - kinv[(i, j)]) * kf;
                if wij == 0.0 {
                    // kf = 0 (points far apart in length-scales): no term, and d² w may overflow
                    continue;
                }
                g[0] += wij;
                for l in 0..nd {
                    let d = xi[l] - xj[l];
                    g[1 + l] += 0.5 * wij * d * d * w[l];
                }
            }
        }
        g[nd + 1] = self.sigma_eps * self.sigma_eps * trace_w;
        g
    }

    /// Typical absolute rounding error (about one standard deviation) of a computed latent
    /// variance σ_f² − ‖L⁻¹k*‖²: a few units in the last place of σ_f², since the subtraction
    /// cancels when the variance is small next to σ_f². With [`Gp::mean_rounding`] it lets a
    /// solver tell the rounding noise of a cost built from GP predictions from real progress;
    /// it matters for GPs whose fit ran to a large σ_f (e.g. σ_f = 1000, ℓ = 1000 imitating a
    /// linear function: variances then jitter by ~3e-10 and means by ~3e-7).
    pub fn variance_rounding(&self) -> f64 {
        VARIANCE_ULPS * f64::EPSILON * self.kernel.variance()
    }

    /// Typical absolute rounding error of a computed posterior mean m = Σ_i k_i α_i: the
    /// kernel values carry relative errors of order ε, so m jitters by ~ε·‖k ∘ α‖₂ ≤
    /// ε·σ_f²·‖α‖₂ (large when the fit is ill-conditioned and α is large).
    pub fn mean_rounding(&self) -> f64 {
        self.mean_rounding
    }

    /// The numerics of every prediction: for k points `d`, writes output `o` of `q` into
    /// `mean[j*q + o]`, `var[j*q + o]` and the gradients at `[(j*q + o)*nd ..]`. With `var` None
    /// only means (and mean gradients if asked) are computed, O(N) per point; variances cost two
    /// (with gradients) or one triangular solve with k right-hand sides.
    ///
    /// Every mean and gradient is a weighted sum over the training points: with the kernel
    /// values c_ij = k(x_i, d_j) and weights b_ij (α_i for the mean, β_ij = [(K + σ²I)⁻¹k*_j]_i
    /// for the variance), s_j = Σ_i c_ij b_ij and g_lj = Σ_i c_ij b_ij x_il, and
    /// ∂/∂d_jl of Σ_i b_i k(x_i, d_j) = −w_l (d_jl s_j − g_lj).
    ///
    /// The loops (kernel columns with their exponentials, products, sums) are built for AVX2 as
    /// well and that build runs when the CPU has it (detected at run time; a portable wheel
    /// targets SSE2; faer dispatches its own kernels). Both builds perform the same operations
    /// in the same order (no fused multiply-add), so their results are identical.
    #[allow(clippy::too_many_arguments)]
    fn predict_block(
        &self,
        d: &[f64],
        k: usize,
        o: usize,
        q: usize,
        mean: &mut [f64],
        var: Option<&mut [f64]>,
        grads: Option<(&mut [f64], &mut [f64])>,
        ws: &mut GpWorkspace,
    ) {
        #[cfg(target_arch = "x86_64")]
        {
            #[target_feature(enable = "avx2")]
            #[allow(clippy::too_many_arguments)]
            fn avx2(
                gp: &Gp,
                d: &[f64],
                k: usize,
                o: usize,
                q: usize,
                mean: &mut [f64],
                var: Option<&mut [f64]>,
                grads: Option<(&mut [f64], &mut [f64])>,
                ws: &mut GpWorkspace,
            ) {
                gp.predict_block_impl(d, k, o, q, mean, var, grads, ws)
            }
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU supports AVX2, checked just above.
                return unsafe { avx2(self, d, k, o, q, mean, var, grads, ws) };
            }
        }
        self.predict_block_impl(d, k, o, q, mean, var, grads, ws)
    }

    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn predict_block_impl(
        &self,
        d: &[f64],
        k: usize,
        o: usize,
        q: usize,
        mean: &mut [f64],
        var: Option<&mut [f64]>,
        mut grads: Option<(&mut [f64], &mut [f64])>,
        ws: &mut GpWorkspace,
    ) {
        let n = self.n_train();
        let nd = self.dim();
        let w = self.kernel.inv_lengthscales_sq();
        let s2 = self.kernel.variance();
        let Buffers {
            kstar,
            v,
            prod,
            sums,
        } = ws.buffers(n * k, (nd + 1) * k);
        // k*: column j holds k(x_i, d_j) for i = 0..N.
        for (j, dj) in d.chunks_exact(nd).enumerate() {
            kernel_column(&self.x, dj, w, s2, &mut kstar[j * n..(j + 1) * n]);
        }
        // Means m_j = s_j with b = α; their gradients −w_l (d_jl m_j − g_lj).
        for (pc, kc) in prod.chunks_exact_mut(n).zip(kstar.chunks_exact(n)) {
            for ((p, c), a) in pc.iter_mut().zip(kc).zip(&self.alpha) {
                *p = c * a;
            }
        }
        self.weighted_sums(prod, k, sums);
        for (j, dj) in d.chunks_exact(nd).enumerate() {
            let sj = &sums[j * (nd + 1)..(j + 1) * (nd + 1)];
            mean[j * q + o] = sj[nd];
            if let Some((dmean, _)) = grads.as_mut() {
                let g = &mut dmean[(j * q + o) * nd..(j * q + o + 1) * nd];
                for l in 0..nd {
                    g[l] = -w[l] * (dj[l] * sj[nd] - sj[l]);
                }
            }
        }
        let Some(var) = var else { return };
        v.copy_from_slice(kstar);
        self.solve(v, k, Triangle::Lower);
        for j in 0..k {
            // Clamp round-off negatives (test points on top of noise-free data) at 0.
            var[j * q + o] = (s2 - sum_of_squares_lanes4(&v[j * n..(j + 1) * n])).max(0.0);
        }
        let Some((_, dvar)) = grads else { return };
        // β = L⁻ᵀ v = (K + σ_ε² I)⁻¹ k*; ∂σ²/∂d_jl = −2 ∂(Σ_i β_ij k_ij)/∂d_jl |_β fixed
        // = 2 w_l (d_jl s_j − g_lj) with b = β.
        self.solve(v, k, Triangle::Upper);
        for ((p, c), b) in prod.iter_mut().zip(kstar.iter()).zip(v.iter()) {
            *p = c * b;
        }
        self.weighted_sums(prod, k, sums);
        for (j, dj) in d.chunks_exact(nd).enumerate() {
            let sj = &sums[j * (nd + 1)..(j + 1) * (nd + 1)];
            let g = &mut dvar[(j * q + o) * nd..(j * q + o + 1) * nd];
            for l in 0..nd {
                g[l] = 2.0 * w[l] * (dj[l] * sj[nd] - sj[l]);
            }
        }
    }

    /// v ← L⁻¹ v (`Triangle::Lower`) or L⁻ᵀ v (`Triangle::Upper`) for the k columns of `v`
    /// (N × k column-major).
    #[inline(always)]
    fn solve(&self, v: &mut [f64], k: usize, tri: Triangle) {
        let n = self.n_train();
        if k <= SMALL_RHS {
            return substitution(&self.chol, n, v, tri);
        }
        let mut vm = MatMut::from_column_major_slice_mut(&mut v[..], n, k);
        match tri {
            Triangle::Lower => {
                solve_lower_triangular_in_place(self.chol_ref(), vm.as_mut(), Par::Seq)
            }
            Triangle::Upper => {
                solve_upper_triangular_in_place(self.chol_ref(), vm.as_mut(), Par::Seq)
            }
        }
    }

    /// For P = `prod` (N × k column-major), column j of `sums` (at j·(n_d+1)) gets
    /// (Σ_i p_ij x_i1, …, Σ_i p_ij x_i,n_d, Σ_i p_ij).
    #[inline(always)]
    fn weighted_sums(&self, prod: &[f64], k: usize, sums: &mut [f64]) {
        let (n, nd) = (self.n_train(), self.dim());
        for (pc, sj) in prod[..n * k]
            .chunks_exact(n)
            .zip(sums.chunks_exact_mut(nd + 1))
        {
            for (l, xl) in self.xt.chunks_exact(n).enumerate() {
                sj[l] = dot_lanes4(pc, xl);
            }
            sj[nd] = sum_lanes4(pc);
        }
    }
}

/// Right-hand sides up to this many columns are solved by [`substitution`]: faer's recursive
/// triangular solve spends most of a one-column solve at N ~ 150 on dispatch (measured, AVX2
/// build: the two solves of one column 7.7 µs with faer, 4 µs by substitution; with two columns
/// faer is already faster). One column is the warm start's single new window point and a
/// GP-EKF's prediction.
const SMALL_RHS: usize = 1;

enum Triangle {
    /// Solve L x = b.
    Lower,
    /// Solve Lᵀ x = b.
    Upper,
}

/// Forward (L x = b) or backward (Lᵀ x = b) substitution for each N-long column of `v`, with
/// `s` the Cholesky storage (N × N column-major, L in the lower and Lᵀ in the strict upper
/// triangle): `linalg::triangular` with this module's rounding ([`DivideByDiagonal`]: division
/// by the diagonal, a solved block's terms summed before they are subtracted, the backward sweep
/// in column form over the stored Lᵀ).
#[inline(always)]
fn substitution(s: &[f64], n: usize, v: &mut [f64], tri: Triangle) {
    let col = |j: usize| &s[j * n..(j + 1) * n];
    for x in v.chunks_exact_mut(n) {
        match tri {
            Triangle::Lower => forward_substitution(col, &DivideByDiagonal, x),
            Triangle::Upper => back_substitution(col, &DivideByDiagonal, x),
        }
    }
}

/// out_i = σ_f² exp(−½ Σ_l w_l (d_l − x_il)²) for the training points x (N × n_d row-major).
/// The scaled squared distances are formed first (the input dimension a compile-time constant
/// for n_d ≤ 4 so the inner loop unrolls), then exponentiated by a vectorised exp
/// ([`scaled_exp`]): the exponentials are the largest part of a kernel column.
#[inline(always)]
pub(crate) fn kernel_column(x: &[f64], d: &[f64], w: &[f64], s2: f64, out: &mut [f64]) {
    #[inline(always)]
    fn fixed<const ND: usize>(x: &[f64], d: &[f64], w: &[f64], out: &mut [f64]) {
        let (Ok(d), Ok(w)) = (<&[f64; ND]>::try_from(d), <&[f64; ND]>::try_from(w)) else {
            return generic(x, d, w, out);
        };
        for (c, xi) in out.iter_mut().zip(x.chunks_exact(ND)) {
            let mut r2 = 0.0;
            for l in 0..ND {
                let t = d[l] - xi[l];
                r2 += t * t * w[l];
            }
            *c = -0.5 * r2;
        }
    }
    #[inline(always)]
    fn generic(x: &[f64], d: &[f64], w: &[f64], out: &mut [f64]) {
        for (c, xi) in out.iter_mut().zip(x.chunks_exact(d.len())) {
            let r2: f64 = d
                .iter()
                .zip(xi)
                .zip(w)
                .map(|((a, b), wl)| (a - b) * (a - b) * wl)
                .sum();
            *c = -0.5 * r2;
        }
    }
    match d.len() {
        1 => fixed::<1>(x, d, w, out),
        2 => fixed::<2>(x, d, w, out),
        3 => fixed::<3>(x, d, w, out),
        4 => fixed::<4>(x, d, w, out),
        _ => generic(x, d, w, out),
    }
    scaled_exp(out, s2);
}

/// v_i ← s·exp(v_i) for kernel exponents v_i ≤ 0, in a form the compiler vectorises.
#[inline(always)]
fn scaled_exp(v: &mut [f64], s: f64) {
    for t in v.iter_mut() {
        *t = s * exp_nonpositive(*t);
    }
}

/// exp(x) for x ≤ 0, within 1 ulp of libm's on the kernel's range (tested), branch-free so that
/// loops over it vectorise: x = n ln2 + r with |r| ≤ ln2/2 (Cody-Waite, ln2 split in two),
/// exp(r) by its degree-13 Taylor polynomial (truncation below 1e-17 relative), 2ⁿ from the
/// exponent bits; 0 below −708 (where exp underflows to subnormals). The same scheme as
/// `wide::f64x4::exp`, which cannot be selected at run time.
#[inline(always)]
fn exp_nonpositive(x: f64) -> f64 {
    const LN2_HI: f64 = 0.693_145_751_953_125;
    const LN2_LO: f64 = 1.428_606_820_309_417_3e-6;
    // Adding 1.5·2⁵² rounds to an integer in the low mantissa bits.
    const SHIFTER: f64 = 6_755_399_441_055_744.0;
    const C: [f64; 12] = [
        1.0 / 6_227_020_800.0,
        1.0 / 479_001_600.0,
        1.0 / 39_916_800.0,
        1.0 / 3_628_800.0,
        1.0 / 362_880.0,
        1.0 / 40_320.0,
        1.0 / 5_040.0,
        1.0 / 720.0,
        1.0 / 120.0,
        1.0 / 24.0,
        1.0 / 6.0,
        0.5,
    ];
    let xc = x.max(-708.0);
    let t = xc * std::f64::consts::LOG2_E + SHIFTER;
    let n = t - SHIFTER;
    let r = (xc - n * LN2_HI) - n * LN2_LO;
    let mut p = C[0];
    for c in &C[1..] {
        p = p * r + c;
    }
    let er = (p * r * r + r) + 1.0;
    // n is in [−1022, 0]: its biased exponent is the low bits of t plus 1023.
    let k = (t.to_bits() as i64).wrapping_sub(SHIFTER.to_bits() as i64);
    let two_n = f64::from_bits(((k + 1023) as u64) << 52);
    if x < -708.0 {
        0.0
    } else {
        er * two_n
    }
}

/// The number k of test points in `d` (k × n_d for `kernel`), after checking that every output
/// buffer (name, buffer, values per point) holds k times its values per point; errors name the
/// argument. Shared by the exact and the sparse GPs' predictions.
pub(crate) fn check_io(kernel: &SeArd, d: &[f64], outs: &[(&str, &[f64], usize)]) -> Result<usize> {
    let k = kernel.count_points("d", d)?;
    for &(arg, buf, per_point) in outs {
        if buf.len() != k * per_point {
            return Err(Error::invalid(
                arg,
                format!(
                    "output buffer needs {} values, has {}",
                    k * per_point,
                    buf.len()
                ),
            ));
        }
    }
    Ok(k)
}

/// log p(y | D, θ) and, if `eval_gradient`, its gradient w.r.t. θ = log([σ_f, φ_1..φ_nd, σ_ε])
/// (empty otherwise). `x` is N × n_d row-major with n_d = `theta.len() - 2`.
pub fn log_marginal_likelihood(
    x: &[f64],
    y: &[f64],
    theta: &[f64],
    eval_gradient: bool,
) -> Result<(f64, Vec<f64>)> {
    let gp = Gp::new(x, y, theta)?;
    let grad = if eval_gradient {
        // between the two O(N³) steps (the factorisation, K⁻¹)
        crate::interrupt::check()?;
        gp.log_marginal_likelihood_gradient()
    } else {
        Vec::new()
    };
    Ok((gp.lml, grad))
}

/// q independent GPs on shared inputs, one per output, each with its own θ: the one prediction
/// interface (a single-output GP is the case q = 1).
///
/// With a prior mean ([`MultiGp::with_mean`]) the GPs were trained on the residuals y − m(d) and
/// every prediction adds m(d) to the means and its gradient to the mean gradients.
#[derive(Clone, Debug)]
pub struct MultiGp {
    gps: Vec<Gp>,
    mean: Option<AffineMean>,
    /// Rounding of m(d) per output on the training inputs' range (zeros without a mean).
    mean_rounding: Vec<f64>,
}

impl MultiGp {
    /// `x`: N × n_d row-major, `y`: N × q row-major, `thetas`: q × (n_d + 2) row-major.
    /// n_d is taken from `x.len() / N` with N = `y.len() / q` and q = `thetas.len() / (n_d + 2)`;
    /// they must be consistent.
    pub fn new(x: &[f64], y: &[f64], thetas: &[f64]) -> Result<Self> {
        // q · (nd + 2) = thetas.len(), N · q = y.len(), N · nd = x.len() give
        // x.len()·q² + 2·y.len()·q − y.len()·thetas.len() = 0, which has exactly one positive root,
        // so the first q found by trial is the only one.
        let (q, nd, n) = (1..=thetas.len())
            .filter(|q| thetas.len() % q == 0 && y.len() % q == 0)
            .filter_map(|q| {
                let nd = (thetas.len() / q).checked_sub(2)?;
                let n = y.len() / q;
                (nd >= 1 && n > 0 && x.len() == n * nd).then_some((q, nd, n))
            })
            .next()
            .ok_or_else(|| {
                Error::invalid(
                    "thetas",
                    format!(
                        "no q, n_d with x = N*n_d ({}), y = N*q ({}) and thetas = q*(n_d+2) ({}) values",
                        x.len(),
                        y.len(),
                        thetas.len()
                    ),
                )
            })?;
        let mut col = vec![0.0; n];
        let gps = (0..q)
            .map(|o| {
                crate::interrupt::check()?;
                for (c, row) in col.iter_mut().zip(y.chunks_exact(q)) {
                    *c = row[o];
                }
                Gp::new(x, &col, &thetas[o * (nd + 2)..(o + 1) * (nd + 2)]).map_err(|e| match e {
                    Error::InvalidInput { arg, msg } => {
                        Error::invalid(arg, format!("output {o}: {msg}"))
                    }
                    Error::Numerical(msg) => Error::numerical(format!("output {o}: {msg}")),
                    e @ Error::Interrupted(_) => e,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self::bundle(gps))
    }

    fn bundle(gps: Vec<Gp>) -> Self {
        let q = gps.len();
        MultiGp {
            gps,
            mean: None,
            mean_rounding: vec![0.0; q],
        }
    }

    /// The same GPs with the prior mean `mean` (q outputs on n_d inputs): the GPs must have
    /// been trained on the residuals y − m(d).
    pub fn with_mean(mut self, mean: AffineMean) -> Result<Self> {
        mean.check_shape(self.n_outputs(), self.dim())?;
        self.mean_rounding = mean.roundings(self.gps[0].x_train());
        self.mean = Some(mean);
        Ok(self)
    }

    /// The prior mean, if any.
    pub fn mean(&self) -> Option<&AffineMean> {
        self.mean.as_ref()
    }

    /// Bundles fitted GPs; they must share the input dimension and the training inputs.
    pub fn from_gps(gps: Vec<Gp>) -> Result<Self> {
        let Some(first) = gps.first() else {
            return Err(Error::invalid("gps", "needs at least one GP"));
        };
        if let Some(o) = gps.iter().position(|g| g.x != first.x) {
            return Err(Error::invalid(
                "gps",
                format!("GP {o} has other training inputs than GP 0"),
            ));
        }
        Ok(Self::bundle(gps))
    }

    /// Number of outputs q.
    pub fn n_outputs(&self) -> usize {
        self.gps.len()
    }

    /// Input dimension n_d.
    pub fn dim(&self) -> usize {
        self.gps[0].dim()
    }

    pub fn gps(&self) -> &[Gp] {
        &self.gps
    }

    /// [`Gp::mean_rounding`] and [`Gp::variance_rounding`] of every output into `mean` and
    /// `var` (q values each).
    pub fn rounding_into(&self, mean: &mut [f64], var: &mut [f64]) {
        for (o, g) in self.gps.iter().enumerate() {
            mean[o] = g.mean_rounding() + self.mean_rounding[o];
            var[o] = g.variance_rounding();
        }
    }

    fn check_io(&self, d: &[f64], outs: &[(&str, &[f64], usize)]) -> Result<usize> {
        check_io(&self.gps[0].kernel, d, outs)
    }

    /// For k test points `d` (k × n_d row-major) writes means and latent variances (k × q), and
    /// ∂mean/∂d, ∂var/∂d (k × q × n_d), all row-major. `ws` is reused across calls.
    pub fn predict_with_gradients_into(
        &self,
        d: &[f64],
        mean: &mut [f64],
        var: &mut [f64],
        dmean: &mut [f64],
        dvar: &mut [f64],
        ws: &mut GpWorkspace,
    ) -> Result<()> {
        let (q, nd) = (self.n_outputs(), self.dim());
        let k = self.check_io(
            d,
            &[
                ("mean", mean, q),
                ("var", var, q),
                ("dmean", dmean, q * nd),
                ("dvar", dvar, q * nd),
            ],
        )?;
        for (o, gp) in self.gps.iter().enumerate() {
            gp.predict_block(d, k, o, q, mean, Some(var), Some((dmean, dvar)), ws);
        }
        if let Some(m) = &self.mean {
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
        ws: &mut GpWorkspace,
    ) -> Result<()> {
        let q = self.n_outputs();
        let k = self.check_io(d, &[("mean", mean, q), ("var", var, q)])?;
        for (o, gp) in self.gps.iter().enumerate() {
            gp.predict_block(d, k, o, q, mean, Some(var), None, ws);
        }
        if let Some(m) = &self.mean {
            m.add_values(d, mean);
        }
        Ok(())
    }

    /// Means only (k × q), O(N) per point and output.
    pub fn predict_mean_into(
        &self,
        d: &[f64],
        mean: &mut [f64],
        ws: &mut GpWorkspace,
    ) -> Result<()> {
        let q = self.n_outputs();
        let k = self.check_io(d, &[("mean", mean, q)])?;
        for (o, gp) in self.gps.iter().enumerate() {
            gp.predict_block(d, k, o, q, mean, None, None, ws);
        }
        if let Some(m) = &self.mean {
            m.add_values(d, mean);
        }
        Ok(())
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A single GP as the one-output case of `MultiGp` (the only prediction interface).
    fn one(gp: &Gp) -> MultiGp {
        MultiGp::from_gps(vec![gp.clone()]).unwrap()
    }
    use nalgebra::{DMatrix, DVector};

    /// A deterministic pseudo-random data set (LCG), N points in n_d dimensions in [-2, 2).
    pub(crate) fn data(n: usize, nd: usize, seed: u64) -> (Vec<f64>, Vec<f64>) {
        let mut s = seed;
        let mut r = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) * 4.0 - 2.0
        };
        let x: Vec<f64> = (0..n * nd).map(|_| r()).collect();
        let y = x
            .chunks_exact(nd)
            .map(|p| p.iter().map(|v| v.sin()).sum::<f64>() + 0.05 * r())
            .collect();
        (x, y)
    }

    pub(crate) fn theta(nd: usize) -> Vec<f64> {
        let mut t = vec![1.3f64.ln()];
        t.extend((0..nd).map(|l| (0.7 + 0.4 * l as f64).ln()));
        t.push(0.1f64.ln());
        t
    }

    /// Mean and variance by an independent dense computation (nalgebra Cholesky solve).
    fn dense_posterior(x: &[f64], y: &[f64], th: &[f64], d: &[f64]) -> (f64, f64) {
        let nd = th.len() - 2;
        let n = y.len();
        let k = SeArd::new(
            th[0].exp(),
            &th[1..=nd].iter().map(|t| t.exp()).collect::<Vec<_>>(),
        )
        .unwrap();
        let s2e = (2.0 * th[nd + 1]).exp();
        let km = DMatrix::from_fn(n, n, |i, j| {
            k.eval(&x[i * nd..(i + 1) * nd], &x[j * nd..(j + 1) * nd])
                + if i == j { s2e } else { 0.0 }
        });
        let ks = DVector::from_fn(n, |i, _| k.eval(d, &x[i * nd..(i + 1) * nd]));
        let chol = km.cholesky().unwrap();
        let a = chol.solve(&DVector::from_column_slice(y));
        let b = chol.solve(&ks);
        (ks.dot(&a), k.variance() - ks.dot(&b))
    }

    #[test]
    fn posterior_matches_dense_computation() {
        for nd in [1, 2, 3, 4, 6] {
            let (x, y) = data(40, nd, nd as u64);
            let th = theta(nd);
            let gp = Gp::new(&x, &y, &th).unwrap();
            assert_eq!(gp.jitter(), 0.0);
            let (d, _) = data(5, nd, 99);
            let mut ws = GpWorkspace::default();
            let (mut m, mut v) = (vec![0.0; 5], vec![0.0; 5]);
            one(&gp).predict_into(&d, &mut m, &mut v, &mut ws).unwrap();
            for j in 0..5 {
                let (me, ve) = dense_posterior(&x, &y, &th, &d[j * nd..(j + 1) * nd]);
                assert!(
                    (m[j] - me).abs() < 1e-10 * (1.0 + me.abs()),
                    "{} {}",
                    m[j],
                    me
                );
                assert!((v[j] - ve).abs() < 1e-10, "{} {}", v[j], ve);
            }
        }
    }

    #[test]
    fn substitution_matches_faers_triangular_solves() {
        // Right-hand sides of up to SMALL_RHS columns take the substitution, larger ones
        // faer's blocked solve: the same systems must agree to rounding either way.
        let nd = 2;
        let (x, y) = data(150, nd, 11);
        let gp = Gp::new(&x, &y, &theta(nd)).unwrap();
        let n = gp.n_train();
        for k in 1..=SMALL_RHS {
            let (b, _) = data(n * k, 1, 12 + k as u64);
            for tri in [Triangle::Lower, Triangle::Upper] {
                let mut ours = b.clone();
                let mut faers = b.clone();
                let mut fm = MatMut::from_column_major_slice_mut(&mut faers[..], n, k);
                match tri {
                    Triangle::Lower => {
                        solve_lower_triangular_in_place(gp.chol_ref(), fm.as_mut(), Par::Seq)
                    }
                    Triangle::Upper => {
                        solve_upper_triangular_in_place(gp.chol_ref(), fm.as_mut(), Par::Seq)
                    }
                }
                substitution(&gp.chol, n, &mut ours, tri);
                let scale = faers.iter().fold(0.0f64, |a, v| a.max(v.abs()));
                for (a, b) in ours.iter().zip(&faers) {
                    assert!((a - b).abs() <= 1e-12 * scale, "{a} vs {b} (k = {k})");
                }
            }
        }
        // Predictions one point at a time (substitution) equal those of a batch (faer).
        let k = 9;
        let (d, _) = data(k, nd, 13);
        let mut ws = GpWorkspace::default();
        let (mut m, mut v) = (vec![0.0; k], vec![0.0; k]);
        let (mut dm, mut dv) = (vec![0.0; k * nd], vec![0.0; k * nd]);
        one(&gp)
            .predict_with_gradients_into(&d, &mut m, &mut v, &mut dm, &mut dv, &mut ws)
            .unwrap();
        for j in 0..k {
            let (mut m1, mut v1, mut dm1, mut dv1) = ([0.0], [0.0], [0.0; 2], [0.0; 2]);
            let dj = &d[j * nd..(j + 1) * nd];
            one(&gp)
                .predict_with_gradients_into(dj, &mut m1, &mut v1, &mut dm1, &mut dv1, &mut ws)
                .unwrap();
            assert!((m1[0] - m[j]).abs() <= 1e-12 * m[j].abs().max(1.0));
            assert!((v1[0] - v[j]).abs() <= 1e-12, "{} vs {}", v1[0], v[j]);
            for l in 0..nd {
                assert!((dm1[l] - dm[j * nd + l]).abs() <= 1e-11);
                assert!((dv1[l] - dv[j * nd + l]).abs() <= 1e-11);
            }
        }
    }

    #[test]
    fn dispatched_and_baseline_builds_predict_identically() {
        for nd in [1, 2, 3, 5] {
            let (x, y) = data(37, nd, nd as u64);
            let gp = Gp::new(&x, &y, &theta(nd)).unwrap();
            let k = 7;
            let (d, _) = data(k, nd, 5);
            let run = |dispatched: bool| {
                let mut ws = GpWorkspace::default();
                let (mut m, mut v) = (vec![0.0; k], vec![0.0; k]);
                let (mut dm, mut dv) = (vec![0.0; k * nd], vec![0.0; k * nd]);
                let grads = Some((&mut dm[..], &mut dv[..]));
                if dispatched {
                    gp.predict_block(&d, k, 0, 1, &mut m, Some(&mut v), grads, &mut ws);
                } else {
                    gp.predict_block_impl(&d, k, 0, 1, &mut m, Some(&mut v), grads, &mut ws);
                }
                [m, v, dm, dv]
            };
            assert_eq!(run(true), run(false));
        }
    }

    #[test]
    fn input_gradients_match_finite_differences() {
        let nd = 3;
        let (x, y) = data(30, nd, 7);
        let gp = Gp::new(&x, &y, &theta(nd)).unwrap();
        let (d, _) = data(4, nd, 11);
        let k = 4;
        let mut ws = GpWorkspace::default();
        let (mut m, mut v) = (vec![0.0; k], vec![0.0; k]);
        let (mut dm, mut dv) = (vec![0.0; k * nd], vec![0.0; k * nd]);
        one(&gp)
            .predict_with_gradients_into(&d, &mut m, &mut v, &mut dm, &mut dv, &mut ws)
            .unwrap();
        let h = 1e-6;
        for l in 0..nd {
            let (mut dp, mut dmi) = (d.clone(), d.clone());
            for j in 0..k {
                dp[j * nd + l] += h;
                dmi[j * nd + l] -= h;
            }
            let (mut mp, mut vp, mut mm, mut vm) =
                (vec![0.0; k], vec![0.0; k], vec![0.0; k], vec![0.0; k]);
            one(&gp)
                .predict_into(&dp, &mut mp, &mut vp, &mut ws)
                .unwrap();
            one(&gp)
                .predict_into(&dmi, &mut mm, &mut vm, &mut ws)
                .unwrap();
            for j in 0..k {
                let fm = (mp[j] - mm[j]) / (2.0 * h);
                let fv = (vp[j] - vm[j]) / (2.0 * h);
                assert!(
                    (fm - dm[j * nd + l]).abs() < 1e-7,
                    "mean {fm} {}",
                    dm[j * nd + l]
                );
                assert!(
                    (fv - dv[j * nd + l]).abs() < 1e-7,
                    "var {fv} {}",
                    dv[j * nd + l]
                );
            }
        }
    }

    #[test]
    fn lml_gradient_matches_finite_differences() {
        let nd = 2;
        let (x, y) = data(25, nd, 3);
        let th = theta(nd);
        let (f0, g) = log_marginal_likelihood(&x, &y, &th, true).unwrap();
        assert!(f0.is_finite());
        let h = 1e-6;
        for i in 0..th.len() {
            let (mut tp, mut tm) = (th.clone(), th.clone());
            tp[i] += h;
            tm[i] -= h;
            let fp = log_marginal_likelihood(&x, &y, &tp, false).unwrap().0;
            let fm = log_marginal_likelihood(&x, &y, &tm, false).unwrap().0;
            let fd = (fp - fm) / (2.0 * h);
            assert!(
                (fd - g[i]).abs() < 1e-6 * (1.0 + fd.abs()),
                "theta[{i}]: {fd} vs {}",
                g[i]
            );
        }
    }

    #[test]
    fn lml_matches_dense_formula() {
        let nd = 2;
        let (x, y) = data(20, nd, 5);
        let th = theta(nd);
        let gp = Gp::new(&x, &y, &th).unwrap();
        let n = y.len();
        let s2e = (2.0 * th[nd + 1]).exp();
        let km = DMatrix::from_fn(n, n, |i, j| {
            gp.kernel()
                .eval(&x[i * nd..(i + 1) * nd], &x[j * nd..(j + 1) * nd])
                + if i == j { s2e } else { 0.0 }
        });
        let yv = DVector::from_column_slice(&y);
        let logdet = km.clone().cholesky().unwrap().determinant().ln();
        let want = -0.5 * yv.dot(&(&km.clone().try_inverse().unwrap() * &yv))
            - 0.5 * logdet
            - 0.5 * n as f64 * (2.0 * std::f64::consts::PI).ln();
        assert!((gp.log_marginal_likelihood() - want).abs() < 1e-9 * want.abs());
        // The exposed factor is lower triangular and reproduces K + σ_ε² I.
        let l = gp.cholesky();
        let llt = &l * l.transpose();
        for i in 0..n {
            for j in 0..n {
                assert!((llt[(i, j)] - km[(i, j)]).abs() < 1e-12);
                if j > i {
                    assert_eq!(l[(i, j)], 0.0);
                }
            }
        }
    }

    #[test]
    fn multi_gp_matches_single_gps_and_layout() {
        let (nd, q, n, k) = (2, 3, 30, 5);
        let (x, y0) = data(n, nd, 1);
        let ys: Vec<Vec<f64>> = (0..q)
            .map(|o| y0.iter().map(|v| v * (o as f64 + 1.0) + o as f64).collect())
            .collect();
        let thetas: Vec<Vec<f64>> = (0..q)
            .map(|o| theta(nd).iter().map(|t| t + 0.1 * o as f64).collect())
            .collect();
        let ymat: Vec<f64> = (0..n)
            .flat_map(|i| (0..q).map(|o| ys[o][i]).collect::<Vec<_>>())
            .collect();
        let multi = MultiGp::new(&x, &ymat, &thetas.concat()).unwrap();
        assert_eq!((multi.n_outputs(), multi.dim()), (q, nd));
        let (d, _) = data(k, nd, 4);
        let mut ws = GpWorkspace::default();
        let (mut m, mut v) = (vec![0.0; k * q], vec![0.0; k * q]);
        let (mut dm, mut dv) = (vec![0.0; k * q * nd], vec![0.0; k * q * nd]);
        multi
            .predict_with_gradients_into(&d, &mut m, &mut v, &mut dm, &mut dv, &mut ws)
            .unwrap();
        let mut mean_only = vec![0.0; k * q];
        multi
            .predict_mean_into(&d, &mut mean_only, &mut ws)
            .unwrap();
        assert_eq!(mean_only, m);
        for o in 0..q {
            let gp = Gp::new(&x, &ys[o], &thetas[o]).unwrap();
            let (mut m1, mut v1) = (vec![0.0; k], vec![0.0; k]);
            let (mut dm1, mut dv1) = (vec![0.0; k * nd], vec![0.0; k * nd]);
            one(&gp)
                .predict_with_gradients_into(&d, &mut m1, &mut v1, &mut dm1, &mut dv1, &mut ws)
                .unwrap();
            for j in 0..k {
                assert_eq!(m[j * q + o], m1[j]);
                assert_eq!(v[j * q + o], v1[j]);
                for l in 0..nd {
                    assert_eq!(dm[(j * q + o) * nd + l], dm1[j * nd + l]);
                    assert_eq!(dv[(j * q + o) * nd + l], dv1[j * nd + l]);
                }
            }
        }
        let again = MultiGp::from_gps(multi.gps().to_vec()).unwrap();
        assert_eq!(again.n_outputs(), q);
    }

    #[test]
    fn vectorised_exp_matches_libm_to_one_ulp() {
        let mut v: Vec<f64> = (0..200_001)
            .map(|i| -750.0 * (i as f64 / 200_000.0).powi(3))
            .collect();
        v.extend([
            0.0,
            -1e-300,
            -5e-324,
            -1e-12,
            -0.5 * std::f64::consts::LN_2,
            -708.0,
            -708.5,
        ]);
        let mut out = v.clone();
        scaled_exp(&mut out, 1.0);
        for (&x, &e) in v.iter().zip(&out) {
            let want = x.exp();
            if x < -708.0 {
                assert!(e == 0.0 && want < 4e-308, "x = {x}");
            } else {
                let ulp = f64::EPSILON * want;
                assert!((e - want).abs() <= ulp, "x = {x}: {e} vs {want}");
            }
        }
        assert_eq!(exp_nonpositive(0.0), 1.0);
    }

    #[test]
    fn duplicated_inputs_use_jitter_and_stay_finite() {
        // Five copies of one point, noise-free: K + σ_ε² I is singular to machine precision.
        let x = vec![0.5; 5];
        let y = vec![1.0; 5];
        let th = [0.0, 0.0, -40.0];
        let gp = Gp::new(&x, &y, &th).unwrap();
        assert!(gp.jitter() > 0.0 && gp.jitter() <= JITTER_MAX * (1.0 + 1e-9));
        let mut ws = GpWorkspace::default();
        let (mut m, mut v) = ([0.0], [0.0]);
        one(&gp)
            .predict_into(&[0.5], &mut m, &mut v, &mut ws)
            .unwrap();
        assert!((m[0] - 1.0).abs() < 1e-4 && v[0] >= 0.0 && v[0] < 1e-4);
    }

    #[test]
    fn bad_input_is_rejected_with_the_argument_named() {
        let (x, y) = data(10, 2, 1);
        let name = |r: Result<Gp>| match r {
            Err(Error::InvalidInput { arg, .. }) => arg,
            other => panic!("expected InvalidInput, got {other:?}"),
        };
        assert_eq!(name(Gp::new(&x, &y, &[0.0, 0.0])), "theta");
        assert_eq!(name(Gp::new(&x, &y, &[0.0, 0.0, f64::NAN, 0.0])), "theta");
        assert_eq!(name(Gp::new(&x, &y, &[800.0, 0.0, 0.0, 0.0])), "theta");
        assert_eq!(name(Gp::new(&x, &y, &[400.0, 0.0, 0.0, 0.0])), "theta");
        let huge = vec![1e200; y.len()];
        assert!(matches!(
            Gp::new(&x, &huge, &theta(2)),
            Err(Error::Numerical(_))
        ));
        assert_eq!(name(Gp::new(&x[..19], &y, &theta(2))), "x");
        assert_eq!(name(Gp::new(&x[..2], &y[..1], &theta(2))), "y");
        let mut yn = y.clone();
        yn[3] = f64::INFINITY;
        assert_eq!(name(Gp::new(&x, &yn, &theta(2))), "y");
        let gp = Gp::new(&x, &y, &theta(2)).unwrap();
        let mut ws = GpWorkspace::default();
        let (mut m, mut v) = (vec![0.0; 2], vec![0.0; 1]);
        assert!(one(&gp)
            .predict_into(&[0.0; 4], &mut m, &mut v, &mut ws)
            .is_err());
        assert!(one(&gp)
            .predict_into(&[0.0; 3], &mut m, &mut v, &mut ws)
            .is_err());
        assert!(MultiGp::new(&x, &y, &[0.0; 5]).is_err());
        assert!(MultiGp::from_gps(vec![]).is_err());
    }

    #[test]
    fn prior_mean_shifts_means_and_gradients_only() {
        let (x, y) = data(25, 2, 7);
        let thetas = [0.1, -0.2, 0.3, -2.0, 0.0, 0.1, 0.2, -1.5];
        let mut yy = Vec::new();
        for v in &y {
            yy.extend([*v, -2.0 * v]);
        }
        let plain = MultiGp::new(&x, &yy, &thetas).unwrap();
        let coef = vec![1.0, 2.0, -1.0, -3.0, 0.0, 0.5];
        let with = plain
            .clone()
            .with_mean(AffineMean::new(2, 2, coef.clone()).unwrap())
            .unwrap();
        let d = [0.3, -0.2, 1.1, 0.4, -0.7, 0.9];
        let mut ws = GpWorkspace::default();
        let run = |g: &MultiGp, ws: &mut GpWorkspace| {
            let (mut m, mut v, mut dm, mut dv) =
                (vec![0.0; 6], vec![0.0; 6], vec![0.0; 12], vec![0.0; 12]);
            g.predict_with_gradients_into(&d, &mut m, &mut v, &mut dm, &mut dv, ws)
                .unwrap();
            (m, v, dm, dv)
        };
        let (m0, v0, dm0, dv0) = run(&plain, &mut ws);
        let (m1, v1, dm1, dv1) = run(&with, &mut ws);
        assert_eq!((v0, dv0), (v1, dv1));
        for j in 0..3 {
            for o in 0..2 {
                let row = &coef[o * 3..o * 3 + 3];
                let prior = row[0] + row[1] * d[2 * j] + row[2] * d[2 * j + 1];
                assert!((m1[j * 2 + o] - m0[j * 2 + o] - prior).abs() < 1e-12);
                for l in 0..2 {
                    let i = (j * 2 + o) * 2 + l;
                    assert!((dm1[i] - dm0[i] - row[1 + l]).abs() < 1e-12);
                }
            }
        }
        let mut mo = vec![0.0; 6];
        with.predict_mean_into(&d, &mut mo, &mut ws).unwrap();
        assert_eq!(mo, m1);
        assert!(plain
            .with_mean(AffineMean::new(1, 2, vec![0.0; 3]).unwrap())
            .is_err());
    }
}
