//! `RGPEKFCore`: the RGP-dKF's per-step calls behind `gpmhe.RGPEKF`. A step converts its inputs,
//! calls the user's functions f, A, e (predict) or h, H (update), reads their results (`read.rs`)
//! and hands them to the core (`crate::rgp`, which also chooses between given and stored
//! Jacobians); copies and pickles at the end.

use numpy::{PyArray1, PyArray2, PyArrayDyn, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyFloat, PyList, PyTuple};

use super::read::read_f64;
use super::recursive_gp::{mat_to_array2, MeanVar, RgpArgs, RgpCore};
use crate::python::convert::{array2, slice1, slice2};
use crate::rgp::{ConstantJacobians, RgpEkf, RgpEkfState};

/// Dimension n + Σ n_b (N in augmented mode) from which the per-step calls of `RGPEKFCore` release the GIL.
/// Below it a step's kernels take a few µs, less than a release and re-acquisition of the GIL costs
/// when other threads contend for it (numpy likewise keeps the GIL for small arrays).
const RGP_STEP_GIL_RELEASE_MIN_DIM: usize = 200;

/// Runs `f` with the GIL released if `release`, else holding it.
fn detach_if<T: Send>(py: Python<'_>, release: bool, f: impl FnOnce() -> T + Send) -> T {
    if release {
        py.detach(f)
    } else {
        f()
    }
}

/// The RGP-dKF state and per-step kernels (see gpmhe.RGPEKF). Constant Jacobians A, e, H are
/// stored once (`set_constant_jacobians`) so that a step passes only what changes.
#[pyclass(name = "RGPEKFCore", module = "gpmhe._core")]
pub(crate) struct RgpEkfCore {
    inner: RgpEkf,
    constants: ConstantJacobians,
    /// Per-step copies of the inputs and of the user functions' results (a few values each).
    buf: StepBuffers,
    /// The constructor arguments of the GPs (for pickling).
    gp_args: Vec<RgpArgs>,
}

#[derive(Default)]
struct StepBuffers {
    zeta: Vec<f64>,
    x_pred: Vec<f64>,
    a: Vec<f64>,
    e: Vec<f64>,
    q: Vec<f64>,
    y: Vec<f64>,
    hx: Vec<f64>,
    h: Vec<f64>,
    r: Vec<f64>,
    nu: Vec<f64>,
    r_full: Vec<f64>,
}

impl RgpEkfCore {
    /// Whether a step's kernels run with the GIL released (see RGP_STEP_GIL_RELEASE_MIN_DIM).
    fn release_gil(&self) -> bool {
        self.inner.dim_x() + self.inner.n_basis_total() >= RGP_STEP_GIL_RELEASE_MIN_DIM
    }

    /// A fresh array of the current state x (the user's functions may keep it).
    fn x_array<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, self.inner.x())
    }
}

#[pymethods]
impl RgpEkfCore {
    #[new]
    fn new(
        x0: PyReadonlyArray1<'_, f64>,
        p0: PyReadonlyArray2<'_, f64>,
        gps: Vec<PyRef<'_, RgpCore>>,
        augmented: bool,
    ) -> PyResult<Self> {
        let (p, _, _) = slice2("P0", &p0)?;
        let gp_args = gps.iter().map(|g| g.args.clone()).collect();
        let gps = gps.iter().map(|g| g.inner.clone()).collect();
        Ok(Self {
            inner: RgpEkf::new(slice1("x0", &x0)?, p, gps, augmented)?,
            constants: ConstantJacobians::default(),
            buf: StepBuffers::default(),
            gp_args,
        })
    }

    /// Stores constant A (n × n), e (n × q), H (p × n) (None: given at every step).
    #[pyo3(signature = (a=None, e=None, h=None))]
    fn set_constant_jacobians(
        &mut self,
        a: Option<PyReadonlyArray2<'_, f64>>,
        e: Option<PyReadonlyArray2<'_, f64>>,
        h: Option<PyReadonlyArray2<'_, f64>>,
    ) -> PyResult<()> {
        let copy = |arg: &str, m: &Option<PyReadonlyArray2<'_, f64>>| -> PyResult<_> {
            m.as_ref()
                .map(|m| slice2(arg, m).map(|s| s.0.to_vec()))
                .transpose()
        };
        let (a, e, h) = (copy("A", &a)?, copy("e", &e)?, copy("H", &h)?);
        self.constants = ConstantJacobians { a, e, h };
        Ok(())
    }

    /// One prediction step (paper §3.4, steps 1–3) in one call: J_k and μ_z^p at the GP inputs
    /// `zeta` (a float for one 1-D GP, else the inputs of all GPs concatenated), then
    /// x⁻ = f(x, u, z), A(x, u, z) and e(x, u, z) (None: the stored constants) called here with
    /// z = μ_z^p (a float for one GP, else an array), then the structured covariance prediction
    /// with Q_x. Bad input or results raise ValueError naming them; C and μ stay unchanged.
    #[pyo3(signature = (f, u, zeta, a_fn, e_fn, q_x))]
    #[allow(clippy::too_many_arguments)]
    fn predict_step(
        &mut self,
        py: Python<'_>,
        f: &Bound<'_, PyAny>,
        u: &Bound<'_, PyAny>,
        zeta: &Bound<'_, PyAny>,
        a_fn: Option<&Bound<'_, PyAny>>,
        e_fn: Option<&Bound<'_, PyAny>>,
        q_x: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let release = self.release_gil();
        read_f64("zeta", zeta, &mut self.buf.zeta)?;
        {
            let (inner, z) = (&mut self.inner, &self.buf.zeta);
            detach_if(py, release, || inner.infer(z).map(|_| ()))?;
        }
        let (n, q) = (self.inner.dim_x(), self.inner.n_gps());
        let x = self.x_array(py);
        let zp = self.inner.inferred_z();
        let z = if q == 1 {
            PyFloat::new(py, zp[0]).into_any()
        } else {
            PyArray1::from_slice(py, zp).into_any()
        };
        let xp = f.call1((&x, u, &z))?;
        let shape = read_f64("f", &xp, &mut self.buf.x_pred)?;
        if self.buf.x_pred.len() != n {
            return Err(PyValueError::new_err(format!(
                "f: returned {} values (shape {}), expected {n}",
                self.buf.x_pred.len(),
                shape.repr()
            )));
        }
        if let Some(a_fn) = a_fn {
            let shape = read_f64("A", &a_fn.call1((&x, u, &z))?, &mut self.buf.a)?;
            if !shape.is(&[n, n]) {
                return Err(PyValueError::new_err(format!(
                    "A: returned shape {}, expected ({n}, {n})",
                    shape.repr()
                )));
            }
        }
        if let Some(e_fn) = e_fn {
            let shape = read_f64("e", &e_fn.call1((&x, u, &z))?, &mut self.buf.e)?;
            if self.buf.e.len() != n * q {
                return Err(PyValueError::new_err(format!(
                    "e: returned shape {}, expected ({n}, {q})",
                    shape.repr()
                )));
            }
        }
        read_f64("Q_x", q_x, &mut self.buf.q)?;
        let a = a_fn.map(|_| &self.buf.a[..]);
        let e = e_fn.map(|_| &self.buf.e[..]);
        let (inner, xp, qb, c) = (
            &mut self.inner,
            &self.buf.x_pred,
            &self.buf.q,
            &self.constants,
        );
        Ok(detach_if(py, release, || {
            inner.predict_step(xp, a, e, qb, c)
        })?)
    }

    /// One EKF update (paper §3.4, step 4) in one call: h(x⁻) and H(x⁻) (None: the stored
    /// constant) called here, ν = y − h(x⁻), then the update with R_x (a (p, p) array, or a
    /// scalar meaning R_x I). `dim_y`, if known, is the required number of outputs. Returns the
    /// log-likelihood. Bad input raises ValueError naming it, an indefinite innovation
    /// covariance gpmhe.NumericalError; C and μ stay unchanged.
    #[pyo3(signature = (y, h, h_fn, r, dim_y, learning))]
    #[allow(clippy::too_many_arguments)]
    fn update_step(
        &mut self,
        py: Python<'_>,
        y: &Bound<'_, PyAny>,
        h: &Bound<'_, PyAny>,
        h_fn: Option<&Bound<'_, PyAny>>,
        r: &Bound<'_, PyAny>,
        dim_y: Option<usize>,
        learning: bool,
    ) -> PyResult<f64> {
        read_f64("y", y, &mut self.buf.y)?;
        let (n, p) = (self.inner.dim_x(), self.buf.y.len());
        if let Some(d) = dim_y {
            if p != d {
                return Err(PyValueError::new_err(format!(
                    "y: expected {d} value(s), got {p}"
                )));
            }
        }
        let x = self.x_array(py);
        read_f64("h", &h.call1((&x,))?, &mut self.buf.hx)?;
        if self.buf.hx.len() != p {
            return Err(PyValueError::new_err(format!(
                "h: returned {} values but y has {p}",
                self.buf.hx.len()
            )));
        }
        if let Some(h_fn) = h_fn {
            let shape = read_f64("H", &h_fn.call1((&x,))?, &mut self.buf.h)?;
            if self.buf.h.len() != p * n {
                return Err(PyValueError::new_err(format!(
                    "H: shape {} does not match ({p}, {n})",
                    shape.repr()
                )));
            }
        }
        let scalar = read_f64("R_x", r, &mut self.buf.r)?.ndim == 0;
        let release = self.release_gil();
        let StepBuffers {
            y,
            hx,
            h: h_given,
            r: r_x,
            nu,
            r_full,
            ..
        } = &mut self.buf;
        let h = h_fn.map(|_| &h_given[..]);
        let (inner, c) = (&mut self.inner, &self.constants);
        Ok(detach_if(py, release, || {
            inner.update_step(y, hx, h, r_x, scalar, learning, c, nu, r_full)
        })?)
    }

    #[getter]
    fn z_pred<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, self.inner.z_pred())
    }

    fn set_x(&mut self, x: PyReadonlyArray1<'_, f64>) -> PyResult<()> {
        Ok(self.inner.set_x(slice1("x", &x)?)?)
    }

    fn set_p(&mut self, p: PyReadonlyArray2<'_, f64>) -> PyResult<()> {
        Ok(self.inner.set_p(slice2("P", &p)?.0)?)
    }
    fn gp_predict<'py>(
        &mut self,
        py: Python<'py>,
        index: usize,
        zeta: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<MeanVar<'py>> {
        let (z, _, _) = slice2("zeta", &zeta)?;
        let inner = &mut self.inner;
        let (m, v) = py.detach(|| inner.gp_predict(index, z))?;
        Ok((PyArray1::from_vec(py, m), PyArray1::from_vec(py, v)))
    }

    #[allow(clippy::type_complexity)]
    fn gp_weights<'py>(
        &self,
        py: Python<'py>,
        index: usize,
    ) -> PyResult<(Bound<'py, PyArray1<f64>>, Bound<'py, PyArray2<f64>>)> {
        if index >= self.inner.n_gps() {
            return Err(PyValueError::new_err(format!(
                "index: there are {} GPs, got {index}",
                self.inner.n_gps()
            )));
        }
        let (m, c) = self.inner.gp_weights(index);
        Ok((PyArray1::from_vec(py, m), mat_to_array2(py, c.as_ref())?))
    }

    #[getter]
    fn x<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, self.inner.x())
    }

    #[getter(P)]
    fn p<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        mat_to_array2(py, self.inner.p())
    }

    #[getter]
    fn mu<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.inner.mu())
    }

    #[getter(C)]
    fn c<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        mat_to_array2(py, self.inner.cov().as_ref())
    }

    #[getter]
    fn innovation<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, self.inner.innovation())
    }

    #[getter(S)]
    fn s<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        mat_to_array2(py, self.inner.innovation_cov())
    }

    #[getter]
    fn log_likelihood(&self) -> f64 {
        self.inner.log_likelihood()
    }

    // ---- copies, pickles and checkpoints ------------------------------------------------------
    /// An independent copy (the scratch buffers start empty); it continues exactly as the
    /// original would.
    fn __copy__(&self) -> Self {
        Self {
            inner: self.inner.clone(),
            constants: self.constants.clone(),
            buf: StepBuffers::default(),
            gp_args: self.gp_args.clone(),
        }
    }

    fn __deepcopy__(&self, _memo: Bound<'_, PyAny>) -> Self {
        self.__copy__()
    }

    /// Pickles as (RGPEKFCore, constructor arguments, `__getstate__()`).
    fn __reduce__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        let n = self.inner.dim_x();
        let gps = PyList::empty(py);
        for (g, args) in self.inner.gps().iter().zip(&self.gp_args) {
            let core = RgpCore {
                inner: g.clone(),
                args: args.clone(),
            };
            gps.append(Py::new(py, core)?)?;
        }
        let args = (
            PyArray1::from_slice(py, &self.inner.state().mu[..n]),
            array2(py, vec![0.0; n * n], n, n)?,
            gps,
            self.inner.augmented(),
        );
        (py.get_type::<Self>(), args, self.__getstate__(py)?).into_pyobject(py)
    }

    /// The state as a dict of arrays: `mu` (N,), `cov` (N, N) as stored, `gp_mean_<i>`,
    /// `gp_cov_<i>` per GP, `j`, `dvar`, `mu_zp`, `z_pred`, `inferred` (bool), `innovation` (p,), `S`
    /// (p, p), `log_likelihood`, and `A_const`, `e_const`, `H_const` when set.
    fn __getstate__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let st = self.inner.state();
        let (n, nt, q) = (
            self.inner.dim_x(),
            self.inner.dim_total(),
            self.inner.n_gps(),
        );
        let d = PyDict::new(py);
        d.set_item("mu", PyArray1::from_vec(py, st.mu))?;
        d.set_item("cov", array2(py, st.cov, nt, nt)?)?;
        for (i, (m, c)) in st.gp_means.into_iter().zip(st.gp_covs).enumerate() {
            let nb = m.len();
            d.set_item(format!("gp_mean_{i}"), PyArray1::from_vec(py, m))?;
            d.set_item(format!("gp_cov_{i}"), array2(py, c, nb, nb)?)?;
        }
        d.set_item("j", PyArray1::from_vec(py, st.j))?;
        d.set_item("dvar", PyArray1::from_vec(py, st.dvar))?;
        d.set_item("mu_zp", PyArray1::from_vec(py, st.mu_zp))?;
        d.set_item("z_pred", PyArray1::from_vec(py, st.z_pred))?;
        d.set_item("inferred", st.inferred)?;
        let p = st.innovation.len();
        d.set_item("innovation", PyArray1::from_vec(py, st.innovation))?;
        d.set_item("S", array2(py, st.s, p, p)?)?;
        d.set_item("log_likelihood", st.log_likelihood)?;
        for (key, m, cols) in [
            ("A_const", &self.constants.a, n),
            ("e_const", &self.constants.e, q),
            ("H_const", &self.constants.h, n),
        ] {
            if let Some(m) = m {
                d.set_item(key, array2(py, m.clone(), m.len() / cols.max(1), cols)?)?;
            }
        }
        Ok(d)
    }

    /// Restores the state from `__getstate__` of an estimator with the same dimensions and GPs.
    /// Every entry is checked (a ValueError names it); on error nothing changes.
    fn __setstate__(&mut self, state: Bound<'_, PyDict>) -> PyResult<()> {
        let vec = |key: &str| -> PyResult<Vec<f64>> {
            let item = state
                .get_item(key)?
                .ok_or_else(|| PyValueError::new_err(format!("{key}: missing from the state")))?;
            let a = item
                .cast::<PyArrayDyn<f64>>()
                .map_err(|_| PyValueError::new_err(format!("{key}: must be a float64 array")))?;
            Ok(a.readonly().as_array().iter().copied().collect())
        };
        let scalar = |key: &str| -> PyResult<Bound<'_, PyAny>> {
            state
                .get_item(key)?
                .ok_or_else(|| PyValueError::new_err(format!("{key}: missing from the state")))
        };
        let q = self.inner.n_gps();
        let mut gp_means = Vec::with_capacity(q);
        let mut gp_covs = Vec::with_capacity(q);
        for i in 0..q {
            gp_means.push(vec(&format!("gp_mean_{i}"))?);
            gp_covs.push(vec(&format!("gp_cov_{i}"))?);
        }
        let st = RgpEkfState {
            mu: vec("mu")?,
            cov: vec("cov")?,
            gp_means,
            gp_covs,
            j: vec("j")?,
            dvar: vec("dvar")?,
            mu_zp: vec("mu_zp")?,
            z_pred: vec("z_pred")?,
            inferred: scalar("inferred")?
                .extract::<bool>()
                .map_err(|_| PyValueError::new_err("inferred: must be a bool"))?,
            innovation: vec("innovation")?,
            s: vec("S")?,
            log_likelihood: scalar("log_likelihood")?
                .extract::<f64>()
                .map_err(|_| PyValueError::new_err("log_likelihood: must be a float"))?,
        };
        let consts = ["A_const", "e_const", "H_const"]
            .into_iter()
            .map(|k| match state.contains(k)? {
                true => vec(k).map(Some),
                false => Ok(None),
            })
            .collect::<PyResult<Vec<_>>>()?;
        self.inner.set_state(st)?;
        let mut consts = consts.into_iter();
        self.constants = ConstantJacobians {
            a: consts.next().flatten(),
            e: consts.next().flatten(),
            h: consts.next().flatten(),
        };
        Ok(())
    }
}
