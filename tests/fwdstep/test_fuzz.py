"""Property-based fuzzing: whatever the diagram, fwdstep either runs it or raises its own error.

Two generators: random wiring of library blocks with random parameters, and random mutations
of the shipped diagrams (deleted keys, swapped ports, wrong shapes, random scalars, changed
types, renamed blocks).  Every example is loaded, validated, compiled and simulated for a few
steps; the only acceptable exception is ``fwdstep.core.errors.FwdstepError``, and each example is
bounded by a wall-clock alarm, so a hang fails the test instead of stalling CI.

Budget: ``FWDSTEP_FUZZ_EXAMPLES`` examples per generator (default 100, about 20 s in all);
``FWDSTEP_FUZZ_REPORT=FILE`` appends every outcome and error message to FILE.

The default run draws the same examples every time (``derandomize``), so the suite gives the
same verdict on every machine; ``FWDSTEP_FUZZ_EXPLORE=1`` draws new ones on each run (how the
overflowing Sine frequency of tests/blocks/test_sources.py was found) — run it with many
examples when changing a block or the loader.
"""
from __future__ import annotations

import copy
import os
import shutil
import signal
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from fwdstep.structure.compiler import compile_spec
from fwdstep.core.errors import FwdstepError
from fwdstep.structure.graph import instantiate
from fwdstep.structure.library import load_library
from fwdstep.run.simulate import simulate
from fwdstep.structure.spec import load_spec

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = int(os.environ.get("FWDSTEP_FUZZ_EXAMPLES", "100"))
REPORT = os.environ.get("FWDSTEP_FUZZ_REPORT")       # file to append every outcome to
EXAMPLE_SECONDS = 20          # wall-clock limit of one example (load + compile + run)
MAX_STEPS = 40                # simulated steps per example

FUZZ = settings(max_examples=EXAMPLES, deadline=None, database=None, print_blob=True,
                suppress_health_check=list(HealthCheck),
                derandomize=not os.environ.get("FWDSTEP_FUZZ_EXPLORE"))

LIBRARY = {name: cls for name, cls in sorted(load_library().items())
           if cls.__module__.startswith("fwdstep.blocks.")}


class ExampleHung(BaseException):
    """Raised by the alarm; a BaseException so that nothing in fwdstep can swallow it."""


class alarm:
    def __init__(self, seconds: float):
        self.seconds = seconds

    def _ring(self, signum, frame):
        raise ExampleHung(f"example took more than {self.seconds} s")

    def __enter__(self):
        self.old = signal.signal(signal.SIGALRM, self._ring)
        signal.setitimer(signal.ITIMER_REAL, self.seconds)

    def __exit__(self, *exc):
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, self.old)
        return False


def note(text: str, detail: str = "") -> None:
    if REPORT:
        with open(REPORT, "a") as fh:
            fh.write(f"{text}\t{detail}\n")
    try:
        event(text)
    except Exception:  # noqa: BLE001 - outside a hypothesis test there is nothing to note
        pass


def run_briefly(path: str) -> str:
    """Load, compile and simulate at most MAX_STEPS steps.  Returns what happened; any
    exception other than FwdstepError propagates and fails the test."""
    with alarm(EXAMPLE_SECONDS):
        try:
            spec = load_spec(path)
            cfg = spec.simulation
            cfg.t_final = cfg.step * min(cfg.n_steps, MAX_STEPS)
            result = simulate(compile_spec(spec))
        except FwdstepError as exc:
            assert str(exc) and "\n" not in str(exc), repr(exc)
            note(f"outcome: {type(exc).__name__}", str(exc))
            return type(exc).__name__
        assert len(result.t) >= 1
        note("outcome: ran")
        return "ran"


# ------------------------------------------------------------------ random values
EXPRESSIONS = ["eye(2)", "2*pi", "zeros(3)", "ones(2, 2)", "alpha", "1/0", "[1, 2", "eq2",
               "eq29", "+-", "++-", "", "-1", "sqrt(-1)", "10**10**10", "diag([1, 2])",
               "__import__('os')", "1e400", "x.y", "[1, [2]]"]
scalars = st.one_of(
    st.integers(-3, 8),
    st.floats(-1e3, 1e3, allow_nan=False),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, 1, 2, 10 ** 9, -10 ** 9, 10 ** 30, 1e-300, 0.5]),
    st.booleans(),
    st.none(),
    st.sampled_from(EXPRESSIONS),
)
small_numbers = st.one_of(st.integers(-2, 5), st.floats(-10, 10, allow_nan=False))
values = st.one_of(
    scalars,
    st.lists(small_numbers, max_size=5),
    st.lists(st.lists(small_numbers, min_size=1, max_size=4), min_size=1, max_size=4),
    st.lists(st.integers(0, 4), min_size=0, max_size=3),                   # shapes
    st.lists(scalars, max_size=3),
    st.dictionaries(st.sampled_from(["a", "b", "type"]), scalars, max_size=2),
)


# ------------------------------------------------------------------ generator 1: random wiring
@st.composite
def block_params(draw, cls, clean: bool) -> dict:
    if clean or draw(st.integers(0, 2)):          # else two blocks in three are valid
        return copy.deepcopy(cls.example)
    params = {}
    for key, decl in cls.params.items():
        choice = draw(st.sampled_from(["example", "example", "example", "random", "omit"]))
        if choice == "example" and key in cls.example:
            params[key] = copy.deepcopy(cls.example[key])
        elif choice == "random":
            if decl.kind == "choice" and draw(st.booleans()):
                params[key] = draw(st.sampled_from(decl.choices))
            else:
                params[key] = draw(values)
    if draw(st.integers(0, 9)) == 0:
        params[draw(st.sampled_from(["gian", "shape", "n", "type2"]))] = draw(scalars)
    return params


def plain(value):
    """numpy -> plain Python, for yaml.safe_dump."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, np.generic):
        return value.item()
    return value


def dump(doc: dict, directory: str, name: str = "fuzz.yaml") -> str:
    path = os.path.join(directory, name)
    with open(path, "w") as fh:
        yaml.safe_dump(plain(doc), fh, sort_keys=False)
    return path


@given(data=st.data())
@FUZZ
def test_random_wiring_runs_or_fails_cleanly(data):
    n_blocks = data.draw(st.integers(1, 6), label="blocks")
    clean = data.draw(st.booleans(), label="clean parameters")
    blocks = {}
    for i in range(n_blocks):
        type_name = data.draw(st.sampled_from(sorted(LIBRARY)), label="type")
        blocks[f"b{i}"] = {"type": type_name,
                           **data.draw(block_params(LIBRARY[type_name], clean))}
    doc = {"parameters": {"alpha": data.draw(st.one_of(st.just(2.0), scalars), label="alpha")},
           "blocks": blocks,
           "simulation": {"t_final": 0.02, "step": 0.001,
                          "solver": data.draw(st.sampled_from(["euler", "heun", "rk4"]))}}
    with tempfile.TemporaryDirectory() as tmp:
        path = dump(doc, tmp)
        try:                                  # learn the ports, if the blocks can be built
            with alarm(EXAMPLE_SECONDS):
                built = instantiate(load_spec(path))
        except FwdstepError:
            run_briefly(path)                 # the full pipeline must fail cleanly as well
            return
        outputs = [(b.name, p.name, p.shape) for b in built for p in b.outputs.values()]
        connections = []
        for blk in built:
            for port in blk.inputs.values():
                if data.draw(st.integers(0, 19), label="leave open") == 0:
                    continue
                same = [o for o in outputs if o[2] == port.shape]
                if not same or not data.draw(st.integers(0, 3), label="new source"):
                    # a source of the right shape, so most diagrams get past validation
                    name = f"c{len(blocks)}"
                    value = np.full(port.shape, data.draw(small_numbers, label="value"))
                    blocks[name] = {"type": "Constant", "value": value}
                    same = [(name, "y", port.shape)]
                pool = same if data.draw(st.integers(0, 19)) else outputs or same
                src = data.draw(st.sampled_from(pool), label="source")
                connections.append(f"{src[0]}.{src[1]} -> {blk.name}.{port.name}")
        if connections and data.draw(st.integers(0, 9), label="corrupt") == 0:
            k = data.draw(st.integers(0, len(connections) - 1))
            connections.append(data.draw(st.sampled_from([
                connections[k],                                          # driven twice
                connections[k].replace(" -> ", " -> nowhere."),
                connections[k].split(" -> ")[1] + " -> " + connections[k].split(" -> ")[0],
                connections[k].replace(".", ".x", 1),
            ])))
        doc["connections"] = connections
        if outputs and data.draw(st.booleans(), label="log"):
            src = data.draw(st.sampled_from(outputs))
            doc["log"] = [f"{src[0]}.{src[1]}"]
            doc["metrics"] = {"error": f"{src[0]}.{src[1]}"}
        run_briefly(dump(doc, tmp))


# ------------------------------------------------------------------ generator 2: mutations
SHIPPED = sorted(p.relative_to(REPO / "diagrams").as_posix()
                 for p in (REPO / "diagrams").rglob("*.yaml"))


@pytest.fixture(scope="module")
def shipped_copy():
    """A private copy of diagrams/ (subsystem paths are relative to the diagram file)."""
    tmp = tempfile.mkdtemp(prefix="fwdstep-fuzz-")
    shutil.copytree(REPO / "diagrams", os.path.join(tmp, "diagrams"))
    yield os.path.join(tmp, "diagrams")
    shutil.rmtree(tmp, ignore_errors=True)


def locations(node, path=()):
    """Every (container, key) in a parsed YAML document."""
    items = node.items() if isinstance(node, dict) else \
        enumerate(node) if isinstance(node, list) else ()
    for key, value in items:
        yield node, key
        yield from locations(value, path + (key,))


def swap_ports(doc, draw) -> None:
    if not isinstance(doc.get("connections"), list):
        return
    conns = [c for c in doc["connections"] if isinstance(c, str) and "->" in c]
    if not conns:
        return
    c = draw(st.sampled_from(conns))
    i = doc["connections"].index(c)
    src, dsts = c.split("->", 1)
    dst = dsts.split(",")
    how = draw(st.sampled_from(["reverse", "swap-names", "other-port"]))
    if how == "reverse":
        doc["connections"][i] = f"{dst[0].strip()} -> {src.strip()}"
    elif how == "swap-names" and len(conns) > 1:
        other = draw(st.sampled_from(conns))
        j = doc["connections"].index(other)
        doc["connections"][i], doc["connections"][j] = (
            other.split("->")[0] + "->" + dsts, src + "->" + other.split("->", 1)[1])
    else:
        block, _, port = dst[0].strip().rpartition(".")
        doc["connections"][i] = f"{src.strip()} -> {block}.{draw(st.sampled_from(['u', 'q', 'y', 'tau', port + 'x']))}"


def wrong_shape(value, draw):
    if isinstance(value, list) and value:
        how = draw(st.sampled_from(["shorter", "longer", "nest", "flatten"]))
        if how == "shorter":
            return value[:-1]
        if how == "longer":
            return value + [value[-1]]
        if how == "nest":
            return [value, value]
        return value[0]
    return draw(st.sampled_from([[1, 2, 3], [[1, 0], [0, 1], [1, 1]], [], [[]]]))


def mutate(doc, draw) -> None:
    how = draw(st.sampled_from(["delete", "scalar", "swap", "shape", "type", "rename",
                                "drop-connection", "duplicate-connection", "parameter",
                                "parameter"]), label="mutation")
    spots = list(locations(doc))
    blocks = doc.get("blocks") if isinstance(doc.get("blocks"), dict) else {}
    params = doc.get("parameters") if isinstance(doc.get("parameters"), dict) else {}
    numeric = [k for k, v in params.items() if isinstance(v, (int, float))
               and not isinstance(v, bool)]
    if how == "parameter" and numeric:           # a plausible value: the diagram may well run
        key = draw(st.sampled_from(numeric))
        params[key] = params[key] * draw(st.sampled_from([-1, 0, 0.5, 2, 10, 1e3, 1e8]))
    elif how == "delete" and spots:
        container, key = draw(st.sampled_from(spots))
        del container[key]
    elif how == "scalar" and spots:
        container, key = draw(st.sampled_from(spots))
        container[key] = draw(values)
    elif how == "swap":
        swap_ports(doc, draw)
    elif how == "shape":
        lists = [(c, k) for c, k in spots if isinstance(c[k], list)]
        if lists:
            container, key = draw(st.sampled_from(lists))
            container[key] = wrong_shape(container[key], draw)
    elif how == "type" and blocks:
        name = draw(st.sampled_from(sorted(blocks)))
        if isinstance(blocks[name], dict):
            blocks[name]["type"] = draw(st.sampled_from(sorted(LIBRARY) + ["subsystem"]))
    elif how == "rename" and blocks:
        name = draw(st.sampled_from(sorted(blocks)))
        blocks[name + "x"] = blocks.pop(name)
    elif how in ("drop-connection", "duplicate-connection") and doc.get("connections"):
        conns = doc["connections"]
        if isinstance(conns, list) and conns:
            k = draw(st.integers(0, len(conns) - 1))
            if how == "drop-connection":
                del conns[k]
            else:
                conns.append(conns[k])


@pytest.mark.skipif(not SHIPPED, reason="no shipped diagrams in diagrams/ yet")
@given(data=st.data())
@FUZZ
def test_mutated_shipped_diagrams_run_or_fail_cleanly(shipped_copy, data):
    name = data.draw(st.sampled_from(SHIPPED), label="diagram")
    with open(os.path.join(shipped_copy, name)) as fh:
        doc = yaml.safe_load(fh)
    for _ in range(data.draw(st.integers(1, 3), label="mutations")):
        if isinstance(doc, dict):
            mutate(doc, data.draw)
    directory = os.path.dirname(os.path.join(shipped_copy, name))
    path = dump(doc, directory, f".fuzz-{os.getpid()}.yaml")
    try:
        run_briefly(path)
    finally:
        os.unlink(path)


@pytest.mark.skipif(not SHIPPED, reason="no shipped diagrams in diagrams/ yet")
def test_unmutated_shipped_diagrams_pass_through_the_fuzz_harness(shipped_copy):
    """The harness itself: each shipped top-level diagram runs for a few steps (the robot
    diagrams only where pinocchio, the ``robots`` extra, is installed)."""
    import importlib.util
    robots = importlib.util.find_spec("pinocchio") is not None
    for name in SHIPPED:
        if not name.startswith("lib/") and (robots or not name.startswith("robots/")):
            assert run_briefly(os.path.join(shipped_copy, name)) == "ran", name
