//! `RecursiveGPCore`: Huber's recursive GP (`crate::rgp::Rgp`) on a grid of basis vectors or at
//! given points (a sparse GP's inducing inputs), behind `gpmhe.RecursiveGP`.

use numpy::{PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyTuple, PyType};

use crate::error::Error;
use crate::kernel::SeArd;
use crate::python::convert::{array2, slice1, slice2};
use crate::python::error::detach_interruptible;
use crate::python::sparse::PySparseMultiGp;
use crate::rgp::{Jitter, Rgp, RgpBasis};
use faer::MatRef;

/// A (mean, variance) pair of 1-D arrays.
pub(super) type MeanVar<'py> = (Bound<'py, PyArray1<f64>>, Bound<'py, PyArray1<f64>>);

pub(super) fn mat_to_array2<'py>(
    py: Python<'py>,
    m: MatRef<'_, f64>,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let (r, c) = (m.nrows(), m.ncols());
    let mut out = Vec::with_capacity(r * c);
    for i in 0..r {
        for j in 0..c {
            out.push(m[(i, j)]);
        }
    }
    array2(py, out, r, c)
}

/// Huber's recursive GP on a unit grid of basis vectors, or at given points (see
/// gpmhe.RecursiveGP).
#[pyclass(name = "RecursiveGPCore", module = "gpmhe._core")]
#[derive(Clone)]
pub(crate) struct RgpCore {
    pub(super) inner: Rgp,
    /// The constructor's arguments (for pickling).
    pub(super) args: RgpArgs,
}

/// The arguments that rebuild a GP's basis: `RecursiveGPCore(lower, upper, n_points, sigma_k,
/// l, sigma_r, sigma_p)` for a grid, `RecursiveGPCore.from_points(points, sigma_k, lengthscales,
/// jitter, prior_mean, sigma_r, sigma_p)` for given points.
#[derive(Clone)]
pub(super) enum RgpArgs {
    Grid {
        lower: Vec<f64>,
        upper: Vec<f64>,
        n_points: Vec<usize>,
        params: [f64; 4],
    },
    Points {
        points: Vec<f64>,
        lengthscales: Vec<f64>,
        prior_mean: Option<Vec<f64>>,
        /// σ_K, jitter, σ_r, σ_p.
        params: [f64; 4],
    },
}

#[pymethods]
impl RgpCore {
    #[new]
    #[allow(clippy::too_many_arguments)]
    fn new(
        lower: PyReadonlyArray1<'_, f64>,
        upper: PyReadonlyArray1<'_, f64>,
        n_points: Vec<usize>,
        sigma_k: f64,
        l: f64,
        sigma_r: f64,
        sigma_p: f64,
    ) -> PyResult<Self> {
        let basis = RgpBasis::new(
            slice1("lower", &lower)?,
            slice1("upper", &upper)?,
            &n_points,
            sigma_k,
            l,
            sigma_r,
            sigma_p,
        )?;
        let args = RgpArgs::Grid {
            lower: slice1("lower", &lower)?.to_vec(),
            upper: slice1("upper", &upper)?.to_vec(),
            n_points,
            params: [sigma_k, l, sigma_r, sigma_p],
        };
        Ok(Self {
            inner: Rgp::new(basis),
            args,
        })
    }

    /// A fresh GP (weights N(0, K)) with basis vectors at `points` (m, n_X), the SE-ARD kernel
    /// (σ_K, `lengthscales` in ζ units), exactly the diagonal `jitter` on K, the prior mean's
    /// coefficients [b, w_1, …, w_nX] or None, floor σ_r and process noise σ_p.
    #[classmethod]
    #[allow(clippy::too_many_arguments)]
    #[pyo3(signature = (points, sigma_k, lengthscales, jitter, prior_mean, sigma_r, sigma_p))]
    fn from_points(
        _cls: &Bound<'_, PyType>,
        points: PyReadonlyArray2<'_, f64>,
        sigma_k: f64,
        lengthscales: PyReadonlyArray1<'_, f64>,
        jitter: f64,
        prior_mean: Option<PyReadonlyArray1<'_, f64>>,
        sigma_r: f64,
        sigma_p: f64,
    ) -> PyResult<Self> {
        let (pts, _, nx) = slice2("points", &points)?;
        let ls = slice1("lengthscales", &lengthscales)?;
        if ls.len() != nx {
            return Err(PyValueError::new_err(format!(
                "lengthscales: expected {nx} values (one per column of points), got {}",
                ls.len()
            )));
        }
        let kernel = SeArd::new(sigma_k, ls).map_err(|e| match e {
            Error::InvalidInput { arg, msg } if arg == "sigma_f" => Error::invalid("sigma_K", msg),
            e => e,
        })?;
        let mut basis =
            RgpBasis::from_points(pts, kernel, Jitter::Fixed(jitter), sigma_r, sigma_p)?;
        let mean = prior_mean
            .as_ref()
            .map(|m| slice1("prior_mean", m).map(<[f64]>::to_vec))
            .transpose()?;
        if let Some(m) = &mean {
            basis = basis.with_prior_mean(m)?;
        }
        let args = RgpArgs::Points {
            points: pts.to_vec(),
            lengthscales: ls.to_vec(),
            prior_mean: mean,
            params: [sigma_k, jitter, sigma_r, sigma_p],
        };
        Ok(Self {
            inner: Rgp::new(basis),
            args,
        })
    }

    /// The GP that predicts as output `output` of the fitted sparse GPs `model`: basis vectors
    /// at its inducing inputs, its kernel, jitter and prior mean, and weights N(μ_u, Σ_u), the
    /// posterior of the inducing outputs.
    #[classmethod]
    fn from_sparse(
        _cls: &Bound<'_, PyType>,
        model: PyRef<'_, PySparseMultiGp>,
        output: usize,
        sigma_r: f64,
        sigma_p: f64,
    ) -> PyResult<Self> {
        let inner = Rgp::from_sparse(&model.inner, output, sigma_r, sigma_p)?;
        let b = inner.basis();
        let args = RgpArgs::Points {
            points: b.basis_vectors(),
            lengthscales: b.kernel().lengthscales().to_vec(),
            prior_mean: b.prior_mean().map(<[f64]>::to_vec),
            params: [b.kernel().sigma_f(), b.jitter(), sigma_r, sigma_p],
        };
        Ok(Self { inner, args })
    }

    fn copy(&self) -> Self {
        self.clone()
    }

    fn update(
        &mut self,
        py: Python<'_>,
        zeta: PyReadonlyArray1<'_, f64>,
        y: f64,
        var_y: f64,
    ) -> PyResult<f64> {
        let z = slice1("zeta", &zeta)?;
        let inner = &mut self.inner;
        Ok(py.detach(|| inner.update(z, y, var_y))?)
    }

    fn update_many<'py>(
        &mut self,
        py: Python<'py>,
        zeta: PyReadonlyArray2<'py, f64>,
        y: PyReadonlyArray1<'py, f64>,
        var_y: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let (z, _, _) = slice2("zeta", &zeta)?;
        let (y, v) = (slice1("y", &y)?, slice1("var_y", &var_y)?);
        let inner = &mut self.inner;
        let out = detach_interruptible(py, || inner.update_many(z, y, v))?;
        Ok(PyArray1::from_vec(py, out))
    }

    fn predict<'py>(
        &mut self,
        py: Python<'py>,
        zeta: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<MeanVar<'py>> {
        let (z, _, _) = slice2("zeta", &zeta)?;
        let inner = &mut self.inner;
        let (m, v) = py.detach(|| inner.predict(z))?;
        Ok((PyArray1::from_vec(py, m), PyArray1::from_vec(py, v)))
    }

    fn j_row<'py>(
        &mut self,
        py: Python<'py>,
        zeta: PyReadonlyArray1<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let j = self.inner.j_row(slice1("zeta", &zeta)?)?;
        Ok(PyArray1::from_vec(py, j))
    }

    fn set_weights(
        &mut self,
        mean: PyReadonlyArray1<'_, f64>,
        cov: PyReadonlyArray2<'_, f64>,
    ) -> PyResult<()> {
        let (c, _, _) = slice2("cov", &cov)?;
        Ok(self.inner.set_weights(slice1("mean", &mean)?, c)?)
    }

    #[getter]
    fn mean<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_slice(py, self.inner.mean())
    }

    #[getter]
    fn cov<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        mat_to_array2(py, self.inner.cov())
    }

    #[getter]
    fn basis_vectors<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        let b = self.inner.basis();
        array2(py, b.basis_vectors(), b.n_basis(), b.dim())
    }

    #[getter]
    fn kernel_matrix<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<f64>>> {
        mat_to_array2(py, self.inner.basis().kernel_matrix())
    }

    #[getter]
    fn jitter(&self) -> f64 {
        self.inner.basis().jitter()
    }

    /// σ_K, the kernel's prior standard deviation.
    #[getter]
    fn sigma_k(&self) -> f64 {
        self.inner.basis().kernel().sigma_f()
    }

    /// The kernel's length-scales in ζ units.
    #[getter]
    fn lengthscales<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.inner.basis().lengthscales_zeta())
    }

    /// The prior mean's coefficients [b, w_1, …, w_nX], or None.
    #[getter]
    fn prior_mean<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyArray1<f64>>> {
        self.inner
            .basis()
            .prior_mean()
            .map(|c| PyArray1::from_slice(py, c))
    }

    /// Whether the basis vectors form a grid (the constructor) or sit at given points.
    #[getter]
    fn is_grid(&self) -> bool {
        self.inner.basis().is_grid()
    }

    // ---- copies and pickles -----------------------------------------------------------------
    fn __copy__(&self) -> Self {
        self.clone()
    }

    fn __deepcopy__(&self, _memo: Bound<'_, PyAny>) -> Self {
        self.clone()
    }

    /// Pickles as (RecursiveGPCore or RecursiveGPCore.from_points, its arguments, (mean, cov as
    /// stored)).
    fn __reduce__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        let nb = self.inner.mean().len();
        let state = (
            PyArray1::from_slice(py, self.inner.mean()),
            array2(py, self.inner.cov_raw(), nb, nb)?,
        );
        let ty = py.get_type::<Self>();
        let make = match self.args {
            RgpArgs::Grid { .. } => ty.into_any(),
            RgpArgs::Points { .. } => ty.getattr("from_points")?,
        };
        (make, self.args.to_tuple(py)?, state).into_pyobject(py)
    }

    /// Restores the weights exactly from `(mean, cov)` as `__reduce__` gives them.
    fn __setstate__(
        &mut self,
        state: (PyReadonlyArray1<'_, f64>, PyReadonlyArray2<'_, f64>),
    ) -> PyResult<()> {
        let (c, _, _) = slice2("cov", &state.1)?;
        Ok(self.inner.set_weights_raw(slice1("mean", &state.0)?, c)?)
    }
}

impl RgpArgs {
    /// The arguments of the constructor (grid) or of `from_points`, as a tuple.
    fn to_tuple<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        match self {
            RgpArgs::Grid {
                lower,
                upper,
                n_points,
                params: [k, l, r, p],
            } => (
                PyArray1::from_slice(py, lower),
                PyArray1::from_slice(py, upper),
                n_points.clone(),
                *k,
                *l,
                *r,
                *p,
            )
                .into_pyobject(py),
            RgpArgs::Points {
                points,
                lengthscales,
                prior_mean,
                params: [k, jitter, r, p],
            } => {
                let nx = lengthscales.len();
                (
                    array2(py, points.clone(), points.len() / nx, nx)?,
                    *k,
                    PyArray1::from_slice(py, lengthscales),
                    *jitter,
                    prior_mean.as_ref().map(|m| PyArray1::from_slice(py, m)),
                    *r,
                    *p,
                )
                    .into_pyobject(py)
            }
        }
    }
}
