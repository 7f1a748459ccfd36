#!/usr/bin/env python3
"""A minimal "sign recogniser" in Python: how a downstream program plugs into handflow.

It subscribes to the trajectory samples of a running pipeline (shared memory, through the
`iceoryx2` package from PyPI: `pip install iceoryx2==0.10.0`) and reports two simple
events: a hand coming to the face, and the hands crossing. `sign_recogniser.rs` beside it
does the same in Rust.

    python3 examples/sign_recogniser.py &        # before the pipeline: it sees every sample
    target/release/handflow run --recording out/hands-cross

On another machine it reads the samples as JSON through the pipeline's Zenoh bridge (the
`eclipse-zenoh` package from PyPI, the version of the bridge's zenoh crate:
`pip install eclipse-zenoh==1.10.2`):

    python3 examples/sign_recogniser.py --zenoh tcp/rig-host:7447
"""

import argparse
import ctypes
import json
import math
import os
import sys

PROTOCOL_VERSION = 4  # handflow_protocol::messages::PROTOCOL_VERSION (the crate's test of this script fails when they differ)
END_OF_STREAM = 1
LOST = 2
# A hand is at the face closer than this to the head's centre (metres), and leaves it
# farther than the second (hysteresis: no flicker at the boundary).
AT_FACE_M = 0.20
LEFT_FACE_M = 0.25


class TrajectoryObject(ctypes.Structure):
    """One object's estimate; the layout of handflow_protocol::messages::TrajectoryObject."""

    _fields_ = [
        ("position", ctypes.c_double * 3),
        ("velocity", ctypes.c_double * 3),
        ("confidence", ctypes.c_double),
        ("state", ctypes.c_uint32),
        ("reserved", ctypes.c_uint32),
    ]

    @staticmethod
    def type_name() -> str:
        return "HandflowTrajectoryObject"


class TrajectorySample(ctypes.Structure):
    """Every object at one frame; the layout of handflow_protocol::messages::TrajectorySample."""

    _fields_ = [
        ("protocol_version", ctypes.c_uint32),
        ("flags", ctypes.c_uint32),
        ("sequence", ctypes.c_uint64),
        ("frame", ctypes.c_uint64),
        ("timestamp_s", ctypes.c_double),
        ("capture_unix_ns", ctypes.c_uint64),
        ("published_unix_ns", ctypes.c_uint64),
        ("dropped_frames", ctypes.c_uint64),
        ("missing_views", ctypes.c_uint32),  # bit k: camera k had no view in this frame set
        ("reserved", ctypes.c_uint32),
        ("objects", TrajectoryObject * 3),  # head, left hand, right hand
    ]

    @staticmethod
    def type_name() -> str:
        return "HandflowTrajectorySample"


class Recogniser:
    """Events from a stream of samples."""

    def __init__(self):
        self.at_face = [False, False]
        self.sides = None  # right hand to left hand when first seen; crossing reverses it
        self.crossed = False

    def observe(self, s):
        events = []
        head, left, right = s.objects[0], s.objects[1], s.objects[2]
        for k, (hand, name) in enumerate(((left, "left hand"), (right, "right hand"))):
            if hand.state == LOST or head.state == LOST:
                continue
            d = math.dist(tuple(hand.position), tuple(head.position))
            if not self.at_face[k] and d < AT_FACE_M:
                self.at_face[k] = True
                events.append(f"{name} at the face")
            elif self.at_face[k] and d > LEFT_FACE_M:
                self.at_face[k] = False
                events.append(f"{name} leaves the face")
        if left.state != LOST and right.state != LOST:
            between = [a - b for a, b in zip(left.position, right.position)]
            if self.sides is None:
                self.sides = between
            crossed = sum(a * b for a, b in zip(between, self.sides)) < 0.0
            if crossed != self.crossed:
                self.crossed = crossed
                events.append("hands crossed" if crossed else "hands uncrossed")
        return events


class Report:
    """What the recogniser has seen, for its summary."""

    def __init__(self):
        self.recogniser = Recogniser()
        self.samples, self.events, self.first, self.last, self.dropped = 0, 0, None, 0, 0

    def handle(self, s):
        """Handles one sample; True at the end of the stream."""
        if s.protocol_version != PROTOCOL_VERSION:
            print(f"skipping a sample of protocol version {s.protocol_version}", file=sys.stderr)
            return False
        if s.flags & END_OF_STREAM:
            frames = "none" if self.first is None else f"{self.first}..={self.last}"
            print(f"summary: {self.samples} samples, frames {frames}, {self.dropped} dropped upstream, {self.events} events")
            return True
        self.samples += 1
        self.first = s.frame if self.first is None else self.first
        self.last, self.dropped = s.frame, s.dropped_frames
        for event in self.recogniser.observe(s):
            self.events += 1
            print(f"frame {s.frame} t {s.timestamp_s:.3f} s: {event}", flush=True)
        return False


def sample_from_json(text):
    """A trajectory sample from the bridge's JSON form (`handflow/<rig>/trajectories/json`),
    with the fields the recogniser reads, named as in the binary layout."""
    d = json.loads(text)
    s = TrajectorySample()
    s.protocol_version = PROTOCOL_VERSION
    s.flags = END_OF_STREAM if d["end_of_stream"] else 0
    s.sequence, s.frame, s.timestamp_s, s.dropped_frames = d["sequence"], d["frame"], d["t"], d["dropped_frames"]
    states = {"tracked": 0, "predicted": 1, "lost": LOST}
    for k, label in enumerate(("head", "left_hand", "right_hand")):
        o = d["objects"].get(label)
        if o is None:
            s.objects[k].state = LOST
            continue
        s.objects[k].position[:] = o["pos"]
        s.objects[k].velocity[:] = o["vel"]
        s.objects[k].confidence = o["confidence"]
        s.objects[k].state = states.get(o["state"], LOST)
    return s


def run_zenoh(endpoint, rig):
    """Reads the trajectories of `rig` (every rig when None) behind a Zenoh endpoint."""
    import zenoh

    config = zenoh.Config()
    # Only the endpoint given (no multicast scouting); retry every 250 ms to 1 s, so a bridge
    # that restarts is found again within a second.
    for key, value in (
        ("mode", '"peer"'),
        ("scouting/multicast/enabled", "false"),
        ("connect/endpoints", json.dumps([endpoint])),
        ("connect/timeout_ms", "-1"),
        ("connect/exit_on_failure", "false"),
        ("connect/retry", "{ period_init_ms: 250, period_max_ms: 1000, period_increase_factor: 2 }"),
    ):
        config.insert_json5(key, value)
    report = Report()
    with zenoh.open(config) as session:
        subscriber = session.declare_subscriber(f"handflow/{rig or '*'}/trajectories/json")
        print(f"listening on `{endpoint}` (Zenoh)", flush=True)
        while True:
            sample = subscriber.recv()
            try:
                s = sample_from_json(sample.payload.to_string())
            except (ValueError, KeyError, TypeError) as e:
                print(f"skipping a malformed sample on {sample.key_expr}: {e}", file=sys.stderr)
                continue
            if report.handle(s):
                return 0


def handflow_iceoryx2_config(iox2):
    """handflow keeps each user's iceoryx2 files apart (protocol/src/ipc.rs, UserNamespace):
    a directory and a file prefix of the user's own. A subscriber must use the same."""
    uid = os.geteuid()
    config = iox2.config.default()
    config.global_cfg.root_path = iox2.Path.new(f"/tmp/handflow-iox2-{uid}/")
    config.global_cfg.prefix = iox2.FileName.new(f"hf{uid}_")
    return config


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--services", default="handflow", help="prefix of the pipeline's service names")
    parser.add_argument("--zenoh", metavar="ENDPOINT", help="read a pipeline on another machine through its Zenoh bridge")
    parser.add_argument("--rig", help="with --zenoh: the rig to follow (default: every rig there)")
    args = parser.parse_args()
    if args.zenoh:
        return run_zenoh(args.zenoh, args.rig)

    import iceoryx2 as iox2

    iox2.set_log_level_from_env_or(iox2.LogLevel.Error)
    node = iox2.NodeBuilder.new().config(handflow_iceoryx2_config(iox2)).create(iox2.ServiceType.Ipc)
    name = f"{args.services}/trajectories"
    # The publisher owns the service's settings (replay or live): open it as it is, and
    # wait for the pipeline if it has not started yet.
    while True:
        try:
            service = node.service_builder(iox2.ServiceName.new(name)).publish_subscribe(TrajectorySample).open()
            break
        except iox2.PublishSubscribeOpenError:
            node.wait(iox2.Duration.from_millis(50))
    subscriber = service.subscriber_builder().create()
    # Wake on the publisher's notification (the event service of the same name), or after
    # 100 ms at the latest.
    listener = node.service_builder(iox2.ServiceName.new(name)).event().open_or_create().listener_builder().create()
    waitset = iox2.WaitSetBuilder.new().create(iox2.ServiceType.Ipc)
    guard = waitset.attach_deadline(listener, iox2.Duration.from_millis(100))
    print(f"listening on `{name}`", flush=True)

    report = Report()
    while True:
        listener.try_wait_all() if hasattr(listener, "try_wait_all") else listener.try_wait()
        while True:
            sample = subscriber.receive()
            if sample is None:
                break
            if report.handle(sample.payload().contents):
                return 0
        _, result = waitset.wait_and_process()
        if result in (iox2.WaitSetRunResult.TerminationRequest, iox2.WaitSetRunResult.Interrupt):
            del guard
            return 0


if __name__ == "__main__":
    sys.exit(main())
