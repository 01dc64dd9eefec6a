"""``piezod ctl``: control a running daemon through its API.

::

    piezod ctl [--api SPEC] [--token-file F] [--timeout S] [--json F] COMMAND
      status                                   what the daemon is doing
      scan --range-um R --line-rate-hz F ...   start a scan (options = ScanRequest fields)
      change [--range-um R] [--line-rate-hz F] [--offset-x-um X] ...
      stop                                     stop and hold, clear a fault
      move [--x-um X] [--y-um Y] [--z-um Z] [--speed-um-per-s V]
      recordings                               list the recordings
      fetch NAME [-o F]                        download one ('-o -' = stdout)
      watch [--rate-hz HZ] [--count N]         follow live, one line per update

``--api`` defaults to ``$PIEZOD_API``, else the socket of the one running daemon (in
/run/piezod, $XDG_RUNTIME_DIR or /tmp/piezod-<uid>, where ``serve`` puts it).
``--json F`` (``-`` = stdout) writes the answer as JSON; with ``watch`` one JSON
object per line.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import types
import typing
from pathlib import Path
from typing import Any, TextIO

from pydantic import BaseModel

from piezod.cli._common import finite_float, human_stream, positive_float, positive_int, write_json
from piezod.client import API_ENV, PiezodClient, default_api_spec
from piezod.service.schemas import (
    FaultInfo,
    MoveRequest,
    RecordingInfo,
    ScanChange,
    ScanEvent,
    ScanRequest,
    Status,
)
from piezod.service.server import read_token


def _option_type(annotation: Any) -> tuple[Any, list[Any] | None, bool]:
    """argparse ``type``, ``choices`` and whether it is a flag, from a field annotation."""
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        annotation = inner[0] if len(inner) == 1 else str
        args = typing.get_args(annotation)
    if typing.get_origin(annotation) is typing.Literal:
        return type(args[0]), list(args), False
    if annotation is bool:
        return bool, None, True
    if annotation in (int, float, str):
        return annotation, None, False
    return str, None, False


def _add_model_options(parser: argparse.ArgumentParser, model: type[BaseModel]) -> None:
    """One option per field (``range_um`` -> ``--range-um``); unset options are not sent."""
    for name, info in model.model_fields.items():
        flag = "--" + name.replace("_", "-")
        kind, choices, is_flag = _option_type(info.annotation)
        help_text = info.description or name.replace("_", " ")
        if not info.is_required() and info.default is not None:
            help_text += f" (daemon default: {info.default})"
        if is_flag:
            parser.add_argument(
                flag,
                dest=name,
                action=argparse.BooleanOptionalAction,
                default=argparse.SUPPRESS,
                help=help_text,
            )
            continue
        metavar = {int: "N", float: "X"}.get(kind, "TEXT") if choices is None else None
        parser.add_argument(
            flag,
            dest=name,
            type=finite_float if kind is float else kind,
            choices=choices,
            metavar=metavar,
            required=info.is_required(),
            default=argparse.SUPPRESS,
            help=help_text,
        )


def register(subparsers: Any) -> None:
    """Add ``piezod ctl``."""
    parser = subparsers.add_parser(
        "ctl",
        help="client of a running daemon's API",
        description="Control a running piezod daemon through its API.",
        epilog=(
            f"--api defaults to ${API_ENV}, else the one running daemon's socket "
            "(/run/piezod/*.sock, $XDG_RUNTIME_DIR/piezod-*.sock, /tmp/piezod-<uid>/*.sock)."
        ),
    )
    parser.add_argument("--api", metavar="SPEC", help="unix:PATH or tcp:HOST:PORT of the daemon")
    parser.add_argument("--token-file", metavar="F", help="file holding the API bearer token (TCP)")
    parser.add_argument(
        "--timeout", type=positive_float, default=10.0, metavar="S", help="seconds to wait for answers"
    )
    json_help = "write the answer as JSON to F ('-' = stdout)"
    parser.add_argument("--json", metavar="F", help=json_help)
    sub = parser.add_subparsers(dest="ctl_command", metavar="COMMAND", required=True)

    def add(name: str, help_text: str) -> argparse.ArgumentParser:
        p: argparse.ArgumentParser = sub.add_parser(name, help=help_text, description=help_text)
        p.add_argument("--json", metavar="F", default=argparse.SUPPRESS, help=json_help)
        return p

    add("status", "what the daemon is doing")
    _add_model_options(add("scan", "start a scan"), ScanRequest)
    _add_model_options(add("change", "change the running scan at its next line"), ScanChange)
    add("stop", "stop scanning or moving and hold; clears a fault")
    _add_model_options(add("move", "move to a position and hold it"), MoveRequest)
    add("recordings", "list the recordings")
    fetch = add("fetch", "download a recording")
    fetch.add_argument("name", metavar="NAME", help="recording name, as listed by 'recordings'")
    fetch.add_argument("-o", "--output", metavar="F", help="file or directory to write ('-' = stdout)")
    watch = add("watch", "follow the daemon live, one line per update")
    watch.add_argument(
        "--rate-hz", type=positive_float, metavar="HZ", help="updates per second (daemon default 5)"
    )
    watch.add_argument("--count", type=positive_int, metavar="N", help="stop after N updates")
    parser.set_defaults(func=run)


def _fmt(values: dict[str, float], unit: str) -> str:
    return " ".join(f"{k}={v:.4g}{unit}" for k, v in values.items()) or "-"


def _scan_text(scan: ScanRequest) -> str:
    slow = scan.slow_range_um if scan.slow_range_um is not None else scan.range_um
    parts = [
        f"{scan.range_um:g} x {slow:g} um at {scan.line_rate_hz:g} lines/s, {scan.lines} lines",
        f"offset ({scan.offset_x_um:g}, {scan.offset_y_um:g}) um",
    ]
    if scan.rotation_deg:
        parts.append(f"rotated {scan.rotation_deg:g} deg")
    if not scan.correction:
        parts.append("NO correction")
    return ", ".join(parts)


def _fault_text(fault: FaultInfo) -> str:
    at = f" at sample {fault.index}" if fault.index is not None else ""
    return f"fault [{fault.source}] {fault.code}: {fault.message}{at} (t={fault.time_s:.3f} s)"


def status_text(status: Status) -> str:
    """A few human lines describing a status."""
    lines = [
        f"{status.scanner}: {status.state} (uptime {status.uptime_s:.1f} s, "
        f"sample {status.sample_index} at {status.sample_rate_hz:g} Hz)"
    ]
    if status.scan is not None:
        where = ""
        if status.line is not None:
            where = f"; frame {status.frame if status.frame is not None else '-'}, "
            where += f"line {status.line}/{status.scan.lines}"
        lines.append(f"scan: {_scan_text(status.scan)}{where}")
    if status.recording:
        lines.append(f"recording: {status.recording}")
    if not status.calibrated:
        lines.append(
            f"warning: uncalibrated model on axes {', '.join(status.uncalibrated_axes)} (a first guess): "
            "corrected scans will not be linear; run piezod calibrate"
        )
    clipped = {a: n for a, n in status.sensor_clipped.items() if n}
    if clipped:
        lines.append(
            f"warning: {status.sensor_clipped_job}: readback at the sensor's full scale on "
            + ", ".join(f"{a} ({n} samples)" for a, n in clipped.items())
            + "; positions there are not measured (axes.<axis>.sensor_full_scale_um)"
        )
    lines.append(
        f"fifo: {status.fifo_level_ms:.1f} ms (target {status.lead_target_ms:.0f} ms); "
        f"underruns {status.underruns}, crc errors {status.crc_errors}, "
        f"frames dropped {status.frames_dropped}"
    )
    lines.append(f"position: {_fmt(status.position_um, ' um')}; voltage: {_fmt(status.voltage_v, ' V')}")
    if status.last_line is not None:
        ll = status.last_line
        lines.append(f"last line {ll.line} ({ll.direction}): {ll.figures()}")
    if status.sensitivity_scale:
        lines.append(f"sensitivity scale: {_fmt(status.sensitivity_scale, '')}")
    if status.faults:
        lines.append(f"faults: {len(status.faults)}; latest {_fault_text(status.faults[-1])}")
    return "\n".join(lines)


def watch_line(event: Status | FaultInfo | ScanEvent) -> str:
    """One human line per live event."""
    stamp = time.strftime("%H:%M:%S")
    if isinstance(event, FaultInfo):
        return f"{stamp} FAULT {_fault_text(event)}"
    if isinstance(event, ScanEvent):
        where = f"{event.recording} frame {event.frame}"
        if event.kind == "line":
            return f"{stamp} LINE  {where} line {event.line}/{event.lines} {event.direction}"
        files = f" images {', '.join(event.images)}" if event.images else ""
        return f"{stamp} FRAME {where} done{files}" + (f" ({event.image_error})" if event.image_error else "")
    s = event
    text = f"{stamp} {s.state:<12}"
    if s.scan is not None and s.line is not None:
        text += f" frame {s.frame if s.frame is not None else '-'} line {s.line}/{s.scan.lines}"
    text += f" fifo {s.fifo_level_ms:6.1f} ms underruns {s.underruns}"
    if s.position_um:
        text += f" {_fmt(s.position_um, 'um')}"
    ll = s.last_line
    if ll is not None and ll.nonlinearity_pct is not None and ll.length_error_pct is not None:
        text += f" nl {ll.nonlinearity_pct:.3f}% le {ll.length_error_pct:+.3f}%"
    elif ll is not None:
        text += " line not scored"
    return text


def _recordings_text(recs: list[RecordingInfo]) -> str:
    if not recs:
        return "no recordings"
    width = max(len(r.name) for r in recs)
    rows = []
    for r in recs:
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(r.modified_unix))
        state = "" if r.complete else "  (being written)"
        rows.append(f"{r.name:<{width}}  {r.size_bytes:>12,d} B  {when}{state}")
    return "\n".join(rows)


def _fields(args: argparse.Namespace, model: type[BaseModel]) -> dict[str, Any]:
    return {name: getattr(args, name) for name in model.model_fields if hasattr(args, name)}


def _watch(client: PiezodClient, args: argparse.Namespace, human: TextIO) -> int:
    target = args.json
    out: TextIO | None = None
    if target == "-":
        out = sys.stdout
    elif target is not None:
        out = Path(target).open("w", encoding="utf-8")  # noqa: SIM115 - closed below
    try:
        for event in client.events(rate_hz=args.rate_hz, limit=args.count):
            if out is not None:
                kind = (
                    "fault"
                    if isinstance(event, FaultInfo)
                    else event.kind
                    if isinstance(event, ScanEvent)
                    else "status"
                )
                out.write(json.dumps({"event": kind, "data": event.model_dump(mode="json")}) + "\n")
                out.flush()
            if target != "-":
                print(watch_line(event), file=human, flush=True)
    finally:
        if out is not None and out is not sys.stdout:
            out.close()
    return 0


def run(args: argparse.Namespace) -> int:
    """Run one ``piezod ctl`` command."""
    token = read_token(args.token_file) if args.token_file else None
    human = human_stream(args)
    command: str = args.ctl_command
    with PiezodClient(args.api or default_api_spec(), token=token, timeout=args.timeout) as client:
        if command == "watch":
            return _watch(client, args, human)
        if command == "recordings":
            recs = client.recordings()
            print(_recordings_text(recs), file=human)
            write_json(args.json, {"recordings": [r.model_dump(mode="json") for r in recs]})
            return 0
        if command == "fetch":
            if args.output == "-":
                for chunk in client.iter_recording(args.name):
                    sys.stdout.buffer.write(chunk)
                sys.stdout.buffer.flush()
                return 0
            path = client.fetch_recording(args.name, args.output)
            size = path.stat().st_size
            print(f"wrote {path} ({size} bytes)", file=human)
            write_json(args.json, {"name": args.name, "path": str(path), "size_bytes": size})
            return 0
        if command == "status":
            status = client.status()
        elif command == "scan":
            status = client.scan(**_fields(args, ScanRequest))
        elif command == "change":
            status = client.change(**_fields(args, ScanChange))
        elif command == "stop":
            status = client.stop()
        elif command == "move":
            status = client.move(**_fields(args, MoveRequest))
        else:  # pragma: no cover - argparse restricts the choices
            raise AssertionError(command)
        print(status_text(status), file=human)
        write_json(args.json, status.model_dump(mode="json"))
        return 0
