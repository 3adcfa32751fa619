//! The linear algebra of one solver iteration: the block-tridiagonal Cholesky factorisation of the
//! damped Gauss-Newton Hessian (the Riccati-like recursion over the horizon), its solves, the last
//! diagonal block of its inverse (the last node's Laplace covariance) and the block-tridiagonal
//! matrix-vector product.

// Index loops over variables touch several parallel arrays (z, bounds, duals, steps) and read
// better than zipped iterator chains.
#![allow(clippy::needless_range_loop)]

use nalgebra::allocator::Allocator;
use nalgebra::{Cholesky, DMatrix, DefaultAllocator, Dim, MatrixView, MatrixViewMut, OMatrix, U1};

/// Block-tridiagonal Cholesky factorisation A = LLᵀ of a symmetric positive-definite matrix with
/// n×n blocks: L has diagonal blocks L_i and sub-diagonal blocks X_iᵀ with X_i = L_i⁻¹ A_{i,i+1};
/// L_{i+1}L_{i+1}ᵀ = A_{i+1,i+1} − X_iᵀX_i (the Riccati-like recursion). Cost O(nodes·n³).
#[derive(Debug, Default, Clone)]
pub struct BlockTridiagCholesky {
    n: usize,
    l: Vec<DMatrix<f64>>,
    x: Vec<DMatrix<f64>>,
}

impl BlockTridiagCholesky {
    /// Factors A + diag(shift), with `diag`/`off` row-major blocks as in [`BlockLsqProblem`].
    /// Variables with `fixed[k]` get a unit row and column (their solution equals their
    /// right-hand side). Returns false if the matrix is not numerically positive definite.
    pub fn factor(
        &mut self,
        nodes: usize,
        n: usize,
        diag: &[f64],
        off: &[f64],
        shift: &[f64],
        fixed: &[bool],
    ) -> bool {
        if self.n != n || self.l.len() != nodes {
            self.n = n;
            self.l = (0..nodes).map(|_| DMatrix::zeros(n, n)).collect();
            self.x = (0..nodes.saturating_sub(1))
                .map(|_| DMatrix::zeros(n, n))
                .collect();
        }
        let a = (diag, off, shift, fixed);
        with_block_dim!(n, d => self.factor_in(d, a))
    }

    /// [`factor`](Self::factor) with n×n blocks of dimension type D (stack matrices for small
    /// n; the same operations in the same order for every D).
    fn factor_in<D: Dim>(
        &mut self,
        d: D,
        (diag, off, shift, fixed): (&[f64], &[f64], &[f64], &[bool]),
    ) -> bool
    where
        DefaultAllocator: Allocator<D, D>,
    {
        let (n, nodes) = (d.value(), self.l.len());
        let nn = n * n;
        for i in 0..nodes {
            let mut a = OMatrix::<f64, D, D>::zeros_generic(d, d);
            for r in 0..n {
                for c in 0..=r {
                    let (kr, kc) = (i * n + r, i * n + c);
                    a[(r, c)] = if fixed[kr] || fixed[kc] {
                        if r == c {
                            1.0
                        } else {
                            0.0
                        }
                    } else if r == c {
                        diag[i * nn + r * n + c] + shift[kr]
                    } else {
                        diag[i * nn + r * n + c]
                    };
                }
            }
            if i > 0 {
                let xp = block(&self.x[i - 1], d);
                // Lower triangle of a − XᵀX (the upper part of `a` is never read).
                for r in 0..n {
                    for c in 0..=r {
                        a[(r, c)] -= xp.column(r).dot(&xp.column(c));
                    }
                }
            }
            let Some(ch) = Cholesky::new(a) else {
                self.l[i].fill(0.0);
                return false;
            };
            let li = ch.unpack_dirty();
            self.l[i].as_mut_slice().copy_from_slice(li.as_slice());
            if (0..n).any(|k| !(li[(k, k)].is_finite() && li[(k, k)] > 0.0)) {
                return false;
            }
            if i + 1 < nodes {
                let x = &mut self.x[i];
                for r in 0..n {
                    for c in 0..n {
                        x[(r, c)] = if fixed[i * n + r] || fixed[(i + 1) * n + c] {
                            0.0
                        } else {
                            off[i * nn + r * n + c]
                        };
                    }
                }
                li.solve_lower_triangular_unchecked_mut(&mut block_mut(x, d));
            }
        }
        true
    }

    /// The block size n.
    pub fn block_dim(&self) -> usize {
        self.n
    }

    /// Solves A x = b in place (after a successful [`factor`](Self::factor)).
    pub fn solve_in_place(&self, b: &mut [f64]) {
        with_block_dim!(self.n, d => self.solve_in(d, b))
    }

    /// [`solve_in_place`](Self::solve_in_place) with blocks of dimension type D.
    fn solve_in<D: Dim>(&self, d: D, b: &mut [f64])
    where
        DefaultAllocator: Allocator<D, D>,
    {
        let n = d.value();
        let nodes = self.l.len();
        for i in 0..nodes {
            let (prev, cur) = b.split_at_mut(i * n);
            let mut cur = MatrixViewMut::from_slice_generic(&mut cur[..n], d, U1);
            if i > 0 {
                let yp = MatrixView::from_slice_generic(&prev[(i - 1) * n..i * n], d, U1);
                cur.gemv_tr(-1.0, &block(&self.x[i - 1], d), &yp, 1.0);
            }
            block(&self.l[i], d).solve_lower_triangular_unchecked_mut(&mut cur);
        }
        for i in (0..nodes).rev() {
            let (cur, next) = b.split_at_mut((i + 1) * n);
            let mut cur = MatrixViewMut::from_slice_generic(&mut cur[i * n..], d, U1);
            if i + 1 < nodes {
                let xn = MatrixView::from_slice_generic(&next[..n], d, U1);
                cur.gemv(-1.0, &block(&self.x[i], d), &xn, 1.0);
            }
            block(&self.l[i], d).tr_solve_lower_triangular_unchecked_mut(&mut cur);
        }
    }
}

/// An n × n block as a view of dimension type D (d.value() = n).
fn block<D: Dim>(m: &DMatrix<f64>, d: D) -> MatrixView<'_, f64, D, D> {
    MatrixView::from_slice_generic(m.as_slice(), d, d)
}

/// [`block`], mutable.
fn block_mut<D: Dim>(m: &mut DMatrix<f64>, d: D) -> MatrixViewMut<'_, f64, D, D> {
    MatrixViewMut::from_slice_generic(m.as_mut_slice(), d, d)
}

/// An n × n nalgebra matrix as a faer view.
fn view(m: &DMatrix<f64>) -> faer::MatRef<'_, f64> {
    faer::MatRef::from_column_major_slice(m.as_slice(), m.nrows(), m.ncols())
}

impl BlockTridiagCholesky {
    /// Solves A X = B in place for `cols` right-hand sides at once after a successful
    /// [`factor`](Self::factor): `b` is row-major (nodes·n × cols), so each node's rows form one
    /// n × cols block (the solves of [`solve_in_place`](Self::solve_in_place) on matrix blocks).
    pub fn solve_many_in_place(&self, b: &mut [f64], cols: usize) {
        let (n, nodes) = (self.n, self.l.len());
        let block = n * cols;
        for i in 0..nodes {
            let (prev, cur) = b.split_at_mut(i * block);
            let mut cur = faer::MatMut::from_row_major_slice_mut(&mut cur[..block], n, cols);
            if i > 0 {
                let yp = faer::MatRef::from_row_major_slice(&prev[(i - 1) * block..], n, cols);
                let x = view(&self.x[i - 1]).transpose();
                faer::linalg::matmul::matmul(
                    cur.as_mut(),
                    faer::Accum::Add,
                    x,
                    yp,
                    -1.0,
                    faer::Par::Seq,
                );
            }
            faer::linalg::triangular_solve::solve_lower_triangular_in_place(
                view(&self.l[i]),
                cur,
                faer::Par::Seq,
            );
        }
        for i in (0..nodes).rev() {
            let (cur, next) = b.split_at_mut((i + 1) * block);
            let mut cur = faer::MatMut::from_row_major_slice_mut(&mut cur[i * block..], n, cols);
            if i + 1 < nodes {
                let xn = faer::MatRef::from_row_major_slice(&next[..block], n, cols);
                faer::linalg::matmul::matmul(
                    cur.as_mut(),
                    faer::Accum::Add,
                    view(&self.x[i]),
                    xn,
                    -1.0,
                    faer::Par::Seq,
                );
            }
            faer::linalg::triangular_solve::solve_upper_triangular_in_place(
                view(&self.l[i]).transpose(),
                cur,
                faer::Par::Seq,
            );
        }
    }
}

/// Which diagonal blocks of A⁻¹ [`BlockTridiagCholesky::inverse_blocks`] returns.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InverseBlocks {
    Last,
    All,
}

impl BlockTridiagCholesky {
    /// The `which` diagonal n×n blocks of A⁻¹ (row-major, stacked) after a successful
    /// [`factor`](Self::factor); None if one is not finite.
    pub fn inverse_blocks(&self, which: InverseBlocks) -> Option<Vec<f64>> {
        let n = self.n;
        let out = match which {
            InverseBlocks::Last => {
                let mut out = vec![0.0; n * n];
                self.last_block_of_inverse(&mut out);
                out
            }
            InverseBlocks::All => {
                let mut out = vec![0.0; self.l.len() * n * n];
                self.diagonal_blocks_of_inverse(&mut out);
                out
            }
        };
        out.iter().all(|v| v.is_finite()).then_some(out)
    }

    /// The last n×n diagonal block of A⁻¹ (row-major into `out`) after a successful
    /// [`factor`](Self::factor): L is block lower-bidiagonal, so (A⁻¹)_NN = L_N⁻ᵀ L_N⁻¹.
    pub fn last_block_of_inverse(&self, out: &mut [f64]) {
        let Some(l) = self.l.last() else { return };
        write_block(&gram_of_inverse(l).1, out);
    }

    /// Every diagonal n×n block of A⁻¹ (nodes blocks, row-major, into `out`) after a successful
    /// [`factor`](Self::factor), by the backward recursion of selected inversion:
    /// Σ_N = L_N⁻ᵀL_N⁻¹ and Σ_i = L_i⁻ᵀL_i⁻¹ + G_i Σ_{i+1} G_iᵀ with G_i = L_i⁻ᵀX_i (the
    /// block-row i of LᵀΣ = L⁻¹). O(nodes·n³); the last block is `last_block_of_inverse`'s.
    pub fn diagonal_blocks_of_inverse(&self, out: &mut [f64]) {
        let (n, nodes) = (self.n, self.l.len());
        if nodes == 0 {
            return;
        }
        let mut next = gram_of_inverse(&self.l[nodes - 1]).1;
        write_block(&next, &mut out[(nodes - 1) * n * n..]);
        for i in (0..nodes - 1).rev() {
            let (l_inv, own) = gram_of_inverse(&self.l[i]);
            let g = l_inv.transpose() * &self.x[i];
            next = own + &g * &next * g.transpose();
            write_block(&next, &mut out[i * n * n..]);
        }
    }
}

/// (L⁻¹, L⁻ᵀL⁻¹) of a lower-triangular factor L.
fn gram_of_inverse(l: &DMatrix<f64>) -> (DMatrix<f64>, DMatrix<f64>) {
    let n = l.nrows();
    let mut x = DMatrix::<f64>::identity(n, n);
    l.solve_lower_triangular_unchecked_mut(&mut x);
    let inv = x.transpose() * &x;
    (x, inv)
}

/// The n×n matrix `m` row-major into the first n² entries of `out`.
fn write_block(m: &DMatrix<f64>, out: &mut [f64]) {
    let n = m.nrows();
    for r in 0..n {
        for c in 0..n {
            out[r * n + c] = m[(r, c)];
        }
    }
}

/// The last n×n block of (2JᵀJ)⁻¹ from the block-tridiagonal Gauss-Newton blocks (row-major
/// into `out`), or None when 2JᵀJ is not positive definite. O(nodes·n³).
pub fn gauss_newton_last_block_inverse(
    nodes: usize,
    n: usize,
    diag: &[f64],
    off: &[f64],
) -> Option<Vec<f64>> {
    let zero = vec![0.0; nodes * n];
    let free = vec![false; nodes * n];
    let mut chol = BlockTridiagCholesky::default();
    if !chol.factor(nodes, n, diag, off, &zero, &free) {
        return None;
    }
    chol.inverse_blocks(InverseBlocks::Last)
}

/// y = A x for a block-tridiagonal symmetric A given by row-major `diag`/`off` blocks.
pub fn block_tridiag_matvec(
    nodes: usize,
    n: usize,
    diag: &[f64],
    off: &[f64],
    x: &[f64],
    y: &mut [f64],
) {
    with_block_dim!(n, d => matvec_in(d, nodes, diag, off, x, y))
}

/// [`block_tridiag_matvec`] with the block size n = `d` (a constant for small blocks, so the
/// inner loops unroll; the same sums in the same order either way).
fn matvec_in<D: Dim>(d: D, nodes: usize, diag: &[f64], off: &[f64], x: &[f64], y: &mut [f64]) {
    let n = d.value();
    let nn = n * n;
    for i in 0..nodes {
        let xi = &x[i * n..(i + 1) * n];
        let di = &diag[i * nn..(i + 1) * nn];
        let below =
            (i + 1 < nodes).then(|| (&off[i * nn..(i + 1) * nn], &x[(i + 1) * n..(i + 2) * n]));
        let above = (i > 0).then(|| (&off[(i - 1) * nn..i * nn], &x[(i - 1) * n..i * n]));
        for r in 0..n {
            let mut s = 0.0;
            for c in 0..n {
                s += di[r * n + c] * xi[c];
                if let Some((o, xn)) = below {
                    s += o[r * n + c] * xn[c];
                }
                if let Some((o, xp)) = above {
                    // block (i, i−1) = off_{i−1}ᵀ
                    s += o[c * n + r] * xp[c];
                }
            }
            y[i * n + r] = s;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solver::test_problem::{random_z, Lcg, Synthetic};
    use crate::solver::BlockLsqProblem;
    use nalgebra::DVector;

    fn dense_from_blocks(nodes: usize, n: usize, diag: &[f64], off: &[f64]) -> DMatrix<f64> {
        let mut a = DMatrix::zeros(nodes * n, nodes * n);
        for i in 0..nodes {
            for r in 0..n {
                for c in 0..n {
                    a[(i * n + r, i * n + c)] = diag[i * n * n + r * n + c];
                    if i + 1 < nodes {
                        let v = off[i * n * n + r * n + c];
                        a[(i * n + r, (i + 1) * n + c)] = v;
                        a[((i + 1) * n + c, i * n + r)] = v;
                    }
                }
            }
        }
        a
    }

    #[test]
    fn block_tridiagonal_solve_matches_dense_solve() {
        for &(nodes, n) in &[(1usize, 1usize), (1, 3), (2, 2), (16, 2), (7, 4)] {
            let mut p = Synthetic::new(nodes, n, 11 + nodes as u64);
            let z = random_z(nodes, n, 3);
            p.evaluate(&z, true).unwrap();
            let mut diag = vec![0.0; nodes * n * n];
            let mut off = vec![0.0; nodes.saturating_sub(1) * n * n];
            p.gauss_newton_blocks_into(&mut diag, &mut off);
            let mut rng = Lcg(5);
            let shift: Vec<f64> = (0..nodes * n).map(|_| 0.1 + rng.next().abs()).collect();
            let rhs: Vec<f64> = (0..nodes * n).map(|_| rng.next()).collect();
            for mask_every in [0usize, 3] {
                let fixed: Vec<bool> = (0..nodes * n)
                    .map(|k| mask_every > 0 && k % mask_every == 1)
                    .collect();
                let mut chol = BlockTridiagCholesky::default();
                assert!(chol.factor(nodes, n, &diag, &off, &shift, &fixed));
                let mut x: Vec<f64> = rhs
                    .iter()
                    .zip(&fixed)
                    .map(|(&b, &f)| if f { 0.0 } else { b })
                    .collect();
                chol.solve_in_place(&mut x);
                // Dense reference: the same matrix with fixed rows/cols replaced by identity.
                let mut a = dense_from_blocks(nodes, n, &diag, &off);
                for k in 0..nodes * n {
                    a[(k, k)] += shift[k];
                }
                for k in 0..nodes * n {
                    if fixed[k] {
                        a.row_mut(k).fill(0.0);
                        a.column_mut(k).fill(0.0);
                        a[(k, k)] = 1.0;
                    }
                }
                let b = DVector::from_iterator(
                    nodes * n,
                    rhs.iter()
                        .zip(&fixed)
                        .map(|(&b, &f)| if f { 0.0 } else { b }),
                );
                let xd = a.clone().cholesky().unwrap().solve(&b);
                for k in 0..nodes * n {
                    assert!(
                        (x[k] - xd[k]).abs() < 1e-10 * (1.0 + xd[k].abs()),
                        "{nodes} {n} {k}"
                    );
                }
                if mask_every == 0 {
                    // last diagonal block of the inverse of A + diag(shift)
                    let mut d2 = diag.clone();
                    for k in 0..nodes * n {
                        d2[(k / n) * n * n + (k % n) * n + k % n] += shift[k];
                    }
                    let inv = gauss_newton_last_block_inverse(nodes, n, &d2, &off).unwrap();
                    let ainv = a.clone().try_inverse().unwrap();
                    for r in 0..n {
                        for c in 0..n {
                            let e = ainv[((nodes - 1) * n + r, (nodes - 1) * n + c)];
                            assert!((inv[r * n + c] - e).abs() < 1e-9 * (1.0 + e.abs()));
                        }
                    }
                    // every diagonal block, the last one bit for bit as above
                    let mut all = vec![0.0; nodes * n * n];
                    chol.diagonal_blocks_of_inverse(&mut all);
                    assert_eq!(&all[(nodes - 1) * n * n..], &inv[..]);
                    for (k, v) in all.iter().enumerate() {
                        let (i, r, c) = (k / (n * n), (k / n) % n, k % n);
                        let e = ainv[(i * n + r, i * n + c)];
                        assert!((v - e).abs() < 1e-9 * (1.0 + e.abs()), "{nodes} {n} {k}");
                    }
                }
                let mut y = vec![0.0; nodes * n];
                block_tridiag_matvec(nodes, n, &diag, &off, &x, &mut y);
                let yd = dense_from_blocks(nodes, n, &diag, &off) * DVector::from_column_slice(&x);
                for k in 0..nodes * n {
                    assert!((y[k] - yd[k]).abs() < 1e-10 * (1.0 + yd[k].abs()));
                }
            }
        }
    }

    #[test]
    fn factor_reports_indefinite_matrix() {
        let diag = vec![1.0, 0.0, 0.0, -1.0];
        let mut chol = BlockTridiagCholesky::default();
        assert!(!chol.factor(1, 2, &diag, &[], &[0.0, 0.0], &[false, false]));
        // ... and recovers on the next call.
        assert!(chol.factor(1, 2, &diag, &[], &[0.0, 2.0], &[false, false]));
    }
}
