//! The moving-horizon estimator's core: one object built once with the window problem (weights,
//! form), the horizon, the state box and the solver settings, which owns the sliding history and
//! the warm start. [`MovingHorizon::update`] is one whole update — cut the window, warm-start
//! it, solve it, compute the next arrival prior, record the step; a failure before the record
//! leaves the estimator unchanged.
//!
//! The same steps are available one by one for other solvers (SciPy's, from Python):
//! [`MovingHorizon::prepare`] stages the next window and returns its warm start,
//! [`MovingHorizon::evaluate`] evaluates the staged window at any z, and
//! [`MovingHorizon::commit`] records a solution. [`MovingHorizon::solve_step`] solves an update
//! without recording it, [`MovingHorizon::apply`] records it (a bank records only once all its
//! estimators have succeeded).

use super::arrival::{ekf_mean_step, ekf_step, evaluate_at, Arrival, ArrivalMean, ArrivalWeight};
use super::history::{History, HistoryState, WindowData};
use super::innovation::{innovation, Innovation};
use super::joint_arrival::{joint_ekf_step, LeavingNode};
use super::learning_state::{Learning, LearningState, LearningUpdate};
use super::lsq::WindowLsq;
use super::outcome::{last_block, Outcome, Solved};
use super::problem::{Form, WindowEval, WindowProblem};
use super::stage::StageModel;
use super::weights::Covariance;
use crate::error::{check_finite, check_len, Error, Result};
use crate::solver::{BoxLsqSolver, Covariances, SolveReport, SolverOptions};

/// Relative margin by which the warm start is kept inside the box (1e-6 of its width, of 1 where
/// the width is infinite), so the solver's barrier phase does not start on a bound.
const INNER_MARGIN: f64 = 1e-6;

/// What one update did.
#[derive(Debug, Clone)]
pub struct UpdateReport {
    /// The optimal window (nodes × n), oldest first; its last row is the estimate.
    pub x_window: Vec<f64>,
    /// The arrival prior of the window's first node.
    pub x_prior: Vec<f64>,
    /// The last n×n block of 4(2JᵀJ)⁻¹ at the solution (None if singular or no solve ran).
    pub covariance: Option<Vec<f64>>,
    /// The solver's report, or the error that stopped it (the window then keeps its warm start).
    pub solve: std::result::Result<SolveReport, Error>,
    /// The cost J at `x_window`.
    pub cost: f64,
}

/// A solved update not yet recorded ([`MovingHorizon::solve_step`]); recording it
/// ([`MovingHorizon::apply`]) cannot fail.
#[derive(Debug, Clone)]
pub struct Pending {
    data: WindowData,
    x_window: Vec<f64>,
    next_prior: Vec<f64>,
    outcome: Outcome,
    /// The next window's arrival mean (smoothed or filtered) and weight, when it slides.
    next_arrival_mean: Option<Vec<f64>>,
    next_arrival_sqrt: Option<Vec<f64>>,
    /// What the update changes in the learning state, if the estimator learns.
    learning: Option<LearningUpdate>,
}

/// The data of one update.
#[derive(Debug, Clone, Copy, Default)]
pub struct Step<'a> {
    /// u(t); None: not known yet (see [`MovingHorizon::prepare`]).
    pub u: Option<&'a [f64]>,
    /// y(t); None: not measured.
    pub y: Option<&'a [f64]>,
    /// The covariance of y(t) (p or p² values, as R0), kept with it; None: R0.
    pub r: Option<&'a [f64]>,
    /// The input row of the last recorded step u(t − 1) as completed by this sample (see
    /// [`History::revise_last_input`]); None: as recorded.
    pub u_last: Option<&'a [f64]>,
}

/// See the module documentation.
#[derive(Debug, Clone)]
pub struct MovingHorizon {
    problem: WindowProblem,
    eval: WindowEval,
    /// z of the evaluation held in `eval` (empty: none).
    evaluated_at: Vec<f64>,
    history: History,
    /// The state box X, and X shrunk by `INNER_MARGIN` (for the warm start).
    x_bounds: (Vec<f64>, Vec<f64>),
    inner: (Vec<f64>, Vec<f64>),
    /// X stacked over the staged window's nodes.
    lower: Vec<f64>,
    upper: Vec<f64>,
    solver: BoxLsqSolver,
    opts: SolverOptions,
    /// The staged step (after `prepare`), recorded by `commit`.
    staged: Option<WindowData>,
    /// Whether the problem holds a window (staged, or set by `set_window`).
    has_window: bool,
    /// The arrival cost's mean and weight (`arrival.rs`).
    arrival: Arrival,
    /// The last one-step prediction: the filtering form's commit computes the one the next
    /// warm start needs.
    prediction: LastPrediction,
    /// How many times the weights were replaced (`set_weights`): lets a caller that keeps its
    /// own copy of the weights tell whether a replacement took effect.
    weights_version: u64,
    /// The model's global variables estimated with the states (`learning_state.rs`), if any.
    learning: Option<Learning>,
    /// The innovation of the newest sample once computed ([`MovingHorizon::innovation`]);
    /// every method that changes what it reads forgets it.
    innovation_memo: Option<Innovation>,
}

/// A one-step prediction m_x(x, u) with the model's global variables g (none without learning)
/// and the bits of the point it was made at (a model is a function of (x, u, g), so the same
/// point gives the same prediction without calling it again).
#[derive(Debug, Clone, Default)]
struct LastPrediction {
    d: Vec<u64>,
    x_next: Vec<f64>,
}

impl LastPrediction {
    /// m_x(x, u) with the model's global variables set to `g` (left as they are when empty).
    fn predict(
        &mut self,
        model: &mut dyn StageModel,
        (x, u, g): (&[f64], &[f64], &[f64]),
        out: &mut [f64],
    ) -> Result<()> {
        let point = || x.iter().chain(u).chain(g);
        let same = self.d.len() == x.len() + u.len() + g.len()
            && point().zip(&self.d).all(|(v, b)| v.to_bits() == *b)
            && self.x_next.len() == out.len();
        if same {
            out.copy_from_slice(&self.x_next);
            return Ok(());
        }
        self.d.clear();
        if !g.is_empty() {
            model.set_globals(g)?;
        }
        model.predict_state(x, u, out)?;
        self.d.extend(point().map(|v| v.to_bits()));
        self.x_next.clear();
        self.x_next.extend_from_slice(out);
        Ok(())
    }
}

impl MovingHorizon {
    /// An estimator at x̂(0) = x0 with horizon M ≥ 1 and the box lower < upper (entries may be
    /// ±∞) for every window state.
    pub fn new(
        problem: WindowProblem,
        horizon: usize,
        x0: &[f64],
        lower: &[f64],
        upper: &[f64],
        opts: SolverOptions,
    ) -> Result<Self> {
        opts.validate()?;
        let n = problem.dim_x();
        let history = History::new(
            horizon,
            problem.form(),
            (n, problem.dim_u(), problem.dim_y()),
            x0,
        )?;
        check_len("x_bounds", lower, n)?;
        check_len("x_bounds", upper, n)?;
        if (0..n).any(|a| lower[a].is_nan() || upper[a].is_nan() || lower[a] >= upper[a]) {
            return Err(Error::invalid(
                "x_bounds",
                "need lower < upper, without NaN",
            ));
        }
        let width = |a: usize| match upper[a] - lower[a] {
            w if w.is_finite() => w,
            _ => 1.0,
        };
        let inner = (
            (0..n).map(|a| lower[a] + INNER_MARGIN * width(a)).collect(),
            (0..n).map(|a| upper[a] - INNER_MARGIN * width(a)).collect(),
        );
        let mut history = history;
        history.set_arrival_sqrt(problem.p2_sqrt().to_vec());
        history.reset(x0, initial_covariance(&problem)?)?;
        Ok(Self {
            problem,
            eval: WindowEval::default(),
            evaluated_at: Vec::new(),
            history,
            x_bounds: (lower.to_vec(), upper.to_vec()),
            inner,
            lower: Vec::new(),
            upper: Vec::new(),
            solver: BoxLsqSolver::new(),
            opts,
            staged: None,
            has_window: false,
            arrival: Arrival::default(),
            prediction: LastPrediction::default(),
            weights_version: 0,
            learning: None,
            innovation_memo: None,
        })
    }

    /// Makes the estimator estimate the model's n_g global variables g with the states (a GP
    /// that keeps learning), from the prior N(g0, sigma0) (n_g² values, row-major), g drifting
    /// by a random walk of variance `drift` per step. The arrival cost then follows the joint
    /// EKF of the first state and g (`joint_arrival.rs`), whatever the arrival weight setting.
    /// Only before the first update; on error nothing changes.
    pub fn enable_learning(&mut self, g0: &[f64], sigma0: &[f64], drift: f64) -> Result<()> {
        self.innovation_memo = None;
        if self.history.t() != 0 {
            return Err(Error::invalid(
                "learning",
                "must be enabled before the first update",
            ));
        }
        self.learning = Some(Learning::new(
            g0,
            sigma0,
            drift,
            &initial_covariance(&self.problem)?,
        )?);
        self.staged = None;
        self.has_window = false;
        Ok(())
    }

    /// The learning part (None unless [`MovingHorizon::enable_learning`]).
    pub fn learning(&self) -> Option<&Learning> {
        self.learning.as_ref()
    }

    /// A learning part from its prior (as [`MovingHorizon::enable_learning`] takes it) and
    /// state, checked, for [`MovingHorizon::set_learning`] (copies and checkpoints).
    pub fn restored_learning(
        &self,
        g0: &[f64],
        sigma0: &[f64],
        drift: f64,
        state: LearningState,
    ) -> Result<Learning> {
        let mut l = Learning::new(g0, sigma0, drift, &initial_covariance(&self.problem)?)?;
        l.set_state(self.problem.dim_x(), state)?;
        Ok(l)
    }

    /// Installs (or removes) the learning part; drops any staged window.
    pub fn set_learning(&mut self, learning: Option<Learning>) {
        self.innovation_memo = None;
        self.learning = learning;
        self.staged = None;
        self.has_window = false;
        self.evaluated_at.clear();
    }

    /// Replaces the learning state (checkpoints; see [`Learning::set_state`]); an error if the
    /// estimator does not learn. Drops any staged window; nothing changes on error.
    pub fn set_learning_state(&mut self, state: LearningState) -> Result<()> {
        self.innovation_memo = None;
        let n = self.problem.dim_x();
        let l = self
            .learning
            .as_mut()
            .ok_or_else(|| Error::invalid("learning", "this estimator does not learn"))?;
        l.set_state(n, state)?;
        self.staged = None;
        self.has_window = false;
        self.evaluated_at.clear();
        Ok(())
    }

    /// How many times the weights were replaced since construction.
    pub fn weights_version(&self) -> u64 {
        self.weights_version
    }

    /// The arrival cost settings.
    pub fn arrival(&self) -> Arrival {
        self.arrival
    }

    /// Sets the arrival cost; takes effect from the next window (the EKF weight recursion
    /// starts from the current arrival weight).
    pub fn set_arrival(&mut self, arrival: Arrival) {
        self.innovation_memo = None;
        self.arrival = arrival;
    }

    /// Replaces the weights given (η, Q0, R0, S of P2 = SᵀS; see
    /// [`WindowProblem::set_weights`]) from the next window on and keeps the others. A new P2
    /// also becomes the arrival weight of the next window (restarting the EKF recursion); the
    /// other weights leave the arrival weight as it is. Drops any staged window. On error
    /// nothing changes.
    pub fn set_weights(
        &mut self,
        eta: Option<f64>,
        q0: Option<&[f64]>,
        r0: Option<&[f64]>,
        p2_sqrt: Option<&[f64]>,
    ) -> Result<()> {
        self.innovation_memo = None;
        let p = &self.problem;
        let (q0_now, r0_now, p2_now) = (p.q0().to_vec(), p.r0().to_vec(), p.p2_sqrt().to_vec());
        // With learning, a new P2 restarts the states' block of the joint arrival prior.
        let restart = match (p2_sqrt, &self.learning) {
            (Some(s), Some(_)) => {
                check_len("P2", s, p.dim_x() * p.dim_x())?;
                Some(covariance_of_sqrt(p.dim_x(), s)?)
            }
            _ => None,
        };
        self.problem.set_weights(
            eta.unwrap_or(p.eta()),
            q0.unwrap_or(&q0_now),
            r0.unwrap_or(&r0_now),
            p2_sqrt.unwrap_or(&p2_now),
        )?;
        if let Some(s) = p2_sqrt {
            self.history.set_arrival_sqrt(s.to_vec());
        }
        if let (Some(x_cov), Some(l)) = (restart, self.learning.as_mut()) {
            l.restart_states(&x_cov);
        }
        self.weights_version += 1;
        self.staged = None;
        self.has_window = false;
        self.evaluated_at.clear();
        Ok(())
    }

    /// Replaces u(t − 1), the input of the last update (given as a placeholder when u(t) was not
    /// known yet in the filtering form). With the paper's arrival mean in the filtering form the
    /// newest arrival prior m_x(x̂(t−1), u(t−1)) is recomputed with it. On error nothing
    /// changes.
    pub fn set_last_input(&mut self, model: &mut dyn StageModel, u: &[f64]) -> Result<()> {
        self.innovation_memo = None;
        let (n, m) = (self.problem.dim_x(), self.problem.dim_u());
        check_len("u", u, m)?;
        check_finite("u", u)?;
        if !self.history.outcome().input_pending {
            return Err(Error::invalid(
                "u",
                "no update is waiting for its input (set_input follows an update given u=None)",
            ));
        }
        let mut prior = None;
        if self.problem.form() == Form::Filtering && self.arrival.mean == ArrivalMean::Estimate {
            let (window, _) = self.history.x_window();
            let mut out = vec![0.0; n];
            let g = self.learning.as_ref().map_or(&[][..], |l| &l.state().g[..]);
            let x = &window[window.len() - n..];
            self.prediction.predict(model, (x, u, g), &mut out)?;
            check_finite("u", &out)
                .map_err(|_| Error::numerical("the model's prediction with u is not finite"))?;
            prior = Some(out);
        }
        self.history.set_last_input(u);
        if let Some(prior) = prior {
            self.history.set_newest_prior(&prior);
        }
        self.history.set_input_given();
        self.staged = None;
        Ok(())
    }

    /// Forgets every step: t = 0, x̂(0) = x0 with covariance P2⁻¹, arrival weight P2.
    pub fn reset(&mut self, x0: &[f64]) -> Result<()> {
        self.innovation_memo = None;
        let x_cov = initial_covariance(&self.problem)?;
        if let Some(l) = self.learning.as_mut() {
            let mut fresh = l.clone();
            fresh.reset(&x_cov)?;
            self.history.reset(x0, x_cov)?;
            self.learning = Some(fresh);
        } else {
            self.history.reset(x0, x_cov)?;
        }
        self.history
            .set_arrival_sqrt(self.problem.p2_sqrt().to_vec());
        self.staged = None;
        self.has_window = false;
        self.evaluated_at.clear();
        Ok(())
    }

    pub fn problem(&self) -> &WindowProblem {
        &self.problem
    }

    pub fn history(&self) -> &History {
        &self.history
    }

    /// The staged window's evaluation (after [`MovingHorizon::evaluate`] or an update).
    pub fn eval(&self) -> &WindowEval {
        &self.eval
    }

    /// The box for the staged window's stacked states.
    pub fn bounds(&self) -> (&[f64], &[f64]) {
        (&self.lower, &self.upper)
    }

    /// The state box X (lower, upper).
    pub fn x_bounds(&self) -> (&[f64], &[f64]) {
        (&self.x_bounds.0, &self.x_bounds.1)
    }

    /// The solver settings.
    pub fn options(&self) -> &SolverOptions {
        &self.opts
    }

    /// The history's state (see [`HistoryState`]): with the settings, all an update depends on.
    pub fn history_state(&self) -> HistoryState {
        self.history.state()
    }

    /// Replaces the history's state (validated, see [`History::set_state`]) and drops any staged
    /// window; on error nothing changes.
    pub fn set_history_state(&mut self, state: HistoryState) -> Result<()> {
        self.innovation_memo = None;
        self.history.set_state(state)?;
        self.staged = None;
        self.has_window = false;
        self.evaluated_at.clear();
        Ok(())
    }

    /// One whole update with (u(t), y(t)) (`y` None: not measured; `u` None: not known yet,
    /// see [`MovingHorizon::prepare`]); see the module docs. On error nothing is recorded and
    /// nothing stays staged.
    pub fn update(
        &mut self,
        model: &mut dyn StageModel,
        u: Option<&[f64]>,
        y: Option<&[f64]>,
    ) -> Result<UpdateReport> {
        self.update_step(
            model,
            Step {
                u,
                y,
                ..Step::default()
            },
        )
    }

    /// One whole update with the data of `step`: (u(t), y(t)) as for [`MovingHorizon::update`],
    /// the covariance of y(t) (kept while the sample is in the window) and the revised last
    /// input row.
    pub fn update_step(
        &mut self,
        model: &mut dyn StageModel,
        step: Step<'_>,
    ) -> Result<UpdateReport> {
        let (pending, report) = self.solve_step(model, step)?;
        self.apply(pending);
        Ok(report)
    }

    /// Solves the window of `step` as [`MovingHorizon::update_step`] does, without recording
    /// it: the history is unchanged until [`MovingHorizon::apply`] records the result (so a
    /// bank can record its estimators' updates only once every one has succeeded). On error
    /// nothing stays staged.
    pub fn solve_step(
        &mut self,
        model: &mut dyn StageModel,
        step: Step<'_>,
    ) -> Result<(Pending, UpdateReport)> {
        let solved = self.solve_staged(model, step);
        if solved.is_err() {
            self.staged = None;
        }
        solved
    }

    fn solve_staged(
        &mut self,
        model: &mut dyn StageModel,
        step: Step<'_>,
    ) -> Result<(Pending, UpdateReport)> {
        let z0 = self.prepare_step(model, step)?;
        let mut z = z0.clone();
        self.evaluated_at.clear();
        let solve = {
            let mut lsq = WindowLsq {
                problem: &self.problem,
                model: &mut *model,
                eval: &mut self.eval,
            };
            self.solver
                .solve(&mut lsq, &mut z, &self.lower, &self.upper, &self.opts)
        };
        let (solve, cost, cov) = match solve {
            Ok(report) => {
                self.evaluated_at.extend_from_slice(&z);
                let cov = match self.learning {
                    Some(_) => self.solver.window_and_global_covariance(),
                    None => Covariances {
                        window: self.window_covariance(),
                        ..Covariances::default()
                    },
                };
                (Ok(report.clone()), report.cost, cov)
            }
            // A numerical failure keeps the warm start; anything else is an error.
            Err(e @ Error::Numerical(_)) => {
                z = z0;
                let cost = self.evaluate(model, &z, false)?.cost();
                (Err(e), cost, Covariances::default())
            }
            Err(e) => return Err(e),
        };
        let n = self.problem.dim_x();
        let covariance = cov.window.as_deref().map(|b| last_block(b, n * n));
        let solved = Solved::Rust(solve.clone());
        let pending = self.finish_with(model, z, cov, cost, &solved)?;
        let report = UpdateReport {
            x_window: pending.x_window.clone(),
            x_prior: pending.data.x_prior.clone(),
            covariance,
            solve,
            cost,
        };
        Ok((pending, report))
    }

    /// The covariance of the nodes of the window just solved (without learning; nodes × n × n):
    /// 4H⁻¹'s diagonal blocks when η = 1; with η < 1 the discounted rows weigh the data by less
    /// than their information, so the covariance of the estimate is the sandwich 4H⁻¹GH⁻¹, G the
    /// Gauss-Newton Hessian with every row's discount applied twice (docs/user_guide/
    /// uncertainty.rst). None as for [`BoxLsqSolver::window_covariance`].
    fn window_covariance(&mut self) -> Option<Vec<f64>> {
        if self.problem.eta() == 1.0 {
            return self.solver.window_covariance();
        }
        let (nodes, n) = (self.problem.n_nodes(), self.problem.dim_x());
        let discounts = self.problem.row_discounts(&self.eval);
        let mut diag = vec![0.0; nodes * n * n];
        let mut off = vec![0.0; nodes.saturating_sub(1) * n * n];
        self.eval
            .discounted_gauss_newton_blocks_into(&discounts, &mut diag, &mut off);
        self.solver.sandwich_window_covariance(&diag, &off)
    }

    /// Stages the window of the next update with (u(t), y(t)) and returns its warm start z0:
    /// the previous window's nodes that overlap the new one, each further node predicted from
    /// the one before with the model, all clipped into the inner box (nodes already inside stay
    /// bit-identical, so the learned model reuses their GP values). The history is unchanged.
    ///
    /// `u` None (u(t) not known yet; filtering form only, or a model without inputs) stands in
    /// u(t − 1) (zeros at t = 0), which only the output at the newest node reads; the update
    /// then waits for u(t) ([`MovingHorizon::set_last_input`]) before the next one.
    pub fn prepare(
        &mut self,
        model: &mut dyn StageModel,
        u: Option<&[f64]>,
        y: Option<&[f64]>,
    ) -> Result<Vec<f64>> {
        self.prepare_step(
            model,
            Step {
                u,
                y,
                ..Step::default()
            },
        )
    }

    /// [`MovingHorizon::prepare`] with the data of `step`.
    pub fn prepare_step(&mut self, model: &mut dyn StageModel, step: Step<'_>) -> Result<Vec<f64>> {
        self.staged = None;
        let r = self.sample_covariance(step.y, step.r)?;
        let mut data = self.next_window(step.u, step.y, r)?;
        if let Some(u_last) = step.u_last {
            self.revise_last_input(model, &mut data, u_last)?;
        }
        self.problem
            .set_data(&data.u, &data.y, &data.present, &data.x_prior)?;
        self.problem.set_output_covariances(&data.r)?;
        let weight = match self.arrival.weight {
            ArrivalWeight::Constant => self.problem.p2_sqrt().to_vec(),
            ArrivalWeight::Ekf => self.history.arrival_sqrt().to_vec(),
        };
        self.problem.set_prior_weight(&weight)?;
        if let Some(l) = &self.learning {
            l.prepare(model, &mut self.problem)?;
        }
        self.evaluated_at.clear();
        let mut z0 = self.warm_start(model, &data)?;
        let n = self.problem.dim_x();
        self.lower.clear();
        self.upper.clear();
        for _ in 0..data.nodes {
            self.lower.extend_from_slice(&self.x_bounds.0[..n]);
            self.upper.extend_from_slice(&self.x_bounds.1[..n]);
        }
        if let Some(l) = &self.learning {
            // The global variables: warm-started at the last posterior mean, unbounded.
            z0.extend_from_slice(&l.state().g);
            self.lower
                .resize(self.lower.len() + l.dim(), f64::NEG_INFINITY);
            self.upper.resize(self.upper.len() + l.dim(), f64::INFINITY);
        }
        self.staged = Some(data);
        self.has_window = true;
        Ok(z0)
    }

    /// Revises u(t − 1) in the window `data` ([`History::revise_last_input`]). With the paper's
    /// arrival mean the arrival prior of time t, the prediction from x̂(t − 1), is made again
    /// with it. The prediction form with horizon 1 refuses: its window holds no stage the row
    /// belongs to, and its arrival prior and weight were carried over the old row.
    fn revise_last_input(
        &mut self,
        model: &mut dyn StageModel,
        data: &mut WindowData,
        u: &[f64],
    ) -> Result<()> {
        let form = self.problem.form();
        if form == Form::Prediction && self.history.horizon() == 1 {
            return Err(Error::invalid(
                "u_last",
                "the prediction form with horizon 1 cannot revise the last step (its arrival \
                 cost was carried over it)",
            ));
        }
        self.history.revise_last_input(data, u)?;
        if self.arrival.mean == ArrivalMean::Estimate {
            let n = self.problem.dim_x();
            let (window, _) = self.history.x_window();
            // x̂(t − 1): the last node (filtering form) or the one before it (prediction form).
            let from = window.len() - if form == Form::Filtering { n } else { 2 * n };
            let mut out = vec![0.0; n];
            let g = self.learning.as_ref().map_or(&[][..], |l| &l.state().g[..]);
            let x = &window[from..from + n];
            self.prediction.predict(model, (x, u, g), &mut out)?;
            check_finite("u_last", &out).map_err(|_| {
                Error::numerical("the model's prediction with the revised input is not finite")
            })?;
            data.last_prior = Some(out);
        }
        Ok(())
    }

    /// The covariance given with an output sample (p or p² values), checked; None for R0.
    fn sample_covariance(
        &self,
        y: Option<&[f64]>,
        r: Option<&[f64]>,
    ) -> Result<Option<Covariance>> {
        match (y, r) {
            (_, None) => Ok(None),
            (None, Some(_)) => Err(Error::invalid("R", "given without an output y")),
            (Some(_), Some(r)) => Covariance::new("R", r, self.problem.dim_y()).map(Some),
        }
    }

    /// Records an output measured `age` steps before the newest one, with its covariance `r`
    /// (None: R0), for the windows from the next update on ([`History::add_delayed`]). Drops any
    /// staged window; on error nothing changes.
    pub fn add_delayed(&mut self, y: &[f64], age: usize, r: Option<&[f64]>) -> Result<()> {
        self.innovation_memo = None;
        let r = self.sample_covariance(Some(y), r)?;
        self.history.add_delayed(y, age, r, self.problem.r0_cov())?;
        self.staged = None;
        self.has_window = false;
        self.evaluated_at.clear();
        Ok(())
    }

    /// The next window's data, with the placeholder input when `u` is None (see `prepare`).
    fn next_window(
        &self,
        u: Option<&[f64]>,
        y: Option<&[f64]>,
        r: Option<Covariance>,
    ) -> Result<WindowData> {
        let m = self.problem.dim_u();
        if self.history.outcome().input_pending {
            return Err(Error::invalid(
                "u",
                "the last update was given u=None; call set_input(u) with the input applied at \
                 that step before the next update",
            ));
        }
        match u {
            Some(u) => self.history.next_window(u, y, r),
            None if m == 0 => self.history.next_window(&[], y, r),
            None if self.problem.form() == Form::Prediction => Err(Error::invalid(
                "u",
                format!(
                    "required (dim_u = {m}; only the filtering form accepts None, see set_input)"
                ),
            )),
            None => {
                let zeros = vec![0.0; m];
                let last = self.history.last_input().unwrap_or(&zeros);
                let mut data = self.history.next_window(last, y, r)?;
                data.input_pending = true;
                Ok(data)
            }
        }
    }

    fn warm_start(&mut self, model: &mut dyn StageModel, data: &WindowData) -> Result<Vec<f64>> {
        let (n, m) = (self.problem.dim_x(), self.problem.dim_u());
        let (prev, prev_t0) = self.history.x_window();
        let rows = prev.len() / n;
        let first = data.s0 - prev_t0;
        // The new window starts no later than the previous one ended: they overlap.
        let kept = rows.saturating_sub(first).min(data.nodes);
        if kept == 0 {
            return Err(Error::numerical("internal: windows do not overlap"));
        }
        let mut z = vec![0.0; data.nodes * n];
        z[..kept * n].copy_from_slice(&prev[first * n..(first + kept) * n]);
        let mut next = vec![0.0; n];
        for i in kept..data.nodes {
            let (done, rest) = z.split_at_mut(i * n);
            let u = &data.u[(i - 1) * m..i * m];
            let g = self.learning.as_ref().map_or(&[][..], |l| &l.state().g[..]);
            let x = &done[(i - 1) * n..i * n];
            self.prediction.predict(model, (x, u, g), &mut next)?;
            rest[..n].copy_from_slice(&next);
        }
        let (lo, hi) = &self.inner;
        for (k, v) in z.iter_mut().enumerate() {
            *v = v.clamp(lo[k % n], hi[k % n]);
        }
        Ok(z)
    }

    /// The staged window's evaluation at z (with the Jacobian if `want_jacobian`); reuses the
    /// last one when it was at the same z.
    pub fn evaluate(
        &mut self,
        model: &mut dyn StageModel,
        z: &[f64],
        want_jacobian: bool,
    ) -> Result<&WindowEval> {
        self.check_window()?;
        let cached =
            self.evaluated_at.as_slice() == z && (self.eval.has_jacobian() || !want_jacobian);
        if !cached {
            self.evaluated_at.clear();
            self.problem
                .evaluate(model, z, want_jacobian, &mut self.eval)?;
            self.evaluated_at.extend_from_slice(z);
        }
        Ok(&self.eval)
    }

    /// The discount of every residual row of the staged window evaluated at z
    /// ([`WindowProblem::row_discounts`]).
    pub fn row_discounts(&mut self, model: &mut dyn StageModel, z: &[f64]) -> Result<Vec<f64>> {
        self.evaluate(model, z, false)?;
        Ok(self.problem.row_discounts(&self.eval))
    }

    /// Records the staged window's solution z (nodes × n) with how it was solved (its cost,
    /// the covariance estimates of its nodes, nodes × n × n, whose last block is the estimate's,
    /// None if not computable, and the solver's report), all in one step: the next arrival prior
    /// is the new estimate (prediction form) or its one-step prediction m_x(x̄_t, u(t))
    /// (filtering form); when the next window starts one node later, the arrival cost moves with
    /// it (the smoothed or filtered mean and the EKF weight, `arrival.rs`). Returns (x_window,
    /// x_prior of the window). On error nothing changes: [`MovingHorizon::finish`] computes
    /// what may fail, [`MovingHorizon::apply`] records.
    pub fn commit(
        &mut self,
        model: &mut dyn StageModel,
        z: Vec<f64>,
        window_covariance: Option<Vec<f64>>,
        cost: f64,
        solved: &Solved,
    ) -> Result<(Vec<f64>, Vec<f64>)> {
        if self.learning.is_some() {
            return Err(Error::invalid(
                "solver",
                "an estimator that learns is solved by the core's solver only",
            ));
        }
        let cov = Covariances {
            window: window_covariance,
            ..Covariances::default()
        };
        let pending = self.finish_with(model, z, cov, cost, solved)?;
        let out = (pending.x_window.clone(), pending.data.x_prior.clone());
        self.apply(pending);
        Ok(out)
    }

    /// Everything [`MovingHorizon::commit`] computes (its fallible part, the model's
    /// evaluations), as a [`Pending`] record; the history is unchanged and the staged window
    /// is taken. With learning, z ends with g and `cov` has g's covariance and its cross
    /// covariance with the newest node (None: keep the last).
    fn finish_with(
        &mut self,
        model: &mut dyn StageModel,
        mut z: Vec<f64>,
        cov: Covariances,
        cost: f64,
        solved: &Solved,
    ) -> Result<Pending> {
        let Covariances {
            window: window_covariance,
            global: g_cov,
            cross: xg_cov,
        } = cov;
        let (n, m) = (self.problem.dim_x(), self.problem.dim_u());
        let data = self
            .staged
            .as_ref()
            .ok_or_else(|| Error::invalid("z", "no window staged: call prepare first"))?;
        let ng = self.learning.as_ref().map_or(0, Learning::dim);
        check_len("z", &z, data.nodes * n + ng)?;
        check_finite("z", &z)?;
        let g = z.split_off(data.nodes * n);
        if ng > 0 {
            model.set_globals(&g)?;
        }
        if let Some(c) = &window_covariance {
            check_len("P_window", c, data.nodes * n * n)?;
            check_finite("P_window", c)?;
        }
        let last = &z[z.len() - n..];
        let next_prior = match self.problem.form() {
            Form::Prediction => last.to_vec(),
            Form::Filtering => {
                let mut out = vec![0.0; n];
                let u_t = &data.u[(data.nodes - 1) * m..data.nodes * m];
                self.prediction.predict(model, (last, u_t, &g), &mut out)?;
                out
            }
        };
        let slides = self.history.window_start(self.history.t() + 1) == data.s0 + 1;
        let ekf_weight = self.arrival.weight == ArrivalWeight::Ekf;
        let filtered_mean = self.arrival.mean == ArrivalMean::Filtered;
        let (mut weight, mut mean) = (None, None);
        let mut learning = None;
        if let Some(l) = &self.learning {
            let (x_mean, mut arrival) = match slides {
                true => self.joint_arrival_step(model, l, data, &z, &g)?,
                false => (None, None),
            };
            mean = x_mean.filter(|_| filtered_mean);
            // The prior mean of g goes with that of x: with the smoothed x̄_1 of this window, its
            // g (the filter's g next to the smoother's x made the prior contradict the data).
            if let (ArrivalMean::Smoothed, Some(a)) = (self.arrival.mean, arrival.as_mut()) {
                a.g.clone_from(&g);
            }
            learning = Some(LearningUpdate {
                arrival,
                g,
                g_cov,
                xg_cov,
            });
        } else if slides && (ekf_weight || filtered_mean) {
            let p = self.problem.dim_y();
            let y0 = data.present[0].then(|| &data.y[..p]);
            let s = match self.arrival.weight {
                ArrivalWeight::Constant => self.problem.p2_sqrt(),
                ArrivalWeight::Ekf => self.history.arrival_sqrt(),
            };
            // The window's last evaluation holds the model's values at node 0 when it was
            // at z (the solver's solution); otherwise evaluate there.
            let fresh;
            let st = if self.evaluated_at == z {
                self.eval.stage()
            } else {
                fresh = evaluate_at(model, &z[..n], &data.u[..m])?;
                &fresh
            };
            // A numerical failure keeps the weight (and the mean: the estimate's prediction).
            if ekf_weight {
                weight = keep_on_numerical(ekf_step(st, &self.problem, y0, s))?;
            }
            if filtered_mean {
                let step = ekf_mean_step(st, &self.problem, y0, s, &data.x_prior, &z[..n]);
                mean = keep_on_numerical(step)?;
            }
        }
        let data = self
            .staged
            .take()
            .ok_or_else(|| Error::numerical("lost the window"))?;
        let (before, _) = self.history.x_window();
        let x_before = before[before.len() - n..].to_vec();
        let outcome = self.history.outcome().record(
            data.x_prior.clone(),
            window_covariance,
            data.nodes,
            x_before,
            cost,
            solved,
            data.input_pending,
        );
        let smoothed = (slides && self.arrival.mean == ArrivalMean::Smoothed && z.len() >= 2 * n)
            .then(|| z[n..2 * n].to_vec());
        Ok(Pending {
            data,
            x_window: z,
            next_prior,
            outcome,
            next_arrival_mean: mean.or(smoothed),
            next_arrival_sqrt: weight,
            learning,
        })
    }

    /// The joint arrival prior of the next window (`joint_arrival.rs`) over the staged window's
    /// first node at the solution (z, g): the filtered x̂ and the next [`JointArrival`]; (None,
    /// None) when the step fails numerically (the prior is kept).
    fn joint_arrival_step(
        &self,
        model: &mut dyn StageModel,
        l: &Learning,
        data: &WindowData,
        z: &[f64],
        g: &[f64],
    ) -> Result<(Option<Vec<f64>>, Option<super::JointArrival>)> {
        let (n, m, p) = (
            self.problem.dim_x(),
            self.problem.dim_u(),
            self.problem.dim_y(),
        );
        let y0 = data.present[0].then(|| &data.y[..p]);
        let mut at = z.to_vec();
        at.extend_from_slice(g);
        let fresh;
        let st = if self.evaluated_at == at {
            self.eval.stage()
        } else {
            fresh = evaluate_at(model, &z[..n], &data.u[..m])?;
            &fresh
        };
        let node = LeavingNode {
            st,
            z0: &z[..n],
            g,
            y0,
        };
        let step = joint_ekf_step(
            &self.problem,
            &node,
            &data.x_prior,
            &l.state().arrival,
            l.drift(),
        );
        Ok(match keep_on_numerical(step)? {
            Some((x, arrival)) => (Some(x), Some(arrival)),
            None => (None, None),
        })
    }

    /// Records a solved update ([`MovingHorizon::solve_step`]): the window's data and
    /// solution, the next arrival prior, the outcome, and the next window's arrival mean and
    /// weight when the window slides. Cannot fail.
    pub fn apply(&mut self, pending: Pending) {
        self.innovation_memo = None;
        let Pending {
            data,
            x_window,
            next_prior,
            outcome,
            next_arrival_mean,
            next_arrival_sqrt,
            learning,
        } = pending;
        let s0 = data.s0;
        self.history.push(data, x_window, next_prior, outcome);
        if let Some(prior) = next_arrival_mean {
            self.history.set_prior(s0 + 1, &prior);
        }
        if let Some(next) = next_arrival_sqrt {
            self.history.set_arrival_sqrt(next);
        }
        if let (Some(l), Some(update)) = (self.learning.as_mut(), learning) {
            l.apply(update);
        }
    }

    /// The innovation of the newest sample (`innovation.rs`), computed at the first call after
    /// a change of what it reads (the history, the weights, the learning state) and kept.
    pub fn innovation(&mut self, model: &mut dyn StageModel) -> Result<Innovation> {
        if let Some(memo) = &self.innovation_memo {
            return Ok(memo.clone());
        }
        let out = match &self.learning {
            None => innovation(&self.problem, &self.history, model, None)?,
            Some(l) => {
                let out = innovation(&self.problem, &self.history, model, Some(&l.state().before));
                // The model back at the posterior mean whatever happened (the filtering form's
                // prediction sets it to the posterior before; the output map does not depend
                // on it).
                model.set_globals(&l.state().g)?;
                out?
            }
        };
        self.innovation_memo = Some(out.clone());
        Ok(out)
    }

    /// The innovation kept by the last [`MovingHorizon::innovation`], if nothing it reads has
    /// changed since.
    pub fn kept_innovation(&self) -> Option<&Innovation> {
        self.innovation_memo.as_ref()
    }

    /// Drops the staged window, if any (its solve was abandoned); the history is unchanged.
    pub fn drop_staged(&mut self) {
        self.staged = None;
    }

    /// Sets the window data directly (for diagnostics and tests: such a window cannot be
    /// committed): `u` (nodes × m), `y` (nodes × p, rows ignored where not `present`), the
    /// arrival prior `x_prior`. On error the previous window is kept.
    pub fn set_window(
        &mut self,
        u: &[f64],
        y: &[f64],
        present: &[bool],
        x_prior: &[f64],
    ) -> Result<()> {
        self.innovation_memo = None;
        self.problem.set_data(u, y, present, x_prior)?;
        self.evaluated_at.clear();
        self.staged = None;
        self.has_window = true;
        Ok(())
    }

    fn check_window(&self) -> Result<()> {
        match self.has_window {
            true => Ok(()),
            false => Err(Error::invalid("z", "no window set: call prepare first")),
        }
    }

    /// Runs the solver on the staged window from z (in place) with other settings.
    pub fn solve_with(
        &mut self,
        model: &mut dyn StageModel,
        z: &mut [f64],
        lower: &[f64],
        upper: &[f64],
        solver: &mut BoxLsqSolver,
        opts: &SolverOptions,
    ) -> Result<SolveReport> {
        self.check_window()?;
        self.evaluated_at.clear();
        let mut lsq = WindowLsq {
            problem: &self.problem,
            model,
            eval: &mut self.eval,
        };
        let report = solver.solve(&mut lsq, z, lower, upper, opts)?;
        self.evaluated_at.extend_from_slice(z);
        Ok(report)
    }
}

/// Ok(None) for a numerical error (the caller keeps what it had), the value or the other errors.
fn keep_on_numerical<T>(r: Result<T>) -> Result<Option<T>> {
    match r {
        Ok(v) => Ok(Some(v)),
        Err(Error::Numerical(_)) => Ok(None),
        Err(e) => Err(e),
    }
}

/// P2⁻¹ = S⁻¹S⁻ᵀ (n × n, row-major, symmetric) for the window's P2 = SᵀS: the covariance of
/// x̂(0) before any update.
fn initial_covariance(problem: &WindowProblem) -> Result<Vec<f64>> {
    covariance_of_sqrt(problem.dim_x(), problem.p2_sqrt())
}

/// (SᵀS)⁻¹, symmetrised (n × n row-major), of S (n × n row-major); an error naming P2 if S is
/// singular.
fn covariance_of_sqrt(n: usize, s: &[f64]) -> Result<Vec<f64>> {
    let s = nalgebra::DMatrix::from_row_slice(n, n, s);
    let inv = s
        .try_inverse()
        .ok_or_else(|| Error::invalid("P2", "must be positive definite"))?;
    let p = &inv * inv.transpose();
    let sym = (0..n * n)
        .map(|k| 0.5 * (p[(k / n, k % n)] + p[(k % n, k / n)]))
        .collect::<Vec<_>>();
    check_finite("P2", &sym).map_err(|_| Error::invalid("P2", "its inverse is not finite"))?;
    Ok(sym)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mhe::StageEval;

    /// x(t+1) = 0.9 x + u, y = x (n = m = p = 1, exact: zero variances); fails from `fail_at`
    /// evaluations on.
    struct Scalar {
        calls: usize,
        fail_at: usize,
    }

    impl StageModel for Scalar {
        fn dim_x(&self) -> usize {
            1
        }
        fn dim_u(&self) -> usize {
            1
        }
        fn dim_y(&self) -> usize {
            1
        }
        fn evaluate(&mut self, d: &[f64], out: &mut StageEval) -> Result<()> {
            self.calls += 1;
            if self.calls >= self.fail_at {
                return Err(Error::invalid("model", "refused"));
            }
            let k = d.len() / 2;
            out.resize(k, 1, 1, 1);
            for i in 0..k {
                out.mean_x[i] = 0.9 * d[2 * i] + d[2 * i + 1];
                out.dmean_x[2 * i] = 0.9;
                out.dmean_x[2 * i + 1] = 1.0;
                out.mean_y[i] = d[2 * i];
                out.dmean_y[2 * i] = 1.0;
            }
            Ok(())
        }
    }

    /// `Scalar` plus a global variable g: x(t+1) = 0.9 x + u + g.
    struct Shifted {
        inner: Scalar,
        g: f64,
    }

    impl StageModel for Shifted {
        fn dim_x(&self) -> usize {
            1
        }
        fn dim_u(&self) -> usize {
            1
        }
        fn dim_y(&self) -> usize {
            1
        }
        fn n_globals(&self) -> usize {
            1
        }
        fn set_globals(&mut self, g: &[f64]) -> Result<()> {
            check_len("globals", g, 1)?;
            self.g = g[0];
            Ok(())
        }
        fn evaluate(&mut self, d: &[f64], out: &mut StageEval) -> Result<()> {
            self.inner.evaluate(d, out)?;
            out.mean_x.iter_mut().for_each(|v| *v += self.g);
            Ok(())
        }
    }

    #[test]
    fn the_last_prediction_is_reused_only_at_the_same_point_and_global_variables() {
        let mut model = Shifted {
            inner: Scalar {
                calls: 0,
                fail_at: usize::MAX,
            },
            g: 0.0,
        };
        let mut last = LastPrediction::default();
        let mut out = [0.0];
        let (x, u) = ([1.0], [0.5]);
        last.predict(&mut model, (&x, &u, &[1.0]), &mut out)
            .unwrap();
        assert_eq!((out[0], model.inner.calls), (0.9 + 0.5 + 1.0, 1));
        last.predict(&mut model, (&x, &u, &[1.0]), &mut out)
            .unwrap();
        assert_eq!(model.inner.calls, 1);
        // The same (x, u) with other global variables is another prediction, made with them
        // whatever the model held.
        model.g = 7.0;
        last.predict(&mut model, (&x, &u, &[2.0]), &mut out)
            .unwrap();
        assert_eq!((out[0], model.inner.calls), (0.9 + 0.5 + 2.0, 2));
    }

    fn estimator(form: Form) -> MovingHorizon {
        let problem = WindowProblem::new(1, 1, 1, 0.9, &[0.1], &[0.1], &[1.0], form).unwrap();
        let opts = SolverOptions::default();
        MovingHorizon::new(problem, 3, &[0.0], &[-10.0], &[10.0], opts).unwrap()
    }

    #[test]
    fn updates_track_a_noise_free_system_and_record_every_step() {
        for form in [Form::Prediction, Form::Filtering] {
            let mut est = estimator(form);
            let mut model = Scalar {
                calls: 0,
                fail_at: usize::MAX,
            };
            let (mut x, mut last_err) = (2.0, f64::INFINITY);
            for t in 0..8 {
                let u = [0.1 * t as f64];
                let rep = est.update(&mut model, Some(&u), Some(&[x])).unwrap();
                assert!(rep.solve.as_ref().is_ok_and(|s| s.status.is_success()));
                x = 0.9 * x + u[0];
                let estimate = rep.x_window[rep.x_window.len() - 1];
                let truth = if form == Form::Prediction {
                    x
                } else {
                    (x - u[0]) / 0.9
                };
                // From the poor x̂(0) = 0 the error shrinks at every step (by the dynamics' 0.9
                // once the window is full: the arrival prior carries it).
                let err = (estimate - truth).abs();
                assert!(err < last_err, "{form:?} t={t}: {err} after {last_err}");
                last_err = err;
                assert_eq!(est.history().t(), t + 1);
            }
            assert!(last_err < 1e-3, "{form:?}: {last_err}");
        }
    }

    /// Once the window is full, the filtering form's update calls the model for the solver's
    /// evaluations and once more, for the next arrival prior m_x(x̂(t), u(t)): the next warm
    /// start's new node is that same prediction, and the EKF arrival step reads node 0 from the
    /// solution's evaluation.
    #[test]
    fn a_full_window_update_calls_the_model_only_for_the_solver() {
        let mut est = estimator(Form::Filtering);
        est.set_arrival(Arrival {
            mean: ArrivalMean::Smoothed,
            weight: ArrivalWeight::Ekf,
        });
        let mut model = Scalar {
            calls: 0,
            fail_at: usize::MAX,
        };
        let mut x = 2.0;
        for t in 0..10 {
            let u = [0.1 * t as f64];
            let before = model.calls;
            let rep = est.update(&mut model, Some(&u), Some(&[x])).unwrap();
            x = 0.9 * x + u[0];
            if t >= 5 {
                let nfev = rep.solve.as_ref().map(|s| s.nfev).unwrap();
                assert_eq!(model.calls - before, nfev + 1, "t = {t}");
            }
        }
    }

    #[test]
    fn a_failing_model_leaves_the_estimator_unchanged() {
        let mut est = estimator(Form::Prediction);
        let mut model = Scalar {
            calls: 0,
            fail_at: usize::MAX,
        };
        for t in 0..4 {
            est.update(&mut model, Some(&[0.0]), Some(&[t as f64]))
                .unwrap();
        }
        let before = (est.history().x_window().0.to_vec(), est.history().t());
        model.fail_at = model.calls + 2; // fails inside the solve
        let err = est
            .update(&mut model, Some(&[0.0]), Some(&[1.0]))
            .unwrap_err();
        assert!(err.to_string().starts_with("model:"));
        assert_eq!(
            (est.history().x_window().0.to_vec(), est.history().t()),
            before
        );
        let solved = Solved::Other {
            success: true,
            nit: 0,
            message: String::new(),
        };
        assert!(est
            .commit(&mut model, vec![0.0; 4], None, 0.0, &solved)
            .is_err()); // nothing left staged
                        // Bad input is refused before anything is staged.
        model.fail_at = usize::MAX;
        assert!(est.update(&mut model, Some(&[0.0, 1.0]), None).is_err());
        assert_eq!(est.history().t(), 4);
        est.update(&mut model, Some(&[0.0]), None).unwrap();
        assert_eq!(est.history().t(), 5);
    }

    /// Only a new P2 restarts the EKF arrival weight; η, Q0 and R0 leave it as it is.
    #[test]
    fn weights_other_than_p2_keep_the_arrival_weight() {
        let mut est = estimator(Form::Prediction);
        est.set_arrival(Arrival {
            mean: ArrivalMean::Smoothed,
            weight: ArrivalWeight::Ekf,
        });
        let mut model = Scalar {
            calls: 0,
            fail_at: usize::MAX,
        };
        for t in 0..6 {
            est.update(&mut model, Some(&[0.0]), Some(&[t as f64]))
                .unwrap();
        }
        let weight = est.history().arrival_sqrt().to_vec();
        assert_ne!(weight, est.problem().p2_sqrt());
        est.set_weights(Some(0.5), Some(&[0.2]), Some(&[0.3]), None)
            .unwrap();
        assert_eq!(est.history().arrival_sqrt(), weight);
        assert_eq!((est.problem().eta(), est.problem().q0()), (0.5, &[0.2][..]));
        // A refused weight changes nothing.
        assert!(est.set_weights(None, Some(&[-1.0]), None, None).is_err());
        assert_eq!(est.problem().q0(), &[0.2]);
        est.set_weights(None, None, None, Some(&[2.0])).unwrap();
        assert_eq!(est.history().arrival_sqrt(), &[2.0]);
    }

    /// The outcome is recorded with the step, and an update that fails leaves it as it was.
    #[test]
    fn the_outcome_is_recorded_with_the_step_or_not_at_all() {
        let mut est = estimator(Form::Prediction);
        assert_eq!(est.history().outcome().covariance, vec![1.0]); // P2⁻¹
        let mut model = Scalar {
            calls: 0,
            fail_at: usize::MAX,
        };
        let rep = est.update(&mut model, Some(&[0.0]), Some(&[1.0])).unwrap();
        let out = est.history().outcome().clone();
        assert_eq!(out.cost, rep.cost);
        assert_eq!(Some(out.covariance.clone()), rep.covariance);
        assert!(out.success && out.message.starts_with("gradient-tolerance"));
        model.fail_at = model.calls + 1;
        assert!(est.update(&mut model, Some(&[0.0]), Some(&[2.0])).is_err());
        assert_eq!(est.history().outcome(), &out);
        assert_eq!(est.history().t(), 1);
    }

    /// u = None: refused in the prediction form; in the filtering form the update runs with a
    /// placeholder and the next one waits until the input is given.
    #[test]
    fn an_input_not_known_yet_must_be_given_before_the_next_update() {
        let mut model = Scalar {
            calls: 0,
            fail_at: usize::MAX,
        };
        let mut pred = estimator(Form::Prediction);
        let err = pred.update(&mut model, None, Some(&[1.0])).unwrap_err();
        assert!(err.to_string().starts_with("u: required"));
        let mut est = estimator(Form::Filtering);
        assert!(est.set_last_input(&mut model, &[0.5]).is_err());
        est.update(&mut model, None, Some(&[1.0])).unwrap();
        assert!(est.history().outcome().input_pending);
        let err = est
            .update(&mut model, Some(&[0.0]), Some(&[1.0]))
            .unwrap_err();
        assert!(err.to_string().contains("set_input"));
        est.set_last_input(&mut model, &[0.5]).unwrap();
        assert!(!est.history().outcome().input_pending);
        assert_eq!(est.history().last_input(), Some(&[0.5][..]));
        est.update(&mut model, Some(&[0.0]), Some(&[1.0])).unwrap();
        assert_eq!(est.history().t(), 2);
    }

    /// An input row completed only by the next sample (`Step::u_last`) gives the windows the
    /// data they would have had with the input on time: bit for bit in the filtering form, and
    /// to rounding for every node but the predicted one in the prediction form (a placeholder
    /// near a bound would move them through the barrier); the paper's arrival mean is predicted
    /// again with the completed row.
    #[test]
    fn a_last_input_completed_by_the_next_sample_counts_as_given_on_time() {
        let inputs = [0.3, -0.2, 0.5, 0.1, -0.4, 0.2, 0.0, 0.6];
        for (form, mean) in [
            (Form::Filtering, ArrivalMean::Smoothed),
            (Form::Filtering, ArrivalMean::Estimate),
            (Form::Prediction, ArrivalMean::Smoothed),
            (Form::Prediction, ArrivalMean::Estimate),
        ] {
            let arrival = Arrival {
                mean,
                weight: ArrivalWeight::Ekf,
            };
            let (mut on_time, mut late) = (estimator(form), estimator(form));
            on_time.set_arrival(arrival);
            late.set_arrival(arrival);
            let mut model = Scalar {
                calls: 0,
                fail_at: usize::MAX,
            };
            for (t, &u) in inputs.iter().enumerate() {
                let y = [(t as f64 * 0.7).sin()];
                on_time.update(&mut model, Some(&[u]), Some(&y)).unwrap();
                let revised = [inputs[t.max(1) - 1]];
                let step = Step {
                    u: Some(&[2.0]), // a placeholder, completed by the next sample
                    y: Some(&y),
                    r: None,
                    u_last: (t > 0).then_some(&revised[..]),
                };
                late.update_step(&mut model, step).unwrap();
                let (a, _) = on_time.history().x_window();
                let (b, _) = late.history().x_window();
                match form {
                    Form::Filtering => assert_eq!(a, b, "{mean:?} t={t}"),
                    Form::Prediction => {
                        for (x, z) in a.iter().zip(b).take(a.len() - 1) {
                            assert!((x - z).abs() < 1e-10, "{mean:?} t={t}: {x} vs {z}");
                        }
                    }
                }
            }
        }
        // Nothing to complete before the first step; a row of the wrong size is refused.
        let mut est = estimator(Form::Filtering);
        let mut model = Scalar {
            calls: 0,
            fail_at: usize::MAX,
        };
        let first = Step {
            u: Some(&[0.0]),
            y: Some(&[1.0]),
            r: None,
            u_last: Some(&[0.0]),
        };
        let err = est.update_step(&mut model, first).unwrap_err();
        assert!(err.to_string().starts_with("u_last:"));
        est.update(&mut model, Some(&[0.0]), Some(&[1.0])).unwrap();
        let wide = Step {
            u_last: Some(&[0.0, 1.0]),
            ..first
        };
        assert!(est.update_step(&mut model, wide).is_err());
        assert_eq!(est.history().t(), 1);
    }
}
