#!/usr/bin/env python3
"""The fault campaign of BENCHMARKS.md: faults injected at random moments into real pipelines
(`handflow run`, release build), in replay and live mode, on a rendered and on a real
recording; per fault: recovered or not, time to recover, frames lost (exactly: against the
ingest sequence, and whether the publisher reported each one), output intact (every line
valid JSON, no frame twice), shared memory left behind. Not part of CI.

    scripts/faults.py                          # every fault, 6 trials per scenario (24 per fault)
    scripts/faults.py --trials 2 --only kill-flow,stop-cluster
    scripts/faults.py --json out/faults.json   # also the raw trials

Faults: kill-<stage> (SIGKILL), stop-<stage> (SIGSTOP for 0.5 to 5 s, then SIGCONT) for
ingest, flow, cluster, publish; stall-rust, stall-python, stall-zenoh, stall-websocket (a
subscriber that stops reading for 0.5 to 5 s); inject-<service> (malformed samples on frames,
particles, clusters, trajectories); disk-full (the output on a small tmpfs filled, then
freed); truncated-video and corrupt-frames (a copy of a recording damaged at random);
camera-gone (live cameras served over HTTP by ffmpeg, one killed for 0.5 to 5 s, then back).
"""

import argparse
import json
import os
import random
import re
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
HANDFLOW = Path(os.environ.get("HANDFLOW_BIN", REPO / "target" / "release" / "handflow"))
REAL = REPO / ".." / "shared" / "data" / "real" / "caliscope-hands"
RENDERED = REPO / "out" / "faults-signer-3cam"
STAGES = ["ingest", "flow", "cluster", "publish"]
UID = os.geteuid()


def log(*args):
    print(*args, file=sys.stderr, flush=True)


# ---------------------------------------------------------------- processes and files


def pids_of(binary, prefix):
    """Process ids of `binary` running with `--services prefix`."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            argv = Path(f"/proc/{entry}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if argv and os.path.basename(argv[0].decode(errors="replace")) == binary and prefix.encode() in argv:
            found.append(int(entry))
    return found


def shm_files():
    """handflow's iceoryx2 files of this user: shared memory and the namespace directory."""
    files = {f"/dev/shm/{n}" for n in os.listdir("/dev/shm") if n.startswith(f"hf{UID}_")}
    root = Path(f"/tmp/handflow-iox2-{UID}")
    if root.exists():
        files |= {str(p) for p in root.rglob("*") if p.is_file()}
    return files


class Follower:
    """Follows a JSON Lines file as it grows: each line with the moment it was seen."""

    def __init__(self, path):
        self.path = Path(path)
        self.lines = []  # (time, text)
        self.lock = threading.Lock()
        self.stop = False
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        offset, partial, inode = 0, b"", None
        while not self.stop:
            try:
                st = self.path.stat()
                if inode is not None and (st.st_ino != inode or st.st_size < offset):
                    # Replaced or emptied: a publisher that truncated its file (a finding).
                    with self.lock:
                        self.lines.append((time.monotonic(), "<<truncated>>"))
                    offset, partial = 0, b""
                inode = st.st_ino
                if st.st_size > offset:
                    with open(self.path, "rb") as f:
                        f.seek(offset)
                        data = f.read()
                    offset += len(data)
                    now = time.monotonic()
                    chunks = (partial + data).split(b"\n")
                    partial = chunks.pop()
                    with self.lock:
                        self.lines.extend((now, c.decode(errors="replace")) for c in chunks)
            except FileNotFoundError:
                pass
            time.sleep(0.005)

    def count(self):
        with self.lock:
            return len(self.lines)

    def first_after(self, t):
        with self.lock:
            for when, _ in self.lines:
                if when > t:
                    return when
        return None

    def close(self):
        self.stop = True
        self.thread.join()


class Run:
    """One `handflow run` of a pipeline file, its log kept with arrival times."""

    def __init__(self, pipeline, workdir, extra_args=()):
        self.workdir = Path(workdir)
        self.log = []  # (time, line)
        self.proc = subprocess.Popen(
            [str(HANDFLOW), "run", str(pipeline), *extra_args],
            cwd=REPO,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            errors="replace",
        )
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self):
        for line in self.proc.stderr:
            self.log.append((time.monotonic(), line.rstrip("\n")))

    def text(self):
        return "\n".join(line for _, line in list(self.log))

    def first_log_after(self, t, needle):
        for when, line in list(self.log):
            if when > t and needle in line:
                return when
        return None

    def stop(self, timeout=30):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.reader.join(5)


def write_pipeline(path, **fields):
    lines = []
    tables = {}
    for key, value in fields.items():
        if isinstance(value, dict):
            tables[key] = value
        else:
            lines.append(f"{key} = {json.dumps(value)}")
    for name, table in tables.items():
        lines.append(f"[{name}]")
        for key, value in table.items():
            if isinstance(value, dict):
                inner = ", ".join(f"{k} = {json.dumps(v)}" for k, v in value.items())
                lines.append(f"{key} = {{ {inner} }}")
            else:
                lines.append(f"{key} = {json.dumps(value).lower() if isinstance(value, bool) else json.dumps(value)}")
    Path(path).write_text("\n".join(lines) + "\n")


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ---------------------------------------------------------------- checking a run's output


def recording_length(run):
    """Frame sets in the recording, from ingest's log line `N frame sets (a..=b)`."""
    m = re.search(r"(\d+) frame sets \((\d+)\.\.=(\d+)\)", run.text())
    return (int(m.group(1)), int(m.group(2))) if m else (None, 0)


def reported_losses(text):
    lost = set()
    for m in re.finditer(r"frames lost upstream: sequence (\d+)\.\.=(\d+)", text):
        lost.update(range(int(m.group(1)), int(m.group(2)) + 1))
    return lost


def check_output(follower, run):
    """Sequences present (from frames, unwrapping loops by the records' stream times), missing,
    and the integrity checks."""
    length, first = recording_length(run)
    parsed, invalid, truncated = [], 0, False
    for _, text in list(follower.lines):
        if text == "<<truncated>>":
            truncated = True
            continue
        try:
            record = json.loads(text)
            parsed.append((int(record["frame"]), float(record["t"])))
        except (ValueError, KeyError, TypeError):
            invalid += 1
    # A looped replay's stream time keeps growing across passes, its frame numbers start
    # again: the frames elapsed between two records are the time between them over one
    # frame's time, which tells how many passes lie between them, however long a stall was.
    steps = [t1 - t0 for (f0, t0), (f1, t1) in zip(parsed, parsed[1:]) if f1 == f0 + 1 and t1 > t0]
    frame_time = statistics.median(steps) if steps else None
    sequences, twice = [], 0
    previous = None  # (sequence, t)
    for frame, t in parsed:
        sequence = frame - first
        if length and previous is not None and frame_time:
            elapsed = (t - previous[1]) / frame_time
            passes = round((previous[0] + elapsed - sequence) / length)
            sequence += max(passes, 0) * length
        if previous is not None and sequence <= previous[0]:
            twice += 1
            continue
        previous = (sequence, t)
        sequences.append(sequence)
    present = set(sequences)
    last = max(present) if present else 0
    missing = set(range(1, last + 1)) - present
    reported = {s for s in reported_losses(run.text()) if s <= last}
    return {
        "records": len(sequences),
        "invalid_lines": invalid,
        "frames_twice": twice,
        "file_truncated": truncated,
        "missing": missing,
        "reported": reported,
        "exact": missing == reported,
        "sequences": sequences,
    }


def lost_between(result, times_and_sequences, t0, t1):
    """Missing sequences between the last record before t0 and the first after t1."""
    before = [s for t, s in times_and_sequences if t <= t0]
    after = [s for t, s in times_and_sequences if t >= t1]
    if not before or not after:
        return None
    return len([s for s in result["missing"] if before[-1] < s < after[0]])


# ---------------------------------------------------------------- the faults


def wait_records(follower, n, timeout, run):
    target = follower.count() + n
    deadline = time.monotonic() + timeout
    while follower.count() < target:
        if time.monotonic() > deadline or run.proc.poll() is not None:
            return False
        time.sleep(0.01)
    return True


def start_subscriber(kind, prefix, zenoh_endpoint, viewer_port):
    if kind == "rust":
        return subprocess.Popen(
            [str(HANDFLOW), "tap", "trajectories", "--services", prefix],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    if kind == "python":
        return subprocess.Popen(
            [sys.executable, str(REPO / "examples" / "sign_recogniser.py"), "--services", prefix],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    if kind == "zenoh":
        return subprocess.Popen(
            [str(HANDFLOW), "tap", "trajectories", "--zenoh", zenoh_endpoint],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    raise ValueError(kind)


def websocket_that_never_reads(port):
    """A WebSocket client of the viewer's trajectories that never reads a byte."""
    s = socket.create_connection(("127.0.0.1", port))
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.sendall(
        (
            "GET /ws/trajectories HTTP/1.1\r\n"
            f"Host: 127.0.0.1:{port}\r\n"
            "Upgrade: websocket\r\nConnection: Upgrade\r\n"
            "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
        ).encode()
    )
    return s


def run_scenario(fault, source, mode, trials, rng, workdir):
    """Runs `trials` injections of `fault` in one pipeline; returns the trials' records."""
    prefix = f"faults-{fault}-{source}-{mode}-{os.getpid()}"
    out = Path(workdir) / f"{prefix}.jsonl"
    recording = REAL if source == "real" else RENDERED
    pipeline = Path(workdir) / f"{prefix}.toml"
    zenoh_port = free_port()
    viewer_port = free_port()
    fields = dict(
        mode=mode,
        recording=str(recording.resolve()),
        out=str(out),
        services=prefix,
        max_restarts=1000,
        viewer={"enabled": fault == "stall-websocket", "listen": f"127.0.0.1:{viewer_port}"},
    )
    # Replay: the stream must not end before the trials do (looped, with a generous bound).
    fields["loop"] = True
    fields["pace"] = "recorded" if mode == "live" else "max"
    if fault == "stall-zenoh":
        fields["network"] = {"zenoh": {"listen": f"tcp/127.0.0.1:{zenoh_port}"}}
    write_pipeline(pipeline, **fields)
    before = shm_files()
    run = Run(pipeline, workdir)
    follower = Follower(out)
    records = []
    subscriber = None
    sock = None
    try:
        if not wait_records(follower, 15, 180, run):
            return [{"fault": fault, "source": source, "mode": mode, "recovered": False, "note": "no start:\n" + run.text()[-2000:]}]
        if fault.startswith("stall-") and fault != "stall-websocket":
            subscriber = start_subscriber(fault[len("stall-"):], prefix, f"tcp/127.0.0.1:{zenoh_port}", viewer_port)
            time.sleep(2.0)
        if fault == "stall-websocket":
            sock = websocket_that_never_reads(viewer_port)
        for trial in range(trials):
            if not wait_records(follower, 8, 120, run):
                records.append({"recovered": False, "note": "stream stopped before the trial"})
                break
            time.sleep(rng.uniform(0.0, 1.0))
            t_fault = time.monotonic()
            pause = None
            if fault.startswith("kill-"):
                stage = fault[len("kill-"):]
                victims = pids_of(f"handflow-{stage}", prefix)
                for pid in victims:
                    os.kill(pid, signal.SIGKILL)
                t_from = t_fault
            elif fault.startswith("stop-"):
                stage = fault[len("stop-"):]
                victims = pids_of(f"handflow-{stage}", prefix)
                pause = rng.uniform(0.5, 5.0)
                for pid in victims:
                    os.kill(pid, signal.SIGSTOP)
                time.sleep(pause)
                for pid in victims:
                    os.kill(pid, signal.SIGCONT)
                t_from = time.monotonic()
            elif fault == "stall-websocket":
                pause = rng.uniform(0.5, 5.0)
                time.sleep(pause)
                # Reads what piled up, then stops reading again: the next trial stalls anew.
                sock.setblocking(False)
                try:
                    while sock.recv(1 << 20):
                        pass
                except (BlockingIOError, OSError):
                    pass
                sock.setblocking(True)
                t_from = time.monotonic()
            elif fault.startswith("stall-"):
                pause = rng.uniform(0.5, 5.0)
                subscriber.send_signal(signal.SIGSTOP)
                time.sleep(pause)
                subscriber.send_signal(signal.SIGCONT)
                t_from = time.monotonic()
            elif fault.startswith("inject-"):
                service = fault[len("inject-"):]
                subprocess.run(
                    [str(HANDFLOW), "bench", "inject", "--services", prefix, "--service", service, "--mode", mode,
                     "--count", "5", "--seed", str(rng.randrange(1 << 30))],
                    check=False,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                    timeout=60,
                )
                t_from = time.monotonic()
            else:
                raise ValueError(fault)
            # Recovered: a record written after the fault ended (within 30 s). After a kill,
            # a record written by the stages downstream from what they already held is not
            # the killed stage back: the record must follow the launcher's `started` line
            # for its replacement.
            deadline = t_from + 30
            t_back = None
            while time.monotonic() < deadline:
                after = t_from
                if fault.startswith("kill-"):
                    started_at = run.first_log_after(t_fault, f"started {fault[len('kill-'):]} (pid")
                    if started_at is None:
                        if run.proc.poll() is not None:
                            break
                        time.sleep(0.005)
                        continue
                    after = started_at
                t_back = follower.first_after(after)
                if t_back is not None or run.proc.poll() is not None:
                    break
                time.sleep(0.005)
            stalled_gap = None
            if pause is not None:
                # The longest pause between records during the fault: zero impact means the
                # usual frame interval.
                with follower.lock:
                    times = [t for t, _ in follower.lines if t_fault <= t <= t_from]
                stalled_gap = max((b - a for a, b in zip([t_fault] + times, times + [t_from])), default=None)
            records.append(
                {
                    "trial": trial,
                    "t_fault": t_fault,
                    "t_from": t_from,
                    "recovered": t_back is not None,
                    "recovery_s": (t_back - t_from) if t_back is not None else None,
                    "pause_s": pause,
                    "longest_gap_during_s": stalled_gap,
                    "restarted": run.first_log_after(t_fault, "restarting it") is not None,
                }
            )
        wait_records(follower, 5, 60, run)
    finally:
        if subscriber is not None:
            subscriber.send_signal(signal.SIGCONT)
            subscriber.send_signal(signal.SIGINT)
            try:
                subscriber.wait(10)
            except subprocess.TimeoutExpired:
                subscriber.kill()
        if sock is not None:
            sock.close()
        run.stop()
        time.sleep(0.5)
        follower.close()
    result = check_output(follower, run)
    # Which record (sequence) each line's time belongs to, for the frames lost per trial.
    timed = list(zip([t for t, text in follower.lines if text != "<<truncated>>"], result["sequences"]))
    for r in records:
        if "t_fault" in r:
            r["frames_lost"] = lost_between(result, timed, r["t_fault"], r["t_from"] + (r["recovery_s"] or 0))
    # A restart logged after the trial's fault and before the next one's (the first record
    # after a fault can be one already in flight, before the launcher has logged anything).
    faults_at = [r["t_fault"] for r in records if "t_fault" in r] + [float("inf")]
    for r, t_next in zip([r for r in records if "t_fault" in r], faults_at[1:]):
        at = run.first_log_after(r["t_fault"], "restarting it")
        r["restarted"] = at is not None and at < t_next
    leftover = sorted(shm_files() - before)
    gave_up = "giving up" in run.text()
    for r in records:
        r.update(fault=fault, source=source, mode=mode)
    summary = {
        "fault": fault,
        "source": source,
        "mode": mode,
        "exact": result["exact"],
        "unreported": sorted(result["missing"] - result["reported"])[:20],
        "reported_not_missing": sorted(result["reported"] - result["missing"])[:20],
        "intact": result["invalid_lines"] == 0 and result["frames_twice"] == 0 and not result["file_truncated"],
        "invalid_lines": result["invalid_lines"],
        "frames_twice": result["frames_twice"],
        "file_truncated": result["file_truncated"],
        "leftover_shm": leftover,
        "gave_up": gave_up,
        "records": result["records"],
    }
    if not summary["exact"] or not summary["intact"] or leftover or gave_up:
        log(f"  finding in {fault}/{source}/{mode}: {json.dumps(summary)[:600]}")
        (Path(workdir) / f"{prefix}.log").write_text(run.text())
    return records, summary


# ---------------------------------------------------------------- a camera that goes away


class NetworkCamera:
    """A network camera as many are (MJPEG over HTTP), played from a recording's video by
    ffmpeg at its own rate, looped; killed and started again (at the point it would have
    reached) to take it off the network and bring it back."""

    def __init__(self, inputs, port, fps, epoch):
        self.inputs, self.port, self.fps, self.epoch = inputs, port, fps, epoch
        self.proc = None
        self.down = False
        self.start()

    def uri(self):
        return f"http://127.0.0.1:{self.port}/cam"

    def start(self):
        offset = (time.monotonic() - self.epoch)
        self.proc = subprocess.Popen(
            ["ffmpeg", "-loglevel", "error", "-re", "-stream_loop", "-1", *self.inputs(offset),
             "-c:v", "mjpeg", "-q:v", "4", "-r", str(self.fps), "-f", "mpjpeg", "-listen", "1", self.uri()],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
        self.down = False

    def kill(self):
        self.down = True
        self.proc.kill()
        self.proc.wait()

    def keep_up(self):
        """ffmpeg serves one client: once that client is gone it exits; listen again."""
        if not self.down and self.proc.poll() is not None:
            self.start()


def camera_gone_trials(source, mode, trials, rng, workdir):
    """Live cameras served over HTTP; one at a time killed for 0.5 to 5 s, then back."""
    prefix = f"faults-camera-gone-{source}-{mode}-{os.getpid()}"
    out = Path(workdir) / f"{prefix}.jsonl"
    if source == "real":
        calibration = REAL / "camera_array.toml"
        names = [f"cam_{k}" for k in range(4)]
        fps = 6
        duration = 111 / fps
        videos = [REAL / f"cam_{k}.mp4" for k in range(4)]
        inputs = [lambda off, v=v: ["-ss", f"{off % duration:.3f}", "-i", str(v)] for v in videos]
    else:
        calibration = RENDERED / "rig.toml"
        names = [f"cam{k}" for k in range(3)]
        fps = 30
        duration = 150 / fps
        inputs = [
            lambda off, k=k: ["-framerate", str(fps), "-start_number", str(int(off % duration * fps)), "-i",
                              str(RENDERED / f"cam{k}" / "%06d.png")]
            for k in range(3)
        ]
    epoch = time.monotonic()
    cameras = [NetworkCamera(inputs[k], free_port(), fps, epoch) for k in range(len(names))]
    stop_keeping = threading.Event()

    def keeper():
        while not stop_keeping.is_set():
            for c in cameras:
                c.keep_up()
            time.sleep(0.05)

    keeping = threading.Thread(target=keeper, daemon=True)
    keeping.start()
    time.sleep(1.0)
    pipeline = Path(workdir) / f"{prefix}.toml"
    lines = [f'mode = "{mode}"', f'calibration = "{calibration.resolve()}"', f'out = "{out}"',
             f'services = "{prefix}"', "max_restarts = 1000", "[viewer]", "enabled = false"]
    for name, cam in zip(names, cameras):
        lines += ["[[cameras]]", f'name = "{name}"', f'source = "{cam.uri()}"', f"fps = {fps}"]
    pipeline.write_text("\n".join(lines) + "\n")
    before = shm_files()
    run = Run(pipeline, workdir)
    follower = Follower(out)
    records = []
    try:
        if not wait_records(follower, 15, 120, run):
            return [{"fault": "camera-gone", "source": source, "mode": mode, "recovered": False,
                     "note": "no start:\n" + run.text()[-2000:]}]
        for trial in range(trials):
            if not wait_records(follower, 8, 60, run):
                records.append({"recovered": False, "note": "stream stopped before the trial"})
                break
            time.sleep(rng.uniform(0.0, 1.0))
            k = rng.randrange(len(cameras))
            pause = rng.uniform(0.5, 5.0)
            t_fault = time.monotonic()
            cameras[k].kill()
            time.sleep(pause)
            cameras[k].start()
            t_from = time.monotonic()
            # Recovered: ingest says the camera is back (it delivers again).
            needle = f"camera `{names[k]}`: back after"
            deadline = t_from + 30
            t_back = None
            while time.monotonic() < deadline and run.proc.poll() is None:
                t_back = run.first_log_after(t_fault, needle)
                if t_back is not None:
                    break
                time.sleep(0.01)
            lost_seen = run.first_log_after(t_fault, f"camera `{names[k]}` lost") is not None
            records.append({
                "trial": trial, "t_fault": t_fault, "t_from": t_from, "camera": names[k],
                "recovered": t_back is not None, "recovery_s": (t_back - t_from) if t_back is not None else None,
                "pause_s": pause, "loss_noticed": lost_seen,
                "restarted": run.first_log_after(t_fault, "restarting it") is not None,
            })
            log(f"  {names[k]} away {pause:.2f} s: lost noticed {lost_seen}, back "
                + (f"{t_back - t_from:.2f} s after it returned" if t_back else "NEVER"))
            # Settles with every camera in its sets before the next trial.
            wait_records(follower, 2 * fps, 60, run)
        wait_records(follower, 5, 60, run)
    finally:
        run.stop()
        stop_keeping.set()
        keeping.join()
        for c in cameras:
            c.kill()
        time.sleep(0.5)
        follower.close()
    result = check_output(follower, run)
    timed = list(zip([t for t, text in follower.lines if text != "<<truncated>>"], result["sequences"]))
    for r in records:
        if "t_fault" in r:
            r["frames_lost"] = lost_between(result, timed, r["t_fault"], r["t_from"] + (r["recovery_s"] or 0))
            r.update(fault="camera-gone", source=source, mode=mode)
    summary = {
        "fault": "camera-gone", "source": source, "mode": mode, "exact": result["exact"],
        "unreported": sorted(result["missing"] - result["reported"])[:20],
        "intact": result["invalid_lines"] == 0 and result["frames_twice"] == 0 and not result["file_truncated"],
        "invalid_lines": result["invalid_lines"], "frames_twice": result["frames_twice"],
        "file_truncated": result["file_truncated"], "leftover_shm": sorted(shm_files() - before),
        "gave_up": "giving up" in run.text(), "records": result["records"],
    }
    if not summary["exact"] or not summary["intact"] or summary["leftover_shm"] or summary["gave_up"]:
        log(f"  finding in camera-gone/{source}/{mode}: {json.dumps(summary)[:600]}")
        (Path(workdir) / f"{prefix}.log").write_text(run.text())
    return records, summary


# ---------------------------------------------------------------- damaged recordings and a full disk


def damaged_recording_trial(kind, rng, workdir, trial):
    """A copy of the real session with one video truncated, or a rendered one with PNG frames
    overwritten with garbage; replayed (30 frame sets): the run must end, every lost frame
    reported, the file intact."""
    copy = Path(workdir) / f"{kind}-{trial}"
    if copy.exists():
        shutil.rmtree(copy)
    if kind == "truncated-video":
        copy.mkdir()
        for f in REAL.iterdir():
            if f.is_file():
                os.symlink(f.resolve(), copy / f.name)
        victim = rng.choice(sorted(REAL.glob("cam_*.mp4")))
        (copy / victim.name).unlink()
        data = victim.read_bytes()
        cut = int(len(data) * rng.uniform(0.02, 0.3))
        (copy / victim.name).write_bytes(data[:cut])
        what = f"{victim.name} cut at {cut} of {len(data)} bytes"
        frames = 30
    else:
        shutil.copytree(RENDERED, copy, symlinks=False)
        pngs = sorted(copy.glob("*/*.png"))
        hit = rng.sample(pngs[3 * 3 : 3 * 40], 3)
        for png in hit:
            data = bytearray(png.read_bytes())
            at = rng.randrange(len(data) // 4, len(data))
            data[at : at + 512] = os.urandom(min(512, len(data) - at))
            png.write_bytes(bytes(data))
        what = "garbage in " + ", ".join(f"{p.parent.name}/{p.name}" for p in hit)
        frames = 50
    prefix = f"faults-{kind}-{trial}-{os.getpid()}"
    out = Path(workdir) / f"{prefix}.jsonl"
    pipeline = Path(workdir) / f"{prefix}.toml"
    write_pipeline(pipeline, mode="replay", recording=str(copy), out=str(out), services=prefix, frames=frames,
                   viewer={"enabled": False})
    before = shm_files()
    started = time.monotonic()
    run = Run(pipeline, workdir)
    follower = Follower(out)
    try:
        run.proc.wait(240)
    except subprocess.TimeoutExpired:
        pass
    ended = run.proc.poll() is not None
    run.stop()
    time.sleep(0.3)
    follower.close()
    result = check_output(follower, run)
    # Frames never published (the end of the stream counts the ones before it).
    expected = set(range(1, frames))
    present = set(result["sequences"])
    missing = expected - present
    reported = reported_losses(run.text())
    errors = [line for _, line in run.log if " ERROR " in line or "error:" in line]
    leftover = sorted(shm_files() - before)
    shutil.rmtree(copy, ignore_errors=True)
    return {
        "fault": kind,
        "source": "real" if kind == "truncated-video" else "rendered",
        "mode": "replay",
        "what": what,
        "recovered": ended and run.proc.returncode == 0,
        "recovery_s": time.monotonic() - started,
        "frames_lost": len(missing),
        "exact": missing == reported,
        "intact": result["invalid_lines"] == 0 and result["frames_twice"] == 0,
        "errors_name_camera_and_frame": all(("cam" in e and "frame" in e) for e in errors) if errors else None,
        "first_error": errors[0][-300:] if errors else None,
        "leftover_shm": leftover,
    }


def disk_full_trials(trials, rng, workdir):
    """The output on a 512 KiB tmpfs: filled by another file until the publisher cannot
    write, then freed; recovered when a record is written again."""
    mount = Path(workdir) / "small-disk"
    mount.mkdir(exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=512k", "tmpfs", str(mount)], check=True)
    records = []
    try:
        prefix = f"faults-disk-full-{os.getpid()}"
        out = mount / "trajectories.jsonl"
        pipeline = Path(workdir) / f"{prefix}.toml"
        write_pipeline(pipeline, mode="live", recording=str(RENDERED.resolve()), out=str(out), services=prefix,
                       loop=True, pace="recorded", viewer={"enabled": False})
        before = shm_files()
        run = Run(pipeline, workdir)
        follower = Follower(out)
        if not wait_records(follower, 15, 180, run):
            raise RuntimeError("no start:\n" + run.text()[-2000:])
        for trial in range(trials):
            wait_records(follower, 8, 60, run)
            time.sleep(rng.uniform(0, 1))
            filler = mount / "filler"
            try:
                with open(filler, "wb") as f:
                    while True:
                        f.write(b"\0" * 4096)
                        f.flush()
            except OSError:
                pass
            t_full = time.monotonic()
            while run.first_log_after(t_full - 0.05, "cannot write frame") is None and time.monotonic() - t_full < 10:
                time.sleep(0.01)
            noticed = run.first_log_after(t_full - 0.05, "cannot write frame")
            time.sleep(rng.uniform(0.5, 3.0))
            filler.unlink()
            t_free = time.monotonic()
            t_back = None
            while time.monotonic() - t_free < 30:
                t_back = follower.first_after(t_free)
                if t_back:
                    break
                time.sleep(0.005)
            records.append({
                "fault": "disk-full", "source": "rendered", "mode": "live", "trial": trial,
                "recovered": t_back is not None and run.proc.poll() is None,
                "recovery_s": (t_back - t_free) if t_back else None,
                "noticed": noticed is not None,
                "restarted": run.first_log_after(t_full, "restarting it") is not None,
            })
            # Trim the file so the next trial fills the disk again soon.
        run.stop()
        time.sleep(0.3)
        follower.close()
        result = check_output(follower, run)
        left_out = sum(int(m.group(1)) for m in re.finditer(r"the (\d+) record\(s\) from frame", run.text()))
        summary = {
            "fault": "disk-full", "source": "rendered", "mode": "live",
            "exact": result["exact"] or None,
            "intact": result["invalid_lines"] == 0 and result["frames_twice"] == 0 and not result["file_truncated"],
            "records_left_out_reported": left_out,
            "leftover_shm": sorted(shm_files() - before),
            "gave_up": "giving up" in run.text(),
        }
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)
    return records, summary


# ---------------------------------------------------------------- the table


def table(all_trials, summaries):
    faults = []
    for t in all_trials:
        if t["fault"] not in faults:
            faults.append(t["fault"])
    rows = ["| fault | trials | recovered | recovery median | worst | frames lost (median / worst) | lost frames all reported | outputs intact | shm left | stage restarts |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for f in faults:
        ts = [t for t in all_trials if t["fault"] == f]
        ss = [s for s in summaries if s["fault"] == f]
        rec = [t["recovery_s"] for t in ts if t.get("recovery_s") is not None]
        lost = [t["frames_lost"] for t in ts if t.get("frames_lost") is not None]
        exact = all(s.get("exact") is not False for s in ss) and all(t.get("exact", True) is not False for t in ts)
        intact = all(s.get("intact", True) for s in ss) and all(t.get("intact", True) for t in ts)
        shm = sum(len(s.get("leftover_shm", [])) for s in ss) + sum(len(t.get("leftover_shm", [])) for t in ts)
        rows.append(
            f"| {f} | {len(ts)} | {sum(1 for t in ts if t['recovered'])} | "
            f"{statistics.median(rec):.2f} s | {max(rec):.2f} s | " if rec else f"| {f} | {len(ts)} | {sum(1 for t in ts if t['recovered'])} | – | – | "
        )
        rows[-1] += (f"{statistics.median(lost):.0f} / {max(lost)} | " if lost else "– | ") + f"{'yes' if exact else 'NO'} | {'yes' if intact else 'NO'} | {shm} | {sum(1 for t in ts if t.get('restarted'))} |"
    return "\n".join(rows)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=6, help="trials per fault and scenario (4 scenarios)")
    parser.add_argument("--only", help="comma-separated faults")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--json", help="write every trial and run summary here")
    parser.add_argument("--camera-gone-replay", action="store_true",
                        help="camera-gone in replay mode too (a stream buffered behind a slow pipeline can hide the cut)")
    args = parser.parse_args()
    if not HANDFLOW.exists():
        sys.exit(f"{HANDFLOW} missing: cargo build --release --workspace")
    if not REAL.exists():
        sys.exit(f"{REAL} missing: the real session is needed")
    if not RENDERED.exists():
        subprocess.run([str(HANDFLOW), "render", "--preset", "signer-3cam", "--frames", "150", "--out", str(RENDERED)], check=True, cwd=REPO)
    rng = random.Random(args.seed)
    faults = [f"kill-{s}" for s in STAGES] + [f"stop-{s}" for s in STAGES]
    faults += ["stall-rust", "stall-python", "stall-zenoh", "stall-websocket"]
    faults += [f"inject-{s}" for s in ["frames", "particles", "clusters", "trajectories"]]
    faults += ["disk-full", "truncated-video", "corrupt-frames", "camera-gone"]
    if args.only:
        wanted = args.only.split(",")
        faults = [f for f in faults if f in wanted]
    scenarios = [("rendered", "replay"), ("rendered", "live"), ("real", "replay"), ("real", "live")]
    all_trials, summaries = [], []
    with tempfile.TemporaryDirectory(prefix="handflow-faults-") as workdir:
        for fault in faults:
            log(f"== {fault}")
            if fault == "disk-full":
                trials, summary = disk_full_trials(args.trials * 4, rng, workdir)
                all_trials += trials
                summaries.append(summary)
                continue
            if fault in ("truncated-video", "corrupt-frames"):
                for k in range(args.trials * 4):
                    t = damaged_recording_trial(fault, rng, workdir, k)
                    log(f"  {t['what']}: ended {t['recovered']}, lost {t['frames_lost']}, exact {t['exact']}")
                    all_trials.append(t)
                continue
            for source, mode in scenarios:
                if fault == "camera-gone" and mode == "replay" and not args.camera_gone_replay:
                    # Replay holds a lossless camera back; its network stream's buffer then
                    # hides the cut for as long as it holds frames (--camera-gone-replay runs it).
                    continue
                if fault == "camera-gone":
                    out = camera_gone_trials(source, mode, args.trials, rng, workdir)
                else:
                    out = run_scenario(fault, source, mode, args.trials, rng, workdir)
                if isinstance(out, list):
                    all_trials += out
                    log(f"  {source}/{mode}: did not start")
                    continue
                trials, summary = out
                all_trials += trials
                summaries.append(summary)
                rec = [t["recovery_s"] for t in trials if t.get("recovery_s") is not None]
                log(f"  {source}/{mode}: {sum(t['recovered'] for t in trials)}/{len(trials)} recovered"
                    + (f", median {statistics.median(rec):.2f} s, worst {max(rec):.2f} s" if rec else "")
                    + f", exact {summary['exact']}, intact {summary['intact']}, shm left {len(summary['leftover_shm'])}"
                    + "".join(f", longest gap during {t['longest_gap_during_s']:.2f} s of {t['pause_s']:.2f}" for t in trials if t.get("longest_gap_during_s") is not None))
        if args.json:
            Path(args.json).write_text(json.dumps({"trials": all_trials, "runs": summaries}, indent=1, default=str))
    print(table(all_trials, summaries))


if __name__ == "__main__":
    main()
