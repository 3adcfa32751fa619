//! The training objective of a sparse GP (the VFE bound or FITC's log marginal likelihood, see
//! the module docs of `sparse`) and its analytic gradient w.r.t. θ and the inducing inputs Z.
//!
//! **Forward pass** (a fit and every objective evaluation): with L = chol(Kuu + δI) the data are
//! streamed in blocks of columns of Kuf; each block is whitened, V = L⁻¹ Kuf (q_j = ‖V_j‖² is
//! the diagonal of Qff, and Λ_j = σ_f² − q_j + σ_ε² for FITC), and adds to A = V Λ⁻¹ Vᵀ and
//! V Λ⁻¹ y. Then B = I + A = L_B L_Bᵀ, c = L_B⁻¹ V Λ⁻¹ y and
//!
//! F = −N/2 log 2π − ½ Σ log Λ_j − Σ log L_B,ii − ½ yᵀΛ⁻¹y + ½ cᵀc − [VFE] Σ_j (σ_f² − q_j)/(2σ_ε²).
//!
//! Whitening each block before squaring (as GPflow's SGPR does) keeps B positive definite to
//! working precision even when Kuu is ill-conditioned; forming Kuf Λ⁻¹ Kfu first and whitening
//! afterwards does not.
//!
//! **Backward pass** (the gradient), in the whitened quantities, with no explicit inverse of Kuu
//! or P: with β = B⁻¹ V Λ⁻¹ y and the adjoint Ā = ∂F/∂A = −½ (B⁻¹ + β βᵀ) (B ⪰ I is well
//! conditioned), each block gives
//! ∂F/∂Λ⁻¹_j = V_jᵀ Ā V_j + (V_jᵀ β) y_j − ½ y_j², ∂F/∂Λ_j = −½/Λ_j − Λ_j⁻² ∂F/∂Λ⁻¹_j and
//! V̄_j = ∂F/∂V_j = 2 Ā V_j / Λ_j + β y_j / Λ_j + [VFE] V_j/σ_ε² − [FITC] 2 (∂F/∂Λ_j) V_j.
//! Through V = L⁻¹ Kuf and L = chol(Kuu + δI): G_uf = ∂F/∂Kuf = L⁻ᵀ V̄ (one triangular solve per
//! block) and G_uu = ∂F/∂Kuu = −L⁻ᵀ Φ(V̄ Vᵀ) L⁻¹, symmetrised, where Φ keeps the lower triangle
//! and halves the diagonal (the adjoint of a Cholesky factor). Each θ_k and z_il enters through
//! Kuf, Kuu and diag Kff, so ∂F/∂θ_k = Σ G_uf ∘ ∂Kuf/∂θ_k + Σ G_uu ∘ ∂Kuu/∂θ_k +
//! Σ_j ∂F/∂Kff_jj ∂Kff_jj/∂θ_k (+ ∂F/∂σ_ε² ∂σ_ε²/∂θ_k). Forming Kuu⁻¹ and P⁻¹ instead and
//! subtracting them loses the gradient when Kuu is ill-conditioned (errors of order one at
//! cond(Kuu) ≈ 1e10) while the objective stays accurate. Blocks of G_uf are formed and
//! contracted at once, never stored whole. Cost per evaluation with gradient: about 4 N m²
//! multiply-adds.
//!
//! Blocks run in parallel (rayon) in waves of [`WAVE`]; their sums are added in block order, so
//! results are identical whatever the number of threads. An interrupt check runs between waves.

use std::ops::Range;

use faer::linalg::matmul::matmul;
use faer::linalg::matmul::triangular::{self, BlockStructure};
use faer::linalg::triangular_solve::{
    solve_lower_triangular_in_place, solve_upper_triangular_in_place,
};
use faer::{Accum, Mat, MatMut, MatRef, Par};
use rayon::prelude::*;

use super::{dispatch, Problem, SparseMethod, JITTER_START, JITTER_STEPS, PIVOT_FLOOR};
use crate::error::{Error, Result};
use crate::gp::kernel_column;

/// Columns of Kuf per block.
const BLOCK: usize = 512;
/// Blocks per parallel wave.
const WAVE: usize = 16;

/// The objective at one θ and Z, with its gradients (empty unless asked for).
#[derive(Clone, Debug)]
pub struct SparseObjective {
    pub value: f64,
    /// ∂F/∂θ, θ = log([σ_f, φ_1..φ_nd, σ_ε]).
    pub grad_theta: Vec<f64>,
    /// ∂F/∂Z, m × n_d row-major.
    pub grad_z: Vec<f64>,
    pub jitter: f64,
}

/// The result of a forward pass: the objective and every factor the predictions and the
/// gradient use.
pub(crate) struct Fit {
    pub value: f64,
    pub jitter: f64,
    /// chol(Kuu + δI), chol(B), t = P⁻¹ r (as in the module docs) and β = B⁻¹ V Λ⁻¹ y = Lᵀ t.
    pub l: Mat<f64>,
    pub lb: Mat<f64>,
    pub t: Vec<f64>,
    beta: Vec<f64>,
    /// K(Z, Z) without jitter and Σ_j q_j.
    kuu: Mat<f64>,
    sum_q: f64,
}

/// The training objective of the sparse GP on `x` (N × n_d), `y` (N) with inducing inputs `z`
/// (m × n_d) at θ = log([σ_f, φ.., σ_ε]); with `eval_gradient` also ∂F/∂θ and ∂F/∂Z. Errors as
/// [`super::SparseGp::new`].
pub fn sparse_objective(
    x: &[f64],
    y: &[f64],
    z: &[f64],
    theta: &[f64],
    method: SparseMethod,
    eval_gradient: bool,
) -> Result<SparseObjective> {
    let p = Problem::new(x, y, z, theta, method)?;
    let fit = fit(&p)?;
    let (grad_theta, grad_z) = if eval_gradient {
        crate::interrupt::check()?;
        gradient(&p, &fit)?
    } else {
        (Vec::new(), Vec::new())
    };
    Ok(SparseObjective {
        value: fit.value,
        grad_theta,
        grad_z,
        jitter: fit.jitter,
    })
}

/// Runs `f` on every block of columns of the N training points, in parallel waves, and hands
/// the results to `sink` in block order.
fn for_blocks<T: Send>(
    n: usize,
    f: impl Fn(Range<usize>) -> T + Sync,
    mut sink: impl FnMut(T),
) -> Result<()> {
    let blocks: Vec<Range<usize>> = (0..n)
        .step_by(BLOCK)
        .map(|s| s..(s + BLOCK).min(n))
        .collect();
    for wave in blocks.chunks(WAVE) {
        crate::interrupt::check()?;
        let parts: Vec<T> = if wave.len() == 1 {
            vec![f(wave[0].clone())]
        } else {
            wave.par_iter().map(|r| f(r.clone())).collect()
        };
        parts.into_iter().for_each(&mut sink);
    }
    Ok(())
}

/// Kuf for the training points `cols` into `out` (m × b column-major).
fn kernel_block(p: &Problem, cols: &Range<usize>, out: &mut [f64]) {
    dispatch(
        #[inline(always)]
        || kernel_block_impl(p, cols, out),
    )
}

#[inline(always)]
fn kernel_block_impl(p: &Problem, cols: &Range<usize>, out: &mut [f64]) {
    let (m, nd) = (p.m(), p.kernel.dim());
    let (w, s2) = (p.kernel.inv_lengthscales_sq(), p.kernel.variance());
    let x = &p.x[cols.start * nd..cols.end * nd];
    for (xj, col) in x.chunks_exact(nd).zip(out.chunks_exact_mut(m)) {
        kernel_column(p.z, xj, w, s2, col);
    }
}

/// V = L⁻¹ K of a block's columns `k` (m × b), q_j = ‖V_j‖² and Λ_j: σ_ε² (VFE) or
/// max(σ_f² − q_j, 0) + σ_ε² (FITC).
fn whiten(p: &Problem, l: MatRef<'_, f64>, k: &[f64]) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let m = p.m();
    let b = k.len() / m;
    let sig2 = p.sigma_eps * p.sigma_eps;
    let mut v = k.to_vec();
    solve_lower_triangular_in_place(
        l,
        MatMut::from_column_major_slice_mut(&mut v[..], m, b),
        Par::Seq,
    );
    let q: Vec<f64> = v
        .chunks_exact(m)
        .map(|c| c.iter().map(|a| a * a).sum())
        .collect();
    let s2 = p.kernel.variance();
    let lam = match p.method {
        SparseMethod::Vfe => vec![sig2; b],
        SparseMethod::Fitc => q.iter().map(|qj| (s2 - qj).max(0.0) + sig2).collect(),
    };
    (v, q, lam)
}

/// The lower triangle of K diag(s) Kᵀ (zeros above: see [`mirror_lower`]) for K (m × b
/// column-major) and b weights s.
fn weighted_gram(k: &[f64], s: &[f64], m: usize) -> Mat<f64> {
    let b = s.len();
    let mut ks = k.to_vec();
    for (c, sj) in ks.chunks_exact_mut(m).zip(s) {
        c.iter_mut().for_each(|v| *v *= sj);
    }
    let mut out = Mat::zeros(m, m);
    let kr = MatRef::from_column_major_slice(k, m, b);
    let ksr = MatRef::from_column_major_slice(&ks, m, b);
    triangular::matmul(
        out.as_mut(),
        BlockStructure::TriangularLower,
        Accum::Replace,
        ksr,
        BlockStructure::Rectangular,
        kr.transpose(),
        BlockStructure::Rectangular,
        1.0,
        Par::Seq,
    );
    out
}

/// Copies the lower triangle of `a` into its upper triangle.
fn mirror_lower(a: &mut Mat<f64>) {
    for j in 0..a.ncols() {
        for i in 0..j {
            a[(i, j)] = a[(j, i)];
        }
    }
}

/// One block's share of the forward pass: V Λ⁻¹ Vᵀ (lower triangle), V Λ⁻¹ y, Σ log Λ_j,
/// Σ y_j²/Λ_j, Σ q_j.
struct Forward {
    a: Mat<f64>,
    r: Vec<f64>,
    sum_log_lam: f64,
    sum_y2_lam: f64,
    sum_q: f64,
}

fn forward_block(p: &Problem, l: MatRef<'_, f64>, cols: Range<usize>) -> Forward {
    let m = p.m();
    let mut k = vec![0.0; m * cols.len()];
    kernel_block(p, &cols, &mut k);
    let (v, q, lam) = whiten(p, l, &k);
    let inv: Vec<f64> = lam.iter().map(|v| 1.0 / v).collect();
    let y = &p.y[cols];
    let mut r = vec![0.0; m];
    for ((c, yj), ij) in v.chunks_exact(m).zip(y).zip(&inv) {
        let a = yj * ij;
        r.iter_mut().zip(c).for_each(|(ri, ci)| *ri += a * ci);
    }
    Forward {
        a: weighted_gram(&v, &inv, m),
        r,
        sum_log_lam: lam.iter().map(|v| v.ln()).sum(),
        sum_y2_lam: y.iter().zip(&inv).map(|(a, b)| a * a * b).sum(),
        sum_q: q.iter().sum(),
    }
}

/// The forward pass: factors Kuu under the jitter policy, streams the data, and returns the
/// objective with the factors.
pub(crate) fn fit(p: &Problem) -> Result<Fit> {
    let (n, m) = (p.n(), p.m());
    let kuu = p.kernel.gram(p.z);
    let (l, jitter) = factor_kuu(&kuu, p.kernel.variance())?;
    let mut a = Mat::<f64>::zeros(m, m);
    let mut c = vec![0.0; m];
    let (mut sum_log_lam, mut sum_y2_lam, mut sum_q) = (0.0, 0.0, 0.0);
    for_blocks(
        n,
        |cols| forward_block(p, l.as_ref(), cols),
        |f| {
            a += &f.a;
            c.iter_mut().zip(&f.r).for_each(|(x, y)| *x += y);
            sum_log_lam += f.sum_log_lam;
            sum_y2_lam += f.sum_y2_lam;
            sum_q += f.sum_q;
        },
    )?;
    mirror_lower(&mut a);
    let b = Mat::from_fn(m, m, |i, j| a[(i, j)] + if i == j { 1.0 } else { 0.0 });
    let lb = cholesky(&b).ok_or_else(|| {
        Error::numerical(
            "B = I + L^-1 Kuf Lambda^-1 Kfu L^-T is not numerically positive definite \
             (sigma_eps far too small next to sigma_f)",
        )
    })?;
    solve_lower_triangular_in_place(lb.as_ref(), col_mut(&mut c), Par::Seq);
    let sig2 = p.sigma_eps * p.sigma_eps;
    let mut value = -0.5 * n as f64 * (2.0 * std::f64::consts::PI).ln()
        - 0.5 * sum_log_lam
        - (0..m).map(|i| lb[(i, i)].ln()).sum::<f64>()
        - 0.5 * sum_y2_lam
        + 0.5 * c.iter().map(|v| v * v).sum::<f64>();
    if p.method == SparseMethod::Vfe {
        value -= (n as f64 * p.kernel.variance() - sum_q) / (2.0 * sig2);
    }
    if !value.is_finite() {
        return Err(Error::numerical(
            "the sparse GP's training objective is not finite (ill-conditioned Kuu or data)",
        ));
    }
    let mut beta = c;
    solve_upper_triangular_in_place(lb.transpose(), col_mut(&mut beta), Par::Seq);
    let mut t = beta.clone();
    solve_upper_triangular_in_place(l.transpose(), col_mut(&mut t), Par::Seq);
    Ok(Fit {
        value,
        jitter,
        l,
        lb,
        t,
        beta,
        kuu,
        sum_q,
    })
}

fn col_mut(v: &mut [f64]) -> MatMut<'_, f64> {
    let n = v.len();
    MatMut::from_column_major_slice_mut(v, n, 1)
}

/// The lower Cholesky factor of a symmetric positive definite `a` (zeros above the diagonal),
/// None if a pivot is not positive.
pub(super) fn cholesky(a: &Mat<f64>) -> Option<Mat<f64>> {
    use faer::dyn_stack::{MemBuffer, MemStack};
    use faer::linalg::cholesky::llt;
    let n = a.nrows();
    let mut f = a.clone();
    let mut mem = MemBuffer::new(llt::factor::cholesky_in_place_scratch::<f64>(
        n,
        Par::Seq,
        Default::default(),
    ));
    llt::factor::cholesky_in_place(
        f.as_mut(),
        Default::default(),
        Par::Seq,
        MemStack::new(&mut mem),
        Default::default(),
    )
    .ok()?;
    for j in 0..n {
        for i in 0..j {
            f[(i, j)] = 0.0;
        }
    }
    Some(f)
}

/// chol(Kuu + δI) under the jitter policy of the module `sparse`; returns (L, δ).
pub(super) fn factor_kuu(kuu: &Mat<f64>, signal_var: f64) -> Result<(Mat<f64>, f64)> {
    let m = kuu.nrows();
    for attempt in 0..=JITTER_STEPS {
        let jitter = if attempt == 0 {
            0.0
        } else {
            JITTER_START * signal_var * 10f64.powi(attempt - 1)
        };
        let mut a = kuu.clone();
        for i in 0..m {
            a[(i, i)] += jitter;
        }
        if let Some(l) = cholesky(&a) {
            if (0..m).all(|i| l[(i, i)] * l[(i, i)] >= PIVOT_FLOOR * signal_var) {
                return Ok((l, jitter));
            }
        }
    }
    Err(Error::numerical(format!(
        "K(Z, Z) is not positive definite even with a diagonal jitter of {:.3e} (m = {m}, \
         sigma_f^2 = {signal_var:.3e}); check for duplicated inducing points",
        JITTER_START * signal_var * 10f64.powi(JITTER_STEPS - 1)
    )))
}

/// One block's share of the backward pass: contractions of G_uf with ∂Kuf.
struct Backward {
    /// Σ G∘K, Σ G∘K∘(z_l − x_l)² per l, ∂F/∂Z through Kuf (m × n_d).
    gk: f64,
    gl: Vec<f64>,
    gz: Vec<f64>,
    /// Σ_j ∂F/∂Λ_j, and the same over the points where FITC's Λ_j is not clipped at σ_ε².
    sum_lambar: f64,
    sum_lambar_open: f64,
    /// V̄ Vᵀ of the block (m × m), for G_uu.
    vbar_vt: Mat<f64>,
}

/// Ā = −½ (B⁻¹ + β βᵀ) (module docs).
fn abar(fit: &Fit) -> Mat<f64> {
    let m = fit.lb.nrows();
    let mut e = Mat::<f64>::identity(m, m);
    solve_lower_triangular_in_place(fit.lb.as_ref(), e.as_mut(), Par::Seq);
    let binv = e.transpose() * &e;
    Mat::from_fn(m, m, |i, j| {
        -0.5 * (binv[(i, j)] + fit.beta[i] * fit.beta[j])
    })
}

fn backward_block(p: &Problem, fit: &Fit, abar: &Mat<f64>, cols: Range<usize>) -> Backward {
    let (m, nd, b) = (p.m(), p.kernel.dim(), cols.len());
    let mut k = vec![0.0; m * b];
    kernel_block(p, &cols, &mut k);
    let (v, q, lam) = whiten(p, fit.l.as_ref(), &k);
    let y = &p.y[cols.clone()];
    let sig2 = p.sigma_eps * p.sigma_eps;
    let s2 = p.kernel.variance();
    let mut av = vec![0.0; m * b];
    matmul(
        MatMut::from_column_major_slice_mut(&mut av[..], m, b),
        Accum::Replace,
        abar.as_ref(),
        MatRef::from_column_major_slice(&v, m, b),
        1.0,
        Par::Seq,
    );
    // V̄ (m × b), column by column.
    let mut vbar = vec![0.0; m * b];
    let (mut sum_lambar, mut sum_lambar_open) = (0.0, 0.0);
    for j in 0..b {
        let (vc, ac) = (&v[j * m..(j + 1) * m], &av[j * m..(j + 1) * m]);
        let il = 1.0 / lam[j];
        let u: f64 = vc.iter().zip(&fit.beta).map(|(a, c)| a * c).sum();
        let s: f64 = vc.iter().zip(ac).map(|(a, c)| a * c).sum();
        let ilbar = s + u * y[j] - 0.5 * y[j] * y[j];
        let lambar = -0.5 * il - ilbar * il * il;
        sum_lambar += lambar;
        let open = s2 - q[j] > 0.0;
        if open {
            sum_lambar_open += lambar;
        }
        let own = match p.method {
            SparseMethod::Vfe => 1.0 / sig2,
            SparseMethod::Fitc if open => -2.0 * lambar,
            SparseMethod::Fitc => 0.0,
        };
        let vb = &mut vbar[j * m..(j + 1) * m];
        for i in 0..m {
            vb[i] = 2.0 * ac[i] * il + fit.beta[i] * (y[j] * il) + own * vc[i];
        }
    }
    let mut vbar_vt = Mat::<f64>::zeros(m, m);
    matmul(
        vbar_vt.as_mut(),
        Accum::Replace,
        MatRef::from_column_major_slice(&vbar, m, b),
        MatRef::from_column_major_slice(&v, m, b).transpose(),
        1.0,
        Par::Seq,
    );
    // G_uf = L⁻ᵀ V̄.
    solve_upper_triangular_in_place(
        fit.l.transpose(),
        MatMut::from_column_major_slice_mut(&mut vbar[..], m, b),
        Par::Seq,
    );
    let mut out = contract(p, &k, &vbar, &cols, nd);
    out.sum_lambar = sum_lambar;
    out.sum_lambar_open = sum_lambar_open;
    out.vbar_vt = vbar_vt;
    out
}

/// G_uu = −L⁻ᵀ Φ(V̄ Vᵀ) L⁻¹, symmetrised (module docs).
fn guu(fit: &Fit, vbar_vt: &Mat<f64>) -> Mat<f64> {
    let m = vbar_vt.nrows();
    let mut x = Mat::from_fn(m, m, |i, j| match i.cmp(&j) {
        std::cmp::Ordering::Greater => vbar_vt[(i, j)],
        std::cmp::Ordering::Equal => 0.5 * vbar_vt[(i, j)],
        std::cmp::Ordering::Less => 0.0,
    });
    // X ← L⁻ᵀ Φ, then X ← (L⁻ᵀ Xᵀ)ᵀ = X L⁻¹.
    solve_upper_triangular_in_place(fit.l.transpose(), x.as_mut(), Par::Seq);
    let mut xt = x.transpose().to_owned();
    solve_upper_triangular_in_place(fit.l.transpose(), xt.as_mut(), Par::Seq);
    Mat::from_fn(m, m, |i, j| -0.5 * (xt[(j, i)] + xt[(i, j)]))
}

/// The contractions Σ G∘K, Σ G∘K∘(z_l − x_l)² and ∂F/∂Z = Σ_j G_ij K_ij (−w_l)(z_il − x_jl) of a
/// block (K, G: m × b column-major).
fn contract(p: &Problem, k: &[f64], g: &[f64], cols: &Range<usize>, nd: usize) -> Backward {
    dispatch(
        #[inline(always)]
        || contract_impl(p, k, g, cols, nd),
    )
}

#[inline(always)]
fn contract_impl(p: &Problem, k: &[f64], g: &[f64], cols: &Range<usize>, nd: usize) -> Backward {
    let m = p.m();
    let w = p.kernel.inv_lengthscales_sq();
    let mut out = Backward {
        gk: 0.0,
        gl: vec![0.0; nd],
        gz: vec![0.0; m * nd],
        sum_lambar: 0.0,
        sum_lambar_open: 0.0,
        vbar_vt: Mat::new(),
    };
    let x = &p.x[cols.start * nd..cols.end * nd];
    for (j, xj) in x.chunks_exact(nd).enumerate() {
        for i in 0..m {
            let gk = g[j * m + i] * k[j * m + i];
            out.gk += gk;
            let zi = &p.z[i * nd..(i + 1) * nd];
            for l in 0..nd {
                let diff = zi[l] - xj[l];
                out.gl[l] += gk * diff * diff;
                out.gz[i * nd + l] -= gk * diff * w[l];
            }
        }
    }
    out
}

/// The contractions of G_uu with ∂Kuu: (Σ G∘K, Σ G∘K∘(z_il − z_jl)² per l), and ∂F/∂Z through
/// Kuu added to `gz` (K symmetric: z_i enters row and column i).
fn contract_uu(p: &Problem, guu: &Mat<f64>, kuu: &Mat<f64>, gz: &mut [f64]) -> (f64, Vec<f64>) {
    let (m, nd) = (p.m(), p.kernel.dim());
    let w = p.kernel.inv_lengthscales_sq();
    let (mut gk, mut gl) = (0.0, vec![0.0; nd]);
    for i in 0..m {
        let zi = &p.z[i * nd..(i + 1) * nd];
        for j in 0..m {
            let g = guu[(i, j)] * kuu[(i, j)];
            gk += g;
            let zj = &p.z[j * nd..(j + 1) * nd];
            for l in 0..nd {
                let diff = zi[l] - zj[l];
                gl[l] += g * diff * diff;
                gz[i * nd + l] -= 2.0 * g * diff * w[l];
            }
        }
    }
    (gk, gl)
}

/// ∂F/∂θ and ∂F/∂Z from a forward pass (module docs).
fn gradient(p: &Problem, fit: &Fit) -> Result<(Vec<f64>, Vec<f64>)> {
    let (n, m, nd) = (p.n(), p.m(), p.kernel.dim());
    let abar = abar(fit);
    let (mut gk, mut gl, mut gz) = (0.0, vec![0.0; nd], vec![0.0; m * nd]);
    let (mut sum_lambar, mut sum_lambar_open) = (0.0, 0.0);
    let mut vbar_vt = Mat::<f64>::zeros(m, m);
    for_blocks(
        n,
        |cols| backward_block(p, fit, &abar, cols),
        |b| {
            gk += b.gk;
            gl.iter_mut().zip(&b.gl).for_each(|(a, v)| *a += v);
            gz.iter_mut().zip(&b.gz).for_each(|(a, v)| *a += v);
            sum_lambar += b.sum_lambar;
            sum_lambar_open += b.sum_lambar_open;
            vbar_vt += &b.vbar_vt;
        },
    )?;
    let guu = guu(fit, &vbar_vt);
    let sig2 = p.sigma_eps * p.sigma_eps;
    let s2 = p.kernel.variance();
    let nf = n as f64;
    // The derivatives of F through diag Kff (= σ_f²) and σ_ε².
    let (g_kdiag, g_sig2) = match p.method {
        SparseMethod::Vfe => (
            -nf / (2.0 * sig2),
            sum_lambar + (nf * s2 - fit.sum_q) / (2.0 * sig2 * sig2),
        ),
        SparseMethod::Fitc => (sum_lambar_open, sum_lambar),
    };
    let w = p.kernel.inv_lengthscales_sq();
    let (gk_uu, gl_uu) = contract_uu(p, &guu, &fit.kuu, &mut gz);
    let mut grad = vec![0.0; nd + 2];
    // The jitter δ is a multiple of σ_f² (module `sparse`): ∂(Kuu + δI)/∂log σ_f = 2 Kuu + 2δ I.
    let trace_guu: f64 = (0..m).map(|i| guu[(i, i)]).sum();
    grad[0] = 2.0 * (gk + gk_uu) + 2.0 * s2 * g_kdiag + 2.0 * fit.jitter * trace_guu;
    for l in 0..nd {
        grad[1 + l] = w[l] * (gl[l] + gl_uu[l]);
    }
    grad[nd + 1] = 2.0 * sig2 * g_sig2;
    if grad.iter().chain(&gz).any(|v| !v.is_finite()) {
        return Err(Error::numerical(
            "the sparse GP's objective gradient is not finite",
        ));
    }
    Ok((grad, gz))
}
