//! Tests of the solver on stiff windows: process rows weighted 1e8 to 1e12 in J against output
//! rows of weight 1 (an MHE window with near-zero process noise), started like an MHE warm start
//! on the model's trajectory from a poor initial state. There a "small" Marquardt damping still
//! freezes the directions that matter, the `dtol` test must use the undamped step, and long steps
//! along the curved valley of J are rejected unless corrected (`damping.rs`, `correction.rs`).

use super::test_problem::{random_z, strict, trajectory, Synthetic};
use super::{BlockLsqProblem, BoxLsqSolver, SolverOptions};

/// Default solve of the stiff window `seed` with process weight `wq`: (nfev, cost gained by
/// continuing to first-order optimality from its result).
fn solve_stiff(seed: u64, wq: f64) -> (usize, f64) {
    let (nodes, n) = (10, 3);
    let mut p = Synthetic::stiff(nodes, n, 500 + seed, wq);
    let lo = vec![f64::NEG_INFINITY; nodes * n];
    let hi = vec![f64::INFINITY; nodes * n];
    let x0: Vec<f64> = (p.a.iter().zip(random_z(1, n, 600 + seed)))
        .map(|(a, e)| a + 0.5 * e)
        .collect();
    let mut z = trajectory(&p, &x0);
    let c0 = p.evaluate(&z, false).unwrap();
    let opts = SolverOptions::default();
    let rep = BoxLsqSolver::new()
        .solve(&mut p, &mut z, &lo, &hi, &opts)
        .unwrap();
    assert!(rep.status.is_success(), "seed {seed}, wq {wq}: {rep:?}");
    assert!(rep.cost < c0, "seed {seed}, wq {wq}: {rep:?}");
    let polished = BoxLsqSolver::new()
        .solve(&mut p, &mut z, &lo, &hi, &strict())
        .unwrap();
    (rep.nfev, rep.cost - polished.cost)
}

#[test]
fn stiff_windows_are_solved_to_dtol_in_few_evaluations() {
    // With a damping that started at 1e-6, a `dtol` test on damped steps and no correction,
    // most of these windows ended at the iteration cap or stopped on a damped step's decrement
    // far above the minimum (at wq ≥ 1e5 several after a single evaluation).
    for wq in [1e4, 1e5, 1e6] {
        let mut total = 0;
        for seed in 0..8 {
            let (nfev, gain) = solve_stiff(seed, wq);
            assert!(
                gain <= 2.0 * SolverOptions::default().dtol,
                "seed {seed}, wq {wq}: {gain} left to gain"
            );
            assert!(nfev <= 50, "seed {seed}, wq {wq}: {nfev} evaluations");
            total += nfev;
        }
        assert!(total <= 160, "wq {wq}: {total} evaluations for 8 windows");
    }
}
