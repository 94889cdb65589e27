#!/usr/bin/env python3
"""Decodes every message of a microstereo recording with the reference MCAP readers
(the `mcap` and `mcap-ros2-support` packages): proof that tools other than ours read it.

Usage: check_mcap.py FILE.mcap [FILE.mcap ...]. Exit 0 when every message decodes and
the decoded fields agree with the channel's type; 1 otherwise.
"""
import sys
from collections import Counter

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

BYTES_PER_PIXEL = {"mono8": 1, "rgb8": 3, "32FC1": 4, "32SC1": 4}


def check(path):
    counts = Counter()
    problems = []
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        if header.profile != "ros2":
            problems.append(f"profile {header.profile!r}, not 'ros2'")
        for schema, channel, message, ros in reader.iter_decoded_messages():
            counts[(channel.topic, schema.name)] += 1
            if channel.message_encoding != "cdr" or schema.encoding != "ros2msg":
                problems.append(f"{channel.topic}: {channel.message_encoding}/{schema.encoding}")
            stamp = ros.header.stamp.sec * 10**9 + ros.header.stamp.nanosec
            if stamp != message.publish_time:
                problems.append(f"{channel.topic}: header stamp {stamp} ≠ publish time")
            if schema.name == "sensor_msgs/msg/Image":
                bpp = BYTES_PER_PIXEL.get(ros.encoding)
                if bpp is None or ros.step != ros.width * bpp or len(ros.data) != ros.step * ros.height:
                    problems.append(f"{channel.topic}: image {ros.width}x{ros.height} {ros.encoding} step {ros.step}, {len(ros.data)} bytes")
            elif schema.name == "sensor_msgs/msg/PointCloud2":
                names = [fld.name for fld in ros.fields]
                if names[:3] != ["x", "y", "z"] or len(ros.data) != ros.point_step * ros.width * ros.height:
                    problems.append(f"{channel.topic}: cloud fields {names}, {len(ros.data)} bytes")
            elif schema.name == "microstereo_msgs/msg/CellArray":
                for c in list(ros.left) + list(ros.right):
                    if len(c.contour) % 2 or not (c.x0 <= c.centroid[0] <= c.x1):
                        problems.append(f"{channel.topic}: cell {c.id} malformed")
            elif schema.name == "sensor_msgs/msg/CameraInfo":
                if len(ros.k) != 9 or len(ros.p) != 12 or ros.k[0] <= 0 or ros.width == 0:
                    problems.append(f"{channel.topic}: camera info k={list(ros.k)} p={list(ros.p)}")
            elif schema.name == "microstereo_msgs/msg/Targets":
                if ros.capture_ns != message.publish_time:
                    problems.append(f"{channel.topic}: capture_ns {ros.capture_ns} ≠ publish time")
                for c in ros.cells:
                    if len(c.contour) % 3:
                        problems.append(f"{channel.topic}: cell {c.id} contour not x,y,z")
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
    total = sum(counts.values())
    print(f"{path}: {total} messages on {len(counts)} channels decoded by mcap + mcap-ros2-support")
    for (topic, name), n in sorted(counts.items()):
        print(f"  {topic:<26} {name:<38} {n}")
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
