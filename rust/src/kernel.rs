//! The squared-exponential ARD kernel of docs/user_guide/notation.rst,
//! k(d, d') = σ_f² exp(−½ (d − d')ᵀ Λ⁻¹ (d − d')), Λ = diag(φ_1², …, φ_nd²),
//! with its derivatives w.r.t. the first argument and w.r.t. the log-hyperparameters.
//!
//! Point sets are row-major slices: `k` points of dimension `nd` are `k * nd` values, point `i`
//! at `[i * nd .. (i + 1) * nd]` (zero-copy from a C-contiguous numpy array). Kernel matrices are
//! faer matrices.

use faer::{Mat, MatMut, MatRef};

use crate::error::{check_finite, Error, Result};

/// Whether 1/φ² is a finite number (φ > 0): below about 1.5e-154 it overflows, and the kernel
/// would be 0 · ∞ at coinciding points.
pub(crate) fn inverse_square_finite(phi: f64) -> bool {
    (1.0 / (phi * phi)).is_finite()
}

/// SE-ARD kernel with signal std `sigma_f` and one length-scale per input dimension.
#[derive(Debug, Clone, PartialEq)]
pub struct SeArd {
    sigma_f: f64,
    lengthscales: Vec<f64>,
    /// 1 / φ_i², the diagonal of Λ⁻¹.
    inv_l2: Vec<f64>,
}

impl SeArd {
    /// Fails with `InvalidInput` unless `sigma_f` and every length-scale are finite and positive.
    pub fn new(sigma_f: f64, lengthscales: &[f64]) -> Result<Self> {
        if !(sigma_f.is_finite() && sigma_f > 0.0) {
            return Err(Error::invalid(
                "sigma_f",
                format!("must be finite and > 0, got {sigma_f}"),
            ));
        }
        if lengthscales.is_empty() {
            return Err(Error::invalid(
                "lengthscales",
                "needs at least one length-scale",
            ));
        }
        if let Some(l) = lengthscales.iter().find(|l| !(l.is_finite() && **l > 0.0)) {
            return Err(Error::invalid(
                "lengthscales",
                format!("must be finite and > 0, got {l}"),
            ));
        }
        if let Some(l) = lengthscales.iter().find(|l| !inverse_square_finite(**l)) {
            return Err(Error::invalid(
                "lengthscales",
                format!("{l:e} is too small: 1/lengthscale^2 overflows (at least about 1.5e-154)"),
            ));
        }
        Ok(Self {
            sigma_f,
            lengthscales: lengthscales.to_vec(),
            inv_l2: lengthscales.iter().map(|l| 1.0 / (l * l)).collect(),
        })
    }

    pub fn sigma_f(&self) -> f64 {
        self.sigma_f
    }

    pub fn lengthscales(&self) -> &[f64] {
        &self.lengthscales
    }

    /// The diagonal of Λ⁻¹, 1 / φ_i².
    pub fn inv_lengthscales_sq(&self) -> &[f64] {
        &self.inv_l2
    }

    /// Input dimension n_d.
    pub fn dim(&self) -> usize {
        self.lengthscales.len()
    }

    /// The prior variance k(d, d) = σ_f².
    pub fn variance(&self) -> f64 {
        self.sigma_f * self.sigma_f
    }

    /// Checks that `points` is a finite row-major set of points of this kernel's dimension and
    /// returns how many points it holds.
    pub fn count_points(&self, arg: &str, points: &[f64]) -> Result<usize> {
        let nd = self.dim();
        if points.len() % nd != 0 {
            return Err(Error::invalid(
                arg,
                format!(
                    "{} values do not form points of dimension {nd}",
                    points.len()
                ),
            ));
        }
        check_finite(arg, points)?;
        Ok(points.len() / nd)
    }

    /// (a − b)ᵀ Λ⁻¹ (a − b) for two points.
    #[inline]
    pub fn scaled_sq_dist(&self, a: &[f64], b: &[f64]) -> f64 {
        a.iter()
            .zip(b)
            .zip(&self.inv_l2)
            .map(|((x, y), w)| (x - y) * (x - y) * w)
            .sum()
    }

    /// k(a, b) for two points.
    #[inline]
    pub fn eval(&self, a: &[f64], b: &[f64]) -> f64 {
        self.variance() * (-0.5 * self.scaled_sq_dist(a, b)).exp()
    }

    /// Writes k(a, b) and ∂k(a, b)/∂a = −k(a, b) Λ⁻¹ (a − b) into `grad` (length n_d); returns k.
    #[inline]
    pub fn eval_grad_a(&self, a: &[f64], b: &[f64], grad: &mut [f64]) -> f64 {
        let k = self.eval(a, b);
        for ((g, (x, y)), w) in grad.iter_mut().zip(a.iter().zip(b)).zip(&self.inv_l2) {
            *g = -k * w * (x - y);
        }
        k
    }

    /// Fills `out[(i, j)] = k(a_i, b_j)`; `out` must be (#a × #b).
    pub fn cross_into(&self, a: &[f64], b: &[f64], mut out: MatMut<'_, f64>) {
        let nd = self.dim();
        debug_assert_eq!(out.nrows() * nd, a.len());
        debug_assert_eq!(out.ncols() * nd, b.len());
        for (j, bj) in b.chunks_exact(nd).enumerate() {
            let mut col = out.as_mut().col_mut(j);
            for (i, ai) in a.chunks_exact(nd).enumerate() {
                col[i] = self.eval(ai, bj);
            }
        }
    }

    /// The cross-kernel matrix k(a_i, b_j), (#a × #b).
    pub fn cross(&self, a: &[f64], b: &[f64]) -> Mat<f64> {
        let nd = self.dim();
        let mut out = Mat::zeros(a.len() / nd, b.len() / nd);
        self.cross_into(a, b, out.as_mut());
        out
    }

    /// The Gram matrix K = k(x_i, x_j) without noise, exactly symmetric.
    pub fn gram(&self, x: &[f64]) -> Mat<f64> {
        let nd = self.dim();
        let n = x.len() / nd;
        let mut k = Mat::zeros(n, n);
        let s2 = self.variance();
        for j in 0..n {
            let xj = &x[j * nd..(j + 1) * nd];
            k[(j, j)] = s2;
            for i in j + 1..n {
                let v = self.eval(&x[i * nd..(i + 1) * nd], xj);
                k[(i, j)] = v;
                k[(j, i)] = v;
            }
        }
        k
    }

    /// ∂K/∂log φ_l for the Gram matrix `k_gram` of the points `x`:
    /// K ∘ ((x_{i,l} − x_{j,l})² / φ_l²). (∂K/∂log σ_f is simply 2K.)
    pub fn gram_grad_log_lengthscale(
        &self,
        x: &[f64],
        k_gram: MatRef<'_, f64>,
        l: usize,
        mut out: MatMut<'_, f64>,
    ) {
        let nd = self.dim();
        let n = k_gram.nrows();
        let w = self.inv_l2[l];
        for j in 0..n {
            let xj = x[j * nd + l];
            for i in 0..n {
                let d = x[i * nd + l] - xj;
                let k = k_gram[(i, j)];
                // k = 0 where d²/φ² is huge: the product's limit is 0 (d² w may overflow).
                out[(i, j)] = if k == 0.0 { 0.0 } else { k * d * d * w };
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kernel() -> SeArd {
        SeArd::new(1.7, &[0.8, 2.5]).unwrap()
    }

    #[test]
    fn eval_matches_formula() {
        let k = kernel();
        let (a, b) = ([0.3, -1.0], [1.1, 0.4]);
        let r2 = (0.8f64 / 0.8).powi(2) + (1.4f64 / 2.5).powi(2);
        assert!((k.eval(&a, &b) - 1.7f64.powi(2) * (-0.5 * r2).exp()).abs() < 1e-14);
        assert_eq!(k.eval(&a, &a), k.variance());
    }

    #[test]
    fn tiny_lengthscales_are_refused_and_far_points_have_zero_derivatives() {
        assert!(SeArd::new(1.0, &[1e-160]).is_err());
        let k = SeArd::new(1.0, &[1e-150]).unwrap();
        // coinciding points: σ_f², not 0 · ∞
        assert_eq!(k.eval(&[0.3], &[0.3]), 1.0);
        // far apart: k = 0, and its log-length-scale derivative 0 (d² w overflows)
        let x = [0.0, 1e10];
        let gram = k.gram(&x);
        let mut g = Mat::zeros(2, 2);
        k.gram_grad_log_lengthscale(&x, gram.as_ref(), 0, g.as_mut());
        assert_eq!((gram[(0, 1)], g[(0, 1)], g[(0, 0)]), (0.0, 0.0, 0.0));
    }

    #[test]
    fn input_gradient_matches_finite_differences() {
        let k = kernel();
        let (a, b) = ([0.3, -1.0], [1.1, 0.4]);
        let mut g = [0.0; 2];
        k.eval_grad_a(&a, &b, &mut g);
        for l in 0..2 {
            let h: f64 = 1e-6;
            let (mut ap, mut am) = (a, a);
            ap[l] += h;
            am[l] -= h;
            let fd = (k.eval(&ap, &b) - k.eval(&am, &b)) / (2.0 * h);
            assert!((fd - g[l]).abs() < 1e-8, "dim {l}: {fd} vs {}", g[l]);
        }
    }

    #[test]
    fn lengthscale_gradient_matches_finite_differences() {
        let x = [0.0, 0.0, 0.5, 1.0, -0.7, 2.0];
        let k = kernel();
        let gram = k.gram(&x);
        let mut g = Mat::zeros(3, 3);
        k.gram_grad_log_lengthscale(&x, gram.as_ref(), 1, g.as_mut());
        let h: f64 = 1e-6;
        let kp = SeArd::new(1.7, &[0.8, 2.5 * h.exp()]).unwrap().gram(&x);
        let km = SeArd::new(1.7, &[0.8, 2.5 * (-h).exp()]).unwrap().gram(&x);
        for i in 0..3 {
            for j in 0..3 {
                let fd = (kp[(i, j)] - km[(i, j)]) / (2.0 * h);
                assert!((fd - g[(i, j)]).abs() < 1e-8);
            }
        }
    }

    #[test]
    fn rejects_bad_hyperparameters() {
        assert!(matches!(
            SeArd::new(0.0, &[1.0]),
            Err(Error::InvalidInput { .. })
        ));
        assert!(matches!(
            SeArd::new(1.0, &[1.0, f64::NAN]),
            Err(Error::InvalidInput { .. })
        ));
        assert!(matches!(
            SeArd::new(1.0, &[]),
            Err(Error::InvalidInput { .. })
        ));
        let k = kernel();
        assert!(k.count_points("D", &[1.0, 2.0, 3.0]).is_err());
        assert!(k.count_points("D", &[1.0, f64::INFINITY]).is_err());
        assert_eq!(k.count_points("D", &[1.0, 2.0, 3.0, 4.0]).unwrap(), 2);
    }
}
