"""SEKernel and the GP layer's structure: the kernel owns theta and its bounds (one home for a
fitted GP's hyperparameters: the core model), exact and sparse GPs are separate classes with the
same API, files written by the previous layout load bit for bit, and the certificate refuses
sparse GPs instead of bounding the exact posterior they do not use."""

import inspect
import io
import zipfile
from pathlib import Path

import numpy as np
import pytest
from sklearn.gaussian_process.kernels import RBF, ConstantKernel

from gpmhe import (GaussianProcess, LearnedModel, MultiOutputGP, SEKernel, SparseGaussianProcess,
                   SparseMultiOutputGP)
from gpmhe.theory import certify_ioss

DATA = Path(__file__).parent / "data"
RNG = np.random.default_rng(0)
D = RNG.uniform(-2.0, 2.0, (40, 2))
Y = np.column_stack([np.sin(D[:, 0]) * D[:, 1], np.cos(D[:, 1])]) + 0.05 * RNG.standard_normal((40, 2))


# ----------------------------------------------------------------------------- the kernel


def test_kernel_matrix_matches_scikit_learn():
    k = SEKernel(sigma_f=[0.5, 2.0], lengthscales=[[0.3, 1.0], [1.5, 0.7]])
    A, B = RNG.normal(size=(6, 2)), RNG.normal(size=(4, 2))
    ref = ConstantKernel(4.0) * RBF([1.5, 0.7])
    np.testing.assert_allclose(k(A, B, output=1), ref(A, B), rtol=1e-13)
    np.testing.assert_allclose(k(A), (ConstantKernel(0.25) * RBF([0.3, 1.0]))(A), rtol=1e-13)


def test_theta_round_trip_and_broadcast():
    k = SEKernel(sigma_f=2.0, lengthscales=[1.0, 3.0], sigma_eps=0.2)
    theta = k.theta(3, 2)
    np.testing.assert_array_equal(theta, np.tile(np.log([2.0, 1.0, 3.0, 0.2]), (3, 1)))
    back = SEKernel.from_theta(theta)
    np.testing.assert_allclose(back.theta(3, 2), theta, rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="lengthscales"):
        k.theta(1, 3)
    with pytest.raises(ValueError, match="overflows"):
        SEKernel.from_theta([800.0, 0.0, 0.0])


def test_bounds_expand_per_input_and_are_checked():
    k = SEKernel(bounds=[(0.1, 10.0), (0.2, 5.0), (1e-3, 1.0)])
    np.testing.assert_allclose(np.exp(k.log_bounds(3)), [(0.1, 10.0)] + [(0.2, 5.0)] * 3 + [(1e-3, 1.0)])
    with pytest.raises(ValueError, match="bounds"):
        SEKernel(bounds=[(1.0, 0.5), (1.0, 2.0), (1.0, 2.0)])
    with pytest.raises(ValueError, match=r"bounds: expected shape"):
        SEKernel(bounds=np.ones((5, 2))).log_bounds(2)


def test_kernel_is_immutable_and_leaves_the_callers_arrays_writable():
    ls = np.array([1.0, 2.0])
    k = SEKernel(lengthscales=ls)
    assert ls.flags.writeable
    ls[0] = 50.0  # the kernel kept its own copy
    assert k.lengthscales[0] == 1.0
    inner = k._lengthscales
    with pytest.raises(ValueError):
        inner[0] = 3.0
    with pytest.raises(AttributeError):
        k.extra = 1
    assert k.with_bounds([(1.0, 2.0)] * 3) is not k


# ----------------------------------------------------------------------------- GPs own one


@pytest.mark.parametrize("cls, y", [(GaussianProcess, Y[:, 0]), (MultiOutputGP, Y),
                                    (SparseGaussianProcess, Y[:, 0]), (SparseMultiOutputGP, Y)])
def test_a_fitted_gp_reads_its_hyperparameters_from_the_model(cls, y):
    gp = cls(sigma_f=0.7, lengthscales=0.9, sigma_eps=0.3).fit(D, y)
    rows = np.atleast_2d(gp.theta)
    np.testing.assert_allclose(gp.kernel.theta(len(rows), 2), rows, rtol=0, atol=1e-14)  # log(exp(theta))
    np.testing.assert_allclose(np.log(np.atleast_1d(gp.sigma_f)), rows[:, 0], rtol=1e-15)
    np.testing.assert_allclose(np.log(np.atleast_2d(gp.lengthscales)), rows[:, 1:-1], rtol=1e-15)
    assert not np.allclose(rows[:, 0], np.log(0.7))  # the fit moved it: not the initial value


@pytest.mark.parametrize("cls, y", [(GaussianProcess, Y[:, 0]), (MultiOutputGP, Y),
                                    (SparseGaussianProcess, Y[:, 0]), (SparseMultiOutputGP, Y)])
def test_setting_a_hyperparameter_on_a_fitted_gp_refactors_it(cls, y):
    """Setting sigma_f, lengthscales or sigma_eps after fit must reach the model (before, the
    attribute changed while theta and the predictions kept the fitted values)."""
    gp = cls(optimizer=None, sigma_eps=0.1, **({"n_inducing": 15} if "Sparse" in cls.__name__ else {})).fit(D, y)
    gp.sigma_f, gp.lengthscales, gp.sigma_eps = 2.0, [0.5, 1.5], 0.2
    ref_kw = dict(sigma_f=2.0, lengthscales=[0.5, 1.5], sigma_eps=0.2, optimizer=None)
    if "Sparse" in cls.__name__:
        ref_kw["inducing"] = gp.inducing_points
    ref = cls(**ref_kw).fit(D, y)
    np.testing.assert_array_equal(gp.theta, ref.theta)
    np.testing.assert_allclose(gp.predict(D[:5]), ref.predict(D[:5]), rtol=1e-12, atol=1e-12)
    before = gp.theta.copy()
    gp.bounds = [(1e-2, 1e2), (1e-2, 1e2), (1e-4, 10.0)]  # bounds alone: the model stays
    np.testing.assert_array_equal(gp.theta, before)
    np.testing.assert_allclose(np.exp(gp.kernel.log_bounds(2))[0], (1e-2, 1e2))
    with pytest.raises(ValueError, match="sigma_f"):
        gp.sigma_f = -1.0
    np.testing.assert_array_equal(gp.theta, before)


def test_an_unfitted_gp_keeps_initial_values_in_its_kernel():
    gp = GaussianProcess(sigma_f=2.0, lengthscales=[1.0, 3.0])
    gp.sigma_eps = 0.5
    assert gp.kernel == SEKernel(2.0, [1.0, 3.0], 0.5)
    gp.fit(D, Y[:, 0])  # starts from the kernel's values
    assert gp.kernel != SEKernel(2.0, [1.0, 3.0], 0.5)


# ----------------------------------------------------------------------------- exact and sparse


@pytest.mark.parametrize("exact, sparse", [(GaussianProcess, SparseGaussianProcess),
                                           (MultiOutputGP, SparseMultiOutputGP)])
def test_sparse_gps_are_not_exact_gps_but_have_their_api(exact, sparse):
    assert not issubclass(sparse, exact) and not issubclass(exact, sparse)
    public = {n for n in dir(exact) if not n.startswith("_")}
    assert public <= set(dir(sparse)), public - set(dir(sparse))
    exact_args = list(inspect.signature(exact.__init__).parameters)[1:]
    sparse_args = list(inspect.signature(sparse.__init__).parameters)[1:]
    assert sparse_args[-len(exact_args):] == exact_args


def test_files_saved_by_the_previous_layout_load_bit_for_bit():
    """tests/data/gp_files_format2.zip: one saved file of each GP class and its predictions at
    seven points, written by the build before the kernel object and the approximation split."""
    classes = {c.__name__: c for c in (GaussianProcess, MultiOutputGP, SparseGaussianProcess, SparseMultiOutputGP)}
    with zipfile.ZipFile(DATA / "gp_files_format2.zip") as z:
        for name, cls in classes.items():
            gp = cls.load(io.BytesIO(z.read(name + ".npz")))
            with np.load(io.BytesIO(z.read(name + "_expected.npz"))) as ref:
                mean, std = gp.predict(ref["T"], return_std=True)
                np.testing.assert_array_equal(mean, ref["mean"])
                np.testing.assert_array_equal(std, ref["std"])
                np.testing.assert_array_equal(gp.theta, ref["theta"])


def test_the_certificate_refuses_sparse_gps():
    X = np.cumsum(RNG.normal(scale=0.1, size=(60, 2)), axis=0)
    model = LearnedModel.from_trajectories([X], [X[:, :1]], n_inducing=10)
    with pytest.raises(ValueError, match="exact GPs"):
        certify_ioss(model, x_bounds=([-3.0, -3.0], [3.0, 3.0]), Q0=np.eye(2), R0=np.eye(1))
