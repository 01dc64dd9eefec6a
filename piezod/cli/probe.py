"""``piezod probe URL``: connect to a board, say HELLO, and show its capabilities."""

from __future__ import annotations

import argparse
import contextlib
from typing import Any

from firmware_proto import Capabilities
from piezod.cli._common import add_json_option, human_stream, positive_float, write_json
from piezod.errors import ConfigError
from piezod.link.board import board_scheme
from piezod.link.session import BoardSession, LinkSettings


def register(sub: Any) -> None:
    """Add the ``probe`` subcommand."""
    p: argparse.ArgumentParser = sub.add_parser(
        "probe",
        help="connect to a board and print its capabilities",
        description=(
            "Open the link (a serial device, a pyserial URL such as socket://host:port, unix:///path, "
            "usb://VID:PID[?serial=S], or sim://[SCANNER.yaml] for a freshly started simulator), "
            "exchange HELLO / CAPABILITIES and print them. "
            "Nothing is configured or changed on the board."
        ),
    )
    p.add_argument("url", nargs="?", metavar="URL", help="the board's link URL")
    p.add_argument("--sim", action="store_true", help="probe a freshly started simulator instead of URL")
    p.add_argument("--timeout", type=positive_float, default=3.0, metavar="S", help="handshake timeout (s)")
    add_json_option(p)
    p.set_defaults(func=run)


def capabilities_dict(caps: Capabilities, url: str) -> dict[str, Any]:
    """The capabilities as JSON-ready data (plus derived values)."""
    rate = caps.sample_rate_max_hz
    return {
        "url": url,
        "protocol_version": caps.protocol_version,
        "firmware_version": ".".join(str(v) for v in caps.firmware_version),
        "board_serial": caps.board_serial,
        "board_serial_hex": f"0x{caps.board_serial:08x}",
        "n_channels": caps.n_channels,
        "dac_bits": caps.dac_bits,
        "adc_bits": caps.adc_bits,
        "max_samples_per_frame": caps.max_samples_per_frame,
        "sample_rate_min_hz": caps.sample_rate_min_hz,
        "sample_rate_max_hz": caps.sample_rate_max_hz,
        "sample_clock_hz": caps.sample_clock_hz,
        "fifo_depth_samples": caps.fifo_depth_samples,
        "fifo_ms_at_max_rate": 1000.0 * caps.fifo_depth_samples / rate if rate else None,
        "amplifier_ranges_v": [list(r) for r in caps.amplifier_ranges_v],
    }


def format_table(info: dict[str, Any]) -> str:
    """A readable two-column table of :func:`capabilities_dict`."""
    clock = info["sample_clock_hz"]
    rows = [
        ("link", info["url"]),
        ("protocol version", str(info["protocol_version"])),
        ("firmware", info["firmware_version"]),
        ("board serial", f"{info['board_serial']} ({info['board_serial_hex']})"),
        ("channels", str(info["n_channels"])),
        ("DAC / ADC bits", f"{info['dac_bits']} / {info['adc_bits']}"),
        ("sample rate", f"{info['sample_rate_min_hz']:,} .. {info['sample_rate_max_hz']:,} Hz"),
        ("sample clock", f"{clock:,} Hz (rates clock/k)" if clock else "any integer rate"),
        (
            "FIFO",
            f"{info['fifo_depth_samples']:,} samples/channel"
            + (
                f" ({info['fifo_ms_at_max_rate']:.1f} ms at the maximum rate)"
                if info["fifo_ms_at_max_rate"] is not None
                else ""
            ),
        ),
        ("samples per frame", f"<= {info['max_samples_per_frame']:,}"),
    ]
    for i, (lo, hi) in enumerate(info["amplifier_ranges_v"]):
        rows.append((f"amplifier {i}", f"{lo:g} .. {hi:g} V"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


def probe(url: str, timeout_s: float = 3.0) -> dict[str, Any]:
    """Connect to ``url``, exchange HELLO / CAPABILITIES, disconnect; returns :func:`capabilities_dict`."""
    settings = LinkSettings(reconnect=False)
    with BoardSession.open(url, settings=settings, timeout_s=timeout_s) as session:
        caps = session.capabilities
        assert caps is not None
        return capabilities_dict(caps, url)


def run(args: argparse.Namespace) -> int:
    """Run ``piezod probe``."""
    if args.timeout <= 0:
        raise ConfigError(f"--timeout: {args.timeout} must be > 0")
    if bool(args.sim) == bool(args.url):
        raise ConfigError("probe: give either a URL or --sim")
    with contextlib.ExitStack() as stack:
        url = args.url
        scheme = None if args.sim else board_scheme(url)
        if args.sim or scheme == "sim":
            from piezod.simulator import parse_sim_url, spawn_sim

            path, effects, seed = parse_sim_url(url) if scheme == "sim" else (None, (), 0)
            url = stack.enter_context(spawn_sim(path, effects=effects, seed=seed)).path
        elif scheme is not None:
            raise ConfigError(
                f"probe: {url} names a {scheme}:// board, not a link of the framed protocol "
                "(probe speaks HELLO / CAPABILITIES); use piezod scan / serve --port"
            )
        info = probe(url, args.timeout)
    print(format_table(info), file=human_stream(args))
    write_json(args.json, info)
    return 0
