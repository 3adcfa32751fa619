//! The penalty ρ of the whitened output residuals e of the window problem (the user guide's
//! *Data as plants send it*, robust output penalty): squared (ρ = e²), Huber or Cauchy with a
//! scale k in units of the residual's standard deviation.
//!
//! The window stays a least-squares problem: an output row a·e becomes a·ψ(e) with
//! ψ(e) = sign(e) √ρ(e), so ‖r‖² is the robust cost itself and the Gauss-Newton solver, its line
//! search, statuses and stopping tests apply unchanged; the row's Jacobian is multiplied by ψ′(e).
//! For |e| small against k both losses are e² (ψ ≈ e, ψ′ ≈ 1); beyond k the Huber cost grows
//! linearly, 2k|e| − k², and the Cauchy cost logarithmically, k² log(1 + e²/k²).

use crate::error::{Error, Result};

/// See the module documentation.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum Loss {
    #[default]
    Squared,
    Huber(f64),
    Cauchy(f64),
}

impl Loss {
    /// The loss called `name` ("squared", "huber" or "cauchy") with scale `k` > 0 (ignored for
    /// "squared").
    pub fn from_name(name: &str, k: f64) -> Result<Self> {
        let scaled = |make: fn(f64) -> Loss| {
            if k.is_finite() && k > 0.0 {
                Ok(make(k))
            } else {
                Err(Error::invalid(
                    "loss_scale",
                    format!("must be positive and finite, got {k}"),
                ))
            }
        };
        match name {
            "squared" => Ok(Loss::Squared),
            "huber" => scaled(Loss::Huber),
            "cauchy" => scaled(Loss::Cauchy),
            _ => Err(Error::invalid(
                "loss",
                format!("expected 'squared', 'huber' or 'cauchy', got {name:?}"),
            )),
        }
    }

    /// The name and scale (1 for "squared").
    pub fn name_and_scale(&self) -> (&'static str, f64) {
        match *self {
            Loss::Squared => ("squared", 1.0),
            Loss::Huber(k) => ("huber", k),
            Loss::Cauchy(k) => ("cauchy", k),
        }
    }

    pub fn is_squared(&self) -> bool {
        matches!(self, Loss::Squared)
    }

    /// (ψ(e), ψ′(e)) with ψ(e)² = ρ(e) and sign(ψ) = sign(e).
    pub fn psi(&self, e: f64) -> (f64, f64) {
        match *self {
            Loss::Squared => (e, 1.0),
            Loss::Huber(k) => {
                if e.abs() <= k {
                    (e, 1.0)
                } else {
                    let root = (2.0 * k * e.abs() - k * k).sqrt();
                    (e.signum() * root, k / root)
                }
            }
            Loss::Cauchy(k) => {
                let u = (e / k) * (e / k);
                if u < 1e-8 {
                    // Series of k √log(1 + u): the closed form divides 0 by 0 near e = 0.
                    (e * (1.0 - 0.25 * u), 1.0 - 0.75 * u)
                } else {
                    let root = u.ln_1p().sqrt();
                    (e.signum() * k * root, (e.abs() / k) / ((1.0 + u) * root))
                }
            }
        }
    }

    /// A weighted row r = a·e (weight a ≥ 0) mapped to a·ψ(e); returns (a·ψ(e), ψ′(e)), the
    /// factor of the row's derivatives. A row of weight 0 stays 0, and a row where ψ is the
    /// identity (Huber within k) stays r exactly (not a·(r/a)).
    pub fn row(&self, a: f64, r: f64) -> (f64, f64) {
        if a == 0.0 {
            return (r, 1.0);
        }
        let e = r / a;
        match *self {
            Loss::Squared => (r, 1.0),
            Loss::Huber(k) if e.abs() <= k => (r, 1.0),
            _ => {
                let (psi, slope) = self.psi(e);
                (a * psi, slope)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rho(loss: Loss, e: f64) -> f64 {
        match loss {
            Loss::Squared => e * e,
            Loss::Huber(k) if e.abs() <= k => e * e,
            Loss::Huber(k) => 2.0 * k * e.abs() - k * k,
            Loss::Cauchy(k) => k * k * (e * e / (k * k)).ln_1p(),
        }
    }

    const LOSSES: [Loss; 4] = [
        Loss::Squared,
        Loss::Huber(1.345),
        Loss::Cauchy(2.0),
        Loss::Cauchy(0.3),
    ];

    #[test]
    fn psi_squared_is_the_loss_with_the_residuals_sign() {
        for loss in LOSSES {
            for e in [-50.0f64, -3.0, -1.0, -1e-5, 0.0, 2e-9, 0.7, 1.345, 4.0, 1e3] {
                let (psi, _) = loss.psi(e);
                assert!(
                    (psi * psi - rho(loss, e)).abs() <= 1e-12 * (1.0 + rho(loss, e)),
                    "{loss:?} {e}"
                );
                assert!(psi * e >= 0.0);
            }
        }
    }

    #[test]
    fn slope_matches_central_differences() {
        for loss in LOSSES {
            for e in [-20.0f64, -2.5, -0.4, -3e-5, 0.0, 1e-3, 0.9, 1.3, 1.4, 6.0] {
                let h = 1e-6 * (1.0 + e.abs());
                let fd = (loss.psi(e + h).0 - loss.psi(e - h).0) / (2.0 * h);
                let (_, slope) = loss.psi(e);
                assert!(
                    (fd - slope).abs() < 1e-6,
                    "{loss:?} at {e}: {fd} vs {slope}"
                );
            }
        }
    }

    #[test]
    fn the_series_and_the_closed_form_agree_where_they_meet() {
        // u = e²/k² just above and just below the switch at 1e-8: ψ continues as ψ′ ≈ 1 says.
        let loss = Loss::Cauchy(1.0);
        let (above, below) = (1e-4 * (1.0 + 1e-9), 1e-4 * (1.0 - 1e-9));
        let ((p, s), (q, t)) = (loss.psi(above), loss.psi(below));
        assert!(
            ((p - q) - (above - below)).abs() < 1e-19,
            "{}",
            (p - q) - (above - below)
        );
        assert!((s - t).abs() < 1e-12);
    }

    #[test]
    fn names_and_scales_are_checked() {
        assert_eq!(Loss::from_name("huber", 2.0).unwrap(), Loss::Huber(2.0));
        assert_eq!(Loss::from_name("squared", f64::NAN).unwrap(), Loss::Squared);
        for (name, k) in [("huber", 0.0), ("cauchy", f64::INFINITY), ("cauchy", -1.0)] {
            assert!(Loss::from_name(name, k)
                .unwrap_err()
                .to_string()
                .contains("loss_scale"));
        }
        assert!(Loss::from_name("l1", 1.0)
            .unwrap_err()
            .to_string()
            .contains("loss"));
        assert_eq!(Loss::row(&Loss::Huber(1.0), 0.0, 0.0), (0.0, 1.0));
    }
}
