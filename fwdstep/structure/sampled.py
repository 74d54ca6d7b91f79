"""Sampled subsystems: ``sample_period: T`` on a subsystem runs it as a digital controller.

    ctrl: {type: subsystem, file: lib/pd.yaml, sample_period: 1.0e-3, sample_offset: 0}

is expanded (in ``fwdstep.structure.spec``) into the subsystem's blocks plus one ZeroOrderHold on
each of its inputs (named ``ctrl/sample_<port>``) and one on each of its outputs
(``ctrl/hold_<port>``), all with that period and offset.  Semantics (docs/discrete-time.md):

* at each sample instant t_k the subsystem's inputs are sampled, u_k = u(t_k); its outputs
  are computed from u_k and its state at t_k and held until t_{k+1};
* between samples the subsystem's own continuous states (filters, reference dynamics)
  still evolve, driven by the held inputs - for a linear controller this is exactly its
  zero-order-hold discretisation (scipy.signal.cont2discrete(..., method='zoh'));
* the plant and everything outside are integrated continuously, with steps ending at
  every t_k (fwdstep.run.events).

``sample_period: 0`` (also ``--set ctrl.sample_period=0``) runs the subsystem continuously,
as if it had no sample period: the comparison of a digital controller with its analog
design is one option away.
"""
from __future__ import annotations

from fwdstep.core.errors import ConfigError, DiagramError
from fwdstep.structure.library import lookup
from fwdstep.structure.model import BlockEntry, Connection, _line, evaluate_value


def sample_subsystem(level, name: str, body, file: str, line) -> None:
    """Insert the holds of subsystem ``name`` (already expanded into ``level``)."""

    full = level.full(name)
    values = {}
    for key, param in (("sample_period", "period"), ("sample_offset", "offset")):
        if key in body:
            try:
                level.uses(body[key])
                values[param] = evaluate_value(body[key], level.ns, f"subsystem '{full}' {key}")
            except DiagramError as exc:
                raise exc.located(file, _line(body, key)) from None
            if not isinstance(values[param], float):
                raise ConfigError(f"subsystem '{full}' {key} must be a number of seconds, got "
                                  f"{body[key]!r}", file=file, line=_line(body, key))
    if values.get("period") == 0.0:      # sample_period: 0 -- run it continuously
        return
    if not values.get("period", 0.0) > 0:
        raise ConfigError(f"subsystem '{full}' sample_period must be positive, or 0 to run it "
                          "continuously", file=file, line=_line(body, "sample_period"))
    level.sampled[full] = {"period": values["period"], "offset": values.get("offset", 0.0)}
    hold = lookup("ZeroOrderHold")
    entries = {b.name: b for b in level.blocks}

    def add_hold(hname: str) -> None:
        """A ZeroOrderHold whose shape the wiring fixes (fwdstep.structure.shapes)."""
        if hname in entries:
            raise ConfigError(f"subsystem '{full}' has a block named '{hname.rsplit('/', 1)[1]}'"
                              f", the name of its sample-and-hold; rename that block",
                              file=file, line=line)
        level.budget.add_block(hname, file, line)
        level.blocks.append(BlockEntry(hname, "ZeroOrderHold", hold, dict(values), file, line))
        entries[hname] = level.blocks[-1]

    for pname, targets in level.sub_inputs[name].items():
        if not targets:
            continue
        hname = f"{full}/sample_{pname}"
        add_hold(hname)
        for target in targets:
            level.connections.append(Connection((hname, "y"), target, file, line,
                                                f"{full}.{pname} (sampled)"))
        level.sub_inputs[name][pname] = [(hname, "u")]
        level.input_ports[(hname, "u")] = (f"{full}.{pname}", file, line)
    for pname, src in level.sub_outputs[name].items():
        hname = f"{full}/hold_{pname}"
        add_hold(hname)
        level.connections.append(Connection(src, (hname, "u"), file, line,
                                            f"{full}.{pname} (held)"))
        level.sub_outputs[name][pname] = (hname, "y")
        level.aliases[f"{full}.{pname}"] = f"{hname}.y"
