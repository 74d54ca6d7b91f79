"""A fixed step outside a block's stability region is refused before anything runs, and a
step that leaves a decaying mode unresolved is warned about (fwdstep/structure/stiffness.py).

References: the stability polynomials of the tableaux written out by hand, the real stability
limit of rk4 as the root of z^3 + 4 z^2 + 12 z + 24 (numpy.roots), the exact solutions
exp(-a t) of the diagrams."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

import fwdstep
from fwdstep.cli import arguments as cli
from fwdstep.core.errors import ConfigError, FwdstepWarning
from fwdstep.core.solvers import TABLEAUX, amplification, stable_step

RK4_LIMIT = -max(float(r.real) for r in np.roots([1, 4, 12, 24]) if abs(r.imag) < 1e-12)


def test_stability_polynomials_are_the_textbook_ones():
    z = np.array([-2.5, -1.0 + 0.7j, 0.3j, 0.1])
    np.testing.assert_allclose(amplification(TABLEAUX["euler"], z), 1 + z)
    np.testing.assert_allclose(amplification(TABLEAUX["heun"], z), 1 + z + z ** 2 / 2)
    np.testing.assert_allclose(amplification(TABLEAUX["rk4"], z),
                               1 + z + z ** 2 / 2 + z ** 3 / 6 + z ** 4 / 24)


def test_largest_stable_step_on_the_real_axis():
    assert RK4_LIMIT == pytest.approx(2.785293563405, abs=1e-11)
    assert stable_step(TABLEAUX["rk4"], -1.0) == pytest.approx(RK4_LIMIT, rel=1e-11)
    assert stable_step(TABLEAUX["rk4"], -1000.0) == pytest.approx(RK4_LIMIT / 1000, rel=1e-11)
    assert stable_step(TABLEAUX["euler"], -4.0) == pytest.approx(0.5, rel=1e-11)
    assert stable_step(TABLEAUX["heun"], -4.0) == pytest.approx(0.5, rel=1e-11)
    # rk4 on the imaginary axis: |R(iy)| <= 1 up to y = 2 sqrt(2)
    assert stable_step(TABLEAUX["rk4"], -1e-12 + 1j) == pytest.approx(2 * np.sqrt(2), rel=1e-6)


LAG = """\
parameters: {{a: {a}}}
blocks:
  u: {{type: Constant, value: 0.0}}
  f: {{type: TransferFunction, num: [1], den: [1, a], initial: [1.0]}}
connections:
  - u.y -> f.u
simulation: {{t_final: {t_final}, step: {step}{extra}}}
"""


def _lag(tmp_path, a, step, t_final=None, extra=""):
    path = tmp_path / "lag.yaml"
    t_final = t_final or repr(100 * float(step))
    path.write_text(LAG.format(a=a, step=step, t_final=t_final, extra=extra))
    return str(path)


@pytest.mark.parametrize("solver, limit", [("rk4", RK4_LIMIT), ("heun", 2.0), ("euler", 2.0)])
def test_refused_just_beyond_the_analytic_limit_accepted_just_inside(tmp_path, solver, limit):
    a = 100.0
    inside = _lag(tmp_path, a, f"{0.999 * limit / a!r}", extra=f", solver: {solver}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FwdstepWarning)      # unresolved, but stable
        res = fwdstep.simulate(fwdstep.load_diagram(inside))
    assert np.abs(res["f.y"][-1]) < 1.0                       # decays, as exp(-a t) does
    beyond = _lag(tmp_path, a, f"{1.001 * limit / a!r}", extra=f", solver: {solver}")
    with pytest.raises(ConfigError) as info:
        fwdstep.load_diagram(beyond)
    msg = str(info.value)
    assert msg.startswith(f"{beyond}:4: block 'f' (TransferFunction) has eigenvalue -100: "
                          f"with solver {solver} and step ")
    assert f"the largest stable step is {limit / a:.4g}." in msg
    assert "solver radau" in msg and "simulation.stability_check: false" in msg


def test_the_issues_lag_is_warned_with_the_numbers(tmp_path):
    """1/(p + 270) under rk4 at h = 0.01: stable (h lambda = -2.7 > -2.785) but its mode
    decays by |R(-2.7)| = 0.879 per step instead of exp(-2.7) = 0.067."""
    path = _lag(tmp_path, 270, 0.01, t_final=0.1)
    with pytest.warns(FwdstepWarning) as caught:
        d = fwdstep.load_diagram(path)
    text = str(caught[0].message)
    assert text.startswith(f"{path}:4: block 'f' (TransferFunction) has eigenvalue -270: "
                           "with solver rk4 and step 0.01 (h*lambda = -2.7)")
    assert "decays at 12.92/s instead of 270/s" in text
    # the step it proposes does resolve the mode: |R| <= exp(h Re lambda / 2)
    h = float(text.split("a step of at most ")[1].split()[0])
    assert abs(complex(amplification(TABLEAUX["rk4"], -270 * h))) <= np.exp(-270 * h / 2) + 1e-4
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        y = fwdstep.simulate(fwdstep.load_diagram(_lag(tmp_path, 270, 0.001, t_final=0.1)))
    assert y["f.y"][-1] == pytest.approx(np.exp(-27.0), rel=1e-3)
    assert fwdstep.simulate(d)["f.y"][-1] > 0.27                # what the warning is about


RATE = """\
blocks:
  u: {{type: Constant, value: 1.0}}
  r: {{type: RateLimiter, rising: 2.0}}
connections:
  - u.y -> r.u
simulation: {{t_final: {t_final}, step: {step}}}
"""


def test_rate_limiter_default_time_constant(tmp_path, capsys):
    """T = 1e-3: its lag's eigenvalue is -1000, rk4 is stable up to h = 2.785e-3."""
    path = tmp_path / "rate.yaml"
    path.write_text(RATE.format(t_final=2.8, step=2.8e-3))
    code = cli.main(["validate", str(path)])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith(f"fwdstep: {path}:3: block 'r' (RateLimiter) has "
                                        "eigenvalue -1000: with solver rk4 and step 0.0028")
    assert "the largest stable step is 0.002785." in err
    code = cli.main(["run", str(path), "-o", str(tmp_path / "o"), "--no-plots", "-q",
                     "--set", "simulation.stability_check=false"])
    assert code != 2                                   # the escape hatch runs it anyway
    path.write_text(RATE.format(t_final=2.0, step=1e-3))
    res = fwdstep.simulate(fwdstep.load_diagram(str(path)))
    assert res["r.y"][-1] == pytest.approx(1.0, abs=1e-9)   # the ramp reaches u and stays


def test_a_batch_names_the_variant_that_is_refused(tmp_path):
    from fwdstep.structure.compiler import compile_batch
    from fwdstep.structure.spec import load_spec
    path = _lag(tmp_path, 1.0, 0.01)
    specs = [load_spec(path, {"a": a}) for a in (1.0, 10.0, 400.0)]
    with pytest.raises(ConfigError, match=r"has eigenvalue -400 \(variant 2: a = 400"):
        compile_batch(specs)


def test_adaptive_solvers_and_growing_modes_are_not_checked(tmp_path):
    fwdstep.load_diagram(_lag(tmp_path, 1e6, 0.01, extra=", solver: radau"))
    fwdstep.load_diagram(_lag(tmp_path, -500.0, 0.01))    # 1/(p - 500): grows anyway


def test_the_setting_must_be_a_boolean(tmp_path):
    with pytest.raises(ConfigError, match="simulation.stability_check must be true or false"):
        fwdstep.load_diagram(_lag(tmp_path, 1.0, 0.01, extra=", stability_check: 0"))


def test_a_large_filter_bank_is_checked_quickly(tmp_path):
    """kron(I_300, A): 900 states split into 300 equal 3x3 blocks, solved once."""
    import time
    from fwdstep.core.linear import matrix_eigenvalues
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-6.0, -11.0, -6.0]])   # roots -1, -2, -3
    big = np.kron(np.eye(300), A)[None]
    matrix_eigenvalues(np.kron(np.eye(12), A)[None])        # scipy's import, once
    t0 = time.perf_counter()
    ev = matrix_eigenvalues(big)
    assert time.perf_counter() - t0 < 0.5
    np.testing.assert_allclose(np.sort(ev[0].real), np.repeat([-3.0, -2.0, -1.0], 300),
                               atol=1e-9)
