//! [`BorderedCholesky`]: the factorisation of a damped [`GnHessian`] H = [T B; Bᵀ C] whose node
//! part T is block-tridiagonal and whose m global variables couple with every node. T is factored
//! by the block-tridiagonal Cholesky recursion, Z = T⁻¹B by m of its solves, and the Schur
//! complement S = C − BᵀZ (m × m, dense) by faer's Cholesky: O(nodes·n³ + nodes·n²·m +
//! nodes·n·m² + m³). With m = 0 it is exactly the block-tridiagonal factorisation.
//!
//! Solves: g = S⁻¹(r_g − Zᵀr_x), x = T⁻¹r_x − Z g. Diagonal blocks of H⁻¹ over the nodes:
//! (T⁻¹)_ii + Z_i S⁻¹ Z_iᵀ.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt;
use faer::linalg::matmul::matmul;
use faer::linalg::triangular_solve::{
    solve_lower_triangular_in_place, solve_upper_triangular_in_place,
};
use faer::{Accum, Mat, MatMut, MatRef, Par};

use super::block_tridiag::{BlockTridiagCholesky, InverseBlocks};
use super::hessian::GnHessian;

/// The factorisation of H + diag(shift) with held variables (unit rows and columns).
#[derive(Debug, Default, Clone)]
pub struct BorderedCholesky {
    tri: BlockTridiagCholesky,
    /// Variables of the nodes and global variables of the last factorisation.
    nx: usize,
    m: usize,
    /// Z = T⁻¹B, row-major nx × m.
    z: Vec<f64>,
    /// The lower Cholesky factor of S (column-major m × m; the upper triangle is scratch).
    s: Vec<f64>,
}

impl BorderedCholesky {
    /// Factors H + diag(shift); variables with `fixed[k]` get a unit row and column (their
    /// solution equals their right-hand side). False if the matrix is not numerically positive
    /// definite.
    pub fn factor(&mut self, h: &GnHessian, shift: &[f64], fixed: &[bool]) -> bool {
        let (nx, m) = (h.node_vars(), h.m);
        (self.nx, self.m) = (nx, m);
        let (sx, fx) = (&shift[..nx], &fixed[..nx]);
        if !self.tri.factor(h.nodes, h.n, &h.diag, &h.off, sx, fx) {
            return false;
        }
        if m == 0 {
            return true;
        }
        self.z.clear();
        self.z.extend_from_slice(&h.border);
        for (k, row) in self.z.chunks_exact_mut(m).enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                if fixed[k] || fixed[nx + j] {
                    *v = 0.0;
                }
            }
        }
        self.tri.solve_many_in_place(&mut self.z, m);
        self.schur_complement(h, shift, fixed)
    }

    /// S = C + diag(shift_g) − BᵀZ into `s` (held global variables: unit rows) and its factor.
    fn schur_complement(&mut self, h: &GnHessian, shift: &[f64], fixed: &[bool]) -> bool {
        let (nx, m) = (self.nx, self.m);
        // C is symmetric: its row-major storage is its column-major storage.
        self.s.clear();
        self.s.extend_from_slice(&h.corner);
        let mut s = MatMut::from_column_major_slice_mut(&mut self.s, m, m);
        // Z's rows of held node variables are zero, so BᵀZ needs no masking of B.
        let b = MatRef::from_row_major_slice(&h.border, nx, m);
        let z = MatRef::from_row_major_slice(&self.z, nx, m);
        matmul(s.as_mut(), Accum::Add, b.transpose(), z, -1.0, Par::Seq);
        for j in 0..m {
            if fixed[nx + j] {
                for i in 0..m {
                    s[(i, j)] = 0.0;
                    s[(j, i)] = 0.0;
                }
                s[(j, j)] = 1.0;
            } else {
                s[(j, j)] += shift[nx + j];
            }
        }
        let mut mem = MemBuffer::new(llt::factor::cholesky_in_place_scratch::<f64>(
            m,
            Par::Seq,
            Default::default(),
        ));
        let factored = llt::factor::cholesky_in_place(
            s.as_mut(),
            Default::default(),
            Par::Seq,
            MemStack::new(&mut mem),
            Default::default(),
        );
        factored.is_ok() && (0..m).all(|j| s[(j, j)].is_finite() && s[(j, j)] > 0.0)
    }

    /// Solves (H + diag(shift)) x = b in place after a successful [`factor`](Self::factor).
    pub fn solve_in_place(&self, b: &mut [f64]) {
        let (nx, m) = (self.nx, self.m);
        let (bx, bg) = b.split_at_mut(nx);
        if m > 0 {
            // b_g − Zᵀ b_x
            for (row, &v) in self.z.chunks_exact(m).zip(bx.iter()) {
                bg.iter_mut().zip(row).for_each(|(g, a)| *g -= a * v);
            }
            self.solve_schur(MatMut::from_column_major_slice_mut(bg, m, 1));
        }
        self.tri.solve_in_place(bx);
        if m > 0 {
            for (row, v) in self.z.chunks_exact(m).zip(bx.iter_mut()) {
                *v -= row.iter().zip(bg.iter()).map(|(a, g)| a * g).sum::<f64>();
            }
        }
    }

    /// The lower Cholesky factor L of S.
    fn schur_factor(&self) -> MatRef<'_, f64> {
        MatRef::from_column_major_slice(&self.s, self.m, self.m)
    }

    /// rhs ← S⁻¹ rhs (S = LLᵀ).
    fn solve_schur(&self, mut rhs: MatMut<'_, f64>) {
        let l = self.schur_factor();
        solve_lower_triangular_in_place(l, rhs.as_mut(), Par::Seq);
        solve_upper_triangular_in_place(l.transpose(), rhs, Par::Seq);
    }

    /// The global variables' block of H⁻¹, S⁻¹ (m × m, row-major), after a successful
    /// [`factor`](Self::factor); None without global variables or if it is not finite.
    pub fn global_block_of_inverse(&self) -> Option<Vec<f64>> {
        let m = self.m;
        if m == 0 {
            return None;
        }
        // S⁻¹ solved in place in an identity (symmetric: row- and column-major alike).
        let mut out = vec![0.0; m * m];
        out.iter_mut().step_by(m + 1).for_each(|v| *v = 1.0);
        self.solve_schur(MatMut::from_column_major_slice_mut(&mut out, m, m));
        out.iter().all(|v| v.is_finite()).then_some(out)
    }

    /// The block of H⁻¹ of the last node (rows) with the global variables (columns), −Z_last S⁻¹
    /// (n × m, row-major), from `s_inverse` = S⁻¹ ([`global_block_of_inverse`]
    /// (Self::global_block_of_inverse)); None without global variables or if not finite.
    pub fn last_node_global_block(&self, s_inverse: &[f64]) -> Option<Vec<f64>> {
        let (nx, m, n) = (self.nx, self.m, self.tri.block_dim());
        if m == 0 || nx < n || s_inverse.len() != m * m {
            return None;
        }
        let z_last = MatRef::from_row_major_slice(&self.z[(nx - n) * m..nx * m], n, m);
        let mut out = vec![0.0; n * m];
        let o = MatMut::from_row_major_slice_mut(&mut out, n, m);
        let s_inv = MatRef::from_row_major_slice(s_inverse, m, m);
        matmul(o, Accum::Replace, z_last, s_inv, -1.0, Par::Seq);
        out.iter().all(|v| v.is_finite()).then_some(out)
    }

    /// The `which` diagonal blocks over the nodes of H⁻¹ (row-major, stacked), after a
    /// successful [`factor`](Self::factor): T⁻¹'s plus Z_i S⁻¹ Z_iᵀ = W_i W_iᵀ with W = Z L⁻ᵀ.
    /// None if one is not finite.
    pub fn inverse_blocks(&self, which: InverseBlocks) -> Option<Vec<f64>> {
        let mut out = self.tri.inverse_blocks(which)?;
        let (nx, m) = (self.nx, self.m);
        let n = self.tri.block_dim();
        if m == 0 || nx == 0 {
            return Some(out);
        }
        // Wᵀ = L⁻¹ Zᵀ (m × nx).
        let mut wt = Mat::<f64>::zeros(m, nx);
        wt.copy_from(MatRef::from_row_major_slice(&self.z, nx, m).transpose());
        solve_lower_triangular_in_place(self.schur_factor(), wt.as_mut(), Par::Seq);
        let first = match which {
            InverseBlocks::Last => nx / n - 1,
            InverseBlocks::All => 0,
        };
        let mut block = Mat::<f64>::zeros(n, n);
        for (b, i) in (first..nx / n).enumerate() {
            let w = wt.as_ref().subcols(i * n, n);
            matmul(
                block.as_mut(),
                Accum::Replace,
                w.transpose(),
                w,
                1.0,
                Par::Seq,
            );
            for r in 0..n {
                for c in 0..n {
                    out[b * n * n + r * n + c] += block[(r, c)];
                }
            }
        }
        out.iter().all(|v| v.is_finite()).then_some(out)
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::{DMatrix, DVector};

    use super::*;
    use crate::solver::test_problem::{random_z, Lcg, Synthetic, GLOBAL_SIZES};
    use crate::solver::BlockLsqProblem;

    /// The Gauss-Newton Hessian of a synthetic problem with global variables, in the solver's
    /// storage and dense, at a random point.
    fn hessians(nodes: usize, n: usize, m: usize, seed: u64) -> (GnHessian, DMatrix<f64>) {
        let mut p = Synthetic::with_globals(nodes, n, m, seed);
        let mut z = random_z(nodes, n, seed + 1);
        z.extend(random_z(1, m, seed + 2));
        p.evaluate(&z, true).unwrap();
        let mut h = GnHessian::default();
        h.resize(nodes, n, m);
        h.take(&p);
        (h, p.dense_hessian())
    }

    /// The dense matrix the factorisation should factor: H + diag(shift) with unit rows and
    /// columns for held variables.
    fn damped(h: &DMatrix<f64>, shift: &[f64], fixed: &[bool]) -> DMatrix<f64> {
        let mut a = h.clone();
        for k in 0..a.nrows() {
            a[(k, k)] += shift[k];
            if fixed[k] {
                a.row_mut(k).fill(0.0);
                a.column_mut(k).fill(0.0);
                a[(k, k)] = 1.0;
            }
        }
        a
    }

    #[test]
    fn bordered_solve_matches_dense_solve_with_held_variables() {
        for (case, &(nodes, n, m)) in GLOBAL_SIZES.iter().enumerate() {
            let seed = 40 + case as u64;
            let (h, dense) = hessians(nodes, n, m, seed);
            let len = nodes * n + m;
            let mut rng = Lcg(seed);
            let shift: Vec<f64> = (0..len).map(|_| 0.1 + rng.next().abs()).collect();
            // Hold one node variable and, when there are several, one global variable.
            let mut fixed = vec![false; len];
            fixed[(n * nodes) / 2] = true;
            if m > 1 {
                fixed[len - 1] = true;
            }
            let b: Vec<f64> = (0..len).map(|_| rng.next()).collect();
            let mut chol = BorderedCholesky::default();
            assert!(chol.factor(&h, &shift, &fixed));
            let mut x = b.clone();
            chol.solve_in_place(&mut x);
            let a = damped(&dense, &shift, &fixed);
            let want = a.lu().solve(&DVector::from_column_slice(&b)).unwrap();
            for k in 0..len {
                assert!(
                    (x[k] - want[k]).abs() <= 1e-10 * (1.0 + want[k].abs()),
                    "{case} {k}"
                );
            }
            // The product the solver uses for its model decrease is the dense one.
            let mut y = vec![0.0; len];
            h.matvec(&b, &mut y);
            let want = &dense * DVector::from_column_slice(&b);
            for k in 0..len {
                assert!((y[k] - want[k]).abs() <= 1e-12 * (1.0 + want[k].abs()));
            }
        }
    }

    #[test]
    fn node_blocks_of_the_inverse_match_the_dense_inverse() {
        for (case, &(nodes, n, m)) in GLOBAL_SIZES.iter().enumerate() {
            let (h, dense) = hessians(nodes, n, m, 60 + case as u64);
            let len = nodes * n + m;
            let mut chol = BorderedCholesky::default();
            assert!(chol.factor(&h, &vec![0.0; len], &vec![false; len]));
            let inv = dense.try_inverse().unwrap();
            let all = chol.inverse_blocks(InverseBlocks::All).unwrap();
            let last = chol.inverse_blocks(InverseBlocks::Last).unwrap();
            for i in 0..nodes {
                for r in 0..n {
                    for c in 0..n {
                        let want = inv[(i * n + r, i * n + c)];
                        let got = all[i * n * n + r * n + c];
                        assert!(
                            (got - want).abs() <= 1e-9 * (1.0 + want.abs()),
                            "{case} {i}"
                        );
                    }
                }
            }
            assert_eq!(last[..], all[(nodes - 1) * n * n..]);
            let global = chol.global_block_of_inverse().unwrap();
            for a in 0..m {
                for b in 0..m {
                    let want = inv[(nodes * n + a, nodes * n + b)];
                    assert!((global[a * m + b] - want).abs() <= 1e-9 * (1.0 + want.abs()));
                }
            }
        }
    }

    #[test]
    fn indefinite_schur_complement_is_reported() {
        let (mut h, _) = hessians(3, 2, 2, 7);
        h.corner.iter_mut().for_each(|v| *v = -1.0);
        let mut chol = BorderedCholesky::default();
        assert!(!chol.factor(&h, &[0.0; 8], &[false; 8]));
    }
}
