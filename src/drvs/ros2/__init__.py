"""drvs-ros2 (the `ros2` extra): DRVS's fused tracks on a robot's own ROS 2 topics, over Cyclone DDS
(drvs.ros2.bridge, drvs.ros2.cli), and DRVS recordings as rosbag2 (drvs.ros2.bag). No ROS
installation is needed: the message types come from the upstream .msg files shipped in
drvs/ros2/msg (drvs.ros2.types). docs/ros2.md describes the topics and how Nav2 and RViz use them."""

from __future__ import annotations

import argparse
import importlib.util
import sys

#: The `ros2` extra's libraries.
LIBRARIES = ("cyclonedds", "rosbags")


def rosbag2(args: argparse.Namespace) -> int:
    """drvs-replay FILE.mcap --rosbag2 OUT (drvs.ros2.bag.main); exit code 2 when another flag
    is given (it writes a bag and plays nothing), or, naming the extra, when the ros2 extra is missing."""
    others = [flag for flag, given in (
        ("--summary", args.summary), ("--json", args.json), ("--foxglove", args.foxglove is not None),
        ("--speed", args.speed is not None), ("--loop", args.loop), ("--no-wait", not args.wait),
    ) if given]  # fmt: skip
    if others:
        print(f"drvs-replay: --rosbag2 writes a bag and plays nothing: not with {', '.join(others)}", file=sys.stderr)
        return 2
    missing = [name for name in LIBRARIES if importlib.util.find_spec(name) is None]
    if missing:
        need = f"needs the ROS 2 extra: pip install 'drvs[ros2]' (no module named {missing[0]!r})"
        print(f"drvs-replay: --rosbag2 {need}", file=sys.stderr)
        return 2
    from drvs.ros2.bag import main

    return main(args.file, args.rosbag2)
