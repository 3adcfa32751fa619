//! What a moving-horizon estimator carries when its model has global variables g (a GP that keeps
//! learning, `learning.rs`): the joint arrival prior of the window's first state and g
//! (`joint_arrival.rs`), the posterior of g after the last update (the next warm start, and what
//! a snapshot of the learned model is made of), the random-walk drift of g per step, and the
//! prior g starts from (for a reset).
//!
//! Before each window the estimator hands the model the last posterior mean
//! ([`StageModel::set_globals`]) and the window the joint prior ([`Learning::prepare`]); the
//! model's state is thus a function of the estimator's, and a failed update leaves nothing to
//! undo.

use super::joint_arrival::{joint_sqrt, JointArrival};
use super::problem::WindowProblem;
use super::stage::StageModel;
use crate::error::{check_finite, check_len, Error, Result};

/// The learning part of an estimator (module docs).
#[derive(Debug, Clone)]
pub struct Learning {
    drift: f64,
    /// The prior of g at t = 0: mean and covariance (n_g², row-major).
    g0: Vec<f64>,
    sigma0: Vec<f64>,
    state: LearningState,
}

/// The learning state an update changes (for checkpoints): the joint arrival prior of the
/// window's first node, the posterior of g after the last update (mean, n_g × n_g covariance
/// and its cross covariance with the newest node, n × n_g, row-major), and that posterior as it
/// was before the last update ([`GlobalsBefore`]).
#[derive(Debug, Clone, PartialEq)]
pub struct LearningState {
    pub arrival: JointArrival,
    pub g: Vec<f64>,
    pub g_cov: Vec<f64>,
    pub xg_cov: Vec<f64>,
    pub before: GlobalsBefore,
}

/// The posterior of g before the last update: what the innovation of the filtering form
/// predicts the newest state with (`innovation.rs`): x̂(t − 1) and g are jointly uncertain.
/// NaN when not known: from a checkpoint of format 8, which kept neither it nor the cross
/// covariance, until the second update after loading.
#[derive(Debug, Clone, PartialEq)]
pub struct GlobalsBefore {
    pub g: Vec<f64>,
    pub g_cov: Vec<f64>,
    pub xg_cov: Vec<f64>,
}

impl GlobalsBefore {
    /// NaN-filled, for n states and n_g global variables.
    pub fn unknown(n: usize, ng: usize) -> Self {
        Self {
            g: vec![f64::NAN; ng],
            g_cov: vec![f64::NAN; ng * ng],
            xg_cov: vec![f64::NAN; n * ng],
        }
    }

    /// Whether every value is known (finite).
    pub fn is_known(&self) -> bool {
        self.g
            .iter()
            .chain(&self.g_cov)
            .chain(&self.xg_cov)
            .all(|v| v.is_finite())
    }
}

impl Learning {
    /// Learning from the prior N(g0, sigma0) with `drift` ≥ 0 per step, the states' initial
    /// covariance being `x_cov` (n × n).
    pub fn new(g0: &[f64], sigma0: &[f64], drift: f64, x_cov: &[f64]) -> Result<Self> {
        let ng = g0.len();
        if ng == 0 {
            return Err(Error::invalid("g0", "needs at least one global variable"));
        }
        check_len("sigma0", sigma0, ng * ng)?;
        check_finite("g0", g0)?;
        check_finite("sigma0", sigma0)?;
        if !(drift.is_finite() && drift >= 0.0) {
            return Err(Error::invalid("drift", "must be finite and >= 0"));
        }
        // Positive definite (with the states' block, checked by the joint factor).
        let arrival = initial_arrival(g0, sigma0, x_cov)?;
        joint_sqrt(&arrival.cov, arrival.cov.len().isqrt())?;
        let n = x_cov.len().isqrt();
        Ok(Self {
            drift,
            g0: g0.to_vec(),
            sigma0: sigma0.to_vec(),
            state: initial_state(arrival, g0, sigma0, n),
        })
    }

    pub fn drift(&self) -> f64 {
        self.drift
    }

    /// The prior of g at t = 0: mean and covariance (n_g², row-major).
    pub fn prior(&self) -> (&[f64], &[f64]) {
        (&self.g0, &self.sigma0)
    }

    /// n_g.
    pub fn dim(&self) -> usize {
        self.g0.len()
    }

    pub fn state(&self) -> &LearningState {
        &self.state
    }

    /// Back to the prior N(g0, sigma0), the states' covariance being `x_cov`.
    pub fn reset(&mut self, x_cov: &[f64]) -> Result<()> {
        let arrival = initial_arrival(&self.g0, &self.sigma0, x_cov)?;
        self.state = initial_state(arrival, &self.g0, &self.sigma0, x_cov.len().isqrt());
        Ok(())
    }

    /// Restarts the states' block of the joint arrival prior at `x_cov` (n × n; a new arrival
    /// weight P2), with no correlation to g; g's block is kept.
    pub fn restart_states(&mut self, x_cov: &[f64]) {
        let n = x_cov.len().isqrt();
        let d = n + self.dim();
        let cov = &mut self.state.arrival.cov;
        for r in 0..d {
            for c in 0..d {
                if r < n && c < n {
                    cov[r * d + c] = x_cov[r * n + c];
                } else if r < n || c < n {
                    cov[r * d + c] = 0.0;
                }
            }
        }
    }

    /// Replaces the state (from [`Learning::state`] of an estimator with the same dimensions);
    /// lengths and finiteness are checked (the cross covariance and the posterior before may be
    /// NaN: not known) and nothing changes on error.
    pub fn set_state(&mut self, n: usize, s: LearningState) -> Result<()> {
        let ng = self.dim();
        let arrival = JointArrival::new(n, s.arrival.g, s.arrival.cov)?;
        if arrival.dim() != ng {
            return Err(Error::invalid(
                "arrival",
                format!("needs {ng} global variables"),
            ));
        }
        check_len("g", &s.g, ng)?;
        check_len("g_cov", &s.g_cov, ng * ng)?;
        check_finite("g", &s.g)?;
        check_finite("g_cov", &s.g_cov)?;
        check_len("xg_cov", &s.xg_cov, n * ng)?;
        let b = &s.before;
        check_len("g_before", &b.g, ng)?;
        check_len("g_cov_before", &b.g_cov, ng * ng)?;
        check_len("xg_cov_before", &b.xg_cov, n * ng)?;
        let infinite = |v: &[f64]| v.iter().any(|x| x.is_infinite());
        for (name, v) in [
            ("xg_cov", &s.xg_cov),
            ("g_before", &b.g),
            ("g_cov_before", &b.g_cov),
            ("xg_cov_before", &b.xg_cov),
        ] {
            if infinite(v) {
                return Err(Error::invalid(name, "contains inf"));
            }
        }
        self.state = LearningState { arrival, ..s };
        Ok(())
    }

    /// Hands the model the last posterior mean of g and the window the joint arrival prior.
    pub fn prepare(&self, model: &mut dyn StageModel, problem: &mut WindowProblem) -> Result<()> {
        let s = &self.state;
        model.set_globals(&s.g)?;
        let d = problem.dim_x() + self.dim();
        problem.set_global_prior(&s.arrival.g, &joint_sqrt(&s.arrival.cov, d)?)
    }

    /// Records an update: the next arrival prior when the window slid, the posterior of g (the
    /// last one becomes the posterior before).
    pub fn apply(&mut self, update: LearningUpdate) {
        let s = &mut self.state;
        if let Some(arrival) = update.arrival {
            s.arrival = arrival;
        }
        // The last posterior moves to `before` (copied only where it is kept).
        let replace = |now: &mut Vec<f64>, new: Option<Vec<f64>>| match new {
            Some(v) => std::mem::replace(now, v),
            None => now.clone(),
        };
        s.before = GlobalsBefore {
            g: std::mem::replace(&mut s.g, update.g),
            g_cov: replace(&mut s.g_cov, update.g_cov),
            xg_cov: replace(&mut s.xg_cov, update.xg_cov),
        };
    }
}

/// What one update changes in [`Learning`]: the next arrival prior (None: the window did not
/// slide, or its update failed numerically), g of the solution, its covariance and its cross
/// covariance with the newest node (None: not computable, the last ones are kept).
#[derive(Debug, Clone)]
pub struct LearningUpdate {
    pub arrival: Option<JointArrival>,
    pub g: Vec<f64>,
    pub g_cov: Option<Vec<f64>>,
    pub xg_cov: Option<Vec<f64>>,
}

/// The state at t = 0: g at its prior, uncorrelated with the states; the same before.
fn initial_state(arrival: JointArrival, g0: &[f64], sigma0: &[f64], n: usize) -> LearningState {
    let before = GlobalsBefore {
        g: g0.to_vec(),
        g_cov: sigma0.to_vec(),
        xg_cov: vec![0.0; n * g0.len()],
    };
    LearningState {
        arrival,
        g: before.g.clone(),
        g_cov: before.g_cov.clone(),
        xg_cov: before.xg_cov.clone(),
        before,
    }
}

/// N([x̂; g0], diag(x_cov, sigma0)) with x̂ kept by the estimator: the joint prior at t = 0.
fn initial_arrival(g0: &[f64], sigma0: &[f64], x_cov: &[f64]) -> Result<JointArrival> {
    let (n, ng) = (x_cov.len().isqrt(), g0.len());
    let d = n + ng;
    let mut cov = vec![0.0; d * d];
    for r in 0..n {
        cov[r * d..r * d + n].copy_from_slice(&x_cov[r * n..(r + 1) * n]);
    }
    for r in 0..ng {
        cov[(n + r) * d + n..(n + r + 1) * d].copy_from_slice(&sigma0[r * ng..(r + 1) * ng]);
    }
    JointArrival::new(n, g0.to_vec(), cov)
}
