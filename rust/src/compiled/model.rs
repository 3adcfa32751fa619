//! [`CompiledModel`]: a compiled CasADi model as the estimator's stage model. Known models have
//! no variances (zero), and every value is checked as a Python model's output is: NaN, ±inf or a
//! magnitude beyond `MAX_ABS` rejects the point (a numerical failure, see `mhe::stage`).

use std::sync::Arc;

use super::function::{Function, Work};
use super::CompiledLibrary;
use crate::error::{Error, Result};
use crate::mhe::stage::find_point;
use crate::mhe::{StageEval, StageModel};

/// The largest magnitude a model value may have (gpmhe._validation.MAX_ABS): beyond it squares
/// overflow.
const MAX_ABS: f64 = 1e150;

/// The stage model of one estimator on a shared [`CompiledLibrary`], with work buffers of its
/// own. `domain_error` keeps the message of the last value the model returned out of range (a
/// `ModelDomainError` for Python), to tell it from a failure its generated code reported.
///
/// The points and values of the last evaluation are kept: a point given again with the same
/// bits is copied, not recomputed (a window's first evaluation after it slid repeats all but its
/// newest point). Each point's values depend on that point alone, so copies equal recomputation.
#[derive(Debug, Clone)]
pub struct CompiledModel {
    lib: Arc<CompiledLibrary>,
    work: Work,
    domain_error: Option<String>,
    last_d: Vec<f64>,
    last: StageEval,
    /// The point [x; u] of `predict_state`.
    point: Vec<f64>,
}

impl CompiledModel {
    pub fn new(lib: Arc<CompiledLibrary>) -> Self {
        let mut work = Work::default();
        work.fit(&lib.stage);
        work.fit(&lib.predict);
        Self {
            lib,
            work,
            domain_error: None,
            last_d: Vec::new(),
            last: StageEval::default(),
            point: Vec::new(),
        }
    }

    pub fn library(&self) -> &Arc<CompiledLibrary> {
        &self.lib
    }

    /// Whether `err` is the last value out of range this model reported (rather than a failed
    /// evaluation or an error of the solver's own).
    pub fn is_domain_error(&self, err: &Error) -> bool {
        matches!((err, &self.domain_error), (Error::Numerical(a), Some(b)) if a == b)
    }

    /// `f` at `d` into `res` with the work buffers `work` (a function, not a method, so that
    /// the library is borrowed, not shared by reference count, by estimators on other threads).
    fn run(f: &Function, d: &[f64], res: &mut [&mut [f64]], work: &mut Work) -> Result<()> {
        if !f.call(d, res, work) {
            return Err(Error::numerical(format!(
                "{}: the compiled CasADi model's evaluation failed at this point (an implicit \
                 integration step whose Newton iteration did not converge: try more substeps \
                 or a larger newton_max_iter)",
                f.name()
            )));
        }
        Ok(())
    }

    /// Index of a point of the last evaluation with the bits of `di` (see
    /// [`find_point`]: bits, so that −0 and 0, which a model may tell apart, are two points).
    fn find_last(&self, di: &[f64], hint: usize) -> Option<usize> {
        let bits = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits());
        find_point(&self.last_d, di, hint, bits)
    }

    fn check(&mut self, part: &str, values: &[f64]) -> Result<()> {
        if values.iter().all(|v| v.abs() <= MAX_ABS) {
            return Ok(());
        }
        let msg =
            format!("{part}: returned NaN or inf or a value of magnitude > 1e+150 (CasADi model)");
        self.domain_error = Some(msg.clone());
        Err(Error::numerical(msg))
    }
}

impl StageModel for CompiledModel {
    fn dim_x(&self) -> usize {
        self.lib.dims.0
    }
    fn dim_u(&self) -> usize {
        self.lib.dims.1
    }
    fn dim_y(&self) -> usize {
        self.lib.dims.2
    }

    fn evaluate(&mut self, d: &[f64], out: &mut StageEval) -> Result<()> {
        let (n, m, p) = self.lib.dims;
        let nd = n + m;
        if nd == 0 || d.len() % nd != 0 {
            return Err(Error::invalid("d", format!("expected rows of {nd} values")));
        }
        let k = d.len() / nd;
        out.resize(k, n, m, p);
        for v in [
            &mut out.var_x,
            &mut out.dvar_x,
            &mut out.var_y,
            &mut out.dvar_y,
        ] {
            v.fill(0.0);
        }
        for (i, di) in d.chunks_exact(nd).enumerate() {
            if let Some(j) = self.find_last(di, i + 1) {
                out.copy_means_of_point(i, &self.last, j, (n, p, nd));
                continue;
            }
            let mut res: [&mut [f64]; 4] = [
                &mut out.mean_x[i * n..(i + 1) * n],
                &mut out.dmean_x[i * n * nd..(i + 1) * n * nd],
                &mut out.mean_y[i * p..(i + 1) * p],
                &mut out.dmean_y[i * p * nd..(i + 1) * p * nd],
            ];
            Self::run(&self.lib.stage, di, &mut res, &mut self.work)?;
        }
        for (part, values) in [("f", &out.mean_x), ("f_jacobian", &out.dmean_x)] {
            self.check(part, values)?;
        }
        for (part, values) in [("h", &out.mean_y), ("h_jacobian", &out.dmean_y)] {
            self.check(part, values)?;
        }
        self.last_d.clear();
        self.last_d.extend_from_slice(d);
        self.last.copy_means_from(out); // (the variances are zero)
        Ok(())
    }

    fn predict_state(&mut self, x: &[f64], u: &[f64], out: &mut [f64]) -> Result<()> {
        let (n, m, _) = self.lib.dims;
        if x.len() != n || u.len() != m || out.len() != n {
            return Err(Error::invalid(
                "x",
                format!("expected {n} states and {m} inputs"),
            ));
        }
        self.point.clear();
        self.point.extend_from_slice(x);
        self.point.extend_from_slice(u);
        Self::run(&self.lib.predict, &self.point, &mut [out], &mut self.work)?;
        self.check("f", out)
    }
}

/// Stateless for an update's undo: its cache holds values that equal recomputation.
impl crate::mhe::bank::ModelState for CompiledModel {
    fn mark(&mut self) {}
    fn rollback(&mut self) {}
}
