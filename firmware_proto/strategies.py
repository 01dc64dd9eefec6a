"""Hypothesis strategies for every message (test helper; needs the ``test`` extra).

>>> from firmware_proto.strategies import messages
>>> # @given(messages()) def test_...(msg): ...
"""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from .messages import (
    MAX_CHANNELS,
    NO_CHANNEL,
    NO_INDEX,
    Ack,
    BoardState,
    Capabilities,
    ChannelConfig,
    Configure,
    Fault,
    FaultCode,
    FaultFlags,
    Heartbeat,
    Hello,
    Message,
    Nak,
    NakReason,
    RampToSafe,
    Samples,
    Sensor,
    Start,
    Status,
    Stop,
    Sync,
    max_samples_per_frame,
)

u8 = st.integers(0, 0xFF)
u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFFFFFF)
u64 = st.integers(0, 2**64 - 1)
i16 = st.integers(-32768, 32767)
f32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
index = st.one_of(st.integers(0, 10**7), st.integers(0, 2**63), st.just(NO_INDEX))
channels = st.integers(1, MAX_CHANNELS)


def code_blocks(max_samples: int = 64, n_channels: int | None = None) -> st.SearchStrategy[np.ndarray]:
    """int16 arrays of shape (n_samples, n_channels)."""
    n_ch = st.just(n_channels) if n_channels is not None else channels
    shapes = st.tuples(st.integers(1, max_samples), n_ch)
    return shapes.flatmap(lambda shape: hnp.arrays(np.int16, shape, elements=i16))


@st.composite
def capabilities(draw: st.DrawFn) -> Capabilities:
    """Valid CAPABILITIES."""
    n = draw(channels)
    ranges = []
    for _ in range(n):
        lo = draw(st.floats(-2000, 1000, width=32))
        hi = draw(st.floats(lo, 2000, width=32, exclude_min=True))
        ranges.append((lo, hi))
    rmin = draw(st.integers(1, 10**6))
    return Capabilities(
        reply_to_seq=draw(u32),
        protocol_version=draw(u16),
        firmware_version=(draw(u8), draw(u8), draw(u16)),
        dac_bits=draw(st.integers(1, 16)),
        adc_bits=draw(st.integers(1, 16)),
        max_samples_per_frame=draw(st.integers(1, max_samples_per_frame(n))),
        sample_rate_min_hz=rmin,
        sample_rate_max_hz=draw(st.integers(rmin, 2**32 - 1)),
        sample_clock_hz=draw(u32),
        fifo_depth_samples=draw(u32),
        board_serial=draw(u32),
        amplifier_ranges_v=tuple(ranges),
        sync_outputs=draw(st.integers(0, 8)),
        position_sensor=draw(st.booleans()),
    )


channel_configs = st.builds(ChannelConfig, f32, f32, i16, i16, i16, f32, f32, f32)
"""ChannelConfig with arbitrary (not necessarily acceptable) values."""


def configures(n_channels: int | None = None) -> st.SearchStrategy[Configure]:
    """CONFIGURE with arbitrary field values (see :meth:`Configure.check` for acceptability)."""
    n = st.just(n_channels) if n_channels is not None else channels
    chans = n.flatmap(lambda k: st.lists(channel_configs, min_size=k, max_size=k).map(tuple))
    return st.builds(Configure, u32, u32, u16, u16, chans)


def samples(max_samples: int = 64, n_channels: int | None = None) -> st.SearchStrategy[Samples]:
    """SAMPLES frames."""
    return st.builds(Samples, st.integers(0, 2**62), code_blocks(max_samples, n_channels))


def sensors(max_samples: int = 64, n_channels: int | None = None) -> st.SearchStrategy[Sensor]:
    """SENSOR frames."""
    return st.builds(
        Sensor, st.integers(0, 2**40), st.integers(1, 0xFFFF), code_blocks(max_samples, n_channels)
    )


statuses = st.builds(
    Status,
    st.sampled_from(BoardState),
    u32.map(FaultFlags),
    u64.filter(lambda v: v != NO_INDEX) | st.just(0),
    index,
    u32,
    u32,
    u32,
    u32,
    u32,
    u32,
    u32,
)
faults = st.builds(
    Fault, st.sampled_from(FaultCode), st.one_of(st.integers(0, 7), st.just(NO_CHANNEL)), index, u32
)


syncs = st.builds(
    Sync,
    st.integers(0, 2**48),
    st.lists(st.tuples(st.integers(0, 10_000), u8, u8), min_size=1, max_size=32).map(
        lambda evs: tuple(sorted(evs))
    ),
)


def messages(max_samples: int = 64) -> st.SearchStrategy[Message]:
    """Any message type with arbitrary valid field values."""
    return st.one_of(
        st.builds(Hello, u16, u32),
        capabilities(),
        configures(),
        st.builds(Ack, u32, u8),
        st.builds(Nak, u32, u8, st.sampled_from(NakReason), u32),
        st.builds(Start, u64, u32),
        st.builds(Stop, u64),
        st.just(RampToSafe()),
        st.builds(Heartbeat, u64),
        samples(max_samples),
        statuses,
        sensors(max_samples),
        faults,
        syncs,
    )
