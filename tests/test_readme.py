"""The README's quickstart code runs as written against the installed package, and does what its
comments say (the estimates end near the truth)."""

import pathlib
import re

import numpy as np

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"^```python\n(.*?)^```", README.read_text(encoding="utf-8"), re.S | re.M)
QUICKSTARTS = [b for b in BLOCKS if "import" in b]


def _run(block):
    namespace = {"__name__": "__readme__"}
    exec(compile(block, str(README), "exec"), namespace)
    return namespace


def test_readme_has_the_three_quickstarts():
    names = [re.search(r"from gpmhe import ([\w, ]+)", b).group(1) for b in QUICKSTARTS]
    assert names == ["GPMHE, LearnedModel", "GPMHE, KnownModel", "RGPEKF, RecursiveGP"]


def test_learned_model_quickstart_converges():
    ns = _run(QUICKSTARTS[0])
    assert ns["est"].t == 100
    assert np.linalg.norm(ns["est"].x - ns["x_true"][100]) < 0.5


def test_known_model_quickstart_tracks_the_plant():
    ns = _run(QUICKSTARTS[1])
    x_prev = ns["x"]  # the loop leaves x = x(50); est.x is x̂(49) in the filtering form
    u = np.array([0.6])
    # x̂(49) mapped one step ahead through the model is close to x(50)
    assert np.linalg.norm(ns["f"](ns["est"].x, u) - x_prev) < 0.1


def test_rgp_quickstart_learns_the_disturbance():
    ns = _run(QUICKSTARTS[2])
    err = np.max(np.abs(ns["mean"] - ns["so"].disturbance(ns["zeta"])))
    assert err < 0.5   # z spans about -28 ... 8 on this range
    assert np.all(ns["std"] > 0)

