"""The clock exchange over loopback UDP, and the fit of offset and rate."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from sensors.errors import RecordingError
from sensors.recording.clock import (
    MAGIC,
    ClockSample,
    ClockServer,
    ClockSync,
    exchange,
    fit_mapping,
    parse_endpoint,
)


def samples(offset_s: float, rate: float, seed: int = 0, n: int = 200) -> list[ClockSample]:
    """Exchanges against a reference = offset + rate · local, with one-sided queueing delays."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        t1 = 100.0 + 0.5 * k
        up, down = 1e-4 + rng.exponential(2e-3), 1e-4 + rng.exponential(2e-3)
        t2 = offset_s + rate * (t1 + up)
        t3 = t2 + rate * 5e-5
        out.append(ClockSample(t1, t2, t3, t1 + up + 5e-5 + down))
    return out


def test_the_fit_recovers_offset_and_drift_from_the_low_delay_samples() -> None:
    mapping = fit_mapping(samples(12.5, 1 + 40e-6))
    assert mapping.rate == pytest.approx(1 + 40e-6, abs=2e-6)
    assert float(mapping.to_reference(150.0)) == pytest.approx(12.5 + (1 + 40e-6) * 150, abs=5e-4)
    assert mapping.samples_used == 100
    assert mapping.uncertainty_s < 0.01


def test_the_fit_handles_a_clock_ten_times_faster() -> None:
    mapping = fit_mapping(samples(-3.0, 10.0, seed=1))
    assert mapping.rate == pytest.approx(10.0, rel=1e-5)
    assert mapping.to_local(float(mapping.to_reference(120.0))) == pytest.approx(120.0)


def test_samples_within_a_short_span_fix_the_rate_at_one() -> None:
    burst = [ClockSample(1.0 + k * 1e-3, 51.0 + k * 1e-3, 51.0 + k * 1e-3, 1.0 + k * 1e-3 + 2e-4)
             for k in range(8)]  # fmt: skip
    mapping = fit_mapping(burst)
    assert mapping.rate == 1.0
    assert mapping.offset_s == pytest.approx(50.0 - 1e-4, abs=1e-9)


def test_no_samples_is_an_error() -> None:
    with pytest.raises(RecordingError, match="no clock samples"):
        fit_mapping([])


@pytest.mark.parametrize(
    ("text", "expected"), [("10.0.0.2:123", ("10.0.0.2", 123)), (":99", ("127.0.0.1", 99))]
)
def test_endpoints_parse(text: str, expected: tuple[str, int]) -> None:
    assert parse_endpoint(text) == expected


@pytest.mark.parametrize(("text", "message"), [("host", "expected HOST:PORT"),
                                              ("h:70000", "port must be 0-65535")])  # fmt: skip
def test_bad_endpoints_are_errors(text: str, message: str) -> None:
    with pytest.raises(RecordingError, match=message):
        parse_endpoint(text)


class Scaled:
    def __init__(self, offset_s: float, rate: float) -> None:
        self.offset_s, self.rate = offset_s, rate

    def __call__(self) -> float:
        return self.offset_s + self.rate * time.monotonic()


@pytest.fixture
def server() -> Iterator[ClockServer]:
    with ClockServer(Scaled(-500.0, 4.0), "127.0.0.1", 0) as running:
        yield running


def test_exchanges_on_loopback_map_the_local_clock_onto_the_server(server: ClockServer) -> None:
    sync = ClockSync((server.host, server.port))
    try:
        sync.burst(8)
        time.sleep(0.3)
        sync.burst(8)
        mapping = sync.mapping()
    finally:
        sync.close()
    now = time.monotonic()
    assert mapping.rate == pytest.approx(4.0, rel=2e-3)
    assert float(mapping.to_reference(now)) == pytest.approx(-500.0 + 4.0 * now, abs=4e-3)
    assert server.answered >= 16


def test_the_server_ignores_garbage(server: ClockServer) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.sendto(b"hello", (server.host, server.port))
        sock.sendto(b"X" * 16, (server.host, server.port))
        sample = exchange(sock, (server.host, server.port))
    assert sample is not None
    assert sample.round_trip_s < 0.1
    assert server.ignored == 2


def test_garbage_answers_are_skipped_and_silence_is_a_bounded_error() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as fake:
        fake.bind(("127.0.0.1", 0))
        fake.settimeout(0.05)
        stop = threading.Event()

        def answer_garbage() -> None:
            while not stop.is_set():
                try:
                    _, peer = fake.recvfrom(64)
                except TimeoutError:
                    continue
                fake.sendto(MAGIC + b"\x00" * 8, peer)  # wrong length
                fake.sendto(b"NOTCLOCK" + b"\x00" * 24, peer)  # wrong magic

        thread = threading.Thread(target=answer_garbage, daemon=True)
        thread.start()
        sync = ClockSync(fake.getsockname(), timeout_s=0.05)
        started = time.monotonic()
        try:
            with pytest.raises(RecordingError, match=r"did not answer \(5 tries, 0.05 s each\)"):
                sync.burst(3, tries=5)
        finally:
            stop.set()
            thread.join(timeout=2)
            sync.close()
        assert time.monotonic() - started < 2.0
        assert sync.lost == 5
