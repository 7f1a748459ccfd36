#!/usr/bin/env python3
"""Derives variants of a real caliscope session that stand for sessions we have not seen, and
scores `handflow track` on each against the session's reference (transformed with the world
where the variant moves it).

Each variant changes one thing a user's session may differ in:
  as-is          the session unchanged (the row to compare with)
  rig-toml       its calibration as an anipose / Pose2Sim TOML, in metres
  pose2sim       laid out as a Pose2Sim project has it: `Calib.toml` with cameras cam_01..,
                 videos cam01.mp4.., no capture times (frame i of every video is one instant)
  millimetres    the same in millimetres (anipose, FreeMoCap and OpenCV calibrations often are)
  z-up           the world turned to Z-up and moved 2 m (a motion-capture world)
  half-size      videos at half the width and height (640x360 webcams), calibration scaled
  without-CAM    one camera left out (a three-camera rig), once per camera
  pair-CAM-CAM   two cameras only (a two-webcam rig): the most frontal one with each other one
  sideways-CAM   one camera mounted a quarter turn clockwise (its video turned, calibrated as
                 turned, no mount recorded), for the most frontal camera and a side one
  lossy          videos re-encoded at H.264 CRF 30 (a streaming-quality recording)
  warm-light     videos under warmer light (3500 K)
  dim            videos darker and less contrasted (a badly lit room)
  dropped-frames every camera drops one frame in DROP_EVERY at its own instants (a webcam
                 that cannot keep up), its video without them, `timestamps.csv` as caliscope
                 writes it: no row for a camera's dropped frame
  caliscope-older laid out as older caliscope versions write a project: the calibration in the
                 project's `config.toml` (`[cam_N]` tables with a `port`, Rodrigues rotations,
                 among the project's settings), the recording in `recordings/recording_1/`
                 with videos `port_N.mp4` and `frame_time_history.csv`; the recording folder
                 is the one scored
  freemocap      laid out as FreeMoCap writes a recording: videos synchronized_videos/
                 Camera_000_synchronized.mp4.., the calibration (millimetres, as FreeMoCap's
                 boards are measured) as `<session>_camera_calibration.toml`, no capture times
  fisheye        every camera as a wide lens calibrated with OpenCV's fisheye model: each
                 video resampled from its pinhole calibration into a fisheye image of the same
                 focal length (coefficients FISHEYE; the wider field's rim is black), the
                 rig's `fisheye = true` (needs numpy)

Needs ffmpeg for the video variants and Python 3.11 (tomllib). The videos are re-encoded once
into OUT and reused by later runs.

Usage: scripts/session_variants.py [--session DIR] [--out DIR] [--seeds 0 1 2] [--only NAME ...]
"""

import argparse
import csv
import json
import math
import os
import shutil
import subprocess
import sys
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def caliscope_cameras(session):
    """The session's caliscope cameras as dicts: name, size, K, distortions, R (3x3), t."""
    with open(session / "camera_array.toml", "rb") as f:
        data = tomllib.load(f)
    cameras = []
    for key in sorted(data["cameras"], key=int):
        c = data["cameras"][key]
        if c.get("ignore", False):
            continue
        cameras.append(
            {
                "name": f"cam_{key}",
                "size": list(c["size"]),
                "matrix": [list(r) for r in c["matrix"]],
                "distortions": list(c["distortions"]),
                "rotation": [list(r) for r in c["rotation"]],
                "translation": list(c["translation"]),
            }
        )
    return cameras


def write_rig(cameras, path):
    """An anipose / Pose2Sim TOML (3x3 rotations are accepted), numbers written exactly."""
    lines = []
    for c in cameras:
        lines += [
            f"[{c['name']}]",
            f'name = "{c["name"]}"',
            f"size = [{c['size'][0]}, {c['size'][1]}]",
            f"matrix = {json.dumps(c['matrix'])}",
            f"distortions = {json.dumps(c['distortions'])}",
            f"rotation = {json.dumps(c['rotation'])}",
            f"translation = {json.dumps(c['translation'])}",
        ]
        if c.get("fisheye"):
            lines.append("fisheye = true")
        lines.append("")
    path.write_text("\n".join(lines))


def rodrigues(r):
    """The Rodrigues vector (axis times angle) of a 3x3 rotation."""
    angle = math.acos(max(-1.0, min(1.0, (r[0][0] + r[1][1] + r[2][2] - 1.0) / 2.0)))
    if angle < 1e-12:
        return [0.0, 0.0, 0.0]
    axis = [r[2][1] - r[1][2], r[0][2] - r[2][0], r[1][0] - r[0][1]]
    if math.pi - angle < 1e-6:
        raise SystemExit("a rotation of half a turn: its axis is not written here")
    return [a * angle / (2.0 * math.sin(angle)) for a in axis]


def write_caliscope_config(cameras, path):
    """An older caliscope project's `config.toml`: settings, `[cam_N]` tables, a charuco board."""
    lines = [f"camera_count = {len(cameras)}", "fps_sync_stream_processing = 100", ""]
    for c in cameras:
        port = int(c["name"].split("_")[-1])
        lines += [
            f"[{c['name']}]",
            f"port = {port}",
            f"size = [{c['size'][0]}, {c['size'][1]}]",
            "rotation_count = 0",
            "error = 0.5",
            f"matrix = {json.dumps(c['matrix'])}",
            f"distortions = {json.dumps(c['distortions'])}",
            f"translation = {json.dumps(c['translation'])}",
            f"rotation = {json.dumps(rodrigues(c['rotation']))}",
            "exposure = -7",
            "grid_count = 30",
            "ignore = false",
            "",
        ]
    lines += ["[charuco]", "columns = 4", "rows = 5", 'dictionary = "DICT_4X4_50"', 'units = "inch"', ""]
    path.write_text("\n".join(lines))


def most_frontal(cameras):
    """Name of the camera whose optical axis (third row of R) is nearest the mean axis."""
    axes = [c["rotation"][2] for c in cameras]
    mean = [sum(a[i] for a in axes) for i in range(3)]
    best = max(range(len(cameras)), key=lambda k: sum(axes[k][i] * mean[i] for i in range(3)))
    return cameras[best]["name"]


def matmul(a, b):
    return [[sum(a[i][k] * b[k][j] for k in range(3)) for j in range(3)] for i in range(3)]


def matvec(a, v):
    return [sum(a[i][k] * v[k] for k in range(3)) for i in range(3)]


def transpose(a):
    return [[a[j][i] for j in range(3)] for i in range(3)]


# The z-up variant's world: x' = TURN x + SHIFT (a quarter turn about x takes a Y-up world's
# up to +Z; the shift moves the origin 2 m away from the rig).
TURN = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
SHIFT = [1.2, -2.0, 0.4]


def moved_world(cameras):
    """The cameras in the world x' = TURN x + SHIFT: R' = R TURN^T, t' = t - R' SHIFT."""
    out = []
    for c in cameras:
        r = matmul(c["rotation"], transpose(TURN))
        shifted = matvec(r, SHIFT)
        out.append(dict(c, rotation=r, translation=[t - s for t, s in zip(c["translation"], shifted)]))
    return out


def moved_reference(reference):
    ref = json.loads(json.dumps(reference))
    for frame in ref["frames"]:
        for obj in frame["objects"].values():
            if "3d" in obj:
                obj["3d"] = [a + b for a, b in zip(matvec(TURN, obj["3d"]), SHIFT)]
    return ref


def halved(cameras):
    """Intrinsics of frames scaled by 1/2 (pixel centres at integer coordinates)."""
    out = []
    for c in cameras:
        k = [row[:] for row in c["matrix"]]
        k[0][0] /= 2
        k[1][1] /= 2
        k[0][2] = (k[0][2] + 0.5) / 2 - 0.5
        k[1][2] = (k[1][2] + 0.5) / 2 - 0.5
        out.append(dict(c, matrix=k, size=[c["size"][0] // 2, c["size"][1] // 2]))
    return out


# Clockwise quarter turn of a camera's frames: pixel (u, v) of a W x H frame goes to
# (H - 1 - v, u), so camera axes (x, y, z) become (-y, x, z).
QUARTER_CW = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]


def turned_clockwise(camera):
    """The camera calibrated on its frames turned a quarter clockwise."""
    k = camera["matrix"]
    (w, h) = camera["size"]
    fx, fy, cx, cy = k[0][0], k[1][1], k[0][2], k[1][2]
    k1, k2, p1, p2, k3 = camera["distortions"]
    return dict(
        camera,
        size=[h, w],
        matrix=[[fy, 0.0, h - 1 - cy], [0.0, fx, cx], [0.0, 0.0, 1.0]],
        # Radial terms do not turn; the tangential ones do: p1' = p2, p2' = -p1.
        distortions=[k1, k2, p2, -p1, k3],
        rotation=matmul(QUARTER_CW, camera["rotation"]),
        translation=matvec(QUARTER_CW, camera["translation"]),
    )


def encode(src, dst, video_filter, crf):
    if dst.exists():
        return
    tmp = dst.with_suffix(".part.mp4")
    cmd = ["ffmpeg", "-hide_banner", "-loglevel", "error", "-y", "-i", str(src)]
    if video_filter:
        cmd += ["-vf", video_filter]
    cmd += ["-c:v", "libx264", "-crf", str(crf), "-pix_fmt", "yuv420p", str(tmp)]
    subprocess.run(cmd, check=True)
    tmp.rename(dst)


# The fisheye variant's lens: OpenCV fisheye k1 k2 k3 k4 (a mildly barrel wide lens).
FISHEYE = [0.05, -0.02, 0.004, 0.0]


def fisheye_maps(camera, lens):
    """Per pixel of the fisheye image (the camera's K, `lens`), where the pinhole view shows
    the same ray: source coordinates x, y (float arrays)."""
    import numpy as np

    (w, h), k, (k1, k2, p1, p2, k3) = camera["size"], camera["matrix"], camera["distortions"]
    fx, s, cx, fy, cy = k[0][0], k[0][1], k[0][2], k[1][1], k[1][2]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    yd = (v - cy) / fy
    xd = (u - cx - s * yd) / fx
    theta_d = np.hypot(xd, yd)
    theta = np.minimum(theta_d, 1.5)
    c1, c2, c3, c4 = lens
    for _ in range(30):
        t2 = theta * theta
        f = theta * (1 + t2 * (c1 + t2 * (c2 + t2 * (c3 + t2 * c4)))) - theta_d
        df = 1 + t2 * (3 * c1 + t2 * (5 * c2 + t2 * (7 * c3 + t2 * 9 * c4)))
        theta = np.clip(theta - f / df, 0.0, 1.5)
    scale = np.where(theta_d > 1e-12, np.tan(theta) / np.maximum(theta_d, 1e-12), 1.0)
    x, y = xd * scale, yd * scale
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xs = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    ys = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return fx * xs + s * ys + cx, fy * ys + cy


def fisheye_video(src, dst, camera, lens):
    """`src` resampled (bilinear) into the fisheye view of `camera` with `lens`, H.264 CRF 12."""
    import numpy as np

    if dst.exists():
        return
    w, h = camera["size"]
    mx, my = fisheye_maps(camera, lens)
    x0, y0 = np.floor(mx).astype(np.int64), np.floor(my).astype(np.int64)
    fx, fy = (mx - x0)[..., None], (my - y0)[..., None]
    inside = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < w) & (y0 + 1 < h)
    x0, y0 = np.clip(x0, 0, w - 2), np.clip(y0, 0, h - 2)
    tmp = dst.with_suffix(".part.mp4")
    decode = subprocess.Popen(
        ["ffmpeg", "-loglevel", "error", "-i", str(src), "-f", "rawvideo", "-pix_fmt", "rgb24", "-"],
        stdout=subprocess.PIPE,
    )
    encode = subprocess.Popen(
        ["ffmpeg", "-loglevel", "error", "-y", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{w}x{h}",
         "-r", "6", "-i", "-", "-c:v", "libx264", "-crf", "12", "-pix_fmt", "yuv420p", str(tmp)],
        stdin=subprocess.PIPE,
    )
    size = w * h * 3
    while True:
        raw = decode.stdout.read(size)
        if len(raw) < size:
            break
        img = np.frombuffer(raw, np.uint8).reshape(h, w, 3).astype(np.float32)
        top = img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx
        bottom = img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx
        out = (top * (1 - fy) + bottom * fy) * inside[..., None]
        encode.stdin.write(np.clip(out + 0.5, 0, 255).astype(np.uint8).tobytes())
    encode.stdin.close()
    if decode.wait() != 0 or encode.wait() != 0:
        raise SystemExit(f"fisheye: re-encoding {src} failed")
    tmp.rename(dst)


# The dropped-frames variant: camera k drops its frames n with (n + dropped_offset(k)) %
# DROP_EVERY == 0, 5 % of each camera's frames, at instants no two cameras share.
DROP_EVERY = 20


def dropped_offset(k):
    return 7 + 5 * k


def build(name, session, out, cameras, reference):
    """Writes variant `name` into out/name and returns its folder."""
    d = out / name
    d.mkdir(parents=True, exist_ok=True)
    names = [c["name"] for c in cameras]
    kept = names
    rig = None
    calibration = "rig.toml"
    video_name = {n: n for n in names}  # the file stem each camera's video gets
    timestamps = True
    timestamps_file = "timestamps.csv"
    ref = reference
    video = None  # (ffmpeg filter, crf) when the videos are re-encoded
    if name == "as-is":
        shutil.copy(session / "camera_array.toml", d / "camera_array.toml")
    elif name == "rig-toml":
        rig = cameras
    elif name == "pose2sim":
        # Pose2Sim numbers cameras from 1, two digits, and names videos without the underscore;
        # its projects carry no capture times.
        numbered = {n: f"cam_{i + 1:02d}" for i, n in enumerate(names)}
        rig = [dict(c, name=numbered[c["name"]]) for c in cameras]
        calibration = "Calib.toml"
        video_name = {n: numbered[n].replace("_", "") for n in names}
        timestamps = False
    elif name == "millimetres":
        rig = [dict(c, translation=[1000.0 * t for t in c["translation"]]) for c in cameras]
    elif name == "z-up":
        rig, ref = moved_world(cameras), moved_reference(reference)
    elif name == "half-size":
        rig, video = halved(cameras), ("scale=iw/2:ih/2:flags=area", 16)
    elif name.startswith("without-"):
        left_out = name[len("without-") :]
        kept = [n for n in names if n != left_out]
        rig = [c for c in cameras if c["name"] != left_out]
    elif name.startswith("pair-"):
        kept = [n for n in names if n in name[len("pair-") :].split("-")]
        if len(kept) != 2:
            raise SystemExit(f"variant `{name}` names no two cameras of the session")
        rig = [c for c in cameras if c["name"] in kept]
    elif name.startswith("sideways-"):
        turned = name[len("sideways-") :]
        rig = [turned_clockwise(c) if c["name"] == turned else c for c in cameras]
        video = {turned: ("transpose=clock", 16)}
    elif name == "lossy":
        rig, video = cameras, ("null", 30)
    elif name == "warm-light":
        rig, video = cameras, ("colortemperature=temperature=3500", 16)
    elif name == "dim":
        rig, video = cameras, ("eq=brightness=-0.08:contrast=0.7:gamma=0.8", 16)
    elif name == "caliscope-older":
        project, d = d, d / "recordings" / "recording_1"
        d.mkdir(parents=True, exist_ok=True)
        write_caliscope_config(cameras, project / "config.toml")
        video_name = {n: n.replace("cam_", "port_") for n in names}
        timestamps_file = "frame_time_history.csv"
    elif name == "freemocap":
        rig = [dict(c, translation=[1000.0 * t for t in c["translation"]]) for c in cameras]
        calibration = "session_camera_calibration.toml"
        (d / "synchronized_videos").mkdir(exist_ok=True)
        (d / "output_data").mkdir(exist_ok=True)
        video_name = {n: f"synchronized_videos/Camera_{int(n.split('_')[-1]):03d}_synchronized" for n in names}
        timestamps = False
    elif name == "fisheye":
        rig = [dict(c, distortions=FISHEYE, fisheye=True) for c in cameras]
        for c in cameras:
            fisheye_video(session / f"{c['name']}.mp4", d / f"{c['name']}.mp4", c, FISHEYE)
    elif name == "dropped-frames":
        # Near-lossless re-encoding of the frames each camera kept.
        rig = cameras
        video = {n: (f"select='not(eq(mod(n+{dropped_offset(k)},{DROP_EVERY}),0))',setpts=N/FRAME_RATE/TB", 8)
                 for k, n in enumerate(names)}
    else:
        raise SystemExit(f"unknown variant `{name}`")
    if rig is not None:
        write_rig(rig, d / calibration)
    for n in kept:
        src = session / f"{n}.mp4"
        dst = d / f"{video_name[n]}.mp4"
        this_video = video.get(n) if isinstance(video, dict) else video
        if this_video is None:
            if not dst.exists():
                os.symlink(src.resolve(), dst)
        else:
            encode(src, dst, *this_video)
    if timestamps:
        with open(session / "timestamps.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        # Older caliscope versions call the camera column `port`.
        column = "port" if timestamps_file == "frame_time_history.csv" else "cam_id"
        with open(d / timestamps_file, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=[column if k == "cam_id" else k for k in rows[0].keys()])
            w.writeheader()
            position = {}
            for r in sorted(rows, key=lambda r: (int(r["cam_id"]), int(r["sync_index"]))):
                if f"cam_{r['cam_id']}" not in kept:
                    continue
                if name == "dropped-frames":
                    k = names.index(f"cam_{r['cam_id']}")
                    n = int(r["frame_index"]) - min(int(q["frame_index"]) for q in rows if q["cam_id"] == r["cam_id"])
                    if (n + dropped_offset(k)) % DROP_EVERY == 0:
                        continue
                    # caliscope's frame_index counts the frames the camera's video holds.
                    p = position.get(k, int(r["frame_index"]))
                    position[k] = p + 1
                    r = dict(r, frame_index=str(p))
                w.writerow({column if k == "cam_id" else k: v for k, v in r.items()})
    (d / "reference.json").write_text(json.dumps(ref))
    return d


def score(binary, folder, seed):
    tracks = folder / f"tracks-{seed}.jsonl"
    start = time.monotonic()
    run = subprocess.run(
        [binary, "track", "--recording", str(folder), "--out", str(tracks), "--seed", str(seed)],
        capture_output=True,
        text=True,
    )
    seconds = time.monotonic() - start
    if run.returncode != 0:
        return None, seconds, run.stderr.strip().splitlines()[-1:]
    ev = subprocess.run(
        [binary, "eval", "tracks", "--recording", str(folder), "--tracks", str(tracks), "--reference",
         str(folder / "reference.json"), "--json"],
        capture_output=True,
        text=True,
    )
    if ev.returncode != 0:
        return None, seconds, ev.stderr.strip().splitlines()[-1:]
    warnings = [line for line in run.stderr.splitlines() if " WARN " in line]
    return json.loads(ev.stdout), seconds, warnings


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--session", type=Path, default=ROOT.parent / "shared/data/real/caliscope-hands")
    p.add_argument("--out", type=Path, default=ROOT / "out/session-variants")
    p.add_argument("--seeds", nargs="+", type=int, default=[0])
    p.add_argument("--only", nargs="+")
    args = p.parse_args()
    if not (args.session / "camera_array.toml").is_file():
        print(f"skipped: no caliscope session at {args.session}", file=sys.stderr)
        return 0
    binary = os.environ.get("HANDFLOW_BIN", str(ROOT / "target/release/handflow"))
    if not os.access(binary, os.X_OK):
        subprocess.run(["cargo", "build", "--release", "-q", "-p", "handflow"], cwd=ROOT, check=True)
    cameras = caliscope_cameras(args.session)
    reference = json.loads((args.session / "reference.json").read_text())
    names = ["as-is", "rig-toml", "pose2sim", "millimetres", "z-up", "half-size"]
    names += [f"without-{c['name']}" for c in cameras]
    # The camera handflow takes as its reference (its optical axis nearest the rig's mean
    # viewing direction, as `Rig::most_frontal_camera` chooses) with each other camera.
    frontal = most_frontal(cameras)
    names += [f"pair-{'-'.join(sorted([frontal, c['name']]))}" for c in cameras if c["name"] != frontal]
    names += ["sideways-cam_2", "sideways-cam_0"]
    names += ["lossy", "warm-light", "dim", "dropped-frames", "caliscope-older", "freemocap", "fisheye"]
    if args.only:
        names = [n for n in names if n in args.only]
    objects = ("head", "left_hand", "right_hand")
    print("| variant | seed | " + " | ".join(f"{o}: within 5 / 10 cm" for o in objects) + " | switches | sets/s |")
    print("|---|---|" + "---|" * (len(objects) + 2))
    for name in names:
        folder = build(name, args.session, args.out, cameras, reference)
        for seed in args.seeds:
            report, seconds, notes = score(binary, folder, seed)
            if report is None:
                print(f"| {name} | {seed} | failed: {' '.join(notes)} |")
                continue
            cells = []
            for o in objects:
                r = report.get(o)
                cells.append("-" if r is None else f"{100 * r['within_5cm']:.1f} / {100 * r['within_10cm']:.1f} %")
            frames = report["frames"]
            print(f"| {name} | {seed} | " + " | ".join(cells) + f" | {report.get('identity_switches', '-')} | "
                  f"{frames / seconds:.1f} |", flush=True)
            for warning in notes[:3]:
                print(f"  warning: {warning.split(' WARN ', 1)[-1][:200]}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
