"""The recording format (DESIGN section 3): reader, streaming writer, experiments, scan inference.

Format
------
A recording is a UTF-8 CSV file::

    # piezod recording
    # sample_rate_hz: 10000
    t,voltage,position,axis,experiment
    0,-40,-3.2171,x,r80_f1
    0.0001,-39.84,-3.2102,x,r80_f1
    ...

* Lines starting with ``#`` (in column 0) and empty lines are comments; they may
  appear before the header and between data lines. Comment lines before the header
  of the form ``# key: value`` are metadata (:attr:`Recording.metadata`).
* Exactly one header line names the columns, in any order. Required: ``t`` (s, since
  the start of the measurement session, strictly increasing per axis), ``voltage`` (V
  at the piezo), ``position`` (um, sensor). Optional: ``target`` (um, commanded
  position), ``axis`` (``x``/``y``/``z``), ``experiment`` (a label), ``z_voltage`` (V, the
  height channel of a microscope: the z-piezo voltage its z feedback applied at that
  sample; ``piezod image`` makes height images of it). Unknown columns
  are allowed and ignored (:attr:`Recording.ignored_columns`); every data line must
  still have one cell per header column.
* Numbers are finite decimal floats. Labels may not contain ``,``, ``"`` or line
  breaks (no CSV quoting is used or accepted); surrounding blanks are stripped.
* A file without an ``experiment`` column is one experiment. With an ``axis`` column
  rows of several axes may be interleaved (one row per axis and sample time); ``t``
  must increase within each axis and the rows of one experiment (per axis) must be
  contiguous.

Well-known metadata keys (all optional): ``range_um`` (nominal fast-axis scan range,
the image width) and ``overscan`` (extra travel at each turning point as a fraction of
``range_um``, as :class:`piezod.scan.RasterParams`); ``piezod linearity`` uses the
first when there is no ``target`` column and excludes the overscan from its regression.

Crash tolerance
---------------
:class:`RecordingWriter` writes whole lines in one ``write`` and flushes after every
block, so a crash can at worst leave one partial final line without a newline. The
reader accepts an unterminated final line if it parses; if it does not, the error
says so and names the line. ``allow_truncated_tail=True`` drops any unterminated
final line unread (a complete-looking one may still be cut inside a number).
Reopening a file with ``RecordingWriter(..., append=True)`` truncates such a partial
line before appending.

Scan inference
--------------
:func:`infer_scan` finds the turning points of a voltage (or target) waveform with a
Schmitt trigger at 30 % / 70 % of its span, fits a straight line and a half cosine to
every half period, and classifies the waveform as ``triangle``, ``sine``, ``periodic``
(regular back-and-forth motion of another shape, e.g. a corrected scan), ``ramp``,
``constant`` or ``arbitrary``. It returns the line frequency, the turning voltages,
the per-sample direction (+1 trace, -1 retrace) and the number of complete loops.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import IO, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezod.errors import RecordingError

F64 = NDArray[np.float64]

REQUIRED_COLUMNS: tuple[str, ...] = ("t", "voltage", "position")
NUMERIC_COLUMNS: tuple[str, ...] = ("t", "voltage", "position", "target", "z_voltage")
TEXT_COLUMNS: tuple[str, ...] = ("axis", "experiment")
KNOWN_COLUMNS: tuple[str, ...] = NUMERIC_COLUMNS + TEXT_COLUMNS
AXES: tuple[str, ...] = ("x", "y", "z")

#: printf formats of the writer: t to 15 significant digits (0.1 ns after a day), others to 10.
_FORMATS = {"t": "%.15g", "voltage": "%.10g", "position": "%.10g", "target": "%.10g", "z_voltage": "%.10g"}
_META_RE = re.compile(r"^#\s*([A-Za-z_][A-Za-z0-9_.\-]*)\s*:\s*(.*?)\s*$")
_BAD_LABEL_CHARS = re.compile(r"[,\"\r\n]")
_TRUNCATED_HINT = (
    " (the last line has no newline: cut short by a crash while writing? "
    "allow_truncated_tail / --allow-truncated-tail drops it)"
)

ScanKind = Literal["triangle", "sine", "periodic", "ramp", "constant", "arbitrary"]


def _frozen(a: ArrayLike, dtype: type | np.dtype[np.generic]) -> NDArray[np.generic]:
    arr = np.array(a, dtype=dtype)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class Recording:
    """One recording: the columns of a file (or of a synthetic session) and its metadata.

    Attributes
    ----------
    t_s, voltage_v, position_um
        The required columns, shape ``(n,)``.
    target_um
        Commanded position (um) or None.
    z_voltage_v
        The height channel of a microscope (V): the z-piezo voltage the z feedback applied at the
        row's sample (column ``z_voltage``), or None.
    axis
        Axis name per row (``x``/``y``/``z``) or None when the file has no axis column.
    experiment
        Experiment label per row, or None (the whole recording is one experiment).
    metadata
        ``# key: value`` comment lines before the header.
    path
        Source file, for error messages (None for in-memory recordings).
    line_numbers
        1-based file line of every row, or None.
    ignored_columns
        Header columns piezod does not know (kept out of the arrays).
    dropped_tail
        True when the reader dropped an unterminated final line.
    """

    t_s: F64
    voltage_v: F64
    position_um: F64
    target_um: F64 | None = None
    axis: NDArray[np.str_] | None = None
    experiment: NDArray[np.str_] | None = None
    metadata: Mapping[str, str] = field(default_factory=dict)
    path: str | None = None
    line_numbers: NDArray[np.int64] | None = None
    z_voltage_v: F64 | None = None
    ignored_columns: tuple[str, ...] = ()
    dropped_tail: bool = False

    def __post_init__(self) -> None:
        n = np.shape(self.t_s)[0] if np.ndim(self.t_s) == 1 else -1
        set_ = object.__setattr__
        for name in ("t_s", "voltage_v", "position_um", "target_um", "z_voltage_v"):
            value = getattr(self, name)
            if value is None:
                continue
            arr = _frozen(value, np.float64)
            if arr.ndim != 1 or arr.shape[0] != n:
                raise ValueError(
                    f"Recording.{name} must be 1-D with the length of t_s ({n}), got {arr.shape}"
                )
            set_(self, name, arr)
        for name in ("axis", "experiment"):
            value = getattr(self, name)
            if value is None:
                continue
            arr = _frozen(value, np.str_)
            if arr.ndim != 1 or arr.shape[0] != n:
                raise ValueError(
                    f"Recording.{name} must be 1-D with the length of t_s ({n}), got {arr.shape}"
                )
            set_(self, name, arr)
        if self.line_numbers is not None:
            set_(self, "line_numbers", _frozen(self.line_numbers, np.int64))
        set_(self, "metadata", MappingProxyType(dict(self.metadata)))

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def columns(self) -> tuple[str, ...]:
        """The piezod columns present, in canonical order."""
        present = {
            "t": True,
            "voltage": True,
            "position": True,
            "target": self.target_um is not None,
            "z_voltage": self.z_voltage_v is not None,
            "axis": self.axis is not None,
            "experiment": self.experiment is not None,
        }
        return tuple(c for c in KNOWN_COLUMNS if present[c])

    def line_of(self, row: int) -> int | None:
        """The file line of ``row`` (None for in-memory recordings)."""
        return None if self.line_numbers is None else int(self.line_numbers[row])


@dataclass(frozen=True, eq=False)
class Experiment:
    """The rows of one experiment on one axis (a contiguous slice of a recording).

    Attributes
    ----------
    label
        Experiment label (the file name stem when the file has no experiment column).
    axis
        Axis name, or None when the recording has no axis column.
    t_s, voltage_v, position_um, target_um
        The columns of the experiment's rows.
    path, line_numbers, metadata
        Provenance, as in :class:`Recording`.
    """

    label: str
    axis: str | None
    t_s: F64
    voltage_v: F64
    position_um: F64
    target_um: F64 | None = None
    path: str | None = None
    line_numbers: NDArray[np.int64] | None = None
    metadata: Mapping[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def first_line(self) -> int | None:
        """File line of the first row (None for in-memory data)."""
        return None if self.line_numbers is None or len(self) == 0 else int(self.line_numbers[0])

    def scan(self) -> ScanInfo:
        """Infer the scan from the voltage waveform (:func:`infer_scan`)."""
        return infer_scan(self.t_s, self.voltage_v)

    def require_scan(self) -> ScanInfo:
        """The inferred scan, which must be a periodic triangle with at least one complete loop.

        Raises
        ------
        RecordingError
            Naming the file and the experiment's first line otherwise.
        """
        info = self.scan()
        if not info.is_scan:
            raise RecordingError(
                f"experiment {self.describe()}: the voltage is not a periodic triangular scan "
                f"with a complete loop ({info.kind}: {info.reason})",
                self.path,
                self.first_line,
            )
        return info

    def describe(self) -> str:
        """``'label'`` plus the axis, for messages."""
        return repr(self.label) + (f" (axis {self.axis})" if self.axis else "")


# ----------------------------------------------------------------------------------------------- reader


def read_recording(path: str | os.PathLike[str], *, allow_truncated_tail: bool = False) -> Recording:
    """Read a recording CSV file.

    Parameters
    ----------
    path
        The file.
    allow_truncated_tail
        Drop a final line that has no newline (left by a crash while writing)
        instead of parsing it.

    Returns
    -------
    Recording
        The parsed, validated columns with their file line numbers.

    Raises
    ------
    RecordingError
        With ``path:line: reason`` for the first problem: unreadable or non-UTF-8
        file, no header, missing / duplicate column, wrong number of cells,
        non-numeric or non-finite number, bad axis or empty label, ``t`` not strictly
        increasing, non-contiguous experiment, no data rows.
    """
    name = os.fspath(path)
    try:
        raw = Path(name).read_bytes()
    except OSError as exc:
        raise RecordingError(f"cannot read: {exc.strerror or exc}", name) from exc
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise RecordingError(f"not UTF-8 text (byte 0x{raw[exc.start]:02x})", name, line) from exc
    return parse_recording(text, path=name, allow_truncated_tail=allow_truncated_tail)


def parse_recording(text: str, *, path: str | None = None, allow_truncated_tail: bool = False) -> Recording:
    """Parse the text of a recording (see :func:`read_recording`)."""
    if text.startswith("\ufeff"):
        text = text[1:]
    if "\r" in text:
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    if not text.strip():
        raise RecordingError("empty file (no header line)", path, 1)
    terminated = text.endswith("\n")
    lines = text.split("\n")
    if terminated:
        lines.pop()

    metadata: dict[str, str] = {}
    i = 0
    while i < len(lines) and (not lines[i] or lines[i][0] == "#"):
        m = _META_RE.match(lines[i])
        if m:
            metadata[m.group(1)] = m.group(2)
        i += 1
    if i == len(lines):
        raise RecordingError("no header line (only comments)", path, len(lines))
    header_line = i + 1
    names = [c.strip() for c in lines[i].split(",")]
    _check_header(names, path, header_line)

    body = lines[i + 1 :]
    first = header_line + 1
    dropped_tail = False
    unterminated_last = not terminated and len(body) > 0
    if unterminated_last and allow_truncated_tail:
        body.pop()
        dropped_tail = True
        unterminated_last = False
    header_end = sum(len(line) + 1 for line in lines[: i + 1])
    if text.find("#", header_end) >= 0 or text.find("\n\n", header_end - 1) >= 0:
        keep = [k for k, line in enumerate(body) if line and line[0] != "#"]
        body = [body[k] for k in keep]
        line_numbers = np.asarray(keep, dtype=np.int64) + first
    else:
        line_numbers = np.arange(first, first + len(body), dtype=np.int64)
    last_line = len(lines)
    if not body:
        raise RecordingError("no data rows after the header", path, header_line)

    def fail(reason: str, row: int) -> RecordingError:
        line = int(line_numbers[row])
        if unterminated_last and line == last_line:
            reason += _TRUNCATED_HINT
        return RecordingError(reason, path, line)

    ncells = len(names)
    counts = np.fromiter((line.count(",") for line in body), dtype=np.int64, count=len(body))
    bad = np.flatnonzero(counts != ncells - 1)
    if bad.size:
        r = int(bad[0])
        raise fail(
            f"wrong number of cells: {counts[r] + 1}, expected {ncells} (header line {header_line})", r
        )

    num_idx = [names.index(c) for c in NUMERIC_COLUMNS if c in names]
    num_names = [c for c in NUMERIC_COLUMNS if c in names]
    try:
        values = np.loadtxt(body, delimiter=",", usecols=num_idx, dtype=np.float64, ndmin=2, comments=None)
    except ValueError as exc:
        for r, line in enumerate(body):
            cells = line.split(",")
            for c, k in zip(num_names, num_idx, strict=True):
                if not _is_float(cells[k]):
                    raise fail(f"column {c!r}: not a number: {cells[k].strip()!r}", r) from exc
        raise RecordingError(f"cannot parse the numeric columns: {exc}", path) from exc
    finite = np.isfinite(values)
    if not finite.all():
        rr, cc = (int(a[0]) for a in np.nonzero(~finite))
        raise fail(f"column {num_names[cc]!r}: non-finite value {float(values[rr, cc])!r}", rr)
    cols = {c: np.ascontiguousarray(values[:, j]) for j, c in enumerate(num_names)}

    text_cols: dict[str, NDArray[np.str_]] = {}
    txt_names = [c for c in TEXT_COLUMNS if c in names]
    if txt_names:
        txt_idx = [names.index(c) for c in txt_names]
        raw_txt = np.loadtxt(body, delimiter=",", usecols=txt_idx, dtype=str, ndmin=2, comments=None)
        for j, c in enumerate(txt_names):
            text_cols[c] = np.char.strip(raw_txt[:, j])
    if "axis" in text_cols:
        bad = np.flatnonzero(~np.isin(text_cols["axis"], AXES))
        if bad.size:
            r = int(bad[0])
            raise fail(f"column 'axis': {str(text_cols['axis'][r])!r} is not one of x, y, z", r)
    if "experiment" in text_cols:
        bad = np.flatnonzero(np.char.str_len(text_cols["experiment"]) == 0)
        if bad.size:
            raise fail("column 'experiment': empty label", int(bad[0]))

    axis = text_cols.get("axis")
    t = cols["t"]
    groups = [np.arange(t.size)] if axis is None else [np.flatnonzero(axis == a) for a in np.unique(axis)]
    for rows in groups:
        dt = np.diff(t[rows])
        bad = np.flatnonzero(dt <= 0)
        if bad.size:
            r = int(rows[bad[0] + 1])
            prev = float(t[rows[bad[0]]])
            where = f" on axis {axis[r]}" if axis is not None else ""
            raise fail(f"column 't': not strictly increasing{where}: {float(t[r])!r} after {prev!r}", r)

    rec = Recording(
        t_s=t,
        voltage_v=cols["voltage"],
        position_um=cols["position"],
        target_um=cols.get("target"),
        z_voltage_v=cols.get("z_voltage"),
        axis=axis,
        experiment=text_cols.get("experiment"),
        metadata=metadata,
        path=path,
        line_numbers=line_numbers,
        ignored_columns=tuple(c for c in names if c not in KNOWN_COLUMNS),
        dropped_tail=dropped_tail,
    )
    split_experiments(rec)  # validates contiguity
    return rec


def _check_header(names: list[str], path: str | None, line: int | None) -> None:
    seen: set[str] = set()
    for c in names:
        if not c:
            raise RecordingError("header: empty column name", path, line)
        if c in seen:
            raise RecordingError(f"header: duplicate column {c!r}", path, line)
        seen.add(c)
    for c in REQUIRED_COLUMNS:
        if c not in seen:
            raise RecordingError(
                f"header: missing required column {c!r} (header has: {', '.join(names)})", path, line
            )


def _is_float(cell: str) -> bool:
    s = cell.strip()
    if not s or "_" in s:
        return False
    try:
        float(s)
    except ValueError:
        return False
    return True


# ----------------------------------------------------------------------------------------------- writer


def _check_label(label: str, what: str) -> str:
    if not isinstance(label, str) or not label.strip() or _BAD_LABEL_CHARS.search(label):
        raise RecordingError(f"invalid {what} {label!r}: must be non-empty without ',', '\"' or line breaks")
    if label.strip() != label or label.startswith("#"):
        raise RecordingError(f"invalid {what} {label!r}: no surrounding blanks, must not start with '#'")
    return label


class RecordingWriter:
    """Streaming, append-friendly recording writer.

    Every :meth:`write` formats a whole block of rows, writes it with one call and
    flushes (optionally ``fsync``), so a crash leaves at most one partial last line.

    Parameters
    ----------
    path
        The file to write.
    columns
        Column names in file order (must include ``t``, ``voltage``, ``position``).
    metadata
        ``# key: value`` lines written before the header (new files only).
    append
        Append to an existing file: its header must list the same columns; a partial
        last line (no newline) is truncated first. A missing or empty file is created.
    fsync
        ``os.fsync`` after every block (durable against power loss, slower).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        columns: Sequence[str] = REQUIRED_COLUMNS,
        *,
        metadata: Mapping[str, object] | None = None,
        append: bool = False,
        fsync: bool = False,
    ) -> None:
        self.path = os.fspath(path)
        self.columns = tuple(columns)
        _check_header(list(self.columns), self.path, None)
        unknown = [c for c in self.columns if c not in KNOWN_COLUMNS]
        if unknown:
            raise RecordingError(f"cannot write unknown columns {unknown}", self.path)
        self.fsync = fsync
        self.rows_written = 0
        self.dropped_tail_bytes = 0
        p = Path(self.path)
        if append and p.exists() and p.stat().st_size > 0:
            self._check_existing(p)
            self._fh: IO[str] = open(p, "a", encoding="utf-8", newline="\n")  # noqa: SIM115
        else:
            self._fh = open(p, "w", encoding="utf-8", newline="\n")  # noqa: SIM115
            head = "".join(f"# {_check_meta(k)}: {_meta_value(v)}\n" for k, v in (metadata or {}).items())
            self._fh.write(head + ",".join(self.columns) + "\n")
            self._flush()

    def _check_existing(self, p: Path) -> None:
        with open(p, "rb") as fh:
            header: list[str] | None = None
            n = 0
            for n, raw in enumerate(fh, start=1):  # noqa: B007 - n names the header line below
                line = raw.decode("utf-8", errors="replace").rstrip("\r\n")
                if line and line[0] != "#":
                    header = [c.strip() for c in line.split(",")]
                    break
            if header is None:
                raise RecordingError("cannot append: no header line", self.path)
            if tuple(header) != self.columns:
                raise RecordingError(
                    f"cannot append: header {','.join(header)} differs from {','.join(self.columns)}",
                    self.path,
                    n,
                )
        with open(p, "rb+") as fh:
            size = fh.seek(0, os.SEEK_END)
            fh.seek(max(0, size - 65536))
            tail = fh.read()
            if not tail.endswith(b"\n"):
                cut = tail.rfind(b"\n")
                new_size = size - len(tail) + cut + 1 if cut >= 0 else 0
                if new_size == 0:
                    raise RecordingError(
                        "cannot append: the file does not end with a complete line", self.path
                    )
                fh.truncate(new_size)
                self.dropped_tail_bytes = size - new_size

    def write(
        self,
        t_s: ArrayLike,
        voltage_v: ArrayLike,
        position_um: ArrayLike,
        *,
        target_um: ArrayLike | None = None,
        axis: str | Sequence[str] | NDArray[np.str_] | None = None,
        experiment: str | Sequence[str] | NDArray[np.str_] | None = None,
        z_voltage_v: ArrayLike | None = None,
    ) -> int:
        """Append a block of rows and flush.

        Numeric arguments are arrays of one length; ``axis`` / ``experiment`` are one
        string for the whole block or one per row. Every column of the writer must be
        given, and no other.

        Returns
        -------
        int
            Number of rows written.
        """
        given: dict[str, object] = {
            "t": t_s,
            "voltage": voltage_v,
            "position": position_um,
            "target": target_um,
            "z_voltage": z_voltage_v,
            "axis": axis,
            "experiment": experiment,
        }
        for c, v in given.items():
            if (v is None) == (c in self.columns):
                state = "missing" if v is None else "not a column of this file"
                raise RecordingError(f"write: {c!r} {state} (columns: {','.join(self.columns)})", self.path)
        n = int(np.size(t_s))
        parts: list[str] = []
        lists: list[Iterable[object]] = []
        for c in self.columns:
            v = given[c]
            if c in NUMERIC_COLUMNS:
                arr = np.asarray(v, dtype=np.float64).reshape(-1)
                if arr.size != n:
                    raise RecordingError(f"write: column {c!r} has {arr.size} values, t has {n}", self.path)
                if not np.isfinite(arr).all():
                    raise RecordingError(f"write: column {c!r} has non-finite values", self.path)
                parts.append(_FORMATS[c])
                lists.append(arr.tolist())
            elif isinstance(v, str):
                _check_label(v, c)
                if c == "axis" and v not in AXES:
                    raise RecordingError(f"write: axis {v!r} is not one of x, y, z", self.path)
                parts.append(v.replace("%", "%%"))
            else:
                labels = np.asarray(v, dtype=np.str_).reshape(-1)
                if labels.size != n:
                    raise RecordingError(
                        f"write: column {c!r} has {labels.size} values, t has {n}", self.path
                    )
                for u in np.unique(labels):
                    _check_label(str(u), c)
                    if c == "axis" and u not in AXES:
                        raise RecordingError(f"write: axis {u!r} is not one of x, y, z", self.path)
                parts.append("%s")
                lists.append(labels.tolist())
        fmt = ",".join(parts) + "\n"
        block = "".join(map(fmt.__mod__, zip(*lists, strict=True)))
        self._fh.write(block)
        self._flush()
        self.rows_written += n
        return n

    def write_recording(self, rec: Recording) -> int:
        """Write all rows of ``rec`` (its columns must match the writer's)."""
        return self.write(
            rec.t_s,
            rec.voltage_v,
            rec.position_um,
            target_um=rec.target_um,
            axis=rec.axis,
            experiment=rec.experiment,
            z_voltage_v=rec.z_voltage_v,
        )

    def _flush(self) -> None:
        self._fh.flush()
        if self.fsync:
            os.fsync(self._fh.fileno())

    def close(self) -> None:
        """Flush and close the file."""
        if not self._fh.closed:
            self._flush()
            self._fh.close()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _check_meta(key: str) -> str:
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_.\-]*", key):
        raise RecordingError(f"invalid metadata key {key!r}")
    return key


def _meta_value(value: object) -> str:
    text = str(value)
    if "\n" in text or "\r" in text:
        raise RecordingError(f"metadata value {text!r} contains a line break")
    return text


def write_recording(
    path: str | os.PathLike[str], rec: Recording, *, metadata: Mapping[str, object] | None = None
) -> None:
    """Write ``rec`` to ``path`` (its metadata, updated by ``metadata``)."""
    meta: dict[str, object] = dict(rec.metadata)
    meta.update(metadata or {})
    with RecordingWriter(path, rec.columns, metadata=meta) as w:
        w.write_recording(rec)


# ------------------------------------------------------------------------------------------ experiments


def split_experiments(rec: Recording, *, default_label: str | None = None) -> list[Experiment]:
    """Split a recording into experiments, one per (label, axis), in file order.

    Parameters
    ----------
    rec
        The recording.
    default_label
        Label of a recording without ``experiment`` column (default: the file stem,
        or ``"recording"``).

    Raises
    ------
    RecordingError
        When the rows of one experiment on one axis are not contiguous.
    """
    if default_label is None:
        default_label = Path(rec.path).stem if rec.path else "recording"
    n = len(rec)
    axes = [None] if rec.axis is None else [str(a) for a in dict.fromkeys(rec.axis.tolist())]
    out: list[tuple[int, Experiment]] = []
    for ax in axes:
        rows = np.arange(n) if ax is None or rec.axis is None else np.flatnonzero(rec.axis == ax)
        if rec.experiment is None:
            bounds = [(0, rows.size, default_label)]
        else:
            labels = rec.experiment[rows]
            change = np.flatnonzero(labels[1:] != labels[:-1]) + 1
            starts = np.concatenate(([0], change))
            ends = np.concatenate((change, [rows.size]))
            bounds = [(int(s), int(e), str(labels[s])) for s, e in zip(starts, ends, strict=True)]
            seen: set[str] = set()
            for s, _e, lab in bounds:
                if lab in seen:
                    where = f" on axis {ax}" if ax else ""
                    raise RecordingError(
                        f"experiment {lab!r}{where} resumes after other experiments (rows of one "
                        "experiment must be contiguous)",
                        rec.path,
                        rec.line_of(int(rows[s])),
                    )
                seen.add(lab)
        for s, e, lab in bounds:
            sel = rows[s:e]
            sl: slice | NDArray[np.int64] = slice(int(sel[0]), int(sel[-1]) + 1) if ax is None else sel
            out.append(
                (
                    int(sel[0]),
                    Experiment(
                        label=lab,
                        axis=ax,
                        t_s=rec.t_s[sl],
                        voltage_v=rec.voltage_v[sl],
                        position_um=rec.position_um[sl],
                        target_um=None if rec.target_um is None else rec.target_um[sl],
                        path=rec.path,
                        line_numbers=None if rec.line_numbers is None else rec.line_numbers[sl],
                        metadata=rec.metadata,
                    ),
                )
            )
    out.sort(key=lambda item: item[0])
    return [e for _, e in out]


def read_experiments(
    paths: Sequence[str | os.PathLike[str]],
    *,
    axis: str | None = None,
    allow_truncated_tail: bool = False,
) -> list[Experiment]:
    """Read recordings and split them into experiments.

    With several files, labels are prefixed by the file name (``name.csv:label``) so
    that they stay unique. ``axis`` keeps only that axis (rows of files without an
    axis column are taken to belong to it).

    Raises
    ------
    RecordingError
        For a malformed file, or when no experiment is left.
    """
    out: list[Experiment] = []
    for p in paths:
        rec = read_recording(p, allow_truncated_tail=allow_truncated_tail)
        for e in split_experiments(rec):
            if axis is not None and e.axis not in (None, axis):
                continue
            if len(paths) > 1:
                e = Experiment(
                    label=f"{Path(os.fspath(p)).name}:{e.label}",
                    axis=e.axis,
                    t_s=e.t_s,
                    voltage_v=e.voltage_v,
                    position_um=e.position_um,
                    target_um=e.target_um,
                    path=e.path,
                    line_numbers=e.line_numbers,
                    metadata=e.metadata,
                )
            out.append(e)
    if not out:
        where = f" for axis {axis}" if axis else ""
        raise RecordingError(f"no experiments{where} in {', '.join(os.fspath(p) for p in paths)}")
    return out


# --------------------------------------------------------------------------------------- scan inference


@dataclass(frozen=True, eq=False)
class ScanInfo:
    """What the voltage (or target) waveform of an experiment is.

    Attributes
    ----------
    kind
        ``triangle`` (periodic, straight half periods), ``sine``, ``periodic`` (regular
        back-and-forth of another shape), ``ramp``, ``constant`` or ``arbitrary``.
    reason
        Why the waveform is not a periodic triangle (empty when it is).
    frequency_hz
        Line (trace + retrace) frequency; nan when there is no complete half period.
    v_min, v_max
        Turning values: the median lower / upper turning point (extreme samples for a
        clean waveform, intersections of the fitted half-period lines for a noisy
        triangle); the sample minimum / maximum when there are no turning points.
    turning_indices
        Sample indices of the turning points, in time order.
    turning_kinds
        +1 for an upper (maximum), -1 for a lower (minimum) turning point.
    direction
        Per sample: +1 trace (rising), -1 retrace (falling). A turning sample belongs to
        the half period that starts there.
    n_loops
        Number of complete periods between the first and the last turning point.
    shape_error
        RMS deviation of the half periods from straight lines, relative to the span.
    noise
        RMS deviation from the best fitting shape (line or half cosine), in waveform units.
    duty
        Fraction of the period spent rising (0.5 for a symmetric triangle; nan if unknown).
    """

    kind: ScanKind
    reason: str
    frequency_hz: float
    v_min: float
    v_max: float
    turning_indices: NDArray[np.int64]
    turning_kinds: NDArray[np.int8]
    direction: NDArray[np.int8]
    n_loops: int
    shape_error: float
    noise: float
    duty: float

    @property
    def range_v(self) -> float:
        """Peak-to-peak range ``v_max - v_min``."""
        return self.v_max - self.v_min

    @property
    def offset_v(self) -> float:
        """Centre ``(v_max + v_min) / 2``."""
        return 0.5 * (self.v_max + self.v_min)

    @property
    def period_s(self) -> float:
        """``1 / frequency_hz``."""
        return 1.0 / self.frequency_hz

    @property
    def is_scan(self) -> bool:
        """A periodic triangular scan with at least one complete loop."""
        return self.kind == "triangle" and self.n_loops >= 1

    @property
    def is_periodic(self) -> bool:
        """Regular back-and-forth motion (triangle, sine or another periodic shape), >= 1 loop."""
        return self.kind in ("triangle", "sine", "periodic") and self.n_loops >= 1


#: Largest straight-line (or half-cosine) shape error of a triangle (or sine), relative to the span.
_SHAPE_TOL = 0.01
#: The better shape must fit at least this much better than the other one.
_SHAPE_RATIO = 0.4
#: Largest relative spread of turning values and half-period durations of a periodic waveform.
_REGULAR_TOL = 0.05
#: Below this sample noise / span the extreme samples are the turning values.
_CLEAN_TOL = 1e-4


def infer_scan(t_s: ArrayLike, voltage: ArrayLike) -> ScanInfo:
    """Infer scan frequency, range, offset, direction and turning points of a waveform.

    Parameters
    ----------
    t_s
        Sample times (s), strictly increasing.
    voltage
        The waveform (V; any unit works, e.g. a target position in um).

    Returns
    -------
    ScanInfo
        The classification and the inferred scan (see :class:`ScanInfo`).
    """
    t = np.asarray(t_s, dtype=np.float64)
    v = np.asarray(voltage, dtype=np.float64)
    n = v.size
    if n < 4:
        return _nonscan("arbitrary", f"only {n} samples", t, v)
    vmin_all, vmax_all = float(v.min()), float(v.max())
    scale = max(abs(vmin_all), abs(vmax_all), 1e-300)
    if vmax_all - vmin_all <= 1e-9 * scale:
        return _nonscan("constant", "the waveform is constant", t, v)
    lo, hi = (float(q) for q in np.percentile(v, [1.0, 99.0]))
    span = hi - lo
    if span <= 1e-6 * (vmax_all - vmin_all):
        lo, hi, span = vmin_all, vmax_all, vmax_all - vmin_all

    # Schmitt trigger: forward-filled band state, +1 above 70 %, -1 below 30 % of the span.
    band = np.zeros(n, dtype=np.int8)
    band[v >= lo + 0.7 * span] = 1
    band[v <= lo + 0.3 * span] = -1
    nz = np.flatnonzero(band)
    fill = np.maximum.accumulate(np.where(band != 0, np.arange(n), 0))
    state = band[fill]
    state[: nz[0]] = 0
    change = np.flatnonzero(np.diff(state)) + 1
    starts = np.concatenate(([0], change))
    ends = np.concatenate((change, [n]))
    cand_idx: list[int] = []
    cand_kind: list[int] = []
    for s, e in zip(starts.tolist(), ends.tolist(), strict=True):
        k = int(state[s])
        if k == 0:
            continue
        run_v = v[s:e]
        cand_idx.append(s + int(np.argmax(run_v) if k > 0 else np.argmin(run_v)))
        cand_kind.append(k)
    idx = np.asarray(cand_idx, dtype=np.int64)
    kinds = np.asarray(cand_kind, dtype=np.int8)

    d2 = np.diff(v, 2)
    noise_d2 = float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0)) if n > 2 else 0.0
    tol = 0.005 * span + 4.0 * noise_d2
    if idx.size:
        # The first and last band runs may be cut by the record's start or end and then hold no
        # turning point at all: they count only next to real ones and at their level.
        interior = np.ones(idx.size, dtype=bool)
        interior[[0, -1]] = False
        keep = interior.copy()
        for edge in np.flatnonzero(~interior) if interior.any() else ():
            same = kinds == kinds[edge]
            ref_pool = v[idx[same & interior]] if np.any(same & interior) else v[idx[same]]
            keep[edge] = abs(v[idx[edge]] - float(np.median(ref_pool))) <= tol
        idx, kinds = idx[keep], kinds[keep]

    if idx.size < 2:
        direction = _direction_from_slope(v)
        net = v[-1] - v[0]
        if idx.size == 0 and abs(net) >= 0.8 * (vmax_all - vmin_all):
            return _nonscan("ramp", "monotonic ramp, no turning point", t, v, direction)
        return _nonscan(
            "arbitrary", f"{idx.size} turning point(s): not a back-and-forth scan", t, v, direction
        )

    # Per half period: straight-line and half-cosine least-squares fits (vectorised over segments).
    nseg = idx.size - 1
    lo_i, hi_i = int(idx[0]), int(idx[-1])
    rows = np.arange(lo_i, hi_i + 1)
    seg = np.clip(np.searchsorted(idx, rows, side="right") - 1, 0, nseg - 1).astype(np.intp)
    t_start = t[idx[:-1]]
    dur = t[idx[1:]] - t_start
    u = (t[rows] - t_start[seg]) / dur[seg]
    vv = v[rows]
    r_line, line_a, line_b = _segment_fit(u, vv, seg, nseg)
    r_cos, _, _ = _segment_fit(np.cos(np.pi * u), vv, seg, nseg)
    npts = rows.size
    line_rms = math.sqrt(float(np.sum(r_line**2)) / npts)
    cos_rms = math.sqrt(float(np.sum(r_cos**2)) / npts)
    shape_line = line_rms / span
    # Shape errors in excess of white sample noise (estimated from second differences).
    ex_line = math.sqrt(max(0.0, line_rms**2 - noise_d2**2)) / span
    ex_cos = math.sqrt(max(0.0, cos_rms**2 - noise_d2**2)) / span
    triangle = ex_line <= _SHAPE_TOL and ex_line <= _SHAPE_RATIO * ex_cos
    sine = not triangle and ex_cos <= _SHAPE_TOL and ex_cos <= _SHAPE_RATIO * ex_line
    noise = min(line_rms, cos_rms)
    clean = noise_d2 <= _CLEAN_TOL * span

    # Turning times and values: extreme samples, or intersections of adjacent lines (triangle).
    t_turn = t[idx].copy()
    v_turn = v[idx].copy()
    if triangle:
        # line k: v = icpt_k + slope_k t
        slope = line_b / dur
        icpt = line_a - slope * t_start
        if nseg >= 2:
            ds = slope[:-1] - slope[1:]
            ok = np.abs(ds) > 0
            tx = np.where(ok, (icpt[1:] - icpt[:-1]) / np.where(ok, ds, 1.0), t_turn[1:-1])
            t_turn[1:-1] = tx
            if not clean:
                v_turn[1:-1] = np.where(ok, icpt[:-1] + slope[:-1] * tx, v_turn[1:-1])
        # An extreme sample at a record edge is a poor turning time (the vertex may lie just
        # outside, or noise moved it): where the edge's line reaches the level of the other
        # turning points of that kind is a better one.
        for end, sg in ((0, 0), (idx.size - 1, nseg - 1)):
            pos = np.arange(idx.size)
            others = (kinds == kinds[end]) & (pos > 0) & (pos < idx.size - 1)
            if not others.any():
                others = (kinds == kinds[end]) & (pos != end)
            level = float(np.median(v_turn[others])) if others.any() else float(v_turn[end])
            if slope[sg] != 0:
                t_turn[end] = (level - icpt[sg]) / slope[sg]
                if not clean:
                    v_turn[end] = level
        if not clean:
            # Re-anchor the turning samples at the refined times (nearest sample).
            j = np.clip(np.searchsorted(t, t_turn), 1, n - 1)
            near = np.where(t_turn - t[j - 1] <= t[j] - t_turn, j - 1, j)
            if np.all(np.diff(near) > 0):
                idx = near.astype(np.int64)
                lo_i, hi_i = int(idx[0]), int(idx[-1])
                rows = np.arange(lo_i, hi_i + 1)
                seg = np.clip(np.searchsorted(idx, rows, side="right") - 1, 0, nseg - 1).astype(np.intp)
    vmaxs = v_turn[kinds > 0]
    vmins = v_turn[kinds < 0]
    v_max = float(np.median(vmaxs)) if vmaxs.size else vmax_all
    v_min = float(np.median(vmins)) if vmins.size else vmin_all

    # Period: same-kind turning times regress linearly on their count.
    slopes: list[tuple[float, int]] = []
    for k in (1, -1):
        tk = t_turn[kinds == k]
        if tk.size >= 2:
            j = np.arange(tk.size, dtype=np.float64)
            slopes.append((float(np.polyfit(j, tk, 1)[0]), tk.size - 1))
    if slopes:
        period = sum(s * w for s, w in slopes) / sum(w for _, w in slopes)
    else:
        period = 2.0 * float(t_turn[1] - t_turn[0])
    frequency = 1.0 / period if period > 0 else math.nan
    seg_dur = np.diff(t_turn)
    rising = -kinds[:-1] > 0
    duty = float(np.mean(seg_dur[rising]) * frequency) if np.any(rising) else math.nan
    if not (np.any(rising) and np.any(~rising)):
        duty = 0.5

    direction = np.empty(n, dtype=np.int8)
    direction[: idx[0]] = kinds[0]
    direction[lo_i : hi_i + 1] = (-kinds[:-1])[seg]
    direction[hi_i:] = -kinds[-1]
    n_loops = (idx.size - 1) // 2

    problems: list[str] = []
    # Back-and-forth, not wandering: between turning points the motion may not turn back by much.
    part = np.searchsorted(idx, np.arange(n), side="right")
    w = direction * (v - 0.5 * (vmax_all + vmin_all)) + part * (2.0 * (vmax_all - vmin_all))
    backtrack = float(np.max(np.maximum.accumulate(w) - w))
    if backtrack > _REGULAR_TOL * span + 6.0 * noise_d2:
        problems.append(f"the motion turns back by {backtrack:.4g} between turning points (span {span:.4g})")
    for name, vals in (("upper", vmaxs), ("lower", vmins)):
        if vals.size >= 2 and np.ptp(vals) > _REGULAR_TOL * span + 6.0 * noise:
            problems.append(f"{name} turning points vary by {np.ptp(vals):.4g} of span {span:.4g}")
    for name, sel in (("rising", rising), ("falling", ~rising)):
        d = seg_dur[sel]
        # Turning times of a rounded waveform jitter with the noise (flat tops); a triangle's do not.
        jitter = 0.0 if triangle else 4.0 * float(np.mean(d)) / math.pi * math.sqrt(2.0 * noise / span)
        if (
            d.size >= 2
            and np.ptp(d) > _REGULAR_TOL * np.mean(d) + 4.0 * float(np.median(np.diff(t))) + jitter
        ):
            problems.append(f"{name} half periods last {d.min():.4g} s to {d.max():.4g} s")
    if problems:
        kind: ScanKind = "arbitrary"
        reason = "not periodic: " + "; ".join(problems)
    elif triangle:
        kind, reason = "triangle", ""
        if n_loops < 1:
            reason = f"only {idx.size} turning points, no complete loop"
    elif sine:
        kind, reason = "sine", f"sinusoidal (straight-line error {shape_line:.2%} of the span)"
    else:
        kind = "periodic"
        reason = f"half periods are not straight (error {shape_line:.2%} of the span)"
    return ScanInfo(
        kind=kind,
        reason=reason,
        frequency_hz=float(frequency),
        v_min=v_min,
        v_max=v_max,
        turning_indices=_frozen(idx, np.int64),  # type: ignore[arg-type]
        turning_kinds=_frozen(kinds, np.int8),  # type: ignore[arg-type]
        direction=_frozen(direction, np.int8),  # type: ignore[arg-type]
        n_loops=int(n_loops),
        shape_error=float(shape_line),
        noise=float(noise),
        duty=duty,
    )


def _segment_fit(basis: F64, v: F64, seg: NDArray[np.intp], nseg: int) -> tuple[F64, F64, F64]:
    """Per-segment least squares ``v = a + b * basis``; returns residuals, a, b."""
    cnt = np.bincount(seg, minlength=nseg).astype(np.float64)
    mb = np.bincount(seg, basis, nseg) / cnt
    mv = np.bincount(seg, v, nseg) / cnt
    bc = basis - mb[seg]
    vc = v - mv[seg]
    sbb = np.bincount(seg, bc * bc, nseg)
    sbv = np.bincount(seg, bc * vc, nseg)
    b = np.divide(sbv, sbb, out=np.zeros(nseg), where=sbb > 0)
    a = mv - b * mb
    return vc - b[seg] * bc, a, b


def _direction_from_slope(v: F64) -> NDArray[np.int8]:
    d = np.sign(np.diff(v)).astype(np.int8)
    nz = d != 0
    if not nz.any():
        return np.ones(v.size, dtype=np.int8)
    fill = np.maximum.accumulate(np.where(nz, np.arange(d.size), 0))
    d = d[fill]
    first = int(np.flatnonzero(nz)[0])
    d[:first] = d[first]
    return np.concatenate((d, d[-1:]))


def _nonscan(
    kind: ScanKind, reason: str, t: F64, v: F64, direction: NDArray[np.int8] | None = None
) -> ScanInfo:
    del t
    if direction is None:
        direction = _direction_from_slope(v) if v.size else np.zeros(0, dtype=np.int8)
    return ScanInfo(
        kind=kind,
        reason=reason,
        frequency_hz=math.nan,
        v_min=float(v.min()) if v.size else math.nan,
        v_max=float(v.max()) if v.size else math.nan,
        turning_indices=_frozen(np.zeros(0), np.int64),  # type: ignore[arg-type]
        turning_kinds=_frozen(np.zeros(0), np.int8),  # type: ignore[arg-type]
        direction=_frozen(direction, np.int8),  # type: ignore[arg-type]
        n_loops=0,
        shape_error=math.nan,
        noise=math.nan,
        duty=math.nan,
    )
