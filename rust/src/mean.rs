//! The affine prior mean m(d) = b + W d of a GP's outputs (`gpmhe`'s ``mean="linear"`` and
//! ``"constant"``): the GPs regress the residuals y − m(d), and every prediction adds m(d) to the
//! posterior mean and W to its input gradient. The variances are unchanged (the mean is fixed,
//! fitted before the hyperparameters).

use crate::error::{check_finite, check_len, Error, Result};

/// m(d) = b + W d for q outputs on n_d inputs; the coefficients are a row per output,
/// [b_o, w_o1, …, w_o,n_d] (q × (n_d + 1), row-major).
#[derive(Clone, Debug, PartialEq)]
pub struct AffineMean {
    q: usize,
    nd: usize,
    coef: Vec<f64>,
}

impl AffineMean {
    /// Checks that `coef` has q × (n_d + 1) finite values.
    pub fn new(q: usize, nd: usize, coef: Vec<f64>) -> Result<Self> {
        check_len("mean", &coef, q * (nd + 1))?;
        check_finite("mean", &coef)?;
        Ok(Self { q, nd, coef })
    }

    /// The coefficients, q × (n_d + 1) row-major.
    pub fn coefficients(&self) -> &[f64] {
        &self.coef
    }

    pub fn n_outputs(&self) -> usize {
        self.q
    }

    pub fn dim(&self) -> usize {
        self.nd
    }

    /// Adds m(d) to the means (k × q) of the k points `d`.
    pub fn add_values(&self, d: &[f64], mean: &mut [f64]) {
        let w = self.nd + 1;
        for (dj, mj) in d.chunks_exact(self.nd).zip(mean.chunks_exact_mut(self.q)) {
            for (m, row) in mj.iter_mut().zip(self.coef.chunks_exact(w)) {
                *m += row[0] + row[1..].iter().zip(dj).map(|(a, b)| a * b).sum::<f64>();
            }
        }
    }

    /// Adds W to the mean gradients (k × q × n_d) of k points.
    pub fn add_gradients(&self, dmean: &mut [f64]) {
        let w = self.nd + 1;
        for gj in dmean.chunks_exact_mut(self.q * self.nd) {
            for (g, row) in gj.chunks_exact_mut(self.nd).zip(self.coef.chunks_exact(w)) {
                for (gi, wi) in g.iter_mut().zip(&row[1..]) {
                    *gi += wi;
                }
            }
        }
    }

    /// Fails with an error naming `mean` unless these are coefficients for q outputs on n_d
    /// inputs (the model the mean is given to).
    pub fn check_shape(&self, q: usize, nd: usize) -> Result<()> {
        if self.q == q && self.nd == nd {
            return Ok(());
        }
        Err(Error::invalid(
            "mean",
            format!(
                "expected coefficients for {q} outputs on {nd} inputs, got {} on {}",
                self.q, self.nd
            ),
        ))
    }

    /// [`AffineMean::rounding`] of every output on the range of the training inputs `x`
    /// (N × n_d row-major): the model's share of its mean rounding.
    pub fn roundings(&self, x: &[f64]) -> Vec<f64> {
        let mut scale = vec![0.0f64; self.nd];
        for row in x.chunks_exact(self.nd) {
            for (s, v) in scale.iter_mut().zip(row) {
                *s = s.max(v.abs());
            }
        }
        (0..self.q).map(|o| self.rounding(o, &scale)).collect()
    }

    /// A typical absolute rounding error of m(d) for output `o` on inputs of magnitude up to
    /// `scale` (per input): a few ulps of |b| + Σ|w_i| scale_i.
    pub fn rounding(&self, o: usize, scale: &[f64]) -> f64 {
        let row = &self.coef[o * (self.nd + 1)..(o + 1) * (self.nd + 1)];
        let size = row[0].abs()
            + row[1..]
                .iter()
                .zip(scale)
                .map(|(w, s)| (w * s).abs())
                .sum::<f64>();
        4.0 * f64::EPSILON * size
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_and_gradients_match_the_formula() {
        // q = 2, n_d = 2: m_0 = 1 + 2 d0 − d1, m_1 = −3 + 0.5 d1.
        let m = AffineMean::new(2, 2, vec![1.0, 2.0, -1.0, -3.0, 0.0, 0.5]).unwrap();
        let d = [1.0, 2.0, -1.0, 4.0];
        let mut mean = vec![10.0; 4];
        m.add_values(&d, &mut mean);
        assert_eq!(mean, vec![11.0, 8.0, 5.0, 9.0]);
        let mut g = vec![0.0; 2 * 2 * 2];
        m.add_gradients(&mut g);
        assert_eq!(g, vec![2.0, -1.0, 0.0, 0.5, 2.0, -1.0, 0.0, 0.5]);
    }

    #[test]
    fn rejects_wrong_sizes_and_non_finite_values() {
        assert!(AffineMean::new(1, 2, vec![1.0, 2.0]).is_err());
        assert!(AffineMean::new(1, 1, vec![1.0, f64::NAN]).is_err());
    }
}
