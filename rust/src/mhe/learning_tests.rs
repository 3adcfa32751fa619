//! Tests of an estimator whose GP keeps learning (`learning.rs`, `learning_state.rs`,
//! `joint_arrival.rs`): with the states measured exactly its posterior of the inducing outputs
//! is the recursive GP's after the same transitions; without outputs and drift it stays at the
//! prior; failed updates change nothing; a reset returns to the prior.

use super::*;
use crate::error::Error;
use crate::gp::tests::theta;
use crate::rgp::Rgp;
use crate::solver::test_problem::strict;
use crate::sparse::{SparseMethod, SparseMultiGp};

/// The plant x' = 0.8 x + 0.5 sin(2x) + 0.3 u, a GP trained on a different one (0.8 x + 0.3 u).
fn plant(x: f64, u: f64) -> f64 {
    0.8 * x + 0.5 * (2.0 * x).sin() + 0.3 * u
}

fn sparse_f() -> SparseMultiGp {
    let (mut d, mut y) = (Vec::new(), Vec::new());
    for i in 0..60 {
        let (x, u) = (
            -2.0 + 4.0 * (i as f64) / 59.0,
            ((i * 7) % 11) as f64 / 5.0 - 1.0,
        );
        d.extend([x, u]);
        y.push(0.8 * x + 0.3 * u);
    }
    let z: Vec<f64> = (0..8)
        .flat_map(|i| [-2.0 + 4.0 * i as f64 / 7.0, 0.0])
        .collect();
    SparseMultiGp::new(&d, &y, &[&z], &theta(2), SparseMethod::Vfe).unwrap()
}

/// The learning model with h = identity, exact (the states measured).
#[derive(Clone)]
struct MeasuredStates(LearningStageModel);

impl StageModel for MeasuredStates {
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
        self.0.n_globals()
    }
    fn set_globals(&mut self, g: &[f64]) -> crate::Result<()> {
        self.0.set_globals(g)
    }
    fn evaluate(&mut self, d: &[f64], out: &mut StageEval) -> crate::Result<()> {
        self.0.evaluate(d, out)?;
        let (k, ng) = (d.len() / 2, self.n_globals());
        out.resize(k, 1, 1, 1);
        for i in 0..k {
            out.mean_y[i] = d[2 * i];
            out.var_y[i] = 0.0;
            out.dmean_y[2 * i..2 * i + 2].copy_from_slice(&[1.0, 0.0]);
            out.dvar_y[2 * i..2 * i + 2].fill(0.0);
        }
        out.dmean_y_dg.clear();
        out.dmean_y_dg.resize(k * ng, 0.0);
        Ok(())
    }
}

const Q: f64 = 0.01;

fn estimator(model: &LearningStageModel, horizon: usize, r0: f64, drift: f64) -> MovingHorizon {
    let p = WindowProblem::new(1, 1, 1, 1.0, &[Q], &[r0], &[1.0], Form::Filtering).unwrap();
    let mut est = MovingHorizon::new(p, horizon, &[0.5], &[-1e3], &[1e3], strict()).unwrap();
    est.set_arrival(Arrival {
        mean: ArrivalMean::Filtered,
        weight: ArrivalWeight::Ekf,
    });
    let (g0, s0) = model.fitted_posterior();
    let s0: Vec<f64> = (0..g0.len() * g0.len())
        .map(|k| s0[(k / g0.len(), k % g0.len())])
        .collect();
    est.enable_learning(&g0, &s0, drift).unwrap();
    est
}

/// Largest |a − b| relative to the largest |b| (at least 1).
fn rel_diff(a: &[f64], b: &[f64]) -> f64 {
    let scale = b.iter().fold(1.0f64, |m, v| m.max(v.abs()));
    a.iter()
        .zip(b)
        .fold(0.0f64, |m, (p, q)| m.max((p - q).abs()))
        / scale
}

#[test]
fn with_the_states_measured_the_posterior_is_the_recursive_gps() {
    let f = sparse_f();
    let model = LearningStageModel::new(f.clone(), None, 1, false).unwrap();
    for horizon in [1, 4] {
        let mut rgp = Rgp::from_sparse(&f, 0, 0.0, 0.0).unwrap();
        let mut m = MeasuredStates(model.clone());
        let mut est = estimator(&model, horizon, 1e-12, 0.0);
        let (mut x, mut worst) = (0.5, (0.0f64, 0.0f64));
        for t in 0..25 {
            let u = ((t * 5) % 7) as f64 / 3.0 - 1.0;
            est.update(&mut m, Some(&[u]), Some(&[x])).unwrap();
            // The estimator has the transitions up to x(t), the recursive GP too.
            let l = est.learning().unwrap().state();
            worst.0 = worst.0.max(rel_diff(&l.g, rgp.mean()));
            worst.1 = worst.1.max(rel_diff(&l.g_cov, &rgp.cov_raw()));
            let next = plant(x, u);
            rgp.update(&[x, u], next, Q).unwrap();
            x = next;
        }
        assert!(
            worst.0 <= 1e-8 && worst.1 <= 1e-8,
            "M = {horizon}: {worst:?}"
        );
        // The plant is not the training one: the posterior has moved.
        let (g0, _) = model.fitted_posterior();
        let moved = rel_diff(&est.learning().unwrap().state().g, &g0);
        assert!(moved > 0.01, "{moved}");
        eprintln!("M = {horizon}: {worst:?}, moved {moved}");
    }
}

#[test]
fn with_the_states_measured_the_innovation_is_the_recursive_gps_prediction() {
    // The filtering form predicts y(t) = x(t) from x̂(t − 1) = x(t − 1) with g before the update,
    // jointly uncertain: ŷ and S − Q − R0 are the recursive GP's predictive mean and variance
    // at (x(t − 1), u(t − 1)) before it learns that transition.
    let f = sparse_f();
    let model = LearningStageModel::new(f.clone(), None, 1, false).unwrap();
    let r0 = 1e-12;
    for horizon in [1, 4] {
        let mut rgp = Rgp::from_sparse(&f, 0, 0.0, 0.0).unwrap();
        let mut m = MeasuredStates(model.clone());
        let mut est = estimator(&model, horizon, r0, 0.0);
        let (mut x, mut worst) = (0.5, (0.0f64, 0.0f64));
        let mut predicted: Option<(f64, f64)> = None;
        for t in 0..25 {
            let u = ((t * 5) % 7) as f64 / 3.0 - 1.0;
            est.update(&mut m, Some(&[u]), Some(&[x])).unwrap();
            let inn = est.innovation(&mut m).unwrap();
            if let Some((mu, var)) = predicted {
                let (y_hat, s): (f64, f64) = (x - inn.nu[0], inn.s[0] - Q - r0);
                worst.0 = worst.0.max((y_hat - mu).abs());
                worst.1 = worst.1.max((s - var).abs() / var);
            }
            let (mu, var) = rgp.predict(&[x, u]).unwrap();
            predicted = Some((mu[0], var[0]));
            let next = plant(x, u);
            rgp.update(&[x, u], next, Q).unwrap();
            x = next;
        }
        assert!(
            worst.0 <= 1e-9 && worst.1 <= 1e-8,
            "M = {horizon}: {worst:?}"
        );
    }
}

/// The g-block of the joint arrival covariance (n = 1).
fn arrival_g_cov(est: &MovingHorizon) -> Vec<f64> {
    let a = &est.learning().unwrap().state().arrival;
    let d = a.dim() + 1;
    (1..d)
        .flat_map(|r| a.cov[r * d + 1..(r + 1) * d].to_vec())
        .collect()
}

#[test]
fn without_outputs_g_stays_and_its_covariance_grows_by_the_drift() {
    let model = LearningStageModel::new(sparse_f(), None, 1, false).unwrap();
    let (g0, s0) = model.fitted_posterior();
    let ng = g0.len();
    for drift in [0.0, 1e-3] {
        let mut m = MeasuredStates(model.clone());
        let mut est = estimator(&model, 3, 1e-4, drift);
        for t in 0..10 {
            est.update(&mut m, Some(&[0.2]), None).unwrap();
            let l = est.learning().unwrap().state();
            assert!(rel_diff(&l.g, &g0) <= 1e-10, "t = {t}: g moved");
            // Slides so far: t + 1 − M windows started later than time 0.
            let slides = (t + 1usize).saturating_sub(3) as f64;
            let cov = arrival_g_cov(&est);
            for r in 0..ng {
                for c in 0..ng {
                    let want = s0[(r, c)] + if r == c { slides * drift } else { 0.0 };
                    assert!((cov[r * ng + c] - want).abs() <= 1e-12, "t = {t}");
                }
            }
        }
    }
}

/// The model failing at its `fail_at`-th evaluation with an error that stops the update.
struct FailsAt {
    inner: MeasuredStates,
    count: usize,
    fail_at: usize,
}

impl StageModel for FailsAt {
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
        self.inner.n_globals()
    }
    fn set_globals(&mut self, g: &[f64]) -> crate::Result<()> {
        self.inner.set_globals(g)
    }
    fn evaluate(&mut self, d: &[f64], out: &mut StageEval) -> crate::Result<()> {
        self.count += 1;
        match self.count == self.fail_at {
            true => Err(Error::invalid("model", "injected")),
            false => self.inner.evaluate(d, out),
        }
    }
}

#[test]
fn failed_updates_change_nothing_and_checkpoints_continue_identically() {
    let model = LearningStageModel::new(sparse_f(), None, 1, false).unwrap();
    let mut m = MeasuredStates(model.clone());
    let mut est = estimator(&model, 3, 1e-4, 1e-4);
    let mut x = 0.5;
    let step = |t: usize, x: f64| (((t * 5) % 7) as f64 / 3.0 - 1.0, plant(x, 0.1) + 0.01);
    for t in 0..6 {
        let (u, next) = step(t, x);
        est.update(&mut m, Some(&[u]), Some(&[x])).unwrap();
        x = next;
    }
    // An error at any evaluation of an update leaves the estimator as it was.
    let (history, learning) = (est.history_state(), est.learning().unwrap().state().clone());
    for fail_at in 1..6 {
        let mut bad = FailsAt {
            inner: m.clone(),
            count: 0,
            fail_at,
        };
        assert!(est.update(&mut bad, Some(&[0.3]), Some(&[x])).is_err());
        assert_eq!(est.history_state().x_window, history.x_window);
        assert_eq!(est.history_state().t, history.t);
        assert_eq!(est.learning().unwrap().state(), &learning);
    }
    // A checkpoint (history and learning state) continues bit for bit.
    let mut copy = estimator(&model, 3, 1e-4, 1e-4);
    copy.set_history_state(history).unwrap();
    copy.set_learning_state(learning).unwrap();
    let mut m2 = m.clone();
    for t in 6..12 {
        let (u, next) = step(t, x);
        let a = est.update(&mut m, Some(&[u]), Some(&[x])).unwrap();
        let b = copy.update(&mut m2, Some(&[u]), Some(&[x])).unwrap();
        assert_eq!(a.x_window, b.x_window);
        assert_eq!(
            est.learning().unwrap().state(),
            copy.learning().unwrap().state()
        );
        x = next;
    }
    // A reset returns to the prior.
    est.reset(&[0.5]).unwrap();
    let fresh = estimator(&model, 3, 1e-4, 1e-4);
    assert_eq!(
        est.learning().unwrap().state(),
        fresh.learning().unwrap().state()
    );
    // Learning is enabled before the first update only, and a bad state is refused.
    let mut late = estimator(&model, 3, 1e-4, 0.0);
    late.update(&mut m, Some(&[0.0]), Some(&[0.5])).unwrap();
    let (g0, _) = model.fitted_posterior();
    let e = late
        .enable_learning(&g0, &vec![0.0; g0.len().pow(2)], 0.0)
        .unwrap_err();
    assert!(matches!(e, Error::InvalidInput { ref arg, .. } if arg == "learning"));
    let mut state = late.learning().unwrap().state().clone();
    state.g.pop();
    let before = late.learning().unwrap().state().clone();
    let e = late.set_learning_state(state).unwrap_err();
    assert!(matches!(e, Error::InvalidInput { ref arg, .. } if arg == "g"));
    assert_eq!(late.learning().unwrap().state(), &before);
}

#[test]
fn a_new_arrival_weight_restarts_the_states_block_and_keeps_gs() {
    let model = LearningStageModel::new(sparse_f(), None, 1, false).unwrap();
    let mut m = MeasuredStates(model.clone());
    let mut est = estimator(&model, 3, 1e-4, 0.0);
    for t in 0..8 {
        est.update(&mut m, Some(&[0.1 * t as f64]), Some(&[0.5]))
            .unwrap();
    }
    let before = est.learning().unwrap().state().arrival.clone();
    let d = before.dim() + 1;
    // S = [0.5]: P2 = 0.25, the states' arrival covariance 4.
    est.set_weights(None, None, None, Some(&[0.5])).unwrap();
    let after = est.learning().unwrap().state().arrival.clone();
    assert_eq!(after.cov[0], 4.0);
    assert!((1..d).all(|k| after.cov[k] == 0.0 && after.cov[k * d] == 0.0));
    for r in 1..d {
        assert_eq!(
            after.cov[r * d + 1..(r + 1) * d],
            before.cov[r * d + 1..(r + 1) * d]
        );
    }
    assert_eq!(after.g, before.g);
    // A singular S is refused and changes nothing.
    let e = est.set_weights(None, None, None, Some(&[0.0])).unwrap_err();
    assert!(matches!(e, Error::InvalidInput { .. }));
    assert_eq!(est.learning().unwrap().state().arrival, after);
}
