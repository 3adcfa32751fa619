//! Global variables of the window: n_g quantities of the model that are constant over the window
//! and estimated with its states (a sparse GP's inducing outputs), after the nodes in z.
//!
//! * [`GlobalPrior`]: their joint arrival prior with x̄_0, the n + n_g rows
//!   S ([a (x̄_0 − x̂); √2 (g − ĝ)]) that replace the prior rows of the states, and their Gram
//!   blocks, computed once per window;
//! * the rows' ∂r/∂g: −(a/√s) ∂m/∂g for a variance-weighted row, −a L⁻¹ ∂m/∂g for a block whitened
//!   with a full covariance (the variances do not depend on g);
//! * the window's gradient 2Jᵀr and Gauss-Newton Hessian 2JᵀJ with respect to g: the border
//!   (nodes·n × n_g) and corner (n_g × n_g) of the solver's bordered Hessian.

use std::sync::Arc;

use faer::linalg::matmul::matmul;
use faer::{Accum, MatMut, MatRef, Par};

use super::problem::WindowEval;
use crate::error::{check_finite, check_len, Error, Result};

/// The joint arrival prior of (x̄_0, g): mean ĝ of g (x̂ is the window's state prior) and S with
/// weight SᵀS, (n + n_g)² row-major.
#[derive(Debug, Clone)]
pub struct GlobalPrior {
    n: usize,
    mean: Vec<f64>,
    sqrt: Vec<f64>,
    gram: Arc<PriorGram>,
}

/// The prior rows' Gram blocks S_xᵀS_g (n × n_g) and S_gᵀS_g (n_g × n_g), row-major (S = [S_x
/// S_g]): their part of the Gauss-Newton Hessian, the same at every evaluation of a window.
#[derive(Debug, Clone)]
pub(super) struct PriorGram {
    xg: Vec<f64>,
    gg: Vec<f64>,
}

/// Where a window evaluation's prior rows are and what scales them (`WindowEval`).
#[derive(Debug, Clone)]
pub(super) struct PriorRows {
    gram: Arc<PriorGram>,
    /// The rows 0 … rows − 1, with weights a (states) and a_g (g).
    rows: usize,
    a: f64,
    a_g: f64,
}

impl GlobalPrior {
    /// Checks ĝ (`mean`, n_g ≥ 1 values) and S (`sqrt`, (n + n_g)² values).
    pub fn new(n: usize, mean: &[f64], sqrt: &[f64]) -> Result<Self> {
        if mean.is_empty() {
            return Err(Error::invalid(
                "g_prior",
                "needs at least one global variable",
            ));
        }
        let d = n + mean.len();
        check_len("joint_sqrt", sqrt, d * d)?;
        check_finite("g_prior", mean)?;
        check_finite("joint_sqrt", sqrt)?;
        let ng = mean.len();
        let s = MatRef::from_row_major_slice(sqrt, d, d);
        let (sx, sg) = (s.subcols(0, n), s.subcols(n, ng));
        let (mut xg, mut gg) = (vec![0.0; n * ng], vec![0.0; ng * ng]);
        let xg_m = MatMut::from_row_major_slice_mut(&mut xg, n, ng);
        matmul(xg_m, Accum::Replace, sx.transpose(), sg, 1.0, Par::Seq);
        let gg_m = MatMut::from_row_major_slice_mut(&mut gg, ng, ng);
        matmul(gg_m, Accum::Replace, sg.transpose(), sg, 1.0, Par::Seq);
        Ok(Self {
            n,
            mean: mean.to_vec(),
            sqrt: sqrt.to_vec(),
            gram: Arc::new(PriorGram { xg, gg }),
        })
    }

    /// n_g.
    pub fn dim(&self) -> usize {
        self.mean.len()
    }

    /// ĝ.
    pub fn mean(&self) -> &[f64] {
        &self.mean
    }

    /// S ((n + n_g)², row-major).
    pub fn sqrt(&self) -> &[f64] {
        &self.sqrt
    }

    /// Writes the rows S ([a (x̄_0 − x̂); √2 (g − ĝ)]) from row 0 (their ∂/∂x̄_0 into `ja`, ∂/∂g
    /// into `jg`): the states' part discounted as the window's prior (a = √(2η^{M_t})), g's not
    /// (its prior carries everything learned before the window; discounting it every window
    /// would forget it geometrically). Returns the next row.
    pub(super) fn write_rows(
        &self,
        a: f64,
        x0: &[f64],
        x_prior: &[f64],
        g: &[f64],
        want_jacobian: bool,
        out: &mut WindowEval,
    ) -> usize {
        let (n, ng) = (self.n, self.dim());
        let d = n + ng;
        let a_g = std::f64::consts::SQRT_2;
        let dev: Vec<f64> = (0..d)
            .map(|c| match c < n {
                true => a * (x0[c] - x_prior[c]),
                false => a_g * (g[c - n] - self.mean[c - n]),
            })
            .collect();
        for r in 0..d {
            let s = &self.sqrt[r * d..(r + 1) * d];
            out.r[r] = s.iter().zip(&dev).map(|(a, b)| a * b).sum::<f64>();
            out.node[r] = 0;
            out.process[r] = false;
            if want_jacobian {
                out.ja[r * n..(r + 1) * n]
                    .iter_mut()
                    .zip(&s[..n])
                    .for_each(|(j, v)| *j = a * v);
                out.jg[r * ng..(r + 1) * ng]
                    .iter_mut()
                    .zip(&s[n..])
                    .for_each(|(j, v)| *j = a_g * v);
            }
        }
        out.prior = Some(PriorRows {
            gram: Arc::clone(&self.gram),
            rows: d,
            a,
            a_g,
        });
        d
    }
}

/// ∂r/∂g = −scale ∂m/∂g of a variance-weighted row (scale = a/√s).
pub(super) fn global_row(jg: &mut [f64], scale: f64, dm: &[f64]) {
    jg.iter_mut().zip(dm).for_each(|(j, d)| *j = -scale * d);
}

/// ∂r/∂g = −a L⁻¹ ∂m/∂g of a whitened block of k rows (`a_linv` k × k, `dm` k × n_g).
pub(super) fn global_block(jg: &mut [f64], a_linv: &[f64], dm: &[f64], k: usize, ng: usize) {
    for (q, row) in jg.chunks_exact_mut(ng).enumerate().take(k) {
        for (c, j) in row.iter_mut().enumerate() {
            *j = -(0..k)
                .map(|l| a_linv[q * k + l] * dm[l * ng + c])
                .sum::<f64>();
        }
    }
}

/// The rows `rows` of the stage whose first component is `first` in a k × q × n_g array of
/// ∂m/∂g (row `first + j` for each j in `rows`), stacked; empty when n_g = 0.
pub(super) fn selected_rows(dg: &[f64], first: usize, rows: &[usize], ng: usize) -> Vec<f64> {
    rows.iter()
        .flat_map(|&j| dg[(first + j) * ng..(first + j + 1) * ng].iter().copied())
        .collect()
}

impl WindowEval {
    /// 2 J_gᵀ r into `g` (n_g values).
    pub(super) fn global_gradient_into(&self, g: &mut [f64]) {
        let ng = self.ng;
        for (row, rk) in self.jg.chunks_exact(ng).zip(&self.r) {
            g.iter_mut().zip(row).for_each(|(a, j)| *a += 2.0 * j * rk);
        }
    }

    /// The border 2 J_xᵀ J_g (nodes·n × n_g, row-major) and corner 2 J_gᵀ J_g (n_g × n_g) of
    /// the Gauss-Newton Hessian. Needs an evaluation with the Jacobian. The prior rows add
    /// their precomputed Gram blocks; every other row only its nonzero range of ∂r/∂g (a process
    /// row of a GP's state touches that GP's inducing outputs only).
    pub fn gauss_newton_border_into(&self, border: &mut [f64], corner: &mut [f64]) {
        let (n, ng) = (self.n, self.ng);
        border.fill(0.0);
        corner.fill(0.0);
        let first = self.prior.as_ref().map_or(0, |p| p.rows);
        if let Some(p) = &self.prior {
            let (sx, sg) = (2.0 * p.a * p.a_g, 2.0 * p.a_g * p.a_g);
            border[..n * ng]
                .iter_mut()
                .zip(&p.gram.xg)
                .for_each(|(b, v)| *b = sx * v);
            corner
                .iter_mut()
                .zip(&p.gram.gg)
                .for_each(|(c, v)| *c = sg * v);
        }
        for (k, jg) in self.jg.chunks_exact(ng).enumerate().skip(first) {
            let Some(lo) = jg.iter().position(|&v| v != 0.0) else {
                continue;
            };
            let hi = ng - jg.iter().rev().position(|&v| v != 0.0).unwrap_or(0);
            let jr = &jg[lo..hi];
            // A zero factor changes nothing unless the other is not finite (0·inf is NaN), as
            // in `gauss_newton_blocks_into`.
            let finite = jr.iter().all(|v| v.is_finite());
            let i = self.node[k];
            let mut add = |node: usize, jx: &[f64]| {
                for (l, &v) in jx.iter().enumerate() {
                    if v != 0.0 || !finite {
                        let row = (node * n + l) * ng;
                        let b = &mut border[row + lo..row + hi];
                        b.iter_mut().zip(jr).for_each(|(b, j)| *b += 2.0 * v * j);
                    }
                }
            };
            add(i, &self.ja[k * n..(k + 1) * n]);
            if self.process[k] {
                add(i + 1, &self.jb[k * n..(k + 1) * n]);
            }
            // The corner's upper triangle: 2 J_a J_b rounds to the same number for (a, b) and
            // (b, a) (doubling is exact), so the lower one is its mirror.
            for (a, &va) in jr.iter().enumerate() {
                if va != 0.0 || !finite {
                    let row = (lo + a) * ng;
                    let c = &mut corner[row + lo + a..row + hi];
                    c.iter_mut()
                        .zip(&jr[a..])
                        .for_each(|(c, j)| *c += 2.0 * va * j);
                }
            }
        }
        for a in 0..ng {
            for b in a + 1..ng {
                corner[b * ng + a] = corner[a * ng + b];
            }
        }
    }

    /// Adds the border and corner to a dense Gauss-Newton Hessian (row-major, n_vars²).
    pub(super) fn dense_global_blocks(&self, h: &mut [f64]) {
        let (ng, nx) = (self.ng, self.nodes * self.n);
        let nv = nx + ng;
        let mut border = vec![0.0; nx * ng];
        let mut corner = vec![0.0; ng * ng];
        self.gauss_newton_border_into(&mut border, &mut corner);
        for k in 0..nx {
            for c in 0..ng {
                h[k * nv + nx + c] = border[k * ng + c];
                h[(nx + c) * nv + k] = border[k * ng + c];
            }
        }
        for a in 0..ng {
            h[(nx + a) * nv + nx..(nx + a + 1) * nv].copy_from_slice(&corner[a * ng..(a + 1) * ng]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mhe::problem::tests::check_derivatives;
    use crate::mhe::{Form, Loss, StageEval, StageModel, WindowLsq, WindowProblem};
    use crate::solver::test_problem::strict;
    use crate::solver::BoxLsqSolver;

    /// An analytic model (n = 2, m = 1, p = 2) with two global variables g:
    /// m_x = [x0 + 0.1 x1 sin x0 + 0.2u + g0 x1, 0.9 x1 + 0.05 x0² + 0.3 g1 + 0.1 g1²],
    /// m_y = [x0 x1 + u + g0 x0, x1 + 0.5 g1], var_x = [0.01 + 0.02 x0², 0.03 + 0.01 (x1 − u)²],
    /// var_y = [0.02 + 0.01 x0², 0.05].
    #[derive(Default)]
    struct WithGlobals {
        g: [f64; 2],
    }

    impl StageModel for WithGlobals {
        fn dim_x(&self) -> usize {
            2
        }
        fn dim_u(&self) -> usize {
            1
        }
        fn dim_y(&self) -> usize {
            2
        }
        fn n_globals(&self) -> usize {
            2
        }
        fn set_globals(&mut self, g: &[f64]) -> Result<()> {
            check_len("globals", g, 2)?;
            self.g.copy_from_slice(g);
            Ok(())
        }
        fn evaluate(&mut self, d: &[f64], out: &mut StageEval) -> Result<()> {
            let k = d.len() / 3;
            let [g0, g1] = self.g;
            out.resize(k, 2, 1, 2);
            for v in [
                &mut out.dmean_x,
                &mut out.dvar_x,
                &mut out.dmean_y,
                &mut out.dvar_y,
            ] {
                v.fill(0.0);
            }
            out.resize_globals(k, 2, 2, 2);
            for i in 0..k {
                let (x0, x1, u) = (d[3 * i], d[3 * i + 1], d[3 * i + 2]);
                out.mean_x[2 * i] = x0 + 0.1 * x1 * x0.sin() + 0.2 * u + g0 * x1;
                out.mean_x[2 * i + 1] = 0.9 * x1 + 0.05 * x0 * x0 + 0.3 * g1 + 0.1 * g1 * g1;
                let dm = &mut out.dmean_x[6 * i..6 * i + 6];
                dm.copy_from_slice(&[
                    1.0 + 0.1 * x1 * x0.cos(),
                    0.1 * x0.sin() + g0,
                    0.2,
                    0.1 * x0,
                    0.9,
                    0.0,
                ]);
                out.var_x[2 * i] = 0.01 + 0.02 * x0 * x0;
                out.var_x[2 * i + 1] = 0.03 + 0.01 * (x1 - u).powi(2);
                out.dvar_x[6 * i] = 0.04 * x0;
                out.dvar_x[6 * i + 4] = 0.02 * (x1 - u);
                out.dvar_x[6 * i + 5] = -0.02 * (x1 - u);
                out.mean_y[2 * i] = x0 * x1 + u + g0 * x0;
                out.mean_y[2 * i + 1] = x1 + 0.5 * g1;
                out.dmean_y[6 * i..6 * i + 6].copy_from_slice(&[x1 + g0, x0, 1.0, 0.0, 1.0, 0.0]);
                out.var_y[2 * i] = 0.02 + 0.01 * x0 * x0;
                out.var_y[2 * i + 1] = 0.05;
                out.dvar_y[6 * i] = 0.02 * x0;
                out.dmean_x_dg[4 * i..4 * i + 4].copy_from_slice(&[x1, 0.0, 0.0, 0.3 + 0.2 * g1]);
                out.dmean_y_dg[4 * i..4 * i + 4].copy_from_slice(&[x0, 0.0, 0.0, 0.5]);
            }
            Ok(())
        }
    }

    const S: [f64; 16] = [
        1.0, 0.3, 0.1, 0.0, 0.0, 0.8, -0.2, 0.1, 0.0, 0.0, 1.5, 0.4, 0.0, 0.0, 0.0, 0.7,
    ];

    /// A window of `nodes` nodes, output `missing` absent, with full or diagonal weights.
    fn window(form: Form, nodes: usize, missing: &[usize], full: bool) -> WindowProblem {
        let (q0, r0): (&[f64], &[f64]) = match full {
            true => (&[1e-3, 4e-4, 4e-4, 2e-3], &[1e-2, 3e-3, 3e-3, 2e-2]),
            false => (&[1e-3, 2e-3], &[1e-2, 2e-2]),
        };
        let mut w = WindowProblem::new(2, 1, 2, 0.9, q0, r0, &[1.0, 0.3, 0.0, 0.8], form).unwrap();
        let u: Vec<f64> = (0..nodes).map(|i| 0.1 * i as f64).collect();
        let y: Vec<f64> = (0..2 * nodes).map(|j| 1.0 + 0.2 * j as f64).collect();
        let present: Vec<bool> = (0..nodes).map(|i| !missing.contains(&i)).collect();
        w.set_data(&u, &y, &present, &[0.7, 1.3]).unwrap();
        w.set_global_prior(&[0.2, -0.4], &S).unwrap();
        w
    }

    fn z0(nodes: usize) -> Vec<f64> {
        let mut z: Vec<f64> = (0..2 * nodes)
            .map(|j| 0.5 + 0.37 * ((j * 7 % 5) as f64))
            .collect();
        z.extend([0.35, -0.1]);
        z
    }

    /// Gradient and dense Jacobian against central differences (the window's own check), and
    /// the solver's blocks (diagonal, off-diagonal, border, corner) against the dense 2JᵀJ.
    fn check_window(w: &WindowProblem, z: &[f64]) {
        let mut model = WithGlobals::default();
        let jac = check_derivatives(w, &mut model, z, 1e-5);
        let mut ev = WindowEval::default();
        w.evaluate(&mut model, z, true, &mut ev).unwrap();
        let (nv, rows) = (z.len(), ev.n_residuals());
        let dense = ev.dense_gauss_newton();
        for a in 0..nv {
            for b in 0..nv {
                let want: f64 = (0..rows)
                    .map(|r| 2.0 * jac[r * nv + a] * jac[r * nv + b])
                    .sum();
                assert!((dense[a * nv + b] - want).abs() <= 1e-10 * (1.0 + want.abs()));
            }
        }
    }

    #[test]
    fn window_with_globals_derivatives_match_finite_differences() {
        for form in [Form::Prediction, Form::Filtering] {
            for full in [false, true] {
                for loss in [Loss::Squared, Loss::Huber(0.5)] {
                    for (nodes, missing) in [(1, vec![]), (2, vec![]), (5, vec![2])] {
                        let mut w = window(form, nodes, &missing, full);
                        w.set_loss(loss);
                        check_window(&w, &z0(nodes));
                    }
                }
            }
        }
    }

    #[test]
    fn joint_prior_rows_are_the_prior_quadratic_form() {
        // With one node in the prediction form the window is the prior alone.
        let w = window(Form::Prediction, 1, &[], false);
        let z = z0(1);
        let mut ev = WindowEval::default();
        w.evaluate(&mut WithGlobals::default(), &z, false, &mut ev)
            .unwrap();
        let dev = [z[0] - 0.7, z[1] - 1.3, z[2] - 0.2, z[3] + 0.4];
        let want: f64 = (0..4)
            .map(|r| (0..4).map(|c| S[r * 4 + c] * dev[c]).sum::<f64>().powi(2))
            .sum::<f64>()
            * 2.0;
        assert!((ev.cost() - want).abs() <= 1e-14 * want);
    }

    #[test]
    fn solver_reaches_a_stationary_point_of_a_window_with_globals() {
        for form in [Form::Prediction, Form::Filtering] {
            let w = window(form, 6, &[3], true);
            let mut z = z0(6);
            let mut model = WithGlobals::default();
            let mut eval = WindowEval::default();
            let mut lsq = WindowLsq {
                problem: &w,
                model: &mut model,
                eval: &mut eval,
            };
            let len = z.len();
            let (lo, hi) = (vec![f64::NEG_INFINITY; len], vec![f64::INFINITY; len]);
            let rep = BoxLsqSolver::new()
                .solve(&mut lsq, &mut z, &lo, &hi, &strict())
                .unwrap();
            assert!(
                rep.status.is_success() && rep.projected_gradient <= 1e-6,
                "{rep:?}"
            );
        }
    }

    #[test]
    fn mismatched_globals_are_refused_and_keep_the_window() {
        let mut w = window(Form::Filtering, 3, &[], false);
        let mut ev = WindowEval::default();
        let short = &z0(3)[..6];
        let e = w
            .evaluate(&mut WithGlobals::default(), short, false, &mut ev)
            .unwrap_err();
        assert!(matches!(e, Error::InvalidInput { ref arg, .. } if arg == "z"));
        let e = w.set_global_prior(&[0.0, 0.0], &S[..9]).unwrap_err();
        assert!(matches!(e, Error::InvalidInput { ref arg, .. } if arg == "joint_sqrt"));
        assert_eq!(w.global_prior().unwrap().sqrt(), &S[..]);
        let e = w.set_global_prior(&[0.0, f64::NAN], &S).unwrap_err();
        assert!(matches!(e, Error::InvalidInput { ref arg, .. } if arg == "g_prior"));
        // A window without the prior refuses a model with global variables.
        let plain = WindowProblem::new(
            2,
            1,
            2,
            0.9,
            &[1.0; 2],
            &[1.0; 2],
            &[1.0, 0.0, 0.0, 1.0],
            Form::Filtering,
        )
        .unwrap();
        let e = plain
            .evaluate(&mut WithGlobals::default(), &[0.0; 2], false, &mut ev)
            .unwrap_err();
        assert!(matches!(e, Error::InvalidInput { ref arg, .. } if arg == "model"));
    }
}
