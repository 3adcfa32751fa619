//! The posterior of a sparse GP's inducing outputs u = f(Z), N(μ_u, Σ_u), from the stored
//! factors: with L = chol(Kuu + δI), B = I + L⁻¹ Kuf Λ⁻¹ Kfu L⁻ᵀ = L_B L_Bᵀ (so P = L B Lᵀ) and
//! t = P⁻¹ Kuf Λ⁻¹ y, μ_u = (Kuu + δI) t = L Lᵀ t and Σ_u = (Kuu + δI) P⁻¹ (Kuu + δI) = L B⁻¹ Lᵀ
//! = Mᵀ M with M = L_B⁻¹ Lᵀ. The mean at d is then k(d, Z) (Kuu + δI)⁻¹ μ_u = k*ᵀ t and the
//! latent variance σ_f² − J (Kuu + δI) Jᵀ + J Σ_u Jᵀ (J = k*ᵀ (Kuu + δI)⁻¹), the sparse GP's own:
//! the weights of the equivalent recursive GP (`crate::rgp::Rgp::from_sparse`).

use faer::linalg::triangular_solve::solve_lower_triangular_in_place;
use faer::{Mat, MatRef, Par};

use super::SparseGp;

impl SparseGp {
    /// (μ_u, Σ_u) of the module docs: the mean (m) and the exactly symmetric covariance (m × m)
    /// of the inducing outputs.
    pub fn inducing_posterior(&self) -> (Vec<f64>, Mat<f64>) {
        let m = self.n_inducing();
        let t = MatRef::from_column_major_slice(&self.t, m, 1);
        let mu = &self.l * (self.l.transpose() * t);
        let mut mt = self.l.transpose().to_owned();
        solve_lower_triangular_in_place(self.lb.as_ref(), mt.as_mut(), Par::Seq);
        let s = mt.transpose() * &mt;
        let sigma = Mat::from_fn(m, m, |i, j| 0.5 * (s[(i, j)] + s[(j, i)]));
        ((0..m).map(|i| mu[(i, 0)]).collect(), sigma)
    }
}
