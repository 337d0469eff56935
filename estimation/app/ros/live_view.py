"""A live view in Foxglove: the bag's topics, as the work goes, over a Foxglove WebSocket
(docs/ros.md, "Live view in Foxglove").

:class:`LiveView` runs a WebSocket server of the Foxglove SDK (protocol ``foxglove.sdk.v1``)
and publishes the messages of :func:`~estimation.app.ros.export.result_messages` — the same
topics, ROS 2 types and CDR bytes as ``coopmap export`` writes, each channel with its
``ros2msg`` schema — so one Foxglove layout serves the bag and the live view. A live view shows
the latest state, not the history: per topic its last message, and for ``/tf`` and
``/tf_static`` the latest transform of every child frame. Every topic is latched: a client that
subscribes gets the topic's latest message at once.

The server listens on the loopback interface unless told otherwise; it serves anyone who can
reach it, without authentication.
"""

from __future__ import annotations

import errno
import queue
import socket
import threading
import time
from collections.abc import Iterable
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import foxglove
import numpy as np
from foxglove.websocket import ChannelView, Client, ServerListener

from estimation.app.ros.bag import BagMessage
from estimation.app.ros.export import Trajectory, read_result, result_messages
from estimation.app.ros.messages import RosMessages
from estimation.errors import EstimationError
from sensors.trajio import pose_at

if TYPE_CHECKING:
    from estimation.app.mission.loop import MissionLoop

__all__ = ["DEFAULT_HOST", "DEFAULT_PORT", "LiveView", "latest_state"]

DEFAULT_HOST = "127.0.0.1"
#: Foxglove's default port for a WebSocket connection.
DEFAULT_PORT = 8765
_TF_TOPICS = ("/tf", "/tf_static")
#: How long :meth:`LiveView.stop` waits for the server's socket to close (it closes a moment
#: after the SDK's ``stop`` returns).
_RELEASE_S = 5.0
#: How long after the last message logged :meth:`LiveView.stop` lets the server send it: the
#: SDK sends from queues of its own, has no flush, and drops what is still queued when it stops.
_FLUSH_S = 0.5
#: How long the resender waits after a subscription before it resends the topic's latest
#: message. The SDK's server has been reported to call ``on_subscribe`` before the new
#: subscriber is registered, so that a message logged at once does not reach it (foxglove-sdk
#: pull request 533, 2–5 % of latched messages); not seen with the version used here.
_SETTLE_S = 0.05


def latest_state(messages: Iterable[BagMessage], ros: RosMessages) -> list[BagMessage]:
    """The state a stream of messages ends in: per topic its last message (by stamp, then
    order); for ``/tf`` and ``/tf_static`` one message holding the latest transform of every
    child frame, stamped with the latest of them."""
    last: dict[str, BagMessage] = {}
    frames: dict[str, dict[str, tuple[int, Any]]] = {}
    for m in messages:
        if m.topic in _TF_TOPICS:
            held = frames.setdefault(m.topic, {})
            for t in m.message.transforms:
                stamp = int(t.header.stamp.sec) * 10**9 + int(t.header.stamp.nanosec)
                if t.child_frame_id not in held or held[t.child_frame_id][0] <= stamp:
                    held[t.child_frame_id] = (stamp, t)
        if m.topic not in last or last[m.topic].stamp_ns <= m.stamp_ns:
            last[m.topic] = m
    out = []
    for topic, m in last.items():
        if topic in frames:
            held = frames[topic]
            stamp = max(s for s, _ in held.values())
            message = ros.tf([t for _, t in held.values()])
            m = BagMessage(topic, m.msgtype, stamp, message, m.latched)
        out.append(m)
    return out


def _wait_released(host: str, port: int, seconds: float) -> None:
    """Wait until ``host``:``port`` can be bound again, for at most ``seconds``: the SDK's
    server closes its listening socket a moment after ``stop`` returns."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except OSError:
        return
    deadline = time.monotonic() + seconds
    while True:
        with socket.socket(family, kind, proto) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                probe.bind(address)
                return
            except OSError as exc:
                if exc.errno != errno.EADDRINUSE or time.monotonic() > deadline:
                    return
        time.sleep(0.002)


class _Latch(ServerListener):
    """Hands the topics that a client subscribed to to the view's resender thread: the
    server's callback returns at once and never waits for a lock of the view."""

    def __init__(self, requests: queue.SimpleQueue[str | None]) -> None:
        self.requests = requests

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        self.requests.put(channel.topic)


class LiveView:
    """A Foxglove WebSocket server publishing coopmap's topics (see the module's docstring).

    Use it as a context manager (``with LiveView(port=0) as view: view.publish_result(...)``);
    ``port`` 0 takes any free port, which :attr:`port` then tells.
    """

    def __init__(self, *, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT) -> None:
        if not 0 <= port <= 65535:
            raise EstimationError(f"live view: port must be in 0..65535, got {port}")
        self.host, self._asked_port = host, port
        self.ros = RosMessages()
        #: Held while a message is logged: a topic's latest message is the one logged last.
        self._lock = threading.Lock()
        self._requests: queue.SimpleQueue[str | None] = queue.SimpleQueue()
        self._resender: threading.Thread | None = None
        self._context: Any = None
        self._server: Any = None
        self._channels: dict[str, Any] = {}
        self._latest: dict[str, tuple[int, bytes]] = {}
        self._first_seen: dict[tuple[str, int], float] = {}
        self._last_log = -float("inf")  # time.monotonic() of the last message logged

    # -- the server ----------------------------------------------------------------------------

    def start(self) -> LiveView:
        """Listen on ``host``:``port``; EstimationError (one line) when that is not possible."""
        if self._server is not None:
            return self
        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(
                name="coopmap",
                host=self.host,
                port=self._asked_port,
                context=self._context,
                server_listener=_Latch(self._requests),
            )
        except RuntimeError as exc:
            reason = str(exc).removeprefix("FoxgloveError: ").removeprefix("Failed to bind port: ")
            raise EstimationError(
                f"live view: cannot listen on {self.host}:{self._asked_port}: {reason}"
            ) from None
        self._resender = threading.Thread(target=self._resend, name="live-view", daemon=True)
        self._resender.start()
        return self

    def stop(self) -> None:
        """Close the channels and stop the server (idempotent). When it returns, the port is
        free again (waited for up to a few seconds)."""
        server, self._server = self._server, None
        if server is None:
            return
        # Clients that subscribed before the end get the latest state before the server stops.
        self._requests.put(None)
        if self._resender is not None:
            self._resender.join()
        # Subscriptions that reached the server while the resender ended are answered here.
        pending, _ = self._queued()
        if pending:
            time.sleep(_SETTLE_S)
        for topic in dict.fromkeys(pending):
            self._resend_latest(topic)
        time.sleep(max(0.0, self._last_log + _FLUSH_S - time.monotonic()))
        port = int(server.port)
        server.stop()
        _wait_released(self.host, port, _RELEASE_S)
        with self._lock:
            for channel in self._channels.values():
                channel.close()
            self._channels.clear()

    def __enter__(self) -> LiveView:
        return self.start()

    def __exit__(
        self,
        kind: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    @property
    def port(self) -> int:
        """The port the server listens on (the bound one when asked for port 0)."""
        if self._server is None:
            raise EstimationError("live view: the server is not running")
        return int(self._server.port)

    @property
    def url(self) -> str:
        """``ws://host:port``, the address to open in Foxglove."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    # -- publishing ----------------------------------------------------------------------------

    def publish(self, messages: Iterable[BagMessage]) -> list[str]:
        """Publish the state ``messages`` end in (:func:`latest_state`); returns the topics."""
        if self._server is None:
            raise EstimationError("live view: the server is not running")
        topics = []
        for m in sorted(latest_state(messages, self.ros), key=lambda m: m.stamp_ns):
            data = self.ros.serialize(m.message)
            with self._lock:
                channel = self._channels.get(m.topic)
                if channel is None:
                    schema = foxglove.Schema(
                        name=m.msgtype, encoding="ros2msg", data=self.ros.msgdef(m.msgtype).encode()
                    )
                    channel = foxglove.Channel(
                        m.topic, schema=schema, message_encoding="cdr", context=self._context
                    )
                    self._channels[m.topic] = channel
                self._latest[m.topic] = (m.stamp_ns, data)
                channel.log(data, log_time=m.stamp_ns)
                self._last_log = time.monotonic()
            topics.append(m.topic)
        return topics

    def _resend(self) -> None:
        """Publish a topic's latest message again when a client subscribed to it."""
        while (topic := self._requests.get()) is not None:
            time.sleep(_SETTLE_S)  # once for the subscriptions that come together
            more, ended = self._queued()
            for each in dict.fromkeys([topic, *more]):
                self._resend_latest(each)
            if ended:
                return

    def _queued(self) -> tuple[list[str], bool]:
        """The topics whose subscriptions are queued now, and whether the end is among them."""
        topics: list[str] = []
        ended = False
        while True:
            try:
                topic = self._requests.get_nowait()
            except queue.Empty:
                return topics, ended
            if topic is None:
                ended = True
            else:
                topics.append(topic)

    def _resend_latest(self, topic: str) -> None:
        with self._lock:
            channel, latest = self._channels.get(topic), self._latest.get(topic)
            if channel is not None and latest is not None:
                channel.log(latest[1], log_time=latest[0])
                self._last_log = time.monotonic()

    def publish_result(
        self, result_dir: Path | str, *, dataset_dir: Path | str | None = None
    ) -> list[str]:
        """Publish a result folder's final state (as ``coopmap export`` reads it); returns
        the notes on what could not be published."""
        content = read_result(result_dir, dataset_dir=dataset_dir)
        messages, notes = result_messages(
            self.ros,
            content.config,
            content.trajectories,
            content.grid,
            odometry=content.odometry,
            report=content.report,
        )
        self.publish(messages)
        return content.notes + notes

    def publish_loop(self, loop: MissionLoop) -> None:
        """Publish the mission loop's state after a dwell: the estimated map, every robot's
        estimated poses (each stamped with the mission time it was first estimated at) and its
        odometry frames. The searches' markers come with the final result."""
        from estimation.posegraph.keys import split_key

        poses: dict[str, dict[int, np.ndarray]] = {}
        for key, pose in loop.estimate.items():
            robot, index = split_key(key)
            poses.setdefault(robot, {})[index] = pose
            self._first_seen.setdefault((robot, index), loop.now_s)
        trajectories = {}
        for robot in loop.robots:
            indices = sorted(poses.get(robot, {}))
            if indices:
                stamps = np.array([self._first_seen[(robot, i)] for i in indices])
                estimate = np.array([poses[robot][i] for i in indices])
                trajectories[robot] = Trajectory(indices, stamps, estimate, None)
        if not trajectories:
            return
        odometry: dict[str, tuple[np.ndarray, np.ndarray]] | None = {}
        for robot, trajectory in trajectories.items():
            times, samples = loop.odometry[robot]
            if not len(times):
                odometry = None
                break
            assert odometry is not None
            # Only the samples the state ends in: at the poses' stamps, and the last one.
            wanted = np.unique(np.append(trajectory.stamps_s, times[-1]))
            odometry[robot] = (wanted, pose_at(times, samples, wanted))
        messages, _ = result_messages(
            self.ros, loop.config, trajectories, loop.map.grid, odometry=odometry
        )
        self.publish(messages)
