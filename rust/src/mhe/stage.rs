//! The model side of the window: [`StageEval`] (means, variances and their input gradients at a
//! batch of points d = [x; u]), the [`StageModel`] trait every model implements, and the learned
//! model [`GpStageModel`] (the GPs of f and h, with a cache of the last window's points).

// Index loops over row-major blocks read better than iterator chains here.
#![allow(clippy::needless_range_loop)]

use crate::error::{check_len, Error, Result};
use std::sync::Arc;

use crate::gp_model::{GpModel, ModelWorkspace};

/// Means, variances and their input gradients of a stage model at k points d = [x; u].
/// All row-major: `mean_x` k×n, `var_x` k×n, `dmean_x` and `dvar_x` k×n×nd, `mean_y` k×p,
/// `var_y` k×p, `dmean_y` and `dvar_y` k×p×nd, with nd = n + m.
#[derive(Debug, Default)]
pub struct StageEval {
    pub mean_x: Vec<f64>,
    pub var_x: Vec<f64>,
    pub dmean_x: Vec<f64>,
    pub dvar_x: Vec<f64>,
    pub mean_y: Vec<f64>,
    pub var_y: Vec<f64>,
    pub dmean_y: Vec<f64>,
    pub dvar_y: Vec<f64>,
    /// Typical absolute rounding errors of each output's mean and variance (n and p values,
    /// the same at every point; zero for a model computed to full precision): how much of a
    /// change in the window cost is noise (see `WindowEval::cost_noise`).
    pub mean_x_rounding: Vec<f64>,
    pub var_x_rounding: Vec<f64>,
    pub mean_y_rounding: Vec<f64>,
    pub var_y_rounding: Vec<f64>,
    /// For a model with n_g global variables g ([`StageModel::n_globals`]): ∂mean_x/∂g (k×n×n_g)
    /// and ∂mean_y/∂g (k×p×n_g), row-major; empty otherwise. The variances do not depend on g.
    pub dmean_x_dg: Vec<f64>,
    pub dmean_y_dg: Vec<f64>,
}

/// `clone_from` reuses the buffers (a model that keeps its last evaluation copies one per window
/// evaluation; the derived one would allocate all fourteen).
impl Clone for StageEval {
    fn clone(&self) -> Self {
        let mut out = Self::default();
        out.clone_from(self);
        out
    }

    fn clone_from(&mut self, o: &Self) {
        self.mean_x.clone_from(&o.mean_x);
        self.var_x.clone_from(&o.var_x);
        self.dmean_x.clone_from(&o.dmean_x);
        self.dvar_x.clone_from(&o.dvar_x);
        self.mean_y.clone_from(&o.mean_y);
        self.var_y.clone_from(&o.var_y);
        self.dmean_y.clone_from(&o.dmean_y);
        self.dvar_y.clone_from(&o.dvar_y);
        self.mean_x_rounding.clone_from(&o.mean_x_rounding);
        self.var_x_rounding.clone_from(&o.var_x_rounding);
        self.mean_y_rounding.clone_from(&o.mean_y_rounding);
        self.var_y_rounding.clone_from(&o.var_y_rounding);
        self.dmean_x_dg.clone_from(&o.dmean_x_dg);
        self.dmean_y_dg.clone_from(&o.dmean_y_dg);
    }
}

/// Row `j` (of width `w`) of `dst` ← row `i` of `src`.
fn copy_row(dst: &mut [f64], src: &[f64], j: usize, i: usize, w: usize) {
    dst[j * w..(j + 1) * w].copy_from_slice(&src[i * w..(i + 1) * w]);
}

impl StageEval {
    /// Sizes every buffer for k points (reuses capacity; contents unspecified).
    pub fn resize(&mut self, k: usize, n: usize, m: usize, p: usize) {
        let nd = n + m;
        self.mean_x.resize(k * n, 0.0);
        self.var_x.resize(k * n, 0.0);
        self.dmean_x.resize(k * n * nd, 0.0);
        self.dvar_x.resize(k * n * nd, 0.0);
        self.mean_y.resize(k * p, 0.0);
        self.var_y.resize(k * p, 0.0);
        self.dmean_y.resize(k * p * nd, 0.0);
        self.dvar_y.resize(k * p * nd, 0.0);
        // Full precision unless the model says otherwise.
        for (v, len) in [
            (&mut self.mean_x_rounding, n),
            (&mut self.var_x_rounding, n),
            (&mut self.mean_y_rounding, p),
            (&mut self.var_y_rounding, p),
        ] {
            v.clear();
            v.resize(len, 0.0);
        }
    }
}

impl StageEval {
    /// Sizes the Jacobians with respect to n_g global variables for k points (zero-filled).
    pub fn resize_globals(&mut self, k: usize, n: usize, p: usize, ng: usize) {
        for (v, len) in [
            (&mut self.dmean_x_dg, k * n * ng),
            (&mut self.dmean_y_dg, k * p * ng),
        ] {
            v.clear();
            v.resize(len, 0.0);
        }
    }

    /// The means and their gradients of `src` (all its points), for a model whose variances are
    /// zero: what [`copy_means_of_point`](Self::copy_means_of_point) reads back.
    pub(crate) fn copy_means_from(&mut self, src: &StageEval) {
        self.mean_x.clone_from(&src.mean_x);
        self.dmean_x.clone_from(&src.dmean_x);
        self.mean_y.clone_from(&src.mean_y);
        self.dmean_y.clone_from(&src.dmean_y);
    }

    /// Copies the means and their gradients of point `i` of `src` into point `j` of `self` (both
    /// sized for dimensions n, p, nd); the variances are left as they are.
    pub(crate) fn copy_means_of_point(
        &mut self,
        j: usize,
        src: &StageEval,
        i: usize,
        (n, p, nd): (usize, usize, usize),
    ) {
        copy_row(&mut self.mean_x, &src.mean_x, j, i, n);
        copy_row(&mut self.dmean_x, &src.dmean_x, j, i, n * nd);
        copy_row(&mut self.mean_y, &src.mean_y, j, i, p);
        copy_row(&mut self.dmean_y, &src.dmean_y, j, i, p * nd);
    }

    /// Copies point `i` of `src` into point `j` of `self` (both sized for dimensions n, p, nd).
    pub(crate) fn copy_point(
        &mut self,
        j: usize,
        src: &StageEval,
        i: usize,
        n: usize,
        p: usize,
        nd: usize,
    ) {
        self.copy_means_of_point(j, src, i, (n, p, nd));
        copy_row(&mut self.var_x, &src.var_x, j, i, n);
        copy_row(&mut self.dvar_x, &src.dvar_x, j, i, n * nd);
        copy_row(&mut self.var_y, &src.var_y, j, i, p);
        copy_row(&mut self.dvar_y, &src.dvar_y, j, i, p * nd);
    }

    /// Fails unless the Jacobians with respect to n_g global variables have the size for k
    /// points.
    pub(super) fn check_global_sizes(&self, k: usize, n: usize, p: usize, ng: usize) -> Result<()> {
        if self.dmean_x_dg.len() == k * n * ng && self.dmean_y_dg.len() == k * p * ng {
            Ok(())
        } else {
            Err(Error::invalid(
                "model",
                "returned global Jacobians of the wrong size",
            ))
        }
    }

    /// Fails unless every buffer has the size for k points (guards against a model that
    /// resized them wrongly).
    pub(super) fn check_sizes(&self, k: usize, n: usize, m: usize, p: usize) -> Result<()> {
        let nd = n + m;
        let ok = self.mean_x.len() == k * n
            && self.var_x.len() == k * n
            && self.dmean_x.len() == k * n * nd
            && self.dvar_x.len() == k * n * nd
            && self.mean_y.len() == k * p
            && self.var_y.len() == k * p
            && self.dmean_y.len() == k * p * nd
            && self.dvar_y.len() == k * p * nd
            && self.mean_x_rounding.len() == n
            && self.var_x_rounding.len() == n
            && self.mean_y_rounding.len() == p
            && self.var_y_rounding.len() == p;
        if ok {
            Ok(())
        } else {
            Err(Error::invalid("model", "returned arrays of the wrong size"))
        }
    }
}

/// Index of the point of `points` (rows of `dj.len()` values) that is `same` as `dj`, trying
/// `hint` first: a window that slid by one finds its point j at j + 1 of the last evaluation.
/// The models' caches of their last evaluation look points up with it.
pub(crate) fn find_point(
    points: &[f64],
    dj: &[f64],
    hint: usize,
    same: impl Fn(&[f64], &[f64]) -> bool,
) -> Option<usize> {
    let nd = dj.len();
    let k = points.len() / nd;
    let at = |i: usize| same(&points[i * nd..(i + 1) * nd], dj);
    if hint < k && at(hint) {
        return Some(hint);
    }
    (0..k).find(|&i| at(i))
}

/// A model x(t+1) = f(x, u) + w, y = h(x, u) + v with input-dependent variances (zero for a
/// known model), evaluated for a batch of points at once.
pub trait StageModel {
    fn dim_x(&self) -> usize;
    fn dim_u(&self) -> usize;
    fn dim_y(&self) -> usize;
    /// Evaluate at k points d (k×(n+m) row-major) into `out` (resized as needed, reused).
    fn evaluate(&mut self, d: &[f64], out: &mut StageEval) -> Result<()>;

    /// Number of global variables g: quantities the means depend on at every point (such as a
    /// sparse GP's inducing outputs), estimated with the window's states. 0 by default.
    fn n_globals(&self) -> usize {
        0
    }

    /// Sets g (n_globals values) for the evaluations that follow; with g, `evaluate` also
    /// sizes and writes ∂mean/∂g (`StageEval::dmean_x_dg`, `dmean_y_dg`, e.g. with
    /// `StageEval::resize_globals`). Fails on a wrong length.
    fn set_globals(&mut self, g: &[f64]) -> Result<()> {
        check_len("globals", g, self.n_globals())
    }

    /// The one-step prediction m_x(x, u) into `out` (n): by default the means of one
    /// evaluation at d = [x; u]. The warm start and the filtering form's arrival prior use it.
    fn predict_state(&mut self, x: &[f64], u: &[f64], out: &mut [f64]) -> Result<()> {
        let mut d = x.to_vec();
        d.extend_from_slice(u);
        let mut ev = StageEval::default();
        self.evaluate(&d, &mut ev)?;
        check_len("model", &ev.mean_x, out.len())?;
        out.copy_from_slice(&ev.mean_x);
        Ok(())
    }
}

/// The learned model of GP-MHE: n independent GPs for f (regression targets x(t+1), or the
/// increment x(t+1) − x(t) when `f_residual`, i.e. prior mean x) and p GPs for h, all on the
/// inputs d = [x; u]. The variances are the GPs' latent variances (docs/user_guide/gaussian_processes.rst).
///
/// The values at the points of the last evaluation are kept: a point given again with exactly
/// the same coordinates is copied instead of recomputed. A moving-horizon window starts from the
/// previous solution shifted by one step, so its first evaluation recomputes only the new point.
///
/// The GPs (exact or sparse, [`GpModel`]) are immutable and shared (`Arc`): a clone copies only
/// the workspace and the cache, so copying an estimator (`copy.deepcopy`, filterpy's `Saver`)
/// does not copy the training data.
#[derive(Debug, Clone)]
pub struct GpStageModel {
    f: Arc<GpModel>,
    h: Option<Arc<GpModel>>,
    f_residual: bool,
    n: usize,
    m: usize,
    ws: ModelWorkspace,
    /// Points (k × nd) and values of the last evaluation.
    last_d: Vec<f64>,
    last: StageEval,
    /// The cache as it was at [`GpStageModel::mark`], kept for [`GpStageModel::rollback`].
    undo: Undo,
    /// Scratch: the points not found in `last`, their values, and where each point comes from
    /// (`Ok(i)`: point i of `last`; `Err(i)`: point i of `fresh`).
    miss_d: Vec<f64>,
    fresh: StageEval,
    source: Vec<std::result::Result<usize, usize>>,
}

impl GpStageModel {
    /// `f` has n outputs on inputs of dimension n + `dim_u`; `h` (None when p = 0) has p outputs
    /// on the same inputs.
    pub fn new<G: Into<GpModel>>(
        f: G,
        h: Option<G>,
        dim_u: usize,
        f_residual: bool,
    ) -> Result<Self> {
        let (f, h): (GpModel, Option<GpModel>) = (f.into(), h.map(Into::into));
        let n = f.n_outputs();
        if f.dim() != n + dim_u {
            return Err(Error::invalid(
                "f",
                format!(
                    "GP input dimension {} is not dim_x + dim_u = {}",
                    f.dim(),
                    n + dim_u
                ),
            ));
        }
        if let Some(h) = &h {
            if h.dim() != n + dim_u {
                return Err(Error::invalid(
                    "h",
                    format!(
                        "GP input dimension {} is not dim_x + dim_u = {}",
                        h.dim(),
                        n + dim_u
                    ),
                ));
            }
        }
        Ok(Self {
            f: Arc::new(f),
            h: h.map(Arc::new),
            f_residual,
            n,
            m: dim_u,
            ws: ModelWorkspace::default(),
            last_d: Vec::new(),
            last: StageEval::default(),
            undo: Undo::Off,
            miss_d: Vec::new(),
            fresh: StageEval::default(),
            source: Vec::new(),
        })
    }

    /// Forgets the last evaluation: the next evaluates every point afresh.
    pub fn clear_cache(&mut self) {
        self.last_d.clear();
        self.last = StageEval::default();
        self.undo = Undo::Off;
    }

    /// Remembers the cache as it is now, for [`GpStageModel::rollback`]: the first evaluation
    /// after the mark moves it aside instead of overwriting it (no copy is made).
    pub fn mark(&mut self) {
        self.undo = Undo::Marked;
    }

    /// Puts back the cache [`GpStageModel::mark`] remembered (an update that failed must not
    /// change which values later updates reuse: see [`GpStageModel::cache`]).
    pub fn rollback(&mut self) {
        if let Undo::Saved(d, eval) = std::mem::replace(&mut self.undo, Undo::Off) {
            self.last_d = d;
            self.last = *eval;
        }
    }

    /// The one-step prediction m_x(x, u) (the f-GPs' means, plus x with `f_residual`) into
    /// `out` (n). Does not touch the cache of the last evaluation.
    pub fn predict_mean(&mut self, x: &[f64], u: &[f64], out: &mut [f64]) -> Result<()> {
        check_len("x", x, self.n)?;
        check_len("u", u, self.m)?;
        check_len("out", out, self.n)?;
        self.miss_d.clear();
        self.miss_d.extend_from_slice(x);
        self.miss_d.extend_from_slice(u);
        self.f.predict_mean_into(&self.miss_d, out, &mut self.ws)?;
        if self.f_residual {
            for (o, xi) in out.iter_mut().zip(x) {
                *o += xi;
            }
        }
        Ok(())
    }

    /// Index of a point of the last evaluation equal to `dj` (see [`find_point`]).
    fn find_last(&self, dj: &[f64], hint: usize) -> Option<usize> {
        find_point(&self.last_d, dj, hint, |a, b| a == b)
    }

    /// GP values at the k points `d` into `out` (already sized for k points).
    fn predict(&mut self, d: &[f64], out: &mut StageEval) -> Result<()> {
        let (n, nd) = (self.n, self.n + self.m);
        self.f.predict_with_gradients_into(
            d,
            &mut out.mean_x,
            &mut out.var_x,
            &mut out.dmean_x,
            &mut out.dvar_x,
            &mut self.ws,
        )?;
        if self.f_residual {
            add_state(d, n, nd, out);
        }
        if let Some(h) = &self.h {
            predict_outputs(h, d, out, &mut self.ws)?;
        }
        Ok(())
    }

    pub fn f_residual(&self) -> bool {
        self.f_residual
    }

    /// The GPs of f and h (shared, see the struct's doc).
    pub fn gps(&self) -> (&Arc<GpModel>, Option<&Arc<GpModel>>) {
        (&self.f, self.h.as_ref())
    }
}

/// Adds each point's x to the means of f and the identity to their gradients (f's GPs model
/// x(t+1) − x(t)): the points `d` of n_d = n + m values.
pub(crate) fn add_state(d: &[f64], n: usize, nd: usize, out: &mut StageEval) {
    for i in 0..d.len() / nd {
        for c in 0..n {
            out.mean_x[i * n + c] += d[i * nd + c];
            out.dmean_x[(i * n + c) * nd + c] += 1.0;
        }
    }
}

/// The h-GPs' values and gradients at the points `d` into the output part of `out`.
pub(crate) fn predict_outputs(
    h: &GpModel,
    d: &[f64],
    out: &mut StageEval,
    ws: &mut ModelWorkspace,
) -> Result<()> {
    h.predict_with_gradients_into(
        d,
        &mut out.mean_y,
        &mut out.var_y,
        &mut out.dmean_y,
        &mut out.dvar_y,
        ws,
    )
}

/// The number of points of n_d values in `d`; an error naming `d` if it is not whole.
pub(crate) fn count_points(d: &[f64], nd: usize) -> Result<usize> {
    if d.len() % nd != 0 {
        return Err(Error::invalid(
            "d",
            format!(
                "length {} is not a multiple of dim_x + dim_u = {nd}",
                d.len()
            ),
        ));
    }
    Ok(d.len() / nd)
}

/// What [`GpStageModel::rollback`] puts back: nothing (`Off`), the cache as it is (`Marked`,
/// no evaluation since the mark) or the cache at the mark, moved aside by an evaluation.
#[derive(Debug, Clone)]
enum Undo {
    Off,
    Marked,
    Saved(Vec<f64>, Box<StageEval>),
}

/// Names of the cache's parts, in the order of [`GpStageModel::cache`].
pub const GP_CACHE_PARTS: [&str; 9] = [
    "d", "mean_x", "var_x", "dmean_x", "dvar_x", "mean_y", "var_y", "dmean_y", "dvar_y",
];

impl GpStageModel {
    /// The cache of the last evaluation: its points d (k × nd) and the values there (the fields
    /// of [`StageEval`] in the order of [`GP_CACHE_PARTS`]). A point found in the cache is
    /// copied, not recomputed, and a batch's values depend (in the last bits) on the batch: an
    /// estimator restored with its cache continues bit-identically, one without would not.
    pub fn cache(&self) -> [Vec<f64>; 9] {
        let l = &self.last;
        [
            self.last_d.clone(),
            l.mean_x.clone(),
            l.var_x.clone(),
            l.dmean_x.clone(),
            l.dvar_x.clone(),
            l.mean_y.clone(),
            l.var_y.clone(),
            l.dmean_y.clone(),
            l.dvar_y.clone(),
        ]
    }

    /// Sets the cache from [`GpStageModel::cache`]'s parts; lengths and finiteness are checked
    /// (an error names the part) and nothing changes on error.
    pub fn set_cache(&mut self, parts: [Vec<f64>; 9]) -> Result<()> {
        let (n, m, p) = (self.n, self.m, self.dim_y());
        let nd = n + m;
        let k = parts[0].len() / nd;
        let widths = [nd, n, n, n * nd, n * nd, p, p, p * nd, p * nd];
        for ((part, name), w) in parts.iter().zip(GP_CACHE_PARTS).zip(widths) {
            check_len(name, part, k * w)?;
            crate::error::check_finite(name, part)?;
        }
        let [d, mean_x, var_x, dmean_x, dvar_x, mean_y, var_y, dmean_y, dvar_y] = parts;
        self.undo = Undo::Off;
        self.last_d = d;
        self.last = StageEval {
            mean_x,
            var_x,
            dmean_x,
            dvar_x,
            mean_y,
            var_y,
            dmean_y,
            dvar_y,
            ..StageEval::default()
        };
        Ok(())
    }
}

impl StageModel for GpStageModel {
    fn dim_x(&self) -> usize {
        self.n
    }
    fn dim_u(&self) -> usize {
        self.m
    }
    fn dim_y(&self) -> usize {
        self.h.as_ref().map_or(0, |h| h.n_outputs())
    }
    fn predict_state(&mut self, x: &[f64], u: &[f64], out: &mut [f64]) -> Result<()> {
        self.predict_mean(x, u, out)
    }

    fn evaluate(&mut self, d: &[f64], out: &mut StageEval) -> Result<()> {
        let (n, m, p) = (self.n, self.m, self.dim_y());
        let nd = n + m;
        let k = count_points(d, nd)?;
        out.resize(k, n, m, p);
        self.f
            .rounding_into(&mut out.mean_x_rounding, &mut out.var_x_rounding);
        if let Some(h) = &self.h {
            h.rounding_into(&mut out.mean_y_rounding, &mut out.var_y_rounding);
        }
        self.source.clear();
        self.miss_d.clear();
        for (j, dj) in d.chunks_exact(nd).enumerate() {
            match self.find_last(dj, j + 1) {
                Some(i) => self.source.push(Ok(i)),
                None => {
                    self.source.push(Err(self.miss_d.len() / nd));
                    self.miss_d.extend_from_slice(dj);
                }
            }
        }
        let misses = self.miss_d.len() / nd;
        if misses == k {
            self.predict(d, out)?;
        } else {
            if misses > 0 {
                let (miss_d, mut fresh) = (
                    std::mem::take(&mut self.miss_d),
                    std::mem::take(&mut self.fresh),
                );
                fresh.resize(misses, n, m, p);
                let r = self.predict(&miss_d, &mut fresh);
                self.miss_d = miss_d;
                self.fresh = fresh;
                r?;
            }
            for j in 0..k {
                match self.source[j] {
                    Ok(i) => out.copy_point(j, &self.last, i, n, p, nd),
                    Err(i) => out.copy_point(j, &self.fresh, i, n, p, nd),
                }
            }
        }
        if matches!(self.undo, Undo::Marked) {
            // The marked cache is moved aside, not copied (it is replaced just below).
            let (d, eval) = (
                std::mem::take(&mut self.last_d),
                std::mem::take(&mut self.last),
            );
            self.undo = Undo::Saved(d, Box::new(eval));
        }
        self.last_d.clear();
        self.last_d.extend_from_slice(d);
        self.last.clone_from(out);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gp::tests::{data, theta};
    use crate::gp::{Gp, MultiGp};

    /// A model with one state, no input, no output: f is one GP on 20 points.
    fn model() -> GpStageModel {
        let (x, y) = data(20, 1, 7);
        let gp = MultiGp::from_gps(vec![Gp::new(&x, &y, &theta(1)).unwrap()]).unwrap();
        GpStageModel::new(gp, None, 0, false).unwrap()
    }

    #[test]
    fn rollback_restores_the_cache_of_the_mark_without_copying_it_first() {
        let mut m = model();
        let mut out = StageEval::default();
        m.evaluate(&[0.1, 0.2, 0.3], &mut out).unwrap();
        let before = m.cache();
        // No evaluation since the mark: nothing to put back.
        m.mark();
        m.rollback();
        assert_eq!(m.cache(), before);
        // Two evaluations after the mark: the first moved the marked cache aside.
        m.mark();
        m.evaluate(&[0.2, 0.3, 0.4], &mut out).unwrap();
        m.evaluate(&[-1.0, 1.0], &mut out).unwrap();
        assert_ne!(m.cache(), before);
        m.rollback();
        assert_eq!(m.cache(), before);
        // A rollback without a mark changes nothing.
        m.evaluate(&[0.5], &mut out).unwrap();
        let after = m.cache();
        m.rollback();
        assert_eq!(m.cache(), after);
    }
}
