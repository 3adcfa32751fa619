//! The sliding history of a moving-horizon estimator: the inputs and outputs of the last M + 1
//! steps, the arrival priors of the last M + 2 times and the previous optimal window. From it,
//! [`History::next_window`] cuts the data of the next window (without changing anything) and
//! [`History::push`] records a solved step.
//!
//! Time t counts the updates since the last reset. The t-th update adds (u(t), y(t)); its window
//! starts at time s0 = max(0, end − M) and ends at `end` = t + 1 (prediction form: the last node
//! has no data) or t (filtering form), so it has M_t + 1 = end − s0 + 1 nodes.

use std::collections::VecDeque;

use super::outcome::Outcome;
use super::problem::Form;
use super::weights::Covariance;
use crate::error::{check_finite, check_len, Error, Result};

/// The data of one window, cut from the history and the new step.
#[derive(Debug, Clone)]
pub struct WindowData {
    /// (nodes × m) inputs, (nodes × p) outputs (zeros where missing), presence per node.
    pub u: Vec<f64>,
    pub y: Vec<f64>,
    pub present: Vec<bool>,
    /// The output covariance given with each node's sample (None: R0).
    pub r: Vec<Option<Covariance>>,
    /// The arrival prior x̂(s0) for the first node.
    pub x_prior: Vec<f64>,
    /// Time of the first node.
    pub s0: usize,
    /// Number of nodes M_t + 1.
    pub nodes: usize,
    /// The new step (u(t), y(t), whether y(t) was measured, its covariance), recorded by
    /// [`History::push`].
    step: (Vec<f64>, Vec<f64>, bool, Option<Covariance>),
    /// Whether u(t) is a placeholder the caller will replace (`set_last_input`).
    pub input_pending: bool,
    /// The input row of the last recorded step (t − 1) as revised with the new step
    /// ([`History::revise_last_input`]); [`History::push`] records it in place of the old one.
    last_input: Option<Vec<f64>>,
    /// The arrival prior of time t recomputed with that row (the estimate's own prediction),
    /// recorded by [`History::push`] in place of the old one.
    pub last_prior: Option<Vec<f64>>,
}

/// The newest recorded sample: u(t), u(t − 1) (None at the first), y(t) (None: not measured; NaN
/// for channels not measured) and the covariance given with it (None: R0).
#[derive(Debug, Clone, Copy)]
pub struct Sample<'a> {
    pub u: &'a [f64],
    pub u_before: Option<&'a [f64]>,
    pub y: Option<&'a [f64]>,
    pub r: Option<&'a Covariance>,
}

/// See the module documentation.
#[derive(Debug, Clone)]
pub struct History {
    horizon: usize,
    form: Form,
    dims: (usize, usize, usize),
    t: usize,
    /// Rows of the last ≤ M + 1 steps, oldest first.
    u: Vec<f64>,
    y: Vec<f64>,
    present: Vec<bool>,
    /// The output covariance given with each row's sample (None: R0).
    r: Vec<Option<Covariance>>,
    /// Arrival priors of the last ≤ M + 2 times, the newest (for time t) last.
    priors: VecDeque<Vec<f64>>,
    /// The last optimal window (rows × n), oldest first, and the time of its first row.
    x_window: Vec<f64>,
    window_t0: usize,
    /// S (n × n, row-major) of the arrival weight SᵀS of the next window's first node (set by
    /// the estimator: P2's, or its EKF update, see `arrival.rs`).
    arrival_sqrt: Vec<f64>,
    /// What the last update reported (`outcome.rs`).
    outcome: Outcome,
}

impl History {
    /// An empty history for horizon M ≥ 1 and dimensions (n, m, p), at x̂(0) = x0 with the
    /// identity as its covariance (see [`History::reset`]).
    pub fn new(
        horizon: usize,
        form: Form,
        dims: (usize, usize, usize),
        x0: &[f64],
    ) -> Result<Self> {
        if horizon == 0 {
            return Err(Error::invalid("horizon", "must be at least 1"));
        }
        let identity: Vec<f64> = (0..dims.0 * dims.0)
            .map(|k| if k % (dims.0 + 1) == 0 { 1.0 } else { 0.0 })
            .collect();
        let mut h = Self {
            horizon,
            form,
            dims,
            t: 0,
            u: Vec::new(),
            y: Vec::new(),
            present: Vec::new(),
            r: Vec::new(),
            priors: VecDeque::with_capacity(horizon + 2),
            x_window: Vec::new(),
            window_t0: 0,
            arrival_sqrt: identity.clone(),
            outcome: Outcome::initial(x0, identity.clone()),
        };
        h.reset(x0, identity)?;
        Ok(h)
    }

    /// Forgets every step: t = 0, x̂(0) = x0 with covariance `covariance` (n × n).
    pub fn reset(&mut self, x0: &[f64], covariance: Vec<f64>) -> Result<()> {
        check_len("x0", x0, self.dims.0)?;
        check_finite("x0", x0)?;
        check_len("covariance", &covariance, self.dims.0 * self.dims.0)?;
        self.outcome = Outcome::initial(x0, covariance);
        self.t = 0;
        self.u.clear();
        self.y.clear();
        self.present.clear();
        self.r.clear();
        self.priors.clear();
        self.priors.push_back(x0.to_vec());
        self.x_window = x0.to_vec();
        self.window_t0 = 0;
        Ok(())
    }

    pub fn horizon(&self) -> usize {
        self.horizon
    }

    /// Number of updates since the last reset.
    pub fn t(&self) -> usize {
        self.t
    }

    /// The last optimal window (rows × n) and the time of its first row.
    pub fn x_window(&self) -> (&[f64], usize) {
        (&self.x_window, self.window_t0)
    }

    /// S of the next window's arrival weight SᵀS (the identity until the estimator sets it).
    pub fn arrival_sqrt(&self) -> &[f64] {
        &self.arrival_sqrt
    }

    pub fn set_arrival_sqrt(&mut self, s: Vec<f64>) {
        self.arrival_sqrt = s;
    }

    /// What the last update reported (the initial outcome before any).
    pub fn outcome(&self) -> &Outcome {
        &self.outcome
    }

    /// The time of the first node of the window of update `t` (s0 = max(0, end − M)).
    pub fn window_start(&self, t: usize) -> usize {
        let end = match self.form {
            Form::Prediction => t + 1,
            Form::Filtering => t,
        };
        end.saturating_sub(self.horizon)
    }

    /// Replaces the arrival prior of time `time` if it is held (the newest is for time t).
    pub fn set_prior(&mut self, time: usize, prior: &[f64]) {
        let len = self.priors.len();
        if time <= self.t && self.t - time < len {
            self.priors[len - 1 - (self.t - time)].copy_from_slice(prior);
        }
    }

    /// Replaces the input row of the last recorded step (t − 1), if there is one (`u` of m
    /// values, checked by the caller).
    pub fn set_last_input(&mut self, u: &[f64]) {
        let m = self.dims.1;
        if self.t > 0 && u.len() == m {
            let at = self.u.len() - m;
            self.u[at..].copy_from_slice(u);
        }
    }

    /// Marks the last update's input as given (after [`History::set_last_input`]).
    pub fn set_input_given(&mut self) {
        self.outcome.input_pending = false;
    }

    /// The input of the last recorded step (t − 1), or None before the first.
    pub fn last_input(&self) -> Option<&[f64]> {
        let m = self.dims.1;
        (self.t > 0).then(|| &self.u[self.u.len() - m..])
    }

    /// The newest recorded sample (of time t − 1), or None before the first.
    pub fn newest_sample(&self) -> Option<Sample<'_>> {
        let (_, m, p) = self.dims;
        let rows = self.present.len();
        if self.t == 0 || rows == 0 {
            return None;
        }
        let u = &self.u[(rows - 1) * m..rows * m];
        let u_before = (rows >= 2).then(|| &self.u[(rows - 2) * m..(rows - 1) * m]);
        let y = self.present[rows - 1].then(|| &self.y[(rows - 1) * p..rows * p]);
        Some(Sample {
            u,
            u_before,
            y,
            r: self.r[rows - 1].as_ref(),
        })
    }

    /// Replaces the newest arrival prior (for time t).
    pub fn set_newest_prior(&mut self, prior: &[f64]) {
        if let Some(last) = self.priors.back_mut() {
            last.copy_from_slice(prior);
        }
    }

    /// The window of the t-th update with the new step (u(t), y(t)) (`y` None: not measured)
    /// and the covariance `r` given with y(t) (None: R0). Only the lengths are checked here; the
    /// window problem checks the values it is given.
    pub fn next_window(
        &self,
        u: &[f64],
        y: Option<&[f64]>,
        r: Option<Covariance>,
    ) -> Result<WindowData> {
        let (_, m, p) = self.dims;
        check_len("u", u, m)?;
        if let Some(y) = y {
            check_len("y", y, p)?;
        }
        let y_t = y.map_or_else(|| vec![0.0; p], <[f64]>::to_vec);
        let t = self.t;
        let s0 = self.window_start(t);
        let nodes = match self.form {
            Form::Prediction => t + 1,
            Form::Filtering => t,
        } - s0
            + 1;
        // Steps with data: times s0 ..= t, the last of them the new one.
        let k = t + 1 - s0;
        let old = k - 1;
        let mut data = WindowData {
            u: last_rows(&self.u, m, old),
            y: last_rows(&self.y, p, old),
            present: self.present[self.present.len() - old..].to_vec(),
            r: self.r[self.r.len() - old..].to_vec(),
            x_prior: self.priors[self.priors.len() - 1 - (t - s0)].clone(),
            s0,
            nodes,
            step: (u.to_vec(), y_t.clone(), y.is_some(), r.clone()),
            input_pending: false,
            last_input: None,
            last_prior: None,
        };
        data.u.extend_from_slice(u);
        data.y.extend_from_slice(&y_t);
        data.present.push(y.is_some());
        data.r.push(r);
        if nodes > k {
            // Prediction form: the last node x̄(t+1) carries no data.
            data.u.resize(nodes * m, 0.0);
            data.y.resize(nodes * p, 0.0);
            data.present.push(false);
            data.r.push(None);
        }
        Ok(data)
    }

    /// Revises, in the window `data`, the input row of the last recorded step (t − 1) to `u`
    /// (m values): a row the caller completes only when the next sample arrives (the interval
    /// a continuous-time model integrates over, known once the sample that ends it is in).
    /// The history itself takes it with [`History::push`]. Refused before the first step.
    pub fn revise_last_input(&self, data: &mut WindowData, u: &[f64]) -> Result<()> {
        let m = self.dims.1;
        check_len("u_last", u, m)?;
        check_finite("u_last", u)?;
        if self.t == 0 {
            return Err(Error::invalid("u_last", "no step is recorded yet"));
        }
        // Row t − 1 is in the window when the window starts before t.
        if data.s0 < self.t {
            let at = (self.t - 1 - data.s0) * m;
            data.u[at..at + m].copy_from_slice(u);
        }
        data.last_input = Some(u.to_vec());
        Ok(())
    }

    /// Records a solved step: its data, the optimal window `x_window`, the arrival prior of
    /// the next time and what the update reports.
    pub fn push(
        &mut self,
        data: WindowData,
        x_window: Vec<f64>,
        next_prior: Vec<f64>,
        outcome: Outcome,
    ) {
        let (_, m, p) = self.dims;
        let (u, y, present, r) = data.step;
        let keep = self.horizon + 1;
        if let Some(last) = data.last_input {
            let at = self.u.len() - m;
            self.u[at..].copy_from_slice(&last);
        }
        self.u.extend_from_slice(&u);
        self.y.extend_from_slice(&y);
        self.present.push(present);
        self.r.push(r);
        if self.present.len() > keep {
            let drop = self.present.len() - keep;
            self.present.drain(..drop);
            self.r.drain(..drop);
            self.u.drain(..drop * m);
            self.y.drain(..drop * p);
        }
        if let Some(prior) = data.last_prior {
            self.set_newest_prior(&prior);
        }
        self.priors.push_back(next_prior);
        if self.priors.len() > self.horizon + 2 {
            self.priors.pop_front();
        }
        self.x_window = x_window;
        self.window_t0 = data.s0;
        self.outcome = outcome;
        self.t += 1;
    }

    /// The largest age a late output can have to enter the next window: the age of the
    /// window's first node with an output (age 0 is the newest recorded output, of time t − 1).
    pub fn max_delay(&self) -> Option<usize> {
        (self.t > 0).then(|| self.t - 1 - self.window_start(self.t).min(self.t - 1))
    }

    /// Records an output `y` (p values, NaN for channels not in it) measured `age` steps before
    /// the newest recorded one (1 ≤ age ≤ [`History::max_delay`]), with its covariance `r`
    /// (None: `r0`), into the row of its time: it enters every window from the next update on.
    /// A channel already measured at that time is refused. The row's covariance keeps the
    /// measured channels' block and takes the new channels' block from `r`, uncorrelated with
    /// the others. On error nothing changes.
    pub fn add_delayed(
        &mut self,
        y: &[f64],
        age: usize,
        r: Option<Covariance>,
        r0: &Covariance,
    ) -> Result<()> {
        let p = self.dims.2;
        check_len("y", y, p)?;
        if y.iter().any(|v| v.is_infinite()) {
            return Err(Error::invalid("y", "contains an infinite value"));
        }
        let new: Vec<usize> = (0..p).filter(|&k| y[k].is_finite()).collect();
        if new.is_empty() {
            return Err(Error::invalid("y", "has no measured channel (all NaN)"));
        }
        let max = self.max_delay().unwrap_or(0);
        if max == 0 {
            return Err(Error::invalid(
                "age",
                format!("got {age}, but the next window holds no earlier output yet (max_delay 0)"),
            ));
        }
        if age == 0 || age > max {
            return Err(Error::invalid(
                "age",
                format!(
                    "must be between 1 and {max} (the oldest output the next window uses), got {age}"
                ),
            ));
        }
        let row = self.present.len() - 1 - age;
        let old = &mut self.y[row * p..(row + 1) * p];
        let present = self.present[row];
        if let Some(&k) = new.iter().find(|&&k| present && old[k].is_finite()) {
            return Err(Error::invalid(
                "y",
                format!("channel {k} is already measured at that time"),
            ));
        }
        let cov = match (present, r) {
            (false, r) => r,
            (true, None) if self.r[row].is_none() && r0.is_diagonal() => None,
            (true, r) => {
                let mine = self.r[row].as_ref().unwrap_or(r0);
                Some(mine.with_block(r.as_ref().unwrap_or(r0), &new)?)
            }
        };
        if !present {
            old.iter_mut().for_each(|v| *v = f64::NAN);
        }
        new.iter().for_each(|&k| old[k] = y[k]);
        self.present[row] = true;
        self.r[row] = cov;
        Ok(())
    }
}

/// The whole state of a [`History`] (what [`History::push`] changes), for copies and
/// checkpoints: `t`, the rows of the last min(t, M + 1) steps (`u` rows × m, `y` rows × p,
/// `present`), the arrival priors of the last min(t + 1, M + 2) times (`priors`, oldest first,
/// k × n), the last optimal window `x_window` (rows × n) and the time of its first row.
#[derive(Debug, Clone, PartialEq)]
pub struct HistoryState {
    pub t: usize,
    pub u: Vec<f64>,
    pub y: Vec<f64>,
    pub present: Vec<bool>,
    /// The output covariance given with each row's sample (None: R0).
    pub r: Vec<Option<Covariance>>,
    pub priors: Vec<f64>,
    pub x_window: Vec<f64>,
    pub window_t0: usize,
    /// S of the next arrival weight (n × n).
    pub arrival_sqrt: Vec<f64>,
    /// What the last update reported.
    pub outcome: Outcome,
}

impl History {
    /// A copy of the state (see [`HistoryState`]).
    pub fn state(&self) -> HistoryState {
        HistoryState {
            t: self.t,
            u: self.u.clone(),
            y: self.y.clone(),
            present: self.present.clone(),
            r: self.r.clone(),
            priors: self.priors.iter().flatten().copied().collect(),
            x_window: self.x_window.clone(),
            window_t0: self.window_t0,
            arrival_sqrt: self.arrival_sqrt.clone(),
            outcome: self.outcome.clone(),
        }
    }

    /// Replaces the state by `s` (from [`History::state`] of a history with the same horizon,
    /// form and dimensions). Every length follows from `t`, M and the form; a state that does not
    /// fit, or holds a non-finite value, is rejected naming the entry, and nothing changes.
    pub fn set_state(&mut self, s: HistoryState) -> Result<()> {
        let (n, m, p) = self.dims;
        let (t, big_m) = (s.t, self.horizon);
        let rows = t.min(big_m + 1);
        if s.present.len() != rows {
            return Err(Error::invalid(
                "present",
                format!("expected {rows} values at t = {t}, got {}", s.present.len()),
            ));
        }
        check_len("u", &s.u, rows * m)?;
        check_len("y", &s.y, rows * p)?;
        if s.r.len() != rows || s.r.iter().flatten().any(|c| c.dim() != p) {
            return Err(Error::invalid(
                "r",
                format!("expected {rows} covariances of dimension {p} at t = {t}"),
            ));
        }
        check_len("priors", &s.priors, t.saturating_add(1).min(big_m + 2) * n)?;
        // The window of the last update (t − 1), or x0 as one row before any.
        let (t0, nodes) = match t.checked_sub(1) {
            None => (0, 1),
            Some(last) => {
                let end = match self.form {
                    Form::Prediction => last + 1,
                    Form::Filtering => last,
                };
                let s0 = end.saturating_sub(big_m);
                (s0, end - s0 + 1)
            }
        };
        check_len("x_window", &s.x_window, nodes * n)?;
        if s.window_t0 != t0 {
            return Err(Error::invalid(
                "window_t0",
                format!("must be {t0} at t = {t}, got {}", s.window_t0),
            ));
        }
        check_finite("u", &s.u)?;
        check_finite("priors", &s.priors)?;
        check_finite("x_window", &s.x_window)?;
        check_len("arrival_sqrt", &s.arrival_sqrt, n * n)?;
        check_finite("arrival_sqrt", &s.arrival_sqrt)?;
        s.outcome.check(n)?;
        check_len(
            "outcome_P_window",
            &s.outcome.window_covariance,
            s.x_window.len() * n,
        )?;
        // Outputs that were not measured are stored as zeros; measured channels are finite and
        // channels not measured NaN.
        if s.y.iter().any(|v| v.is_infinite()) {
            return Err(Error::invalid("y", "contains an infinite value"));
        }
        self.t = t;
        self.u = s.u;
        self.y = s.y;
        self.present = s.present;
        self.r = s.r;
        self.priors = s.priors.chunks_exact(n).map(<[f64]>::to_vec).collect();
        self.x_window = s.x_window;
        self.window_t0 = s.window_t0;
        self.arrival_sqrt = s.arrival_sqrt;
        self.outcome = s.outcome;
        Ok(())
    }
}

/// The last `rows` rows (of width `width`) of a row-major buffer.
fn last_rows(buf: &[f64], width: usize, rows: usize) -> Vec<f64> {
    buf[buf.len() - rows * width..].to_vec()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Windows of the prediction form for M = 2 and no input: node times and priors.
    #[test]
    fn windows_slide_and_pick_their_arrival_prior() {
        let mut h = History::new(2, Form::Prediction, (1, 0, 1), &[10.0]).unwrap();
        let mut seen = Vec::new();
        for t in 0..5 {
            let y = [t as f64];
            let w = h.next_window(&[], Some(&y), None).unwrap();
            seen.push((w.s0, w.nodes, w.x_prior[0], w.y.clone(), w.present.clone()));
            let x = vec![100.0 + t as f64; w.nodes];
            let last = x[w.nodes - 1];
            h.push(w, x, vec![last], h.outcome().clone());
        }
        // t = 0: nodes {0, 1}, prior x0; t = 1: {0, 1, 2}; t ≥ 2: {t−1, t, t+1}.
        assert_eq!(seen[0], (0, 2, 10.0, vec![0.0, 0.0], vec![true, false]));
        assert_eq!(
            seen[1],
            (0, 3, 10.0, vec![0.0, 1.0, 0.0], vec![true, true, false])
        );
        assert_eq!(seen[2].0..seen[2].1, 1..3);
        // The prior of time s0 = t − 1 is the estimate x̂(t−1) pushed two updates before.
        assert_eq!(seen[2].2, 100.0);
        assert_eq!(
            seen[4],
            (3, 3, 102.0, vec![3.0, 4.0, 0.0], vec![true, true, false])
        );
        assert_eq!(h.t(), 5);
    }

    #[test]
    fn filtering_windows_end_at_the_newest_output_and_missing_outputs_are_zero() {
        let mut h = History::new(2, Form::Filtering, (1, 1, 1), &[0.0]).unwrap();
        for t in 0..4 {
            let y = if t == 2 { None } else { Some([t as f64]) };
            let w = h
                .next_window(&[t as f64], y.as_ref().map(|v| &v[..]), None)
                .unwrap();
            assert_eq!(w.nodes, t.min(2) + 1);
            assert_eq!(w.u.last(), Some(&(t as f64)));
            assert_eq!(*w.present.last().unwrap(), t != 2);
            if t == 2 {
                assert_eq!(w.y.last(), Some(&0.0));
            }
            let nodes = w.nodes;
            h.push(w, vec![0.0; nodes], vec![t as f64], h.outcome().clone());
        }
    }

    #[test]
    fn a_state_set_on_a_fresh_history_continues_identically() {
        for form in [Form::Prediction, Form::Filtering] {
            let mut a = History::new(2, form, (1, 1, 1), &[0.5]).unwrap();
            let mut b = History::new(2, form, (1, 1, 1), &[0.0]).unwrap();
            for t in 0..6 {
                if t == 3 {
                    b.set_state(a.state()).unwrap();
                    assert_eq!(a.state(), b.state());
                }
                let y = [t as f64];
                let step = |h: &mut History| {
                    let w = h.next_window(&[1.0], Some(&y), None).unwrap();
                    let x = vec![t as f64 * 0.1; w.nodes];
                    // An outcome with one covariance per node, as an update records it.
                    let mut outcome = h.outcome().clone();
                    outcome.window_covariance = vec![1.0; w.nodes];
                    h.push(w, x, vec![t as f64], outcome);
                };
                step(&mut a);
                step(&mut b);
            }
            assert_eq!(a.state(), b.state());
        }
    }

    #[test]
    fn a_state_that_does_not_fit_is_rejected_naming_the_entry() {
        let mut h = History::new(2, Form::Prediction, (1, 0, 1), &[0.0]).unwrap();
        let good = h.state();
        let err = |h: &mut History, s: HistoryState| h.set_state(s).unwrap_err().to_string();
        let mut s = good.clone();
        s.t = 3;
        assert!(err(&mut h, s).starts_with("present:"));
        let mut s = good.clone();
        s.priors = vec![f64::NAN];
        assert!(err(&mut h, s).starts_with("priors:"));
        let mut s = good.clone();
        s.window_t0 = 1;
        assert!(err(&mut h, s).starts_with("window_t0:"));
        assert_eq!(h.state(), good);
    }

    #[test]
    fn bad_steps_are_rejected_naming_the_argument() {
        let h = History::new(3, Form::Prediction, (2, 1, 1), &[0.0, 0.0]).unwrap();
        let err = |r: Result<WindowData>| r.unwrap_err().to_string();
        assert!(err(h.next_window(&[], Some(&[0.0]), None)).starts_with("u:"));
        assert!(err(h.next_window(&[0.0], Some(&[0.0, 1.0]), None)).starts_with("y:"));
        assert!(History::new(0, Form::Prediction, (2, 1, 1), &[0.0, 0.0]).is_err());
        assert!(History::new(1, Form::Prediction, (2, 1, 1), &[0.0]).is_err());
    }

    /// A late output fills the channels not measured at its time, with its covariance block
    /// apart from the old channels', and is refused where it cannot go.
    #[test]
    fn late_outputs_fill_their_row_or_are_refused() {
        let mut h = History::new(4, Form::Filtering, (1, 0, 2), &[0.0]).unwrap();
        let r0 = Covariance::new("R0", &[1.0, 0.5, 0.5, 2.0], 2).unwrap();
        let late = Covariance::new("R", &[9.0, 3.0], 2).unwrap();
        for t in 0..6 {
            let w = h
                .next_window(&[], Some(&[t as f64, f64::NAN]), None)
                .unwrap();
            let nodes = w.nodes;
            h.push(w, vec![0.0; nodes], vec![0.0], h.outcome().clone());
        }
        assert_eq!(h.max_delay(), Some(3));
        let before = h.state();
        let err = |r: Result<()>| r.unwrap_err().to_string();
        assert!(err(h.add_delayed(&[f64::NAN, 1.0], 4, None, &r0)).starts_with("age:"));
        assert!(err(h.add_delayed(&[f64::NAN, 1.0], 0, None, &r0)).starts_with("age:"));
        assert!(err(h.add_delayed(&[2.0, f64::NAN], 2, None, &r0)).contains("already measured"));
        assert!(err(h.add_delayed(&[f64::NAN; 2], 2, None, &r0)).contains("no measured"));
        assert_eq!(format!("{:?}", h.state()), format!("{before:?}")); // (NaN != NaN)
        h.add_delayed(&[f64::NAN, 7.0], 2, Some(late), &r0).unwrap();
        let s = h.state();
        let row = s.present.len() - 3;
        assert_eq!(&s.y[2 * row..2 * row + 2], &[3.0, 7.0]);
        let cov = s.r[row].as_ref().unwrap();
        // R0's block for channel 0, the late one's for channel 1, no correlation between them.
        assert_eq!(cov.as_slice(), &[1.0, 0.0, 0.0, 3.0]);
        let w = h.next_window(&[], None, None).unwrap();
        assert_eq!(w.r.len(), w.nodes);
        assert_eq!(w.r[w.nodes - 1 - 3].as_ref(), Some(cov));
    }
}
