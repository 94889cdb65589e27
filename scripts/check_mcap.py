#!/usr/bin/env python3
"""Decodes every message of a microstereo recording with the reference MCAP readers
(the `mcap` and `mcap-ros2-support` packages) and again with `rosbags` (its own CDR
reader and message parser): proof that tools other than ours read it. Then checks that
the data fits together as ROS tools and Foxglove need it: `/tf_static` (latched) with
the cameras' optical frames and every frame a message names, CameraInfo beside every
image with the same stamps, labels as 16UC1, a cloud in metres with packed rgb, and a
MarkerArray beside the targets with one cell body per cell.

Usage: check_mcap.py FILE.mcap [FILE.mcap ...]. Exit 0 when every message decodes and
the decoded fields agree with the channel's type; 1 otherwise.
"""
import struct
import sys
from collections import Counter

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.typesys import Stores, get_typestore, get_types_from_msg

BYTES_PER_PIXEL = {"mono8": 1, "rgb8": 3, "32FC1": 4, "32SC1": 4, "16UC1": 2}
OPTICAL = {"left_camera_optical_frame", "right_camera_optical_frame"}


def rosbags_decodes(path):
    """Decodes every message with rosbags; returns (messages, problems)."""
    store = get_typestore(Stores.EMPTY)
    done, problems, n = set(), [], 0
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if schema.name not in done:
                done.add(schema.name)
                types = get_types_from_msg(schema.data.decode(), schema.name)
                store.register({k: v for k, v in types.items() if k not in store.fielddefs})
            try:
                store.deserialize_cdr(message.data, schema.name)
                n += 1
            except Exception as e:  # noqa: BLE001 - any failure is the finding
                problems.append(f"rosbags: {channel.topic}: {e}")
    return n, problems


def check(path):
    counts = Counter()
    problems = []
    stamps = {}  # topic -> [(publish time, header stamp)]
    frames_named = set()
    tree, latched = set(), False
    cells_at, bodies_at = {}, {}
    annotated = set()
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        if header.profile != "ros2":
            problems.append(f"profile {header.profile!r}, not 'ros2'")
        for schema, channel, message, ros in reader.iter_decoded_messages():
            counts[(channel.topic, schema.name)] += 1
            if channel.message_encoding != "cdr" or schema.encoding != "ros2msg":
                problems.append(f"{channel.topic}: {channel.message_encoding}/{schema.encoding}")
            if hasattr(ros, "header"):
                stamp = ros.header.stamp.sec * 10**9 + ros.header.stamp.nanosec
                if stamp != message.publish_time:
                    problems.append(f"{channel.topic}: header stamp {stamp} ≠ publish time")
                stamps.setdefault(channel.topic, []).append((message.publish_time, stamp))
                frames_named.add(ros.header.frame_id)
            if schema.name == "tf2_msgs/msg/TFMessage":
                latched = "durability: 1" in channel.metadata.get("offered_qos_profiles", "")
                for t in ros.transforms:
                    tree.add((t.header.frame_id, t.child_frame_id))
                    q = t.transform.rotation
                    if abs(q.x**2 + q.y**2 + q.z**2 + q.w**2 - 1) > 1e-9:
                        problems.append(f"{channel.topic}: {t.child_frame_id} rotation not unit")
            elif schema.name == "sensor_msgs/msg/Image":
                bpp = BYTES_PER_PIXEL.get(ros.encoding)
                if bpp is None or ros.step != ros.width * bpp or len(ros.data) != ros.step * ros.height:
                    problems.append(f"{channel.topic}: image {ros.width}x{ros.height} {ros.encoding} step {ros.step}, {len(ros.data)} bytes")
                if "/labels/" in channel.topic and ros.encoding != "16UC1":
                    problems.append(f"{channel.topic}: labels as {ros.encoding}, not 16UC1")
            elif schema.name == "sensor_msgs/msg/PointCloud2":
                names = [fld.name for fld in ros.fields]
                if names[:3] != ["x", "y", "z"] or len(ros.data) != ros.point_step * ros.width * ros.height:
                    problems.append(f"{channel.topic}: cloud fields {names}, {len(ros.data)} bytes")
                rgb = [fld for fld in ros.fields if fld.name == "rgb"]
                if not rgb or rgb[0].datatype != 7 or rgb[0].offset != 12:
                    problems.append(f"{channel.topic}: no packed rgb (float32 at 12): {names}")
                zs = [struct.unpack_from("<f", ros.data, i * ros.point_step + 8)[0]
                      for i in range(0, ros.width * ros.height, 97)]
                if any(not (0 < z < 10) for z in zs):
                    problems.append(f"{channel.topic}: depths {min(zs)}..{max(zs)} are not metres")
            elif schema.name == "visualization_msgs/msg/MarkerArray":
                ids = [m.id for m in ros.markers if m.type == 2 and m.ns in ("cells", "tracks")]
                if len(set(ids)) != len(ids):
                    problems.append(f"{channel.topic}: a cell's body twice")
                for m in ros.markers:
                    if m.action != 3:
                        frames_named.add(m.header.frame_id)
                bodies_at[(channel.topic, message.publish_time)] = sorted(
                    m.id for m in ros.markers if m.type == 2 and m.ns == "cells")
            elif schema.name == "foxglove_msgs/msg/ImageAnnotations":
                for a in ros.points:
                    if a.type != 2 or len(a.points) < 3:
                        problems.append(f"{channel.topic}: outline of type {a.type}, {len(a.points)} points")
                annotated.add(channel.topic)
            elif schema.name == "microstereo_msgs/msg/CellArray":
                for c in list(ros.left) + list(ros.right):
                    if len(c.contour) % 2 or not (c.x0 <= c.centroid[0] <= c.x1):
                        problems.append(f"{channel.topic}: cell {c.id} malformed")
            elif schema.name == "sensor_msgs/msg/CameraInfo":
                if len(ros.k) != 9 or len(ros.p) != 12 or ros.k[0] <= 0 or ros.width == 0:
                    problems.append(f"{channel.topic}: camera info k={list(ros.k)} p={list(ros.p)}")
                if ros.header.frame_id not in OPTICAL:
                    problems.append(f"{channel.topic}: camera info in {ros.header.frame_id!r}")
            elif schema.name == "microstereo_msgs/msg/Targets":
                if ros.capture_ns != message.publish_time:
                    problems.append(f"{channel.topic}: capture_ns {ros.capture_ns} ≠ publish time")
                for c in ros.cells:
                    if len(c.contour) % 3:
                        problems.append(f"{channel.topic}: cell {c.id} contour not x,y,z")
                cells_at[(channel.topic + "/markers", message.publish_time)] = sorted(
                    c.id for c in ros.cells)
            elif schema.name == "microstereo_msgs/msg/DisparityTiles":
                if ros.side not in ("left", "right") or ros.min_disparity >= ros.max_disparity:
                    problems.append(f"{channel.topic}: tiles side {ros.side!r}, range {ros.min_disparity}..{ros.max_disparity}")
                for t in ros.tiles:
                    if len(t.data) != t.width * t.height or t.x + t.width > ros.width or t.y + t.height > ros.height:
                        problems.append(f"{channel.topic}: tile {t.width}x{t.height} at {t.x},{t.y} with {len(t.data)} values")
                    if (t.left_cell == 0) != (t.right_cell == 0):
                        problems.append(f"{channel.topic}: tile of cells {t.left_cell}, {t.right_cell}")
            elif schema.name == "microstereo_msgs/msg/ManipulatorState":
                if ros.capture_ns != message.publish_time or len(ros.tip) != 3:
                    problems.append(f"{channel.topic}: capture_ns {ros.capture_ns} or tip {list(ros.tip)}")
                if len(ros.trajectory) % 4 or len(ros.plan_waypoints) % 3:
                    problems.append(f"{channel.topic}: trajectory or waypoints not whole points")
            elif schema.name == "microstereo_msgs/msg/Tracks":
                if ros.capture_ns != message.publish_time:
                    problems.append(f"{channel.topic}: capture_ns {ros.capture_ns} ≠ publish time")
                ids = [t.id for t in ros.tracks]
                if len(set(ids)) != len(ids):
                    problems.append(f"{channel.topic}: a track id twice in one frame")
                for t in ros.tracks:
                    if t.state not in ("tentative", "confirmed", "lost") or len(t.cell) > 1:
                        problems.append(f"{channel.topic}: track {t.id} state {t.state!r}, {len(t.cell)} cells")
            else:
                problems.append(f"{channel.topic}: unexpected type {schema.name}")
    # The frame tree holds the cameras' optical frames and every frame a message names.
    children = {c for _, c in tree}
    roots = {p for p, _ in tree} - children
    if not OPTICAL <= children or len(roots) != 1 or not latched:
        problems.append(f"/tf_static: frames {sorted(tree)}, roots {sorted(roots)}, latched {latched}")
    missing = frames_named - children - roots
    if missing:
        problems.append(f"frames named but not in /tf_static: {sorted(missing)}")
    # CameraInfo beside every image, with the same stamps.
    for topic in [t for t in stamps if t.endswith("/image")]:
        info = topic[: -len("image")] + "camera_info"
        if stamps.get(info) != stamps[topic]:
            problems.append(f"{topic}: its CameraInfo {info} has other stamps or none")
    # One cell body per cell of the same frame.
    if not cells_at:
        problems.append("no targets")
    for key, ids in cells_at.items():
        if bodies_at.get(key) != ids:
            problems.append(f"{key[0]} at {key[1]}: bodies {bodies_at.get(key)} for cells {ids}")
    # Each cell list's outlines over both camera images.
    for topic in [t for (t, n) in counts if n == "microstereo_msgs/msg/CellArray"]:
        for side in ("left", "right"):
            if f"{topic}/{side}/annotations" not in annotated:
                problems.append(f"{topic}: no image annotations for the {side} view")
    decoded, trouble = rosbags_decodes(path)
    problems += trouble
    total = sum(counts.values())
    print(f"{path}: {total} messages on {len(counts)} channels decoded by mcap + mcap-ros2-support, {decoded} by rosbags")
    for (topic, name), n in sorted(counts.items()):
        print(f"  {topic:<34} {name:<38} {n}")
    if total == 0:
        problems.append("no messages")
    for p in problems[:20]:
        print(f"  PROBLEM: {p}")
    return not problems


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    ok = all([check(p) for p in sys.argv[1:]])
    sys.exit(0 if ok else 1)
