//! Choosing inducing inputs from the training inputs: greedy conditional-variance selection.
//!
//! Starting from the empty set, each step adds the training input whose prior variance
//! conditioned on the inputs already chosen is largest (a pivoted Cholesky factorisation of
//! K(X, X), never formed: one kernel column per step). The conditional variance is exactly the
//! diagonal of Kff − Qff, so each step removes the largest term of VFE's trace penalty and of
//! FITC's extra noise (Burt, Rasmussen & van der Wilk 2020 use this selection for VFE). It stops
//! after m points or when no input has a conditional variance above 10⁻⁸ σ_f²: the remaining
//! inputs are then determined by the chosen ones to working precision (clustered or duplicated
//! inputs), and further points would only make K(Z, Z) singular. O(N m²) time, O(N m) memory.

use crate::error::{check_finite, Error, Result};
use crate::gp::kernel_column;

/// Stop when the largest conditional variance is below this fraction of σ_f².
const SELECT_FLOOR: f64 = 1e-8;

/// Indices (in order of selection) of at most `m` of the N training inputs `x` (N × n_d
/// row-major) chosen greedily by conditional variance under the kernel of θ = log([σ_f, φ.., σ_ε])
/// (σ_ε is not used). Fewer than `m` when the floor (module docs) is reached first.
pub fn select_inducing(x: &[f64], theta: &[f64], m: usize) -> Result<Vec<usize>> {
    super::dispatch(
        #[inline(always)]
        || select(x, theta, m),
    )
}

#[inline(always)]
fn select(x: &[f64], theta: &[f64], m: usize) -> Result<Vec<usize>> {
    let (kernel, _) = crate::gp::hyperparameters(theta)?;
    let nd = kernel.dim();
    if x.is_empty() || x.len() % nd != 0 {
        return Err(Error::invalid(
            "x",
            format!("{} values do not form points of dimension {nd}", x.len()),
        ));
    }
    check_finite("x", x)?;
    if m == 0 {
        return Err(Error::invalid("m", "needs at least one inducing point"));
    }
    let n = x.len() / nd;
    let (w, s2) = (kernel.inv_lengthscales_sq(), kernel.variance());
    let mut resid = vec![s2; n];
    let mut rows: Vec<Vec<f64>> = Vec::new();
    let mut chosen = Vec::new();
    while chosen.len() < m.min(n) {
        crate::interrupt::check()?;
        let (p, rp) = resid
            .iter()
            .enumerate()
            .fold((0, f64::NEG_INFINITY), |(bi, bv), (i, &v)| {
                if v > bv {
                    (i, v)
                } else {
                    (bi, bv)
                }
            });
        if rp.is_nan() || rp <= SELECT_FLOOR * s2 {
            break;
        }
        let mut col = vec![0.0; n];
        kernel_column(x, &x[p * nd..(p + 1) * nd], w, s2, &mut col);
        for r in &rows {
            let a = r[p];
            col.iter_mut().zip(r).for_each(|(c, ri)| *c -= a * ri);
        }
        let inv = 1.0 / rp.sqrt();
        for (c, d) in col.iter_mut().zip(resid.iter_mut()) {
            *c *= inv;
            *d -= *c * *c;
        }
        resid[p] = f64::NEG_INFINITY;
        rows.push(col);
        chosen.push(p);
    }
    Ok(chosen)
}
