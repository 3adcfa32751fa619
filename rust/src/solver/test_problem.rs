//! A synthetic window-like least-squares problem with an analytic Jacobian, shared by the
//! solver's tests (compiled for tests only).

// The residual loops index several arrays at once.
#![allow(clippy::needless_range_loop)]

use nalgebra::{DMatrix, DVector};

use super::{projected_gradient_norm, BlockLsqProblem, SolverOptions};
use crate::error::Result;

/// The defaults without the early decrement stop: tests of first-order optimality run to
/// `gtol`.
pub(crate) fn strict() -> SolverOptions {
    SolverOptions {
        dtol: 0.0,
        ..SolverOptions::default()
    }
}

/// Deterministic pseudo-random numbers in [−1, 1) (no rand dependency).
pub(super) struct Lcg(pub(super) u64);
impl Lcg {
    pub(super) fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }
}

/// A synthetic window-like problem: prior rows on node 0, process rows
/// z_{j+1} − f(z_j) on nodes j, j+1, output rows y_j − h(z_j) (p = 2) on node j; dense
/// analytic Jacobian, from which the gradient and the Gauss-Newton blocks are formed.
pub(super) struct Synthetic {
    pub(super) nodes: usize,
    pub(super) n: usize,
    pub(super) a: Vec<f64>,
    pub(super) y: Vec<f64>,
    pub(super) wq: f64,
    pub(super) wr: f64,
    /// cost is +inf when z[0] exceeds this (tests robustness to failed evaluations)
    pub(super) blowup: f64,
    /// Global variables θ (after the nodes in z): the process rows are
    /// z_{j+1} − f(z_j) − (1 + 0.2 z_j) ⊙ Gθ, with G (n × m, row-major) in `g` and prior rows
    /// θ − θ̄ (θ̄ in `theta_bar`).
    pub(super) globals: usize,
    pub(super) g: Vec<f64>,
    pub(super) theta_bar: Vec<f64>,
    pub(super) r: Vec<f64>,
    pub(super) jac: DMatrix<f64>,
}

const P: usize = 2;

impl Synthetic {
    pub(super) fn new(nodes: usize, n: usize, seed: u64) -> Self {
        Self::with_weights(nodes, n, seed, 3.0, 2.0, 0.3)
    }

    /// A stiff window: process rows weighted `wq` (e.g. 1e4, i.e. 1e8 in J against 1 for the
    /// outputs), data from a trajectory with process noise 1/wq, output weight 1, so that the
    /// optimum lies in a narrow valley of J along the trajectories of the (nonlinear) model.
    pub(super) fn stiff(nodes: usize, n: usize, seed: u64, wq: f64) -> Self {
        Self::with_weights(nodes, n, seed, wq, 1.0, 1.0 / wq)
    }

    /// Process weight `wq`, output weight `wr`, data from a trajectory with process noise
    /// `sigma_w` (uniform in ±sigma_w).
    fn with_weights(nodes: usize, n: usize, seed: u64, wq: f64, wr: f64, sigma_w: f64) -> Self {
        let mut rng = Lcg(seed);
        let a: Vec<f64> = (0..n).map(|_| rng.next()).collect();
        let rows = n + (nodes - 1) * n + nodes * P;
        let mut p = Synthetic {
            nodes,
            n,
            a: a.clone(),
            y: vec![0.0; nodes * P],
            wq,
            wr,
            blowup: f64::INFINITY,
            globals: 0,
            g: Vec::new(),
            theta_bar: Vec::new(),
            r: vec![0.0; rows],
            jac: DMatrix::zeros(rows, nodes * n),
        };
        // Outputs of a noisy trajectory from a perturbed initial state, plus output noise:
        // residuals of order one at the optimum, as in a whitened MHE window.
        let mut x: Vec<f64> = a.iter().map(|v| v + 0.3 * rng.next()).collect();
        let (mut fx, mut fj) = (vec![0.0; n], DMatrix::zeros(n, n));
        let (mut hx, mut hj) = (vec![0.0; P], DMatrix::zeros(P, n));
        for j in 0..nodes {
            p.h(&x, &mut hx, &mut hj);
            for r in 0..P {
                p.y[j * P + r] = hx[r] + 0.5 * rng.next();
            }
            p.f(&x, &mut fx, &mut fj);
            for r in 0..n {
                x[r] = fx[r] + sigma_w * rng.next();
            }
        }
        p
    }
    /// The problem of [`Synthetic::new`] with `m` global variables (see the field `globals`).
    pub(super) fn with_globals(nodes: usize, n: usize, m: usize, seed: u64) -> Self {
        let mut p = Self::new(nodes, n, seed);
        let mut rng = Lcg(seed ^ 0x5eed);
        p.globals = m;
        p.g = (0..n * m).map(|_| 0.5 * rng.next()).collect();
        p.theta_bar = (0..m).map(|_| rng.next()).collect();
        p.r.resize(p.r.len() + m, 0.0);
        p.jac = DMatrix::zeros(p.r.len(), nodes * n + m);
        p
    }

    /// (Gθ)_r for the global variables at the end of z.
    fn g_theta(&self, z: &[f64], r: usize) -> f64 {
        let (m, th) = (self.globals, &z[self.nodes * self.n..]);
        (0..m).map(|c| self.g[r * m + c] * th[c]).sum()
    }

    fn f(&self, x: &[f64], out: &mut [f64], jac: &mut DMatrix<f64>) {
        let n = self.n;
        for r in 0..n {
            let nx = x[(r + 1) % n];
            out[r] = x[r] + 0.3 * nx.sin() - 0.1 * x[r] * x[r];
            for c in 0..n {
                jac[(r, c)] = 0.0;
            }
            jac[(r, r)] += 1.0 - 0.2 * x[r];
            jac[(r, (r + 1) % n)] += 0.3 * nx.cos();
        }
    }
    fn h(&self, x: &[f64], out: &mut [f64], jac: &mut DMatrix<f64>) {
        let n = self.n;
        out[0] = x[0] + x[n - 1] * x[n - 1];
        out[1] = (0.5 * x[0]).exp() - x[1 % n];
        jac.fill(0.0);
        jac[(0, 0)] += 1.0;
        jac[(0, n - 1)] += 2.0 * x[n - 1];
        jac[(1, 0)] += 0.5 * (0.5 * x[0]).exp();
        jac[(1, 1 % n)] -= 1.0;
    }
    pub(super) fn residuals(&mut self, z: &[f64]) {
        let n = self.n;
        self.jac.fill(0.0);
        let mut row = 0;
        for c in 0..n {
            self.r[row] = z[c] - self.a[c];
            self.jac[(row, c)] = 1.0;
            row += 1;
        }
        let mut fx = vec![0.0; n];
        let mut fj = DMatrix::zeros(n, n);
        let (nx, m) = (self.nodes * n, self.globals);
        for j in 0..self.nodes - 1 {
            self.f(&z[j * n..(j + 1) * n], &mut fx, &mut fj);
            for r in 0..n {
                let (xr, gt) = (z[j * n + r], self.g_theta(z, r));
                self.r[row] = self.wq * (z[(j + 1) * n + r] - fx[r] - (1.0 + 0.2 * xr) * gt);
                self.jac[(row, (j + 1) * n + r)] = self.wq;
                for c in 0..n {
                    self.jac[(row, j * n + c)] = -self.wq * fj[(r, c)];
                }
                self.jac[(row, j * n + r)] -= self.wq * 0.2 * gt;
                for c in 0..m {
                    self.jac[(row, nx + c)] = -self.wq * (1.0 + 0.2 * xr) * self.g[r * m + c];
                }
                row += 1;
            }
        }
        let mut hx = vec![0.0; P];
        let mut hj = DMatrix::zeros(P, n);
        for j in 0..self.nodes {
            self.h(&z[j * n..(j + 1) * n], &mut hx, &mut hj);
            for r in 0..P {
                self.r[row] = self.wr * (self.y[j * P + r] - hx[r]);
                for c in 0..n {
                    self.jac[(row, j * n + c)] = -self.wr * hj[(r, c)];
                }
                row += 1;
            }
        }
        for c in 0..m {
            self.r[row] = z[nx + c] - self.theta_bar[c];
            self.jac[(row, nx + c)] = 1.0;
            row += 1;
        }
    }
    pub(super) fn dense_hessian(&self) -> DMatrix<f64> {
        self.jac.transpose() * &self.jac * 2.0
    }
}

impl BlockLsqProblem for Synthetic {
    fn n_nodes(&self) -> usize {
        self.nodes
    }
    fn node_dim(&self) -> usize {
        self.n
    }
    fn evaluate(&mut self, z: &[f64], _want: bool) -> Result<f64> {
        if z[0] > self.blowup {
            return Ok(f64::INFINITY);
        }
        self.residuals(z);
        Ok(self.r.iter().map(|v| v * v).sum())
    }
    fn gradient_into(&self, g: &mut [f64]) {
        let gv = self.jac.transpose() * DVector::from_column_slice(&self.r) * 2.0;
        g.copy_from_slice(gv.as_slice());
    }
    fn gauss_newton_blocks_into(&self, diag: &mut [f64], off: &mut [f64]) {
        let h = self.dense_hessian();
        let n = self.n;
        for i in 0..self.nodes {
            for r in 0..n {
                for c in 0..n {
                    diag[i * n * n + r * n + c] = h[(i * n + r, i * n + c)];
                    if i + 1 < self.nodes {
                        off[i * n * n + r * n + c] = h[(i * n + r, (i + 1) * n + c)];
                    }
                }
            }
        }
    }
    fn global_dim(&self) -> usize {
        self.globals
    }
    fn gauss_newton_border_into(&self, border: &mut [f64], corner: &mut [f64]) {
        let h = self.dense_hessian();
        let (nx, m) = (self.nodes * self.n, self.globals);
        for c in 0..m {
            for k in 0..nx {
                border[k * m + c] = h[(k, nx + c)];
            }
            for j in 0..m {
                corner[j * m + c] = h[(nx + j, nx + c)];
            }
        }
    }
}

/// The model's trajectory from `x0` over the window (an MHE warm start: on the valley of a
/// stiff window, where the process rows vanish).
pub(super) fn trajectory(p: &Synthetic, x0: &[f64]) -> Vec<f64> {
    let n = p.n;
    let mut z = x0.to_vec();
    let (mut fx, mut fj) = (vec![0.0; n], DMatrix::zeros(n, n));
    for j in 1..p.nodes {
        p.f(&z[(j - 1) * n..j * n], &mut fx, &mut fj);
        z.extend_from_slice(&fx);
    }
    z
}

pub(super) fn random_z(nodes: usize, n: usize, seed: u64) -> Vec<f64> {
    let mut rng = Lcg(seed);
    (0..nodes * n).map(|_| rng.next()).collect()
}

/// Reference: projected gradient descent with Armijo backtracking on the dense problem,
/// many iterations (slow but independent of the Gauss-Newton machinery).
pub(super) fn reference_projected_gradient(
    p: &mut Synthetic,
    z0: &[f64],
    lo: &[f64],
    hi: &[f64],
) -> (Vec<f64>, f64) {
    let mut z: Vec<f64> = z0
        .iter()
        .zip(lo.iter().zip(hi))
        .map(|(&v, (&l, &u))| v.clamp(l, u))
        .collect();
    let mut c = p.evaluate(&z, true).unwrap();
    let mut g = vec![0.0; z.len()];
    let mut step = 1.0;
    for _ in 0..1500 {
        p.gradient_into(&mut g);
        if projected_gradient_norm(&z, &g, lo, hi) < 1e-9 {
            break;
        }
        step *= 4.0;
        loop {
            let zt: Vec<f64> = (0..z.len())
                .map(|k| (z[k] - step * g[k]).clamp(lo[k], hi[k]))
                .collect();
            let dec: f64 = (0..z.len()).map(|k| g[k] * (z[k] - zt[k])).sum();
            let ct = p.evaluate(&zt, true).unwrap();
            if ct <= c - 1e-4 * dec {
                z = zt;
                c = ct;
                break;
            }
            step *= 0.5;
            p.evaluate(&z, true).unwrap();
            if step < 1e-20 {
                return (z, c);
            }
        }
    }
    (z, c)
}

/// Sizes of the problems with global variables the tests run: (nodes, n, m).
#[cfg(test)]
pub(super) const GLOBAL_SIZES: [(usize, usize, usize); 4] =
    [(1, 2, 3), (5, 3, 1), (6, 2, 7), (4, 1, 12)];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn synthetic_jacobian_matches_finite_differences() {
        check_jacobian(Synthetic::new(5, 3, 7), random_z(5, 3, 8));
        check_jacobian(Synthetic::with_globals(5, 3, 2, 7), random_z(5, 3, 8 + 2));
        // The Hessian really is block-tridiagonal.
        let mut p = Synthetic::new(5, 3, 7);
        p.residuals(&random_z(5, 3, 8));
        let hd = p.dense_hessian();
        for i in 0..15usize {
            for j in 0..15 {
                if (i / 3).abs_diff(j / 3) > 1 {
                    assert_eq!(hd[(i, j)], 0.0);
                }
            }
        }
    }

    fn check_jacobian(mut p: Synthetic, mut z: Vec<f64>) {
        z.resize(p.jac.ncols(), 0.3);
        p.residuals(&z);
        let (r0, jac) = (p.r.clone(), p.jac.clone());
        let h = 1e-6;
        for k in 0..z.len() {
            let mut zp = z.clone();
            zp[k] += h;
            p.residuals(&zp);
            for row in 0..r0.len() {
                let fd = (p.r[row] - r0[row]) / h;
                assert!((fd - jac[(row, k)]).abs() < 1e-4, "row {row} col {k}");
            }
        }
    }
}
