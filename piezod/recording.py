"""The recording format (docs/formats.md): reader, streaming writer, experiments.

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
first when there is no ``target`` column and excludes the overscan from its regression;
``sensor_delay_s`` (a readback delay the instrument documents, aligned by
:func:`piezod.readback.align_known_delay` before any fit).

Crash tolerance
---------------
:class:`RecordingWriter` writes whole lines in one ``write`` and flushes after every
block, so a crash can at worst leave one partial final line without a newline. The
reader accepts an unterminated final line if it parses; if it does not, the error
says so and names the line. ``allow_truncated_tail=True`` drops any unterminated
final line unread (a complete-looking one may still be cut inside a number).
Reopening a file with ``RecordingWriter(..., append=True)`` truncates such a partial
line before appending. A block that cannot be written (a full disk) is cut back, so the
file always ends with a complete line; ``exclusive=True`` never opens an existing file.

The writer (:class:`RecordingWriter`, :func:`write_recording`) lives in
:mod:`piezod.recording_writer`, scan inference (what a voltage waveform is) in
:mod:`piezod.scan_inference`; both are re-exported here, as are
:class:`ScanInfo` and :func:`infer_scan`.
"""

from __future__ import annotations

import codecs
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezod.errors import RecordingError
from piezod.recording_writer import (
    AXES,
    KNOWN_COLUMNS,
    NUMERIC_COLUMNS,
    TEXT_COLUMNS,
    RecordingWriter,
    _check_header,
    write_recording,
)
from piezod.scan_inference import ScanInfo, ScanKind, infer_scan

__all__ = [
    "AXES",
    "Experiment",
    "Recording",
    "RecordingWriter",
    "ScanInfo",
    "ScanKind",
    "infer_scan",
    "parse_recording",
    "read_experiments",
    "read_recording",
    "split_experiments",
    "write_recording",
]

F64 = NDArray[np.float64]

_META_RE = re.compile(r"^#\s*([A-Za-z_][A-Za-z0-9_.\-]*)\s*:\s*(.*?)\s*$")
_TRUNCATED_HINT = (
    " (the last line has no newline: cut short by a crash while writing? "
    "allow_truncated_tail / --allow-truncated-tail drops it)"
)


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

    @classmethod
    def of_experiments(cls, experiments: Sequence[Experiment]) -> Recording:
        """One recording of ``experiments`` in order: time, voltage, position and the experiment
        labels (what a lab writes of a session with :func:`write_recording`)."""
        return cls(
            t_s=np.concatenate([e.t_s for e in experiments]),
            voltage_v=np.concatenate([e.voltage_v for e in experiments]),
            position_um=np.concatenate([e.position_um for e in experiments]),
            experiment=np.concatenate([np.full(len(e.t_s), e.label) for e in experiments]),
        )

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

    def rows(self, sl: slice, **changes: Any) -> Experiment:
        """The experiment's rows ``sl`` (every per-sample column sliced), with ``changes`` replaced."""
        columns: dict[str, Any] = {
            "t_s": self.t_s[sl],
            "voltage_v": self.voltage_v[sl],
            "position_um": self.position_um[sl],
            "target_um": None if self.target_um is None else self.target_um[sl],
            "line_numbers": None if self.line_numbers is None else self.line_numbers[sl],
        }
        return replace(self, **{**columns, **changes})

    def describe(self) -> str:
        """``'label'`` plus the axis, for messages."""
        return repr(self.label) + (f" (axis {self.axis})" if self.axis else "")


# ----------------------------------------------------------------------------------------------- reader


def decode_text(raw: bytes, encoding: str | None, path: str | None = None) -> tuple[str, str]:
    """Decode the bytes of a text file: ``encoding``, or detected.

    Detection: a UTF-16 / UTF-32 byte-order mark, else UTF-8 (with or without BOM), else
    Windows-1252 (a superset of Latin-1 in its printable range, what Windows instruments write),
    else Latin-1, which decodes any byte.

    Returns
    -------
    text, encoding
        The text and the encoding used.

    Raises
    ------
    RecordingError
        An unknown ``encoding``, or bytes it cannot decode (with the line).
    """
    if encoding is not None:
        try:
            codecs.lookup(encoding)
        except LookupError as exc:
            raise RecordingError(f"unknown encoding {encoding!r}", path) from exc
        try:
            return raw.decode(encoding), encoding
        except UnicodeDecodeError as exc:
            line = raw.count(b"\n", 0, exc.start) + 1
            raise RecordingError(f"not {encoding} text (byte 0x{raw[exc.start]:02x})", path, line) from exc
    for bom, enc in (
        (codecs.BOM_UTF32_LE, "utf-32"),
        (codecs.BOM_UTF32_BE, "utf-32"),
        (codecs.BOM_UTF16_LE, "utf-16"),
        (codecs.BOM_UTF16_BE, "utf-16"),
    ):
        if raw.startswith(bom):
            try:
                return raw.decode(enc), enc
            except UnicodeDecodeError as exc:
                raise RecordingError(f"not {enc} text despite its byte-order mark", path) from exc
    for enc in ("utf-8", "cp1252"):
        try:
            return raw.decode(enc), enc
        except UnicodeDecodeError:
            continue
    return raw.decode("latin-1"), "latin-1"  # maps every byte: the last resort cannot fail


def read_recording(
    path: str | os.PathLike[str], *, allow_truncated_tail: bool = False, encoding: str | None = None
) -> Recording:
    """Read a recording CSV file.

    Parameters
    ----------
    path
        The file.
    allow_truncated_tail
        Drop a final line that has no newline (left by a crash while writing)
        instead of parsing it.
    encoding
        Text encoding; None detects it (:func:`decode_text`: UTF-8, else Windows-1252 /
        Latin-1 as instruments on Windows write); the encoding used is in the metadata
        (``encoding``) when it is not UTF-8.

    Returns
    -------
    Recording
        The parsed, validated columns with their file line numbers.

    Raises
    ------
    RecordingError
        With ``path:line: reason`` for the first problem: unreadable file or one
        not in the given ``encoding``, no header, missing / duplicate column, wrong number of cells,
        non-numeric or non-finite number, bad axis or empty label, ``t`` not strictly
        increasing, non-contiguous experiment, no data rows.
    """
    name = os.fspath(path)
    try:
        raw = Path(name).read_bytes()
    except OSError as exc:
        raise RecordingError(f"cannot read: {exc.strerror or exc}", name) from exc
    text, used = decode_text(raw, encoding, name)
    del raw  # a large recording: its bytes are not needed beside the text
    rec = parse_recording(text, path=name, allow_truncated_tail=allow_truncated_tail)
    if used.replace("-", "").lower() not in ("utf8", "ascii"):
        rec = replace(rec, metadata={**rec.metadata, "encoding": used})
    return rec


#: Characters of the body parsed at a time (whole lines): the memory of a parse is the columns
#: plus about this much text in per-line objects, not the whole file's lines at once.
PARSE_CHUNK_CHARS = 1 << 24


@dataclass
class _Columns:
    """The file's column layout and the rows parsed so far, chunk by chunk (text cells as codes
    into per-column label tables)."""

    names: list[str]
    path: str | None
    header_line: int
    numeric: list[NDArray[np.float64]] = field(default_factory=list)
    line_numbers: list[NDArray[np.int64]] = field(default_factory=list)
    codes: dict[str, list[NDArray[np.intp]]] = field(default_factory=dict)
    tables: dict[str, dict[str, int]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.num_names = [c for c in NUMERIC_COLUMNS if c in self.names]
        self.num_idx = [self.names.index(c) for c in self.num_names]
        self.txt_names = [c for c in TEXT_COLUMNS if c in self.names]
        self.txt_idx = [self.names.index(c) for c in self.txt_names]

    def add_text(self, name: str, cells: NDArray[np.str_]) -> None:
        table = self.tables.setdefault(name, {})
        uniq, inverse = np.unique(cells, return_inverse=True)
        known = np.array([table.setdefault(str(u), len(table)) for u in uniq], dtype=np.intp)
        self.codes.setdefault(name, []).append(known[inverse.reshape(-1)])

    def text(self, name: str) -> NDArray[np.str_]:
        table = self.tables[name]
        labels = np.array(list(table), dtype=np.str_) if table else np.zeros(0, dtype=np.str_)
        return labels[np.concatenate(self.codes[name])]

    def parse(self, body: list[str], numbers: NDArray[np.int64], unterminated_line: int | None) -> None:
        """Parse and check one chunk of data lines (file lines ``numbers``)."""
        path, ncells = self.path, len(self.names)

        def fail(reason: str, row: int) -> RecordingError:
            line = int(numbers[row])
            if line == unterminated_line:
                reason += _TRUNCATED_HINT
            return RecordingError(reason, path, line)

        counts = np.fromiter((row.count(",") for row in body), dtype=np.int64, count=len(body))
        bad = np.flatnonzero(counts != ncells - 1)
        if bad.size:
            r = int(bad[0])
            got = f"wrong number of cells: {counts[r] + 1}, expected {ncells}"
            raise fail(f"{got} (header line {self.header_line})", r)
        try:
            values = np.loadtxt(
                body, delimiter=",", usecols=self.num_idx, dtype=np.float64, ndmin=2, comments=None
            )
        except ValueError as exc:
            for r, row in enumerate(body):
                cells = row.split(",")
                for c, k in zip(self.num_names, self.num_idx, strict=True):
                    if not _is_float(cells[k]):
                        raise fail(f"column {c!r}: not a number: {cells[k].strip()!r}", r) from exc
            raise RecordingError(f"cannot parse the numeric columns: {exc}", path) from exc
        finite = np.isfinite(values)
        if not finite.all():
            rr, cc = (int(a[0]) for a in np.nonzero(~finite))
            raise fail(f"column {self.num_names[cc]!r}: non-finite value {float(values[rr, cc])!r}", rr)
        if self.txt_names:
            raw_txt = np.loadtxt(body, delimiter=",", usecols=self.txt_idx, dtype=str, ndmin=2, comments=None)
            for j, c in enumerate(self.txt_names):
                labels = np.char.strip(raw_txt[:, j])
                if c == "axis":
                    bad = np.flatnonzero(~np.isin(labels, AXES))
                    if bad.size:
                        r = int(bad[0])
                        raise fail(f"column 'axis': {str(labels[r])!r} is not one of x, y, z", r)
                elif c == "experiment":
                    bad = np.flatnonzero(np.char.str_len(labels) == 0)
                    if bad.size:
                        raise fail("column 'experiment': empty label", int(bad[0]))
                self.add_text(c, labels)
        self.numeric.append(values)
        self.line_numbers.append(numbers)


def parse_recording(text: str, *, path: str | None = None, allow_truncated_tail: bool = False) -> Recording:
    """Parse the text of a recording (see :func:`read_recording`)."""
    if text.startswith("\ufeff"):
        text = text[1:]
    if "\r" in text:
        text = text.replace("\r\n", "\n").replace("\r", "\n")
    if not text or text.isspace():
        raise RecordingError("empty file (no header line)", path, 1)
    terminated = text.endswith("\n")
    last_line = text.count("\n") + (0 if terminated else 1)

    metadata: dict[str, str] = {}
    pos = 0
    header_line = 0
    while True:
        if pos >= len(text):
            raise RecordingError("no header line (only comments)", path, last_line)
        cut = text.find("\n", pos)
        cut = len(text) if cut < 0 else cut
        line = text[pos:cut]
        header_line += 1
        pos = cut + 1
        if line and line[0] != "#":
            break
        m = _META_RE.match(line)
        if m:
            metadata[m.group(1)] = m.group(2)
    names = [c.strip() for c in line.split(",")]
    _check_header(names, path, header_line, sensorless=not metadata_position_sensor(metadata))

    unterminated_last = not terminated and pos < len(text)
    dropped_tail = False
    cols = _Columns(names, path, header_line)
    first = header_line + 1
    while pos < len(text):
        cut = text.find("\n", pos + PARSE_CHUNK_CHARS)
        cut = len(text) if cut < 0 else cut + 1
        chunk = text[pos:cut]
        pos = cut
        body = chunk.split("\n")
        if chunk.endswith("\n"):
            body.pop()
        numbers = np.arange(first, first + len(body), dtype=np.int64)
        first += len(body)
        if pos >= len(text) and unterminated_last and allow_truncated_tail:
            body.pop()
            numbers = numbers[:-1]
            dropped_tail = True
            unterminated_last = False
        if "#" in chunk or "\n\n" in chunk or chunk.startswith("\n"):
            keep = [k for k, row in enumerate(body) if row and row[0] != "#"]
            body = [body[k] for k in keep]
            numbers = numbers[np.asarray(keep, dtype=np.intp)]
        if body:
            cols.parse(body, numbers, last_line if unterminated_last else None)
    if not cols.numeric:
        raise RecordingError("no data rows after the header", path, header_line)
    line_numbers = np.concatenate(cols.line_numbers)

    def fail(reason: str, row: int) -> RecordingError:
        return RecordingError(reason, path, int(line_numbers[row]))

    values = np.concatenate(cols.numeric)
    cols.numeric.clear()
    num = {c: np.ascontiguousarray(values[:, j]) for j, c in enumerate(cols.num_names)}
    del values
    text_cols = {c: cols.text(c) for c in cols.txt_names}
    cols.codes.clear()

    axis = text_cols.get("axis")
    t = num["t"]
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
        voltage_v=num["voltage"],
        position_um=num["position"] if "position" in num else np.full(t.size, np.nan),
        target_um=num.get("target"),
        z_voltage_v=num.get("z_voltage"),
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


def metadata_position_sensor(metadata: Mapping[str, str]) -> bool:
    """False when the metadata say the board had no position sensor (``# position_sensor: no``)."""
    return metadata.get("position_sensor", "yes").strip().lower() not in ("no", "false", "0")


def require_position_sensor(rec: Recording | Experiment, what: str = "this analysis") -> None:
    """Refuse a recording made without a position sensor for an analysis that needs positions.

    Raises
    ------
    RecordingError
        The recording says ``# position_sensor: no`` (a board without a sensor), or it has no
        measured positions.
    """
    if not metadata_position_sensor(rec.metadata) or not np.isfinite(rec.position_um).all():
        raise RecordingError(
            f"recorded without a position sensor ('# position_sensor: no'): {what} needs measured "
            "positions; images of a reference work without one (piezod image --pitch-um P, "
            "piezod calibrate --from-images)",
            rec.path,
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


# ------------------------------------------------------------------------------------------ experiments


#: A step of ``t`` longer than this many median sample intervals is a gap in the recording.
GAP_FACTOR = 10.0


def time_gaps(t_s: ArrayLike) -> NDArray[np.intp]:
    """Indices where a gap in ``t`` starts a new piece (a step above :data:`GAP_FACTOR` x the median).

    Nothing is interpolated across a gap: the samples on both sides become separate experiments.
    """
    t = np.asarray(t_s, dtype=np.float64)
    if t.size < 3:
        return np.zeros(0, dtype=np.intp)
    dt = np.diff(t)
    med = float(np.median(dt))
    if not med > 0:
        return np.zeros(0, dtype=np.intp)
    return (np.flatnonzero(dt > GAP_FACTOR * med) + 1).astype(np.intp)


def split_experiments(rec: Recording, *, default_label: str | None = None) -> list[Experiment]:
    """Split a recording into experiments, one per (label, axis), in file order.

    A gap in ``t`` (a step longer than :data:`GAP_FACTOR` median sample intervals) splits an
    experiment into pieces labelled ``label#1``, ``label#2``, ...; every later piece carries
    ``gap_before_s`` and ``split_from`` in its metadata.

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
            whole = rows[s:e]
            cuts = time_gaps(rec.t_s[whole])
            pieces = np.split(whole, cuts)
            for k, sel in enumerate(pieces):
                sl: slice | NDArray[np.int64] = slice(int(sel[0]), int(sel[-1]) + 1) if ax is None else sel
                meta = rec.metadata
                if k > 0:
                    gap = float(rec.t_s[sel[0]] - rec.t_s[pieces[k - 1][-1]])
                    meta = {**rec.metadata, "gap_before_s": f"{gap:.6g}", "split_from": lab}
                out.append(
                    (
                        int(sel[0]),
                        Experiment(
                            label=lab if len(pieces) == 1 else f"{lab}#{k + 1}",
                            axis=ax,
                            t_s=rec.t_s[sl],
                            voltage_v=rec.voltage_v[sl],
                            position_um=rec.position_um[sl],
                            target_um=None if rec.target_um is None else rec.target_um[sl],
                            path=rec.path,
                            line_numbers=None if rec.line_numbers is None else rec.line_numbers[sl],
                            metadata=meta,
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
    encoding: str | None = None,
    require_sensor: bool = True,
) -> list[Experiment]:
    """Read recordings and split them into experiments.

    With several files, labels are prefixed by the file name (``name.csv:label``) so
    that they stay unique. ``axis`` keeps only that axis (rows of files without an
    axis column are taken to belong to it). Every analysis of experiments compares positions:
    a recording made without a position sensor is refused (:func:`require_position_sensor`)
    unless ``require_sensor`` is false.

    Raises
    ------
    RecordingError
        For a malformed file, a recording without a position sensor, or when no experiment is
        left.
    """
    out: list[Experiment] = []
    for p in paths:
        rec = read_recording(p, allow_truncated_tail=allow_truncated_tail, encoding=encoding)
        if require_sensor:
            require_position_sensor(rec, "an analysis of measured positions")
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
