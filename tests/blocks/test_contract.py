"""Contract test over every registered block (python-control's kwargs/docstring tests in spirit).

For each block type, built from its ``example`` parameters:
* the docstring's port table lists exactly the declared ports, with their directions;
* outputs and derivative have the declared shapes, for a single run and for a batch of 3;
* per-output feedthrough is honoured: perturbing an input outside an output's feedthrough set
  leaves that output unchanged;
* unknown parameters are refused with a message listing the valid ones;
* output() is pure: the same call twice gives the same values and inputs are not modified.
"""
import re

import numpy as np
import pytest

from fwdstep.core.errors import ParameterError
from fwdstep.structure.library import load_library

REGISTRY = load_library()
NAMES = sorted(REGISTRY)


def _port_rows(doc: str):
    rows = {}
    for line in doc.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if not line.strip().startswith("|") or len(cells) < 3:
            continue
        name, direction = cells[0], cells[1].lower()
        if name.lower() == "port" or set(name) <= set("-: "):
            continue
        rows[name] = direction
    return rows


def _needs_extra(name) -> bool:
    """A block whose optional extra is not installed says so in its summary
    ("... [install fwdstep[robots]]") and refuses to be built; its contract is tested where the
    extra is installed (CI installs every extra)."""
    return "[install fwdstep[" in REGISTRY[name].summary()


#: the blocks that can be built here
AVAILABLE = [name for name in NAMES if not _needs_extra(name)]


def _make(name):
    if _needs_extra(name):
        pytest.skip(f"{name}: {REGISTRY[name].summary()}")
    cls = REGISTRY[name]
    return cls("example", **cls.example)


def _inputs(blk, B, rng):
    return tuple(rng.standard_normal((B,) + p.shape) for p in blk.inputs.values())


def _state(blk, B, rng):
    return rng.standard_normal((B, blk.n_states)) * 0.1


def test_registry_is_not_empty():
    for required in ("Constant", "Step", "Sine", "Polynomial", "Gain", "Sum", "Integrator",
                     "TransferFunction", "StateSpace", "Product", "TwoLinkArm", "Regressor",
                     "AdaptationLaw", "ReferenceDynamics"):
        assert required in REGISTRY


@pytest.mark.parametrize("name", NAMES)
def test_docstring_port_table_matches_declared_ports(name):
    blk = _make(name)
    doc = REGISTRY[name].__doc__ or ""
    assert doc.strip().splitlines()[0].strip(), "first docstring line is the summary"
    rows = _port_rows(doc)
    declared = {**{p: "in" for p in blk.inputs}, **{p: "out" for p in blk.outputs}}
    # ports whose names depend on parameters (u1..uN, y_d1..) may be documented by pattern
    for port, direction in declared.items():
        documented = rows.get(port) or next(
            (d for pat, d in rows.items() if re.fullmatch(
                re.sub(r"[kKNnmi]\b|\\{.*?\\}|<.*?>|\{.*?\}", r"\\d+", re.escape(pat)), port)),
            None)
        assert documented is not None, f"{name}: port '{port}' missing from the docstring table"
        assert documented.startswith(direction), (name, port, documented, direction)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("B", [1, 3])
def test_shapes_of_output_and_derivative(name, B):
    rng = np.random.default_rng(0)
    blk = _make(name)
    u = _inputs(blk, B, rng)
    x = _state(blk, B, rng)
    outs = blk.output(0.3, x, u)
    assert len(outs) == len(blk.outputs)
    for y, port in zip(outs, blk.outputs.values()):
        y = np.asarray(y)
        assert np.broadcast_shapes(y.shape, (B,) + port.shape) == (B,) + port.shape, \
            (name, port.name, y.shape)
    if blk.n_states:
        dx = blk.derivative(0.3, x, u)
        assert dx.shape == (B, blk.n_states)
        assert np.all(np.isfinite(dx))


@pytest.mark.parametrize("name", NAMES)
def test_feedthrough_is_honoured(name):
    rng = np.random.default_rng(1)
    blk = _make(name)
    u = _inputs(blk, 2, rng)
    x = _state(blk, 2, rng)
    base = blk.output(0.1, x, u)
    in_names = list(blk.inputs)
    for j, inp in enumerate(in_names):
        bumped = list(u)
        bumped[j] = u[j] + rng.standard_normal(u[j].shape)
        outs = blk.output(0.1, x, tuple(bumped))
        for k, out in enumerate(blk.outputs):
            if inp not in blk.feedthrough(out):
                assert np.array_equal(np.broadcast_to(outs[k], np.shape(base[k])), base[k]), \
                    f"{name}: output '{out}' changed with input '{inp}' outside its feedthrough"


@pytest.mark.parametrize("name", NAMES)
def test_output_is_pure(name):
    rng = np.random.default_rng(2)
    blk = _make(name)
    u = _inputs(blk, 2, rng)
    x = _state(blk, 2, rng)
    u_copy = tuple(a.copy() for a in u)
    x_copy = x.copy()
    a = blk.output(0.2, x, u)
    b = blk.output(0.2, x, u)
    for ya, yb in zip(a, b):
        assert np.array_equal(ya, yb)
    assert all(np.array_equal(p, q) for p, q in zip(u, u_copy))
    assert np.array_equal(x, x_copy)


@pytest.mark.parametrize("name", NAMES)
def test_unknown_parameter_is_refused(name):
    cls = REGISTRY[name]
    with pytest.raises(ParameterError) as info:
        cls("b", **cls.example, no_such_parameter=1)
    msg = str(info.value)
    assert "no parameter 'no_such_parameter'" in msg
    for key in cls.params:
        assert key in msg


# ---------------------------------------------------------------- one definition, two paths
def _compiled_kernel_names():
    """Blocks with kernels that may run compiled (linear blocks run compiled through their
    LinearForm, fused; see tests/diagrams for those)."""
    out = []
    for name in AVAILABLE:
        blk = _make(name)
        if blk.kernels is not None and not REGISTRY[name].cannot_compile:
            out.append(name)
    return out


def test_every_block_can_run_compiled_or_says_why():
    """No list of blocks with a kernel: each block declares kernels, is linear (fused from
    its LinearForm) or names its reason."""
    pytest.importorskip("numba")
    from fwdstep.compiled import backend_numba
    for name in AVAILABLE:
        blk = _make(name)
        reason = backend_numba.refusal(blk)
        assert reason is None or REGISTRY[name].cannot_compile == reason, (name, reason)


def _strided(a):
    """The values of ``a`` in a non-contiguous view (every other element of the last axis)."""
    if a.ndim == 0 or a.size == 0:
        return a
    wide = np.zeros(a.shape[:-1] + (2 * a.shape[-1],))
    wide[..., ::2] = a
    out = wide[..., ::2]
    assert not out.flags.c_contiguous
    return out


@pytest.mark.slow            # jits every kernel (minutes on a loaded 2-core machine)
@pytest.mark.parametrize("name", _compiled_kernel_names())
def test_numpy_and_compiled_kernels_agree(name):
    """The NumPy path (the kernel as a NumPy function) and the compiled path (the same
    function jitted, called one variant at a time as the generated loop does) give the same
    outputs and derivatives at random points, to 1e-12."""
    pytest.importorskip("numba")
    from fwdstep.compiled import backend_numba
    if REGISTRY[name].compile_with == "traced":
        pytest.skip("kernels the compiled backend traces (fwdstep.compiled.scalarize), never jits")
    rng = np.random.default_rng(3)
    blk = _make(name)
    k = blk.kernels
    for trial in range(2):
        # trial 1: inputs and state as strided views, as the generated loop passes slices of
        # its buffers (numba types those as non-contiguous: no reshape on them)
        # (two variants there, so that no view has a single element and passes as contiguous)
        view = (lambda a: a) if trial == 0 else _strided
        u = tuple(view(np.ascontiguousarray(a)) for a in _inputs(blk, 1 + trial, rng))
        x = view(_state(blk, 1 + trial, rng))
        t = float(rng.uniform(0.0, 2.0))
        args = tuple(np.ascontiguousarray(a, dtype=float) if isinstance(a, np.ndarray) else a
                     for a in blk.kernel_args())
        ins = (u,) if k.tuple_inputs else u
        if k.output is not None:
            ref = blk.output(t, x, u)
            got = backend_numba.jit_kernel(k.output)[0](t, x, *ins, *args)
            if k.packed:
                got = tuple(got[:, a:b] if shape is None else
                            got[:, a:b].reshape((got.shape[0],) + shape)
                            for a, b, shape in blk._unpack)
            assert len(got) == len(ref)
            for g, r in zip(got, ref):
                scale = max(1.0, float(np.max(np.abs(r)))) if np.size(r) else 1.0
                np.testing.assert_allclose(np.asarray(g), np.broadcast_to(r, np.shape(g)),
                                           rtol=0, atol=1e-12 * scale, err_msg=name)
        if blk.n_states and k.derivative is not None:
            ref = blk.derivative(t, x, u)
            got = backend_numba.jit_kernel(k.derivative)[0](t, x, *ins, *args)
            scale = max(1.0, float(np.max(np.abs(ref))))
            np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * scale, err_msg=name)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("batch", [1, 3])
def test_finalize_sets_only_its_declared_attributes(name, batch):
    """``finalize`` may set only the class's ``finalize_attributes``: the compiler batches
    variants by every other attribute a block keeps (fwdstep.structure.compiler.setup_state),
    so an undeclared one would be taken from the first variant for all of them."""
    import copy
    from types import SimpleNamespace
    blk = _make(name)
    assigned: set = set()

    class Recording(type(blk)):
        def __setattr__(self, key, value):
            assigned.add(key)
            object.__setattr__(self, key, value)

    probe = copy.copy(blk)
    probe.p = SimpleNamespace(**vars(blk.p))
    probe.__class__ = Recording
    probe.finalize(batch)
    assert assigned <= set(type(blk).finalize_attributes), sorted(assigned)
