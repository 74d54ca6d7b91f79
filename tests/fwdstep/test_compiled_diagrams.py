"""Every shipped diagram runs on both paths with equal results (issue 10): the NumPy path and
the compiled backend (numba), over a short horizon (``STEPS`` solver steps).

Slow: the first run compiles each diagram's structure (minutes each on a loaded 2-core
machine); later runs load the machine code from the cache directory kept in pytest's cache.
A diagram the compiled backend refuses must say why in one line naming the block (e.g. a
block with ``cannot_compile``, or discontinuity times the compiled loop does not step to yet).
"""
import glob
import os

import numpy as np
import pytest

import fwdstep
from fwdstep.compiler import compile_spec
from fwdstep.errors import ConfigError
from fwdstep.solvers import IVP_METHODS
from fwdstep.spec import load_spec

pytest.importorskip("numba")

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SHIPPED = sorted(glob.glob(os.path.join(ROOT, "diagrams", "*.yaml")))
STEPS = 40


@pytest.fixture(autouse=True)
def cache(request, monkeypatch, tmp_path_factory):
    store = getattr(request.config, "cache", None)
    folder = store.mkdir("fwdstep-numba") if store is not None else \
        tmp_path_factory.getbasetemp() / "fwdstep-numba"
    os.makedirs(folder, exist_ok=True)
    os.chmod(folder, 0o700)
    monkeypatch.setenv("FWDSTEP_CACHE_DIR", str(folder))


@pytest.mark.slow
@pytest.mark.parametrize("path", SHIPPED, ids=os.path.basename)
def test_shipped_diagram_on_both_paths(path):
    spec = load_spec(path)
    sim = spec.simulation
    if sim.solver in IVP_METHODS:
        pytest.skip("scipy solve_ivp solver: NumPy path only")
    sim.t_final = STEPS * sim.step
    d = compile_spec(spec)
    ref = fwdstep.simulate(d, backend="numpy")
    try:
        got = fwdstep.simulate(d, backend="compiled")
    except ConfigError as exc:
        text = str(exc)
        assert "\n" not in text and "backend 'compiled'" in text
        pytest.skip(f"refused in one line: {text}")
    np.testing.assert_array_equal(got.t, ref.t)
    for name in ref.names:
        scale = max(1.0, float(np.nanmax(np.abs(ref[name])))) if np.size(ref[name]) else 1.0
        np.testing.assert_allclose(got[name], ref[name], rtol=0, atol=1e-12 * scale,
                                   err_msg=name)
