//! The GP-MHE window problem (docs/user_guide/window.rst) as a nonlinear least-squares problem in the window
//! states z = (x̄_0, …, x̄_{M_t}) (multiple shooting): stacked residuals r(z), their block-banded
//! Jacobian, the cost J = ‖r‖², the gradient 2Jᵀr and the block-tridiagonal Gauss-Newton Hessian
//! 2JᵀJ. The model enters only through [`StageModel`] (means, variances and their input gradients
//! at a batch of points), so the same code serves learned (GP) and known models.
//!
//! Residual rows, in this order (node i is window time t − M_t + i, a_j = √(2η^j)):
//! * prior (n rows, node 0): a_{M_t} · S (x̄_0 − x̂(t − M_t)), with P2 = SᵀS;
//! * for every node i = 0 … M_t:
//!   - output (one row per measured channel of y_i, only if y_i is present and i < M_t, or
//!     i = M_t in the filtering form; NaN entries of y_i are channels not measured): weight
//!     a_{M_t−1−i} (a_0 = √2 for the filtering form's newest output), a L⁻¹ (y_i − m_y(d̄_i))
//!     with L Lᵀ = diag σ²_y(d̄_i) + R0 on the measured channels;
//!   - process (n rows, nodes i and i+1, for i < M_t): a_{M_t−1−i} L⁻¹ (x̄_{i+1} − m_x(d̄_i)),
//!     L Lᵀ = diag σ²_x(d̄_i) + Q0.
//!
//! With n_g global variables g (a model's quantities constant over the window, such as a sparse
//! GP's inducing outputs; [`StageModel::n_globals`]) z ends with g, the prior rows become the n +
//! n_g rows S ([a_{M_t} (x̄_0 − x̂); √2 (g − ĝ)]) of the joint arrival prior (`globals.rs`: g's
//! prior is not discounted), and every model row also depends on g through the model's means.
//!
//! Q0 and R0 are covariances (docs/user_guide/weights.rst), diagonal (each row is divided by
//! its standard deviation) or full (the block is whitened with its Cholesky factor,
//! `weights.rs`). η = 1 is allowed (no discount).

// Index loops mirror the block formulas of docs/user_guide/window.rst and read better than iterator chains here.
#![allow(clippy::needless_range_loop)]

use super::globals::{global_block, global_row, selected_rows, GlobalPrior, PriorRows};
use super::loss::Loss;
use super::stage::{StageEval, StageModel};
use super::weights::{whiten, Block, Covariance};
use crate::error::{check_finite, check_len, Error, Result};
use crate::solver::with_block_dim;
use nalgebra::Dim;

/// Which outputs the window uses (docs/user_guide/window.rst): the paper's prediction form (y up to t−1, the
/// estimate is x̂(t) = x̄_t before seeing y_t) or the filtering form (adds y_t).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Form {
    Prediction,
    Filtering,
}

/// One window's data and weights. Build once with [`WindowProblem::new`], then call
/// [`WindowProblem::set_data`] every time step (buffers are reused).
#[derive(Debug, Clone)]
pub struct WindowProblem {
    n: usize,
    m: usize,
    p: usize,
    eta: f64,
    form: Form,
    q0: Covariance,
    r0: Covariance,
    /// S with P2 = SᵀS, n×n row-major: the configured arrival weight.
    p2_sqrt: Vec<f64>,
    /// The arrival weight's S of the current window (P2's unless set by `set_prior_weight`).
    prior_sqrt: Vec<f64>,
    m_t: usize,
    /// (M_t+1)×m inputs, (M_t+1)×p outputs, (M_t+1) presence flags.
    u: Vec<f64>,
    y: Vec<f64>,
    y_present: Vec<bool>,
    x_prior: Vec<f64>,
    /// The penalty of the whitened output residuals (`loss.rs`).
    loss: Loss,
    /// Per node, the output covariance given with that sample (None: R0).
    r_rows: Vec<Option<Covariance>>,
    /// The joint arrival prior of (x̄_0, g) when the model has global variables.
    globals: Option<GlobalPrior>,
}

/// The settings a problem was built with (for copies and checkpoints of an estimator).
impl WindowProblem {
    pub fn eta(&self) -> f64 {
        self.eta
    }
    /// Q0 (n × n) and R0 (p × p), row-major.
    pub fn q0(&self) -> &[f64] {
        self.q0.as_slice()
    }
    pub fn r0(&self) -> &[f64] {
        self.r0.as_slice()
    }
    pub fn q0_cov(&self) -> &Covariance {
        &self.q0
    }
    pub fn r0_cov(&self) -> &Covariance {
        &self.r0
    }
    /// S with P2 = SᵀS (n × n row-major).
    pub fn p2_sqrt(&self) -> &[f64] {
        &self.p2_sqrt
    }
    pub fn loss(&self) -> Loss {
        self.loss
    }
    /// Sets the penalty of the output residuals from the next evaluation on.
    pub fn set_loss(&mut self, loss: Loss) {
        self.loss = loss;
    }
}

impl WindowProblem {
    /// `q0` and `r0` are Q0 and R0: their diagonals (n and p values) or the whole symmetric
    /// positive definite matrices (n² and p² values, row-major); `p2_sqrt` is S (n×n,
    /// row-major) with P2 = SᵀS; `eta` ∈ [0, 1].
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        n: usize,
        m: usize,
        p: usize,
        eta: f64,
        q0: &[f64],
        r0: &[f64],
        p2_sqrt: &[f64],
        form: Form,
    ) -> Result<Self> {
        if n == 0 {
            return Err(Error::invalid("dim_x", "must be at least 1"));
        }
        let (q0, r0) = Self::check_weights(n, p, eta, q0, r0, p2_sqrt)?;
        Ok(Self {
            n,
            m,
            p,
            eta,
            form,
            q0,
            r0,
            p2_sqrt: p2_sqrt.to_vec(),
            prior_sqrt: p2_sqrt.to_vec(),
            m_t: 0,
            u: vec![0.0; m],
            y: vec![0.0; p],
            y_present: vec![false],
            x_prior: vec![0.0; n],
            loss: Loss::Squared,
            r_rows: vec![None],
            globals: None,
        })
    }

    fn check_weights(
        n: usize,
        p: usize,
        eta: f64,
        q0: &[f64],
        r0: &[f64],
        p2_sqrt: &[f64],
    ) -> Result<(Covariance, Covariance)> {
        if !(eta.is_finite() && (0.0..=1.0).contains(&eta)) {
            return Err(Error::invalid(
                "eta",
                format!("must be in [0, 1], got {eta}"),
            ));
        }
        check_len("P2", p2_sqrt, n * n)?;
        check_finite("P2", p2_sqrt)?;
        Ok((Covariance::new("Q0", q0, n)?, Covariance::new("R0", r0, p)?))
    }

    /// Replaces η, Q0, R0 and P2 (as in [`WindowProblem::new`]) and makes P2 the arrival
    /// weight of the current window; the window's data are kept. On error nothing changes.
    pub fn set_weights(&mut self, eta: f64, q0: &[f64], r0: &[f64], p2_sqrt: &[f64]) -> Result<()> {
        let (q0, r0) = Self::check_weights(self.n, self.p, eta, q0, r0, p2_sqrt)?;
        self.eta = eta;
        self.q0 = q0;
        self.r0 = r0;
        self.p2_sqrt = p2_sqrt.to_vec();
        self.prior_sqrt = p2_sqrt.to_vec();
        Ok(())
    }

    /// Sets the arrival weight of the current window to SᵀS (`s`: n × n row-major).
    pub fn set_prior_weight(&mut self, s: &[f64]) -> Result<()> {
        check_len("arrival weight", s, self.n * self.n)?;
        check_finite("arrival weight", s)?;
        self.prior_sqrt.clear();
        self.prior_sqrt.extend_from_slice(s);
        Ok(())
    }

    /// Sets the window: M_t = rows − 1 with `u` (M_t+1)×m, `y` (M_t+1)×p (rows where
    /// `y_present` is false are ignored and may hold anything, including NaN; in the others a
    /// NaN entry is a channel not measured), and the arrival
    /// prior x̂(t − M_t). In the prediction form the last row of `y` is never used.
    /// On error the previous window is kept.
    pub fn set_data(
        &mut self,
        u: &[f64],
        y: &[f64],
        y_present: &[bool],
        x_prior: &[f64],
    ) -> Result<()> {
        let nodes = y_present.len();
        if nodes == 0 {
            return Err(Error::invalid(
                "y_present",
                "window needs at least one node",
            ));
        }
        check_len("u", u, nodes * self.m)?;
        check_len("y", y, nodes * self.p)?;
        check_len("x_prior", x_prior, self.n)?;
        check_finite("u", u)?;
        check_finite("x_prior", x_prior)?;
        for (i, &present) in y_present.iter().enumerate() {
            let row = &y[i * self.p..(i + 1) * self.p];
            if present && row.iter().any(|v| v.is_infinite()) {
                return Err(Error::invalid("y", "contains an infinite value"));
            }
        }
        self.m_t = nodes - 1;
        self.u.clear();
        self.u.extend_from_slice(u);
        self.y.clear();
        self.y.extend_from_slice(y);
        self.y_present.clear();
        self.y_present.extend_from_slice(y_present);
        self.x_prior.clear();
        self.x_prior.extend_from_slice(x_prior);
        self.r_rows.clear();
        self.r_rows.resize(nodes, None);
        Ok(())
    }

    /// The output covariance of each node of the window set by [`WindowProblem::set_data`]
    /// (None: R0), until the next `set_data`. On error nothing changes.
    pub fn set_output_covariances(&mut self, r: &[Option<Covariance>]) -> Result<()> {
        if r.len() != self.n_nodes() {
            return Err(Error::invalid(
                "R",
                format!(
                    "needs one entry per node ({}), got {}",
                    self.n_nodes(),
                    r.len()
                ),
            ));
        }
        if r.iter().flatten().any(|c| c.dim() != self.p) {
            return Err(Error::invalid("R", format!("must be {0} x {0}", self.p)));
        }
        self.r_rows.clear();
        self.r_rows.extend_from_slice(r);
        Ok(())
    }

    /// The output covariance of node i: the one given with its sample, or R0.
    pub fn output_cov(&self, i: usize) -> &Covariance {
        self.r_rows
            .get(i)
            .and_then(Option::as_ref)
            .unwrap_or(&self.r0)
    }

    /// M_t + 1.
    pub fn n_nodes(&self) -> usize {
        self.m_t + 1
    }
    pub fn dim_x(&self) -> usize {
        self.n
    }
    pub fn dim_u(&self) -> usize {
        self.m
    }
    pub fn dim_y(&self) -> usize {
        self.p
    }
    pub fn horizon_now(&self) -> usize {
        self.m_t
    }
    pub fn form(&self) -> Form {
        self.form
    }

    /// Whether node i carries an output residual block (it may still have no measured
    /// channel).
    fn has_output(&self, i: usize) -> bool {
        self.p > 0
            && self.y_present[i]
            && (i < self.m_t || (i == self.m_t && self.form == Form::Filtering))
    }

    /// The measured channels of node i's output (finite entries of y_i; none if the node has
    /// no output).
    fn measured(&self, i: usize) -> impl Iterator<Item = usize> + '_ {
        let row: &[f64] = match self.has_output(i) {
            true => &self.y[i * self.p..(i + 1) * self.p],
            false => &[],
        };
        row.iter()
            .enumerate()
            .filter(|(_, v)| v.is_finite())
            .map(|(k, _)| k)
    }

    /// Number of points the model is evaluated at: M_t (prediction) or M_t + 1 (filtering).
    fn n_points(&self) -> usize {
        match self.form {
            Form::Prediction => self.m_t,
            Form::Filtering => self.m_t + 1,
        }
    }

    /// Total number of residual rows for the current data.
    pub fn n_residuals(&self) -> usize {
        let outputs: usize = (0..self.n_nodes()).map(|i| self.measured(i).count()).sum();
        self.n + self.n_globals() + self.m_t * self.n + outputs
    }

    /// Number of global variables n_g (0 unless [`WindowProblem::set_global_prior`] was called).
    pub fn n_globals(&self) -> usize {
        self.globals.as_ref().map_or(0, GlobalPrior::dim)
    }

    /// Makes the window estimate n_g global variables g with the states, with the joint arrival
    /// prior S ([a_{M_t} (x̄_0 − x̂); √2 (g − ĝ)]) replacing the prior on x̄_0: `g_prior` is ĝ (n_g
    /// values), `joint_sqrt` S ((n + n_g)² values, row-major). On error nothing changes.
    pub fn set_global_prior(&mut self, g_prior: &[f64], joint_sqrt: &[f64]) -> Result<()> {
        self.globals = Some(GlobalPrior::new(self.n, g_prior, joint_sqrt)?);
        Ok(())
    }

    /// The joint arrival prior of the global variables, if any.
    pub fn global_prior(&self) -> Option<&GlobalPrior> {
        self.globals.as_ref()
    }

    /// Weight √(2η^{M_t−1−i}) of the stage at node i (√2 for node M_t).
    fn stage_weight(&self, i: usize) -> f64 {
        (2.0 * self.discount(i)).sqrt()
    }

    /// The discount η^{M_t−1−i} of the stage at node i (1 for node M_t).
    fn discount(&self, i: usize) -> f64 {
        self.eta.powi(self.m_t.saturating_sub(i + 1) as i32)
    }

    /// The discount of every residual row of `eval` (an evaluation of this window, in its row
    /// order): η^{M_t} for the arrival prior's rows, [`discount`](Self::discount) of its node
    /// for a stage's rows. All 1 when η = 1.
    pub fn row_discounts(&self, eval: &WindowEval) -> Vec<f64> {
        let prior_rows = self.n + self.n_globals();
        let prior = self.eta.powi(self.m_t as i32);
        (0..eval.r.len())
            .map(|k| {
                if k < prior_rows {
                    prior
                } else {
                    self.discount(eval.node[k])
                }
            })
            .collect()
    }

    /// Residuals (and, if `want_jacobian`, the Jacobian blocks) at z ((M_t+1)·n values), in the
    /// row order of the module documentation.
    pub fn evaluate(
        &self,
        model: &mut dyn StageModel,
        z: &[f64],
        want_jacobian: bool,
        out: &mut WindowEval,
    ) -> Result<()> {
        self.check_model(model)?;
        let (nodes, ng) = (self.n_nodes(), self.n_globals());
        check_len("z", z, nodes * self.n + ng)?;
        check_finite("z", z)?;
        if ng > 0 {
            model.set_globals(&z[nodes * self.n..])?;
        }
        self.evaluate_model(model, z, out)?;
        out.reset(self.n, nodes, ng, self.n_residuals(), want_jacobian);
        let mut row = self.write_prior_rows(z, want_jacobian, out);
        for i in 0..nodes {
            let a = self.stage_weight(i);
            if self.measured(i).next().is_some() {
                let first = row;
                row = self.write_output_rows(i, a, row, want_jacobian, out)?;
                if !self.loss.is_squared() {
                    out.robust_rows(self.loss, a, first..row);
                }
            }
            if i < self.m_t {
                row = self.write_process_rows(i, a, z, row, want_jacobian, out)?;
            }
        }
        debug_assert_eq!(row, out.r.len());
        out.finish()
    }

    fn check_model(&self, model: &dyn StageModel) -> Result<()> {
        let (n, m, p) = (self.n, self.m, self.p);
        if model.n_globals() != self.n_globals() {
            return Err(Error::invalid(
                "model",
                format!(
                    "has {} global variables, the window's prior {}",
                    model.n_globals(),
                    self.n_globals()
                ),
            ));
        }
        if model.dim_x() != n || model.dim_u() != m || model.dim_y() != p {
            return Err(Error::invalid(
                "model",
                format!(
                    "dimensions (dim_x, dim_u, dim_y) = ({}, {}, {}) do not match the window's ({n}, {m}, {p})",
                    model.dim_x(),
                    model.dim_u(),
                    model.dim_y()
                ),
            ));
        }
        Ok(())
    }

    /// The model's means, variances and gradients at the stage points d̄_i = [x̄_i; u_i].
    fn evaluate_model(
        &self,
        model: &mut dyn StageModel,
        z: &[f64],
        out: &mut WindowEval,
    ) -> Result<()> {
        let (n, m, p) = (self.n, self.m, self.p);
        let nd = n + m;
        let k = self.n_points();
        out.d.resize(k * nd, 0.0);
        for i in 0..k {
            out.d[i * nd..i * nd + n].copy_from_slice(&z[i * n..(i + 1) * n]);
            out.d[i * nd + n..(i + 1) * nd].copy_from_slice(&self.u[i * m..(i + 1) * m]);
        }
        out.stage.resize(k, n, m, p);
        let ng = self.n_globals();
        if k > 0 {
            model.evaluate(&out.d, &mut out.stage)?;
            out.stage.check_sizes(k, n, m, p)?;
            if ng > 0 {
                out.stage.check_global_sizes(k, n, p, ng)?;
            }
        }
        Ok(())
    }

    /// The prior block a_{M_t} S (x̄_0 − x̂(t − M_t)): rows 0 … n−1 (with global variables the
    /// joint prior's n + n_g rows, `globals.rs`). Returns the next row.
    fn write_prior_rows(&self, z: &[f64], want_jacobian: bool, out: &mut WindowEval) -> usize {
        let n = self.n;
        let a = (2.0 * self.eta.powi(self.m_t as i32)).sqrt();
        if let Some(gp) = &self.globals {
            let nx = self.n_nodes() * n;
            return gp.write_rows(a, &z[..n], &self.x_prior, &z[nx..], want_jacobian, out);
        }
        for r in 0..n {
            let mut acc = 0.0;
            for c in 0..n {
                acc += self.prior_sqrt[r * n + c] * (z[c] - self.x_prior[c]);
            }
            out.r[r] = a * acc;
            out.node[r] = 0;
            out.process[r] = false;
            if want_jacobian {
                for c in 0..n {
                    out.ja[r * n + c] = a * self.prior_sqrt[r * n + c];
                }
            }
        }
        n
    }

    /// The output rows of node i's measured channels from `row` on (weight a). Returns the
    /// next row.
    fn write_output_rows(
        &self,
        i: usize,
        a: f64,
        mut row: usize,
        want_jacobian: bool,
        out: &mut WindowEval,
    ) -> Result<usize> {
        let (n, p, nd) = (self.n, self.p, self.n + self.m);
        let cov = self.output_cov(i);
        if cov.is_diagonal() {
            for kk in self.measured(i) {
                let (t, g) = (i * p + kk, (i * p + kk) * nd);
                let st = &out.stage;
                let w = WeightedRow {
                    a,
                    target: self.y[t],
                    mean: st.mean_y[t],
                    var: st.var_y[t],
                    floor: cov.get(kk, kk),
                    mean_rounding: st.mean_y_rounding[kk],
                    var_rounding: st.var_y_rounding[kk],
                };
                let derivs = want_jacobian.then(|| {
                    (
                        &st.dmean_y[g..g + n],
                        &st.dvar_y[g..g + n],
                        &mut out.ja[row * n..(row + 1) * n],
                    )
                });
                let scale;
                (out.r[row], out.dr[row], scale) = w.write(derivs);
                if want_jacobian && out.ng > 0 {
                    let dm = &st.dmean_y_dg[t * out.ng..(t + 1) * out.ng];
                    global_row(&mut out.jg[row * out.ng..(row + 1) * out.ng], scale, dm);
                }
                out.node[row] = i;
                out.process[row] = false;
                row += 1;
            }
            return Ok(row);
        }
        let measured: Vec<usize> = self.measured(i).collect();
        let st = &out.stage;
        let part = StagePart {
            rows: &measured,
            target: measured.iter().map(|&k| self.y[i * p + k]).collect(),
            mean: &st.mean_y[i * p..(i + 1) * p],
            var: &st.var_y[i * p..(i + 1) * p],
            dmean: &st.dmean_y[i * p * nd..(i + 1) * p * nd],
            dvar: &st.dvar_y[i * p * nd..(i + 1) * p * nd],
            mean_rounding: &st.mean_y_rounding,
            var_rounding: &st.var_y_rounding,
        };
        let block = part.write(cov, a, n, nd, want_jacobian)?;
        let dg = selected_rows(&st.dmean_y_dg, i * p, &measured, out.ng);
        Ok(out.take_block(block, i, row, false, &dg))
    }

    /// The process rows of stage i (nodes i and i+1) from `row` on (weight a). Returns the
    /// next row.
    fn write_process_rows(
        &self,
        i: usize,
        a: f64,
        z: &[f64],
        mut row: usize,
        want_jacobian: bool,
        out: &mut WindowEval,
    ) -> Result<usize> {
        let (n, nd) = (self.n, self.n + self.m);
        if self.q0.is_diagonal() {
            for kk in 0..n {
                let (t, g) = (i * n + kk, (i * n + kk) * nd);
                let st = &out.stage;
                let w = WeightedRow {
                    a,
                    target: z[(i + 1) * n + kk],
                    mean: st.mean_x[t],
                    var: st.var_x[t],
                    floor: self.q0.get(kk, kk),
                    mean_rounding: st.mean_x_rounding[kk],
                    var_rounding: st.var_x_rounding[kk],
                };
                let derivs = want_jacobian.then(|| {
                    (
                        &st.dmean_x[g..g + n],
                        &st.dvar_x[g..g + n],
                        &mut out.ja[row * n..(row + 1) * n],
                    )
                });
                let scale;
                (out.r[row], out.dr[row], scale) = w.write(derivs);
                if want_jacobian && out.ng > 0 {
                    let dm = &st.dmean_x_dg[t * out.ng..(t + 1) * out.ng];
                    global_row(&mut out.jg[row * out.ng..(row + 1) * out.ng], scale, dm);
                }
                if want_jacobian {
                    // ∂r/∂x̄_{i+1}: the target is the next state itself.
                    let jb = &mut out.jb[row * n..(row + 1) * n];
                    jb.iter_mut().for_each(|v| *v = 0.0);
                    jb[kk] = scale;
                }
                out.node[row] = i;
                out.process[row] = true;
                row += 1;
            }
            return Ok(row);
        }
        let st = &out.stage;
        let all: Vec<usize> = (0..n).collect();
        let part = StagePart {
            rows: &all,
            target: z[(i + 1) * n..(i + 2) * n].to_vec(),
            mean: &st.mean_x[i * n..(i + 1) * n],
            var: &st.var_x[i * n..(i + 1) * n],
            dmean: &st.dmean_x[i * n * nd..(i + 1) * n * nd],
            dvar: &st.dvar_x[i * n * nd..(i + 1) * n * nd],
            mean_rounding: &st.mean_x_rounding,
            var_rounding: &st.var_x_rounding,
        };
        let block = part.write(&self.q0, a, n, nd, want_jacobian)?;
        let dg = selected_rows(&st.dmean_x_dg, i * n, &all, out.ng);
        Ok(out.take_block(block, i, row, true, &dg))
    }
}

/// One stage's residual block with a full covariance, before whitening: the selected `rows` of
/// a model part (the outputs or the next state), its targets, the model's means, variances, their gradients
/// (row-major, nd per component: the node's n entries come first) and roundings.
struct StagePart<'a> {
    rows: &'a [usize],
    target: Vec<f64>,
    mean: &'a [f64],
    var: &'a [f64],
    dmean: &'a [f64],
    dvar: &'a [f64],
    mean_rounding: &'a [f64],
    var_rounding: &'a [f64],
}

/// A whitened block: residuals, their roundings, ∂r/∂x̄ of the stage's node (k × n) and
/// ∂r/∂target = a L⁻¹ (k × k, row-major).
struct WrittenBlock {
    r: Vec<f64>,
    rounding: Vec<f64>,
    ja: Vec<f64>,
    dtarget: Vec<f64>,
}

impl StagePart<'_> {
    /// Whitens the block with a·L⁻¹, L Lᵀ = diag σ² + cov on the selected rows (`weights.rs`).
    fn write(
        &self,
        cov: &Covariance,
        a: f64,
        n: usize,
        nd: usize,
        jac: bool,
    ) -> Result<WrittenBlock> {
        let pick = |v: &[f64]| -> Vec<f64> {
            self.rows
                .iter()
                .flat_map(|&j| v[j * nd..j * nd + n].iter().copied())
                .collect()
        };
        let sel = |v: &[f64]| -> Vec<f64> { self.rows.iter().map(|&j| v[j]).collect() };
        let (dm, dv) = (pick(self.dmean), pick(self.dvar));
        let e: Vec<f64> = self
            .rows
            .iter()
            .zip(&self.target)
            .map(|(&j, t)| t - self.mean[j])
            .collect();
        let block = Block {
            a,
            e: &e,
            var: &sel(self.var),
            derivs: jac.then_some((&dm[..], &dv[..])),
            mean_rounding: &sel(self.mean_rounding),
            var_rounding: &sel(self.var_rounding),
        };
        let w = whiten(cov, self.rows, &block, n)?;
        Ok(WrittenBlock {
            r: w.r,
            rounding: w.rounding,
            ja: w.ja,
            dtarget: w.a_linv,
        })
    }
}

/// One variance-weighted residual row r = a (target − m(d̄)) / √s, s = σ²(d̄) + floor (floor:
/// the diagonal of Q0 or R0), docs/user_guide/weights.rst.
struct WeightedRow {
    a: f64,
    target: f64,
    mean: f64,
    var: f64,
    floor: f64,
    mean_rounding: f64,
    var_rounding: f64,
}

impl WeightedRow {
    /// Returns (r, its typical rounding error, a/√s) and, given (∂m/∂x̄, ∂σ²/∂x̄, out), writes
    /// ∂r/∂x̄ of the stage's own node: −(a/√s) ∂m/∂x̄ − r/(2s) ∂σ²/∂x̄.
    fn write(&self, derivs: Option<(&[f64], &[f64], &mut [f64])>) -> (f64, f64, f64) {
        let s = self.var.max(0.0) + self.floor;
        let inv_sqrt = 1.0 / s.sqrt();
        let r = self.a * (self.target - self.mean) * inv_sqrt;
        if let Some((dm, dv, ja)) = derivs {
            for ((j, m), v) in ja.iter_mut().zip(dm).zip(dv) {
                *j = -self.a * inv_sqrt * m - r / (2.0 * s) * v;
            }
        }
        let scale = self.a * inv_sqrt;
        let dr = residual_rounding(r, scale * self.mean_rounding, self.var_rounding / s);
        (r, dr, scale)
    }
}

/// Typical rounding error of a residual r = a (target − m) / √s from the rounding δr_m =
/// a δm / √s it gets through the mean and the relative rounding δs/s of its variance s
/// (∂r/∂s = −r / 2s), independent errors added in quadrature.
#[inline]
fn residual_rounding(r: f64, dr_mean: f64, ds_rel: f64) -> f64 {
    dr_mean.hypot(0.5 * r * ds_rel)
}

/// Residuals and the block-banded Jacobian of one window evaluation. Row `k` belongs to node
/// `node[k]`; `ja` holds ∂r_k/∂x̄_{node} (n values per row) and, for process rows, `jb` holds
/// ∂r_k/∂x̄_{node+1} (zero for other rows), and `jg` ∂r_k/∂g when the window has global
/// variables.
#[derive(Debug, Default, Clone)]
pub struct WindowEval {
    pub(super) n: usize,
    pub(super) nodes: usize,
    /// Number of global variables and ∂r_k/∂g (n_g values per row; empty when n_g = 0).
    pub(super) ng: usize,
    pub(super) has_jacobian: bool,
    pub(super) r: Vec<f64>,
    pub(super) node: Vec<usize>,
    pub(super) process: Vec<bool>,
    pub(super) ja: Vec<f64>,
    pub(super) jb: Vec<f64>,
    pub(super) jg: Vec<f64>,
    /// The joint prior's rows (with global variables): their precomputed Gram blocks.
    pub(super) prior: Option<PriorRows>,
    /// Scratch reused between evaluations: the k×nd stage points and the model's values there.
    d: Vec<f64>,
    stage: StageEval,
    /// Typical rounding error δr_k of each residual (see `residual_rounding`), from the model's
    /// mean and variance rounding.
    dr: Vec<f64>,
    /// The typical rounding noise of J = Σ r_k²: √Σ_k (2 r_k δr_k)² (first order, independent
    /// errors).
    noise: f64,
}

impl WindowEval {
    /// Copies a weighted block of stage i into rows `row..`: ∂r/∂x̄_i into `ja` and, for a
    /// process block (target x̄_{i+1}), ∂r/∂target into `jb`. Returns the next row.
    /// `dg`: the block rows' ∂mean/∂g (k × n_g, empty without global variables).
    fn take_block(
        &mut self,
        b: WrittenBlock,
        i: usize,
        row: usize,
        process: bool,
        dg: &[f64],
    ) -> usize {
        let (n, k, ng) = (self.n, b.r.len(), self.ng);
        if ng > 0 && !b.ja.is_empty() {
            global_block(
                &mut self.jg[row * ng..(row + k) * ng],
                &b.dtarget,
                dg,
                k,
                ng,
            );
        }
        for q in 0..k {
            let at = row + q;
            self.r[at] = b.r[q];
            self.dr[at] = b.rounding[q];
            self.node[at] = i;
            self.process[at] = process;
            if !b.ja.is_empty() {
                self.ja[at * n..(at + 1) * n].copy_from_slice(&b.ja[q * n..(q + 1) * n]);
                if process {
                    self.jb[at * n..(at + 1) * n].copy_from_slice(&b.dtarget[q * k..(q + 1) * k]);
                }
            }
        }
        row + k
    }

    /// Rows `rows` (output rows of weight a) through the robust penalty: r ↦ a ψ(r / a), their
    /// derivatives and roundings times ψ′ (`loss.rs`).
    fn robust_rows(&mut self, loss: Loss, a: f64, rows: std::ops::Range<usize>) {
        let n = self.n;
        for k in rows {
            let (r, slope) = loss.row(a, self.r[k]);
            self.r[k] = r;
            self.dr[k] *= slope;
            if self.has_jacobian {
                self.ja[k * n..(k + 1) * n]
                    .iter_mut()
                    .for_each(|v| *v *= slope);
                let ng = self.ng;
                self.jg[k * ng..(k + 1) * ng]
                    .iter_mut()
                    .for_each(|v| *v *= slope);
            }
        }
    }

    /// The cost's rounding noise, and an error if a residual is not finite.
    fn finish(&mut self) -> Result<()> {
        self.noise = self
            .r
            .iter()
            .zip(&self.dr)
            .map(|(r, d)| (2.0 * r * d).powi(2))
            .sum::<f64>()
            .sqrt();
        if self.r.iter().any(|v| !v.is_finite()) {
            return Err(Error::numerical(
                "window residuals are not finite (model returned NaN/inf)",
            ));
        }
        Ok(())
    }

    fn reset(&mut self, n: usize, nodes: usize, ng: usize, rows: usize, want_jacobian: bool) {
        self.n = n;
        self.nodes = nodes;
        self.ng = ng;
        self.prior = None;
        self.has_jacobian = want_jacobian;
        self.r.resize(rows, 0.0);
        self.dr.clear();
        self.dr.resize(rows, 0.0);
        self.node.resize(rows, 0);
        self.process.resize(rows, false);
        if want_jacobian {
            self.ja.resize(rows * n, 0.0);
            self.jb.clear();
            self.jb.resize(rows * n, 0.0);
            self.jg.clear();
            self.jg.resize(rows * ng, 0.0);
        }
    }

    /// The model's values at the window's stage points of the last evaluation.
    pub fn stage(&self) -> &StageEval {
        &self.stage
    }

    /// Estimated rounding noise of [`WindowEval::cost`] from the model's means and variances (0
    /// for a model computed to full precision); see the field docs.
    pub fn cost_noise(&self) -> f64 {
        self.noise
    }

    /// Estimated rounding noise of the gradient 2Jᵀr (largest over the variables): the residual
    /// rounding δr carried through the Jacobian, √Σ_k (2 J_kj δr_k)². Needs an evaluation with
    /// the Jacobian (0 otherwise).
    pub fn gradient_noise(&self) -> f64 {
        // A model computed to full precision rounds nothing (each term is 0, a non-finite one
        // NaN, which the maximum below ignores).
        if !self.has_jacobian || self.dr.iter().all(|&d| d == 0.0) {
            return 0.0;
        }
        let (n, ng, nx) = (self.n, self.ng, self.nodes * self.n);
        let mut sq = vec![0.0; nx + ng];
        for (k, &d) in self.dr.iter().enumerate() {
            let i = self.node[k];
            for l in 0..n {
                sq[i * n + l] += (2.0 * self.ja[k * n + l] * d).powi(2);
                if self.process[k] {
                    sq[(i + 1) * n + l] += (2.0 * self.jb[k * n + l] * d).powi(2);
                }
            }
            for c in 0..ng {
                sq[nx + c] += (2.0 * self.jg[k * ng + c] * d).powi(2);
            }
        }
        sq.iter().fold(0.0f64, |a, &b| a.max(b)).sqrt()
    }

    /// ‖r‖².
    pub fn cost(&self) -> f64 {
        self.r.iter().map(|v| v * v).sum()
    }
    pub fn residuals(&self) -> &[f64] {
        &self.r
    }
    pub fn n_residuals(&self) -> usize {
        self.r.len()
    }
    /// Number of decision variables, n_nodes · n + n_g.
    pub fn n_vars(&self) -> usize {
        self.nodes * self.n + self.ng
    }
    pub fn n_nodes(&self) -> usize {
        self.nodes
    }
    pub fn dim_x(&self) -> usize {
        self.n
    }
    pub fn has_jacobian(&self) -> bool {
        self.has_jacobian
    }

    /// 2Jᵀr into `g` (length n_nodes·n + n_g). Needs an evaluation with the Jacobian.
    pub fn gradient_into(&self, g: &mut [f64]) {
        g.iter_mut().for_each(|v| *v = 0.0);
        if self.ng > 0 {
            self.global_gradient_into(&mut g[self.nodes * self.n..]);
        }
        with_block_dim!(self.n, d => self.gradient_in(d, g))
    }

    /// The node part of [`gradient_into`](Self::gradient_into) with n = `d` (a constant for
    /// small n: the loops unroll; the same sums in the same order).
    fn gradient_in<D: Dim>(&self, d: D, g: &mut [f64]) {
        let n = d.value();
        for (k, &rk) in self.r.iter().enumerate() {
            let i = self.node[k];
            let ja = &self.ja[k * n..(k + 1) * n];
            for (gl, a) in g[i * n..(i + 1) * n].iter_mut().zip(ja) {
                *gl += 2.0 * a * rk;
            }
            if self.process[k] {
                let jb = &self.jb[k * n..(k + 1) * n];
                for (gl, b) in g[(i + 1) * n..(i + 2) * n].iter_mut().zip(jb) {
                    *gl += 2.0 * b * rk;
                }
            }
        }
    }

    /// 2JᵀJ as block-tridiagonal: `diag` (n_nodes·n·n, block i row-major at i·n·n) and `off`
    /// ((n_nodes−1)·n·n, block (i, i+1) row-major). Needs an evaluation with the Jacobian.
    pub fn gauss_newton_blocks_into(&self, diag: &mut [f64], off: &mut [f64]) {
        self.weighted_gauss_newton_blocks_into(|_| 2.0, diag, off);
    }

    /// 2JᵀWJ (W = diag(`weights`), one per residual row) in the blocks of
    /// [`gauss_newton_blocks_into`](Self::gauss_newton_blocks_into).
    pub fn discounted_gauss_newton_blocks_into(
        &self,
        weights: &[f64],
        diag: &mut [f64],
        off: &mut [f64],
    ) {
        self.weighted_gauss_newton_blocks_into(|k| 2.0 * weights[k], diag, off);
    }

    /// Σ_k c(k) J_kᵀJ_k in blocks (c(k) = 2 for 2JᵀJ: the same bits as doubling each product).
    fn weighted_gauss_newton_blocks_into(
        &self,
        c: impl Fn(usize) -> f64,
        diag: &mut [f64],
        off: &mut [f64],
    ) {
        diag.iter_mut().for_each(|v| *v = 0.0);
        off.iter_mut().for_each(|v| *v = 0.0);
        with_block_dim!(self.n, d => self.weighted_blocks_in(d, c, diag, off))
    }

    /// [`weighted_gauss_newton_blocks_into`](Self::weighted_gauss_newton_blocks_into) on zeroed
    /// blocks with n = `d` (a constant for small n, so the short loops unroll).
    ///
    /// The diagonal blocks' upper triangles are summed and mirrored at the end: 2·a·b and 2·b·a
    /// are the same number (doubling is exact), so the blocks are what the full sums give.
    /// Each entry is the same sum over the rows in the same order as term by term. A zero factor
    /// adds ±0 to every entry of its block row, which changes no entry (none is −0: a sum from +0
    /// that cancels is +0), so such block rows are skipped when the row's other factors are
    /// finite (0·inf would be NaN): rows of parameters and sparse Jacobians cost O(n) instead of
    /// O(n²).
    fn weighted_blocks_in<D: Dim>(
        &self,
        d: D,
        c: impl Fn(usize) -> f64,
        diag: &mut [f64],
        off: &mut [f64],
    ) {
        let n = d.value();
        let nn = n * n;
        let upper_outer = |block: &mut [f64], v: &[f64], finite: bool, c: f64| {
            for a in 0..n {
                let va = c * v[a];
                if va == 0.0 && finite {
                    continue;
                }
                for b in a..n {
                    block[a * n + b] += va * v[b];
                }
            }
        };
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        for (k, &i) in self.node.iter().enumerate().take(self.r.len()) {
            let (ja, ck) = (&self.ja[k * n..(k + 1) * n], c(k));
            upper_outer(&mut diag[i * nn..(i + 1) * nn], ja, finite(ja), ck);
            if self.process[k] {
                let jb = &self.jb[k * n..(k + 1) * n];
                let jb_finite = finite(jb);
                upper_outer(&mut diag[(i + 1) * nn..(i + 2) * nn], jb, jb_finite, ck);
                let block = &mut off[i * nn..(i + 1) * nn];
                for a in 0..n {
                    let va = ck * ja[a];
                    if va == 0.0 && jb_finite {
                        continue;
                    }
                    for b in 0..n {
                        block[a * n + b] += va * jb[b];
                    }
                }
            }
        }
        for block in diag.chunks_exact_mut(nn) {
            for a in 0..n {
                for b in 0..a {
                    block[a * n + b] = block[b * n + a];
                }
            }
        }
    }

    /// 2JᵀJ as a dense (n_nodes·n + n_g)² matrix, row-major (for the SciPy solvers and tests; the
    /// window solver uses the blocks of [`WindowEval::gauss_newton_blocks_into`]).
    pub fn dense_gauss_newton(&self) -> Vec<f64> {
        let (n, nodes) = (self.n, self.nodes);
        let (nn, nv) = (n * n, self.n_vars());
        let mut diag = vec![0.0; nodes * nn];
        let mut off = vec![0.0; nodes.saturating_sub(1) * nn];
        self.gauss_newton_blocks_into(&mut diag, &mut off);
        let mut h = vec![0.0; nv * nv];
        for i in 0..nodes {
            for a in 0..n {
                for b in 0..n {
                    h[(i * n + a) * nv + i * n + b] = diag[i * nn + a * n + b];
                    if i + 1 < nodes {
                        let v = off[i * nn + a * n + b];
                        h[(i * n + a) * nv + (i + 1) * n + b] = v;
                        h[((i + 1) * n + b) * nv + i * n + a] = v;
                    }
                }
            }
        }
        if self.ng > 0 {
            self.dense_global_blocks(&mut h);
        }
        h
    }

    /// The dense Jacobian (n_residuals × (n_nodes·n + n_g), row-major) into `jac`.
    pub fn dense_jacobian_into(&self, jac: &mut [f64]) {
        let (n, ng) = (self.n, self.ng);
        let cols = self.n_vars();
        jac.iter_mut().for_each(|v| *v = 0.0);
        for k in 0..self.r.len() {
            let i = self.node[k];
            jac[k * cols + i * n..k * cols + (i + 1) * n]
                .copy_from_slice(&self.ja[k * n..(k + 1) * n]);
            if self.process[k] {
                jac[k * cols + (i + 1) * n..k * cols + (i + 2) * n]
                    .copy_from_slice(&self.jb[k * n..(k + 1) * n]);
            }
            jac[(k + 1) * cols - ng..(k + 1) * cols]
                .copy_from_slice(&self.jg[k * ng..(k + 1) * ng]);
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::gp::MultiGp;
    use crate::mhe::GpStageModel;

    /// An analytic model with state-dependent means and variances (n = 2, m = 1, p = 1):
    /// f(x, u) = [x0 + 0.1 x1 sin(x0) + 0.2u, 0.9 x1 + 0.05 x0²], h = x0 x1 + u,
    /// var_x = [0.01 + 0.02 x0², 0.03 + 0.01 (x1 − u)²], var_y = 0.02 + 0.01 x0².
    struct Analytic;
    impl StageModel for Analytic {
        fn dim_x(&self) -> usize {
            2
        }
        fn dim_u(&self) -> usize {
            1
        }
        fn dim_y(&self) -> usize {
            1
        }
        fn evaluate(&mut self, d: &[f64], out: &mut StageEval) -> Result<()> {
            let k = d.len() / 3;
            out.resize(k, 2, 1, 1);
            out.dmean_x.iter_mut().for_each(|v| *v = 0.0);
            out.dvar_x.iter_mut().for_each(|v| *v = 0.0);
            for i in 0..k {
                let (x0, x1, u) = (d[3 * i], d[3 * i + 1], d[3 * i + 2]);
                out.mean_x[2 * i] = x0 + 0.1 * x1 * x0.sin() + 0.2 * u;
                out.mean_x[2 * i + 1] = 0.9 * x1 + 0.05 * x0 * x0;
                let g = 6 * i;
                out.dmean_x[g] = 1.0 + 0.1 * x1 * x0.cos();
                out.dmean_x[g + 1] = 0.1 * x0.sin();
                out.dmean_x[g + 2] = 0.2;
                out.dmean_x[g + 3] = 0.1 * x0;
                out.dmean_x[g + 4] = 0.9;
                out.var_x[2 * i] = 0.01 + 0.02 * x0 * x0;
                out.var_x[2 * i + 1] = 0.03 + 0.01 * (x1 - u).powi(2);
                out.dvar_x[g] = 0.04 * x0;
                out.dvar_x[g + 4] = 0.02 * (x1 - u);
                out.dvar_x[g + 5] = -0.02 * (x1 - u);
                out.mean_y[i] = x0 * x1 + u;
                out.var_y[i] = 0.02 + 0.01 * x0 * x0;
                out.dmean_y[3 * i] = x1;
                out.dmean_y[3 * i + 1] = x0;
                out.dmean_y[3 * i + 2] = 1.0;
                out.dvar_y[3 * i] = 0.02 * x0;
                out.dvar_y[3 * i + 1] = 0.0;
                out.dvar_y[3 * i + 2] = 0.0;
            }
            Ok(())
        }
    }

    fn problem(form: Form, nodes: usize, missing: &[usize]) -> WindowProblem {
        let mut w = WindowProblem::new(
            2,
            1,
            1,
            0.91,
            &[1e-3, 2e-3],
            &[1e-2],
            &[1.0, 0.3, 0.0, 0.8],
            form,
        )
        .unwrap();
        let u: Vec<f64> = (0..nodes).map(|i| 0.1 * i as f64).collect();
        let y: Vec<f64> = (0..nodes).map(|i| 1.0 + 0.2 * i as f64).collect();
        let present: Vec<bool> = (0..nodes).map(|i| !missing.contains(&i)).collect();
        w.set_data(&u, &y, &present, &[0.7, 1.3]).unwrap();
        w
    }

    fn z0(nodes: usize) -> Vec<f64> {
        (0..2 * nodes)
            .map(|j| 0.5 + 0.37 * ((j * 7 % 5) as f64))
            .collect()
    }

    /// Direct evaluation of the window cost's sum (no residual stacking) for the analytic model.
    fn direct_cost(w: &WindowProblem, z: &[f64]) -> f64 {
        let mt = w.m_t;
        let dx: Vec<f64> = (0..2).map(|c| z[c] - w.x_prior[c]).collect();
        let p2 = [1.0 * 1.0, 0.3, 0.3, 0.3 * 0.3 + 0.8 * 0.8]; // SᵀS
        let prior =
            dx[0] * (p2[0] * dx[0] + p2[1] * dx[1]) + dx[1] * (p2[2] * dx[0] + p2[3] * dx[1]);
        let mut j = 2.0 * 0.91f64.powi(mt as i32) * prior;
        let mut model = Analytic;
        let mut st = StageEval::default();
        for i in 0..=mt {
            let d = [z[2 * i], z[2 * i + 1], w.u[i]];
            model.evaluate(&d, &mut st).unwrap();
            let weight = 2.0 * 0.91f64.powi(mt.saturating_sub(i + 1) as i32);
            if w.has_output(i) {
                let v = w.y[i] - st.mean_y[0];
                j += weight * v * v / (st.var_y[0] + 1e-2);
            }
            if i < mt {
                let q0 = [1e-3, 2e-3];
                for c in 0..2 {
                    let wv = z[2 * (i + 1) + c] - st.mean_x[c];
                    j += weight * wv * wv / (st.var_x[c] + q0[c]);
                }
            }
        }
        j
    }

    #[test]
    fn cost_matches_direct_sum_and_derivatives_match_finite_differences() {
        for form in [Form::Prediction, Form::Filtering] {
            for (nodes, missing) in [(1, vec![]), (2, vec![]), (6, vec![2]), (6, vec![5, 0])] {
                let w = problem(form, nodes, &missing);
                let mut model = Analytic;
                let mut ev = WindowEval::default();
                let z = z0(nodes);
                w.evaluate(&mut model, &z, true, &mut ev).unwrap();
                let direct = direct_cost(&w, &z);
                assert!((ev.cost() - direct).abs() <= 1e-12 * direct.max(1.0));
                assert_eq!(ev.n_residuals(), w.n_residuals());

                let nv = 2 * nodes;
                let rows = ev.n_residuals();
                let jac = check_derivatives(&w, &mut model, &z, 1e-6);

                // Block-tridiagonal Gauss-Newton Hessian equals the dense 2JᵀJ.
                let mut diag = vec![0.0; nodes * 4];
                let mut off = vec![0.0; (nodes - 1) * 4];
                ev.gauss_newton_blocks_into(&mut diag, &mut off);
                for a in 0..nv {
                    for b in 0..nv {
                        let dense: f64 = (0..rows)
                            .map(|r| 2.0 * jac[r * nv + a] * jac[r * nv + b])
                            .sum();
                        let (ia, ib) = (a / 2, b / 2);
                        let blk = if ia == ib {
                            diag[ia * 4 + (a % 2) * 2 + b % 2]
                        } else if ib == ia + 1 {
                            off[ia * 4 + (a % 2) * 2 + b % 2]
                        } else if ia == ib + 1 {
                            off[ib * 4 + (b % 2) * 2 + a % 2]
                        } else {
                            0.0
                        };
                        assert!((dense - blk).abs() <= 1e-10 * (1.0 + dense.abs()));
                    }
                }
            }
        }
    }

    /// Window gradient and Jacobian against central differences (relative tolerance `tol`) for
    /// any model; returns the dense Jacobian.
    pub(crate) fn check_derivatives(
        w: &WindowProblem,
        model: &mut dyn StageModel,
        z: &[f64],
        tol: f64,
    ) -> Vec<f64> {
        let mut ev = WindowEval::default();
        w.evaluate(model, z, true, &mut ev).unwrap();
        let nv = z.len();
        let rows = ev.n_residuals();
        let mut g = vec![0.0; nv];
        ev.gradient_into(&mut g);
        let mut jac = vec![0.0; rows * nv];
        ev.dense_jacobian_into(&mut jac);
        let mut e2 = WindowEval::default();
        let h = 1e-6;
        for c in 0..nv {
            let mut zp = z.to_vec();
            zp[c] += h;
            w.evaluate(model, &zp, false, &mut e2).unwrap();
            let (cp, rp) = (e2.cost(), e2.residuals().to_vec());
            let mut zm = z.to_vec();
            zm[c] -= h;
            w.evaluate(model, &zm, false, &mut e2).unwrap();
            let fd = (cp - e2.cost()) / (2.0 * h);
            assert!(
                (g[c] - fd).abs() <= tol * (1.0 + fd.abs()),
                "grad {c}: {} vs {fd}",
                g[c]
            );
            for r in 0..rows {
                let fdr = (rp[r] - e2.residuals()[r]) / (2.0 * h);
                assert!((jac[r * nv + c] - fdr).abs() <= tol * (1.0 + fdr.abs()));
            }
        }
        jac
    }

    #[test]
    fn gp_stage_model_window_derivatives_match_finite_differences() {
        // Training data from a smooth 2-state, 1-input system on a small grid.
        let mut x = Vec::new();
        let (mut yf, mut yh) = (Vec::new(), Vec::new());
        for a in 0..4 {
            for b in 0..4 {
                for c in 0..2 {
                    let (x0, x1, u) = (0.3 * a as f64, 0.25 * b as f64, 0.5 * c as f64);
                    x.extend_from_slice(&[x0, x1, u]);
                    yf.extend_from_slice(&[
                        x0 + 0.1 * x1.sin() + 0.1 * u,
                        0.9 * x1 + 0.05 * x0 * x0,
                    ]);
                    yh.push(x0 * x1 + u);
                }
            }
        }
        let th = |sf: f64| [sf.ln(), 0.7f64.ln(), 0.9f64.ln(), 1.2f64.ln(), 0.05f64.ln()];
        let thetas_f: Vec<f64> = [th(1.0), th(0.8)].concat();
        let f = MultiGp::new(&x, &yf, &thetas_f).unwrap();
        let h = MultiGp::new(&x, &yh, &th(1.5)).unwrap();
        for residual in [false, true] {
            let mut model = GpStageModel::new(f.clone(), Some(h.clone()), 1, residual).unwrap();
            for form in [Form::Prediction, Form::Filtering] {
                let w = problem(form, 5, &[3]);
                let z: Vec<f64> = z0(5).iter().map(|v| 0.4 * v).collect();
                check_derivatives(&w, &mut model, &z, 1e-5);
            }
        }
        // The residual form adds the identity to the mean and its gradient.
        let d = [0.4, 0.3, 0.5];
        let (mut a, mut b) = (StageEval::default(), StageEval::default());
        GpStageModel::new(f.clone(), Some(h.clone()), 1, false)
            .unwrap()
            .evaluate(&d, &mut a)
            .unwrap();
        GpStageModel::new(f.clone(), Some(h.clone()), 1, true)
            .unwrap()
            .evaluate(&d, &mut b)
            .unwrap();
        assert!((b.mean_x[0] - a.mean_x[0] - 0.4).abs() < 1e-14);
        assert!((b.mean_x[1] - a.mean_x[1] - 0.3).abs() < 1e-14);
        assert!((b.dmean_x[4] - a.dmean_x[4] - 1.0).abs() < 1e-14);
        assert_eq!(a.var_y, b.var_y);
        assert!(GpStageModel::new(f.clone(), Some(h.clone()), 2, false).is_err());

        // Values reused from the previous evaluation equal a fresh evaluation: a window shifted
        // by one node (one new point), a point moved by 1e-15, and a repeated point.
        for residual in [false, true] {
            let fresh = GpStageModel::new(f.clone(), Some(h.clone()), 1, residual).unwrap();
            let mut model = fresh.clone();
            let d1: Vec<f64> = (0..6 * 3).map(|t| 0.05 * t as f64 - 0.2).collect();
            let mut d2 = d1[3..].to_vec();
            d2.extend_from_slice(&[0.5, 0.1, 0.0, d1[6], d1[7], d1[8]]);
            d2[0] += 1e-15;
            let (mut first, mut reused, mut direct) = Default::default();
            model.evaluate(&d1, &mut first).unwrap();
            model.evaluate(&d2, &mut reused).unwrap();
            fresh.clone().evaluate(&d2, &mut direct).unwrap();
            let close = |a: &[f64], b: &[f64]| {
                a.len() == b.len()
                    && a.iter()
                        .zip(b)
                        .all(|(u, v)| (u - v).abs() <= 1e-14 * (1.0 + v.abs()))
            };
            let (r, e): (&StageEval, &StageEval) = (&reused, &direct);
            assert!(close(&r.mean_x, &e.mean_x) && close(&r.var_x, &e.var_x));
            assert!(close(&r.dmean_x, &e.dmean_x) && close(&r.dvar_x, &e.dvar_x));
            assert!(close(&r.mean_y, &e.mean_y) && close(&r.var_y, &e.var_y));
            assert!(close(&r.dmean_y, &e.dmean_y) && close(&r.dvar_y, &e.dvar_y));
            assert_eq!(r.mean_x_rounding, e.mean_x_rounding);
            // The reused point really is the old one (bit-identical to the first evaluation).
            assert_eq!(r.mean_x[2..4], first.mean_x[4..6]);
        }
    }

    /// With a full Q0 the process term is w̄ᵀ (diag σ²_x + Q0)⁻¹ w̄ (a dense inverse here), the
    /// derivatives match central differences, and a NaN output (p = 1: the only channel) drops
    /// the node's output exactly as a missing row does.
    #[test]
    fn full_q0_and_missing_channels_match_a_dense_evaluation() {
        let q0 = [1e-3, 4e-4, 4e-4, 2e-3];
        for form in [Form::Prediction, Form::Filtering] {
            let mut w = problem(form, 5, &[]);
            w.set_weights(1.0, &q0, &[1e-2], &[1.0, 0.3, 0.0, 0.8])
                .unwrap();
            let z = z0(5);
            let mut ev = WindowEval::default();
            w.evaluate(&mut Analytic, &z, false, &mut ev).unwrap();
            let mut direct = {
                let dx = [z[0] - w.x_prior[0], z[1] - w.x_prior[1]];
                let p2 = [1.0, 0.3, 0.3, 0.73];
                2.0 * (dx[0] * (p2[0] * dx[0] + p2[1] * dx[1])
                    + dx[1] * (p2[2] * dx[0] + p2[3] * dx[1]))
            };
            let mut st = StageEval::default();
            for i in 0..=w.m_t {
                Analytic
                    .evaluate(&[z[2 * i], z[2 * i + 1], w.u[i]], &mut st)
                    .unwrap();
                if w.has_output(i) {
                    direct += 2.0 * (w.y[i] - st.mean_y[0]).powi(2) / (st.var_y[0] + 1e-2);
                }
                if i < w.m_t {
                    let s = [st.var_x[0] + q0[0], q0[1], q0[2], st.var_x[1] + q0[3]];
                    let det = s[0] * s[3] - s[1] * s[2];
                    let e = [z[2 * i + 2] - st.mean_x[0], z[2 * i + 3] - st.mean_x[1]];
                    let quad =
                        (s[3] * e[0] * e[0] - 2.0 * s[1] * e[0] * e[1] + s[0] * e[1] * e[1]) / det;
                    direct += 2.0 * quad;
                }
            }
            assert!(
                (ev.cost() - direct).abs() <= 1e-11 * direct,
                "{} vs {direct}",
                ev.cost()
            );
            check_derivatives(&w, &mut Analytic, &z, 1e-5);
            // A NaN output is a channel not measured.
            let mut y = w.y.clone();
            y[2] = f64::NAN;
            let (u, x_prior) = (w.u.clone(), w.x_prior.clone());
            w.set_data(&u, &y, &[true; 5], &x_prior).unwrap();
            let mut missing = problem(form, 5, &[2]);
            missing
                .set_weights(1.0, &q0, &[1e-2], &[1.0, 0.3, 0.0, 0.8])
                .unwrap();
            let (mut a, mut b) = (WindowEval::default(), WindowEval::default());
            w.evaluate(&mut Analytic, &z, false, &mut a).unwrap();
            missing.evaluate(&mut Analytic, &z, false, &mut b).unwrap();
            assert_eq!(a.residuals(), b.residuals());
        }
    }

    #[test]
    fn residual_count_follows_form_and_missing_outputs() {
        let w = problem(Form::Prediction, 5, &[1]);
        // prior 2 + 4 process stages × 2 + outputs at nodes 0, 2, 3.
        assert_eq!(w.n_residuals(), 2 + 8 + 3);
        let w = problem(Form::Filtering, 5, &[1]);
        assert_eq!(w.n_residuals(), 2 + 8 + 4);
        let w = problem(Form::Prediction, 1, &[]);
        assert_eq!(w.n_residuals(), 2);
    }

    #[test]
    fn bad_inputs_are_rejected_and_keep_the_window() {
        let mut w = problem(Form::Filtering, 3, &[]);
        assert!(matches!(
            w.set_data(&[0.0; 3], &[f64::INFINITY, 1.0, 1.0], &[true; 3], &[0.0, 0.0]),
            Err(Error::InvalidInput { ref arg, .. }) if arg == "y"
        ));
        // NaN where the output is absent is fine.
        assert!(w
            .set_data(
                &[0.0; 3],
                &[f64::NAN, 1.0, 1.0],
                &[false, true, true],
                &[0.0, 0.0]
            )
            .is_ok());
        assert!(w
            .set_data(&[0.0; 2], &[1.0; 3], &[true; 3], &[0.0, 0.0])
            .is_err());
        assert_eq!(w.n_nodes(), 3);
        let mut ev = WindowEval::default();
        assert!(w.evaluate(&mut Analytic, &[0.0; 5], true, &mut ev).is_err());
        assert!(w
            .evaluate(
                &mut Analytic,
                &[0.0, f64::INFINITY, 0.0, 0.0, 0.0, 0.0],
                true,
                &mut ev
            )
            .is_err());
        assert!(WindowProblem::new(
            2,
            1,
            1,
            1.5,
            &[1.0; 2],
            &[1.0],
            &[1.0, 0.0, 0.0, 1.0],
            Form::Prediction
        )
        .is_err());
        assert!(WindowProblem::new(
            2,
            1,
            1,
            0.5,
            &[1.0, 0.0],
            &[1.0],
            &[1.0, 0.0, 0.0, 1.0],
            Form::Prediction
        )
        .is_err());
        let mut w2 = WindowProblem::new(
            2,
            0,
            1,
            0.5,
            &[1.0; 2],
            &[1.0],
            &[1.0, 0.0, 0.0, 1.0],
            Form::Prediction,
        )
        .unwrap();
        w2.set_data(&[], &[1.0, 1.0], &[true; 2], &[0.0, 0.0])
            .unwrap();
        assert!(matches!(
            w2.evaluate(&mut Analytic, &[0.0; 4], true, &mut ev),
            Err(Error::InvalidInput { ref arg, .. }) if arg == "model"
        ));
    }
}
