//! Models compiled from CasADi's generated C code: a shared library with two functions of one
//! point d = [x; u], `<stage>(d) -> (f, ∂f/∂dᵀ, h, ∂h/∂dᵀ)` and `<predict>(d) -> f`, each with
//! CasADi's C interface (`fn(arg, res, iw, w, mem)`, `fn_work`, `fn_sparsity_in/out`, ...).
//!
//! [`CompiledLibrary`] loads and checks the library once (shared between estimators with
//! `Arc`); [`CompiledModel`] is the [`crate::mhe::StageModel`] an estimator runs on: it calls
//! the stage function point by point with work buffers of its own, so estimators on one library
//! run in parallel.

mod function;
mod model;

pub use function::CompiledLibrary;
pub use model::CompiledModel;

#[cfg(test)]
mod tests;
