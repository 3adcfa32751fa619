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
//! **Backward pass** (the gradient): with the adjoints G_uf = ∂F/∂Kuf, G_uu = ∂F/∂Kuu and the
//! mean weights t = P⁻¹ r (P = Kuu + Kuf Λ⁻¹ Kfu), α = Λ⁻¹ (y − Kfu t):
//! G_uf = t αᵀ − P⁻¹ Kuf Λ⁻¹ + Kuu⁻¹ Kuf diag(c_j), with c_j = 1/σ_ε² (VFE) or −2 g_j (FITC),
//! g_j = ½ (α_j² − 1/Λ_j + Kuf_jᵀ P⁻¹ Kuf_j / Λ_j²) = ∂F/∂Λ_j;
//! G_uu = −½ (t tᵀ − Kuu⁻¹ + P⁻¹) − ½ Kuu⁻¹ S Kuu⁻¹ (VFE) or + Kuu⁻¹ Kuf diag(g) Kfu Kuu⁻¹ (FITC).
//! Each θ_k and z_il enters through Kuf, Kuu and diag Kff, so ∂F/∂θ_k = Σ G_uf ∘ ∂Kuf/∂θ_k +
//! Σ G_uu ∘ ∂Kuu/∂θ_k + Σ_j ∂F/∂Kff_jj ∂Kff_jj/∂θ_k (+ ∂F/∂σ_ε² ∂σ_ε²/∂θ_k). Blocks of G_uf are
//! formed (one matrix product each, two for FITC) and contracted at once, never stored whole.
//! Cost per evaluation with gradient: about 2.5 N m² multiply-adds for VFE, 5.5 N m² for FITC.
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
    /// chol(Kuu + δI), chol(B), and t = P⁻¹ r (all as in the module docs).
    pub l: Mat<f64>,
    pub lb: Mat<f64>,
    pub t: Vec<f64>,
    /// K(Z, Z) without jitter, A = L⁻¹ Kuf Λ⁻¹ Kfu L⁻ᵀ and Σ_j q_j.
    kuu: Mat<f64>,
    a: Mat<f64>,
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
    let mut t = c;
    solve_upper_triangular_in_place(lb.transpose(), col_mut(&mut t), Par::Seq);
    solve_upper_triangular_in_place(l.transpose(), col_mut(&mut t), Par::Seq);
    Ok(Fit {
        value,
        jitter,
        l,
        lb,
        t,
        kuu,
        a,
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
    /// Σ G∘K, Σ G∘K∘(z_l − x_l)² per l, ∂F/∂Z through Kuf (m × n_d), Σ α², Σ g_j.
    gk: f64,
    gl: Vec<f64>,
    gz: Vec<f64>,
    sum_alpha2: f64,
    sum_g: f64,
    /// FITC: Kuf diag(g) Kfu.
    u: Option<Mat<f64>>,
}

/// The m × m matrices of the backward pass.
struct Adjoint {
    linv: Mat<f64>,
    kinv: Mat<f64>,
    pinv: Mat<f64>,
    /// VFE: (Kuu⁻¹ − P⁻¹)/σ_ε²; FITC: [P⁻¹; Kuu⁻¹] (2m × m).
    lhs: Mat<f64>,
}

fn adjoint(p: &Problem, fit: &Fit) -> Adjoint {
    let m = p.m();
    let mut linv = Mat::<f64>::identity(m, m);
    solve_lower_triangular_in_place(fit.l.as_ref(), linv.as_mut(), Par::Seq);
    let mut e = linv.clone();
    solve_lower_triangular_in_place(fit.lb.as_ref(), e.as_mut(), Par::Seq);
    let kinv = linv.transpose() * &linv;
    let pinv = e.transpose() * &e;
    let lhs = match p.method {
        SparseMethod::Vfe => {
            let sig2 = p.sigma_eps * p.sigma_eps;
            Mat::from_fn(m, m, |i, j| (kinv[(i, j)] - pinv[(i, j)]) / sig2)
        }
        SparseMethod::Fitc => Mat::from_fn(2 * m, m, |i, j| {
            if i < m {
                pinv[(i, j)]
            } else {
                kinv[(i - m, j)]
            }
        }),
    };
    Adjoint {
        linv,
        kinv,
        pinv,
        lhs,
    }
}

fn backward_block(p: &Problem, fit: &Fit, adj: &Adjoint, cols: Range<usize>) -> Backward {
    let (m, nd, b) = (p.m(), p.kernel.dim(), cols.len());
    let mut k = vec![0.0; m * b];
    kernel_block(p, &cols, &mut k);
    let (_, _, lam) = whiten(p, fit.l.as_ref(), &k);
    let y = &p.y[cols.clone()];
    let alpha: Vec<f64> = k
        .chunks_exact(m)
        .zip(y.iter().zip(&lam))
        .map(|(c, (yj, lj))| (yj - c.iter().zip(&fit.t).map(|(a, b)| a * b).sum::<f64>()) / lj)
        .collect();
    let rows = adj.lhs.nrows();
    let mut prod = vec![0.0; rows * b];
    matmul(
        MatMut::from_column_major_slice_mut(&mut prod[..], rows, b),
        Accum::Replace,
        adj.lhs.as_ref(),
        MatRef::from_column_major_slice(&k, m, b),
        1.0,
        Par::Seq,
    );
    // G (m × b) and g_j.
    let mut g = vec![0.0; m * b];
    let mut gj = vec![0.0; b];
    for j in 0..b {
        let (kc, pc, gc) = (
            &k[j * m..(j + 1) * m],
            &prod[j * rows..(j + 1) * rows],
            &mut g[j * m..(j + 1) * m],
        );
        match p.method {
            SparseMethod::Vfe => {
                for i in 0..m {
                    gc[i] = pc[i] + fit.t[i] * alpha[j];
                }
            }
            SparseMethod::Fitc => {
                let (y1, y2) = pc.split_at(m);
                let quad: f64 = kc.iter().zip(y1).map(|(a, b)| a * b).sum();
                let lj = lam[j];
                gj[j] = 0.5 * (alpha[j] * alpha[j] - 1.0 / lj + quad / (lj * lj));
                for i in 0..m {
                    gc[i] = fit.t[i] * alpha[j] - y1[i] / lj - 2.0 * gj[j] * y2[i];
                }
            }
        }
    }
    let mut out = contract(p, &k, &g, &cols, nd);
    out.sum_alpha2 = alpha.iter().map(|a| a * a).sum();
    out.sum_g = gj.iter().sum();
    if p.method == SparseMethod::Fitc {
        out.u = Some(weighted_gram(&k, &gj, m));
    }
    out
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
        sum_alpha2: 0.0,
        sum_g: 0.0,
        u: None,
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
    let adj = adjoint(p, fit);
    let mut acc = Backward {
        gk: 0.0,
        gl: vec![0.0; nd],
        gz: vec![0.0; m * nd],
        sum_alpha2: 0.0,
        sum_g: 0.0,
        u: None,
    };
    let mut u = Mat::<f64>::zeros(m, m);
    for_blocks(
        n,
        |cols| backward_block(p, fit, &adj, cols),
        |b| {
            acc.gk += b.gk;
            acc.gl.iter_mut().zip(&b.gl).for_each(|(a, v)| *a += v);
            acc.gz.iter_mut().zip(&b.gz).for_each(|(a, v)| *a += v);
            acc.sum_alpha2 += b.sum_alpha2;
            acc.sum_g += b.sum_g;
            if let Some(ub) = &b.u {
                u += ub;
            }
        },
    )?;
    mirror_lower(&mut u);
    let sig2 = p.sigma_eps * p.sigma_eps;
    let s2 = p.kernel.variance();
    let nf = n as f64;
    // G_uu, and the derivatives of F through diag Kff and σ_ε².
    let extra = match p.method {
        SparseMethod::Vfe => {
            // Kuu⁻¹ (Kuf Λ⁻¹ Kfu) Kuu⁻¹ = L⁻ᵀ A L⁻¹.
            let mut e = adj.linv.transpose() * &fit.a * &adj.linv;
            e.col_iter_mut()
                .for_each(|c| c.iter_mut().for_each(|v| *v *= -0.5));
            e
        }
        SparseMethod::Fitc => &adj.kinv * &u * &adj.kinv,
    };
    let t = &fit.t;
    let guu = Mat::from_fn(m, m, |i, j| {
        -0.5 * (t[i] * t[j] - adj.kinv[(i, j)] + adj.pinv[(i, j)]) + extra[(i, j)]
    });
    let (g_kdiag, g_sig2) = match p.method {
        SparseMethod::Vfe => {
            // Σ_j Kuf_jᵀ P⁻¹ Kuf_j / σ_ε⁴ = tr(P⁻¹ Kuf Kfu)/σ_ε⁴ = tr(B⁻¹ A)/σ_ε².
            let mut binv_a = fit.a.clone();
            solve_lower_triangular_in_place(fit.lb.as_ref(), binv_a.as_mut(), Par::Seq);
            solve_upper_triangular_in_place(fit.lb.transpose(), binv_a.as_mut(), Par::Seq);
            let tr_ps: f64 = (0..m).map(|i| binv_a[(i, i)]).sum();
            let g_lam = 0.5 * (acc.sum_alpha2 - nf / sig2 + tr_ps / sig2);
            let trace = (nf * s2 - fit.sum_q) / (2.0 * sig2 * sig2);
            (-nf / (2.0 * sig2), g_lam + trace)
        }
        SparseMethod::Fitc => (acc.sum_g, acc.sum_g),
    };
    let w = p.kernel.inv_lengthscales_sq();
    let mut gz = acc.gz;
    let (gk_uu, gl_uu) = contract_uu(p, &guu, &fit.kuu, &mut gz);
    let mut grad = vec![0.0; nd + 2];
    grad[0] = 2.0 * (acc.gk + gk_uu) + 2.0 * s2 * g_kdiag;
    for l in 0..nd {
        grad[1 + l] = w[l] * (acc.gl[l] + gl_uu[l]);
    }
    grad[nd + 1] = 2.0 * sig2 * g_sig2;
    if grad.iter().chain(&gz).any(|v| !v.is_finite()) {
        return Err(Error::numerical(
            "the sparse GP's objective gradient is not finite",
        ));
    }
    Ok((grad, gz))
}
