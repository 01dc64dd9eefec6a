"""firmware_proto stands on its own: its own exceptions, mixed into piezod's root by the host."""

from __future__ import annotations

import subprocess
import sys

import pytest

import firmware_proto
from firmware_proto import Capabilities, Nak, NakReason, check_capabilities
from piezod import errors


def test_importing_the_codec_pulls_in_no_host_module() -> None:
    code = (
        "import sys, firmware_proto; "
        "bad = sorted(m for m in sys.modules if m == 'piezod' or m.startswith('piezod.')); "
        "print(bad); sys.exit(1 if bad else 0)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stdout + done.stderr


def test_codec_errors_are_caught_by_both_roots() -> None:
    with pytest.raises(firmware_proto.ProtocolError) as info:
        Nak(nacked_seq=-1, nacked_type=1, reason=NakReason.BAD_VALUE, detail=0)
    assert isinstance(info.value, ValueError) and not isinstance(info.value, errors.PiezodError)
    host = errors.from_wire(info.value)
    assert isinstance(host, errors.ProtocolError) and isinstance(host, errors.PiezodError)
    assert isinstance(host, firmware_proto.ProtocolError) and host.__cause__ is info.value
    assert str(host) == str(info.value)
    assert errors.from_wire(host) is host


def test_version_mismatch_translates_to_the_hosts_class() -> None:
    caps = Capabilities(
        reply_to_seq=0,
        protocol_version=2,
        firmware_version=(1, 0, 0),
        dac_bits=16,
        adc_bits=16,
        max_samples_per_frame=100,
        sample_rate_min_hz=1,
        sample_rate_max_hz=1000,
        sample_clock_hz=0,
        fifo_depth_samples=1000,
        board_serial=1,
        amplifier_ranges_v=((-1.0, 1.0),),
    )
    with pytest.raises(firmware_proto.VersionMismatchError) as info:
        check_capabilities(caps)
    host = errors.from_wire(info.value)
    assert isinstance(host, errors.VersionMismatchError)
    assert isinstance(host, firmware_proto.VersionMismatchError)
