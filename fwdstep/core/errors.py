"""One exception hierarchy, split by phase.

Load/validation errors (``DiagramError`` and subclasses) say *where*: the file, the line
when known, the block and the port.  Run-time errors (``SimulationError`` and subclasses)
say *when*: the time, the block, and the offending values.  The CLI prints ``str(err)``
as one line and exits 2 for a ``DiagramError``; nothing here prints.
"""
from __future__ import annotations


def one_line(text: str) -> str:
    """Messages are one printable line: newlines (from multi-line YAML values) become
    spaces, and every other control, format or escape character is shown escaped
    (``printable``), so no file name or value can repaint the terminal."""
    if "\n" in text or "\r" in text:
        text = " ".join(text.splitlines())
    return printable(text)


def printable(text) -> str:
    """``text`` with every character that is not printable (C0/C1 controls such as ESC and
    BEL, DEL, bidi and zero-width format characters, line separators, U+FFFE, surrogates)
    written as a Python escape (``\\x1b``, ``\\u202e``); other text is unchanged."""
    text = str(text)
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else _escape(c) for c in text)


def _escape(c: str) -> str:
    n = ord(c)
    return f"\\x{n:02x}" if n < 0x100 else f"\\u{n:04x}" if n < 0x10000 else f"\\U{n:08x}"


class FwdstepError(Exception):
    """Base class of every error fwdstep raises on purpose."""


# --------------------------------------------------------------------------- load time
class DiagramError(FwdstepError):
    """A diagram could not be loaded or compiled.

    ``str(err)`` is ``"<file>:<line>: <message>"`` (line omitted when unknown).
    """

    def __init__(self, message: str, file: str | None = None, line: int | None = None,
                 block: str | None = None, port: str | None = None):
        self.message = message
        self.file = file
        self.line = line
        self.block = block
        self.port = port
        super().__init__(self.render())

    def render(self) -> str:
        where = ""
        if self.file:
            where = f"{self.file}:{self.line}: " if self.line else f"{self.file}: "
        return one_line(f"{where}{self.message}")

    def located(self, file: str | None, line: int | None = None) -> "DiagramError":
        """Return this error with the file (and line, if not already known) filled in."""
        if self.file is None and file is not None:
            self.file = file
        if self.line is None and line is not None:
            self.line = line
        self.args = (self.render(),)
        return self

    def __str__(self) -> str:  # keep str() in sync with located()
        return self.render()


class YamlError(DiagramError):
    """The file is not acceptable YAML (syntax, tags, duplicate keys, size, aliases)."""


class ExpressionError(DiagramError):
    """A parameter expression is malformed, forbidden, undefined or too large."""


class ParameterError(DiagramError):
    """A block or diagram parameter is unknown, missing, or of the wrong type or shape."""


class UnknownBlockTypeError(DiagramError):
    """A block's ``type:`` is not in the registry."""


class WiringError(DiagramError):
    """A connection names an unknown block or port, an input is unconnected or driven twice."""


class ShapeError(DiagramError):
    """Connected ports have different shapes."""


class AlgebraicLoopError(DiagramError):
    """The diagram has a cycle of direct-feedthrough ports."""


class ConfigError(DiagramError):
    """``simulation:``, ``log:``, ``plots:``, ``metrics:`` or an override is invalid."""


class OutputError(FwdstepError):
    """Results cannot be written where asked (exists without --force, or escapes OUTDIR)."""


class DamagedFileError(OutputError):
    """A result file fwdstep reads back (result.npz, summary.json, a sweep's part) is
    truncated, corrupt or not what fwdstep writes; the message names it."""


# --------------------------------------------------------------------------- run time
class SimulationError(FwdstepError):
    """Something went wrong while integrating; ``result`` holds everything up to ``time``."""

    def __init__(self, message: str, time: float | None = None, block: str | None = None,
                 result=None):
        self.time = time
        self.block = block
        self.result = result
        super().__init__(message)


class DivergenceError(SimulationError):
    """A state became NaN/inf or exceeded the configured bound."""


class FwdstepWarning(UserWarning):
    """Something the user should know that does not stop the work (a step that leaves a
    block's fastest mode unresolved).  The CLI prints it as one line
    ``fwdstep: warning: <message>``; through the API it is a Python warning."""


class LimitExceeded(SimulationError):
    """A signal crossed an operating limit declared with ``stop`` (``stop_on_limits``)."""


class BlockRuntimeError(SimulationError):
    """A block's ``output`` or ``derivative`` raised; chained to the original exception."""
