//! [`WindowLsq`]: the GP-MHE window problem (its stage model and evaluation buffers) seen by the
//! solver as a [`BlockLsqProblem`].

use super::{StageModel, WindowEval, WindowProblem};
use crate::error::Result;
use crate::solver::BlockLsqProblem;

/// The GP-MHE window (its model and evaluation buffers) as a [`BlockLsqProblem`].
pub struct WindowLsq<'a> {
    pub problem: &'a WindowProblem,
    pub model: &'a mut dyn StageModel,
    pub eval: &'a mut WindowEval,
}

impl BlockLsqProblem for WindowLsq<'_> {
    fn n_nodes(&self) -> usize {
        self.problem.n_nodes()
    }
    fn node_dim(&self) -> usize {
        self.problem.dim_x()
    }
    fn evaluate(&mut self, z: &[f64], want_derivatives: bool) -> Result<f64> {
        self.problem
            .evaluate(&mut *self.model, z, want_derivatives, self.eval)?;
        Ok(self.eval.cost())
    }
    fn gradient_into(&self, g: &mut [f64]) {
        self.eval.gradient_into(g);
    }
    fn gauss_newton_blocks_into(&self, diag: &mut [f64], off: &mut [f64]) {
        self.eval.gauss_newton_blocks_into(diag, off);
    }
    fn global_dim(&self) -> usize {
        self.problem.n_globals()
    }
    fn gauss_newton_border_into(&self, border: &mut [f64], corner: &mut [f64]) {
        self.eval.gauss_newton_border_into(border, corner);
    }
    fn cost_noise(&self) -> f64 {
        self.eval.cost_noise()
    }
    fn gradient_noise(&self) -> f64 {
        self.eval.gradient_noise()
    }
}

#[cfg(test)]
mod window_tests {
    use super::*;
    use crate::mhe::{Form, StageEval};
    use crate::solver::test_problem::strict;
    use crate::solver::{projected_gradient_norm, BoxLsqSolver};

    /// The batch reactor (docs/user_guide/systems.rst) as an exact stage model (zero variances).
    struct Reactor;
    const T: f64 = 0.1;
    const K1: f64 = 0.16;
    const K2: f64 = 0.0064;
    fn step(x: &[f64]) -> [f64; 2] {
        [
            x[0] + T * (-2.0 * K1 * x[0] * x[0] + 2.0 * K2 * x[1]),
            x[1] + T * (K1 * x[0] * x[0] - K2 * x[1]),
        ]
    }
    impl StageModel for Reactor {
        fn dim_x(&self) -> usize {
            2
        }
        fn dim_u(&self) -> usize {
            0
        }
        fn dim_y(&self) -> usize {
            1
        }
        fn evaluate(&mut self, d: &[f64], out: &mut StageEval) -> Result<()> {
            let k = d.len() / 2;
            out.resize(k, 2, 0, 1);
            for i in 0..k {
                let x = &d[2 * i..2 * i + 2];
                let f = step(x);
                out.mean_x[2 * i..2 * i + 2].copy_from_slice(&f);
                out.var_x[2 * i..2 * i + 2].fill(0.0);
                out.dvar_x[4 * i..4 * i + 4].fill(0.0);
                out.dmean_x[4 * i..4 * i + 4].copy_from_slice(&[
                    1.0 - 4.0 * T * K1 * x[0],
                    2.0 * T * K2,
                    2.0 * T * K1 * x[0],
                    1.0 - T * K2,
                ]);
                out.mean_y[i] = x[0] + x[1];
                out.var_y[i] = 0.0;
                out.dmean_y[2 * i..2 * i + 2].copy_from_slice(&[1.0, 1.0]);
                out.dvar_y[2 * i..2 * i + 2].fill(0.0);
            }
            Ok(())
        }
    }

    #[test]
    fn batch_reactor_window_from_the_poor_prior_reaches_a_kkt_point() {
        let mut rng: u64 = 17;
        let mut noise = || {
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((rng >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        };
        for &(nodes, form) in &[
            (16usize, Form::Prediction),
            (8, Form::Filtering),
            (1, Form::Filtering),
        ] {
            let mut x = [3.0, 1.0];
            let mut y = vec![0.0; nodes];
            for yi in y.iter_mut() {
                *yi = x[0] + x[1] + 0.1 * noise();
                let f = step(&x);
                x = [f[0] + 0.01 * noise(), f[1] + 0.01 * noise()];
            }
            let mut problem = WindowProblem::new(
                2,
                0,
                1,
                0.91,
                &[1e-3, 1e-3],
                &[1e-2],
                &[1.0, 0.0, 0.0, 1.0],
                form,
            )
            .unwrap();
            let mut present = vec![true; nodes];
            if nodes > 3 {
                present[2] = false; // a y=None step
            }
            problem.set_data(&[], &y, &present, &[0.1, 4.5]).unwrap();
            // Warm start: the poor prior rolled forward through the model (x1 on its bound).
            let mut z = vec![0.0; nodes * 2];
            z[..2].copy_from_slice(&[0.1, 4.5]);
            for i in 1..nodes {
                let f = step(&z[2 * (i - 1)..2 * i]);
                z[2 * i..2 * i + 2].copy_from_slice(&f);
            }
            let lo = vec![0.1; nodes * 2];
            let hi = vec![4.5; nodes * 2];
            let mut model = Reactor;
            let mut eval = WindowEval::default();
            let mut lsq = WindowLsq {
                problem: &problem,
                model: &mut model,
                eval: &mut eval,
            };
            let mut solver = BoxLsqSolver::new();
            let rep = solver.solve(&mut lsq, &mut z, &lo, &hi, &strict()).unwrap();
            assert!(rep.status.is_success(), "{rep:?}");
            assert!(rep.projected_gradient <= 1e-6, "{rep:?}");
            assert!(z.iter().all(|&v| (0.1..=4.5).contains(&v)));
            // The problem's state refers to the returned point.
            assert_eq!(eval.cost(), rep.cost);
            let mut g = vec![0.0; nodes * 2];
            eval.gradient_into(&mut g);
            assert_eq!(
                projected_gradient_norm(&z, &g, &lo, &hi),
                rep.projected_gradient
            );
        }
    }
}
