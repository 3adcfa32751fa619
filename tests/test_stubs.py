"""The hand-written type stub of the Rust module, gpmhe/_core.pyi, against the module itself:
the same classes and functions, the same public methods and properties on every class, and for
every function and method the same parameter names, in order, with defaults where the runtime
has them. A binding change that the stub does not follow fails here."""

import ast
import inspect
import pathlib

import pytest

from gpmhe import _core

STUB = pathlib.Path(_core.__file__).with_name("_core.pyi")
#: Dunder methods that every stub may leave out (Python's own protocol, no signature to keep; an
#: enum's rich comparison slot brings the orderings along with the __eq__ the stub names).
IGNORED = {"__new__", "__init_subclass__", "__subclasshook__", "__class_getitem__", "__lt__",
           "__le__", "__gt__", "__ge__"}


def stub_tree():
    return ast.parse(STUB.read_text())


def stub_params(fn: ast.FunctionDef):
    """[(name, has_default)] of a stub function, without self/cls, keyword-only included."""
    a = fn.args
    positional = a.posonlyargs + a.args
    defaults = [False] * (len(positional) - len(a.defaults)) + [True] * len(a.defaults)
    out = list(zip((p.arg for p in positional), defaults))
    out += [(p.arg, d is not None) for p, d in zip(a.kwonlyargs, a.kw_defaults)]
    is_static = any(isinstance(d, ast.Name) and d.id == "staticmethod" for d in fn.decorator_list)
    if out and out[0][0] in ("self", "cls") and not is_static:
        out = out[1:]
    return out


def runtime_params(obj):
    sig = inspect.signature(obj)
    return [(p.name, p.default is not inspect.Parameter.empty) for p in sig.parameters.values()
            if p.name not in ("self", "cls", "$self", "$cls")
            and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]


def stub_members(cls: ast.ClassDef):
    members = {}
    for node in cls.body:
        if isinstance(node, ast.FunctionDef):
            members[node.name] = node
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            members[node.target.id] = node
    return members


def runtime_members(cls):
    names = set()
    for name, value in vars(cls).items():
        if name.startswith("_") and not (name.startswith("__") and name.endswith("__")):
            continue
        if name in IGNORED or name in ("__doc__", "__module__", "__dict__", "__weakref__",
                                       "__text_signature__", "__init__", "__hash__"):
            continue
        names.add(name)
    return names


STUB_CLASSES = {n.name: n for n in stub_tree().body if isinstance(n, ast.ClassDef)}
STUB_FUNCTIONS = {n.name: n for n in stub_tree().body if isinstance(n, ast.FunctionDef)}


def test_the_stub_names_every_class_and_function_of_the_module_and_no_other():
    runtime_classes = {n for n, v in vars(_core).items() if inspect.isclass(v) and not n.startswith("_")}
    runtime_functions = {n for n, v in vars(_core).items()
                         if callable(v) and not inspect.isclass(v) and not n.startswith("_")}
    assert set(STUB_CLASSES) == runtime_classes
    assert set(STUB_FUNCTIONS) == runtime_functions


@pytest.mark.parametrize("name", sorted(STUB_CLASSES))
def test_every_class_has_the_stubs_methods_and_properties(name):
    cls = getattr(_core, name)
    stub = stub_members(STUB_CLASSES[name])
    runtime = runtime_members(cls)
    if issubclass(cls, BaseException):  # exceptions: only what the stub adds
        runtime = {n for n in runtime if n in vars(cls)} & set(stub)
    missing_in_stub = runtime - set(stub) - {"__init__"}
    missing_at_runtime = {n for n in set(stub) - runtime - {"__init__"}
                          if not hasattr(cls, n)}
    assert not missing_in_stub, f"{name}: not in the stub: {sorted(missing_in_stub)}"
    assert not missing_at_runtime, f"{name}: not in the module: {sorted(missing_at_runtime)}"


def _callables():
    for cname, cls in STUB_CLASSES.items():
        for mname, node in stub_members(cls).items():
            if isinstance(node, ast.FunctionDef) and not any(
                    isinstance(d, ast.Name) and d.id == "property" for d in node.decorator_list):
                yield f"{cname}.{mname}", node
    for fname, node in STUB_FUNCTIONS.items():
        yield fname, node


@pytest.mark.parametrize("qualname, node", list(_callables()), ids=lambda v: v if isinstance(v, str) else "")
def test_every_signature_matches_the_stub(qualname, node):
    obj = _core
    for part in qualname.split("."):
        obj = getattr(obj, part)
    if qualname.endswith(".__init__"):
        obj = getattr(_core, qualname.split(".")[0])
    try:
        runtime = runtime_params(obj)
    except (TypeError, ValueError):
        pytest.skip(f"{qualname}: no signature at runtime (a Python protocol slot)")
    assert stub_params(node) == runtime, qualname
