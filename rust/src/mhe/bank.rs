//! A bank of independent moving-horizon estimators on one model, updated together: n
//! [`MovingHorizon`]s, each with its own copy of the model (for [`GpStageModel`] a clone: the GPs
//! are shared through their `Arc`, only the small evaluation cache and workspace are per
//! estimator), built from one template with per-estimator x̂(0), state box and Q0, R0.
//!
//! [`EstimatorBank::par_update`] runs the n updates of one sample in parallel on rayon's thread
//! pool (models that are `Send`: the learned GPs, a compiled CasADi model);
//! [`EstimatorBank::update_each`] runs them one after another with a model the caller provides
//! (a Python callback that needs the GIL).
//! Each estimator does exactly what a lone `MovingHorizon` would with the same data, so the
//! results do not depend on the number of threads. A solver failure of one estimator is reported
//! in its `UpdateReport` and does not stop the others; an error (bad model output, an interrupt)
//! stops the update and leaves every estimator as it was.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::time::Duration;

use rayon::prelude::*;

use super::estimator::{MovingHorizon, Pending, Step, UpdateReport};
use super::problem::WindowProblem;
use super::stage::{GpStageModel, StageModel};
use crate::error::{check_len, Error, Result};

/// How often the thread waiting for a parallel update runs its interrupt check (which itself
/// runs the installed check at most every `interrupt::INTERVAL`).
const POLL: Duration = Duration::from_millis(10);

/// The part of a model's state an update changes and an error must undo: nothing for a
/// stateless model, the evaluation cache for [`GpStageModel`] (which moves its marked cache
/// aside rather than copying it).
pub trait ModelState {
    /// Remembers the state before an update.
    fn mark(&mut self);
    /// Returns to the state [`ModelState::mark`] remembered.
    fn rollback(&mut self);
}

impl ModelState for () {
    fn mark(&mut self) {}
    fn rollback(&mut self) {}
}

impl ModelState for GpStageModel {
    fn mark(&mut self) {
        GpStageModel::mark(self);
    }
    fn rollback(&mut self) {
        GpStageModel::rollback(self);
    }
}

/// One estimator of the bank and its model.
#[derive(Debug, Clone)]
pub struct Member<M> {
    pub estimator: MovingHorizon,
    pub model: M,
}

/// What differs between the estimators of a bank: x̂(0), the state box, Q0 and R0 (each its
/// diagonal or its row-major matrix, as [`WindowProblem::new`] takes them).
#[derive(Debug, Clone)]
pub struct MemberSettings {
    pub x0: Vec<f64>,
    pub lower: Vec<f64>,
    pub upper: Vec<f64>,
    pub q0: Vec<f64>,
    pub r0: Vec<f64>,
}

/// The data of one sample for every estimator: `u` (n_estimators × m, row-major), `y`
/// (n_estimators × p) and `present` (n_estimators; false: estimator i's y is missing and its
/// row of `y` is ignored).
#[derive(Debug, Clone, Copy)]
pub struct BankSample<'a> {
    pub u: &'a [f64],
    pub y: &'a [f64],
    pub present: &'a [bool],
    /// Each estimator's output covariance for this sample (k × p diagonals or k × p² matrices,
    /// row-major), or None: R0.
    pub r: Option<&'a [f64]>,
    /// Each estimator's last input row as completed by this sample (k × m), or None: as
    /// recorded (see [`Step::u_last`]).
    pub u_last: Option<&'a [f64]>,
}

/// Estimator i's part of a [`BankSample`]: u, y (None: not measured), the covariance of y and
/// the revised last input row.
#[derive(Debug, Clone, Copy)]
pub struct BankRow<'a> {
    pub u: &'a [f64],
    pub y: Option<&'a [f64]>,
    pub r: Option<&'a [f64]>,
    pub u_last: Option<&'a [f64]>,
}

/// One estimator's solved update, recorded once every estimator has succeeded.
pub type Solution = (Pending, UpdateReport);

impl BankRow<'_> {
    /// The update of `estimator` with this row, solved and not yet recorded
    /// ([`MovingHorizon::solve_step`]).
    pub fn solve(
        self,
        estimator: &mut MovingHorizon,
        model: &mut dyn StageModel,
    ) -> Result<Solution> {
        let step = Step {
            u: Some(self.u),
            y: self.y,
            r: self.y.and(self.r),
            u_last: self.u_last,
        };
        estimator.solve_step(model, step)
    }
}

/// See the module documentation.
#[derive(Debug, Clone)]
pub struct EstimatorBank<M> {
    members: Vec<Member<M>>,
}

impl<M: Clone + ModelState> EstimatorBank<M> {
    /// One estimator per entry of `settings`, each with `template`'s horizon, weights η, P2,
    /// form, output loss, arrival cost and solver settings (its history is not used) and a
    /// clone of `model`.
    pub fn new(template: &MovingHorizon, model: &M, settings: &[MemberSettings]) -> Result<Self> {
        if settings.is_empty() {
            return Err(Error::invalid("n", "must be at least 1"));
        }
        let p = template.problem();
        let horizon = template.history().horizon();
        let members = settings
            .iter()
            .map(|s| {
                let mut problem = WindowProblem::new(
                    p.dim_x(),
                    p.dim_u(),
                    p.dim_y(),
                    p.eta(),
                    &s.q0,
                    &s.r0,
                    p.p2_sqrt(),
                    p.form(),
                )?;
                problem.set_loss(p.loss());
                let mut estimator = MovingHorizon::new(
                    problem,
                    horizon,
                    &s.x0,
                    &s.lower,
                    &s.upper,
                    template.options().clone(),
                )?;
                estimator.set_arrival(template.arrival());
                Ok(Member {
                    estimator,
                    model: model.clone(),
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self { members })
    }

    pub fn len(&self) -> usize {
        self.members.len()
    }

    pub fn is_empty(&self) -> bool {
        self.members.is_empty()
    }

    pub fn members(&self) -> &[Member<M>] {
        &self.members
    }

    /// Estimator i and its model (None if out of range).
    pub fn member(&self, i: usize) -> Option<&Member<M>> {
        self.members.get(i)
    }

    /// Mutable access to estimator i (to restore a saved state; None if out of range).
    pub fn member_mut(&mut self, i: usize) -> Option<&mut Member<M>> {
        self.members.get_mut(i)
    }

    /// Restarts estimator i from x̂(0) = x0 ([`MovingHorizon::reset`]) for every (i, x0) of
    /// `rows`; every row is checked first, so on error no estimator changes.
    pub fn reset(&mut self, rows: &[(usize, &[f64])]) -> Result<()> {
        let n = self.dims().0;
        for &(i, x0) in rows {
            if i >= self.len() {
                return Err(Error::invalid("i", format!("no estimator {i}")));
            }
            check_len("x0", x0, n)?;
            crate::error::check_finite("x0", x0)?;
        }
        for &(i, x0) in rows {
            // Cannot fail after the checks (x̂(0)'s covariance P2⁻¹ exists for every estimator:
            // P2 was accepted when the bank was built).
            self.members[i].estimator.reset(x0)?;
        }
        Ok(())
    }

    /// (dim_x, dim_u, dim_y) of the estimators.
    pub fn dims(&self) -> (usize, usize, usize) {
        let p = self.members[0].estimator.problem();
        (p.dim_x(), p.dim_u(), p.dim_y())
    }

    /// Checks the sample's sizes; Ok gives estimator i's (u, y) through [`Self::row`].
    fn check_sample(&self, s: &BankSample<'_>) -> Result<()> {
        let (_, m, p) = self.dims();
        let k = self.len();
        check_len("U", s.u, k * m)?;
        check_len("Y", s.y, k * p)?;
        if let Some(r) = s.r {
            if r.len() != k * p * p {
                check_len("R", r, k * p)?;
            }
        }
        if let Some(u_last) = s.u_last {
            check_len("u_last", u_last, k * m)?;
        }
        if s.present.len() != k {
            return Err(Error::invalid(
                "Y",
                format!("needs one presence flag per estimator ({k})"),
            ));
        }
        Ok(())
    }

    fn row<'a>(s: &BankSample<'a>, i: usize, m: usize, p: usize) -> BankRow<'a> {
        // p values (a diagonal) or p² (a matrix) per estimator, as `check_sample` allowed.
        let w = s.r.map_or(p, |r| r.len() / s.present.len().max(1));
        BankRow {
            u: &s.u[i * m..(i + 1) * m],
            y: s.present[i].then(|| &s.y[i * p..(i + 1) * p]),
            r: s.r.map(|r| &r[i * w..(i + 1) * w]),
            u_last: s.u_last.map(|u| &u[i * m..(i + 1) * m]),
        }
    }

    /// Marks every model's state (to undo an error, [`ModelState`]).
    fn mark_all(&mut self) {
        self.members.iter_mut().for_each(|m| m.model.mark());
    }

    /// Records every estimator's solution when all succeeded and no `interrupt` came;
    /// otherwise rolls every model back (the histories were not touched) and returns the
    /// interrupt or the first error.
    fn finish(
        &mut self,
        results: Vec<Result<Solution>>,
        interrupt: Option<Error>,
    ) -> Result<Vec<UpdateReport>> {
        let results = results.into_iter().collect::<Result<Vec<_>>>();
        match (results, interrupt) {
            (Ok(solutions), None) if solutions.len() == self.members.len() => {
                let reports = self
                    .members
                    .iter_mut()
                    .zip(solutions)
                    .map(|(member, (pending, report))| {
                        member.estimator.apply(pending);
                        report
                    })
                    .collect();
                Ok(reports)
            }
            (results, interrupt) => {
                self.members.iter_mut().for_each(|m| m.model.rollback());
                Err(match (results, interrupt) {
                    (_, Some(e)) | (Err(e), None) => e,
                    (Ok(_), None) => Error::numerical("the bank lost an estimator's update"),
                })
            }
        }
    }

    /// One update of every estimator, one after another, with the model `with_model` gives
    /// for each member's stored model (e.g. a Python callback bound to the GIL). On error
    /// every estimator is as it was.
    pub fn update_each(
        &mut self,
        sample: BankSample<'_>,
        mut step: impl FnMut(&mut MovingHorizon, &mut M, BankRow<'_>) -> Result<Solution>,
    ) -> Result<Vec<UpdateReport>> {
        self.check_sample(&sample)?;
        let (_, m, p) = self.dims();
        self.mark_all();
        let mut results = Vec::with_capacity(self.len());
        for (i, member) in self.members.iter_mut().enumerate() {
            let r = step(
                &mut member.estimator,
                &mut member.model,
                Self::row(&sample, i, m, p),
            );
            let stop = r.is_err();
            results.push(r);
            if stop {
                break;
            }
        }
        self.finish(results, None)
    }
}

impl<M: Clone + ModelState + Send + Sync> EstimatorBank<M> {
    /// One update of every estimator in parallel (rayon's global pool), `step` doing estimator
    /// i's update with its own model; on one thread (one estimator, or a pool of one) on the
    /// calling thread. Meanwhile the calling thread runs its interrupt check
    /// (`crate::interrupt`): an interrupt stops the update. On error or interrupt every
    /// estimator is as it was.
    pub fn par_update_with(
        &mut self,
        sample: BankSample<'_>,
        step: impl Fn(&mut MovingHorizon, &mut M, BankRow<'_>) -> Result<Solution> + Sync,
    ) -> Result<Vec<UpdateReport>> {
        self.check_sample(&sample)?;
        let (_, m, p) = self.dims();
        self.mark_all();
        let run = |(i, member): (usize, &mut Member<M>)| {
            step(
                &mut member.estimator,
                &mut member.model,
                Self::row(&sample, i, m, p),
            )
        };
        if self.len() == 1 || bank_threads() == 1 {
            // On this thread: the core's own interrupt checks run as for a lone estimator.
            let results = self.members.iter_mut().enumerate().map(run).collect();
            return self.finish(results, None);
        }
        if rayon::current_thread_index().is_some() {
            // Called from inside the pool: no waiting thread to poll interrupts on.
            let results = self.members.par_iter_mut().enumerate().map(run).collect();
            return self.finish(results, None);
        }
        // The pool does the work while this thread polls its interrupt check (the binding's runs
        // Python's signal handlers): on an interrupt no further estimator starts, those running
        // finish, and every estimator is restored.
        let stop = AtomicBool::new(false);
        let members = &mut self.members;
        let (results, interrupt) = rayon::in_place_scope(|scope| {
            let (tx, rx) = mpsc::channel();
            let (stop, run) = (&stop, &run);
            scope.spawn(move |_| {
                let results: Vec<Result<Solution>> = members
                    .par_iter_mut()
                    .enumerate()
                    .map(|item| match stop.load(Ordering::Relaxed) {
                        true => Err(Error::interrupted("bank update stopped")),
                        false => run(item),
                    })
                    .collect();
                let _ = tx.send(results);
            });
            let mut interrupt = None;
            loop {
                match rx.recv_timeout(POLL) {
                    Ok(results) => break (results, interrupt),
                    Err(mpsc::RecvTimeoutError::Timeout) => {
                        if interrupt.is_none() {
                            if let Err(e) = crate::interrupt::check() {
                                stop.store(true, Ordering::Relaxed);
                                interrupt = Some(e);
                            }
                        }
                    }
                    // The worker panicked: the scope re-raises its panic when it ends.
                    Err(mpsc::RecvTimeoutError::Disconnected) => break (Vec::new(), interrupt),
                }
            }
        });
        self.finish(results, interrupt)
    }
}

impl<M: super::stage::StageModel + Clone + ModelState + Send + Sync> EstimatorBank<M> {
    /// One update of every estimator in parallel with its own model (see
    /// [`Self::par_update_with`]).
    pub fn par_update(&mut self, sample: BankSample<'_>) -> Result<Vec<UpdateReport>> {
        self.par_update_with(sample, |est, model, row| row.solve(est, model))
    }
}

/// The number of threads [`EstimatorBank::par_update`] runs on (rayon's global pool: one per
/// core unless `RAYON_NUM_THREADS` says otherwise).
pub fn bank_threads() -> usize {
    rayon::current_num_threads()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mhe::{Form, HistoryState, StageEval, StageModel};
    use crate::solver::SolverOptions;

    /// x(t+1) = 0.9 x + u, y = x; fails (bad output) at u ≥ `fail_above`; each evaluation
    /// takes `delay` and is counted in `calls` (shared by all clones).
    #[derive(Clone)]
    struct Scalar {
        fail_above: f64,
        delay: std::time::Duration,
        calls: std::sync::Arc<std::sync::atomic::AtomicUsize>,
    }

    impl ModelState for Scalar {
        fn mark(&mut self) {}
        fn rollback(&mut self) {}
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
            self.calls
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            std::thread::sleep(self.delay);
            let k = d.len() / 2;
            out.resize(k, 1, 1, 1);
            for i in 0..k {
                if d[2 * i + 1] >= self.fail_above {
                    return Err(Error::invalid("model", "refused"));
                }
                out.mean_x[i] = 0.9 * d[2 * i] + d[2 * i + 1];
                out.dmean_x[2 * i] = 0.9;
                out.dmean_x[2 * i + 1] = 1.0;
                out.mean_y[i] = d[2 * i];
                out.dmean_y[2 * i] = 1.0;
            }
            Ok(())
        }
    }

    fn template() -> MovingHorizon {
        let problem =
            WindowProblem::new(1, 1, 1, 0.9, &[0.1], &[0.1], &[1.0], Form::Prediction).unwrap();
        MovingHorizon::new(
            problem,
            3,
            &[0.0],
            &[-10.0],
            &[10.0],
            SolverOptions::default(),
        )
        .unwrap()
    }

    fn scalar(fail_above: f64, delay: Duration) -> Scalar {
        Scalar {
            fail_above,
            delay,
            calls: Default::default(),
        }
    }

    fn sample<'a>(u: &'a [f64], y: &'a [f64], present: &'a [bool]) -> BankSample<'a> {
        BankSample {
            u,
            y,
            present,
            r: None,
            u_last: None,
        }
    }

    fn histories<M: Clone + ModelState>(bank: &EstimatorBank<M>) -> Vec<HistoryState> {
        bank.members()
            .iter()
            .map(|m| m.estimator.history_state())
            .collect()
    }

    fn settings(x0: f64, r0: f64) -> MemberSettings {
        MemberSettings {
            x0: vec![x0],
            lower: vec![-10.0],
            upper: vec![10.0],
            q0: vec![0.1],
            r0: vec![r0],
        }
    }

    #[test]
    fn the_bank_matches_lone_estimators_bit_for_bit() {
        let model = scalar(100.0, Duration::ZERO);
        let set = [settings(0.0, 0.1), settings(1.0, 0.5), settings(-2.0, 0.2)];
        let mut bank = EstimatorBank::new(&template(), &model, &set).unwrap();
        let mut lone: Vec<_> = bank.members().to_vec();
        for t in 0..6 {
            let u = [0.1 * t as f64, 0.0, -0.1];
            let y = [1.0, 2.0 + t as f64, 0.5];
            let present = [true, t % 2 == 0, true];
            let sample = sample(&u, &y, &present);
            let reports = if t % 2 == 0 {
                bank.par_update(sample).unwrap()
            } else {
                bank.update_each(sample, |e, m, row| row.solve(e, m))
                    .unwrap()
            };
            for (i, l) in lone.iter_mut().enumerate() {
                let y_i = present[i].then(|| &y[i..i + 1]);
                let r = l
                    .estimator
                    .update(&mut l.model, Some(&u[i..i + 1]), y_i)
                    .unwrap();
                assert_eq!(r.x_window, reports[i].x_window);
                assert_eq!(r.covariance, reports[i].covariance);
                assert_eq!(r.cost.to_bits(), reports[i].cost.to_bits());
            }
        }
    }

    #[test]
    fn an_error_leaves_every_estimator_unchanged() {
        let model = scalar(5.0, Duration::ZERO);
        let set = [settings(0.0, 0.1), settings(0.0, 0.1)];
        let mut bank = EstimatorBank::new(&template(), &model, &set).unwrap();
        let ok = sample(&[0.0, 0.0], &[1.0, 1.0], &[true, true]);
        bank.par_update(ok).unwrap();
        let before = histories(&bank);
        // Estimator 1's input is outside the model's range: its update fails, 0's is undone.
        let bad = sample(&[0.0, 9.0], &[1.0, 9.0], &[true, true]);
        assert!(bank.par_update(bad).is_err());
        assert!(bank.update_each(bad, |e, m, row| row.solve(e, m)).is_err());
        let after = histories(&bank);
        assert_eq!(before, after);
        // Wrong sizes are refused up front.
        let short = sample(&[0.0], &[1.0, 1.0], &[true, true]);
        assert!(bank.par_update(short).is_err());
        assert!(EstimatorBank::new(&template(), &model, &[]).is_err());
    }

    #[test]
    fn reset_checks_every_row_first_and_restarts_the_estimators() {
        let model = scalar(100.0, Duration::ZERO);
        let set = [settings(0.0, 0.1), settings(1.0, 0.5)];
        let mut bank = EstimatorBank::new(&template(), &model, &set).unwrap();
        let sample = sample(&[0.1, 0.2], &[1.0, 2.0], &[true, true]);
        bank.par_update(sample).unwrap();
        let before = histories(&bank);
        // A bad second row: the first is not applied either.
        assert!(bank.reset(&[(0, &[3.0]), (1, &[f64::NAN])]).is_err());
        assert!(bank.reset(&[(0, &[3.0]), (2, &[1.0])]).is_err());
        assert!(bank.reset(&[(0, &[3.0, 1.0])]).is_err());
        let after = histories(&bank);
        assert_eq!(before, after);
        bank.reset(&[(0, &[3.0]), (1, &[-1.0])]).unwrap();
        for (m, x0) in bank.members().iter().zip([3.0, -1.0]) {
            assert_eq!(m.estimator.history().t(), 0);
            assert_eq!(m.estimator.history().x_window().0, &[x0]);
        }
    }

    #[test]
    fn an_interrupt_stops_the_update_and_leaves_every_estimator_unchanged() {
        let model = scalar(100.0, Duration::from_millis(1));
        // 200 estimators of several 1 ms evaluations each: a whole update takes several times
        // the interrupt check's interval on any pool.
        let set: Vec<_> = (0..200).map(|i| settings(i as f64 * 0.02, 0.1)).collect();
        let mut bank = EstimatorBank::new(&template(), &model, &set).unwrap();
        let (u, y, present) = (vec![0.0; 200], vec![1.0; 200], vec![true; 200]);
        let sample = sample(&u, &y, &present);
        let before = histories(&bank);
        let _guard = crate::interrupt::install(|| Err(Error::interrupted("test")));
        let err = bank.par_update(sample).unwrap_err();
        assert_eq!(err, Error::interrupted("test"));
        // A whole update evaluates each of the 200 windows several times; after the interrupt no
        // further estimator starts, so at most those already running (one per thread) finish.
        let calls = model.calls.load(std::sync::atomic::Ordering::Relaxed);
        drop(_guard);
        let full = {
            let counted = Scalar {
                calls: Default::default(),
                ..model.clone()
            };
            let mut twin = EstimatorBank::new(&template(), &counted, &set).unwrap();
            twin.par_update(sample).unwrap();
            counted.calls.load(std::sync::atomic::Ordering::Relaxed)
        };
        assert!(
            calls * 2 < full,
            "{calls} of {full} evaluations after an interrupt"
        );
        let after = histories(&bank);
        assert_eq!(before, after);
    }
}
