//! The diagonal blocks of the sandwich H⁻¹ G H⁻¹ of two symmetric block-tridiagonal matrices
//! (H positive definite), in O(nodes·n³): the covariance of a weighted least-squares estimate
//! whose weights are not the inverse covariances of its residuals (a discounted MHE window,
//! docs/user_guide/uncertainty.rst).
//!
//! Method: (H − εG)⁻¹ = H⁻¹ + ε H⁻¹GH⁻¹ + O(ε²), so the selected inversion of H − εG over dual
//! numbers a + εb (ε² = 0) gives H⁻¹'s diagonal blocks as its real parts and the sandwich's as
//! its dual parts. The recursion is block LDLᵀ elimination, S_0 = A_00,
//! S_i = A_ii − U_{i−1} A_{i−1,i} with U_i = A_{i,i+1}ᵀ S_i⁻¹, then the selected inversion
//! Σ_N = S_N⁻¹, Σ_i = S_i⁻¹ + U_iᵀ Σ_{i+1} U_i, with the dual inverse
//! (a + εb)⁻¹ = a⁻¹ − ε a⁻¹ b a⁻¹ (a = the real part of S_i, positive definite with H). About
//! three times the real recursion's products, in place in n×n buffers (on the stack for n ≤ 6).

use nalgebra::allocator::Allocator;
use nalgebra::{DefaultAllocator, Dim, OMatrix};

/// A matrix of dual numbers: `re + ε du` (n × n, dimension type D: stack matrices for small n).
#[derive(Debug, Clone)]
struct Dual<D: Dim>
where
    DefaultAllocator: Allocator<D, D>,
{
    re: OMatrix<f64, D, D>,
    du: OMatrix<f64, D, D>,
}

impl<D: Dim> Dual<D>
where
    DefaultAllocator: Allocator<D, D>,
{
    fn zeros(d: D) -> Self {
        Dual {
            re: OMatrix::zeros_generic(d, d),
            du: OMatrix::zeros_generic(d, d),
        }
    }

    /// Block i of H − εG from their row-major stacks of n×n blocks.
    fn block_of(&mut self, h: &[f64], g: &[f64], i: usize) {
        let n = self.re.nrows();
        let (h, g) = (
            &h[i * n * n..(i + 1) * n * n],
            &g[i * n * n..(i + 1) * n * n],
        );
        for r in 0..n {
            for c in 0..n {
                self.re[(r, c)] = h[r * n + c];
                self.du[(r, c)] = -g[r * n + c];
            }
        }
    }

    /// self ← α a b + β self (a, b dual), in place.
    fn gemm(&mut self, alpha: f64, a: &Self, b: &Self, beta: f64) {
        self.re.gemm(alpha, &a.re, &b.re, beta);
        self.du.gemm(alpha, &a.re, &b.du, beta);
        self.du.gemm(alpha, &a.du, &b.re, 1.0);
    }

    /// self ← aᵀ b (a, b dual), in place.
    fn tr_product(&mut self, a: &Self, b: &Self) {
        self.re.gemm_tr(1.0, &a.re, &b.re, 0.0);
        self.du.gemm_tr(1.0, &a.re, &b.du, 0.0);
        self.du.gemm_tr(1.0, &a.du, &b.re, 1.0);
    }

    /// The inverse, by the Cholesky factor of the real part (`scratch`: an n×n buffer); None if
    /// that is not positive definite.
    fn inverse(&self, scratch: &mut OMatrix<f64, D, D>) -> Option<Self> {
        let re = self.re.clone().cholesky()?.inverse();
        let mut du = re.clone();
        scratch.gemm(1.0, &re, &self.du, 0.0);
        du.gemm(-1.0, scratch, &re, 0.0);
        Some(Dual { re, du })
    }
}

/// The diagonal n×n blocks of H⁻¹GH⁻¹ (row-major, stacked over the nodes) for block-tridiagonal
/// H and G given as their diagonal blocks (`nodes` × n × n) and super-diagonal blocks
/// ((i, i+1) at i·n², (nodes − 1) × n × n), both row-major. None if H is not numerically positive
/// definite or a block is not finite.
pub fn sandwich_diagonal_blocks(
    nodes: usize,
    n: usize,
    h: (&[f64], &[f64]),
    g: (&[f64], &[f64]),
) -> Option<Vec<f64>> {
    let nn = n * n;
    if nodes == 0
        || h.0.len() != nodes * nn
        || g.0.len() != nodes * nn
        || h.1.len() != (nodes - 1) * nn
        || g.1.len() != (nodes - 1) * nn
    {
        return None;
    }
    let out = with_block_dim!(n, d => recursion(d, nodes, h, g))?;
    out.iter().all(|v| v.is_finite()).then_some(out)
}

/// The recursion of the module documentation on n×n blocks of dimension type D.
fn recursion<D: Dim>(
    d: D,
    nodes: usize,
    h: (&[f64], &[f64]),
    g: (&[f64], &[f64]),
) -> Option<Vec<f64>>
where
    DefaultAllocator: Allocator<D, D>,
{
    let nn = d.value() * d.value();
    let mut scratch = OMatrix::zeros_generic(d, d);
    let (mut s, mut b) = (Dual::zeros(d), Dual::zeros(d));
    // Forward: S_i⁻¹ and U_i = A_{i,i+1}ᵀ S_i⁻¹ (U_i also serves the backward pass).
    let mut s_inv: Vec<Dual<D>> = Vec::with_capacity(nodes);
    let mut u: Vec<Dual<D>> = Vec::with_capacity(nodes.saturating_sub(1));
    for i in 0..nodes {
        s.block_of(h.0, g.0, i);
        if i > 0 {
            s.gemm(-1.0, &u[i - 1], &b, 1.0); // b = A_{i−1,i}
        }
        s_inv.push(s.inverse(&mut scratch)?);
        if i + 1 < nodes {
            b.block_of(h.1, g.1, i);
            let mut ui = Dual::zeros(d);
            ui.tr_product(&b, &s_inv[i]);
            u.push(ui);
        }
    }
    // Backward: the diagonal blocks Σ_i = S_i⁻¹ + U_iᵀ Σ_{i+1} U_i of the inverse.
    let mut out = vec![0.0; nodes * nn];
    let mut next = s_inv[nodes - 1].clone();
    write_block(&next.du, &mut out[(nodes - 1) * nn..]);
    let (mut w, mut sigma) = (Dual::zeros(d), Dual::zeros(d));
    for i in (0..nodes - 1).rev() {
        w.gemm(1.0, &next, &u[i], 0.0);
        sigma.tr_product(&u[i], &w);
        sigma.re += &s_inv[i].re;
        sigma.du += &s_inv[i].du;
        write_block(&sigma.du, &mut out[i * nn..]);
        std::mem::swap(&mut next, &mut sigma);
    }
    Some(out)
}

/// The n×n matrix `m` row-major into the first n² entries of `out`.
fn write_block<D: Dim>(m: &OMatrix<f64, D, D>, out: &mut [f64])
where
    DefaultAllocator: Allocator<D, D>,
{
    let n = m.nrows();
    for r in 0..n {
        for c in 0..n {
            out[r * n + c] = m[(r, c)];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solver::test_problem::Lcg;
    use nalgebra::DMatrix;

    /// A random symmetric block-tridiagonal matrix J_wᵀJ_w (blocks and dense) from random rows
    /// that each touch two neighbouring nodes, row k weighted by `weight(k)`.
    fn gram(
        nodes: usize,
        n: usize,
        rows: &[(usize, Vec<f64>)],
        weight: impl Fn(usize) -> f64,
    ) -> (Vec<f64>, Vec<f64>, DMatrix<f64>) {
        let nv = nodes * n;
        let mut dense = DMatrix::<f64>::zeros(nv, nv);
        for (k, (i, v)) in rows.iter().enumerate() {
            let mut row = DMatrix::<f64>::zeros(1, nv);
            for (c, &x) in v.iter().enumerate() {
                row[(0, i * n + c)] = x;
            }
            dense += weight(k) * row.transpose() * row;
        }
        let nn = n * n;
        let mut diag = vec![0.0; nodes * nn];
        let mut off = vec![0.0; (nodes - 1) * nn];
        for i in 0..nodes {
            for a in 0..n {
                for b in 0..n {
                    diag[i * nn + a * n + b] = dense[(i * n + a, i * n + b)];
                    if i + 1 < nodes {
                        off[i * nn + a * n + b] = dense[(i * n + a, (i + 1) * n + b)];
                    }
                }
            }
        }
        (diag, off, dense)
    }

    #[test]
    fn sandwich_blocks_match_the_dense_product() {
        let mut rng = Lcg(7);
        for &(nodes, n) in &[
            (1, 1),
            (1, 3),
            (2, 2),
            (6, 3),
            (16, 2),
            (11, 4),
            (4, 5),
            (5, 6),
            (7, 8),
        ] {
            // Rows over nodes (i, i+1) (the last node's rows touch it alone): dense enough that
            // H is positive definite.
            let mut rows = Vec::new();
            for i in 0..nodes {
                let width = if i + 1 < nodes { 2 * n } else { n };
                for _ in 0..2 * n {
                    rows.push((i, (0..width).map(|_| rng.next()).collect::<Vec<_>>()));
                }
            }
            let w: Vec<f64> = (0..rows.len()).map(|_| 0.6 + 0.4 * rng.next()).collect();
            let (hd, ho, h) = gram(nodes, n, &rows, |_| 1.0);
            let (gd, go, g) = gram(nodes, n, &rows, |k| w[k]);
            let got = sandwich_diagonal_blocks(nodes, n, (&hd, &ho), (&gd, &go)).unwrap();
            let hi = h.clone().cholesky().unwrap().inverse();
            let want = &hi * &g * &hi;
            let scale = want.amax();
            for i in 0..nodes {
                for a in 0..n {
                    for b in 0..n {
                        let d = got[i * n * n + a * n + b] - want[(i * n + a, i * n + b)];
                        assert!(d.abs() <= 1e-10 * scale, "{nodes} {n} {i} {a} {b}: {d}");
                    }
                }
            }
        }
    }

    #[test]
    fn equal_weights_give_the_inverse_and_bad_input_gives_none() {
        let mut rng = Lcg(3);
        let (nodes, n) = (5, 2);
        let rows: Vec<_> = (0..nodes)
            .flat_map(|i| {
                let width = if i + 1 < nodes { 2 * n } else { n };
                (0..3).map(move |_| (i, width)).collect::<Vec<_>>()
            })
            .map(|(i, width)| (i, (0..width).map(|_| rng.next()).collect::<Vec<_>>()))
            .collect();
        let (hd, ho, h) = gram(nodes, n, &rows, |_| 1.0);
        let got = sandwich_diagonal_blocks(nodes, n, (&hd, &ho), (&hd, &ho)).unwrap();
        let hi = h.cholesky().unwrap().inverse();
        for i in 0..nodes {
            for a in 0..n {
                for b in 0..n {
                    let d = got[i * n * n + a * n + b] - hi[(i * n + a, i * n + b)];
                    assert!(d.abs() <= 1e-10 * hi.amax());
                }
            }
        }
        let zero = vec![0.0; hd.len()];
        assert!(sandwich_diagonal_blocks(nodes, n, (&zero, &ho), (&hd, &ho)).is_none());
        assert!(sandwich_diagonal_blocks(nodes, n, (&hd[1..], &ho), (&hd, &ho)).is_none());
        assert!(sandwich_diagonal_blocks(0, n, (&[], &[]), (&[], &[])).is_none());
    }
}
