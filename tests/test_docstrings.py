"""The docstrings' examples: every module's doctests pass, and every public class, function and
method of the API has an Examples section with at least one example that the doctests run."""

import doctest
import importlib
import inspect
import pkgutil
import re

import pytest
from numpydoc.docscrape import NumpyDocString

import gpmhe

OPTIONFLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE

MODULES = sorted(
    ["gpmhe"]
    + [info.name for info in pkgutil.walk_packages(gpmhe.__path__, prefix="gpmhe.")]
)


def _public_api():
    """Qualified names -> objects that must carry a run example: everything in gpmhe.__all__
    (except NumericalError, which comes from the Rust module), the EKF baselines, the example
    systems' public functions and classes, and the public methods of all those classes
    (properties are attributes and need no example)."""
    objects = {}
    for name in gpmhe.__all__:
        if name != "NumericalError":
            obj = getattr(gpmhe, name)
            objects[f"{obj.__module__}.{obj.__qualname__}"] = obj
    for modname in ("gpmhe.baselines", "gpmhe.study", "gpmhe.systems.batch_reactor",
                    "gpmhe.systems.second_order", "gpmhe.systems.cart_pole",
                    "gpmhe.systems.rotating_masses"):
        module = importlib.import_module(modname)
        for name, obj in vars(module).items():
            if (not name.startswith("_") and (inspect.isfunction(obj) or inspect.isclass(obj))
                    and obj.__module__ == modname):
                objects[f"{modname}.{obj.__qualname__}"] = obj
    for cls in [obj for obj in objects.values() if inspect.isclass(obj)]:
        # Every public method the class has, under the gpmhe class that defines the one it uses
        # (its doctests run there): a base class's method counts unless the class overrides it.
        for name in dir(cls):
            owner = next((b for b in cls.__mro__ if name in vars(b)), None)
            if name.startswith("_") or owner is None or not owner.__module__.startswith("gpmhe"):
                continue
            attr = vars(owner)[name]
            if isinstance(attr, property):
                continue
            func = attr.__func__ if isinstance(attr, (classmethod, staticmethod)) else attr
            if inspect.isfunction(func):
                objects[f"{owner.__module__}.{owner.__qualname__}.{name}"] = func
    return objects


PUBLIC_API = _public_api()


try:
    import casadi  # noqa: F401

    HAVE_CASADI = True
except ImportError:
    HAVE_CASADI = False


def _needs_missing_casadi(report):
    """Whether a failed doctest failed only because CasADi (an optional dependency) is missing."""
    return not HAVE_CASADI and ("needs CasADi" in report
                                or re.search(r"(ModuleNotFound|Import)Error: .*casadi", report) is not None)


@pytest.fixture(scope="module")
def doctest_results():
    """Runs the doctests of every module once: {test name: (attempted, failed, report)}; without
    CasADi, a doctest that fails for want of it counts as skipped (failed = None)."""
    results = {}
    finder = doctest.DocTestFinder()
    for modname in MODULES:
        module = importlib.import_module(modname)
        for test in finder.find(module, modname):
            if not test.examples:
                continue
            lines = []
            runner = doctest.DocTestRunner(optionflags=OPTIONFLAGS)
            runner.run(test, out=lines.append)
            result = runner.summarize(verbose=False)
            report = "".join(lines)
            failed = None if result.failed and _needs_missing_casadi(report) else result.failed
            results[test.name] = (modname, result.attempted, failed, report)
    return results


@pytest.mark.parametrize("modname", MODULES)
def test_module_doctests_pass(modname, doctest_results):
    failures = [report for mod, _, failed, report in doctest_results.values()
                if mod == modname and failed]
    assert not failures, "\n".join(failures)


def test_api_list_is_complete():
    # A guard against the list silently shrinking (e.g. a renamed module).
    assert "gpmhe.mhe.estimator.GPMHE.update" in PUBLIC_API
    assert "gpmhe.mhe.runs.Runs.batch_filter" in PUBLIC_API
    assert "gpmhe.baselines.GPEKF" in PUBLIC_API
    assert "gpmhe.systems.second_order.Run" in PUBLIC_API
    assert len(PUBLIC_API) > 60


@pytest.mark.parametrize("qualname", sorted(PUBLIC_API))
def test_public_object_has_run_example(qualname, doctest_results):
    doc = inspect.getdoc(PUBLIC_API[qualname]) or ""
    section = "\n".join(NumpyDocString(doc)["Examples"])
    examples = doctest.DocTestParser().get_examples(section)
    assert examples, f"{qualname}: no example in an Examples section"
    skipped = [ex.source for ex in examples if ex.options.get(doctest.SKIP)]
    assert not skipped, f"{qualname}: skipped examples {skipped}"
    assert qualname in doctest_results, f"{qualname}: its doctests were not run"
    _, attempted, failed, _ = doctest_results[qualname]
    if failed is None:
        pytest.skip("needs CasADi")
    assert attempted >= len(examples)
