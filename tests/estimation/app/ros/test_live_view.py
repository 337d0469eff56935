"""The Foxglove live view: a WebSocket client of its own (protocol ``foxglove.sdk.v1``, written
here from the RFC 6455 framing) subscribes, and the CDR it receives, decoded by rosbags'
typestore, is compared with map.npz, the TUM poses and the bag's topics. Servers bind to
127.0.0.1 only; every wait is bounded."""

from __future__ import annotations

import base64
import contextlib
import json
import os
import socket
import struct
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from rosbags.typesys import Stores, get_typestore
from typer.testing import CliRunner

from estimation.app.cli.main import app
from estimation.app.pipeline import run_batch
from estimation.app.ros.bag import BagMessage
from estimation.app.ros.export import read_result, result_messages
from estimation.app.ros.live_view import LiveView, _wait_released, latest_state
from estimation.app.ros.messages import (
    FOXGLOVE_PACKED_ELEMENT_FIELD_MSG,
    FOXGLOVE_VOXEL_GRID_MSG,
    RosMessages,
)
from estimation.app.sim.simulate import run_simulation
from estimation.errors import EstimationError
from estimation.posegraph.keys import split_key
from mapping.formats.npz import load_map
from sensors.trajio import read_tum
from tests.estimation.app.missions import copy_of
from tests.estimation.app.ros.test_export import check_ceiling_band, check_voxel_grid
from tests.paths import REPO

#: The longest any wait for the server may take (s).
TIMEOUT_S = 10.0
LAYOUT = REPO / "configs" / "foxglove" / "coopmap.json"


class SubscriptionRefusedError(Exception):
    """The server refused a subscription to a channel it had advertised."""


class FoxgloveClient:
    """A minimal client of the Foxglove WebSocket protocol: the HTTP upgrade with the
    ``foxglove.sdk.v1`` subprotocol, masked text frames out, frames in (text: JSON operations;
    binary opcode 0x01: subscription id, log time, message bytes)."""

    def __init__(self, port: int, timeout_s: float = TIMEOUT_S) -> None:
        # Each wait (the handshake, for topics, for a message) gets ``timeout_s`` of its own: a
        # client that waits while a mission flies must not run out of time on a loaded machine.
        self.timeout_s = timeout_s
        self.deadline = time.monotonic() + timeout_s
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=TIMEOUT_S)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            (
                f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                "Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
            ).encode()
        )
        self.buffer = b""
        while b"\r\n\r\n" not in self.buffer:
            self._fill()
        head, self.buffer = self.buffer.split(b"\r\n\r\n", 1)
        assert head.startswith(b"HTTP/1.1 101"), head
        self.channels: dict[int, dict[str, Any]] = {}
        self.subscriptions: dict[int, str] = {}
        self.pending: dict[str, list[tuple[int, bytes]]] = {}
        self.server_info: dict[str, Any] | None = None

    def close(self) -> None:
        """Close the connection as the protocol asks: a (masked, empty) close frame first."""
        with contextlib.suppress(OSError):
            self.sock.sendall(bytes([0x88, 0x80]) + os.urandom(4))
        self.sock.close()

    def _fill(self) -> None:
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("the live view did not answer in time")
        self.sock.settimeout(left)
        chunk = self.sock.recv(1 << 20)
        if not chunk:
            raise EOFError("the live view closed the connection")
        self.buffer += chunk

    def _read(self, n: int) -> bytes:
        while len(self.buffer) < n:
            self._fill()
        out, self.buffer = self.buffer[:n], self.buffer[n:]
        return out

    def frame(self) -> tuple[int, bytes]:
        """The next complete message: (opcode, payload); continuation frames joined."""
        opcode, parts = None, []
        while True:
            b0, b1 = self._read(2)
            size = b1 & 0x7F
            if size == 126:
                (size,) = struct.unpack(">H", self._read(2))
            elif size == 127:
                (size,) = struct.unpack(">Q", self._read(8))
            payload = self._read(size)
            if b0 & 0x0F in (0x9, 0xA):  # ping, pong
                continue
            opcode = opcode if b0 & 0x0F == 0 else b0 & 0x0F
            parts.append(payload)
            if b0 & 0x80:
                assert opcode is not None
                return opcode, b"".join(parts)

    def send(self, operation: dict[str, Any]) -> None:
        data, mask = json.dumps(operation).encode(), os.urandom(4)
        size = len(data)
        head = bytes([0x81]) + (
            bytes([0x80 | size]) if size < 126 else bytes([0x80 | 126]) + struct.pack(">H", size)
        )
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def _handle_text(self, payload: bytes) -> None:
        operation = json.loads(payload)
        if operation["op"] == "serverInfo":
            self.server_info = operation
        elif operation["op"] == "advertise":
            self.channels.update({c["id"]: c for c in operation["channels"]})
        elif operation["op"] == "status" and "Unknown channel ID" in operation.get("message", ""):
            # The SDK's server advertised a channel it had not yet recorded for this client
            # (the client connected as the channel was made): this connection cannot have it.
            raise SubscriptionRefusedError(operation["message"])

    def wait_for_topics(self, topics: set[str]) -> dict[str, dict[str, Any]]:
        """Read until every topic of ``topics`` is advertised; the advertised channels."""
        self.deadline = time.monotonic() + self.timeout_s
        while not topics <= {c["topic"] for c in self.channels.values()}:
            opcode, payload = self.frame()
            if opcode == 0x1:
                self._handle_text(payload)
        return {c["topic"]: c for c in self.channels.values()}

    def subscribe(self, topics: set[str]) -> None:
        channels = self.wait_for_topics(topics)
        subscriptions = []
        for topic in sorted(topics):
            number = len(self.subscriptions) + 1
            self.subscriptions[number] = topic
            subscriptions.append({"id": number, "channelId": channels[topic]["id"]})
        self.send({"op": "subscribe", "subscriptions": subscriptions})

    def message(self, topic: str) -> tuple[int, bytes]:
        """The next message on ``topic``: (log time ns, CDR bytes); those of other topics
        that come first are kept for later."""
        self.deadline = time.monotonic() + self.timeout_s
        while not self.pending.get(topic):
            opcode, payload = self.frame()
            if opcode == 0x1:
                self._handle_text(payload)
                continue
            assert opcode == 0x2
            assert payload[0] == 0x01  # message data
            number, log_ns = struct.unpack_from("<IQ", payload, 1)
            self.pending.setdefault(self.subscriptions[number], []).append((log_ns, payload[13:]))
        return self.pending[topic].pop(0)


def typestore() -> Any:
    """rosbags' ROS 2 Jazzy store with Foxglove's VoxelGrid registered, to decode with."""
    from rosbags.typesys import get_types_from_msg

    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(
        get_types_from_msg(
            FOXGLOVE_PACKED_ELEMENT_FIELD_MSG, "foxglove_msgs/msg/PackedElementField"
        )
    )
    store.register(get_types_from_msg(FOXGLOVE_VOXEL_GRID_MSG, "foxglove_msgs/msg/VoxelGrid"))
    return store


@pytest.fixture(scope="module")
def result(tmp_path_factory: pytest.TempPathFactory, essex_simulated: Path) -> Path:
    dataset = copy_of(essex_simulated, tmp_path_factory, "live")
    run_batch(dataset, figures=False)
    return dataset / "result"


@pytest.fixture
def view() -> Iterator[LiveView]:
    live = LiveView(port=0)
    try:
        yield live.start()
    finally:
        live.stop()


@pytest.fixture
def clients() -> Iterator[list[FoxgloveClient]]:
    opened: list[FoxgloveClient] = []
    try:
        yield opened
    finally:
        for client in opened:
            client.close()


def connect(view: LiveView, clients: list[FoxgloveClient]) -> FoxgloveClient:
    client = FoxgloveClient(view.port)
    clients.append(client)
    return client


def export_topics(result: Path) -> dict[str, str]:
    """{topic: ROS type} of what ``coopmap export`` writes for the result."""
    content = read_result(result)
    messages, _ = result_messages(RosMessages(), content.config, content.trajectories,
                                  content.grid, odometry=content.odometry,
                                  report=content.report)  # fmt: skip
    return {m.topic: m.msgtype for m in messages}


def test_a_client_that_joins_late_gets_every_topic_of_the_bag_latched(
    result: Path, view: LiveView, clients: list[FoxgloveClient]
) -> None:
    view.publish_result(result)
    client = connect(view, clients)
    topics = export_topics(result)
    channels = client.wait_for_topics(set(topics))
    assert client.server_info is not None
    assert client.server_info["name"] == "coopmap"
    assert set(channels) == set(topics)
    for topic, channel in channels.items():
        assert channel["encoding"] == "cdr"
        assert channel["schemaEncoding"] == "ros2msg"
        assert channel["schemaName"] == topics[topic]
        assert channel["schema"] == RosMessages().msgdef(topics[topic])
    client.subscribe({"/map", "/map/voxels"})
    store = typestore()
    log_ns, data = client.message("/map")
    grid = store.deserialize_cdr(data, "nav_msgs/msg/OccupancyGrid")
    assert int(grid.header.stamp.sec) * 10**9 + int(grid.header.stamp.nanosec) == log_ns
    check_ceiling_band(grid, result)
    # A second client joining now gets the map as well.
    late = connect(view, clients)
    late.subscribe({"/map"})
    _, again = late.message("/map")
    assert again == data


def test_every_client_that_subscribes_gets_the_latched_message(
    result: Path, view: LiveView, clients: list[FoxgloveClient]
) -> None:
    """Twenty clients in a row, each subscribing as it connects: each gets the latched map,
    the same bytes."""
    view.publish_result(result)
    got = []
    for _ in range(20):
        client = connect(view, clients)
        client.subscribe({"/map"})
        got.append(client.message("/map")[1])
        client.close()
    assert len(set(got)) == 1


def test_a_subscription_that_comes_as_the_view_stops_still_gets_the_latest_message(
    result: Path, clients: list[FoxgloveClient]
) -> None:
    view = LiveView(port=0).start()
    try:
        view.publish_result(result)
        # The resender has ended (as it does when stop begins) before the client subscribes:
        # only stop itself can answer the subscription.
        view._requests.put(None)
        assert view._resender is not None
        view._resender.join(timeout=TIMEOUT_S)
        client = connect(view, clients)
        client.subscribe({"/map"})
        deadline = time.monotonic() + TIMEOUT_S
        while view._requests.empty():
            assert time.monotonic() < deadline, "the subscription never reached the view"
            time.sleep(0.005)
    finally:
        view.stop()
    _, data = client.message("/map")
    grid = typestore().deserialize_cdr(data, "nav_msgs/msg/OccupancyGrid")
    check_ceiling_band(grid, result)


def test_the_voxel_grid_holds_every_occupied_voxel_at_its_cell(
    result: Path, view: LiveView, clients: list[FoxgloveClient]
) -> None:
    client = connect(view, clients)
    view.publish_result(result)
    client.subscribe({"/map/voxels"})
    _, data = client.message("/map/voxels")
    voxels = typestore().deserialize_cdr(data, "foxglove_msgs/msg/VoxelGrid")
    check_voxel_grid(voxels, load_map(result / "map.npz"))


def test_a_subscriber_gets_each_new_state_as_it_is_published(
    result: Path, view: LiveView, clients: list[FoxgloveClient]
) -> None:
    content = read_result(result)
    ros = RosMessages()
    messages, _ = result_messages(ros, content.config, content.trajectories, content.grid,
                                  odometry=content.odometry)  # fmt: skip
    first = [m for m in messages if m.topic == "/a/path"]
    view.publish(first[:2])
    client = connect(view, clients)
    client.subscribe({"/a/path"})
    store = typestore()
    _, data = client.message("/a/path")
    assert len(store.deserialize_cdr(data, "nav_msgs/msg/Path").poses) == 2
    view.publish(first)
    _, data = client.message("/a/path")
    path = store.deserialize_cdr(data, "nav_msgs/msg/Path")
    _, poses = read_tum(result / "poses" / "a.tum")
    assert len(path.poses) == len(poses)
    np.testing.assert_allclose([[p.pose.position.x, p.pose.position.y] for p in path.poses],
                               poses[:, :2], atol=1e-12)  # fmt: skip


def test_the_latest_state_keeps_the_newest_transform_of_every_frame(result: Path) -> None:
    content = read_result(result)
    ros = RosMessages()
    messages, _ = result_messages(ros, content.config, content.trajectories, content.grid,
                                  odometry=content.odometry)  # fmt: skip
    state = {m.topic: m for m in latest_state(messages, ros)}
    assert set(state) == {m.topic for m in messages}
    tf = state["/tf"].message.transforms
    assert sorted(t.child_frame_id for t in tf) == ["a/base_link", "a/odom", "b/base_link",
                                                    "b/odom"]  # fmt: skip
    newest: dict[str, int] = {}
    for m in messages:
        if m.topic == "/tf":
            for t in m.message.transforms:
                stamp = int(t.header.stamp.sec) * 10**9 + int(t.header.stamp.nanosec)
                newest[t.child_frame_id] = max(newest.get(t.child_frame_id, 0), stamp)
    for t in tf:
        stamp = int(t.header.stamp.sec) * 10**9 + int(t.header.stamp.nanosec)
        assert stamp == newest[t.child_frame_id]
    assert state["/tf"].stamp_ns == max(newest.values())
    for r in "ab":
        paths = [m for m in messages if m.topic == f"/{r}/path"]
        assert state[f"/{r}/path"] is paths[-1]
    assert latest_state([], ros) == []
    single = BagMessage("/x", "std_msgs/msg/String", 5, ros.tf([]))
    assert latest_state([single], ros) == [single]


def test_a_port_in_use_and_a_bad_host_are_one_line_errors() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(EstimationError, match=rf"^live view: cannot listen on 127\.0\.0\.1:"
                           rf"{port}: Address already in use"):  # fmt: skip
            LiveView(port=port).start()
        result = CliRunner().invoke(
            app, ["batch", "no-such-dataset", "--view", "--view-port", str(port)]
        )
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith(f"coopmap: error: live view: cannot listen on 127.0.0.1:{port}")
    with pytest.raises(EstimationError, match=r"^live view: cannot listen on no\.such\.host\."):
        LiveView(host="no.such.host.invalid", port=0).start()
    with pytest.raises(EstimationError, match=r"port must be in 0\.\.65535, got 70000"):
        LiveView(port=70000)


def test_the_port_is_free_when_stop_returns() -> None:
    # The SDK closes its listening socket a moment after its stop returns; the view waits.
    for _ in range(30):
        view = LiveView(port=0).start()
        port = view.port
        view.stop()
        with socket.socket() as again:
            again.bind(("127.0.0.1", port))
        view.stop()  # idempotent


def test_stop_waits_for_the_listening_socket_to_close_and_no_longer() -> None:
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    port = listener.getsockname()[1]
    started = time.monotonic()  # before the timer starts: its 0.3 s count from here at least
    threading.Timer(0.3, listener.close).start()
    _wait_released("127.0.0.1", port, 5.0)
    assert 0.3 <= time.monotonic() - started < 2.0
    with socket.socket() as again:
        again.bind(("127.0.0.1", port))
    with socket.socket() as held:  # never released: the wait ends at its bound
        held.bind(("127.0.0.1", 0))
        held.listen()
        started = time.monotonic()
        _wait_released("127.0.0.1", held.getsockname()[1], 0.2)
        assert 0.2 <= time.monotonic() - started < 1.5
    _wait_released("no.such.host.invalid", 1, 5.0)  # a host that does not resolve: no wait


def test_batch_view_serves_the_result_for_the_seconds_asked(result: Path, tmp_path: Path) -> None:
    started = time.monotonic()
    out = CliRunner().invoke(
        app,
        ["batch", str(result.parent), "--out", str(tmp_path / "result"), "--view",
         "--view-port", "0", "--view-seconds", "2"],
    )  # fmt: skip
    assert out.exit_code == 0, out.output
    assert time.monotonic() - started >= 2.0
    lines = out.output.splitlines()
    assert lines[0].startswith("live view: ws://127.0.0.1:")
    port = int(lines[0].split()[2].rsplit(":", 1)[1])
    assert port > 0
    assert f"live view: serving the result at ws://127.0.0.1:{port} for 2 s" in lines
    with socket.socket() as again:  # the server stopped and let the port go
        again.bind(("127.0.0.1", port))


def test_simulate_view_publishes_the_loops_estimate_after_every_dwell(
    tmp_path: Path, view: LiveView, clients: list[FoxgloveClient]
) -> None:
    mission = tmp_path / "mission.yaml"
    mission.write_text(yaml.safe_dump({
        "world": str(REPO / "configs" / "worlds" / "essex_lab.yaml"), "seed": 0,
        "robots": [{"name": "a", "start": [2.0, 3.5, 20]}, {"name": "b", "start": [3.5, 5.75, 220]}],
        "plan": "auto", "auto": {"stations": 2, "scans_per_station": 1, "planner": "map"},
    }), encoding="utf-8")  # fmt: skip
    client = connect(view, clients)
    store = typestore()
    dwells: list[int] = []
    received: list[int] = []

    published: dict[str, np.ndarray] = {}  # the loop's estimate as last published

    def observe(loop: Any) -> None:
        view.publish_loop(loop)
        dwells.append(len(loop.map.grid.occupied()[0]))
        for robot in "ab":
            keys = sorted(k for k in loop.estimate if split_key(k)[0] == robot)
            published[robot] = np.array([loop.estimate[k][:2] for k in keys])
        if len(dwells) == 1:  # joins after the first state: it is sent on subscribing
            client.subscribe({"/map/points"})
            _, data = client.message("/map/points")
            received.append(store.deserialize_cdr(data, "sensor_msgs/msg/PointCloud2").width)

    flown = run_simulation(mission, tmp_path / "dataset", observe=observe)
    assert flown.loop is not None
    assert len(dwells) == flown.loop["dwells"] >= 3
    while len(received) < len(dwells):
        _, data = client.message("/map/points")
        received.append(store.deserialize_cdr(data, "sensor_msgs/msg/PointCloud2").width)
    assert received == dwells
    assert dwells[-1] > dwells[0] > 0  # the map grew dwell by dwell
    # The last state: every robot's poses as the loop estimated them at its last dwell, near
    # the result's settled ones (before the last station's link is in, a turn left untied
    # rests on odometry: centimetres).
    client.subscribe({"/a/path", "/b/path"})
    for robot in "ab":
        _, data = client.message(f"/{robot}/path")
        path = store.deserialize_cdr(data, "nav_msgs/msg/Path")
        _, final = read_tum(tmp_path / "dataset" / "result" / "poses" / f"{robot}.tum")
        assert len(path.poses) == len(final)
        estimated = np.array([[p.pose.position.x, p.pose.position.y] for p in path.poses])
        np.testing.assert_allclose(estimated, published[robot], atol=1e-6)
        assert np.abs(estimated - final[:, :2]).max() < 0.1


def test_simulate_view_needs_a_mission_flown_by_the_loop(tmp_path: Path) -> None:
    result = CliRunner().invoke(
        app, ["simulate", "essex_lab", "--out", str(tmp_path / "d"), "--view", "--view-port", "0"]
    )
    assert result.exit_code == 2
    assert result.output.strip().endswith(
        "--view shows the mission loop's estimate, and this mission is not flown by it (plan: "
        "auto with auto.planner: map); run coopmap batch --view on the dataset instead"
    )
    assert not (tmp_path / "d").exists()


def test_the_layout_names_only_topics_the_bag_holds(result: Path) -> None:
    layout = json.loads(LAYOUT.read_text(encoding="utf-8"))
    panels = layout["configById"]
    assert set(layout) == {"configById", "globalVariables", "userNodes", "playbackConfig",
                           "layout"}  # fmt: skip

    def leaves(node: Any) -> list[str]:
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(panels)
    topics = set(export_topics(result))
    named = set()
    for panel_id, config in panels.items():
        kind = panel_id.split("!")[0]
        assert kind in {"3D", "Plot"}, panel_id
        if kind == "3D":
            assert config["followTf"] == "map"
            named |= set(config["topics"])
        else:
            named |= {p["value"].split(".")[0] for p in config["paths"]}
    assert named <= topics
    assert {"/map", "/map/voxels", "/a/path", "/b/path", "/a/pose", "/markers"} <= named
