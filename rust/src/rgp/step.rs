//! What one RGP-dKF step assembles around the filter's kernels ([`RgpEkf::predict`],
//! [`RgpEkf::update`]): the Jacobians A, e and H given at the step or stored once as constants
//! ([`ConstantJacobians`]), the innovation ν = y − h(x⁻) and R_x from a scalar or a matrix. The
//! binding only calls the user's functions and hands their results here.

use super::RgpEkf;
use crate::error::{check_len, Error, Result};

/// Constant Jacobians A (n × n), e (n × q) and H (p × n), row-major, stored once so that a step
/// passes only what changes; None: given at every step.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ConstantJacobians {
    pub a: Option<Vec<f64>>,
    pub e: Option<Vec<f64>>,
    pub h: Option<Vec<f64>>,
}

impl ConstantJacobians {
    /// The Jacobian `name` of a step: the one `given` at the step, else the stored constant.
    fn choose<'a>(
        name: &str,
        given: Option<&'a [f64]>,
        stored: &'a Option<Vec<f64>>,
    ) -> Result<&'a [f64]> {
        given.or(stored.as_deref()).ok_or_else(|| {
            Error::invalid(name, format!("not given and no constant {name} was stored"))
        })
    }
}

impl RgpEkf {
    /// Steps 1–3 after the GP inference ([`RgpEkf::infer`]): the covariance prediction with the
    /// predicted state `x_pred`, A and e (None: the stored constants) and Q_x (n × n). On error
    /// the state is unchanged.
    pub fn predict_step(
        &mut self,
        x_pred: &[f64],
        a: Option<&[f64]>,
        e: Option<&[f64]>,
        q_x: &[f64],
        constants: &ConstantJacobians,
    ) -> Result<()> {
        let a = ConstantJacobians::choose("A", a, &constants.a)?;
        let e = ConstantJacobians::choose("e", e, &constants.e)?;
        self.predict(x_pred, a, e, q_x)
    }

    /// Step 4: the EKF update with the output `y`, the predicted output `hx` = h(x⁻), H (None:
    /// the stored constant) and R_x: p × p values, or (`r_scalar`) one value meaning R_x I.
    /// `nu` and `r_full` are work buffers. Returns the log-likelihood; on error the state is
    /// unchanged.
    #[allow(clippy::too_many_arguments)]
    pub fn update_step(
        &mut self,
        y: &[f64],
        hx: &[f64],
        h: Option<&[f64]>,
        r_x: &[f64],
        r_scalar: bool,
        learning: bool,
        constants: &ConstantJacobians,
        nu: &mut Vec<f64>,
        r_full: &mut Vec<f64>,
    ) -> Result<f64> {
        let p = y.len();
        check_len("h", hx, p)?;
        let h = ConstantJacobians::choose("H", h, &constants.h)?;
        nu.clear();
        nu.extend(y.iter().zip(hx).map(|(yi, hi)| yi - hi));
        let r = if r_scalar {
            check_len("R_x", r_x, 1)?;
            r_full.clear();
            r_full.resize(p * p, 0.0);
            (0..p).for_each(|i| r_full[i * p + i] = r_x[0]);
            &r_full[..]
        } else {
            r_x
        };
        self.update(nu, h, r, learning)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_jacobian_given_at_the_step_wins_over_the_stored_one() {
        let stored = Some(vec![1.0]);
        assert_eq!(
            ConstantJacobians::choose("A", Some(&[2.0]), &stored).unwrap(),
            &[2.0]
        );
        assert_eq!(
            ConstantJacobians::choose("A", None, &stored).unwrap(),
            &[1.0]
        );
        let err = ConstantJacobians::choose("H", None, &None).unwrap_err();
        assert!(err.to_string().starts_with("H: not given"));
    }
}
