"""coopmap's maps and poses as ROS 2 messages (rosbags typestore objects, serialized as CDR).

Conventions (docs/ros.md): stamps are mission time in nanoseconds (ROS time = mission clock);
planar poses (x_m, y_m, yaw_rad) become 3D poses on the floor (z = 0) rotated about z. A pose
covariance given in gtsam's tangent space of the pose — (x, y) along the robot's axes, then yaw
— is rotated into the header's frame for ``geometry_msgs/PoseWithCovariance`` (rows and columns
x, y, z, roll, pitch, yaw; z, roll and pitch are 0), as ROS localizers publish it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from mapping.band import Band

__all__ = [
    "FOXGLOVE_PACKED_ELEMENT_FIELD_MSG",
    "FOXGLOVE_VOXEL_GRID_MSG",
    "OCTOMAP_MSG",
    "ROS_DISTRO",
    "Color",
    "PlanarPose",
    "RosMessages",
    "covariance_6x6",
    "stamp_ns",
]

#: The ROS 2 release whose message definitions the bag carries (Humble's are the same on the
#: wire for every type written here).
ROS_DISTRO = Stores.ROS2_JAZZY
#: ``octomap_msgs/msg/Octomap`` as the package defines it (rosbags' stores lack it).
OCTOMAP_MSG = """\
# A 3D map in binary format, as Octree
std_msgs/Header header

# Flag to denote a binary (only free/occupied) or full occupancy octree (.bt/.ot file)
bool binary

# Class id of the contained octree
string id

# Resolution (in m) of the smallest octree nodes
float64 resolution

# binary serialization of octree, use conversions.h to read and write octrees
int8[] data
"""
#: ``foxglove_msgs/msg/PackedElementField`` and ``foxglove_msgs/msg/VoxelGrid`` as Foxglove's
#: schema reference (docs.foxglove.dev, "VoxelGrid") defines them for ROS 2; Foxglove's 3D panel
#: knows them by these names.
FOXGLOVE_PACKED_ELEMENT_FIELD_MSG = """\
string name
uint32 offset
uint8 UNKNOWN=0
uint8 UINT8=1
uint8 INT8=2
uint8 UINT16=3
uint8 INT16=4
uint8 UINT32=5
uint8 INT32=6
uint8 FLOAT32=7
uint8 FLOAT64=8
uint8 type
"""
FOXGLOVE_VOXEL_GRID_MSG = """\
builtin_interfaces/Time timestamp
string frame_id
geometry_msgs/Pose pose
uint32 row_count
uint32 column_count
geometry_msgs/Vector3 cell_size
uint32 slice_stride
uint32 row_stride
uint32 cell_stride
foxglove_msgs/PackedElementField[] fields
uint8[] data
"""
#: ``coopmap_msgs/msg/LmsRaw``: one record of an LMS capture (docs/dataset.md, docs/ros.md).
#: ``stamp`` has nanosecond resolution; ``stamp_s`` keeps the capture's float64 stamp exactly,
#: so a capture goes through a bag byte for byte.
LMS_RAW_MSG = """\
# One record of a coopmap LMS capture: bytes as read from the LMS 200's serial port in one go.
builtin_interfaces/Time stamp   # receive time on the mission clock
float64 stamp_s                 # the same, as the capture holds it (float64 seconds, exact)
string capture_header           # the capture's JSON header line: in the first record only
uint8[] data                    # the bytes, as read
"""
#: A planar pose (x_m, y_m, yaw_rad).
PlanarPose = Sequence[float] | np.ndarray
#: sensor_msgs/PointField datatype FLOAT32.
_FLOAT32 = 7


def stamp_ns(t_s: float) -> int:
    """Mission time (s) → ROS time (ns); stamps before 0 are clamped to 0."""
    return max(0, round(t_s * 1e9))


def covariance_6x6(covariance_tangent: np.ndarray, yaw_rad: float) -> np.ndarray:
    """The (6, 6) row-major covariance of ``geometry_msgs/PoseWithCovariance`` from a pose's
    3×3 tangent-space covariance (x, y along the robot's axes, yaw): the position block is
    rotated into the header's frame by the pose's yaw."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    J = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    planar = J @ np.asarray(covariance_tangent, dtype=float) @ J.T
    out = np.zeros((6, 6))
    axes = [0, 1, 5]
    out[np.ix_(axes, axes)] = 0.5 * (planar + planar.T)
    return out


@dataclass(frozen=True)
class Color:
    r: float
    g: float
    b: float
    a: float = 1.0


class RosMessages:
    """Message factory on one typestore (``ROS_DISTRO`` plus ``octomap_msgs/msg/Octomap`` and
    ``coopmap_msgs/msg/LmsRaw``)."""

    def __init__(self) -> None:
        self.store = get_typestore(ROS_DISTRO)
        self.store.register(get_types_from_msg(OCTOMAP_MSG, "octomap_msgs/msg/Octomap"))
        self.store.register(get_types_from_msg(LMS_RAW_MSG, "coopmap_msgs/msg/LmsRaw"))
        for text, name in (
            (FOXGLOVE_PACKED_ELEMENT_FIELD_MSG, "foxglove_msgs/msg/PackedElementField"),
            (FOXGLOVE_VOXEL_GRID_MSG, "foxglove_msgs/msg/VoxelGrid"),
        ):
            self.store.register(get_types_from_msg(text, name))
        self._types = self.store.types

    def _type(self, name: str) -> Any:
        return self._types[name]

    def serialize(self, message: Any) -> bytes:
        return bytes(self.store.serialize_cdr(message, message.__msgtype__))

    def msgdef(self, msgtype: str) -> str:
        """The ``ros2msg`` schema text of ``msgtype`` with its dependencies, as MCAP and the
        Foxglove WebSocket protocol carry it."""
        return str(self.store.generate_msgdef(msgtype, ros_version=2)[0])

    # -- building blocks --------------------------------------------------------------------

    def time(self, ns: int) -> Any:
        return self._type("builtin_interfaces/msg/Time")(sec=ns // 10**9, nanosec=ns % 10**9)

    def header(self, ns: int, frame_id: str) -> Any:
        return self._type("std_msgs/msg/Header")(stamp=self.time(ns), frame_id=frame_id)

    def quaternion(self, xyzw: Sequence[float]) -> Any:
        x, y, z, w = (float(v) for v in xyzw)
        return self._type("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w)

    def pose(self, pose: PlanarPose, z_m: float = 0.0) -> Any:
        """A planar pose (x_m, y_m, yaw_rad) at height ``z_m``."""
        x, y, yaw = (float(v) for v in pose)
        point = self._type("geometry_msgs/msg/Point")(x=x, y=y, z=float(z_m))
        q = (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
        return self._type("geometry_msgs/msg/Pose")(position=point, orientation=self.quaternion(q))

    def transform(
        self, ns: int, parent: str, child: str, pose: PlanarPose, z_m: float = 0.0
    ) -> Any:
        """``geometry_msgs/TransformStamped``: the child frame at planar ``pose`` (x_m, y_m,
        yaw_rad) and height ``z_m`` in the parent frame."""
        x, y, yaw = (float(v) for v in pose)
        translation = self._type("geometry_msgs/msg/Vector3")(x=x, y=y, z=float(z_m))
        rotation = self.quaternion((0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)))
        return self._type("geometry_msgs/msg/TransformStamped")(
            header=self.header(ns, parent),
            child_frame_id=child,
            transform=self._type("geometry_msgs/msg/Transform")(
                translation=translation, rotation=rotation
            ),
        )

    # -- messages ---------------------------------------------------------------------------

    def tf(self, transforms: list[Any]) -> Any:
        return self._type("tf2_msgs/msg/TFMessage")(transforms=transforms)

    def occupancy_grid(self, ns: int, frame_id: str, band: Band) -> Any:
        """``nav_msgs/OccupancyGrid`` of a band: 0–100 = rint(100 × occupied share), −1 unknown;
        row 0 is the band's (lowest y), as in the message."""
        rows, cols = band.shape
        values = np.rint(np.clip(band.occupancy, 0.0, 1.0) * 100.0).astype(np.int8)
        values[~band.known] = -1
        info = self._type("nav_msgs/msg/MapMetaData")(
            map_load_time=self.time(ns),
            resolution=float(band.resolution_m),
            width=cols,
            height=rows,
            origin=self.pose((band.lower_xy[0], band.lower_xy[1], 0.0)),
        )
        return self._type("nav_msgs/msg/OccupancyGrid")(
            header=self.header(ns, frame_id), info=info, data=values.reshape(-1)
        )

    def point_cloud(
        self, ns: int, frame_id: str, points: np.ndarray, probability: np.ndarray
    ) -> Any:
        """``sensor_msgs/PointCloud2``: float32 x, y, z (m) and ``probability`` per point."""
        field = self._type("sensor_msgs/msg/PointField")
        names = ("x", "y", "z", "probability")
        fields = [
            field(name=n, offset=4 * i, datatype=_FLOAT32, count=1) for i, n in enumerate(names)
        ]
        table = np.column_stack(
            [
                np.asarray(points, dtype=np.float32).reshape(-1, 3),
                np.asarray(probability, dtype=np.float32).reshape(-1),
            ]
        )
        data = np.ascontiguousarray(table, dtype="<f4").view(np.uint8).reshape(-1)
        return self._type("sensor_msgs/msg/PointCloud2")(
            header=self.header(ns, frame_id),
            height=1,
            width=len(table),
            fields=fields,
            is_bigendian=False,
            point_step=16,
            row_step=16 * len(table),
            data=data,
            is_dense=True,
        )

    def pose_stamped(self, ns: int, frame_id: str, pose: PlanarPose) -> Any:
        return self._type("geometry_msgs/msg/PoseStamped")(
            header=self.header(ns, frame_id), pose=self.pose(pose)
        )

    def path(self, ns: int, frame_id: str, poses: list[Any]) -> Any:
        """``nav_msgs/Path`` of ``PoseStamped`` messages."""
        return self._type("nav_msgs/msg/Path")(header=self.header(ns, frame_id), poses=poses)

    def pose_with_covariance(
        self, ns: int, frame_id: str, pose: PlanarPose, covariance: np.ndarray
    ) -> Any:
        """``geometry_msgs/PoseWithCovarianceStamped``; ``covariance`` is (6, 6)."""
        inner = self._type("geometry_msgs/msg/PoseWithCovariance")(
            pose=self.pose(pose), covariance=np.asarray(covariance, dtype=float).reshape(36)
        )
        return self._type("geometry_msgs/msg/PoseWithCovarianceStamped")(
            header=self.header(ns, frame_id), pose=inner
        )

    def marker(
        self,
        ns: int,
        frame_id: str,
        namespace: str,
        marker_id: int,
        *,
        kind: str,
        color: Color,
        scale: tuple[float, float, float],
        pose: PlanarPose = (0.0, 0.0, 0.0),
        z_m: float = 0.0,
        points: np.ndarray | None = None,
        text: str = "",
    ) -> Any:
        """A ``visualization_msgs/Marker`` (``kind``: ``ARROW``, ``LINE_LIST``, …; ``points``
        (N, 3) in the marker's frame for arrows given by their ends and for lines)."""
        marker = self._type("visualization_msgs/msg/Marker")
        point = self._type("geometry_msgs/msg/Point")
        rgba = self._type("std_msgs/msg/ColorRGBA")
        vector = self._type("geometry_msgs/msg/Vector3")
        duration = self._type("builtin_interfaces/msg/Duration")
        corners = (
            []
            if points is None
            else [
                point(x=float(p[0]), y=float(p[1]), z=float(p[2]))
                for p in np.asarray(points, dtype=float)
            ]
        )
        return marker(
            header=self.header(ns, frame_id),
            ns=namespace,
            id=marker_id,
            type=getattr(marker, kind),
            action=marker.ADD,
            pose=self.pose(pose, z_m),
            scale=vector(x=scale[0], y=scale[1], z=scale[2]),
            color=rgba(r=color.r, g=color.g, b=color.b, a=color.a),
            lifetime=duration(sec=0, nanosec=0),
            frame_locked=False,
            points=corners,
            colors=[],
            texture_resource="",
            texture=self._type("sensor_msgs/msg/CompressedImage")(
                header=self.header(0, ""), format="", data=np.zeros(0, dtype=np.uint8)
            ),
            uv_coordinates=[],
            text=text,
            mesh_resource="",
            mesh_file=self._type("visualization_msgs/msg/MeshFile")(
                filename="", data=np.zeros(0, dtype=np.uint8)
            ),
            mesh_use_embedded_materials=False,
        )

    def marker_array(self, markers: list[Any]) -> Any:
        return self._type("visualization_msgs/msg/MarkerArray")(markers=markers)

    def octomap(
        self, ns: int, frame_id: str, tree_id: str, resolution_m: float, stream: bytes
    ) -> Any:
        """``octomap_msgs/Octomap`` of a binary tree's node stream (``.bt`` without header)."""
        return self._type("octomap_msgs/msg/Octomap")(
            header=self.header(ns, frame_id),
            binary=True,
            id=tree_id,
            resolution=float(resolution_m),
            data=np.frombuffer(stream, dtype=np.int8).copy(),
        )

    def voxel_grid(
        self,
        ns: int,
        frame_id: str,
        lower_corner_m: Sequence[float] | np.ndarray,
        cell_size_m: float,
        cells: np.ndarray,
    ) -> Any:
        """``foxglove_msgs/VoxelGrid`` of a block of cells: ``cells`` is a structured (nz, ny, nx)
        array (depth-, then row-major: z, y, x) whose fields (float32 or uint8) become the
        message's packed fields; cell (0, 0, 0) has its lower corner at ``lower_corner_m``
        (x, y, z in m) of the frame, the grid's axes are the frame's."""
        field = self._type("foxglove_msgs/msg/PackedElementField")
        kinds = {"<f4": field.FLOAT32, "|u1": field.UINT8}
        block = np.ascontiguousarray(cells)
        _, rows, columns = block.shape
        fields = []
        for name, (dtype, offset, *_) in (block.dtype.fields or {}).items():
            fields.append(field(name=name, offset=offset, type=kinds[dtype.str]))
        step = block.dtype.itemsize
        size = float(cell_size_m)
        x, y, z = (float(v) for v in lower_corner_m)
        return self._type("foxglove_msgs/msg/VoxelGrid")(
            timestamp=self.time(ns),
            frame_id=frame_id,
            pose=self.pose((x, y, 0.0), z),
            row_count=rows,
            column_count=columns,
            cell_size=self._type("geometry_msgs/msg/Vector3")(x=size, y=size, z=size),
            slice_stride=step * rows * columns,
            row_stride=step * columns,
            cell_stride=step,
            fields=fields,
            data=block.reshape(-1).view(np.uint8),
        )

    def string(self, text: str) -> Any:
        return self._type("std_msgs/msg/String")(data=text)

    def laser_scan(
        self,
        ns: int,
        frame_id: str,
        *,
        angles_rad: tuple[float, float, float],
        times_s: tuple[float, float],
        limits_m: tuple[float, float],
        ranges_m: np.ndarray,
        intensities: np.ndarray,
    ) -> Any:
        """``sensor_msgs/LaserScan``: ``angles_rad`` (min, max, increment) counter-clockwise from
        straight ahead, ``times_s`` (time_increment, scan_time), ``limits_m`` (range_min,
        range_max); ranges (m) and intensities as float32."""
        angle_min, angle_max, increment = angles_rad
        return self._type("sensor_msgs/msg/LaserScan")(
            header=self.header(ns, frame_id),
            angle_min=float(angle_min),
            angle_max=float(angle_max),
            angle_increment=float(increment),
            time_increment=float(times_s[0]),
            scan_time=float(times_s[1]),
            range_min=float(limits_m[0]),
            range_max=float(limits_m[1]),
            ranges=np.asarray(ranges_m, dtype=np.float32),
            intensities=np.asarray(intensities, dtype=np.float32),
        )

    def odometry(
        self,
        ns: int,
        frame_id: str,
        child_frame_id: str,
        xyz: Sequence[float],
        xyzw: Sequence[float],
    ) -> Any:
        """``nav_msgs/Odometry`` of a pose given as position ``xyz`` (m) and quaternion ``xyzw``,
        exactly as given (no normalisation); covariances and twist zero."""
        x, y, z = (float(v) for v in xyz)
        pose = self._type("geometry_msgs/msg/Pose")(
            position=self._type("geometry_msgs/msg/Point")(x=x, y=y, z=z),
            orientation=self.quaternion(xyzw),
        )
        vector = self._type("geometry_msgs/msg/Vector3")
        twist = self._type("geometry_msgs/msg/Twist")(
            linear=vector(x=0.0, y=0.0, z=0.0), angular=vector(x=0.0, y=0.0, z=0.0)
        )
        return self._type("nav_msgs/msg/Odometry")(
            header=self.header(ns, frame_id),
            child_frame_id=child_frame_id,
            pose=self._type("geometry_msgs/msg/PoseWithCovariance")(
                pose=pose, covariance=np.zeros(36)
            ),
            twist=self._type("geometry_msgs/msg/TwistWithCovariance")(
                twist=twist, covariance=np.zeros(36)
            ),
        )

    def lms_raw(self, stamp_s: float, data: bytes, capture_header: str = "") -> Any:
        """``coopmap_msgs/LmsRaw`` of one capture record (``LMS_RAW_MSG``)."""
        return self._type("coopmap_msgs/msg/LmsRaw")(
            stamp=self.time(stamp_ns(stamp_s)),
            stamp_s=float(stamp_s),
            capture_header=capture_header,
            data=np.frombuffer(data, dtype=np.uint8).copy(),
        )
