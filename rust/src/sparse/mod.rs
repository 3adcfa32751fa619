//! Sparse (inducing-point) GP regression with the SE-ARD kernel, for training sets of thousands to
//! 10⁵ points per GP (docs/user_guide/gaussian_processes.rst, *Sparse GPs*).
//!
//! [`SparseGp`] is one zero-mean output summarised by m inducing inputs Z (m × n_d): with
//! Kuu = K(Z, Z) (+ jitter), Kuf = K(Z, X), Qff = Kfu Kuu⁻¹ Kuf and the diagonal noise
//! Λ = σ_ε² I (VFE, Titsias 2009) or Λ = diag(Kff − Qff) + σ_ε² I (FITC, Snelson & Ghahramani
//! 2006), the training objective is
//!
//! F = log N(y | 0, Qff + Λ) − [VFE only] tr(Kff − Qff) / (2σ_ε²),
//!
//! the collapsed variational bound on the log marginal likelihood (VFE) or FITC's own log
//! marginal likelihood, computed in O(N m²) time and O(N + m²) memory (`objective.rs`: the data
//! are streamed in column blocks, in parallel, and the blocks summed in a fixed order so results
//! do not depend on the number of threads). With P = Kuu + Kuf Λ⁻¹ Kfu the prediction at d* is
//! mean k*ᵀ P⁻¹ Kuf Λ⁻¹ y and latent variance σ_f² − k*ᵀ (Kuu⁻¹ − P⁻¹) k*, O(m) and O(m²) per
//! point (`predict.rs`); the variance returns to σ_f² far from Z (DTC/SoR's would fall to 0).
//! [`SparseMultiGp`] is q such GPs on shared training inputs, each with its own θ and Z: the
//! sparse counterpart of [`crate::gp::MultiGp`], with the same prediction methods.
//! `inducing.rs` chooses Z from the data by greedy conditional-variance selection;
//! `posterior.rs` gives the posterior of the inducing outputs u = f(Z), the weights of the
//! equivalent recursive GP (`crate::rgp::Rgp::from_sparse`); `learning.rs` replaces it (a GP that
//! keeps learning online) and gives the mean's derivative with respect to it.
//!
//! **Jitter policy.** Kuu is factored as is if its Cholesky factorisation succeeds with every
//! pivot L_ii² ≥ 10⁻¹¹ σ_f² (smaller pivots mean inducing points the others nearly determine, and
//! a factor too ill-conditioned for the explicit inverses of the gradient). Otherwise a diagonal
//! jitter δ = 10⁻¹⁰ σ_f², growing tenfold up to 10⁻⁶ σ_f², is added to Kuu (not to the noise); the
//! jitter used is recorded ([`SparseGp::jitter`]) and is part of the model (every later
//! prediction and the objective use Kuu + δI). If the largest fails, a `Numerical` error results.

mod inducing;
mod learning;
mod objective;
mod posterior;
mod predict;

use std::sync::Arc;

use faer::Mat;

use crate::error::{check_finite, Error, Result};
use crate::kernel::SeArd;
use crate::mean::AffineMean;

pub use inducing::select_inducing;
pub use objective::{sparse_objective, SparseObjective};
pub use predict::SparseWorkspace;

/// The approximation of a sparse GP.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SparseMethod {
    /// Variational free energy (Titsias 2009; GPflow's SGPR): Λ = σ_ε² I and the trace term.
    Vfe,
    /// Fully independent training conditional (Snelson & Ghahramani 2006; GPflow's GPRFITC).
    Fitc,
}

impl SparseMethod {
    /// "vfe" or "fitc" (case-insensitive); an `InvalidInput` naming `method` otherwise.
    pub fn parse(name: &str) -> Result<Self> {
        match name.to_ascii_lowercase().as_str() {
            "vfe" => Ok(Self::Vfe),
            "fitc" => Ok(Self::Fitc),
            other => Err(Error::invalid(
                "method",
                format!("must be 'vfe' or 'fitc', got {other:?}"),
            )),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Vfe => "vfe",
            Self::Fitc => "fitc",
        }
    }
}

/// Smallest accepted pivot L_ii² of chol(Kuu), relative to σ_f² (module docs).
const PIVOT_FLOOR: f64 = 1e-11;
/// Relative jitters tried after a plain factorisation: 1e-10, 1e-9, …, 1e-6 (· σ_f²).
const JITTER_START: f64 = 1e-10;
const JITTER_STEPS: i32 = 5;
/// Units in the last place of σ_f² for the typical rounding error of a latent variance (as the
/// exact GP's `VARIANCE_ULPS`: the variance is σ_f² minus a quadratic form of similar size).
const VARIANCE_ULPS: f64 = 3.0;

/// The training set and hyperparameters of one sparse GP, checked: the input of [`SparseGp::new`]
/// and of [`sparse_objective`].
#[derive(Clone, Debug)]
pub(crate) struct Problem<'a> {
    pub x: &'a [f64],
    pub y: &'a [f64],
    pub z: &'a [f64],
    pub kernel: SeArd,
    pub sigma_eps: f64,
    pub method: SparseMethod,
}

impl<'a> Problem<'a> {
    /// Checks `x` (N × n_d), `y` (N), `z` (m × n_d) and θ = log([σ_f, φ.., σ_ε]); errors name the
    /// argument.
    pub fn new(
        x: &'a [f64],
        y: &'a [f64],
        z: &'a [f64],
        theta: &[f64],
        method: SparseMethod,
    ) -> Result<Self> {
        let (kernel, sigma_eps) = crate::gp::hyperparameters(theta)?;
        let nd = kernel.dim();
        crate::gp::check_training(x, y, nd)?;
        if z.is_empty() || z.len() % nd != 0 {
            return Err(Error::invalid(
                "z",
                format!(
                    "expected m >= 1 inducing points of dimension {nd}, got {} values",
                    z.len()
                ),
            ));
        }
        check_finite("z", z)?;
        Ok(Problem {
            x,
            y,
            z,
            kernel,
            sigma_eps,
            method,
        })
    }

    pub fn n(&self) -> usize {
        self.y.len()
    }

    pub fn m(&self) -> usize {
        self.z.len() / self.kernel.dim()
    }
}

/// One sparse GP: its data, θ, inducing inputs and the factors its predictions need.
#[derive(Clone, Debug)]
pub struct SparseGp {
    /// Training inputs N × n_d (shared between the outputs of a [`SparseMultiGp`]) and targets.
    x: Arc<Vec<f64>>,
    y: Vec<f64>,
    /// Inducing inputs, m × n_d row-major.
    z: Vec<f64>,
    theta: Vec<f64>,
    method: SparseMethod,
    kernel: SeArd,
    jitter: f64,
    /// chol(Kuu + δI) and chol(B), B = I + L⁻¹ Kuf Λ⁻¹ Kfu L⁻ᵀ, both lower triangular (m × m).
    l: Mat<f64>,
    lb: Mat<f64>,
    /// Mean weights t = P⁻¹ Kuf Λ⁻¹ y: the mean at d* is k(Z, d*)ᵀ t.
    t: Vec<f64>,
    objective: f64,
    mean_rounding: f64,
    /// Whether predictions give the variance given the inducing outputs, σ_f² − k*ᵀ Kuu⁻¹ k*,
    /// instead of the posterior's (`learning.rs`).
    conditional: bool,
    /// The posterior of the inducing outputs (mean, row-major covariance) that replaced the
    /// fit's, if one did (`learning.rs`): kept so that a copy rebuilt from the data is the same.
    replaced: Option<Arc<(Vec<f64>, Vec<f64>)>>,
}

impl SparseGp {
    /// Fits the factors of the GP on `x` (N × n_d), `y` (N) with inducing inputs `z` (m × n_d)
    /// and θ = log([σ_f, φ_1..φ_nd, σ_ε]). Bad input gives `InvalidInput` naming the argument; a
    /// Kuu that stays indefinite under the jitter policy gives `Numerical`.
    pub fn new(
        x: &[f64],
        y: &[f64],
        z: &[f64],
        theta: &[f64],
        method: SparseMethod,
    ) -> Result<Self> {
        Self::with_shared_inputs(Arc::new(x.to_vec()), y, z, theta, method)
    }

    fn with_shared_inputs(
        x: Arc<Vec<f64>>,
        y: &[f64],
        z: &[f64],
        theta: &[f64],
        method: SparseMethod,
    ) -> Result<Self> {
        let p = Problem::new(&x, y, z, theta, method)?;
        let fit = objective::fit(&p)?;
        let kernel = p.kernel.clone();
        let mean_rounding =
            f64::EPSILON * kernel.variance() * fit.t.iter().map(|a| a * a).sum::<f64>().sqrt();
        Ok(SparseGp {
            y: y.to_vec(),
            z: z.to_vec(),
            theta: theta.to_vec(),
            method,
            kernel,
            jitter: fit.jitter,
            l: fit.l,
            lb: fit.lb,
            t: fit.t,
            objective: fit.value,
            mean_rounding,
            conditional: false,
            replaced: None,
            x,
        })
    }

    pub fn dim(&self) -> usize {
        self.kernel.dim()
    }
    pub fn n_train(&self) -> usize {
        self.y.len()
    }
    /// Number of inducing points m.
    pub fn n_inducing(&self) -> usize {
        self.z.len() / self.dim()
    }
    pub fn theta(&self) -> &[f64] {
        &self.theta
    }
    pub fn method(&self) -> SparseMethod {
        self.method
    }
    pub fn kernel(&self) -> &SeArd {
        &self.kernel
    }
    /// Diagonal jitter added to Kuu by the jitter policy (0 if none was needed).
    pub fn jitter(&self) -> f64 {
        self.jitter
    }
    pub fn x_train(&self) -> &[f64] {
        &self.x
    }
    pub fn y_train(&self) -> &[f64] {
        &self.y
    }
    /// Inducing inputs, m × n_d row-major.
    pub fn inducing(&self) -> &[f64] {
        &self.z
    }
    /// The training objective F at this GP's θ and Z (module docs).
    pub fn objective(&self) -> f64 {
        self.objective
    }

    /// Typical absolute rounding error of a computed latent variance: as
    /// [`crate::gp::Gp::variance_rounding`], a few ulp of σ_f² (the variance is σ_f² minus
    /// quadratic forms of up to that size).
    pub fn variance_rounding(&self) -> f64 {
        VARIANCE_ULPS * f64::EPSILON * self.kernel.variance()
    }

    /// Typical absolute rounding error of a computed mean Σ_i k(z_i, d) t_i: ε·σ_f²·‖t‖₂, the
    /// analogue of [`crate::gp::Gp::mean_rounding`] with the m mean weights t in place of α.
    pub fn mean_rounding(&self) -> f64 {
        self.mean_rounding
    }
}

/// q independent sparse GPs on shared training inputs, each with its own θ and inducing inputs:
/// the sparse counterpart of [`crate::gp::MultiGp`] (see [`crate::gp_model::GpModel`]), with
/// the same optional prior mean ([`SparseMultiGp::with_mean`]).
#[derive(Clone, Debug)]
pub struct SparseMultiGp {
    gps: Vec<SparseGp>,
    mean: Option<AffineMean>,
    /// Rounding of m(d) per output on the training inputs' range (zeros without a mean).
    mean_rounding: Vec<f64>,
}

impl SparseMultiGp {
    /// `x`: N × n_d row-major, `y`: N × q row-major, `zs`: q sets of inducing inputs (m_o × n_d
    /// row-major each), `thetas`: q × (n_d + 2) row-major. Errors name the argument and output.
    pub fn new(
        x: &[f64],
        y: &[f64],
        zs: &[&[f64]],
        thetas: &[f64],
        method: SparseMethod,
    ) -> Result<Self> {
        let q = zs.len();
        if q == 0 || thetas.len() % q != 0 || y.len() % q != 0 {
            return Err(Error::invalid(
                "thetas",
                format!(
                    "{} values of theta, {} of y do not split into q = {q} outputs",
                    thetas.len(),
                    y.len()
                ),
            ));
        }
        let p = thetas.len() / q;
        let x = Arc::new(x.to_vec());
        let mut col = vec![0.0; y.len() / q];
        let gps = (0..q)
            .map(|o| {
                crate::interrupt::check()?;
                for (c, row) in col.iter_mut().zip(y.chunks_exact(q)) {
                    *c = row[o];
                }
                let theta = &thetas[o * p..(o + 1) * p];
                SparseGp::with_shared_inputs(x.clone(), &col, zs[o], theta, method)
                    .map_err(|e| for_output(e, o))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(SparseMultiGp {
            gps,
            mean: None,
            mean_rounding: vec![0.0; q],
        })
    }

    /// The same GPs with the prior mean `mean`, as [`crate::gp::MultiGp::with_mean`]: the GPs
    /// must have been trained on the residuals y − m(d).
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

    pub fn n_outputs(&self) -> usize {
        self.gps.len()
    }
    pub fn dim(&self) -> usize {
        self.gps[0].dim()
    }
    pub fn gps(&self) -> &[SparseGp] {
        &self.gps
    }
    pub fn method(&self) -> SparseMethod {
        self.gps[0].method
    }

    /// [`SparseGp::mean_rounding`] and [`SparseGp::variance_rounding`] of every output.
    pub fn rounding_into(&self, mean: &mut [f64], var: &mut [f64]) {
        for (o, g) in self.gps.iter().enumerate() {
            mean[o] = g.mean_rounding() + self.mean_rounding[o];
            var[o] = g.variance_rounding();
        }
    }
}

/// Runs `f` in a build for AVX2 when the CPU has it (detected at run time), else in the portable
/// one: the element-wise loops below (kernel exponentials, the contractions) then run four lanes
/// wide. Both builds perform the same operations in the same order (no fused multiply-add), so
/// their results are identical (as for the exact GP's predictions).
#[inline(always)]
pub(crate) fn dispatch<T>(f: impl FnOnce() -> T) -> T {
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx2")]
        fn avx2<T>(f: impl FnOnce() -> T) -> T {
            f()
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2, checked just above.
            return unsafe { avx2(f) };
        }
    }
    f()
}

/// `e` with "output o: " before its message (as `MultiGp::new` reports a failed output).
fn for_output(e: Error, o: usize) -> Error {
    match e {
        Error::InvalidInput { arg, msg } => Error::invalid(arg, format!("output {o}: {msg}")),
        Error::Numerical(msg) => Error::numerical(format!("output {o}: {msg}")),
        e @ Error::Interrupted(_) => e,
    }
}

#[cfg(test)]
mod tests;
