//! The GPs of a learned model, exact ([`MultiGp`]) or sparse ([`SparseMultiGp`]), behind one
//! prediction interface: [`GpModel`] dispatches the prediction methods both kinds share, so the
//! moving-horizon window ([`crate::mhe::GpStageModel`]), its cache, the estimator bank and the
//! binding's pickling work on either unchanged. [`ModelWorkspace`] holds the scratch memory of
//! both kinds.

use crate::error::Result;
use crate::gp::{GpWorkspace, MultiGp};
use crate::sparse::{SparseMultiGp, SparseWorkspace};

/// q GPs on shared inputs of dimension n_d: exact or sparse.
#[derive(Clone, Debug)]
pub enum GpModel {
    Exact(MultiGp),
    Sparse(SparseMultiGp),
}

/// Reusable scratch memory for [`GpModel`] predictions.
#[derive(Default, Clone, Debug)]
pub struct ModelWorkspace {
    exact: GpWorkspace,
    sparse: SparseWorkspace,
}

impl From<MultiGp> for GpModel {
    fn from(gp: MultiGp) -> Self {
        GpModel::Exact(gp)
    }
}

impl From<SparseMultiGp> for GpModel {
    fn from(gp: SparseMultiGp) -> Self {
        GpModel::Sparse(gp)
    }
}

impl GpModel {
    /// Number of outputs q.
    pub fn n_outputs(&self) -> usize {
        match self {
            GpModel::Exact(g) => g.n_outputs(),
            GpModel::Sparse(g) => g.n_outputs(),
        }
    }

    /// Input dimension n_d.
    pub fn dim(&self) -> usize {
        match self {
            GpModel::Exact(g) => g.dim(),
            GpModel::Sparse(g) => g.dim(),
        }
    }

    /// Typical rounding errors of each output's mean and variance (q values each).
    pub fn rounding_into(&self, mean: &mut [f64], var: &mut [f64]) {
        match self {
            GpModel::Exact(g) => g.rounding_into(mean, var),
            GpModel::Sparse(g) => g.rounding_into(mean, var),
        }
    }

    /// Means, latent variances (k × q) and their gradients (k × q × n_d) at k points `d`.
    pub fn predict_with_gradients_into(
        &self,
        d: &[f64],
        mean: &mut [f64],
        var: &mut [f64],
        dmean: &mut [f64],
        dvar: &mut [f64],
        ws: &mut ModelWorkspace,
    ) -> Result<()> {
        match self {
            GpModel::Exact(g) => {
                g.predict_with_gradients_into(d, mean, var, dmean, dvar, &mut ws.exact)
            }
            GpModel::Sparse(g) => {
                g.predict_with_gradients_into(d, mean, var, dmean, dvar, &mut ws.sparse)
            }
        }
    }

    /// Means and latent variances (k × q each).
    pub fn predict_into(
        &self,
        d: &[f64],
        mean: &mut [f64],
        var: &mut [f64],
        ws: &mut ModelWorkspace,
    ) -> Result<()> {
        match self {
            GpModel::Exact(g) => g.predict_into(d, mean, var, &mut ws.exact),
            GpModel::Sparse(g) => g.predict_into(d, mean, var, &mut ws.sparse),
        }
    }

    /// Means only (k × q).
    pub fn predict_mean_into(
        &self,
        d: &[f64],
        mean: &mut [f64],
        ws: &mut ModelWorkspace,
    ) -> Result<()> {
        match self {
            GpModel::Exact(g) => g.predict_mean_into(d, mean, &mut ws.exact),
            GpModel::Sparse(g) => g.predict_mean_into(d, mean, &mut ws.sparse),
        }
    }
}

/// The prediction methods every kind of GP model shares, for code written once for all of them
/// (the binding's array conversions); [`GpModel`] implements it by dispatch.
pub trait GpPredict: Sync {
    type Workspace: Default;
    fn n_outputs(&self) -> usize;
    fn dim(&self) -> usize;
    /// Means, latent variances (k × q) and their gradients (k × q × n_d) at k points `d`.
    fn predict_with_gradients_into(
        &self,
        d: &[f64],
        mean: &mut [f64],
        var: &mut [f64],
        dmean: &mut [f64],
        dvar: &mut [f64],
        ws: &mut Self::Workspace,
    ) -> Result<()>;
    /// Means and latent variances (k × q each).
    fn predict_into(
        &self,
        d: &[f64],
        mean: &mut [f64],
        var: &mut [f64],
        ws: &mut Self::Workspace,
    ) -> Result<()>;
    /// Means only (k × q).
    fn predict_mean_into(
        &self,
        d: &[f64],
        mean: &mut [f64],
        ws: &mut Self::Workspace,
    ) -> Result<()>;
}

/// Implements [`GpPredict`] by calling the type's own (inherent) methods of the same names.
macro_rules! gp_predict {
    ($t:ty, $ws:ty) => {
        impl GpPredict for $t {
            type Workspace = $ws;
            fn n_outputs(&self) -> usize {
                <$t>::n_outputs(self)
            }
            fn dim(&self) -> usize {
                <$t>::dim(self)
            }
            fn predict_with_gradients_into(
                &self,
                d: &[f64],
                mean: &mut [f64],
                var: &mut [f64],
                dmean: &mut [f64],
                dvar: &mut [f64],
                ws: &mut $ws,
            ) -> Result<()> {
                <$t>::predict_with_gradients_into(self, d, mean, var, dmean, dvar, ws)
            }
            fn predict_into(
                &self,
                d: &[f64],
                mean: &mut [f64],
                var: &mut [f64],
                ws: &mut $ws,
            ) -> Result<()> {
                <$t>::predict_into(self, d, mean, var, ws)
            }
            fn predict_mean_into(&self, d: &[f64], mean: &mut [f64], ws: &mut $ws) -> Result<()> {
                <$t>::predict_mean_into(self, d, mean, ws)
            }
        }
    };
}

gp_predict!(MultiGp, GpWorkspace);
gp_predict!(SparseMultiGp, SparseWorkspace);
gp_predict!(GpModel, ModelWorkspace);
