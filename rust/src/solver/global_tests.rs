//! Tests of the solver on windows with global variables (a bordered Gauss-Newton Hessian):
//! optimality against an independent projected-gradient reference, bounds on the nodes with
//! both phases, and the window covariance against the dense inverse.

use nalgebra::DMatrix;

use super::test_problem::{
    random_z, reference_projected_gradient, strict, Synthetic, GLOBAL_SIZES,
};
use super::{BlockLsqProblem, BoxLsqSolver, InteriorMode, SolverOptions};

/// A start for the problem: random nodes, global variables 0.
fn start(p: &Synthetic, seed: u64) -> Vec<f64> {
    let mut z = random_z(p.nodes, p.n, seed);
    z.resize(p.nodes * p.n + p.globals, 0.0);
    z
}

#[test]
fn unconstrained_window_with_globals_is_stationary_and_matches_reference() {
    for (case, &(nodes, n, m)) in GLOBAL_SIZES.iter().enumerate() {
        let mut p = Synthetic::with_globals(nodes, n, m, 500 + case as u64);
        let len = nodes * n + m;
        let (lo, hi) = (vec![f64::NEG_INFINITY; len], vec![f64::INFINITY; len]);
        let mut z = start(&p, 600 + case as u64);
        let z0 = z.clone();
        let rep = BoxLsqSolver::new()
            .solve(&mut p, &mut z, &lo, &hi, &strict())
            .unwrap();
        assert!(
            rep.status.is_success() && rep.projected_gradient <= 1e-6,
            "{case} {rep:?}"
        );
        let mut g = vec![0.0; len];
        p.evaluate(&z, true).unwrap();
        p.gradient_into(&mut g);
        assert!(g.iter().all(|v| v.abs() <= 1e-6), "{case} {g:?}");
        let (_, cref) = reference_projected_gradient(&mut p, &z0, &lo, &hi);
        assert!(
            rep.cost <= cref * (1.0 + 1e-6) + 1e-12,
            "{case} {} vs {cref}",
            rep.cost
        );
    }
}

#[test]
fn bounded_windows_with_globals_satisfy_kkt_in_every_interior_mode() {
    let (mut n_active, mut n_global_active) = (0, 0);
    for (case, &(nodes, n, m)) in GLOBAL_SIZES.iter().enumerate() {
        let mut p = Synthetic::with_globals(nodes, n, m, 700 + case as u64);
        let len = nodes * n + m;
        let mut lo = vec![-0.4; len];
        let mut hi = vec![0.5; len];
        // Free global variables, or bounded ones in every other case.
        let bound = if case % 2 == 0 { f64::INFINITY } else { 0.3 };
        lo[nodes * n..].fill(-bound);
        hi[nodes * n..].fill(bound);
        for mode in [
            InteriorMode::Auto,
            InteriorMode::Always,
            InteriorMode::Never,
        ] {
            let mut z = start(&p, 800 + case as u64);
            let z0 = z.clone();
            let opts = SolverOptions {
                interior: mode,
                ..strict()
            };
            let rep = BoxLsqSolver::new()
                .solve(&mut p, &mut z, &lo, &hi, &opts)
                .unwrap();
            assert!(rep.status.is_success(), "{case} {mode:?} {rep:?}");
            assert!(rep.projected_gradient <= 1e-6, "{case} {mode:?} {rep:?}");
            assert!(z[..nodes * n].iter().all(|&v| (-0.4..=0.5).contains(&v)));
            assert!(z[nodes * n..]
                .iter()
                .all(|&v| (-bound..=bound).contains(&v)));
            n_global_active += z[nodes * n..].iter().filter(|&&v| v.abs() == bound).count();
            n_active += z[..nodes * n]
                .iter()
                .filter(|&&v| v == -0.4 || v == 0.5)
                .count();
            let (_, cref) = reference_projected_gradient(&mut p, &z0, &lo, &hi);
            assert!(
                rep.cost <= cref * (1.0 + 1e-6) + 1e-12,
                "{mode:?} {} vs {cref}",
                rep.cost
            );
        }
    }
    assert!(
        n_active > 0 && n_global_active > 0,
        "the test must exercise active bounds"
    );
}

#[test]
fn window_covariance_with_globals_is_the_dense_inverse() {
    for (case, &(nodes, n, m)) in GLOBAL_SIZES.iter().enumerate() {
        let mut p = Synthetic::with_globals(nodes, n, m, 900 + case as u64);
        let len = nodes * n + m;
        let (lo, hi) = (vec![f64::NEG_INFINITY; len], vec![f64::INFINITY; len]);
        let mut z = start(&p, 910 + case as u64);
        let mut s = BoxLsqSolver::new();
        s.solve(&mut p, &mut z, &lo, &hi, &strict()).unwrap();
        p.evaluate(&z, true).unwrap();
        let inv: DMatrix<f64> = p.dense_hessian().try_inverse().unwrap() * 4.0;
        let cov = s.window_covariance().unwrap();
        let last = s.last_node_covariance().unwrap();
        for i in 0..nodes {
            for r in 0..n {
                for c in 0..n {
                    let want = inv[(i * n + r, i * n + c)];
                    let got = cov[i * n * n + r * n + c];
                    assert!(
                        (got - want).abs() <= 1e-8 * (1.0 + want.abs()),
                        "{case} {i}"
                    );
                }
            }
        }
        assert_eq!(last[..], cov[(nodes - 1) * n * n..]);
        let both = s.window_and_global_covariance();
        assert_eq!(both.window.unwrap(), cov);
        let (global, cross) = (both.global.unwrap(), both.cross.unwrap());
        for a in 0..m {
            for b in 0..m {
                let want = inv[(nodes * n + a, nodes * n + b)];
                assert!((global[a * m + b] - want).abs() <= 1e-8 * (1.0 + want.abs()));
            }
            for r in 0..n {
                let want = inv[((nodes - 1) * n + r, nodes * n + a)];
                assert!((cross[r * m + a] - want).abs() <= 1e-8 * (1.0 + want.abs()));
            }
        }
    }
}
