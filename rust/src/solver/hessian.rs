//! [`GnHessian`]: the Gauss-Newton Hessian 2JᵀJ of a window problem as the solver stores it, a
//! block-tridiagonal part over the nodes (n×n diagonal and super-diagonal blocks) bordered by m
//! global variables that couple with every node (`border`, nodes·n × m, and `corner`, m × m);
//! with m = 0 it is the plain block-tridiagonal matrix. Its product with a vector, its diagonal
//! (the Marquardt scaling) and its filling from a [`BlockLsqProblem`].

use super::block_tridiag::block_tridiag_matvec;
use super::BlockLsqProblem;

/// 2JᵀJ over z = [x̄_0; …; x̄_{nodes−1}; g] (g the m global variables), row-major blocks:
/// `diag` block i at i·n², `off` block (i, i+1) at i·n², `border` row k (variable k of the
/// nodes) at k·m, `corner` row j at j·m.
#[derive(Debug, Default, Clone)]
pub struct GnHessian {
    pub(super) nodes: usize,
    pub(super) n: usize,
    pub(super) m: usize,
    pub(super) diag: Vec<f64>,
    pub(super) off: Vec<f64>,
    pub(super) border: Vec<f64>,
    pub(super) corner: Vec<f64>,
}

impl GnHessian {
    /// Sizes the buffers for `nodes` nodes of `n` variables and `m` global variables.
    pub(super) fn resize(&mut self, nodes: usize, n: usize, m: usize) {
        (self.nodes, self.n, self.m) = (nodes, n, m);
        let nn = n * n;
        self.diag.resize(nodes * nn, 0.0);
        self.off.resize(nodes.saturating_sub(1) * nn, 0.0);
        self.border.resize(nodes * n * m, 0.0);
        self.corner.resize(m * m, 0.0);
    }

    /// Number of variables of the nodes (the global ones follow them in z).
    pub(super) fn node_vars(&self) -> usize {
        self.nodes * self.n
    }

    /// The problem's Gauss-Newton blocks at its last point evaluated with derivatives.
    pub(super) fn take<P: BlockLsqProblem + ?Sized>(&mut self, prob: &P) {
        prob.gauss_newton_blocks_into(&mut self.diag, &mut self.off);
        if self.m > 0 {
            prob.gauss_newton_border_into(&mut self.border, &mut self.corner);
        }
    }

    /// The diagonal entry H_kk.
    pub(super) fn diagonal(&self, k: usize) -> f64 {
        let nx = self.node_vars();
        if k < nx {
            let (i, r) = (k / self.n, k % self.n);
            self.diag[i * self.n * self.n + r * self.n + r]
        } else {
            let j = k - nx;
            self.corner[j * self.m + j]
        }
    }

    /// The floor of the Marquardt scaling: 1e-10 × the largest magnitude among every
    /// (n + 1)-th entry of the diagonal blocks and the corner's diagonal (at least 1e-10).
    pub(super) fn scale_floor(&self) -> f64 {
        let nodes = self.diag.iter().step_by(self.n + 1);
        let corner = self.corner.iter().step_by(self.m + 1);
        1e-10 * nodes.chain(corner).fold(1.0f64, |a, &b| a.max(b.abs()))
    }

    /// y = H x.
    pub(super) fn matvec(&self, x: &[f64], y: &mut [f64]) {
        let (nodes, n, m) = (self.nodes, self.n, self.m);
        block_tridiag_matvec(nodes, n, &self.diag, &self.off, x, y);
        if m == 0 {
            return;
        }
        let nx = nodes * n;
        let (xx, xg) = x.split_at(nx);
        let (yx, yg) = y.split_at_mut(nx);
        for (k, yk) in yx.iter_mut().enumerate() {
            let row = &self.border[k * m..(k + 1) * m];
            *yk += row.iter().zip(xg).map(|(b, v)| b * v).sum::<f64>();
        }
        for (yj, corner) in yg.iter_mut().zip(self.corner.chunks_exact(m)) {
            *yj = corner.iter().zip(xg).map(|(c, v)| c * v).sum();
        }
        for (row, &v) in self.border.chunks_exact(m).zip(xx) {
            yg.iter_mut().zip(row).for_each(|(y, b)| *y += b * v);
        }
    }
}
