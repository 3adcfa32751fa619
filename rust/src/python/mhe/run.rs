//! How a `MovingHorizon` method reaches the core with its model (`Model`, `stage_model.rs`):
//! the learned model without the GIL, a compiled model without Python, a callback with it; an
//! interrupt or a Python exception raised inside is re-raised, and the learned model's
//! evaluation cache is left as it was by an error (or by a read, [`PyMovingHorizon::read`]).

use pyo3::prelude::*;

use super::moving_horizon::PyMovingHorizon;
use super::stage_model::{CallbackModel, Model};
use crate::mhe::{MovingHorizon, StageModel};
use crate::python::error::{detach_interruptible, interruptible, model_domain_error};

impl PyMovingHorizon {
    /// Runs `f` on the core with the model: the learned model without the GIL, a callback with
    /// it (a Python exception it raised is re-raised when `f` fails).
    pub(crate) fn run<T: Send>(
        &mut self,
        py: Python<'_>,
        f: impl FnOnce(&mut MovingHorizon, &mut dyn StageModel) -> crate::Result<T> + Send,
    ) -> PyResult<T> {
        let core = &mut self.core;
        match &mut self.model {
            Model::Gp(model) => {
                // An error (an interrupt among them) leaves the evaluation cache as it was: the
                // cache decides which values later updates reuse, bit for bit.
                model.mark();
                let r = detach_interruptible(py, || f(core, &mut **model));
                if r.is_err() {
                    model.rollback();
                }
                r
            }
            // Its state is set by the estimator before every use: nothing to undo.
            Model::Learning(model) => detach_interruptible(py, || f(core, &mut **model)),
            Model::Compiled { model, .. } => {
                let m = &mut **model;
                match py.detach(|| interruptible(|| f(core, &mut *m))) {
                    (Ok(v), _) => Ok(v),
                    (Err(_), Some(raised)) => Err(raised),
                    (Err(e), None) if m.is_domain_error(&e) => Err(model_domain_error(py, e)),
                    (Err(e), None) => Err(e.into()),
                }
            }
            Model::Callback {
                stage_eval,
                predict,
                dims,
            } => {
                let mut cb = CallbackModel {
                    func: stage_eval.bind(py),
                    predict: predict.as_ref().map(|f| f.bind(py)),
                    dims: *dims,
                    err: None,
                };
                // The model's exceptions reach Python anyway (a signal's handler runs inside the
                // callback); the check covers the core's own work between callbacks.
                match interruptible(|| f(core, &mut cb)) {
                    (Ok(v), _) => Ok(v),
                    (Err(_), Some(raised)) => Err(raised),
                    (Err(e), None) => Err(cb.err.take().unwrap_or_else(|| e.into())),
                }
            }
        }
    }

    /// [`run`](Self::run) for a read: the learned model's evaluation cache stays as it was
    /// whatever `f` evaluates (it decides which values later updates reuse, bit for bit).
    pub(crate) fn read<T: Send>(
        &mut self,
        py: Python<'_>,
        f: impl FnOnce(&mut MovingHorizon, &mut dyn StageModel) -> crate::Result<T> + Send,
    ) -> PyResult<T> {
        let saved = match &self.model {
            Model::Gp(gp) => Some(gp.cache()),
            _ => None,
        };
        let out = self.run(py, f);
        if let (Some(saved), Model::Gp(gp)) = (saved, &mut self.model) {
            let _ = gp.set_cache(saved); // the model's own cache always fits it
        }
        out
    }
}
