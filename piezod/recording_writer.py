"""The streaming recording writer (format: :mod:`piezod.recording`, docs/formats.md).

:class:`RecordingWriter` writes whole lines in one ``write`` and flushes after every block, so
a crash can at worst leave one partial final line; ``append=True`` truncates such a line
before appending, a block that cannot be written (a full disk) is cut back, and
``exclusive=True`` never opens an existing file. The column names the format knows are defined
here and shared with the reader.
"""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezod.errors import RecordingError

if TYPE_CHECKING:
    from piezod.recording import Recording

F64 = NDArray[np.float64]

REQUIRED_COLUMNS: tuple[str, ...] = ("t", "voltage", "position")
NUMERIC_COLUMNS: tuple[str, ...] = ("t", "voltage", "position", "target", "z_voltage")
TEXT_COLUMNS: tuple[str, ...] = ("axis", "experiment")
KNOWN_COLUMNS: tuple[str, ...] = NUMERIC_COLUMNS + TEXT_COLUMNS
AXES: tuple[str, ...] = ("x", "y", "z")

#: printf formats of the writer: t to 15 significant digits (0.1 ns after a day), others to 10.
_FORMATS = {"t": "%.15g", "voltage": "%.10g", "position": "%.10g", "target": "%.10g", "z_voltage": "%.10g"}
_BAD_LABEL_CHARS = re.compile(r"[,\"\r\n]")


def _check_header(names: list[str], path: str | None, line: int | None, *, sensorless: bool = False) -> None:
    seen: set[str] = set()
    for c in names:
        if not c:
            raise RecordingError("header: empty column name", path, line)
        if c in seen:
            raise RecordingError(f"header: duplicate column {c!r}", path, line)
        seen.add(c)
    for c in REQUIRED_COLUMNS:
        if c not in seen and not (sensorless and c == "position"):
            raise RecordingError(
                f"header: missing required column {c!r} (header has: {', '.join(names)})", path, line
            )


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
    exclusive
        Create the file, never open an existing one (``O_EXCL``): raises
        :class:`FileExistsError` if it exists, so a recording is never truncated or reused.

    A block that cannot be written completely (a full disk) is taken back: the file is cut to
    its last complete block, so it stays parseable to its last line, and the ``OSError`` is
    raised. The writer stays usable; a later block is written when space returns.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        columns: Sequence[str] = REQUIRED_COLUMNS,
        *,
        metadata: Mapping[str, object] | None = None,
        append: bool = False,
        fsync: bool = False,
        exclusive: bool = False,
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
        self._fd = -1
        p = Path(self.path)
        if append and not exclusive and p.exists() and p.stat().st_size > 0:
            self._check_existing(p)
            self._fd = os.open(p, os.O_WRONLY | os.O_APPEND | os.O_CLOEXEC)
            self._size = os.fstat(self._fd).st_size
            return
        flags = os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC | (os.O_EXCL if exclusive else os.O_TRUNC)
        self._fd = os.open(p, flags, 0o644)
        self._size = 0
        head = "".join(f"# {_check_meta(k)}: {_meta_value(v)}\n" for k, v in (metadata or {}).items())
        try:
            self._append((head + ",".join(self.columns) + "\n").encode("utf-8"))
        except OSError:
            os.close(self._fd)
            self._fd = -1
            if exclusive:  # ours, and holding no data: leave no empty file behind
                with contextlib.suppress(OSError):
                    os.unlink(p)
            raise

    @property
    def size_bytes(self) -> int:
        """Bytes in the file, all of them complete lines."""
        return self._size

    def _append(self, data: bytes) -> None:
        """Write all of ``data`` at the end or none of it (cut back on failure)."""
        view = memoryview(data)
        try:
            while view:
                n = os.write(self._fd, view)
                view = view[n:]
            if self.fsync:
                os.fsync(self._fd)
        except OSError:
            with contextlib.suppress(OSError):
                os.ftruncate(self._fd, self._size)
            raise
        self._size += len(data)

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
        if self._fd < 0:
            raise RecordingError("write: the writer is closed", self.path)
        self._append(block.encode("utf-8"))
        self.rows_written += n
        return n

    def comment(self, text: str) -> None:
        """Append a comment line ``# text`` (e.g. a scan change between experiments) and flush."""
        _meta_value(text)
        if self._fd < 0:
            raise RecordingError("comment: the writer is closed", self.path)
        self._append(f"# {text}\n".encode())

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

    def close(self) -> None:
        """Close the file (every block is already written)."""
        if self._fd >= 0:
            fd, self._fd = self._fd, -1
            os.close(fd)

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


__all__ = [
    "AXES",
    "KNOWN_COLUMNS",
    "NUMERIC_COLUMNS",
    "REQUIRED_COLUMNS",
    "TEXT_COLUMNS",
    "RecordingWriter",
    "write_recording",
]
